"""``bioscara deploy`` and ``bioscara export``: the safety layer on the emulated arm.

Deployments run in-process through :class:`bioscara_gym.training.deploy.Deployment` (a
hook injects faults mid-run) and, for signals, as a ``bioscara deploy``
subprocess whose emulator state is read back from the run log's summary.
"""

from __future__ import annotations

import errno
import itertools
import json
import os
import shutil
import signal
import stat
import subprocess
import sys
import textwrap
import time
import zipfile
from collections.abc import Callable
from pathlib import Path
from typing import Any

import gymnasium as gym
import numpy as np
import pytest
from rigs import (
    ConstantPolicy,
    DeployRun,
    FlipsNextReply,
    lose_joint_at,
    place_obstacle,
    read_log,
    run_deployment,
    run_log_disk_filling,
    train_tiny_sac,
)

from bioscara_gym.cli import main
from bioscara_gym.hardware.arm import Arm
from bioscara_gym.hardware.backends import make_backend
from bioscara_gym.hardware.emulated_bus import FaultPlan
from bioscara_gym.hardware.registers import Flag
from bioscara_gym.training.deploy import EXIT_REFUSED, EXIT_SAFETY_STOP
from bioscara_gym.training.metadata import read_metadata
from bioscara_gym.training.signals import Interrupted, SignalGuard

REACH = "Bioscara-Reach-v0"


# ------------------------------------------------------------------ helpers
def assert_every_joint_disabled(summary: dict[str, Any]) -> None:
    """Checked on the device side: the firmware emulator (or the mock device), not the host's view."""
    for name, state in summary["final_state"].items():
        assert state["source"] in ("emulator", "mock device"), name
        assert state["flags"] & Flag.NOT_ENABLED, f"{name} still enabled: {state}"
        assert state["drive_current"] in (0, None) and state["hold_current"] in (0, None), state
    assert summary["arm_disabled"] is True
    assert summary["not_confirmed_disabled"] == []
    assert summary["arm_state"] == "finalized"


Run = DeployRun


@pytest.fixture
def deploy(tmp_path: Path, gripper_state_file: Path) -> Callable[..., Run]:
    """``deploy(policy=None, metadata=None, on_cycle=None, **DeployArgs fields)`` on ``emulated``."""

    def run(
        policy: Any = None,
        metadata: dict[str, Any] | None = None,
        on_cycle: Callable[[int, gym.Env], None] | None = None,
        **fields: Any,
    ) -> Run:
        fields.setdefault("backend", "emulated")
        fields.setdefault("log", tmp_path / "run.jsonl")
        fields.setdefault("state_file", gripper_state_file)
        if "model" not in fields and "onnx" not in fields:
            fields.setdefault("expert", policy is None)
            if metadata is None:
                fields.setdefault("env", REACH)
        return run_deployment(fields, policy, metadata, on_cycle)

    return run


class PushJ1:
    """Turns j1 at 0.3 of its speed towards the middle of its range (set on the first call).

    Slow enough for the firmware's stall detection to see a collision (85
    microsteps a pass, within its spike limit; docs/firmware.md).
    """

    def __init__(self) -> None:
        self.direction = 0

    def __call__(self, obs: dict[str, np.ndarray]) -> np.ndarray:
        if self.direction == 0:
            self.direction = -1 if obs["observation"][0] > 0 else 1
        return np.array([0.3 * self.direction, 0.0, 0.0, 0.0], dtype=np.float32)


# ---------------------------------------------------------- a trained policy
@pytest.fixture(scope="module")
def sac_model(tmp_path_factory: pytest.TempPathFactory) -> Path:
    """A SAC + HER policy (as the Reach config trains) after 200 steps, saved with its metadata."""
    return train_tiny_sac(tmp_path_factory.mktemp("sac"))


@pytest.fixture(scope="module")
def onnx_file(sac_model: Path) -> Path:
    from bioscara_gym.training.export import export_onnx

    result = export_onnx(sac_model, sac_model.parent / "policy.onnx", check_samples=64)
    assert result.max_abs_error <= 1e-5
    return result.path


