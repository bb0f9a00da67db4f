"""The emulated RS-485 bus behind a pseudo-terminal, as a USB-RS485 adapter would be.

:class:`PtyServer` opens a pty pair (``os.openpty``), puts it in raw mode,
makes ``link`` a symlink to the slave (``/dev/pts/N``) and serves the
emulated servos on the master from a thread: whatever a program writes to
``link`` (the official SDK's ``PortHandler(link)``, at any baud rate) reaches
the servos, and their status packets come back. The motors run on the wall
clock. ``bioscara emulate dynamixel --ids 1-4 --link PATH`` runs one until
SIGINT, SIGTERM or SIGHUP, then removes the symlink if it still points at its pty.

A packet left incomplete (a client that closed or was killed partway through
one) is dropped once the line has been idle for :data:`RX_IDLE_S`, and at the
next header (:class:`~bioscara_gym.hardware.dynamixel.protocol.PacketParser`):
the bytes that come next are a new packet, not the rest of that one.
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
#: Idle line after which a partial packet is dropped, s (our choice: 20 ms). Inside a packet the
#: bytes follow each other: 1.04 ms apart at the XL430's slowest baud rate (9600), microseconds at
#: 1 Mbps, and on the pty the SDK writes a packet in one go. It is shorter than the SDK's wait for
#: a status packet (two 16 ms latency timers + 2 ms), so a client that retries after a lost reply
#: finds the parser clear. A real servo's receiver also gives up on a packet that stops coming.
RX_IDLE_S = 0.02


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
        self.link_removed = False  # by stop(): False when the link pointed elsewhere by then
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
        """Answer instruction packets until :meth:`stop`; drop a partial packet once the line is idle.

        The idle time is measured by select() while this thread waits, so a
        busy server (a slow reply, the GIL elsewhere) does not count as an
        idle line and split a packet that was arriving meanwhile.
        """
        while not self._stop.is_set():
            partial = self.bus.in_receive > 0
            ready, _, _ = select.select([self.master], [], [], RX_IDLE_S if partial else POLL_S)
            if not ready:
                if partial:  # the rest is not coming: the next bytes start a new packet
                    self.bus.clear_input()
                continue
            try:
                data = os.read(self.master, 4096)
            except OSError:  # EIO: no client has the slave open; what one left is not continued
                self.bus.clear_input()
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
        """Stop serving, close the pty and remove the symlink if it still points at this pty.

        A link re-pointed meanwhile (another emulator's, a user's) is theirs:
        removing it cut their clients off. :attr:`link_removed` says which.
        """
        self._stop.set()
        if self._thread is not None and self._thread is not threading.current_thread():
            self._thread.join(timeout=2.0)
        if self.link is not None and not self.link_removed:
            with contextlib.suppress(OSError):  # gone already, or not a symlink any more
                if os.readlink(self.link) == self.slave_path:
                    self.link.unlink()
                    self.link_removed = True
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
