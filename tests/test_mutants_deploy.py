"""Tests that kill mutants mutmut found surviving in ``training/deploy.py`` (docs/mutation.md).

In-process deployments of Reach's scripted expert (or a constant policy) on
the ``mock`` backend: a run of 50 cycles takes a fraction of a second. The
expected values are literals from deploy.py's module docstring (the run
log's records and their fields, the exit codes 0, 2, 3, 130 and 143), the
summary's own words (``disabled_line``) and the CLI's documented defaults.
"""

from __future__ import annotations

import io
import re
import signal
from collections.abc import Callable
from pathlib import Path
from types import SimpleNamespace
from typing import Any

import gymnasium as gym
import numpy as np
import pytest
from rich.console import Console
from rigs import DeployRun, run_deployment

from bioscara_gym.cli import main
from bioscara_gym.errors import DeployError
from bioscara_gym.fsutil import path_argument
from bioscara_gym.training import deploy as deploy_module
from bioscara_gym.training.deploy import DeployArgs, Deployment
from bioscara_gym.training.metadata import build_metadata
from bioscara_gym.training.signals import Interrupted

REACH = "Bioscara-Reach-v0"
ISO_8601 = r"\d{4}-\d{2}-\d{2}T\d{2}:\d{2}:\d{2}[+-]\d{4}"
DISABLED = "arm disabled: j1, j2, j3, j4 acknowledged their disable (currents 0); arm shut down, bus closed"


Run = DeployRun


@pytest.fixture
def deploy(tmp_path: Path, gripper_state_file: Path) -> Callable[..., Run]:
    """``deploy(policy=None, metadata=None, on_cycle=None, **DeployArgs fields)``: Reach's expert on mock."""

    def run(
        policy: Any = None,
        metadata: dict[str, Any] | None = None,
        on_cycle: Callable[[int, gym.Env], None] | None = None,
        **fields: Any,
    ) -> Run:
        fields.setdefault("backend", "mock")
        fields.setdefault("log", tmp_path / "run.jsonl")
        fields.setdefault("state_file", gripper_state_file)
        fields.setdefault("expert", policy is None)
        if metadata is None:
            fields.setdefault("env", REACH)
        return run_deployment(fields, policy, metadata, on_cycle, catch=(Interrupted, SystemExit))

    return run


def still(obs: dict[str, np.ndarray]) -> np.ndarray:
    return np.zeros(4, dtype=np.float32)


def raising(error: BaseException, at: int = 2) -> Callable[[int, gym.Env], None]:
    """An ``on_cycle`` hook that raises ``error`` before cycle ``at``."""

    def hook(cycle: int, env: gym.Env) -> None:
        if cycle == at:
            raise error

    return hook


# ------------------------------------------------------------------ a completed run
def test_a_run_prints_what_it_deploys_and_each_phase_in_a_column(deploy: Callable[..., Run]) -> None:
    run = deploy()
    assert run.error is None, run.output
    assert run.lines[:2] == [
        "deploy     scripted expert -> Bioscara-Reach-v0 (velocity, 25 Hz) on mock",
        "check      no metadata to check (scripted policy)",
    ]
    assert "configure  connecting and pinging j1, j2, j3, j4 ..." in run.lines
    assert "configure  every joint answered" in run.lines
    assert "deploy summary (completed)" in run.output


def test_the_log_opens_with_the_header_then_the_phases_printed_before_it(deploy: Callable[..., Run]) -> None:
    run = deploy(seed=7)
    records = run.records
    header = records[0]
    assert re.fullmatch(ISO_8601, header.pop("started"))
    assert header == {
        "type": "header",
        "policy": "scripted expert",
        "env_id": REACH,
        "backend": "mock",
        "rate_hz": 25.0,
        "control_mode": "velocity",
        "faults": None,
        "i2c_clock_hz": 100_000.0,
        "seed": 7,
        "episodes": 1,
        "realtime": False,
    }
    phases = [(r["phase"], r["detail"]) for r in records if r["type"] == "phase"]
    assert phases[0] == ("check", "no metadata to check (scripted policy)")  # printed before the log opened
    assert [p for p, _ in phases] == [
        "check",
        "configure",
        "activate",
        "home",
        "run",
        "deactivate",
        "cleanup",
    ]
    t = {r["phase"]: r["t"] for r in records if r["type"] == "phase"}
    assert t["check"] == 0.0  # the backend clock's
    assert t["home"] == pytest.approx(1.0) and t["deactivate"] > t["run"]  # mock homing: 1 s


def test_a_completed_run_returns_its_summary_claiming_only_what_happened(deploy: Callable[..., Run]) -> None:
    run = deploy(episodes=2)
    summary = run.records[-1]
    assert summary.pop("type") == "summary"
    assert summary == run.deployment.summary
    expected = {
        "episodes": 2,
        "successes": 2,
        "cycles": 100,
        "success_rate": 1.0,
        "stop_reason": "completed",
        "message": "completed",
        "joint": None,
        "arm_disabled": True,
        "arm_state": "finalized",
        "problems": [],
        "not_confirmed_disabled": [],
        "not_confirmed_warnings": [],
        "gripper": {"width_m": 0.08, "state_file": str(run.deployment.state_file), "saved_width_m": 0.08},
        "log_error": None,
        "trace_error": None,
        "log_records_lost": [],
        "exit_code": 0,
        "rate_hz": 25.0,
        "overruns": 0,
    }
    assert {k: summary[k] for k in expected} == expected
    assert 0 < summary["wall_time_s"] < 60
    assert summary["period_mean_s"] == pytest.approx(0.04)
    assert DISABLED not in run.output  # a completed run prints no stop line


