"""The signals that stop a command as Ctrl-C does: SIGINT, SIGTERM and SIGHUP.

SIGHUP comes when the terminal a command runs in goes away: its window is
closed, or the SSH session drops. Left to its default it ended the process
at once (seen 2026-11-29: ``monitor`` left every joint enabled and its lock
file behind; a ``deploy`` died with no safe stop and no summary, where on
the arm the firmware's deadman stops a joint in velocity mode 50 ms later,
its currents left on, and a position move runs on). Now
it takes the way out Ctrl-C takes: the arm is made safe, temporary files go,
a training saves a checkpoint, and the exit code is 129 (``emulate``,
which serves until a signal stops it, exits 0). A command started
under ``nohup``, which ignores SIGHUP, goes on ignoring it and runs on, as
``nohup`` promises (:func:`caught`).

The clean-up after a SIGHUP cannot print to the terminal that went away:
every write to it fails (EIO), and the first failed write would have cut
the clean-up short. :func:`after_signal` points the standard streams that
were that terminal at ``/dev/null``.
"""

from __future__ import annotations

import contextlib
import errno
import os
import signal
import threading
from collections.abc import Callable, Iterator, Sequence
from types import FrameType
from typing import Any

#: The signals a command stops on, as Ctrl-C stops it.
STOP_SIGNALS: tuple[signal.Signals, ...] = (signal.SIGINT, signal.SIGTERM, signal.SIGHUP)


def caught() -> tuple[signal.Signals, ...]:
    """The stop signals to catch now: SIGHUP is left out while it is ignored (``nohup``).

    SIGINT and SIGTERM are caught even when ignored: a background job of a
    shell script starts with SIGINT ignored, and its clean-up must still run
    when it is interrupted.
    """
    return tuple(s for s in STOP_SIGNALS if s != signal.SIGHUP or signal.getsignal(s) != signal.SIG_IGN)


def after_signal(signum: int, fds: tuple[int, ...] = (0, 1, 2)) -> None:
    """After a SIGHUP, the ``fds`` (stdin, stdout, stderr) that were the hung-up terminal go nowhere.

    A hung-up terminal answers every request with EIO (a terminal that is
    still there, a file or a pipe is left alone), so a command's clean-up
    and its last line go to ``/dev/null`` instead of failing. It raises
    nothing: called from signal handlers, its own failure (no ``/dev/null``,
    no descriptor left) must not take the place of the interrupt.
    """
    if signum != signal.SIGHUP:
        return
    import termios

    for fd in fds:
        try:
            termios.tcgetattr(fd)
            continue  # a terminal still there
        except termios.error as e:
            if e.args[0] != errno.EIO:
                continue  # not a terminal (a file, a pipe), or closed
        try:  # from a signal handler: no error of its own may take the interrupt's place
            null = os.open(os.devnull, os.O_RDWR)
        except OSError:
            return
        try:
            os.dup2(null, fd)
        except OSError:
            pass
        finally:
            os.close(null)


#: A signal handler as :func:`signal.signal` takes it.
SignalHandler = Callable[[int, FrameType | None], Any]


def put_back(handlers: Sequence[tuple[int, SignalHandler]]) -> None:
    """Install each signal's handler; one that raises as soon as it is back leaves none of the rest out."""
    if not handlers:
        return
    try:
        signal.signal(*handlers[0])
    finally:
        put_back(handlers[1:])


@contextlib.contextmanager
def held() -> Iterator[list[int]]:
    """In the block the stop signals are only noted (yielded, in order), not handled.

    For a command's last steps: it has done its work and writes its state,
    or makes the arm safe after an error. Seen (a hostile test): a SIGTERM
    1-4 ms after ``enable``, ``move``, ``home --no-wait`` or ``disable``
    printed its result cut the state file's write and the bus's release
    short: exit 143, the state file not written (the emulated arm forgot
    what was sent), now and then an empty temporary file left beside it.
    A Python handler is swapped for one that notes the signal (SIGHUP still
    lets go of a hung-up terminal at once: :func:`after_signal`); the
    handlers are put back at the end. Outside the main thread, where no
    handler runs, nothing is held.
    """
    arrived: list[int] = []
    if threading.current_thread() is not threading.main_thread():
        yield arrived
        return

    def note(signum: int, frame: FrameType | None) -> None:
        arrived.append(signum)
        after_signal(signum)

    before: list[tuple[int, SignalHandler]] = []
    try:
        for signum in STOP_SIGNALS:
            handler = signal.getsignal(signum)
            if callable(handler):
                before.append((signum, handler))  # first: a signal landing next finds it put back
                signal.signal(signum, note)
        yield arrived
    finally:
        put_back(before)
