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

Before step 2, every argument is checked, and the files the run writes
(:mod:`~bioscara_gym.training.deploy_outputs`: the run log, the gripper
state file, the bus trace; each may replace only a file of its own kind, and
the gripper's defaults to ``gripper.json`` beside the log on simulated
backends); the bus trace is started only once the policy has passed. A
policy is checked twice:
its metadata must state the task, the control mode and rate and the spaces
(nothing is defaulted), and the policy's own inputs and outputs (the SB3
model's spaces, the ONNX graph's input and output widths) must fit the env
the metadata builds. A refusal is one line and nothing is sent to the arm.

Any stop (NaN action, stall, bus error, deadman, a run log that cannot be
written, Ctrl-C/SIGTERM/SIGHUP) ends in :func:`~bioscara_gym.hardware.safety.safe_stop`.
Exit codes: 0 done, 2 refused (nothing sent to the arm), 3 safety stop,
130/143/129 SIGINT/SIGTERM/SIGHUP (a ``--record`` trace says where), 1 unexpected error;
each joint is sent its disable (currents 0) whatever its flags say, and one
not reached or whose disable was not acknowledged is named (``j2: no answer,
still powered as far as we know: cut the power``): the firmware's deadman
sets NOT_ENABLED and keeps the currents. The run log is JSON Lines, one line
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
               log_records_lost, trace_error, exit_code
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
import time
import warnings
from collections.abc import Callable
from pathlib import Path
from typing import Any

import gymnasium as gym
from rich.console import Console
from rich.markup import escape

from bioscara_gym.errors import DeployError, MetadataError, one_line
from bioscara_gym.training.deploy_checks import (
    DEPLOY_BACKENDS,
    DeployArgs,
    LoadedPolicy,
    Policy,
    check_args,
    check_files,
    check_input_order,
    load_policy,
    make_env,
    probe_policy,
)
from bioscara_gym.training.deploy_log import (
    BusStats,
    CycleTiming,
    RunLog,
    disabled_line,
    note_signal,
    print_summary,
    trace_error,
)
from bioscara_gym.training.deploy_loop import ControlLoop, Target
from bioscara_gym.training.deploy_parser import EPILOG, add_options
from bioscara_gym.training.deploy_safety import (
    EXIT_REFUSED,
    EXIT_SAFETY_STOP,
    SIGNAL_REASONS,
    Outcome,
    SafetyStop,
    StopReason,
    outcome_for,
)
from bioscara_gym.training.metadata import check_metadata, check_policy_shapes
from bioscara_gym.training.signals import Interrupted, SignalGuard

__all__ = [
    "DEPLOY_BACKENDS",
    "EXIT_REFUSED",
    "EXIT_SAFETY_STOP",
    "DeployArgs",
    "Deployment",
    "LoadedPolicy",
    "RunLog",
    "cmd_deploy",
    "load_policy",
    "register",
]

#: Overrun warnings printed before they are only counted.
OVERRUN_WARNINGS = 5