def test_the_run_log_and_the_gripper_state_file_default_beside_each_other(tmp_path: Path) -> None:
    d = Deployment(DeployArgs(expert=True, env=REACH, backend="mock"))
    assert re.fullmatch(r"runs/deploy/deploy-\d{8}-\d{6}\.jsonl", d.log_path.as_posix())
    assert d.state_file == Path("runs/deploy/gripper.json")
    d = Deployment(DeployArgs(expert=True, env=REACH, backend="mock", log=tmp_path / "a" / "r.jsonl"))
    assert d.log_path == tmp_path / "a" / "r.jsonl" and d.state_file == tmp_path / "a" / "gripper.json"
    given = tmp_path / "g.json"
    d = Deployment(
        DeployArgs(expert=True, env=REACH, backend="mock", state_file=given, log=tmp_path / "r.jsonl")
    )
    assert d.state_file == given
    d = Deployment(DeployArgs(expert=True, env=REACH, backend="i2c", log=tmp_path / "r.jsonl"))
    assert d.state_file is None  # on the arm: the backend's own
    assert d.summary == {} and d.env is None and d.target is None


def test_the_env_id_of_an_env_without_a_spec_is_its_class_name() -> None:
    d = Deployment(DeployArgs(expert=True, env=REACH, backend="mock", log=Path("x.jsonl")))
    assert d._env_id() == "NoneType"
    d.target = SimpleNamespace(spec=None)
    assert d._env_id() == "SimpleNamespace"
    d.target = SimpleNamespace(spec=SimpleNamespace(id="Some-v3"))
    assert d._env_id() == "Some-v3"


def test_a_warning_is_one_line_among_the_phases() -> None:
    out = io.StringIO()
    d = Deployment(
        DeployArgs(expert=True, env=REACH, backend="mock", log=Path("x.jsonl")), console=Console(file=out)
    )
    d._show_warning(UserWarning("gripper: [cannot] save"), UserWarning, "f.py", 1)
    assert out.getvalue() == "warning: gripper: [cannot] save\n"


def test_a_phase_that_starts_is_printed_with_dots(tmp_path: Path) -> None:
    out = io.StringIO()
    d = Deployment(
        DeployArgs(expert=True, env=REACH, backend="mock", log=tmp_path / "r.jsonl"),
        console=Console(file=out),
    )
    d.starting("home", "homing [j1]")
    d.done("run", "x")
    assert out.getvalue() == "home       homing [j1] ...\nrun        x\n"
    assert d._early_phases == [{"type": "phase", "phase": "run", "detail": "x", "t": None}]  # no target yet


def test_no_bus_record_before_the_log_or_without_errors(tmp_path: Path) -> None:
    d = Deployment(DeployArgs(expert=True, env=REACH, backend="mock", log=tmp_path / "r.jsonl"))
    d.log_bus("configure")  # nothing to count, nothing to write to: no error

    class Log:
        def __init__(self) -> None:
            self.written: list[dict[str, Any]] = []

        def write(self, record: dict[str, Any]) -> None:
            self.written.append(record)

    d._log = Log()
    d.log_bus("configure")  # no statistics yet
    d._bus = SimpleNamespace(cycle=lambda: {})
    d.log_bus("configure")
    assert d._log.written == []
    d._bus = SimpleNamespace(cycle=lambda: {"j1": {"retries": 1}})
    d.log_bus("reset", episode=2)
    assert d._log.written == [
        {"type": "bus", "phase": "reset", "episode": 2, "joints": {"j1": {"retries": 1}}}
    ]


# ------------------------------------------------------------------ a given policy
def test_a_policy_without_metadata_needs_the_env_named(tmp_path: Path) -> None:
    d = Deployment(DeployArgs(backend="mock", log=tmp_path / "r.jsonl"), policy=still)
    with pytest.raises(DeployError) as caught:
        d.run()
    assert str(caught.value) == "a policy without metadata needs --env ID: the task is never guessed"
    assert not (tmp_path / "r.jsonl").exists()


def test_a_given_policy_without_metadata_runs_as_a_scripted_one(deploy: Callable[..., Run]) -> None:
    run = deploy(policy=still)
    assert run.error is None, run.output
    assert run.lines[:2] == [
        "deploy     given policy -> Bioscara-Reach-v0 (velocity, 25 Hz) on mock",
        "check      no metadata to check (scripted policy)",
    ]


def test_a_given_policy_with_metadata_is_checked_against_the_env(deploy: Callable[..., Run]) -> None:
    env = gym.make(REACH, backend="mock")
    try:
        metadata = build_metadata(env, REACH, {"control_mode": "velocity", "control_freq": 25.0}, algo="sac")
    finally:
        env.close()
    run = deploy(policy=still, metadata=metadata)
    assert run.error is None, run.output
    check = "check      policy metadata matches the env, and acts finitely; nothing sent to the arm yet"
    assert run.lines[1] == check
    run = deploy(policy=still, metadata=metadata, rate=30.0)  # a rate the policy was not trained at
    assert isinstance(run.error, DeployError) and run.error.code == 2
    assert str(run.error).startswith("refused: ") and str(run.error).endswith("; nothing was sent to the arm")


# ------------------------------------------------------------------ stops
def test_a_safety_stop_raises_code_3_with_the_summary_and_says_the_arm_is_disabled(
    deploy: Callable[..., Run],
) -> None:
    def nan(obs: dict[str, np.ndarray]) -> np.ndarray:
        return np.full(4, np.nan, dtype=np.float32)

    run = deploy(policy=nan)
    assert isinstance(run.error, DeployError)
    assert run.error.code == 3 and run.error.summary is run.deployment.summary
    assert str(run.error) == "safe stop: policy returned a non-finite action [nan, nan, nan, nan] (NaN/inf)"
    summary = run.deployment.summary
    assert (summary["stop_reason"], summary["exit_code"], summary["episodes"]) == ("nan_action", 3, 0)
    assert summary["success_rate"] is None  # no episode finished
    assert summary["arm_disabled"] is True and summary["not_confirmed_disabled"] == []
    assert summary["gripper"]["width_m"] == 0.08
    assert run.lines[-1] == DISABLED
    stop = [r for r in run.records if r["type"] == "stop"]
    assert stop == [{"type": "stop", "reason": "nan_action", "message": summary["message"], "joint": None}]
    assert any(line.startswith("safe stop  policy returned a non-finite action [nan") for line in run.lines)


