"""``bioscara emulate dynamixel``: emulated XL430 servos behind a pseudo-terminal.

::

    bioscara emulate dynamixel --ids 1-4 --link /tmp/dxl
    # elsewhere: PortHandler("/tmp/dxl") of the official SDK, 1 Mbps, protocol 2.0

Serves until SIGINT, SIGTERM or SIGHUP, then removes the symlink if it still points
at this emulator's pty. An existing ``--link`` is replaced only if it is a
symlink into ``/dev/pts/`` to a pty that is gone (a stale link of an emulator
that was killed); one to a pty still in use is refused. ``--faults``
takes ``drop=0.01,corrupt=0.001,delay_ms=2``.
"""

from __future__ import annotations

import argparse
import os
import signal
import time
from pathlib import Path

from bioscara_gym.errors import CliError
from bioscara_gym.stop_signals import after_signal, caught

#: How often the serving loop looks for one, s.
STOP_POLL_S = 0.2
#: Where the pseudo-terminals' slave devices are: a symlink into it may be replaced.
PTY_FOLDER = "/dev/pts/"


def cmd_emulate_dynamixel(args: argparse.Namespace) -> int:
    """Serve emulated servos on a pty until SIGINT, SIGTERM or SIGHUP (its terminal closed)."""
    from bioscara_gym.hardware.dynamixel.pty_server import PtyServer, make_bus, parse_ids
    from bioscara_gym.hardware.emulated_bus import RS485_FAULTS, FaultPlan

    try:
        ids = parse_ids(args.ids)
        if args.faults is not None and not args.faults.strip():
            raise ValueError("--faults names no fault; give KEY=VALUE,... e.g. drop=0.01")
        faults = FaultPlan.parse(args.faults, kinds=RS485_FAULTS) if args.faults else None
    except ValueError as e:
        raise CliError(str(e)) from None
    link = _check_link(args.link)
    # The handler only records the signal: one that set a threading.Event deadlocked
    # when the signal landed while this thread held the Event's lock inside wait()
    # (seen under load: SIGTERM ignored for 30 s; python/cpython#126434 is the same trap).
    received: list[int] = []

    def stop(signum: int, frame: object) -> None:
        received.append(signum)
        after_signal(signum)  # a terminal gone: the last line goes nowhere, not into an error

    previous = {sig: signal.signal(sig, stop) for sig in caught()}
    try:
        try:
            server = PtyServer(make_bus(ids, faults), link)
        except OSError as e:
            if e.filename2 != os.fspath(link):  # not the symlink: the pty's own error
                raise
            raise CliError(f"--link {link}: cannot make the symlink there ({e.strerror})") from None
        with server:
            ids_text = ", ".join(str(i) for i in ids)
            print(
                f"XL430 servos {ids_text} on {server.path} -> {server.slave_path}; Ctrl-C stops", flush=True
            )
            while not received:
                time.sleep(STOP_POLL_S)
    finally:
        for sig, handler in previous.items():
            signal.signal(sig, handler)
    if server.link_removed:
        print("stopped; link removed", flush=True)
    else:  # someone re-pointed it meanwhile: theirs now
        print(f"stopped; link {link} not removed: it no longer points at {server.slave_path}", flush=True)
    return 0


def _check_link(text: str) -> Path:
    """The ``--link`` path, refused when empty, in no folder, or anything but a stale link to a pty gone.

    Raises:
        CliError: One line naming the path and what is wrong.
    """
    if not text:
        raise CliError("--link is empty; give the path of the symlink to make, e.g. /tmp/dxl")
    link = Path(text)
    folder = link.parent
    if not folder.is_dir():
        problem = f"{folder} is not a folder" if folder.exists() else f"the folder {folder} does not exist"
        raise CliError(f"--link {link}: {problem}")
    if link.is_symlink():
        target = os.readlink(link)
        if not target.startswith(PTY_FOLDER):  # a stale link of a killed emulator points into it
            raise CliError(
                f"--link {link}: a symlink to {target}, not to a pseudo-terminal ({PTY_FOLDER}*); "
                "not replacing it"
            )
        # A pty's slave device exists while its master is open: the link of a killed emulator
        # points at nothing, one of a running emulator (or a user's link to a terminal) at a
        # live pty. Replacing that one left the running emulator unreachable, still naming it.
        if os.path.exists(target):
            raise CliError(
                f"--link {link}: points at {target}, a pseudo-terminal still in use (another emulator?); "
                "not replacing it"
            )
    elif link.exists() or link.name in ("", ".", ".."):
        raise CliError(f"--link {link}: exists and is not a symlink; not replacing it")
    return link


def register(sub: argparse._SubParsersAction) -> None:
    """Add ``emulate dynamixel``."""
    p = sub.add_parser("emulate", help="run emulated devices for other programs to talk to")
    kinds = p.add_subparsers(dest="device", required=True)
    d = kinds.add_parser("dynamixel", help="XL430 servos (protocol 2.0) behind a pseudo-terminal")
    d.add_argument("--ids", default="1-4", help="servo IDs, e.g. 1-4 or 1,3 (default: 1-4)")
    d.add_argument("--link", required=True, metavar="PATH", help="symlink to create to the pty's slave")
    d.add_argument("--faults", metavar="SPEC", help="e.g. drop=0.01,corrupt=0.001,delay_ms=2")
    d.set_defaults(func=cmd_emulate_dynamixel)