# ---------------------------------------------------------------- deployment
class Deployment:
    """One ``bioscara deploy`` run (see the module docstring).

    The env it builds is the one owner of the arm: deploy asks it to bring
    the arm up (:meth:`Target.bring_up`, each phase printed and logged
    through :meth:`starting` and :meth:`done`), to step, and to shut the
    arm down or stop it safely; everything else it reads from the arm's
    public API.

    Args:
        args: The run's arguments.
        policy: A policy to run instead of the one ``args`` names (tests,
            scripted checks); with ``metadata`` it is checked like a trained one.
        metadata: Metadata of ``policy``.
        console: Where phases and warnings are printed.
        on_cycle: Called with ``(cycle, env)`` before each cycle's policy call
            (test hook: inject a fault mid-run).
        backend_options: Options laid over the backend's (``bioscara replay``: its bus).
    """

    def __init__(
        self,
        args: DeployArgs,
        policy: Policy | None = None,
        metadata: dict[str, Any] | None = None,
        console: Console | None = None,
        on_cycle: Callable[[int, gym.Env], None] | None = None,
        backend_options: dict[str, Any] | None = None,
    ) -> None:
        """Validate the arguments; nothing is built or sent yet."""
        check_args(args)
        self.args = args
        self.console = console or Console(highlight=False, soft_wrap=True)
        self.on_cycle = on_cycle
        self._extra_options = dict(backend_options or {})
        self._policy_override = policy
        self._metadata_override = metadata
        self.env: gym.Env | None = None
        self.target: Target | None = None
        self.summary: dict[str, Any] = {}
        self.log_path = (
            Path(args.log) if args.log else Path("runs/deploy") / time.strftime("deploy-%Y%m%d-%H%M%S.jsonl")
        )
        self.state_file = args.state_file
        if self.state_file is None and args.backend != "i2c":
            self.state_file = self.log_path.parent / "gripper.json"
        check_files(args, self.log_path, self.state_file)
        self._t0 = time.perf_counter()
        self._gripper_width: float | None = None
        self._early_phases: list[dict[str, Any]] = []
        self._log: RunLog | None = None
        self._signals = SignalGuard()
        self._loop: ControlLoop | None = None
        self._timing: CycleTiming | None = None
        self._bus: BusStats | None = None

    # --------------------------------------------------------------- output
    def done(self, phase: str, detail: str) -> None:
        """Print a phase; log it (phases before the log opens are logged when it does)."""
        self.console.print(f"[bold]{phase:<10}[/bold] {escape(detail)}")
        t = self.target.arm.clock.now() if self.target is not None else None
        record = {"type": "phase", "phase": phase, "detail": detail, "t": t}
        if self._log is None:
            self._early_phases.append(record)
        else:
            self._log.write(record)
            self.log_bus(phase)

    def starting(self, phase: str, detail: str) -> None:
        """Print that a phase starts (a failure in it is printed right after)."""
        self.console.print(f"[bold]{phase:<10}[/bold] {escape(detail)} ...")

    def log_bus(self, phase: str, **where: Any) -> None:
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

    # ------------------------------------------------------------------- run
    def run(self) -> dict[str, Any]:
        """Check, bring up, run, shut down. Returns the summary.

        Raises:
            DeployError: Refused (code 2), or stopped by the safety layer
                (code 3); the arm is safe and the summary is attached.
            Interrupted: SIGINT/SIGTERM/SIGHUP; the arm is safe, ``self.summary`` is set.
        """
        loaded = self._load_policy()
        self._make_env(loaded, record=False)  # the trace starts only once the policy is checked
        with warnings.catch_warnings():
            warnings.showwarning = self._show_warning  # one line each, with the phases
            try:
                t = self.target
                where = f"{self._env_id()} ({t.control_mode}, {t.control_freq:g} Hz) on {self.args.backend}"
                self.console.print(f"[bold]deploy[/bold]     {escape(loaded.description)} -> {where}")
                self._check(self.env, loaded)
                return self._run(self.env, loaded.make(self.env), loaded.description)
            except KeyboardInterrupt as e:  # also before the run's guard: the trace says where
                note_signal(self.target.arm.backend, e)
                raise
            finally:
                if self.env is not None:  # the env shuts the arm down if it is still up (not by now)
                    self.env.close()

    def _make_env(self, loaded: LoadedPolicy, record: bool) -> None:
        """Make the env (closing one made before), with ``--record``'s trace or without.

        Seen: a policy refused by its check left a trace holding a header only.
        """
        if self.env is not None:
            self.env, old = None, self.env
            old.close()
        args = self.args if record else dataclasses.replace(self.args, record=None)
        self.env = make_env(args, self.state_file, loaded.metadata, self._extra_options)
        self.target = self.env.unwrapped  # the Bioscara env's public API (Target)

    def _env_id(self) -> str:
        """The registered id of the env (its own spec: no deep copy of the kwargs)."""
        spec = self.target.spec if self.target is not None else None
        return spec.id if spec is not None else type(self.target).__name__

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
        """Check the policy on ``env``; once it passes, start ``--record``'s trace (a new env with it)."""
        self._check_policy(env, loaded)
        if self.args.record is not None:
            self._make_env(loaded, record=True)

    def _check_policy(self, env: gym.Env, loaded: LoadedPolicy) -> None:
        """Refuse a policy trained for another env, or one that does not fit it, before anything is sent."""
        if loaded.metadata is None:
            self.done("check", "no metadata to check (scripted policy)")
            return
        try:
            check_metadata(loaded.metadata, env, self._env_id())
            if loaded.shapes is not None:
                check_policy_shapes(loaded.shapes, env)
        except MetadataError as e:
            raise DeployError(f"refused: {e}; nothing was sent to the arm") from e
        check_input_order(loaded, env)
        probe_policy(loaded, env, self.args.seed)
        checked = "metadata and own inputs and outputs match" if loaded.shapes else "metadata matches"
        self.done("check", f"policy {checked} the env, and acts finitely; nothing sent to the arm yet")

    def _run(self, env: gym.Env, policy: Policy, description: str) -> dict[str, Any]:
        """Bring up, run and shut down; every way out makes the arm safe first."""
        target = self.target
        try:
            self._log = RunLog(self.log_path)
        except OSError as e:
            raise DeployError(
                f"cannot open the run log {self.log_path}: {e.strerror or e}; nothing was sent to the arm"
            ) from e
        self._timing = CycleTiming(nominal_s=target.dt)
        self._bus = BusStats(target.arm.comm_stats())
        outcome = Outcome()
        try:
            try:
                self._write_header(description)
            except SafetyStop as e:  # the log cannot be written: refuse before the arm is touched
                raise DeployError(f"refused: {e}; nothing was sent to the arm") from e
            with self._signals:
                try:
                    target.bring_up(self)  # configure, activate, home, each phase through done()
                    self._loop = self._control_loop()
                    self._loop.run(env, policy)
                    self._shut_down()
                except BaseException as e:
                    outcome = self._stop_safely(e)
                    if not isinstance(e, Exception | KeyboardInterrupt):
                        raise
                finally:
                    with self._signals.shielded():
                        self._finish(outcome)
        finally:
            self._log.close()
        return self._report(outcome)

    def _control_loop(self) -> ControlLoop:
        """The run phase's loop over this run's target, log, statistics and signal guard."""
        return ControlLoop(
            self.target,
            self.args,
            self._log,
            self._bus,
            self._timing,
            self._signals,
            self.console,
            tell=self,
            on_cycle=self.on_cycle,
        )

    def _write_header(self, description: str) -> None:
        """Open the log with the run's header and the phases printed before it."""
        t, args = self.target, self.args
        self._log.write(
            {
                "type": "header",
                "policy": description,
                "env_id": self._env_id(),
                "backend": args.backend,
                "rate_hz": t.control_freq,
                "control_mode": t.control_mode,
                "faults": args.faults,
                "i2c_clock_hz": t.config.i2c_clock_hz,
                "seed": args.seed,
                "episodes": args.episodes,
                "realtime": args.realtime,
                "started": time.strftime("%Y-%m-%dT%H:%M:%S%z"),
            }
        )
        for record in self._early_phases:
            self._log.write(record)

    # ------------------------------------------------------------- shut down
    def _shut_down(self) -> None:
        """The env's orderly end (deactivate, gripper width saved, clean up), signals held off."""
        with self._signals.shielded():
            self._gripper_width = self.target.shut_down(self)

    def _stop_safely(self, e: BaseException) -> Outcome:
        """Have the env make the arm safe after ``e``, then say why it stopped."""
        with self._signals.shielded():
            note_signal(self.target.arm.backend, e)  # in the bus trace, before the safe stop's bytes
            outcome = outcome_for(e)
            outcome.stop_report = self.target.safe_stop()  # the arm first, then the words
            self.log_bus("safe stop")
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

    def _finish(self, outcome: Outcome) -> None:
        """Stop watching the joints, log the summary (the env has shut the arm down)."""
        if self._loop is not None and self._loop.guard is not None:
            self._loop.guard.detach()
        self.log_bus("shutdown")
        self.summary = self._summarise(outcome)
        self._log.write({"type": "summary", **self.summary})

    # --------------------------------------------------------------- summary
    def _summarise(self, outcome: Outcome) -> dict[str, Any]:
        """The summary record: counts, timing, why it stopped, the arm's final state."""
        arm = self.target.arm
        counts = dict(self._loop.counts) if self._loop else {"episodes": 0, "successes": 0, "cycles": 0}
        report = outcome.stop_report
        return {
            **counts,
            "success_rate": counts["successes"] / counts["episodes"] if counts["episodes"] else None,
            **self._timing.summary(),
            "bus": self._bus.summary(),
            "stop_reason": outcome.reason.value,
            "message": outcome.message,
            "joint": outcome.joint,
            "final_state": arm.final_state(),
            # Safe only where the joint's own disable was acknowledged: the flags are no
            # proof (a deadman trip sets NOT_ENABLED and keeps the currents). A completed
            # run got here through shut_down(), which raises unless every disable went through.
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
            "trace_error": trace_error(arm.backend),
            "log_records_lost": list(self._log.lost),
            "exit_code": outcome.exit_code,
            "wall_time_s": time.perf_counter() - self._t0,
        }

    def _report(self, outcome: Outcome) -> dict[str, Any]:
        """Print the summary; return it, or raise what the exit code needs."""
        print_summary(self.console, self.summary, self._log)
        if outcome.reason is StopReason.COMPLETED:
            return self.summary
        self.console.print(disabled_line(self.summary))
        if outcome.reason in SIGNAL_REASONS.values():
            raise Interrupted(outcome.exit_code - 128)
        raise DeployError(f"safe stop: {outcome.message}", outcome.exit_code, self.summary)


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
    err = Console(stderr=True, highlight=False, soft_wrap=True)
    try:
        Deployment(_args_from_namespace(ns)).run()
    except DeployError as e:
        err.print(one_line(f"bioscara deploy: error: {e}"), markup=False)
        return e.code
    except Interrupted as e:
        err.print(f"bioscara deploy: interrupted by {e}", markup=False)
        return e.exit_code
    return 0


def register(sub: argparse._SubParsersAction) -> None:
    """Add the ``deploy`` subcommand (its options: :mod:`~bioscara_gym.training.deploy_parser`)."""
    p = sub.add_parser(
        "deploy",
        help="run a policy on the arm (or its emulation) behind the safety layer",
        description="Check the policy against the env, bring the arm up, run episodes at a fixed rate "
        "behind the safety layer, log every cycle. Exit codes: 0 done, 2 refused (nothing sent), "
        "3 safety stop (arm disabled), 130/143/129 SIGINT/SIGTERM/SIGHUP (arm disabled).",
        epilog=EPILOG,
    )
    add_options(p)
    p.set_defaults(func=cmd_deploy)