@pytest.mark.parametrize(
    ("error", "reason", "code", "signum"),
    [(Interrupted(signal.SIGTERM), "terminated", 143, 15), (KeyboardInterrupt(), "interrupted", 130, 2)],
    ids=["sigterm", "ctrl-c"],
)
def test_a_signal_mid_run_stops_safely_and_raises_it_again(
    deploy: Callable[..., Run], error: BaseException, reason: str, code: int, signum: int
) -> None:
    run = deploy(on_cycle=raising(error))
    assert isinstance(run.error, Interrupted)
    assert run.error.signum == signum and run.error.exit_code == code
    summary = run.deployment.summary
    assert (summary["stop_reason"], summary["exit_code"], summary["cycles"]) == (reason, code, 2)
    assert summary["arm_disabled"] is True
    assert run.lines[-1] == DISABLED


def test_an_unexpected_error_mid_run_is_code_1_after_the_safe_stop(deploy: Callable[..., Run]) -> None:
    run = deploy(on_cycle=raising(RuntimeError("boom")))
    assert isinstance(run.error, DeployError)
    assert run.error.code == 1 and str(run.error) == "safe stop: RuntimeError: boom"
    assert run.deployment.summary["stop_reason"] == "error"


def test_an_exit_mid_run_goes_on_after_the_safe_stop(deploy: Callable[..., Run]) -> None:
    run = deploy(on_cycle=raising(SystemExit(5)))
    assert isinstance(run.error, SystemExit) and run.error.code == 5
    summary = run.records[-1]
    assert summary["type"] == "summary" and summary["arm_disabled"] is True
    assert summary["stop_reason"] == "error" and summary["message"] == "SystemExit: 5"


def test_a_header_that_cannot_be_written_refuses_before_the_arm_is_touched(
    deploy: Callable[..., Run], monkeypatch: pytest.MonkeyPatch
) -> None:
    from bioscara_gym.training.deploy_safety import SafetyStop, StopReason

    def full(self: Any, description: str) -> None:
        raise SafetyStop(StopReason.LOG_ERROR, "run log: disk full")

    monkeypatch.setattr(Deployment, "_write_header", full)
    run = deploy()
    assert isinstance(run.error, DeployError) and run.error.code == 2
    assert str(run.error) == "refused: run log: disk full; nothing was sent to the arm"


def test_a_run_log_that_cannot_be_opened_names_the_reason(
    deploy: Callable[..., Run], monkeypatch: pytest.MonkeyPatch, tmp_path: Path
) -> None:
    def refuse(path: Path) -> None:
        raise OSError("no reason given")

    monkeypatch.setattr(deploy_module, "RunLog", refuse)
    run = deploy()
    assert isinstance(run.error, DeployError) and run.error.code == 2
    log = tmp_path / "run.jsonl"
    assert str(run.error) == f"cannot open the run log {log}: no reason given; nothing was sent to the arm"


# ------------------------------------------------------------------ the command line
def test_bioscara_deploy_exits_0_after_a_completed_run(
    tmp_path: Path, gripper_state_file: Path, capsys: pytest.CaptureFixture[str]
) -> None:
    argv = ["deploy", "--expert", "--env", REACH, "--backend", "mock", "--log", str(tmp_path / "r.jsonl")]
    assert main([*argv, "--state-file", str(gripper_state_file)]) == 0
    assert capsys.readouterr().err == ""


def test_bioscara_deploy_refusal_is_one_line_with_its_code(capsys: pytest.CaptureFixture[str]) -> None:
    assert main(["deploy", "--expert", "--env", REACH, "--episodes", "0"]) == 2
    assert capsys.readouterr().err == "bioscara deploy: error: --episodes must be >= 1, got 0\n"


@pytest.mark.parametrize(
    ("signum", "code", "name"), [(signal.SIGINT, 130, "SIGINT"), (signal.SIGTERM, 143, "SIGTERM")]
)
def test_bioscara_deploy_interrupted_says_by_what_and_exits_128_plus_the_signal(
    monkeypatch: pytest.MonkeyPatch, capsys: pytest.CaptureFixture[str], signum: int, code: int, name: str
) -> None:
    def interrupted(self: Deployment) -> None:
        raise Interrupted(signum)

    monkeypatch.setattr(Deployment, "run", interrupted)
    assert main(["deploy", "--expert", "--env", REACH]) == code
    assert capsys.readouterr().err == f"bioscara deploy: interrupted by {name}\n"


def test_bioscara_deploy_takes_each_flag_into_its_argument(monkeypatch: pytest.MonkeyPatch) -> None:
    seen: list[DeployArgs] = []

    def record(self: Deployment) -> dict[str, Any]:
        seen.append(self.args)
        return {}

    monkeypatch.setattr(Deployment, "run", record)
    assert main(["deploy", "--expert", "--env", REACH, "--log", "x.jsonl"]) == 0
    assert seen[-1] == DeployArgs(expert=True, env=REACH, log=Path("x.jsonl"))  # the documented defaults
    argv = [
        "deploy",
        "--onnx",
        "p.onnx",
        "--env",
        REACH,
        "--backend",
        "emulated",
        "--bus",
        "3",
        "--config",
        "arm.yaml",
        "--episodes",
        "4",
        "--rate",
        "20",
        "--log",
        "l.jsonl",
        "--faults",
        "nack=0.1",
        "--seed",
        "5",
        "--realtime",
        "--state-file",
        "g.json",
        "--record",
        "t.jsonl",
    ]
    assert main(argv) == 0
    assert seen[-1] == DeployArgs(
        onnx=Path("p.onnx"),
        env=REACH,
        backend="emulated",
        bus=3,
        config=Path("arm.yaml"),
        episodes=4,
        rate=20.0,
        log=Path("l.jsonl"),
        faults="nack=0.1",
        seed=5,
        realtime=True,
        state_file=Path("g.json"),
        record=Path("t.jsonl"),
    )


