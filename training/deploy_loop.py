"""The run phase of ``bioscara deploy``: episodes of control cycles, each behind the safety layer.

:class:`ControlLoop` resets the env (and the policy, if it has a ``reset()``)
for each episode and runs its cycles:
the policy's action through :class:`~bioscara_gym.training.deploy_safety.SafetyLayer`,
the cycle's timing on the backend's clock and the wall clock
(:class:`EpisodeClock`), overruns warned about, and one ``cycle`` record per
cycle in the run log, with the bus retries and errors it had. SIGINT and
SIGTERM are taken only between cycles. It reaches the arm through the env
(``step``, ``reset``) and the arm's public API (clock, deadman guard, joint
states, commands).
"""

from __future__ import annotations

import math
import time
from collections.abc import Callable
from dataclasses import dataclass, field
from typing import Any, Protocol

import gymnasium as gym
import numpy as np
from rich.console import Console

from bioscara_gym.hardware.arm import Arm
from bioscara_gym.hardware.config import ArmConfig
from bioscara_gym.hardware.safety import DeadmanGuard, SafeStopReport
from bioscara_gym.training.deploy_checks import DeployArgs, Policy, first_line
from bioscara_gym.training.deploy_log import BusStats, CycleTiming, RunLog
from bioscara_gym.training.deploy_safety import CycleCheck, SafetyLayer, SafetyStop, StopReason
from bioscara_gym.training.signals import SignalGuard

#: Overrun warnings printed before they are only counted.
OVERRUN_WARNINGS = 5


class Target(Protocol):
    """What deploy uses of the env it drives: the Bioscara env's public API (``BioscaraEnv``'s table).

    The env owns the arm's lifecycle (:meth:`bring_up`, :meth:`shut_down`,
    :meth:`safe_stop`; ``close``); deploy reads the arm's state through the
    :class:`~bioscara_gym.hardware.arm.Arm`'s public API (clock, bus
    statistics, deadman guard, final state) and sends nothing to it itself.
    """

    control_mode: str
    control_freq: float
    dt: float
    joint_names: tuple[str, ...]
    config: ArmConfig
    arm: Arm

    def bring_up(self, observer: Any = None) -> None:
        """Configure, activate, home, claim; each step told to ``observer``."""
        ...

    def shut_down(self, observer: Any = None) -> float | None:
        """Deactivate, clean up, finalize; the gripper's width."""
        ...

    def safe_stop(self) -> SafeStopReport:
        """Every joint disabled whatever its flags say; the arm finalized."""
        ...


class Phases(Protocol):
    """Where the loop reports its phase and the bus records between cycles (the deployment)."""

    def done(self, phase: str, detail: str) -> None:
        """A phase (``run``) begins or ends: printed and logged."""
        ...

    def log_bus(self, phase: str, **where: Any) -> None:
        """A ``bus`` record of the retries and errors since the last one (an episode's reset)."""
        ...


@dataclass
class EpisodeClock:
    """One episode's timing from cycle to cycle, on the backend's clock and the wall clock."""

    prev_wall: float | None = None
    prev_clock: float | None = None
    deadline: float = field(default_factory=time.perf_counter)

    def tick(self, clock_now: float) -> tuple[float, float | None, float | None]:
        """Start a cycle: its wall time and its periods on both clocks (``None`` for the first)."""
        t_wall = time.perf_counter()
        period = None if self.prev_clock is None else clock_now - self.prev_clock
        wall_period = None if self.prev_wall is None else t_wall - self.prev_wall
        self.prev_wall, self.prev_clock = t_wall, clock_now
        return t_wall, period, wall_period

    def pace(self, dt: float) -> None:
        """Sleep until the next cycle is due on the wall clock (``--realtime``)."""
        self.deadline = max(self.deadline + dt, time.perf_counter() - dt)
        pause = self.deadline - time.perf_counter()
        if pause > 0:
            time.sleep(pause)


