"""Injectable clocks (wall time on hardware, manual time in tests and simulation) and the loop's deadlines."""

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


class DeadlineScheduler:
    """The deadlines of a fixed-rate loop on a clock: every backend's ``step``.

    :meth:`wait` returns ``period`` after the previous deadline, not after
    now: the time the cycle's own work took (bus transactions, the policy)
    comes out of the period, so the loop keeps its rate without drift. A
    cycle whose work ran past its deadline is an overrun: :meth:`wait`
    returns at once and the schedule restarts from now (no burst of short
    catch-up cycles). On a wall clock the wait is a sleep; on a simulated
    clock it is the simulation advancing to the deadline.

    Args:
        clock: The clock to read and wait on.
        scale: How long a period lasts on ``clock`` per second the loop asks
            for: ``1 + drift_ppm * 1e-6`` when the host's clock runs slow by
            ``drift_ppm`` (its periods last longer; < 0: fast); 1.0 for none.

    Attributes:
        deadline: The last deadline (or where the schedule restarted), s on ``clock``.
        overruns: Cycles that ran past their deadline.
    """

    def __init__(self, clock: Clock, scale: float = 1.0) -> None:
        """Start the schedule at the clock's now."""
        if not scale > 0.0:
            raise ValueError(f"scale={scale} must be > 0 (a drift above -1e6 ppm)")
        self.clock = clock
        self.scale = float(scale)
        self.deadline = clock.now()
        self.overruns = 0

    def restart(self) -> None:
        """Restart the schedule from now: the next deadline is one period away."""
        self.deadline = self.clock.now()

    def wait(self, period: float) -> bool:
        """Wait until ``period`` after the previous deadline; ``False`` on an overrun (no wait).

        A period of 0 (or less) waits for nothing and leaves the schedule as
        it is. A clock that went back (a simulation reset or restored from a
        snapshot) restarts the schedule from now first.
        """
        if period <= 0.0:
            return True
        now = self.clock.now()
        if now < self.deadline - 1e-9:
            self.deadline = now
        deadline = self.deadline + period * self.scale
        if deadline < now:
            self.deadline = now
            self.overruns += 1
            return False
        self.deadline = deadline
        self.clock.sleep(deadline - now)
        return True