def test_bioscara_deploy_needs_exactly_one_policy_source(capsys: pytest.CaptureFixture[str]) -> None:
    with pytest.raises(SystemExit):
        main(["deploy", "--env", REACH])
    with pytest.raises(SystemExit):
        main(["deploy", "--expert", "--model", "m.zip"])
    assert "one of the arguments --model --onnx --expert is required" in capsys.readouterr().err


def test_bioscara_deploy_prints_its_error_verbatim_and_plain_on_a_colour_terminal(
    monkeypatch: pytest.MonkeyPatch, capsys: pytest.CaptureFixture[str]
) -> None:
    # The message carries user input and arrays: brackets are text, not markup, and no
    # number or path is coloured (the line is for a log as much as for a terminal).
    def refused(self: Deployment) -> None:
        raise DeployError("refused: [red]model[/red] /tmp/m.zip gives [nan, 1.0]", 2)

    monkeypatch.setattr(Deployment, "run", refused)
    monkeypatch.setenv("FORCE_COLOR", "1")
    assert main(["deploy", "--expert", "--env", REACH]) == 2
    assert (
        capsys.readouterr().err
        == "bioscara deploy: error: refused: [red]model[/red] /tmp/m.zip gives [nan, 1.0]\n"
    )


def test_bioscara_deploy_help_states_each_option_its_default_and_the_exit_codes() -> None:
    # The CLI's help is the operator's documentation: the defaults it states are the ones
    # DeployArgs and the parser use, and the exit codes are deploy.py's docstring's.
    import argparse

    parser = argparse.ArgumentParser()
    sub = parser.add_subparsers()
    deploy_module.register(sub)
    p = sub.choices["deploy"]
    assert (
        sub._choices_actions[0].help == "run a policy on the arm (or its emulation) behind the safety layer"
    )
    assert p.description == (
        "Check the policy against the env, bring the arm up, run episodes at a fixed rate behind the safety "
        "layer, log every cycle. Exit codes: 0 done, 2 refused (nothing sent), 3 safety stop (arm disabled), "
        "130/143/129 SIGINT/SIGTERM/SIGHUP (arm disabled)."
    )
    options = {a.option_strings[0]: (a.default, a.type, a.metavar, a.help) for a in p._actions[1:]}
    assert options == {
        "--model": (None, Path, None, "model.zip (metadata.json beside it)"),
        "--onnx": (None, Path, None, "ONNX policy from `bioscara export` (no torch needed)"),
        "--expert": (False, None, None, "run the scripted expert of --env"),
        "--env": (None, None, None, "env id (for --expert; with a policy it must match the metadata)"),
        "--backend": ("emulated", None, None, "default: emulated"),
        "--firmware": (
            None,
            Path,
            "DIR",
            "joint firmware source for --backend sitl (Arduino/joint/; default $BIOSCARA_FIRMWARE)",
        ),
        "--bus": (None, int, None, "I2C bus number, /dev/i2c-N (default: the config's)"),
        "--config": (None, path_argument, None, "arm configuration YAML (default: the packaged one)"),
        "--episodes": (1, int, None, None),
        "--rate": (
            None,
            float,
            None,
            "control rate in Hz (default: the policy's; a trained policy refuses another)",
        ),
        "--log": (None, Path, None, "run log, JSON Lines (default: runs/deploy/deploy-<time>.jsonl)"),
        "--faults": (
            None,
            None,
            None,
            "emulated bus faults: nack, short_read, corrupt (rates per transaction), latency_ms, jitter_ms "
            "(extra time per transaction), drift_ppm (host clock), seed (of the faults' draws, default 0; "
            "--seed is the episodes'), e.g. latency_ms=2,jitter_ms=3,seed=7",
        ),
        "--seed": (10_000, int, None, "seed of the first episode"),
        "--realtime": (False, None, None, "pace mock/emulated on the wall clock too"),
        "--state-file": (None, Path, None, "gripper state file"),
        "--record": (None, Path, "FILE", "bus trace to write (docs/traces.md)"),
    }
    backend = next(a for a in p._actions if a.dest == "backend")
    assert list(backend.choices) == ["mock", "emulated", "i2c", "sitl"]
    assert p.get_default("func") is deploy_module.cmd_deploy


def test_the_safe_stops_bus_errors_are_a_record_of_their_own_before_the_stop(tmp_path: Path) -> None:
    # deploy.py's docstring: bus records per phase, "safe stop" among them.
    from bioscara_gym.hardware.safety import SafeStopReport

    class Log:
        def __init__(self) -> None:
            self.written: list[dict[str, Any]] = []

        def write(self, record: dict[str, Any]) -> None:
            self.written.append(record)

    out = io.StringIO()
    d = Deployment(
        DeployArgs(expert=True, env=REACH, backend="mock", log=tmp_path / "r.jsonl"),
        console=Console(file=out),
    )
    report = SafeStopReport(
        problems=["j2: no answer"], not_confirmed=["j2"], gripper_width_m=0.05, gripper_saved=False
    )
    d.target = SimpleNamespace(safe_stop=lambda: report, spec=None, arm=SimpleNamespace(backend=None))
    d._log = Log()
    d._bus = SimpleNamespace(cycle=lambda: {"j2": {"retries": 0, "bus": 3}})
    outcome = d._stop_safely(RuntimeError("boom"))
    assert outcome.stop_report is report and d._gripper_width == 0.05
    assert d._log.written == [
        {"type": "bus", "phase": "safe stop", "joints": {"j2": {"retries": 0, "bus": 3}}},
        {"type": "stop", "reason": "error", "message": "RuntimeError: boom", "joint": None},
    ]
    assert out.getvalue() == "safe stop  RuntimeError: boom\n"


class RecordingLog:
    """The run log as far as deploy writes to it: records kept, no error, nothing lost."""

    def __init__(self) -> None:
        self.written: list[dict[str, Any]] = []
        self.error: OSError | None = None
        self.lost: list[str] = []

    def write(self, record: dict[str, Any]) -> None:
        self.written.append(record)


def bare_deployment(tmp_path: Path) -> Deployment:
    return Deployment(DeployArgs(expert=True, env=REACH, backend="mock", log=tmp_path / "r.jsonl"))


