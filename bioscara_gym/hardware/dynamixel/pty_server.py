"""The emulated RS-485 bus behind a pseudo-terminal, as a USB-RS485 adapter would be.

:class:`PtyServer` opens a pty pair (``os.openpty``), puts it in raw mode,
makes ``link`` a symlink to the slave (``/dev/pts/N``) and serves the
emulated servos on the master from a thread: whatever a program writes to
``link`` (the official SDK's ``PortHandler(link)``, at any baud rate) reaches
the servos, and their status packets come back. The motors run on the wall
clock. ``bioscara emulate dynamixel --ids 1-4 --link PATH`` runs one until
SIGINT or SIGTERM, then removes the symlink.
"""

from __future__ import annotations

import contextlib
import os
import select
import threading
import time
import tty
from pathlib import Path

from bioscara_gym.hardware.clock import WallClock
from bioscara_gym.hardware.dynamixel.emulator import XL430, EmulatedRS485Bus
from bioscara_gym.hardware.emulated_bus import FaultPlan

#: Largest servo ID (protocol 2.0: 253 is reserved, 254 broadcast; the control table's ID item).
MAX_ID = 252
#: How often the server wakes up without traffic, s (to notice stop()).
POLL_S = 0.05


def parse_ids(spec: str) -> list[int]:
    """``"1-4"``, ``"1,3,5"`` or ``"1-3,7"`` to a sorted list of IDs (0-252).

    Raises:
        ValueError: Not a list of IDs and ranges, or an ID outside 0-252.
    """
    ids: set[int] = set()
    for part in filter(None, (p.strip() for p in spec.split(","))):
        first, sep, last = part.partition("-")
        try:
            lo, hi = int(first), int(last) if sep else int(first)
        except ValueError as e:
            raise ValueError(f"--ids {spec!r}: {part!r} is not an ID or a range like 1-4") from e
        if lo > hi:
            raise ValueError(f"--ids {spec!r}: range {part!r} runs backwards")
        for end in (lo, hi):  # checked before the range is expanded: 1-1000000000 is 22 GB of IDs
            if not 0 <= end <= MAX_ID:
                raise ValueError(f"--ids {spec!r}: IDs must be 0-{MAX_ID}, got {end} (in {part!r})")
        ids.update(range(lo, hi + 1))
    if not ids:
        raise ValueError(f"--ids {spec!r}: no IDs")
    return sorted(ids)


class PtyServer:
    """Serve an :class:`EmulatedRS485Bus` on a pseudo-terminal.

    Args:
        bus: The emulated servos (on a wall clock for real use).
        link: Where to put the symlink to the slave device; ``None``: none
            (use :attr:`slave_path`).

    Use as a context manager, or :meth:`start` / :meth:`stop`.
    """

    def __init__(self, bus: EmulatedRS485Bus, link: str | os.PathLike[str] | None = None) -> None:
        """Open the pty pair and make the symlink."""
        self.bus = bus
        self.master, self.slave = os.openpty()
        tty.setraw(self.master)
        tty.setraw(self.slave)
        self.slave_path = os.ttyname(self.slave)
        self.link = Path(link) if link is not None else None
        if self.link is not None:
            if self.link.is_symlink():
                self.link.unlink()  # a stale link from a server that was killed
            os.symlink(self.slave_path, self.link)
        self._stop = threading.Event()
        self._thread: threading.Thread | None = None

    @property
    def path(self) -> str:
        """What a client opens: the symlink if there is one, else the slave device."""
        return os.fspath(self.link) if self.link is not None else self.slave_path

    def start(self) -> PtyServer:
        """Serve from a daemon thread."""
        self._thread = threading.Thread(target=self.serve_forever, name="dynamixel-pty", daemon=True)
        self._thread.start()
        return self

    def serve_forever(self) -> None:
        """Answer instruction packets until :meth:`stop`."""
        while not self._stop.is_set():
            ready, _, _ = select.select([self.master], [], [], POLL_S)
            if not ready:
                continue
            try:
                data = os.read(self.master, 4096)
            except OSError:  # EIO: no client has the slave open; keep waiting
                time.sleep(POLL_S)
                continue
            if not data:
                continue
            self.bus.write(data)
            reply = self.bus.read()
            delay, self.bus.pending_delay_s = self.bus.pending_delay_s, 0.0
            if delay and not isinstance(self.bus.clock, WallClock):
                delay = 0.0  # a manual clock was advanced already
            if delay:
                time.sleep(delay)
            if reply:
                with contextlib.suppress(OSError):
                    os.write(self.master, reply)

    def stop(self) -> None:
        """Stop serving, close the pty and remove the symlink."""
        self._stop.set()
        if self._thread is not None and self._thread is not threading.current_thread():
            self._thread.join(timeout=2.0)
        if self.link is not None and self.link.is_symlink():
            self.link.unlink()
        for fd in (self.master, self.slave):
            with contextlib.suppress(OSError):
                os.close(fd)

    def __enter__(self) -> PtyServer:
        """Start serving."""
        return self.start()

    def __exit__(self, *exc: object) -> None:
        """Stop serving."""
        self.stop()


def make_bus(ids: list[int], faults: FaultPlan | None = None) -> EmulatedRS485Bus:
    """Servos with ``ids`` on the wall clock, at 1 Mbps, centred."""
    clock = WallClock()
    return EmulatedRS485Bus([XL430(i, clock) for i in ids], faults=faults, clock=clock)