# --------------------------------------------------------------------- runs
@pytest.mark.parametrize("backend", ["emulated", "mock"])
def test_expert_deploy_completes_and_logs_every_cycle(deploy: Callable[..., Run], backend: str) -> None:
    run = deploy(episodes=2, backend=backend)
    assert run.error is None, run.output
    lines = read_log(run.log)
    assert lines[0]["type"] == "header"
    assert lines[-1]["type"] == "summary"
    cycles = [r for r in lines if r["type"] == "cycle"]
    summary = lines[-1]
    assert summary["stop_reason"] == "completed"
    assert summary["episodes"] == 2 and summary["cycles"] == len(cycles) == 100
    # In simulation the reset teleports the arm, so each joint's first reading is
    # confirmed by a second (docs/protocol.md): ~3 ms of bus time after the
    # schedule restarts, taken from each episode's first period.
    assert summary["period_mean_s"] == pytest.approx(0.04, abs=1e-4)
    assert summary["period_max_s"] == pytest.approx(0.04, abs=1e-4)
    assert set(cycles[0]) >= {"t", "period_s", "work_s", "action", "commands", "q", "qd", "flags", "overrun"}
    for phase in ("check", "configure", "activate", "home", "run", "deactivate", "cleanup"):
        assert any(r["type"] == "phase" and r["phase"] == phase for r in lines), phase
    assert_every_joint_disabled(summary)


def test_deploy_clamps_actions_outside_the_action_space(deploy: Callable[..., Run]) -> None:
    run = deploy(policy=ConstantPolicy([5.0, 0.0, -5.0, 0.0]))
    assert run.error is None, run.output
    cycles = [r for r in read_log(run.log) if r["type"] == "cycle"]
    config = run.backend.config
    assert all(c["clamped"] for c in cycles)
    for c in cycles:
        for name, command in c["commands"].items():
            assert abs(command) <= config.joint(name).max_velocity + 1e-9


def test_deploy_homes_only_the_joints_not_homed_before(
    deploy: Callable[..., Run], monkeypatch: pytest.MonkeyPatch, gripper_state_file: Path
) -> None:
    backend = make_backend("emulated", state_file=gripper_state_file)
    j1, cfg = backend.joints["j1"], backend.config.joint("j1")
    j1.init()
    j1.enable(cfg.drive_current, cfg.hold_current)
    j1.home(cfg.homing.speed, cfg.homing.threshold, cfg.homing.current)
    j1.deinit()  # the host goes away; the joint stays powered and homed
    monkeypatch.setattr("bioscara_gym.envs.base.make_backend", lambda *a, **k: backend)
    run = deploy()
    assert run.error is None, run.output
    assert "j1 homed before: offset restored from HOMEOFFSET" in run.output
    assert "homing j2, j3, j4" in run.output


# ------------------------------------------------------------- safe stops
def test_stall_mid_run_stops_every_joint_and_names_it(deploy: Callable[..., Run]) -> None:
    policy = PushJ1()

    def obstacle(cycle: int, env: gym.Env) -> None:
        if cycle == 3:
            place_obstacle(env.unwrapped.sim, "j1", direction=policy.direction, gap=0.01)

    run = deploy(policy=policy, on_cycle=obstacle)
    assert run.error is not None and run.error.code == EXIT_SAFETY_STOP
    assert "j1 stalled" in str(run.error)
    summary = read_log(run.log)[-1]
    assert summary["stop_reason"] == "stall" and summary["joint"] == "j1"
    assert summary["final_state"]["j1"]["flags"] & Flag.STALL
    assert_every_joint_disabled(summary)


@pytest.mark.parametrize("backend", ["emulated", "mock"])
def test_nan_action_stops_before_the_arm_sees_it(deploy: Callable[..., Run], backend: str) -> None:
    run = deploy(policy=ConstantPolicy([0.1, 0.0, 0.0, 0.0], bad_from=3), backend=backend)
    assert run.error is not None and run.error.code == EXIT_SAFETY_STOP
    assert "non-finite action [nan" in str(run.error)
    lines = read_log(run.log)
    assert lines[-1]["stop_reason"] == "nan_action"
    assert lines[-1]["cycles"] == 3
    assert [r for r in lines if r["type"] == "cycle"][-1]["action"][0] == "nan"
    assert_every_joint_disabled(lines[-1])


def test_persistent_nacks_end_in_a_named_comm_error_and_no_joint_claimed_safe(
    deploy: Callable[..., Run],
) -> None:
    run = deploy(faults="nack=1.0")
    assert run.error is not None and run.error.code == EXIT_SAFETY_STOP
    assert "communication error: j1 (0x11): PING failed after 3 attempts" in str(run.error)
    summary = read_log(run.log)[-1]
    assert summary["stop_reason"] == "comm_error" and summary["joint"] == "j1"
    for name, state in summary["final_state"].items():  # nothing reached them: as powered up
        assert state["flags"] & Flag.NOT_ENABLED and state["drive_current"] == 0, name
    # ... but no joint acknowledged a disable, so none is claimed safe
    assert summary["arm_disabled"] is False
    assert summary["not_confirmed_disabled"] == ["j1", "j2", "j3", "j4"]
    assert "j4: no answer, still powered as far as we know: cut the power" in run.output