def test_the_end_detaches_the_deadman_guard_and_logs_the_shutdowns_bus_errors(tmp_path: Path) -> None:
    d = bare_deployment(tmp_path)
    detached: list[bool] = []
    d._loop = SimpleNamespace(guard=SimpleNamespace(detach=lambda: detached.append(True)))
    d._log = RecordingLog()
    d._bus = SimpleNamespace(cycle=lambda: {"j1": {"retries": 2}})
    d._summarise = lambda outcome: {"stop_reason": "completed"}
    d._finish(None)
    assert detached == [True]
    assert d._log.written == [
        {"type": "bus", "phase": "shutdown", "joints": {"j1": {"retries": 2}}},
        {"type": "summary", "stop_reason": "completed"},
    ]
    d._loop = SimpleNamespace(guard=None)  # stopped before the loop watched the joints
    d._finish(None)
    assert d.summary == {"stop_reason": "completed"}


def test_a_summary_of_a_run_stopped_before_its_loop_claims_no_episode_and_names_what_failed(
    tmp_path: Path,
) -> None:
    from bioscara_gym.hardware.safety import SafeStopReport
    from bioscara_gym.training.deploy_safety import Outcome, StopReason

    d = bare_deployment(tmp_path)
    gripper = SimpleNamespace(state_file=None, saved_width_m=None)
    final = {"j1": {"flags": 8}, "j2": {"flags": 0}}
    d.target = SimpleNamespace(
        arm=SimpleNamespace(
            final_state=lambda: final, state=SimpleNamespace(value="finalized"), gripper=gripper, backend=None
        )
    )
    d._timing = SimpleNamespace(summary=lambda: {"overruns": 0})
    d._bus = SimpleNamespace(summary=lambda: {"j2": {"transactions": 9}})
    d._log = RecordingLog()
    report = SafeStopReport(
        problems=["j2: no answer"],
        not_confirmed=["j2"],
        gripper_width_m=None,
        gripper_saved=False,
        why_not_confirmed={"j2": "no answer"},
    )
    outcome = Outcome(StopReason.COMM_ERROR, "j2: bus error", "j2", 3, report)
    summary = d._summarise(outcome)
    assert 0 <= summary.pop("wall_time_s") < 60
    assert summary == {
        "episodes": 0,
        "successes": 0,
        "cycles": 0,
        "success_rate": None,
        "overruns": 0,
        "bus": {"j2": {"transactions": 9}},
        "stop_reason": "comm_error",
        "message": "j2: bus error",
        "joint": "j2",
        "final_state": final,
        "arm_disabled": False,
        "arm_state": "finalized",
        "problems": ["j2: no answer"],
        "not_confirmed_disabled": ["j2"],
        "not_confirmed_warnings": ["j2: no answer, still powered as far as we know: cut the power"],
        "gripper": {"width_m": None, "state_file": None, "saved_width_m": None},
        "log_error": None,
        "trace_error": None,
        "log_records_lost": [],
        "exit_code": 3,
    }


def reach_metadata() -> dict[str, Any]:
    env = gym.make(REACH, backend="mock")
    try:
        return build_metadata(env, REACH, {"control_mode": "velocity", "control_freq": 25.0}, algo="sac")
    finally:
        env.close()


def test_a_model_is_checked_on_its_own_inputs_and_outputs_too(
    deploy: Callable[..., Run], monkeypatch: pytest.MonkeyPatch
) -> None:
    from bioscara_gym.training.deploy_checks import LoadedPolicy
    from bioscara_gym.training.metadata import PolicyShapes

    env = gym.make(REACH, backend="mock")
    shapes = PolicyShapes.of_spaces(env.observation_space, env.action_space, "model m.zip")
    env.close()
    loaded = LoadedPolicy(lambda env: still, reach_metadata(), "SAC m.zip", shapes)
    monkeypatch.setattr(deploy_module, "load_policy", lambda args: loaded)
    run = deploy(model=Path("m.zip"), expert=False)
    assert run.error is None, run.output
    assert run.lines[1] == (
        "check      policy metadata and own inputs and outputs match the env, and acts finitely; "
        "nothing sent to the arm yet"
    )


def test_the_probe_observation_is_drawn_with_the_runs_seed(deploy: Callable[..., Run]) -> None:
    seen: list[dict[str, np.ndarray]] = []

    def first(obs: dict[str, np.ndarray]) -> np.ndarray:
        seen.append(obs)
        return np.zeros(4, dtype=np.float32)

    deploy(policy=first, metadata=reach_metadata(), seed=7)
    env = gym.make(REACH, backend="mock")
    env.observation_space.seed(7)
    expected = env.observation_space.sample()
    env.close()
    for key, value in expected.items():
        np.testing.assert_array_equal(seen[0][key], value)


def test_backend_options_given_are_laid_over_the_backends(tmp_path: Path, gripper_state_file: Path) -> None:
    # bioscara replay passes its bus this way; here: another gripper state file.
    other = tmp_path / "other" / "gripper.json"
    other.parent.mkdir()
    other.write_text('{"width_m": 0.05}\n', encoding="utf-8")
    args = DeployArgs(
        expert=True, env=REACH, backend="mock", log=tmp_path / "r.jsonl", state_file=gripper_state_file
    )
    d = Deployment(args, console=Console(file=io.StringIO()), backend_options={"state_file": other})
    summary = d.run()
    assert summary["gripper"]["state_file"] == str(other)


def test_the_default_console_prints_each_phase_on_one_line_without_colouring_numbers(
    tmp_path: Path, monkeypatch: pytest.MonkeyPatch, capsys: pytest.CaptureFixture[str]
) -> None:
    monkeypatch.setenv("FORCE_COLOR", "1")
    d = bare_deployment(tmp_path)  # no console given: deploy's own, on stdout
    detail = "j1, j2, j3, j4 homed in 1.0 s; " + "offset restored from HOMEOFFSET, " * 4
    d.done("home", detail)
    out = capsys.readouterr().out
    assert out.count("\n") == 1  # not wrapped at 80 columns
    assert detail in out  # plain text: no number or name coloured


