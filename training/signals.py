"""SIGINT, SIGTERM and SIGHUP during a deployment or a training run: :class:`Interrupted` at a safe point.

:class:`SignalGuard` turns the signals (:mod:`bioscara_gym.stop_signals`)
into :class:`Interrupted` (exit code 130 / 143 / 129). In a deployment: at
once outside the control loop, at the next cycle boundary inside it, and
never while the arm is being made safe. In training: at once, as Ctrl-C
always did, and never while a checkpoint or the final model is being written.
"""

from __future__ import annotations

import contextlib
import signal
import threading
from collections.abc import Iterator
from types import FrameType
from typing import Any

from bioscara_gym.stop_signals import after_signal, caught


class Interrupted(KeyboardInterrupt):
    """A stop signal arrived; ``exit_code`` is 128 + the signal number.

    ``deferred``: raised at a cycle boundary (:meth:`SignalGuard.check`) for a
    signal that arrived during the cycle, not where it landed (a bus trace
    records which, so a replay raises it at the same place).
    """

    def __init__(self, signum: int, deferred: bool = False) -> None:
        """Remember the signal."""
        self.signum = int(signum)
        self.deferred = deferred
        super().__init__(signal.Signals(self.signum).name)

    @property
    def exit_code(self) -> int:
        """130 for SIGINT, 143 for SIGTERM, 129 for SIGHUP."""
        return 128 + self.signum


class SignalGuard:
    """The stop signals become :class:`Interrupted` for the duration of a ``with`` block.

    By default the exception is raised where the signal lands (bring-up,
    homing and resets can block for seconds). Inside :meth:`deferred` the
    signal is only recorded and :meth:`check` raises it at the next cycle
    boundary, so no log line or bus exchange is cut in half; a second signal
    there raises at once. Inside :meth:`shielded` (the safe stop) signals are
    only recorded. Outside the main thread nothing is installed.
    """

    def __init__(self, signals: tuple[int, ...] | None = None) -> None:
        """Choose the signals to catch (default: :func:`~bioscara_gym.stop_signals.caught`)."""
        self.signals = caught() if signals is None else signals
        self.pending: int | None = None
        self._mode = "raise"
        self._previous: dict[int, Any] = {}

    def __enter__(self) -> SignalGuard:
        """Install the handlers."""
        if threading.current_thread() is threading.main_thread():
            for signum in self.signals:
                self._previous[signum] = signal.signal(signum, self._handle)
        return self

    def __exit__(self, *exc: object) -> None:
        """Restore the previous handlers."""
        for signum, handler in self._previous.items():
            signal.signal(signum, handler)
        self._previous.clear()

    def _handle(self, signum: int, frame: FrameType | None) -> None:
        repeated = self.pending is not None
        if self.pending is None:
            self.pending = signum
        after_signal(signum)
        if self._mode == "raise" or (self._mode == "defer" and repeated):
            raise Interrupted(self.pending)

    @contextlib.contextmanager
    def _in_mode(self, mode: str) -> Iterator[None]:
        previous, self._mode = self._mode, mode
        try:
            yield
        finally:
            self._mode = previous

    def deferred(self) -> contextlib.AbstractContextManager[None]:
        """Record signals; :meth:`check` raises them (a repeated signal raises at once)."""
        return self._in_mode("defer")

    def shielded(self) -> contextlib.AbstractContextManager[None]:
        """Record signals only (while the arm is being made safe)."""
        return self._in_mode("shield")

    def check(self) -> None:
        """Raise :class:`Interrupted` if a signal has arrived."""
        if self.pending is not None:
            raise Interrupted(self.pending, deferred=True)
