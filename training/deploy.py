"""``bioscara deploy``: run a policy on the arm, safely; ``bioscara export``: policy to ONNX.

Reads top to bottom, as a deployment runs:

1. **check** the policy's metadata against the env it would drive (task,
   spaces, control mode and rate); a mismatch is refused before anything is
   sent to the arm.
2. **configure**: connect and ping every joint.
3. **activate**: enable the joints, stall detection and limits.
4. **home** the joints that are not homed (a joint homed before a host
   restart keeps its offset, read back from HOMEOFFSET on configure).
5. **run** the episodes with the env the policy was trained on, on the
   chosen backend, through :class:`~bioscara_gym.training.safety.SafetyLayer`, at a fixed
   rate; every cycle goes to the run log.
6. **deactivate** (joints disabled, gripper width saved) and **clean up**.

Any stop (NaN action, stall, bus error, deadman, Ctrl-C/SIGTERM) ends in
:func:`~bioscara_gym.training.safety.safe_stop`. Exit codes: 0 done, 2 refused (nothing
sent to the arm), 3 safety stop, 130/143 SIGINT/SIGTERM, 1 unexpected error;
the arm is left disabled in every case. The run log is JSON Lines, one line
written and flushed per record, so it is complete after Ctrl-C:

=============  ======================================================================
``type``       fields
=============  ======================================================================
``header``     policy, env_id, backend, rate_hz, control_mode, faults, seed, episodes,
               realtime, started
``phase``      phase, detail, t (backend clock, s)
``cycle``      cycle, episode, step, t, period_s (backend clock), wall_period_s, work_s
               (host time for policy + step), silence_s (longest joint silence), overrun,
               action (policy output), clamped, commands / q / qd / flags (per joint), reward;
               the cycle a safety stop cut short: action, flags, ``stopped: true``
``episode``    episode, success, distance, steps, return, stalled
``stop``       reason, message, joint
``summary``    episodes, successes, cycles, period/jitter/overrun statistics, stop_reason,
               message, joint, final_state (per-joint flags after the stop, read from the
               emulator where there is one), arm_disabled, not_confirmed_disabled,
               gripper (width_m, state_file), exit_code
=============  ======================================================================

On ``mock`` and ``emulated`` time is simulated: ``period_s`` is simulated and
the loop runs as fast as the host can unless ``--realtime`` paces it on the
wall clock; on ``i2c`` the backend waits on a fixed schedule.
"""

from __future__ import annotations

import argparse
import dataclasses
import json
import math
import os
import time
from collections.abc import Callable
from dataclasses import dataclass, field
from pathlib import Path
from typing import Any, Protocol

import gymnasium as gym
import numpy as np
from bioscara_gym.training.metadata import check_metadata, read_metadata
from bioscara_gym.training.safety import (
    DeadmanGuard,
    Interrupted,
    SafetyLayer,
    SafetyStop,
    SignalGuard,
    StopReason,
    final_state,
    joint_named_in,
    safe_stop,
)
from rich.console import Console
from rich.markup import escape
from rich.table import Table

from bioscara_gym.errors import DeployError, MetadataError
from bioscara_gym.hardware.arm import Lifecycle
from bioscara_gym.hardware.config import load_config
from bioscara_gym.hardware.emulated_bus import FaultPlan
from bioscara_gym.hardware.errors import CommError, JointError

#: Backends deploy drives (``sim`` has no bus: use ``bioscara eval``).
DEPLOY_BACKENDS = ("i2c", "emulated", "mock")
#: A cycle is an overrun when its period exceeds the nominal one by this fraction.
OVERRUN_TOLERANCE = 0.1
#: Overrun warnings printed before they are only counted.
OVERRUN_WARNINGS = 5
#: fsync the log at least this often (every line is flushed), s.
FSYNC_INTERVAL_S = 1.0
#: Exit codes: refused before touching the arm, stopped by the safety layer.
EXIT_REFUSED = 2
EXIT_SAFETY_STOP = 3


class Policy(Protocol):
    """Observation -> action; ``reset()`` is called at each episode start if present."""

    def __call__(self, obs: dict[str, np.ndarray]) -> np.ndarray:
        """The action for ``obs``."""
        ...