def test_a_summary_names_the_log_error_and_the_records_lost(tmp_path: Path) -> None:
    from bioscara_gym.training.deploy_safety import Outcome

    d = bare_deployment(tmp_path)
    gripper = SimpleNamespace(state_file=tmp_path / "g.json", saved_width_m=0.08)
    d.target = SimpleNamespace(
        arm=SimpleNamespace(
            final_state=dict, state=SimpleNamespace(value="finalized"), gripper=gripper, backend=None
        )
    )
    d._timing = SimpleNamespace(summary=dict)
    d._bus = SimpleNamespace(summary=dict)
    d._log = RecordingLog()
    d._log.error = OSError(28, "No space left on device")
    d._log.lost = ["cycle 5", "summary"]
    d._gripper_width = 0.08
    summary = d._summarise(Outcome())
    assert summary["log_error"] == "[Errno 28] No space left on device"
    assert summary["log_records_lost"] == ["cycle 5", "summary"]
    assert summary["gripper"] == {
        "width_m": 0.08,
        "state_file": str(tmp_path / "g.json"),
        "saved_width_m": 0.08,
    }
    assert (
        summary["arm_disabled"] is True
        and summary["problems"] == []
        and summary["not_confirmed_warnings"] == []
    )


# ------------------------------------------------------------------ deploy_checks.py
def test_a_policy_source_is_exactly_one_of_model_onnx_and_expert() -> None:
    from bioscara_gym.training.deploy_checks import load_policy

    message = "deploy needs exactly one of --model PATH, --onnx FILE or --expert --env ID"
    for args in (DeployArgs(), DeployArgs(expert=True, env=REACH, onnx=Path("p.onnx"))):
        with pytest.raises(DeployError) as caught:
            load_policy(args)
        assert str(caught.value) == message


@pytest.mark.parametrize(
    ("action", "shown"),
    [
        ([None, 0, 0, 0], "[nan,  0.,  0.,  0.]"),
        ([0.123456, float("nan"), 0, 0], "[0.123,   nan, 0.   , 0.   ]"),
    ],
    ids=["none-is-nan", "three-decimals"],
)
def test_a_probe_action_that_is_not_finite_is_refused_as_numbers_to_three_decimals(
    action: list[Any], shown: str
) -> None:
    from bioscara_gym.training.deploy_checks import LoadedPolicy, probe_policy

    env = gym.make(REACH, backend="mock")
    made_for: list[gym.Env] = []

    def make(for_env: gym.Env) -> Callable[[dict[str, np.ndarray]], list[Any]]:
        made_for.append(for_env)
        return lambda obs: action

    try:
        with pytest.raises(DeployError) as caught:
            probe_policy(LoadedPolicy(make, None, "given policy"), env, 0)
    finally:
        env.close()
    assert made_for == [env]  # the policy is made for the env it will drive
    assert str(caught.value) == (
        f"refused: given policy gives a non-finite action {shown} on a probe observation; "
        "nothing was sent to the arm"
    )


@pytest.mark.parametrize(
    ("error", "line"),
    [
        (ValueError("first\nsecond"), "first"),
        (ValueError(), "no message"),
        (ValueError("  \n "), "no message"),
    ],
)
def test_first_line_of_an_error_or_no_message(error: Exception, line: str) -> None:
    from bioscara_gym.training.deploy_checks import first_line

    assert first_line(error) == line


def test_env_kwargs_the_env_does_not_take_are_refused_naming_what_it_takes() -> None:
    from bioscara_gym.training.deploy_checks import check_env_kwargs

    check_env_kwargs(REACH, {"control_mode": "velocity", "control_freq": 25.0})
    check_env_kwargs(REACH, {"max_episode_steps": 60, "disable_env_checker": True})  # gym.make's own
    with pytest.raises(DeployError) as caught:
        check_env_kwargs(REACH, {"control_mode": "velocity", "arm_speed": 1})
    assert str(caught.value) == (
        "the policy's env_kwargs has 'arm_speed', which Bioscara-Reach-v0 does not take; it takes "
        "goal_horizon_s, goal_radius, control_mode, control_freq, reward_type, distance_threshold, "
        "randomization, render_mode, width, height, cartesian_lead, cartesian_step"
    )
    with pytest.raises(
        DeployError, match=r"^cannot make env 'Bioscara-Nope-v0': Environment `Bioscara-Nope`"
    ):
        check_env_kwargs("Bioscara-Nope-v0", {})


def test_keyword_parameters_follow_kwargs_up_the_bases_and_stop_where_they_end() -> None:
    from bioscara_gym.training.metadata import keyword_parameters

    class Base:
        def __init__(self, a: int, *args: int, b: int = 1) -> None: ...

    class Child(Base):
        def __init__(self, c: int, a: int = 0, **kwargs: Any) -> None: ...

    class Leaf(Child):  # no __init__ of its own
        pass

    class Closed(Base):
        def __init__(self, d: int) -> None: ...

    def creator(x: int, *args: int, y: int = 0, **kwargs: Any) -> None: ...

    assert keyword_parameters(Leaf) == ["c", "a", "b"]
    assert keyword_parameters(Closed) == ["d"]
    assert keyword_parameters(creator) == ["x", "y"]