class ControlLoop:
    """The episodes of one deployment (see the module docstring).

    Args:
        target: The env's public API (``arm``, ``dt``, ``joint_names``, ``control_freq``).
        args: The run's arguments (episodes, seed, realtime, backend).
        log: The run log.
        bus: The bus statistics, per cycle.
        timing: The cycles' timing statistics.
        signals: The run's signal guard (stop signals between cycles only).
        console: Where overruns and episode results are printed.
        tell: Where phases and bus records between cycles go.
        on_cycle: Test hook, called with ``(cycle, env)`` before each cycle's policy call.

    Attributes:
        counts: Episodes, successes and cycles run so far.
        guard: The deadman guard, once :meth:`run` started (``detach()`` it after).
    """

    def __init__(
        self,
        target: Target,
        args: DeployArgs,
        log: RunLog,
        bus: BusStats,
        timing: CycleTiming,
        signals: SignalGuard,
        console: Console,
        tell: Phases,
        on_cycle: Callable[[int, gym.Env], None] | None = None,
    ) -> None:
        """Bind to the run's target, log and statistics."""
        self.target, self.args, self.log, self.bus, self.timing = target, args, log, bus, timing
        self.signals, self.console, self.tell, self.on_cycle = signals, console, tell, on_cycle
        self.counts = {"episodes": 0, "successes": 0, "cycles": 0}
        self.guard: DeadmanGuard | None = None

    def run(self, env: gym.Env, policy: Policy) -> None:
        """Run every episode behind the safety layer (the deadman guard listening from now)."""
        arm = self.target.arm
        self.guard = arm.watch_deadman()
        safety = SafetyLayer(env, arm, self.guard)
        rate = f"{self.target.control_freq:g} Hz"
        self.tell.done("run", f"{self.args.episodes} episode(s) at {rate}, log {self.log.path}")
        for ep in range(self.args.episodes):
            self._run_episode(env, policy, safety, ep)

    def _run_episode(self, env: gym.Env, policy: Policy, safety: SafetyLayer, ep: int) -> None:
        """Reset, then one cycle after another until the episode ends."""
        obs, info = env.reset(seed=self.args.seed + ep)
        self.tell.log_bus("reset", episode=ep)
        if hasattr(policy, "reset"):
            policy.reset()
        self.guard.restart()
        clock = EpisodeClock()
        total, steps, done = 0.0, 0, False
        while not done:
            with self.signals.deferred():
                self.signals.check()
                obs, reward, terminated, truncated, info = self._cycle(
                    env, policy, safety, clock, ep, steps, obs
                )
                total += float(reward)
                steps += 1
                if self.args.realtime:
                    clock.pace(self.target.dt)
            done = terminated or truncated
        self._end_episode(ep, info, steps, total)

    def _cycle(
        self,
        env: gym.Env,
        policy: Policy,
        safety: SafetyLayer,
        clock: EpisodeClock,
        ep: int,
        step: int,
        obs: dict[str, np.ndarray],
    ) -> tuple[Any, float, bool, bool, dict[str, Any]]:
        """One control cycle: the policy's action through the safety layer, accounted and logged."""
        if self.on_cycle is not None:
            self.on_cycle(self.counts["cycles"], env)
        arm = self.target.arm
        t_clock = arm.clock.now()
        t_wall, period, wall_period = clock.tick(t_clock)
        raw = _act(policy, obs)
        where = {"cycle": self.counts["cycles"], "episode": ep, "step": step, "t": t_clock}
        try:
            result, check = safety.step(raw)
        except SafetyStop:
            flags = {n: int(arm.joint_states[n].flags) for n in self.target.joint_names}
            record = {"type": "cycle", **where, "action": _floats(raw), "flags": flags, "stopped": True}
            self.log.write({**record, **self._bus_record()})
            raise
        timing = self._account_cycle(period, wall_period, time.perf_counter() - t_wall, check)
        state = self._cycle_state(raw, check)
        self.log.write(
            {"type": "cycle", **where, **timing, **state, "reward": result[1], **self._bus_record()}
        )
        self.counts["cycles"] += 1
        return result

    def _bus_record(self) -> dict[str, Any]:
        """``{"bus": ...}`` with the cycle's retries and errors per joint, or nothing if it had none."""
        changes = self.bus.cycle()
        return {"bus": changes} if changes else {}

    def _account_cycle(
        self, period: float | None, wall_period: float | None, work: float, check: CycleCheck
    ) -> dict[str, Any]:
        """Add a cycle's timing to the statistics, warn on an overrun; the cycle record's timing."""
        paced_wall = self.args.realtime or self.args.backend == "i2c"
        overrun = self.timing.add(period, wall_period, work, check.silence_s, paced_wall)
        if overrun:
            self._warn_overrun(self.target.dt, wall_period if paced_wall else period)
        return {
            "period_s": period,
            "wall_period_s": wall_period,
            "work_s": work,
            "silence_s": check.silence_s,
            "overrun": overrun,
        }

    def _cycle_state(self, raw: Any, check: CycleCheck) -> dict[str, Any]:
        """The cycle record's action, commands and per-joint state."""
        arm, names = self.target.arm, self.target.joint_names
        states = arm.joint_states
        return {
            "action": _floats(raw),
            "clamped": check.clamped,
            "commands": {n: arm.commands[n] for n in names},
            "q": {n: states[n].position for n in names},
            "qd": {n: states[n].velocity for n in names},
            "flags": {n: int(states[n].flags) for n in names},
        }

    def _warn_overrun(self, dt: float, period: float | None) -> None:
        """Print the first ``OVERRUN_WARNINGS`` overruns; count the rest silently."""
        overruns = self.timing.overruns
        if overruns > OVERRUN_WARNINGS:
            return
        more = " (further overruns are only counted)" if overruns == OVERRUN_WARNINGS else ""
        self.console.print(
            f"[yellow]warning[/yellow]: overrun at cycle {self.counts['cycles']}: period "
            f"{(period or 0.0) * 1000:.1f} ms > {dt * 1000:.0f} ms{more}"
        )

    def _end_episode(self, ep: int, info: dict[str, Any], steps: int, total: float) -> None:
        """Count, log and print the episode's result."""
        success = bool(info.get("is_success", False))
        self.counts["episodes"] += 1
        self.counts["successes"] += success
        self.log.write(
            {
                "type": "episode",
                "episode": ep,
                "success": success,
                "distance": info.get("distance"),
                "steps": steps,
                "return": total,
                "stalled": bool(info.get("stalled", False)),
            }
        )
        self.console.print(
            f"{'':<10} episode {ep + 1}/{self.args.episodes}: {'success' if success else 'miss'}, "
            f"distance {info.get('distance', math.nan) * 1000:.1f} mm, {steps} steps"
        )


def _act(policy: Policy, obs: dict[str, np.ndarray]) -> Any:
    """The policy's action; a failure inside the policy is a safety stop in one line.

    Raises:
        SafetyStop: ``nan_action``: the policy raised (e.g. torch refusing a
            NaN mean); the arm has not seen this cycle's action.
    """
    try:
        return policy(obs)
    except Exception as e:
        raise SafetyStop(
            StopReason.NAN_ACTION, f"the policy failed to act ({type(e).__name__}: {first_line(e)})"
        ) from e


def _floats(action: Any) -> np.ndarray:
    """The policy's raw action as float64, for the log."""
    return np.asarray(action, dtype=np.float64)