def test_bus_lost_mid_run_reports_the_joints_it_could_not_disable(deploy: Callable[..., Run]) -> None:
    def cut_bus(cycle: int, env: gym.Env) -> None:
        if cycle == 5:
            env.unwrapped.backend.bus.faults = FaultPlan(nack=1.0)

    run = deploy(on_cycle=cut_bus)
    assert run.error is not None and run.error.code == EXIT_SAFETY_STOP
    assert "communication error: j1" in str(run.error)
    summary = run.summary
    assert summary["stop_reason"] == "comm_error"
    assert summary["not_confirmed_disabled"] == ["j1", "j2", "j3", "j4"]
    assert "NOT confirmed disabled" in run.output and "cut the power" in run.output


@pytest.mark.parametrize(
    ("fault", "wording"),
    [
        pytest.param("nack", "j2: no answer", id="j2-nacks"),
        pytest.param("ff", "j3: no valid answer", id="j3-answers-0xff"),
    ],
)
def test_a_joint_lost_mid_run_is_named_and_never_counted_as_disabled(
    deploy: Callable[..., Run], fault: str, wording: str
) -> None:
    # Seen: with j2 NACKing from mid-episode the velocity-mode deploy printed
    # "arm disabled: every joint reports not enabled" while the emulator's j2
    # still had 40 % drive current (its deadman set NOT_ENABLED, which keeps
    # the currents).
    name, address = ("j2", 0x12) if fault == "nack" else ("j3", 0x13)

    lose_joint = lose_joint_at(5, name, address, nacks=fault == "nack")
    run = deploy(policy=ConstantPolicy([0.0, -0.5, 0.5, 0.0]), env=REACH, on_cycle=lose_joint)
    assert run.error is not None and run.error.code == EXIT_SAFETY_STOP
    summary = run.summary
    assert summary["arm_disabled"] is False
    assert summary["not_confirmed_disabled"] == [name]
    core = run.backend.sim.cores[name]
    assert core.flags & Flag.NOT_ENABLED  # the deadman tripped ...
    assert core.drive_current > 0  # ... and kept the current: the joint is not safe
    assert summary["final_state"][name]["drive_current"] == core.drive_current
    assert "every joint reports not enabled" not in run.output
    assert f"{wording}, still powered as far as we know: cut the power" in run.output
    others = [n for n in ("j1", "j2", "j3", "j4") if n != name]
    for other in others:
        assert summary["final_state"][other]["drive_current"] == 0
    assert f"confirmed disabled: {', '.join(others)}" in run.output


def test_a_flipped_exponent_bit_in_a_position_is_read_again_and_logged(deploy: Callable[..., Run]) -> None:
    # Seen: one flipped exponent bit in j2's position reply, and the log showed
    # q 0.174 -> 0.338 -> 0.176 m within 40 ms on a 0.03 m/s joint, no error
    # counted. Bit 30 (the exponent's top bit) turns ~14 760 motor degrees
    # into ~1e-34: position = the homing offset, within the end stops.
    def flip(cycle: int, env: gym.Env) -> None:
        if cycle == 20:
            devices = env.unwrapped.backend.bus.devices
            devices[0x12] = FlipsNextReply(devices[0x12], bit=30)

    run = deploy(policy=ConstantPolicy([0.0, -0.5, 0.0, 0.0]), env=REACH, on_cycle=flip)
    assert run.error is None, run.output
    lines = read_log(run.log)
    cycles = [r for r in lines if r["type"] == "cycle"]
    q2 = [c["q"]["j2"] for c in cycles]
    assert max(abs(b - a) for a, b in itertools.pairwise(q2)) < 0.03 * 0.04 * 2  # never 2x the limit
    flipped = [c for c in cycles if "bus" in c and "j2" in c["bus"]]
    assert [c["cycle"] for c in flipped] == [20]
    assert flipped[0]["bus"]["j2"] == {"retries": 1, "implausible": 1}
    assert lines[-1]["bus"]["j2"]["errors"]["implausible"] == 1


@pytest.mark.parametrize("bad_from", [10, None], ids=["safe-stop", "completed"])
def test_the_joints_are_braked_to_rest_before_their_current_is_cut(
    deploy: Callable[..., Run], bad_from: int | None
) -> None:
    # Seen (a hostile test): j3 at 4.5 rad/s and j4 at 9.4 rad/s when the
    # policy returned NaN; the safe stop sent STOP and cut the currents a
    # millisecond later, and the unbraked arm coasted on: j3 0.9 rad, j1 (never
    # commanded) spun up to 2 rad/s by j3's momentum, 3.5 rad in 3 s. The
    # firmware's STOP ramps the speed down, which takes current.
    run = deploy(policy=ConstantPolicy([0.0, -0.5, 1.0, 1.0], bad_from=bad_from), env=REACH)
    assert (run.error is not None) == (bad_from is not None)
    assert_every_joint_disabled(run.summary)
    backend = run.backend
    before = backend.sim.joint_positions().copy()
    for _ in range(15):
        backend.step(0.2)
    travel = np.abs(backend.sim.joint_positions() - before)
    assert travel.max() < 1e-3, f"moved after the run ended: {travel}"