@dataclass
class DeployArgs:
    """Arguments of ``bioscara deploy`` (the CLI flags map one to one).

    Attributes:
        model: A trained ``model.zip`` (metadata.json beside it).
        onnx: An ONNX policy from ``bioscara export`` (runs without torch).
        expert: Run the scripted expert of ``env`` instead of a policy.
        env: Env id for ``expert``; with a policy, must match its metadata.
        backend: ``i2c`` (the arm), ``emulated`` (real driver, emulated bus) or ``mock``.
        bus: I2C bus number (``/dev/i2c-N``); default the config's.
        config: Arm configuration YAML; default the packaged one.
        episodes: Episodes to run.
        rate: Control rate in Hz; default the policy's. Must match a trained policy's.
        log: Run log (JSON Lines); default ``runs/deploy/deploy-<time>.jsonl``.
        faults: Fault injection on ``emulated``, e.g. ``nack=0.01,latency_ms=2``.
        seed: Seed of the first episode.
        realtime: On simulated backends, pace the loop on the wall clock too.
        state_file: Gripper state file; default the backend's (on the arm) or
            ``gripper.json`` beside the log (simulated backends).
    """

    model: Path | None = None
    onnx: Path | None = None
    expert: bool = False
    env: str | None = None
    backend: str = "emulated"
    bus: int | None = None
    config: Path | None = None
    episodes: int = 1
    rate: float | None = None
    log: Path | None = None
    faults: str | None = None
    seed: int = 10_000
    realtime: bool = False
    state_file: Path | None = None


# -------------------------------------------------------------------- run log
def _jsonable(value: Any) -> Any:
    """Numbers, arrays and dicts as strict JSON (non-finite floats as strings)."""
    if isinstance(value, dict):
        return {str(k): _jsonable(v) for k, v in value.items()}
    if isinstance(value, list | tuple | np.ndarray):
        return [_jsonable(v) for v in value]
    if isinstance(value, bool | np.bool_):
        return bool(value)
    if isinstance(value, int | np.integer):
        return int(value)
    if isinstance(value, float | np.floating):
        f = float(value)
        return f if math.isfinite(f) else str(f)
    if value is None or isinstance(value, str):
        return value
    return str(value)


class RunLog:
    """JSON Lines, one ``write`` and flush per record, fsync'd every second and on close.

    Args:
        path: The log file (parents created; an existing file is replaced).
    """

    def __init__(self, path: Path) -> None:
        """Open ``path`` for writing."""
        self.path = Path(path)
        self.path.parent.mkdir(parents=True, exist_ok=True)
        self._f = open(self.path, "w", encoding="utf-8")  # noqa: SIM115 - closed in close()
        self._synced = time.monotonic()
        self.lines = 0

    def write(self, record: dict[str, Any]) -> None:
        """Append one record as a line."""
        self._f.write(json.dumps(_jsonable(record), allow_nan=False, separators=(",", ":")) + "\n")
        self._f.flush()
        self.lines += 1
        now = time.monotonic()
        if now - self._synced >= FSYNC_INTERVAL_S:
            os.fsync(self._f.fileno())
            self._synced = now

    def close(self) -> None:
        """Flush, fsync and close."""
        if not self._f.closed:
            self._f.flush()
            os.fsync(self._f.fileno())
            self._f.close()


# ------------------------------------------------------------------- timing
@dataclass
class LoopStats:
    """Period, jitter and overruns of the control loop.

    ``period`` is on the backend's clock (simulated on ``mock``/``emulated``,
    the wall clock on ``i2c``), ``wall_period`` on the host's wall clock,
    ``work`` the host time the policy and the step took. The first cycle of
    each episode has no period (it follows a reset).
    """

    nominal_s: float
    periods: list[float] = field(default_factory=list)
    wall_periods: list[float] = field(default_factory=list)
    work: list[float] = field(default_factory=list)
    silences: list[float] = field(default_factory=list)
    overruns: int = 0

    def summary(self) -> dict[str, float | int | None]:
        """Mean, max and standard deviation (jitter) of each series."""

        def stats(xs: list[float], name: str) -> dict[str, float | None]:
            a = np.asarray(xs)
            if a.size == 0:
                return {f"{name}_mean_s": None, f"{name}_max_s": None, f"{name}_jitter_s": None}
            return {
                f"{name}_mean_s": float(a.mean()),
                f"{name}_max_s": float(a.max()),
                f"{name}_jitter_s": float(a.std()),
            }

        return {
            "rate_hz": 1.0 / self.nominal_s,
            **stats(self.periods, "period"),
            **stats(self.wall_periods, "wall_period"),
            "work_mean_s": float(np.mean(self.work)) if self.work else None,
            "work_max_s": float(np.max(self.work)) if self.work else None,
            "max_silence_s": float(np.max(self.silences)) if self.silences else None,
            "overruns": self.overruns,
        }


