"""``bioscara deploy``: run a policy on the arm, safely.

Reads top to bottom, as a deployment runs:

1. **check** the policy's metadata against the env it would drive (task,
   spaces, control mode and rate) and against the copy inside the model file,
   and run the policy once on a probe observation (NaN, infinity or a failure
   inside the policy is refused); a mismatch is refused before anything is
   sent to the arm.
2. **configure**: connect and ping every joint.
3. **activate**: enable the joints, stall detection and limits.
4. **home** the joints that are not homed (a joint homed before a host
   restart keeps its offset, read back from HOMEOFFSET on configure).
5. **run** the episodes with the env the policy was trained on, on the
   chosen backend, through :class:`~bioscara_gym.training.deploy_safety.SafetyLayer`,
   at a fixed rate; every cycle goes to the run log.
6. **deactivate** (joints disabled, gripper width saved) and **clean up**.

Before step 2, every argument is checked, and a policy is checked twice:
its metadata must state the task, the control mode and rate and the spaces
(nothing is defaulted), and the policy's own inputs and outputs (the SB3
model's spaces, the ONNX graph's input and output widths) must fit the env
the metadata builds. A refusal is one line and nothing is sent to the arm.

Any stop (NaN action, stall, bus error, deadman, a run log that cannot be
written, Ctrl-C/SIGTERM) ends in
:func:`~bioscara_gym.hardware.safety.safe_stop`. Exit codes: 0 done, 2 refused (nothing
sent to the arm), 3 safety stop, 130/143 SIGINT/SIGTERM, 1 unexpected error;
in every case each joint is sent its disable (currents 0) whatever its flags
say, and one it could not reach or whose disable was not acknowledged is
named (``j2: no answer, still powered as far as we know: cut the power``):
the flags are no proof, since the firmware's deadman sets NOT_ENABLED and
keeps the currents. The run log is JSON Lines, one line
written and flushed per record, so it is complete after Ctrl-C:

=============  ======================================================================
``type``       fields
=============  ======================================================================
``header``     policy, env_id, backend, rate_hz, control_mode, faults, i2c_clock_hz, seed,
               episodes, realtime, started
``phase``      phase, detail, t (backend clock, s)
``cycle``      cycle, episode, step, t, period_s (backend clock), wall_period_s, work_s
               (host time for policy + step), silence_s (longest joint silence), overrun,
               action (policy output), clamped, commands / q / qd / flags (per joint), reward,
               bus (only when the cycle had any: per joint, retries and errors by kind that
               the driver recovered from or not); the cycle a safety stop cut short: action,
               flags, bus, ``stopped: true``
``bus``        phase (configure, activate, home, reset with its episode, deactivate, cleanup,
               safe stop, shutdown), joints: that phase's retries and errors; with the
               cycle records' they add up to the summary's totals
``episode``    episode, success, distance, steps, return, stalled
``stop``       reason, message, joint
``summary``    episodes, successes, cycles, period/jitter/overrun statistics, stop_reason,
               message, joint, final_state (per-joint flags after the stop, read from the
               emulator where there is one, with its drive and hold currents), arm_disabled
               (every joint's own disable acknowledged), not_confirmed_disabled,
               not_confirmed_warnings (one line per such joint: why, and to cut the power),
               bus (per joint: transactions, retries, errors by kind ``bus`` / ``malformed``
               / ``implausible``, as ``bioscara status`` counts them), gripper (width_m,
               state_file, saved_width_m: what was written, ``null`` if nothing), log_error,
               log_records_lost, exit_code
=============  ======================================================================

A record that cannot be written (disk full) stops the run like any safety
stop (exit 3, arm disabled); what of it reached the disk is cut off again, so
every line stays a whole JSON record; the stop and summary records are then
written if the disk lets them, and the printed summary names the records
that are missing. A log that cannot be opened or take its header refuses the run.

On ``mock`` and ``emulated`` time is simulated: ``period_s`` is simulated and
the loop runs as fast as the host can unless ``--realtime`` paces it on the
wall clock; on ``i2c`` the backend waits on a fixed schedule.

Only ``--model`` imports torch and stable-baselines3, only ``--onnx``
onnxruntime; nothing here imports MuJoCo (the ``emulated`` backend does).
"""

from __future__ import annotations

import argparse
import dataclasses
import inspect
import math
import time
import warnings
from collections.abc import Callable
from dataclasses import dataclass, field
from pathlib import Path
from typing import Any, Protocol

import gymnasium as gym
import numpy as np
from gymnasium.envs.registration import load_env_creator
from rich.console import Console
from rich.markup import escape
from rich.table import Table