def test_deadman_guard_stops_when_a_joint_is_silent_over_50_ms(deploy: Callable[..., Run]) -> None:
    run = deploy(faults="latency_ms=30")
    assert run.error is not None and run.error.code == EXIT_SAFETY_STOP
    assert "deadman guard" in str(run.error) and "limit 50 ms" in str(run.error)
    summary = read_log(run.log)[-1]
    assert summary["stop_reason"] == "deadman" and summary["joint"] in ("j1", "j2", "j3", "j4")
    assert_every_joint_disabled(summary)


# ------------------------------------------------------ bus statistics, log
def test_recovered_bus_errors_appear_in_the_cycles_and_the_summary(deploy: Callable[..., Run]) -> None:
    run = deploy(faults="nack=0.02,short_read=0.01,corrupt=0.01")
    assert run.error is None, run.output
    records = read_log(run.log)
    summary = records[-1]
    per_record = [r["bus"] for r in records if r["type"] == "cycle" and "bus" in r]
    per_record += [r["joints"] for r in records if r["type"] == "bus"]
    assert per_record, "faults were injected, yet no cycle reports a retry or an error"
    bus_stats = run.backend.comm_stats()
    for name, totals in summary["bus"].items():
        logged = {k: sum(r.get(name, {}).get(k, 0) for r in per_record) for k in ("retries", "bus_errors")}
        # The log's per-cycle differences add up to the summary, which is what the driver counted.
        assert logged["retries"] == totals["retries"] == bus_stats[name].total_retries
        assert logged["bus_errors"] == totals["errors"]["bus"] == bus_stats[name].total_bus_errors
    # Every transaction on the bus is some joint's: the counts are per attempt, retries included.
    assert sum(t["transactions"] for t in summary["bus"].values()) == run.backend.bus.transactions
    assert sum(t["errors"]["bus"] for t in summary["bus"].values()) > 0
    assert "bus j1: transactions / retries / errors" in run.output


@pytest.mark.parametrize("full_for", [1, None], ids=["space-returns", "stays-full"])
def test_a_full_disk_stops_the_run_safely_and_leaves_no_torn_line(
    deploy: Callable[..., Run], full_for: int | None
) -> None:
    with run_log_disk_filling(5, full_for) as fill:
        run = deploy(on_cycle=fill)
    assert run.error is not None and run.error.code == EXIT_SAFETY_STOP
    assert "cannot write the run log" in str(run.error) and "No space left on device" in str(run.error)
    assert_every_joint_disabled(run.summary)
    records = read_log(run.log)  # every line parses: the half-written ones were cut off again
    assert [r["cycle"] for r in records if r["type"] == "cycle"] == list(range(5))
    if full_for == 1:
        assert records[-2]["type"] == "stop" and records[-2]["reason"] == "log_error"
        assert records[-1]["type"] == "summary" and records[-1]["log_error"]
        assert records[-1]["log_records_lost"] == ["cycle 5"]
        assert "log incomplete: 1 record(s) not written: cycle 5 (No space left on device)" in run.output
    else:
        assert records[-1]["type"] == "cycle"
        assert "log incomplete: 3 record(s) not written: cycle 5, stop, summary" in run.output


