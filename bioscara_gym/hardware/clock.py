"""Injectable clocks: wall time on hardware, manual time in tests and simulation."""

from __future__ import annotations

import time
from typing import Protocol, runtime_checkable


@runtime_checkable
class Clock(Protocol):
    """A source of monotonic time in seconds that can also wait."""

    def now(self) -> float:
        """Return the current time in seconds."""
        ...

    def sleep(self, dt: float) -> None:
        """Let ``dt`` seconds pass."""
        ...


class WallClock:
    """Real time: ``time.monotonic`` and ``time.sleep``."""

    def now(self) -> float:
        """Return monotonic wall time in seconds."""
        return time.monotonic()

    def sleep(self, dt: float) -> None:
        """Sleep ``dt`` seconds of wall time (no-op for dt <= 0)."""
        if dt > 0:
            time.sleep(dt)


class ManualClock:
    """Time that moves only when told to; ``sleep`` advances it instantly.

    Tests use it to run firmware faster than real time and deterministically.
    """

    def __init__(self, start: float = 0.0) -> None:
        """Start at ``start`` seconds."""
        self._t = float(start)

    def now(self) -> float:
        """Return the current manual time in seconds."""
        return self._t

    def sleep(self, dt: float) -> None:
        """Advance time by ``dt`` seconds (negative values are ignored)."""
        if dt > 0:
            self._t += dt