# ------------------------------------------------------------------ policies
def _describe_env(env: gym.Env) -> str:
    u = env.unwrapped
    return f"{_env_id(env)} ({u.control_mode}, {u.control_freq:g} Hz)"


def _env_id(env: gym.Env) -> str:
    """The registered id of ``env`` (the unwrapped env's spec: no deep copy of the kwargs)."""
    spec = env.unwrapped.spec
    return spec.id if spec is not None else type(env.unwrapped).__name__


def load_policy(args: DeployArgs) -> tuple[Callable[[gym.Env], Policy], dict[str, Any] | None, str]:
    """A factory of the policy (given the env), its metadata and a description.

    Only ``--model`` imports torch and stable-baselines3.

    Raises:
        DeployError: No policy source, or more than one.
        MetadataError: ``--model`` without a readable ``metadata.json``.
    """
    sources = [s for s in (args.model is not None, args.onnx is not None, args.expert) if s]
    if len(sources) != 1:
        raise DeployError("deploy needs exactly one of --model PATH, --onnx FILE or --expert --env ID")
    if args.expert:
        from bioscara_gym.experts import expert_for

        return (lambda env: expert_for(env.unwrapped)), None, "scripted expert"
    if args.onnx is not None:
        from bioscara_gym.training.export import OnnxPolicy

        onnx_policy = OnnxPolicy(args.onnx)
        return (lambda env: onnx_policy), onnx_policy.metadata, f"ONNX {args.onnx}"
    from bioscara_gym.training.evaluate import load_model, sb3_policy

    read_metadata(Path(args.model))  # a missing metadata.json is refused before torch loads
    model, metadata = load_model(Path(args.model))
    sb3 = sb3_policy(model)
    return (lambda env: sb3), metadata, f"{str(metadata.get('algo', 'sb3')).upper()} {args.model}"