def test_a_trace_the_disk_cannot_take_stays_whole_and_the_run_goes_on(
    deploy: Callable[..., Run], tmp_path: Path
) -> None:
    # Seen (a hostile test): with --record on a full disk every transaction raised
    # ENOSPC into the driver, so the deploy stopped on "communication error ...
    # Check wiring", named every joint "no answer, ... cut the power" (their
    # currents were 0), and left half a line that `bioscara replay` refused.
    trace = tmp_path / "trace.jsonl"
    writes = [0]

    def filling(fd: int, data: Any) -> int:
        writes[0] += 1
        if writes[0] < 500:
            return os.write(fd, data)
        if writes[0] == 500:
            os.write(fd, bytes(data)[: len(data) // 2])  # what a full disk takes before it refuses
        raise OSError(errno.ENOSPC, os.strerror(errno.ENOSPC))

    with pytest.MonkeyPatch.context() as mp:
        mp.setattr("bioscara_gym.hardware.recording._os_write", filling)
        run = deploy(record=trace)
    assert run.error is None, run.output
    assert_every_joint_disabled(run.summary)
    # the header was write 1: transactions 0-497 recorded, the rest not
    lines = [json.loads(line) for line in trace.read_text(encoding="utf-8").splitlines()]
    assert [d["type"] for d in lines] == ["header"] + ["tx"] * 498
    assert run.summary["trace_error"] == (
        f"cannot write the bus trace {trace}: No space left on device; "
        "transactions from 498 on were not recorded"
    )
    assert "trace      incomplete: cannot write the bus trace" in run.output


def test_every_bus_event_is_in_a_cycle_or_a_phase_record(deploy: Callable[..., Run]) -> None:
    # Seen: retries during deactivate appeared only in the summary's totals (22 + 11 logged of 34).
    def nack_from_the_last_cycle(cycle: int, env: gym.Env) -> None:
        if cycle == 49:
            env.unwrapped.backend.bus.faults = FaultPlan(nack=0.15, seed=3)

    run = deploy(on_cycle=nack_from_the_last_cycle)
    assert run.error is None, run.output
    records = read_log(run.log)
    summary = records[-1]
    phases = {r["phase"] for r in records if r["type"] == "bus"}
    assert "deactivate" in phases
    logged = [r["bus"] for r in records if r["type"] == "cycle" and "bus" in r]
    logged += [r["joints"] for r in records if r["type"] == "bus"]
    for name, totals in summary["bus"].items():
        total = {"retries": totals["retries"], **{k: v for k, v in totals["errors"].items()}}
        counted = {
            key: sum(r.get(name, {}).get(field, 0) for r in logged)
            for key, field in (("retries", "retries"), ("bus", "bus_errors"), ("malformed", "malformed"))
        }
        assert counted == {k: total[k] for k in counted}, name


def test_the_gripper_width_is_called_saved_only_when_it_was(
    deploy: Callable[..., Run], tmp_path: Path, gripper_state_file: Path
) -> None:
    run = deploy()
    assert run.error is None, run.output
    assert f"gripper width 0.080 m saved to {gripper_state_file}" in run.output
    assert json.loads(gripper_state_file.read_text()) == {"width_m": 0.08}
    assert run.summary["gripper"]["saved_width_m"] == 0.08

    def disk_full(path: Any, width_m: float) -> None:
        raise OSError(errno.ENOSPC, os.strerror(errno.ENOSPC), str(path))

    with pytest.MonkeyPatch.context() as mp:
        mp.setattr("bioscara_gym.hardware.gripper.save_width", disk_full)
        run = deploy(log=tmp_path / "second.jsonl")
    assert run.error is None, run.output
    assert f"gripper width 0.080 m NOT saved to {gripper_state_file}: No space left on device" in run.output
    assert "warning: gripper: cannot save width 0.08 m" in run.output
    assert run.summary["gripper"]["saved_width_m"] is None


@pytest.mark.parametrize(
    ("override", "expected"),
    [({"env": "Bioscara-PickPlace-v1"}, "trained on Bioscara-Reach-v0"), ({"rate": 30.0}, "control_freq")],
    ids=["other-task", "other-rate"],
)
def test_metadata_mismatch_is_refused_before_any_bus_traffic(
    deploy: Callable[..., Run], sac_model: Path, override: dict[str, Any], expected: str
) -> None:
    run = deploy(model=sac_model, **override)
    assert run.error is not None and run.error.code == EXIT_REFUSED
    assert "refused" in str(run.error) and expected in str(run.error)
    assert run.backend.bus.transactions == 0
    assert not run.log.exists()


class TorchRefusesNaN:
    """Raises what torch raises for an actor whose weights hold NaN (two lines, as seen)."""

    def __call__(self, obs: dict[str, np.ndarray]) -> np.ndarray:
        raise ValueError(
            "Expected parameter loc (Tensor of shape (1, 4)) of distribution Normal(loc: torch.Size([1, 4]), "
            "scale: torch.Size([1, 4])) to satisfy the constraint Real(), but found invalid values:\n"
            "tensor([[nan, nan, nan, nan]])"
        )


@pytest.mark.parametrize(
    ("policy", "expected"),
    [
        (TorchRefusesNaN(), "fails on a probe observation (ValueError: Expected parameter loc"),
        (ConstantPolicy([0.1, np.inf, 0.0, 0.0]), "gives a non-finite action [0.1, inf, 0. , 0. ]"),
    ],
    ids=["raises", "inf"],
)
def test_a_policy_whose_numbers_are_broken_is_refused_in_the_check_phase(
    deploy: Callable[..., Run], sac_model: Path, policy: Any, expected: str
) -> None:
    # Seen: a model.zip whose actor weights hold NaN reached the arm check as a
    # two-line torch message and exit 1.
    run = deploy(policy=policy, metadata=read_metadata(sac_model))
    assert run.error is not None and run.error.code == EXIT_REFUSED
    message = str(run.error)
    assert message.startswith("refused: given policy ") and expected in message, message
    assert "\n" not in message and "nothing was sent to the arm" in message
    assert run.backend.bus.transactions == 0
    assert not run.log.exists()


def test_a_policy_that_fails_mid_run_is_a_one_line_safety_stop(deploy: Callable[..., Run]) -> None:
    calls = {"n": 0}

    def fails_at_cycle_3(obs: dict[str, np.ndarray]) -> np.ndarray:
        calls["n"] += 1
        if calls["n"] > 3:
            TorchRefusesNaN()(obs)
        return np.zeros(4, dtype=np.float32)

    run = deploy(policy=fails_at_cycle_3)
    assert run.error is not None and run.error.code == EXIT_SAFETY_STOP
    assert "the policy failed to act (ValueError: Expected parameter loc" in str(run.error)
    assert "\n" not in str(run.error)
    summary = read_log(run.log)[-1]
    assert summary["stop_reason"] == "nan_action" and summary["cycles"] == 3
    assert_every_joint_disabled(summary)


# ------------------------------------------------------------------ signals
def test_signal_guard_raises_at_once_outside_the_control_loop() -> None:
    with SignalGuard(), pytest.raises(Interrupted) as caught:
        os.kill(os.getpid(), signal.SIGTERM)
        time.sleep(1)  # not reached: the handler raises
    assert caught.value.exit_code == 143


def test_signal_guard_defers_inside_a_cycle_until_the_next_check() -> None:
    with SignalGuard() as guard:
        with guard.deferred():
            os.kill(os.getpid(), signal.SIGINT)
            finished_cycle = True
        assert finished_cycle and guard.pending == signal.SIGINT
        with pytest.raises(Interrupted):
            guard.check()


def test_sigint_during_homing_disables_every_joint(
    deploy: Callable[..., Run], monkeypatch: pytest.MonkeyPatch, tmp_path: Path
) -> None:
    from bioscara_gym.hardware.arm import Arm

    home = Arm.home

    def interrupted_home(self: Arm, *args: Any, **kwargs: Any) -> None:
        os.kill(os.getpid(), signal.SIGINT)
        home(self, *args, **kwargs)

    monkeypatch.setattr(Arm, "home", interrupted_home)
    with pytest.raises(Interrupted):
        deploy()
    summary = read_log(tmp_path / "run.jsonl")[-1]
    assert summary["stop_reason"] == "interrupted" and summary["exit_code"] == 130
    assert_every_joint_disabled(summary)


@pytest.mark.parametrize(
    ("signum", "code"), [(signal.SIGINT, 130), (signal.SIGTERM, 143)], ids=["INT", "TERM"]
)
def test_signal_to_a_running_deploy_disables_every_joint(tmp_path: Path, signum: int, code: int) -> None:
    log = tmp_path / "run.jsonl"
    cmd = [sys.executable, "-m", "bioscara_gym.cli", "deploy", "--expert", "--env", REACH,
           "--backend", "emulated", "--episodes", "1000", "--log", str(log)]  # fmt: skip
    proc = subprocess.Popen(
        cmd, cwd=tmp_path, stdout=subprocess.PIPE, stderr=subprocess.PIPE, text=True,
        env={**os.environ, "MUJOCO_GL": "egl"},
    )  # fmt: skip
    try:
        deadline = time.monotonic() + 60
        while not (log.exists() and log.read_text(encoding="utf-8").count('"type":"cycle"') >= 20):
            assert proc.poll() is None, proc.communicate()
            assert time.monotonic() < deadline, "deploy never got going"
            time.sleep(0.05)
        proc.send_signal(signum)
        out, err = proc.communicate(timeout=60)
    finally:
        if proc.poll() is None:
            proc.kill()
    assert proc.returncode == code, err
    assert "arm disabled" in out
    lines = read_log(log)
    summary = lines[-1]
    assert summary["type"] == "summary" and summary["exit_code"] == code
    assert summary["cycles"] == sum(r["type"] == "cycle" for r in lines)
    assert_every_joint_disabled(summary)


# --------------------------------------------------------------------- ONNX
def test_onnx_actions_equal_sb3_predict(sac_model: Path, onnx_file: Path) -> None:
    from bioscara_gym.training.algos import load_model
    from bioscara_gym.training.export import OnnxPolicy

    model, _ = load_model(sac_model)
    policy = OnnxPolicy(onnx_file)
    env = gym.make(REACH, control_mode="cartesian", reward_type="log")
    rng = np.random.default_rng(1)
    observations = []
    obs, _ = env.reset(seed=0)
    for _ in range(100):
        observations.append(obs)
        obs, *_ = env.step(env.action_space.sample())
    env.close()
    observations += [{k: rng.normal(0, 2, v.shape) for k, v in obs.items()} for _ in range(100)]
    for o in observations:
        want, _ = model.predict(o, deterministic=True)
        np.testing.assert_allclose(policy(o), want, atol=1e-5)


def test_onnx_file_carries_the_training_metadata(sac_model: Path, onnx_file: Path) -> None:
    from bioscara_gym.training.export import OnnxPolicy

    assert OnnxPolicy(onnx_file).metadata == read_metadata(sac_model)


def test_an_exported_policy_gets_the_mode_open_would_and_keeps_a_replaced_ones(
    sac_model: Path, tmp_path: Path
) -> None:
    # Seen: every ONNX file came out 0600 (tempfile's), also over a 0644 one.
    from bioscara_gym.training.export import export_onnx

    mask = os.umask(0o022)
    try:
        fresh = export_onnx(sac_model, tmp_path / "new.onnx", check_samples=0).path
        kept = tmp_path / "kept.onnx"
        kept.write_bytes(b"old")
        kept.chmod(0o640)
        export_onnx(sac_model, kept, check_samples=0)
    finally:
        os.umask(mask)
    assert stat.S_IMODE(fresh.stat().st_mode) == 0o644
    assert stat.S_IMODE(kept.stat().st_mode) == 0o640 and kept.read_bytes() != b"old"


def _policy_copy(sac_model: Path, tmp_path: Path) -> Path:
    """A copy of the trained policy's folder under ``tmp_path``; returns its ``model.zip``."""
    folder = tmp_path / "policy"
    shutil.copytree(sac_model.parent, folder)
    return folder / sac_model.name


def test_export_refuses_a_hand_edited_metadata_the_model_was_not_saved_with(
    sac_model: Path, tmp_path: Path, capsys: pytest.CaptureFixture[str]
) -> None:
    # Seen: final_eval.success_rate 0.99 -> 1.0 and net_arch edited by hand went into the ONNX file.
    model = _policy_copy(sac_model, tmp_path)
    metadata_path = model.parent / "metadata.json"
    metadata = json.loads(metadata_path.read_text(encoding="utf-8"))
    metadata["final_eval"] = {**metadata.get("final_eval", {}), "success_rate": 1.0}
    metadata_path.write_text(json.dumps(metadata), encoding="utf-8")
    assert main(["export", "--model", str(model), "--onnx", str(tmp_path / "p.onnx"), "--check", "0"]) == 2
    error = capsys.readouterr().err.strip()
    assert "\n" not in error and error.startswith(f"bioscara export: error: {metadata_path} says final_eval")
    assert "was metadata.json edited or swapped? Refused" in error
    assert not (tmp_path / "p.onnx").exists()


def test_export_refuses_a_model_without_its_own_copy_of_the_metadata(
    sac_model: Path, tmp_path: Path, capsys: pytest.CaptureFixture[str]
) -> None:
    model = _policy_copy(sac_model, tmp_path)
    with zipfile.ZipFile(sac_model) as src, zipfile.ZipFile(model, "w") as dst:
        for item in src.infolist():
            if item.filename != "bioscara_metadata.json":
                dst.writestr(item, src.read(item.filename))
    assert main(["export", "--model", str(model), "--onnx", str(tmp_path / "p.onnx"), "--check", "0"]) == 2
    assert capsys.readouterr().err.strip() == (
        f"bioscara export: error: {model} carries no copy of its training metadata (saved by an older "
        "bioscara-gym), so metadata.json beside it cannot be checked; retrain it to deploy it"
    )


def test_a_models_copy_of_the_metadata_is_read_to_1_mb_only(
    sac_model: Path, tmp_path: Path, monkeypatch: pytest.MonkeyPatch
) -> None:
    # Seen: a 2 MB model.zip whose copy unpacks to 2 GB was read whole: MemoryError, a traceback.
    from bioscara_gym.errors import MetadataError
    from bioscara_gym.training.metadata import read_embedded_metadata

    model = _policy_copy(sac_model, tmp_path)
    with zipfile.ZipFile(sac_model) as src, zipfile.ZipFile(model, "w", zipfile.ZIP_DEFLATED) as dst:
        for item in src.infolist():
            if item.filename != "bioscara_metadata.json":
                dst.writestr(item, src.read(item.filename))
        dst.writestr("bioscara_metadata.json", b" " * (8 * 1024 * 1024))
    read_sizes: list[int] = []
    read = zipfile.ZipExtFile.read

    def counted(self: zipfile.ZipExtFile, n: int = -1) -> bytes:
        data = read(self, n)
        read_sizes.append(len(data))
        return data

    monkeypatch.setattr(zipfile.ZipExtFile, "read", counted)
    with pytest.raises(MetadataError) as refused:
        read_embedded_metadata(model)
    assert str(refused.value) == (
        f"{model}: its copy of the training metadata is over 1048576 bytes (ours are a few kB); not read"
    )
    assert sum(read_sizes) == 1048577  # the limit and one byte more, not the whole member


def test_an_interrupted_export_leaves_no_folder_it_made(
    sac_model: Path, tmp_path: Path, monkeypatch: pytest.MonkeyPatch
) -> None:
    # Seen: SIGTERM during export --onnx nd3/a/b/x.onnx: exit 143 with nd3/a/b left, empty.
    from bioscara_gym.training import export

    def interrupted(*args: Any) -> None:
        raise KeyboardInterrupt

    monkeypatch.setattr(export, "_write_graph", interrupted)
    (tmp_path / "nd3").mkdir()
    with pytest.raises(KeyboardInterrupt):
        export.export_onnx(sac_model, tmp_path / "nd3" / "a" / "b" / "x.onnx", check_samples=0)
    assert list((tmp_path / "nd3").iterdir()) == []


def test_deploy_runs_an_onnx_policy_without_torch(tmp_path: Path, onnx_file: Path) -> None:
    log = tmp_path / "run.jsonl"
    script = (
        "import sys; sys.modules['torch'] = None; sys.modules['stable_baselines3'] = None\n"
        "from bioscara_gym.cli import main\n"
        f"sys.exit(main(['deploy', '--onnx', {str(onnx_file)!r}, '--backend', 'emulated', "
        f"'--log', {str(log)!r}]))\n"
    )
    proc = subprocess.run(
        [sys.executable, "-c", script], cwd=tmp_path, capture_output=True, text=True, timeout=120,
        env={**os.environ, "MUJOCO_GL": "egl"},
    )  # fmt: skip
    assert proc.returncode == 0, proc.stderr
    summary = read_log(log)[-1]
    assert summary["stop_reason"] == "completed" and summary["cycles"] == 50


def test_deploy_onnx_on_mock_imports_no_torch_sb3_or_mujoco(tmp_path: Path, onnx_file: Path) -> None:
    log = tmp_path / "run.jsonl"
    heavy = ("torch", "stable_baselines3", "mujoco")
    script = textwrap.dedent(
        f"""
        import sys

        class _Blocked:
            def find_spec(self, name, path=None, target=None):
                if name.split(".")[0] in {heavy!r}:
                    raise ModuleNotFoundError(f"No module named {{name!r}} (blocked)", name=name)
                return None

        sys.meta_path.insert(0, _Blocked())
        from bioscara_gym.cli import main

        code = main(["deploy", "--onnx", {str(onnx_file)!r}, "--backend", "mock", "--episodes", "1",
                     "--log", {str(log)!r}])
        print("loaded:", sorted(m for m in sys.modules if m.split(".")[0] in {heavy!r}))
        sys.exit(code)
        """
    )
    proc = subprocess.run(
        [sys.executable, "-c", script], cwd=tmp_path, capture_output=True, text=True, timeout=120
    )
    assert proc.returncode == 0, proc.stderr
    assert "loaded: []" in proc.stdout
    summary = read_log(log)[-1]
    assert summary["stop_reason"] == "completed" and summary["cycles"] == 50
    assert_every_joint_disabled(summary)


# ------------------------------------------------------------- one owner of the arm
LIFECYCLE = ("configure", "activate", "home", "deactivate", "cleanup", "shutdown")


@pytest.mark.parametrize("nack_from", [None, 3], ids=["completed", "safe-stop"])
def test_the_env_alone_brings_the_arm_up_and_shuts_it_down(
    deploy: Callable[..., Run], monkeypatch: pytest.MonkeyPatch, nack_from: int | None
) -> None:
    """Deploy asks the env (bring_up, shut_down, safe_stop); no deploy module calls the Arm's lifecycle."""
    calls: list[tuple[str, str]] = []
    for name in LIFECYCLE:
        original = getattr(Arm, name)

        def recorded(self: Arm, *args: Any, _name: str = name, _orig: Any = original, **kwargs: Any) -> Any:
            caller = sys._getframe(1).f_globals.get("__name__", "")
            calls.append((_name, caller))
            return _orig(self, *args, **kwargs)

        monkeypatch.setattr(Arm, name, recorded)

    def lose_the_bus(cycle: int, env: gym.Env) -> None:
        if nack_from is not None and cycle == nack_from:
            env.unwrapped.backend.bus.faults = FaultPlan(nack=1.0)

    run = deploy(episodes=1, on_cycle=lose_the_bus)
    assert (run.error is None) == (nack_from is None)
    callers = {caller for _, caller in calls}
    assert not any(c.startswith("bioscara_gym.training") for c in callers), calls
    assert callers <= {"bioscara_gym.hardware.arm", "bioscara_gym.hardware.safety"}, calls
    assert [n for n, _ in calls].count("shutdown") == 1  # finalized once, by one owner
    assert run.summary["arm_state"] == "finalized"