def test_env_kwargs_problem_takes_the_render_modes_the_env_renders_and_no_other() -> None:
    from bioscara_gym.training.metadata import env_kwargs_problem

    for mode in (None, "rgb_array", "human"):  # Reach's metadata["render_modes"], and none
        assert env_kwargs_problem(REACH, {"render_mode": mode}) is None
    for mode, shown in ((5, "5"), ("ansi", "'ansi'"), (["rgb_array"], "['rgb_array']")):
        expected = f"has render_mode {shown}; {REACH} renders rgb_array, human or null"
        assert env_kwargs_problem(REACH, {"render_mode": mode}) == expected

    def make(render_mode: str | None = None) -> gym.Env:  # an env made by a function: no metadata
        raise AssertionError("not made")

    # An unknown keyword is named with the settings a user may give: not the backend's plumbing.
    problem = env_kwargs_problem(REACH, {"bogus": 1})
    assert problem is not None and problem.startswith(f"has 'bogus', which {REACH} does not take; it takes ")
    taken = problem.split("it takes ")[1].split(", ")
    assert all(name.isidentifier() for name in taken), taken
    assert {"control_mode", "control_freq", "render_mode", "randomization"} <= set(taken)
    assert not {"backend", "backend_options", "config"} & set(taken)

    gym.register("Bioscara-ByFunction-v0", entry_point=make)
    try:
        assert env_kwargs_problem("Bioscara-ByFunction-v0", {"render_mode": None}) is None
        assert env_kwargs_problem("Bioscara-ByFunction-v0", {"render_mode": "rgb_array"}) == (
            "has render_mode 'rgb_array'; Bioscara-ByFunction-v0 renders nothing (null)"
        )
    finally:
        del gym.registry["Bioscara-ByFunction-v0"]


def test_output_files_are_each_their_own_regular_file(tmp_path: Path) -> None:
    from bioscara_gym.training.deploy_checks import check_outputs

    log, state = tmp_path / "a" / "run.jsonl", tmp_path / "gripper.json"
    check_outputs({"--log": log, "--state-file": None, "--record": state})
    cases = [
        (
            {"--log": log, "--record": tmp_path / "a" / ".." / "a" / "run.jsonl"},
            f"--log and --record name the same file {tmp_path / 'a' / '..' / 'a' / 'run.jsonl'}; "
            "each needs its own",
        ),
        ({"--log": tmp_path}, f"--log {tmp_path} is not a regular file"),
    ]
    (tmp_path / "file").write_text("", encoding="utf-8")
    under = tmp_path / "file" / "x" / "run.jsonl"
    cases.append(({"--state-file": under}, f"--state-file {under}: {tmp_path / 'file'} is not a directory"))
    for outputs, message in cases:
        with pytest.raises(DeployError) as caught:
            check_outputs(outputs)
        assert str(caught.value) == message


@pytest.mark.parametrize(
    ("changes", "message"),
    [
        ({"backend": "sim"}, "backend 'sim' is not deployable; expected one of mock, emulated, i2c, sitl"),
        ({"bus": -1}, "--bus must be an I2C bus number >= 0 (/dev/i2c-N), got -1"),
        ({"firmware": Path("fw")}, "--firmware needs --backend sitl (the firmware in the loop)"),
        (
            {"backend": "mock", "faults": "nack=0.1"},
            "--faults needs --backend emulated or sitl (faults are injected by the emulated bus)",
        ),
        ({"backend": "sitl", "faults": "nack=lots"}, "--faults: fault 'nack': 'lots' is not a number"),
        # Seen (a hostile test): both ran as a rehearsal without faults.
        (
            {"backend": "emulated", "faults": " "},
            "--faults names no fault; give KEY=VALUE,... e.g. nack=0.01",
        ),
        (
            {"backend": "emulated", "faults": ","},
            "--faults: fault specification ',' has an empty item; expected KEY=VALUE,...",
        ),
    ],
    ids=["backend", "bus", "firmware", "faults-on-mock", "faults-on-sitl", "faults-blank", "faults-comma"],
)
def test_bad_arguments_are_refused_in_their_words(changes: dict[str, Any], message: str) -> None:
    from bioscara_gym.training.deploy_checks import check_args

    with pytest.raises(DeployError) as caught:
        check_args(DeployArgs(expert=True, env=REACH, **changes))
    assert str(caught.value) == message


def test_arguments_on_their_bounds_are_accepted() -> None:
    from bioscara_gym.training.deploy_checks import check_args

    check_args(DeployArgs(expert=True, env=REACH, episodes=1, seed=0, bus=0, rate=20.0))
    check_args(DeployArgs(expert=True, env=REACH, backend="sitl", faults="nack=0.1", firmware=Path("fw")))


def test_the_env_is_made_on_the_backend_with_the_bus_rate_and_options_given(tmp_path: Path) -> None:
    from bioscara_gym.hardware.emulated_bus import FaultPlan
    from bioscara_gym.training.deploy_checks import backend_options, make_env

    args = DeployArgs(expert=True, env="Bioscara-Reach", backend="mock", bus=3, rate=40)
    env = make_env(args, tmp_path / "g.json", None)
    try:
        t = env.unwrapped
        assert t.spec.id == REACH and t.control_freq == 40.0 and t.config.bus == 3 and t.render_mode is None
    finally:
        env.close()
    metadata = {"env_id": REACH, "env_kwargs": {"control_mode": "cartesian"}}
    env = make_env(DeployArgs(model=Path("m.zip"), backend="mock"), None, metadata)
    try:
        assert env.unwrapped.control_mode == "cartesian" and env.unwrapped.control_freq == 25.0
    finally:
        env.close()
    with pytest.raises(DeployError) as caught:
        make_env(
            DeployArgs(model=Path("m.zip"), backend="mock"),
            None,
            {**metadata, "env_kwargs": {"control_mode": "warp"}},
        )
    assert str(caught.value) == (
        "cannot make env 'Bioscara-Reach-v0': "
        "control_mode 'warp' must be one of velocity, position, cartesian"
    )
    with pytest.raises(DeployError, match="Bioscara-Nope"):
        make_env(DeployArgs(expert=True, env="Bioscara-Nope", backend="mock"), None, None)
    assert backend_options(DeployArgs(backend="mock"), None) == {}
    options = backend_options(
        DeployArgs(backend="sitl", faults="nack=0.5", firmware=Path("fw")), tmp_path / "g.json"
    )
    assert options == {
        "state_file": tmp_path / "g.json",
        "faults": FaultPlan.parse("nack=0.5"),
        "firmware": Path("fw"),
    }
    assert backend_options(DeployArgs(backend="sitl"), None) == {"firmware": None}