# ---------------------------------------------------------------- deployment
class Deployment:
    """One ``bioscara deploy`` run (see the module docstring).

    Args:
        args: The run's arguments.
        policy: A policy to run instead of the one ``args`` names (tests,
            scripted checks); with ``metadata`` it is checked like a trained one.
        metadata: Metadata of ``policy``.
        console: Where phases and warnings are printed.
        on_cycle: Called with ``(cycle, env)`` before each cycle's policy call
            (test hook: inject a fault mid-run).
    """

    def __init__(
        self,
        args: DeployArgs,
        policy: Policy | None = None,
        metadata: dict[str, Any] | None = None,
        console: Console | None = None,
        on_cycle: Callable[[int, gym.Env], None] | None = None,
    ) -> None:
        """Validate the arguments; nothing is built or sent yet."""
        if args.backend not in DEPLOY_BACKENDS:
            raise DeployError(
                f"backend {args.backend!r} is not deployable; expected one of {', '.join(DEPLOY_BACKENDS)}"
            )
        if args.episodes < 1:
            raise DeployError(f"--episodes must be >= 1, got {args.episodes}")
        if args.rate is not None and not args.rate > 0:
            raise DeployError(f"--rate must be > 0 Hz, got {args.rate}")
        if args.faults and args.backend != "emulated":
            raise DeployError("--faults needs --backend emulated (faults are injected by the emulated bus)")
        self.args = args
        self.console = console or Console(highlight=False, soft_wrap=True)
        self.on_cycle = on_cycle
        self._policy_override = policy
        self._metadata_override = metadata
        self.env: gym.Env | None = None
        self.summary: dict[str, Any] = {}
        self.log_path = (
            Path(args.log) if args.log else Path("runs/deploy") / time.strftime("deploy-%Y%m%d-%H%M%S.jsonl")
        )
        self._t0 = time.perf_counter()
        self._gripper_width: float | None = None
        self._early_phases: list[dict[str, Any]] = []

    # --------------------------------------------------------------- output
    def _phase(self, name: str, detail: str, log: RunLog | None = None) -> None:
        """Print a phase; log it (phases before the log opens are logged when it does)."""
        self.console.print(f"[bold]{name:<10}[/bold] {escape(detail)}")
        t = self.env.unwrapped.backend.clock.now() if self.env is not None else None
        record = {"type": "phase", "phase": name, "detail": detail, "t": t}
        if log is None:
            self._early_phases.append(record)
        else:
            log.write(record)

    def _starting(self, name: str, detail: str) -> None:
        """Print that a phase starts (a failure in it is printed right after)."""
        self.console.print(f"[bold]{name:<10}[/bold] {escape(detail)} ...")

    # ----------------------------------------------------------------- build
    def _make_env(self, metadata: dict[str, Any] | None) -> gym.Env:
        args = self.args
        kwargs: dict[str, Any] = dict(metadata.get("env_kwargs", {})) if metadata else {}
        if metadata:
            env_id = metadata.get("env_id")
            if args.env is not None:
                env_id = args.env  # checked against the metadata below
        else:
            env_id = args.env or "Bioscara-Reach-v0"
        config = load_config(args.config)
        if args.bus is not None:
            config = dataclasses.replace(config, bus=args.bus)
        options: dict[str, Any] = {}
        state_file = args.state_file
        if state_file is None and args.backend != "i2c":
            state_file = self.log_path.parent / "gripper.json"
        if state_file is not None:
            options["state_file"] = state_file
        if args.faults:
            options["faults"] = FaultPlan.parse(args.faults)
        kwargs.update(backend=args.backend, backend_options=options, config=config, render_mode=None)
        if args.rate is not None:
            kwargs["control_freq"] = float(args.rate)
        try:
            return gym.make(env_id, **kwargs)
        except gym.error.Error as e:
            raise DeployError(f"cannot make env {env_id!r}: {e}") from e

    # ------------------------------------------------------------------- run
    def run(self) -> dict[str, Any]:
        """Check, bring up, run, shut down. Returns the summary.

        Raises:
            DeployError: Refused (code 2), or stopped by the safety layer
                (code 3); the arm is safe and the summary is attached.
            Interrupted: SIGINT/SIGTERM; the arm is safe, ``self.summary`` is set.
        """
        args = self.args
        if self._policy_override is not None:
            given = self._policy_override
            make_policy: Callable[[gym.Env], Policy] = lambda env: given  # noqa: E731
            metadata, description = self._metadata_override, "given policy"
        else:
            make_policy, metadata, description = load_policy(args)
        env = self.env = self._make_env(metadata)
        try:
            env_id = _env_id(env)
            self.console.print(
                f"[bold]deploy[/bold]     {escape(description)} -> {_describe_env(env)} on {args.backend}"
            )
            if metadata is not None:
                try:
                    check_metadata(metadata, env, env_id)
                except MetadataError as e:
                    raise DeployError(f"refused: {e}; nothing was sent to the arm") from e
                self._phase("check", "policy metadata matches the env; nothing sent to the arm yet")
            else:
                self._phase("check", "no metadata to check (scripted policy)")
            return self._run(env, env_id, make_policy(env), description)
        finally:
            env.close()

    def _run(self, env: gym.Env, env_id: str, policy: Policy, description: str) -> dict[str, Any]:
        args = self.args
        u = env.unwrapped
        arm, backend = u.arm, u.backend
        log = RunLog(self.log_path)
        stats = LoopStats(nominal_s=u.dt)
        counts = {"episodes": 0, "successes": 0, "cycles": 0}
        reason, message, joint, exit_code = StopReason.COMPLETED, "completed", None, 0
        guard: DeadmanGuard | None = None
        signals = SignalGuard()
        stop_report = None
        log.write(
            {
                "type": "header",
                "policy": description,
                "env_id": env_id,
                "backend": args.backend,
                "rate_hz": u.control_freq,
                "control_mode": u.control_mode,
                "faults": args.faults,
                "seed": args.seed,
                "episodes": args.episodes,
                "realtime": args.realtime,
                "started": time.strftime("%Y-%m-%dT%H:%M:%S%z"),
            }
        )
        for record in self._early_phases:
            log.write(record)
        try:
            with signals:
                try:
                    self._bring_up(env, log)
                    guard = DeadmanGuard(backend)
                    safety = SafetyLayer(env, guard)
                    self._phase(
                        "run",
                        f"{args.episodes} episode(s) at {u.control_freq:g} Hz, log {self.log_path}",
                        log,
                    )
                    self._episodes(env, policy, safety, signals, log, stats, counts)
                    with signals.shielded():
                        arm.deactivate()
                        self._gripper_width = arm.gripper.get_position()
                        saved = "saved" if arm.gripper.state_file else "not kept (no state file)"
                        self._phase(
                            "deactivate",
                            f"joints disabled, gripper width {self._gripper_width:.3f} m {saved}",
                            log,
                        )
                        arm.cleanup()
                        self._phase("cleanup", "joints and gripper disconnected", log)
                except BaseException as e:  # every way out makes the arm safe first
                    with signals.shielded():
                        reason, message, joint, exit_code = self._classify(e, arm)
                        stop_report = safe_stop(arm)  # the arm first, then the words
                        self._gripper_width = stop_report.gripper_width_m
                        self.console.print(f"[bold red]{'safe stop':<10}[/bold red] {escape(message)}")
                        log.write(
                            {"type": "stop", "reason": reason.value, "message": message, "joint": joint}
                        )
                        if not isinstance(e, Exception | KeyboardInterrupt):
                            raise
                finally:
                    with signals.shielded():
                        if guard is not None:
                            guard.detach()
                        if arm.state is not Lifecycle.FINALIZED:
                            arm.shutdown()
                        self.summary = self._summary(
                            env, stats, counts, reason, message, joint, exit_code, stop_report
                        )
                        log.write({"type": "summary", **self.summary})
        finally:
            log.close()
        self._print_summary()
        if reason is StopReason.COMPLETED:
            return self.summary
        disabled = self._disabled_line()
        self.console.print(disabled)
        if reason in (StopReason.INTERRUPTED, StopReason.TERMINATED):
            raise Interrupted(exit_code - 128)
        raise DeployError(f"safe stop: {message}", exit_code, self.summary)

    @staticmethod
    def _classify(e: BaseException, arm: Any) -> tuple[StopReason, str, str | None, int]:
        if isinstance(e, SafetyStop):
            return e.reason, str(e), e.joint, EXIT_SAFETY_STOP
        if isinstance(e, Interrupted):
            return e.reason, f"{e} received", None, e.exit_code
        if isinstance(e, KeyboardInterrupt):
            return StopReason.INTERRUPTED, "SIGINT received", None, 130
        if isinstance(e, CommError):
            return (
                StopReason.COMM_ERROR,
                f"communication error: {e}",
                joint_named_in(e, arm.names),
                EXIT_SAFETY_STOP,
            )
        if isinstance(e, JointError):
            return StopReason.JOINT_ERROR, f"joint error: {e}", joint_named_in(e, arm.names), EXIT_SAFETY_STOP
        return StopReason.ERROR, f"{type(e).__name__}: {e}", None, 1

    # ---------------------------------------------------------------- phases
    def _bring_up(self, env: gym.Env, log: RunLog) -> None:
        u = env.unwrapped
        arm = u.arm
        addressed = ", ".join(
            f"{n} {j.address:#04x}" if hasattr(j, "address") else n for n, j in arm.joints.items()
        )
        self._starting("configure", f"connecting and pinging {addressed}")
        arm.configure()
        self._phase("configure", "every joint answered", log)
        homed_before = [n for n in arm.names if arm.joint_states[n].homed]
        self._starting("activate", "enabling joints, stall detection and limits")
        arm.activate()
        self._phase("activate", "joints enabled, stall detection and limits set", log)
        todo = [n for n in arm.names if n not in homed_before]
        if homed_before:
            self._phase(
                "home", f"{', '.join(homed_before)} homed before: offset restored from HOMEOFFSET", log
            )
        if todo:
            t0 = u.backend.clock.now()
            self._starting("home", f"homing {', '.join(todo)}")
            arm.home(todo)
            self._phase("home", f"{', '.join(todo)} homed in {u.backend.clock.now() - t0:.1f} s", log)
        from bioscara_gym.envs.base import JOINT_MODE

        mode = JOINT_MODE[u.control_mode]
        for name in u.joint_names:
            arm.claim(name, mode)

    def _episodes(
        self,
        env: gym.Env,
        policy: Policy,
        safety: SafetyLayer,
        signals: SignalGuard,
        log: RunLog,
        stats: LoopStats,
        counts: dict[str, int],
    ) -> None:
        args = self.args
        u = env.unwrapped
        arm, clock = u.arm, u.backend.clock
        dt = u.dt
        names = u.joint_names
        paced_wall = args.realtime or args.backend == "i2c"
        for ep in range(args.episodes):
            obs, info = env.reset(seed=args.seed + ep)
            if hasattr(policy, "reset"):
                policy.reset()
            safety.guard.restart()
            prev_wall = prev_clock = None
            deadline = time.perf_counter()
            total, steps = 0.0, 0
            while True:
                with signals.deferred():
                    signals.check()
                    if self.on_cycle is not None:
                        self.on_cycle(counts["cycles"], env)
                    t_wall, t_clock = time.perf_counter(), clock.now()
                    period = None if prev_clock is None else t_clock - prev_clock
                    wall_period = None if prev_wall is None else t_wall - prev_wall
                    prev_wall, prev_clock = t_wall, t_clock
                    raw = policy(obs)
                    try:
                        (obs, reward, terminated, truncated, info), check = safety.step(raw)
                    except SafetyStop:
                        log.write(
                            {
                                "type": "cycle",
                                "cycle": counts["cycles"],
                                "episode": ep,
                                "step": steps,
                                "t": t_clock,
                                "action": np.asarray(raw, dtype=np.float64),
                                "flags": {n: int(arm.joint_states[n].flags) for n in names},
                                "stopped": True,
                            }
                        )
                        raise
                    work = time.perf_counter() - t_wall
                    overrun = self._account(stats, dt, period, wall_period, work, check.silence_s, paced_wall)
                    if overrun:
                        self._warn_overrun(stats, counts["cycles"], dt, wall_period if paced_wall else period)
                    states = arm.joint_states
                    log.write(
                        {
                            "type": "cycle",
                            "cycle": counts["cycles"],
                            "episode": ep,
                            "step": steps,
                            "t": t_clock,
                            "period_s": period,
                            "wall_period_s": wall_period,
                            "work_s": work,
                            "silence_s": check.silence_s,
                            "overrun": overrun,
                            "action": np.asarray(raw, dtype=np.float64),
                            "clamped": check.clamped,
                            "commands": {n: arm.commands[n] for n in names},
                            "q": {n: states[n].position for n in names},
                            "qd": {n: states[n].velocity for n in names},
                            "flags": {n: int(states[n].flags) for n in names},
                            "reward": reward,
                        }
                    )
                    counts["cycles"] += 1
                    total += float(reward)
                    steps += 1
                    if args.realtime:
                        deadline = max(deadline + dt, time.perf_counter() - dt)
                        pause = deadline - time.perf_counter()
                        if pause > 0:
                            time.sleep(pause)
                if terminated or truncated:
                    break
            success = bool(info.get("is_success", False))
            counts["episodes"] += 1
            counts["successes"] += success
            log.write(
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
                f"{'':<10} episode {ep + 1}/{args.episodes}: {'success' if success else 'miss'}, "
                f"distance {info.get('distance', math.nan) * 1000:.1f} mm, {steps} steps"
            )

    @staticmethod
    def _account(
        stats: LoopStats,
        dt: float,
        period: float | None,
        wall_period: float | None,
        work: float,
        silence: float,
        paced_wall: bool,
    ) -> bool:
        """Add one cycle's timing to ``stats``; return whether it overran.

        A cycle overruns when its period on the backend's clock (what the
        joints see), or on the wall clock where the loop is paced by it, is
        more than ``OVERRUN_TOLERANCE`` over the nominal period.
        """
        limit = dt * (1 + OVERRUN_TOLERANCE)
        overrun = period is not None and period > limit
        overrun |= paced_wall and wall_period is not None and wall_period > limit
        if period is not None:
            stats.periods.append(period)
        if wall_period is not None:
            stats.wall_periods.append(wall_period)
        stats.work.append(work)
        stats.silences.append(silence)
        stats.overruns += overrun
        return overrun

    def _warn_overrun(self, stats: LoopStats, cycle: int, dt: float, period: float | None) -> None:
        if stats.overruns > OVERRUN_WARNINGS:
            return
        more = " (further overruns are only counted)" if stats.overruns == OVERRUN_WARNINGS else ""
        self.console.print(
            f"[yellow]warning[/yellow]: overrun at cycle {cycle}: period "
            f"{(period or 0.0) * 1000:.1f} ms > {dt * 1000:.0f} ms{more}"
        )

    # --------------------------------------------------------------- summary
    def _summary(
        self,
        env: gym.Env,
        stats: LoopStats,
        counts: dict[str, int],
        reason: StopReason,
        message: str,
        joint: str | None,
        exit_code: int,
        stop_report: Any,
    ) -> dict[str, Any]:
        u = env.unwrapped
        state = final_state(u.backend)
        gripper = u.arm.gripper
        return {
            **counts,
            "success_rate": counts["successes"] / counts["episodes"] if counts["episodes"] else None,
            **stats.summary(),
            "stop_reason": reason.value,
            "message": message,
            "joint": joint,
            "final_state": state,
            "arm_disabled": all(not s["enabled"] for s in state.values()),
            "arm_state": u.arm.state.value,
            "problems": stop_report.problems if stop_report else [],
            "not_confirmed_disabled": stop_report.not_confirmed if stop_report else [],
            "gripper": {
                "width_m": self._gripper_width,
                "state_file": str(gripper.state_file) if gripper.state_file else None,
            },
            "exit_code": exit_code,
            "wall_time_s": time.perf_counter() - self._t0,
        }

    def _disabled_line(self) -> str:
        s = self.summary
        if s["arm_disabled"]:
            return "arm disabled: every joint reports not enabled; arm shut down, bus closed"
        enabled = [n for n, st in s["final_state"].items() if st["enabled"]]
        return (
            f"[red]arm NOT confirmed disabled[/red]: {', '.join(enabled)} still enabled "
            f"({escape('; '.join(s['problems'])) or 'no reply'}); cut the power"
        )

    def _print_summary(self) -> None:
        s = self.summary

        def ms(key: str) -> str:
            v = s.get(key)
            return "-" if v is None else f"{v * 1000:.2f} ms"

        table = Table(title=f"deploy summary ({s['stop_reason']})")
        table.add_column("metric")
        table.add_column("value", justify="right")
        rate = f"{s['successes']}/{s['episodes']}"
        if s["success_rate"] is not None:
            rate += f" ({s['success_rate']:.0%})"
        table.add_row("episodes (successes)", rate)
        table.add_row("cycles", str(s["cycles"]))
        table.add_row("rate", f"{s['rate_hz']:g} Hz")
        table.add_row("period mean / max (backend clock)", f"{ms('period_mean_s')} / {ms('period_max_s')}")
        table.add_row("jitter (std, backend clock)", ms("period_jitter_s"))
        table.add_row(
            "host loop mean / jitter (wall)", f"{ms('wall_period_mean_s')} / {ms('wall_period_jitter_s')}"
        )
        table.add_row("host work per cycle mean / max", f"{ms('work_mean_s')} / {ms('work_max_s')}")
        table.add_row("longest joint silence", ms("max_silence_s"))
        table.add_row("overruns", str(s["overruns"]))
        table.add_row("stop", escape(s["message"]))
        flags = ", ".join(f"{n} {st['flag_names']}" for n, st in s["final_state"].items())
        table.add_row("final flags", flags)
        self.console.print(table)
        self.console.print(f"log        {self.log_path}", markup=False)