from bioscara_gym.errors import DeployError, MetadataError, TrainingError
from bioscara_gym.hardware.arm import Arm, Lifecycle, check_control_freq
from bioscara_gym.hardware.config import load_config
from bioscara_gym.hardware.emulated_bus import FaultPlan
from bioscara_gym.hardware.errors import CommError, JointError, SafetyStop, SitlError, StopReason
from bioscara_gym.hardware.gripper import BaseGripper
from bioscara_gym.hardware.joint import Joint
from bioscara_gym.hardware.safety import DeadmanGuard, SafeStopReport, final_state, safe_stop
from bioscara_gym.tasks import task_of
from bioscara_gym.training.deploy_log import BusStats, LoopStats, RunLog
from bioscara_gym.training.deploy_safety import CycleCheck, SafetyLayer
from bioscara_gym.training.extras import needed_by
from bioscara_gym.training.metadata import (
    PolicyShapes,
    check_metadata,
    check_policy_shapes,
    read_metadata,
    resolve_env_id,
)
from bioscara_gym.training.signals import Interrupted, SignalGuard

#: Backends deploy drives (``sim`` has no bus: use ``bioscara eval``); ``sitl`` runs the
#: firmware's own source behind the emulated bus (``--firmware DIR``).
DEPLOY_BACKENDS = ("i2c", "emulated", "sitl", "mock")
#: Overrun warnings printed before they are only counted.
OVERRUN_WARNINGS = 5
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
        backend: ``i2c`` (the arm), ``emulated`` (real driver, emulated bus), ``sitl``
            (the same with the joint firmware's own source behind the bus) or ``mock``.
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
        record: Bus trace: every I2C transaction as a JSON line (docs/traces.md).
        firmware: The joint firmware's folder for ``sitl`` (``Arduino/joint/``);
            default ``$BIOSCARA_FIRMWARE``.
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
    record: Path | None = None
    firmware: Path | None = None


@dataclass
class Outcome:
    """How a run ended: what the summary and the exit code say.

    Attributes:
        reason: Why it ended.
        message: One line for the operator.
        joint: The joint concerned, if one is.
        exit_code: The CLI's exit code.
        stop_report: What the safe stop did (``None`` if the run completed).
    """

    reason: StopReason = StopReason.COMPLETED
    message: str = "completed"
    joint: str | None = None
    exit_code: int = 0
    stop_report: SafeStopReport | None = None


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


# ------------------------------------------------------------------ policies
def _describe_env(env: gym.Env) -> str:
    u = env.unwrapped
    return f"{_env_id(env)} ({u.control_mode}, {u.control_freq:g} Hz)"


def _env_id(env: gym.Env) -> str:
    """The registered id of ``env`` (the unwrapped env's spec: no deep copy of the kwargs)."""
    spec = env.unwrapped.spec
    return spec.id if spec is not None else type(env.unwrapped).__name__


@dataclass(frozen=True)
class LoadedPolicy:
    """A policy ready to be given its env.

    Attributes:
        make: Builds the policy for the env (the scripted expert needs it).
        metadata: What the policy was trained for (``None`` for the expert).
        description: One line for the operator.
        shapes: What the policy itself takes and gives (``None`` for the expert).
    """

    make: Callable[[gym.Env], Policy]
    metadata: dict[str, Any] | None
    description: str
    shapes: PolicyShapes | None = None


def load_policy(args: DeployArgs) -> LoadedPolicy:
    """Load the policy the arguments name.

    Only ``--model`` imports torch and stable-baselines3, only ``--onnx`` onnxruntime.

    Raises:
        DeployError: No policy source, or more than one; ``--expert`` without ``--env``.
        MetadataError: Missing, incomplete or unreadable metadata.
        PolicyFileError: A ``model.zip`` that cannot be loaded.
        ExportError: An ONNX file that cannot be loaded.
        MissingExtraError: The extra the policy source needs is not installed.
    """
    sources = [s for s in (args.model is not None, args.onnx is not None, args.expert) if s]
    if len(sources) != 1:
        raise DeployError("deploy needs exactly one of --model PATH, --onnx FILE or --expert --env ID")
    if args.expert:
        if args.env is None:
            raise DeployError("--expert needs --env ID: the task is never guessed")
        return LoadedPolicy(lambda env: task_of(env).make_expert(env.unwrapped), None, "scripted expert")
    if args.onnx is not None:
        from bioscara_gym.training.export import OnnxPolicy

        onnx_policy = OnnxPolicy(args.onnx)
        return LoadedPolicy(
            lambda env: onnx_policy, onnx_policy.metadata, f"ONNX {args.onnx}", onnx_policy.shapes
        )
    read_metadata(Path(args.model))  # a missing metadata.json is refused before torch loads
    with needed_by("deploy --model"):
        from bioscara_gym.training.algos import load_model, sb3_policy

    # What the policy was trained for is proven by its own copy, not by an editable file.
    model, metadata = load_model(Path(args.model), require_embedded=True)
    sb3 = sb3_policy(model)
    shapes = PolicyShapes.of_spaces(model.observation_space, model.action_space, f"model {args.model}")
    return LoadedPolicy(lambda env: sb3, metadata, f"{metadata['algo'].upper()} {args.model}", shapes)


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
        _check_args(args)
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
        self.state_file = args.state_file
        if self.state_file is None and args.backend != "i2c":
            self.state_file = self.log_path.parent / "gripper.json"
        _check_outputs({"--log": self.log_path, "--state-file": self.state_file, "--record": args.record})
        self._t0 = time.perf_counter()
        self._gripper_width: float | None = None
        self._early_phases: list[dict[str, Any]] = []
        self._log: RunLog | None = None
        self._signals = SignalGuard()
        self._guard: DeadmanGuard | None = None
        self._stats: LoopStats | None = None
        self._bus: BusStats | None = None
        self._counts = {"episodes": 0, "successes": 0, "cycles": 0}

    # --------------------------------------------------------------- output
    def _phase(self, name: str, detail: str) -> None:
        """Print a phase; log it (phases before the log opens are logged when it does)."""
        self.console.print(f"[bold]{name:<10}[/bold] {escape(detail)}")
        t = self.env.unwrapped.arm.backend.clock.now() if self.env is not None else None
        record = {"type": "phase", "phase": name, "detail": detail, "t": t}
        if self._log is None:
            self._early_phases.append(record)
        else:
            self._log.write(record)
            self._log_bus(name)

    def _log_bus(self, phase: str, **where: Any) -> None:
        """A ``bus`` record of the retries and errors since the last record that took them, if any.

        Cycle records take their cycle's; this takes a phase's (configure,
        activate, home, an episode's reset, deactivate, cleanup, the safe
        stop, shutdown), so the records add up to the summary's totals.
        """
        if self._bus is None or self._log is None:
            return
        changes = self._bus.cycle()
        if changes:
            self._log.write({"type": "bus", "phase": phase, **where, "joints": changes})

    def _starting(self, name: str, detail: str) -> None:
        """Print that a phase starts (a failure in it is printed right after)."""
        self.console.print(f"[bold]{name:<10}[/bold] {escape(detail)} ...")

    # ------------------------------------------------------------------- run
    def run(self) -> dict[str, Any]:
        """Check, bring up, run, shut down. Returns the summary.

        Raises:
            DeployError: Refused (code 2), or stopped by the safety layer
                (code 3); the arm is safe and the summary is attached.
            Interrupted: SIGINT/SIGTERM; the arm is safe, ``self.summary`` is set.
        """
        loaded = self._load_policy()
        env = self.env = self._make_env(loaded.metadata)
        with warnings.catch_warnings():
            warnings.showwarning = self._show_warning  # one line each, with the phases
            try:
                target = f"{_describe_env(env)} on {self.args.backend}"
                self.console.print(f"[bold]deploy[/bold]     {escape(loaded.description)} -> {target}")
                self._check(env, loaded)
                return self._run(env, loaded.make(env), loaded.description)
            finally:
                env.close()

    def _show_warning(self, message: Warning | str, *args: Any, **kwargs: Any) -> None:
        """Print a warning (e.g. the gripper's state file) as one line among the phases."""
        self.console.print(f"[yellow]warning[/yellow]: {escape(str(message))}")

    def _load_policy(self) -> LoadedPolicy:
        """Load the policy: the one given to the constructor, else the one the arguments name."""
        if self._policy_override is None:
            return load_policy(self.args)
        given, metadata = self._policy_override, self._metadata_override
        if metadata is None and self.args.env is None:
            raise DeployError("a policy without metadata needs --env ID: the task is never guessed")
        return LoadedPolicy(lambda env: given, metadata, "given policy")

    def _check(self, env: gym.Env, loaded: LoadedPolicy) -> None:
        """Refuse a policy trained for another env, or one that does not fit it, before anything is sent."""
        if loaded.metadata is None:
            self._phase("check", "no metadata to check (scripted policy)")
            return
        try:
            check_metadata(loaded.metadata, env, _env_id(env))
            if loaded.shapes is not None:
                check_policy_shapes(loaded.shapes, env)
        except MetadataError as e:
            raise DeployError(f"refused: {e}; nothing was sent to the arm") from e
        _probe_policy(loaded, env, self.args.seed)
        checked = "metadata and own inputs and outputs match" if loaded.shapes else "metadata matches"
        self._phase("check", f"policy {checked} the env, and acts finitely; nothing sent to the arm yet")

    def _make_env(self, metadata: dict[str, Any] | None) -> gym.Env:
        """Build the policy's env (or ``--env``'s) on the chosen backend; nothing is sent yet."""
        args = self.args
        kwargs: dict[str, Any] = dict(metadata["env_kwargs"]) if metadata else {}
        # With a policy the metadata names the env (--env, if given, must agree: _check);
        # the expert has --env (load_policy).
        try:
            env_id = resolve_env_id(args.env if args.env is not None else metadata["env_id"])
        except TrainingError as e:
            raise DeployError(str(e)) from e
        _check_env_kwargs(env_id, kwargs)
        config = load_config(args.config)
        if args.bus is not None:
            config = dataclasses.replace(config, bus=args.bus)
        kwargs.update(backend=args.backend, backend_options=self._backend_options(), config=config)
        kwargs["render_mode"] = None
        if args.rate is not None:
            kwargs["control_freq"] = float(args.rate)
        try:
            return gym.make(env_id, **kwargs)
        except (gym.error.Error, ValueError, TypeError, SitlError) as e:
            raise DeployError(f"cannot make env {env_id!r}: {e}") from e

    def _backend_options(self) -> dict[str, Any]:
        """The backend's options: the gripper state file and the emulated bus's faults."""
        args = self.args
        options: dict[str, Any] = {}
        if self.state_file is not None:
            options["state_file"] = self.state_file
        if args.faults:
            options["faults"] = FaultPlan.parse(args.faults)  # checked in _check_args
        if args.record is not None:  # every bus transaction to a trace (docs/traces.md)
            from bioscara_gym.hardware.recording import Recording

            options["record"] = Recording(args.record, "deploy", args)
        if args.backend == "sitl":
            options["firmware"] = args.firmware  # None: $BIOSCARA_FIRMWARE
        return options

    def _run(self, env: gym.Env, policy: Policy, description: str) -> dict[str, Any]:
        """Bring up, run and shut down; every way out makes the arm safe first."""
        arm = env.unwrapped.arm
        try:
            self._log = RunLog(self.log_path)
        except OSError as e:
            raise DeployError(
                f"cannot open the run log {self.log_path}: {e.strerror or e}; nothing was sent to the arm"
            ) from e
        self._stats = LoopStats(nominal_s=env.unwrapped.dt)
        self._bus = BusStats(arm.backend.comm_stats())
        outcome = Outcome()
        try:
            try:
                self._write_header(env, description)
            except SafetyStop as e:  # the log cannot be written: refuse before the arm is touched
                raise DeployError(f"refused: {e}; nothing was sent to the arm") from e
            with self._signals:
                try:
                    self._bring_up(env)
                    self._episodes(env, policy)
                    self._shut_down(arm)
                except BaseException as e:
                    outcome = self._stop_safely(e, arm)
                    if not isinstance(e, Exception | KeyboardInterrupt):
                        raise
                finally:
                    with self._signals.shielded():
                        self._finish(env, outcome)
        finally:
            self._log.close()
        return self._report(outcome)

    def _write_header(self, env: gym.Env, description: str) -> None:
        """Open the log with the run's header and the phases printed before it."""
        u = env.unwrapped
        args = self.args
        self._log.write(
            {
                "type": "header",
                "policy": description,
                "env_id": _env_id(env),
                "backend": args.backend,
                "rate_hz": u.control_freq,
                "control_mode": u.control_mode,
                "faults": args.faults,
                "i2c_clock_hz": u.config.i2c_clock_hz,
                "seed": args.seed,
                "episodes": args.episodes,
                "realtime": args.realtime,
                "started": time.strftime("%Y-%m-%dT%H:%M:%S%z"),
            }
        )
        for record in self._early_phases:
            self._log.write(record)

    # ---------------------------------------------------------------- bring up
    def _bring_up(self, env: gym.Env) -> None:
        """Configure, activate and home the arm phase by phase, then claim the control mode."""
        u = env.unwrapped
        arm: Arm = u.arm
        self._configure(arm)
        homed_before = [n for n in arm.names if arm.joint_states[n].homed]
        self._starting("activate", "enabling joints, stall detection and limits")
        arm.activate()
        self._phase("activate", "joints enabled, stall detection and limits set")
        self._home(arm, [n for n in arm.names if n not in homed_before], homed_before)
        u.bring_up()  # configured, active and homed: only the command mode's claim is left

    def _configure(self, arm: Arm) -> None:
        """Connect and ping every joint."""
        addressed = ", ".join(
            f"{n} {j.address:#04x}" if isinstance(j, Joint) else n for n, j in arm.joints.items()
        )
        self._starting("configure", f"connecting and pinging {addressed}")
        arm.configure()
        self._phase("configure", "every joint answered")

    def _home(self, arm: Arm, todo: list[str], homed_before: list[str]) -> None:
        """Home the joints in ``todo``; those homed before keep the offset read on configure."""
        if homed_before:
            self._phase("home", f"{', '.join(homed_before)} homed before: offset restored from HOMEOFFSET")
        if todo:
            clock = arm.backend.clock
            t0 = clock.now()
            self._starting("home", f"homing {', '.join(todo)}")
            arm.home(todo)
            self._phase("home", f"{', '.join(todo)} homed in {clock.now() - t0:.1f} s")

    # -------------------------------------------------------------- episodes
    def _episodes(self, env: gym.Env, policy: Policy) -> None:
        """Run every episode behind the safety layer."""
        self._guard = DeadmanGuard(env.unwrapped.arm.backend)
        safety = SafetyLayer(env, self._guard)
        self._phase(
            "run",
            f"{self.args.episodes} episode(s) at {env.unwrapped.control_freq:g} Hz, log {self.log_path}",
        )
        for ep in range(self.args.episodes):
            self._run_episode(env, policy, safety, ep)

    def _run_episode(self, env: gym.Env, policy: Policy, safety: SafetyLayer, ep: int) -> None:
        """Reset, then one cycle after another until the episode ends."""
        obs, info = env.reset(seed=self.args.seed + ep)
        self._log_bus("reset", episode=ep)
        if hasattr(policy, "reset"):
            policy.reset()
        self._guard.restart()
        clock = EpisodeClock()
        total, steps, done = 0.0, 0, False
        while not done:
            with self._signals.deferred():
                self._signals.check()
                obs, reward, terminated, truncated, info = self._cycle(
                    env, policy, safety, clock, ep, steps, obs
                )
                total += float(reward)
                steps += 1
                if self.args.realtime:
                    clock.pace(env.unwrapped.dt)
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
            self.on_cycle(self._counts["cycles"], env)
        arm = env.unwrapped.arm
        t_clock = arm.backend.clock.now()
        t_wall, period, wall_period = clock.tick(t_clock)
        raw = _act(policy, obs)
        where = {"cycle": self._counts["cycles"], "episode": ep, "step": step, "t": t_clock}
        try:
            result, check = safety.step(raw)
        except SafetyStop:
            flags = {n: int(arm.joint_states[n].flags) for n in env.unwrapped.joint_names}
            record = {"type": "cycle", **where, "action": _floats(raw), "flags": flags, "stopped": True}
            self._log.write({**record, **self._bus_record()})
            raise
        timing = self._account_cycle(env, period, wall_period, time.perf_counter() - t_wall, check)
        state = self._cycle_state(env, raw, check)
        self._log.write(
            {"type": "cycle", **where, **timing, **state, "reward": result[1], **self._bus_record()}
        )
        self._counts["cycles"] += 1
        return result

    def _bus_record(self) -> dict[str, Any]:
        """``{"bus": ...}`` with the cycle's retries and errors per joint, or nothing if it had none."""
        changes = self._bus.cycle()
        return {"bus": changes} if changes else {}

    def _account_cycle(
        self, env: gym.Env, period: float | None, wall_period: float | None, work: float, check: CycleCheck
    ) -> dict[str, Any]:
        """Add a cycle's timing to the statistics, warn on an overrun; the cycle record's timing."""
        paced_wall = self.args.realtime or self.args.backend == "i2c"
        overrun = self._stats.add(period, wall_period, work, check.silence_s, paced_wall)
        if overrun:
            self._warn_overrun(env.unwrapped.dt, wall_period if paced_wall else period)
        return {
            "period_s": period,
            "wall_period_s": wall_period,
            "work_s": work,
            "silence_s": check.silence_s,
            "overrun": overrun,
        }

    @staticmethod
    def _cycle_state(env: gym.Env, raw: Any, check: CycleCheck) -> dict[str, Any]:
        """The cycle record's action, commands and per-joint state."""
        arm = env.unwrapped.arm
        names = env.unwrapped.joint_names
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
        overruns = self._stats.overruns
        if overruns > OVERRUN_WARNINGS:
            return
        more = " (further overruns are only counted)" if overruns == OVERRUN_WARNINGS else ""
        self.console.print(
            f"[yellow]warning[/yellow]: overrun at cycle {self._counts['cycles']}: period "
            f"{(period or 0.0) * 1000:.1f} ms > {dt * 1000:.0f} ms{more}"
        )

    def _end_episode(self, ep: int, info: dict[str, Any], steps: int, total: float) -> None:
        """Count, log and print the episode's result."""
        success = bool(info.get("is_success", False))
        self._counts["episodes"] += 1
        self._counts["successes"] += success
        self._log.write(
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

    # ------------------------------------------------------------- shut down
    def _shut_down(self, arm: Arm) -> None:
        """Deactivate (gripper width saved) and clean up, signals held off."""
        with self._signals.shielded():
            arm.deactivate()
            self._gripper_width = arm.gripper.get_position()
            saved = _gripper_saved(arm.gripper)
            self._phase("deactivate", f"joints disabled, gripper width {self._gripper_width:.3f} m {saved}")
            arm.cleanup()
            self._phase("cleanup", "joints and gripper disconnected")

    def _stop_safely(self, e: BaseException, arm: Arm) -> Outcome:
        """Make the arm safe after ``e``, then say why it stopped."""
        with self._signals.shielded():
            outcome = _classify(e)
            outcome.stop_report = safe_stop(arm)  # the arm first, then the words
            self._log_bus("safe stop")
            self._gripper_width = outcome.stop_report.gripper_width_m
            self.console.print(f"[bold red]{'safe stop':<10}[/bold red] {escape(outcome.message)}")
            self._log.write(
                {
                    "type": "stop",
                    "reason": outcome.reason.value,
                    "message": outcome.message,
                    "joint": outcome.joint,
                }
            )
        return outcome

    def _finish(self, env: gym.Env, outcome: Outcome) -> None:
        """Stop watching the joints, shut the arm down if still up, log the summary."""
        arm = env.unwrapped.arm
        if self._guard is not None:
            self._guard.detach()
        if arm.state is not Lifecycle.FINALIZED:
            arm.shutdown()
        self._log_bus("shutdown")
        self.summary = self._summarise(env, outcome)
        self._log.write({"type": "summary", **self.summary})

    # --------------------------------------------------------------- summary
    def _summarise(self, env: gym.Env, outcome: Outcome) -> dict[str, Any]:
        """The summary record: counts, timing, why it stopped, the arm's final state."""
        arm = env.unwrapped.arm
        state = final_state(arm.backend)
        counts, report = self._counts, outcome.stop_report
        return {
            **counts,
            "success_rate": counts["successes"] / counts["episodes"] if counts["episodes"] else None,
            **self._stats.summary(),
            "bus": self._bus.summary(),
            "stop_reason": outcome.reason.value,
            "message": outcome.message,
            "joint": outcome.joint,
            "final_state": state,
            # Safe only where the joint's own disable was acknowledged: the flags are no
            # proof (a deadman trip sets NOT_ENABLED and keeps the currents). A completed
            # run got here through deactivate(), which raises unless every disable went through.
            "arm_disabled": not report.not_confirmed if report else True,
            "arm_state": arm.state.value,
            "problems": report.problems if report else [],
            "not_confirmed_disabled": report.not_confirmed if report else [],
            "not_confirmed_warnings": report.warnings() if report else [],
            "gripper": {
                "width_m": self._gripper_width,
                "state_file": str(arm.gripper.state_file) if arm.gripper.state_file else None,
                "saved_width_m": arm.gripper.saved_width_m,
            },
            "log_error": None if self._log.error is None else str(self._log.error),
            "log_records_lost": list(self._log.lost),
            "exit_code": outcome.exit_code,
            "wall_time_s": time.perf_counter() - self._t0,
        }

    def _report(self, outcome: Outcome) -> dict[str, Any]:
        """Print the summary; return it, or raise what the exit code needs."""
        self._print_summary()
        if outcome.reason is StopReason.COMPLETED:
            return self.summary
        self.console.print(self._disabled_line())
        if outcome.reason in (StopReason.INTERRUPTED, StopReason.TERMINATED):
            raise Interrupted(outcome.exit_code - 128)
        raise DeployError(f"safe stop: {outcome.message}", outcome.exit_code, self.summary)

    def _disabled_line(self) -> str:
        """Which joints acknowledged their disable, and each one that did not, named."""
        s = self.summary
        names = list(s["final_state"])
        if s["arm_disabled"]:
            return (
                f"arm disabled: {', '.join(names)} acknowledged their disable (currents 0); "
                "arm shut down, bus closed"
            )
        confirmed = [n for n in names if n not in s["not_confirmed_disabled"]]
        lines = "; ".join(s["not_confirmed_warnings"])
        done = f"confirmed disabled: {', '.join(confirmed)}" if confirmed else "no joint confirmed disabled"
        done = f"; {done}"
        return f"[red]arm NOT confirmed disabled[/red]: {escape(lines)}{done}"

    def _print_summary(self) -> None:
        """The summary as a table, and where the log is."""
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
        for name, bus in s["bus"].items():
            errors = ", ".join(f"{k} {v}" for k, v in bus["errors"].items())
            table.add_row(
                f"bus {name}: transactions / retries / errors",
                f"{bus['transactions']} / {bus['retries']} / {errors}",
            )
        table.add_row("stop", escape(s["message"]))
        flags = ", ".join(f"{n} {st['flag_names']}" for n, st in s["final_state"].items())
        table.add_row("final flags", flags)
        self.console.print(table)
        self.console.print(f"log        {self.log_path}", markup=False)
        if self._log.error is not None:
            lost = f": {', '.join(self._log.lost)}" if self._log.lost else ""
            self.console.print(
                f"log incomplete: {self._log.dropped} record(s) not written{lost} "
                f"({self._log.error.strerror or self._log.error}); every line in it is a whole record",
                markup=False,
            )


def _probe_policy(loaded: LoadedPolicy, env: gym.Env, seed: int) -> None:
    """Run the policy once on an observation of the env's space, before the arm is touched.

    The env's first real observation needs the arm homed, so the probe is an
    observation drawn from the env's observation space with the run's seed: a
    policy whose own numbers are broken (a NaN weight) gives NaN or infinity,
    or fails inside its library, for any input.

    Raises:
        DeployError: One line naming the policy and what it gave.
    """
    space = env.observation_space
    space.seed(seed)
    probe = space.sample()
    try:
        action = np.asarray(loaded.make(env)(probe), dtype=np.float64)
    except Exception as e:  # torch's distribution checks, onnxruntime: one line, not their traceback
        raise DeployError(
            f"refused: {loaded.description} fails on a probe observation ({type(e).__name__}: "
            f"{_first_line(e)}); are its weights NaN or infinite? nothing was sent to the arm"
        ) from e
    if not np.all(np.isfinite(action)):
        raise DeployError(
            f"refused: {loaded.description} gives a non-finite action "
            f"{np.array2string(action, precision=3, separator=', ')} on a probe observation; "
            "nothing was sent to the arm"
        )


def _first_line(e: BaseException) -> str:
    """The first line of an exception's message (torch's span several)."""
    text = str(e).strip()
    return text.splitlines()[0] if text else "no message"


def _check_env_kwargs(env_id: str, kwargs: dict[str, Any]) -> None:
    """Refuse a policy's env kwargs that the env does not take, naming them.

    Raises:
        DeployError: Unknown env id, or a kwarg the env's constructor lacks.
    """
    try:
        spec = gym.spec(env_id)
    except gym.error.Error as e:
        raise DeployError(f"cannot make env {env_id!r}: {e}") from e
    creator = load_env_creator(spec.entry_point) if isinstance(spec.entry_point, str) else spec.entry_point
    known = _keyword_parameters(creator)
    unknown = [k for k in kwargs if k not in known]
    if unknown:
        settings = ", ".join(n for n in known if n not in ("backend", "backend_options", "config"))
        raise DeployError(
            f"the policy's env_kwargs has {unknown[0]!r}, which {env_id} does not take; it takes {settings}"
        )


def _keyword_parameters(creator: Any) -> list[str]:
    """The keyword parameters an env class takes, following ``**kwargs`` up its bases."""
    classes = creator.__mro__ if isinstance(creator, type) else (creator,)
    names: list[str] = []
    for cls in classes:
        target = cls.__init__ if isinstance(creator, type) else cls
        if isinstance(creator, type) and "__init__" not in vars(cls):
            continue
        params = inspect.signature(target).parameters.values()
        names += [p.name for p in params if p.kind in (p.POSITIONAL_OR_KEYWORD, p.KEYWORD_ONLY)]
        if not any(p.kind is p.VAR_KEYWORD for p in params):
            break
    return [n for n in dict.fromkeys(names) if n != "self"]


def _check_outputs(outputs: dict[str, Path | None]) -> None:
    """Refuse output files that are one and the same, or that cannot be files.

    The run log, the gripper state file (``None``: the backend's, on the arm)
    and the bus trace are written side by side: one path for two of them
    would leave neither readable.

    Raises:
        DeployError: Two options name one file, or one names a directory, a
            device or a FIFO, or a path under something that is not a directory.
    """
    seen: dict[Path, str] = {}
    for option, path in outputs.items():
        if path is None:
            continue
        resolved = Path(path).resolve()
        if resolved in seen:
            raise DeployError(f"{seen[resolved]} and {option} name the same file {path}; each needs its own")
        seen[resolved] = option
        if resolved.exists() and not resolved.is_file():
            raise DeployError(f"{option} {path} is not a regular file")
        parent = next((p for p in resolved.parents if p.exists()), None)
        if parent is not None and not parent.is_dir():
            raise DeployError(f"{option} {path}: {parent} is not a directory")


def _check_args(args: DeployArgs) -> None:
    """Refuse a bad argument before anything is built or sent.

    Raises:
        DeployError: One line naming the argument and what was expected.
    """
    if args.backend not in DEPLOY_BACKENDS:
        raise DeployError(
            f"backend {args.backend!r} is not deployable; expected one of {', '.join(DEPLOY_BACKENDS)}"
        )
    if args.episodes < 1:
        raise DeployError(f"--episodes must be >= 1, got {args.episodes}")
    if args.seed < 0:
        raise DeployError(f"--seed must be >= 0, got {args.seed}")
    if args.bus is not None and args.bus < 0:
        raise DeployError(f"--bus must be an I2C bus number >= 0 (/dev/i2c-N), got {args.bus}")
    if args.rate is not None:
        try:
            check_control_freq(args.rate, "--rate")
        except ValueError as e:
            raise DeployError(str(e)) from e
    if args.firmware is not None and args.backend != "sitl":
        raise DeployError("--firmware needs --backend sitl (the firmware in the loop)")
    if args.faults:
        if args.backend not in ("emulated", "sitl"):
            raise DeployError(
                "--faults needs --backend emulated or sitl (faults are injected by the emulated bus)"
            )
        try:
            FaultPlan.parse(args.faults)
        except ValueError as e:
            raise DeployError(f"--faults: {e}") from e


def _gripper_saved(gripper: BaseGripper) -> str:
    """Whether the gripper's width was written to its state file, in words."""
    path = gripper.state_file
    if path is None:
        return "not kept (no state file)"
    if gripper.save_error is not None:
        return f"NOT saved to {path}: {gripper.save_error.strerror or gripper.save_error}"
    if gripper.saved_width_m is None:
        return f"not saved (the gripper was not enabled; {path} unchanged)"
    return f"saved to {path}"


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
            StopReason.NAN_ACTION, f"the policy failed to act ({type(e).__name__}: {_first_line(e)})"
        ) from e


def _floats(action: Any) -> np.ndarray:
    """The policy's raw action as float64, for the log."""
    return np.asarray(action, dtype=np.float64)


def _classify(e: BaseException) -> Outcome:
    """Why the run stopped, from the exception that stopped it."""
    if isinstance(e, SafetyStop):
        return Outcome(e.reason, str(e), e.joint, EXIT_SAFETY_STOP)
    if isinstance(e, Interrupted):
        return Outcome(e.reason, f"{e} received", None, e.exit_code)
    if isinstance(e, KeyboardInterrupt):
        return Outcome(StopReason.INTERRUPTED, "SIGINT received", None, 130)
    if isinstance(e, CommError):
        return Outcome(StopReason.COMM_ERROR, f"communication error: {e}", e.joint, EXIT_SAFETY_STOP)
    if isinstance(e, JointError):
        return Outcome(StopReason.JOINT_ERROR, f"joint error: {e}", e.joint, EXIT_SAFETY_STOP)
    return Outcome(StopReason.ERROR, f"{type(e).__name__}: {e}", None, 1)


# ----------------------------------------------------------------------- CLI
def _args_from_namespace(ns: argparse.Namespace) -> DeployArgs:
    return DeployArgs(**{f.name: getattr(ns, f.name) for f in dataclasses.fields(DeployArgs)})


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


def register(sub: argparse._SubParsersAction) -> None:
    """Add the ``deploy`` subcommand (and, until cli.py registers it, ``export``)."""
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
    p.add_argument(
        "--firmware",
        type=Path,
        metavar="DIR",
        help="joint firmware source for --backend sitl (Arduino/joint/; default $BIOSCARA_FIRMWARE)",
    )
    p.add_argument("--bus", type=int, help="I2C bus number, /dev/i2c-N (default: the config's)")
    p.add_argument("--config", type=Path, help="arm configuration YAML (default: the packaged one)")
    p.add_argument("--episodes", type=int, default=1)
    p.add_argument(
        "--rate",
        type=float,
        help="control rate in Hz (default: the policy's; a trained policy refuses another)",
    )
    p.add_argument("--log", type=Path, help="run log, JSON Lines (default: runs/deploy/deploy-<time>.jsonl)")
    p.add_argument(
        "--faults",
        help="emulated bus faults: nack, short_read, corrupt (rates per transaction), latency_ms, "
        "jitter_ms (extra time per transaction), drift_ppm (host clock), e.g. latency_ms=2,jitter_ms=3",
    )
    p.add_argument("--seed", type=int, default=10_000, help="seed of the first episode")
    p.add_argument("--realtime", action="store_true", help="pace mock/emulated on the wall clock too")
    p.add_argument("--state-file", type=Path, help="gripper state file")
    p.add_argument("--record", type=Path, metavar="FILE", help="bus trace to write (docs/traces.md)")
    p.set_defaults(func=cmd_deploy)