def test_the_expert_needs_its_env_named() -> None:
    from bioscara_gym.training.deploy_checks import load_policy

    with pytest.raises(DeployError) as caught:
        load_policy(DeployArgs(expert=True))
    assert str(caught.value) == "--expert needs --env ID: the task is never guessed"


def test_an_onnx_policy_is_the_policy_for_any_env_with_its_own_metadata_and_shapes(
    monkeypatch: pytest.MonkeyPatch,
) -> None:
    from bioscara_gym.training import export
    from bioscara_gym.training.deploy_checks import load_policy

    class OnnxPolicy:
        def __init__(self, path: Path) -> None:
            self.path, self.metadata, self.shapes = path, {"env_id": REACH}, "its shapes"

    monkeypatch.setattr(export, "OnnxPolicy", OnnxPolicy)
    loaded = load_policy(DeployArgs(onnx=Path("p.onnx")))
    policy = loaded.make("any env")
    assert isinstance(policy, OnnxPolicy) and policy.path == Path("p.onnx")
    assert (loaded.metadata, loaded.description, loaded.shapes) == (
        {"env_id": REACH},
        "ONNX p.onnx",
        "its shapes",
    )


def test_a_model_is_loaded_with_its_own_copy_of_the_metadata_and_acts_through_predict(
    monkeypatch: pytest.MonkeyPatch,
) -> None:
    from bioscara_gym.training import algos, deploy_checks

    read: list[Path] = []
    monkeypatch.setattr(deploy_checks, "read_metadata", read.append)
    space = gym.spaces.Box(-1.0, 1.0, (4,))

    class Model:
        observation_space, action_space = space, space

        def predict(self, obs: Any, deterministic: bool = False) -> tuple[np.ndarray, None]:
            return np.full(4, 0.5 if deterministic else 0.0), None

    loads: list[tuple[Path, bool]] = []

    def load_model(path: Path, require_embedded: bool = False) -> tuple[Model, dict[str, Any]]:
        loads.append((path, require_embedded))
        return Model(), {"algo": "sac"}

    monkeypatch.setattr(algos, "load_model", load_model)
    loaded = deploy_checks.load_policy(DeployArgs(model=Path("run/model.zip")))
    assert read == [Path("run/model.zip")] and loads == [(Path("run/model.zip"), True)]
    assert loaded.description == "SAC run/model.zip" and loaded.metadata == {"algo": "sac"}
    assert loaded.shapes.source == "model run/model.zip"
    assert loaded.make("any env")(np.zeros(4)).tolist() == [0.5] * 4  # deterministic actions


def test_a_model_without_the_train_extra_names_deploy_model(monkeypatch: pytest.MonkeyPatch) -> None:
    import sys
    import types

    from bioscara_gym.hardware.errors import MissingExtraError
    from bioscara_gym.training import deploy_checks

    class WithoutTorch(types.ModuleType):
        def __getattr__(self, name: str) -> Any:
            raise MissingExtraError("bioscara train", "train")

    monkeypatch.setattr(deploy_checks, "read_metadata", lambda path: None)
    monkeypatch.setitem(
        sys.modules, "bioscara_gym.training.algos", WithoutTorch("bioscara_gym.training.algos")
    )
    with pytest.raises(MissingExtraError) as caught:
        deploy_checks.load_policy(DeployArgs(model=Path("m.zip")))
    assert str(caught.value) == "deploy --model needs the [train] extra: pip install 'bioscara-gym[train]'"


def test_a_bus_trace_asked_for_records_the_deploy_command_and_its_arguments(tmp_path: Path) -> None:
    # docs/traces.md: the header says which command ran, with its arguments, for bioscara replay.
    from bioscara_gym.hardware.recording import Recording
    from bioscara_gym.training.deploy_checks import backend_options

    args = DeployArgs(expert=True, env=REACH, backend="mock", record=tmp_path / "t.jsonl")
    options = backend_options(args, None)
    assert options == {"record": Recording(tmp_path / "t.jsonl", "deploy", args)}


def test_the_arm_configuration_given_is_the_one_the_env_drives(tmp_path: Path) -> None:
    from importlib import resources

    from bioscara_gym.training.deploy_checks import make_env

    packaged = (resources.files("bioscara_gym.hardware") / "default_config.yaml").read_text(encoding="utf-8")
    config = tmp_path / "arm.yaml"
    config.write_text(packaged.replace("i2c_clock_hz: 100000 ", "i2c_clock_hz: 400000 "), encoding="utf-8")
    env = make_env(DeployArgs(expert=True, env=REACH, backend="mock", config=config), None, None)
    try:
        assert env.unwrapped.config.i2c_clock_hz == 400_000.0
    finally:
        env.close()


def test_an_output_after_one_left_to_the_backend_is_still_checked(tmp_path: Path) -> None:
    from bioscara_gym.training.deploy_checks import check_outputs

    with pytest.raises(DeployError, match="is not a regular file"):
        check_outputs({"--state-file": None, "--log": tmp_path})


def test_keyword_parameters_are_the_constructors_even_with_a_new_of_its_own() -> None:
    from bioscara_gym.training.metadata import keyword_parameters

    class WithNew:
        def __new__(cls, *args: Any, **kwargs: Any) -> Any:
            return super().__new__(cls)

        def __init__(self, p: int, *, q: int = 0) -> None: ...

    assert keyword_parameters(WithNew) == ["p", "q"]


def test_env_kwargs_of_an_env_registered_with_a_class_are_checked_too() -> None:
    from bioscara_gym.training.deploy_checks import check_env_kwargs

    class Probe(gym.Env):
        def __init__(self, size: int = 1) -> None: ...

    gym.register(id="ProbeClass-v0", entry_point=Probe)
    try:
        check_env_kwargs("ProbeClass-v0", {"size": 2})
        with pytest.raises(
            DeployError, match=r"has 'colour', which ProbeClass-v0 does not take; it takes size$"
        ):
            check_env_kwargs("ProbeClass-v0", {"colour": 2})
    finally:
        del gym.registry["ProbeClass-v0"]