# ----------------------------------------------------------------------- CLI
def _args_from_namespace(ns: argparse.Namespace) -> DeployArgs:
    return DeployArgs(
        model=ns.model,
        onnx=ns.onnx,
        expert=ns.expert,
        env=ns.env,
        backend=ns.backend,
        bus=ns.bus,
        config=ns.config,
        episodes=ns.episodes,
        rate=ns.rate,
        log=ns.log,
        faults=ns.faults,
        seed=ns.seed,
        realtime=ns.realtime,
        state_file=ns.state_file,
    )


def cmd_deploy(ns: argparse.Namespace) -> int:
    """``bioscara deploy``: 0 when every episode ran, else one line naming the cause.

    Errors are printed here rather than raised as the CLI's ``CliError``: under
    ``python -m bioscara_gym.cli`` that class exists twice (``__main__`` and
    ``bioscara_gym.cli``), and the exit code must not depend on how deploy
    was started.
    """
    try:
        Deployment(_args_from_namespace(ns)).run()
    except DeployError as e:
        Console(stderr=True, highlight=False, soft_wrap=True).print(
            f"bioscara deploy: error: {e}", markup=False
        )
        return e.code
    except Interrupted as e:
        Console(stderr=True, highlight=False, soft_wrap=True).print(
            f"bioscara deploy: interrupted by {e}", markup=False
        )
        return e.exit_code
    return 0


def cmd_export(ns: argparse.Namespace) -> int:
    """``bioscara export``: write the ONNX file and report the check against torch."""
    from bioscara_gym.training.export import export_onnx

    result = export_onnx(ns.model, ns.onnx, check_samples=ns.check)
    con = Console(highlight=False, markup=False, soft_wrap=True)
    con.print(f"onnx      {result.path}")
    con.print(f"input     obs = {' + '.join(f'{k}[{n}]' for k, n in result.obs_keys)}")
    if result.checked:
        con.print(
            f"check     max |onnx - predict| = {result.max_abs_error:.2e} over {result.checked} observations"
        )
    return 0


def register(sub: argparse._SubParsersAction) -> None:
    """Add the ``deploy`` and ``export`` subcommands."""
    p = sub.add_parser(
        "deploy",
        help="run a policy on the arm (or its emulation) behind the safety layer",
        description="Check the policy against the env, bring the arm up, run episodes at a fixed rate "
        "behind the safety layer, log every cycle. Exit codes: 0 done, 2 refused (nothing sent), "
        "3 safety stop (arm disabled), 130/143 SIGINT/SIGTERM (arm disabled).",
    )
    src = p.add_mutually_exclusive_group(required=True)
    src.add_argument("--model", type=Path, help="model.zip (metadata.json beside it)")
    src.add_argument("--onnx", type=Path, help="ONNX policy from `bioscara export` (no torch needed)")
    src.add_argument("--expert", action="store_true", help="run the scripted expert of --env")
    p.add_argument("--env", help="env id (for --expert; with a policy it must match the metadata)")
    p.add_argument("--backend", choices=DEPLOY_BACKENDS, default="emulated", help="default: emulated")
    p.add_argument("--bus", type=int, help="I2C bus number, /dev/i2c-N (default: the config's)")
    p.add_argument("--config", type=Path, help="arm configuration YAML (default: the packaged one)")
    p.add_argument("--episodes", type=int, default=1)
    p.add_argument(
        "--rate",
        type=float,
        help="control rate in Hz (default: the policy's; a trained policy refuses another)",
    )
    p.add_argument("--log", type=Path, help="run log, JSON Lines (default: runs/deploy/deploy-<time>.jsonl)")
    p.add_argument("--faults", help="emulated bus faults, e.g. nack=0.01,latency_ms=0.5 (per transaction)")
    p.add_argument("--seed", type=int, default=10_000, help="seed of the first episode")
    p.add_argument("--realtime", action="store_true", help="pace mock/emulated on the wall clock too")
    p.add_argument("--state-file", type=Path, help="gripper state file")
    p.set_defaults(func=cmd_deploy)

    p = sub.add_parser("export", help="export a trained policy to ONNX (checked against torch)")
    p.add_argument("--model", type=Path, required=True, help="model.zip (metadata.json beside it)")
    p.add_argument("--onnx", type=Path, required=True, help="ONNX file to write")
    p.add_argument("--check", type=int, default=256, help="observations to compare with model.predict")
    p.set_defaults(func=cmd_export)
