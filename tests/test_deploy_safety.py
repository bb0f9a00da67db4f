"""The two halves of deploy's safety layer, on their own.

The arm-facing half (``bioscara_gym.hardware.safety``: deadman guard, safe
stop, final state) against a backend whose joints report their exchanges,
and the policy-facing half (``bioscara_gym.training.deploy_safety``) against
an env that raises driver errors. Full deployments are in test_deploy.py.
"""

from __future__ import annotations

from pathlib import Path
from typing import Any

import numpy as np
import pytest
from gymnasium import spaces
from rigs import run_blocked

from bioscara_gym.hardware.arm import Arm
from bioscara_gym.hardware.backends import Backend, make_backend
from bioscara_gym.hardware.clock import ManualClock
from bioscara_gym.hardware.emulated_bus import FaultPlan
from bioscara_gym.hardware.errors import CommError, DeadmanError, NotEnabledError, StalledError
from bioscara_gym.hardware.mock import MockJoint
from bioscara_gym.hardware.registers import DEADMAN_S, Flag, Reg
from bioscara_gym.hardware.safety import DeadmanGuard, final_state, safe_stop
from bioscara_gym.training.deploy_safety import SafetyLayer, SafetyStop, StopReason, stop_for

ROOT = Path(__file__).resolve().parents[1]


# ------------------------------------------------------- a listened-to backend
class FlagsBackend(Backend):
    """A backend that can read its devices' flags without a transaction."""

    name = "mock"

    def close(self) -> None:
        """Nothing to release."""

    def device_flags(self, name: str) -> Flag | None:
        joint = self.joints[name]
        return Flag(joint.device_flags) if isinstance(joint, MockJoint) else None


@pytest.fixture
def listened() -> Backend:
    mock = make_backend("mock")
    clock = ManualClock()
    joints = {n: MockJoint(n, clock=clock) for n in ("j1", "j2")}
    return FlagsBackend(mock.config, joints, mock.gripper, clock)


# ------------------------------------------------------------- deadman guard
def test_deadman_guard_trips_on_the_joint_silent_too_long(listened: Backend) -> None:
    clock, j1, j2 = listened.clock, listened.joints["j1"], listened.joints["j2"]
    j1.init()
    j2.init()
    guard = DeadmanGuard(listened)
    clock.sleep(0.03)
    j1.get_velocity()
    j2.get_velocity()
    assert guard.check() == pytest.approx(0.03)
    clock.sleep(0.03)
    j1.get_velocity()
    clock.sleep(0.03)
    with pytest.raises(DeadmanError) as trip:
        guard.check()
    assert trip.value.joint == "j2" and trip.value.limit_s == DEADMAN_S
    assert f"limit {DEADMAN_S * 1000:.0f} ms" in str(trip.value)
    stop = stop_for(trip.value)  # what deploy stops with
    assert stop is not None and stop.reason is StopReason.DEADMAN and stop.joint == "j2"


def test_deadman_guard_sees_a_gap_between_exchanges_within_a_cycle(listened: Backend) -> None:
    clock, j1, j2 = listened.clock, listened.joints["j1"], listened.joints["j2"]
    j1.init()
    j2.init()
    guard = DeadmanGuard(listened)
    clock.sleep(DEADMAN_S + 0.01)
    j1.get_velocity()
    j2.get_velocity()  # both just talked to, but each was silent over the deadman before
    assert guard.silences()["j1"] == pytest.approx(DEADMAN_S + 0.01)
    with pytest.raises(DeadmanError, match="deadman guard"):
        guard.check()


def test_deadman_guard_listens_through_the_joints_and_detaches(listened: Backend) -> None:
    guard = DeadmanGuard(listened)
    j1 = listened.joints["j1"]
    j1.init()
    listened.clock.sleep(0.03)
    j1.get_flags()  # heard: the silence starts again
    assert guard.silences()["j1"] == pytest.approx(0.03)
    guard.detach()
    listened.clock.sleep(0.03)
    j1.get_flags()  # no longer heard: the silence goes on
    listened.clock.sleep(0.01)
    assert guard.silences()["j1"] == pytest.approx(0.04)


def test_deadman_guard_on_the_emulated_bus_gives_the_bus_back(gripper_state_file: Path) -> None:
    backend = make_backend("emulated", state_file=gripper_state_file)
    buses = {n: j.bus for n, j in backend.joints.items()}
    guard = DeadmanGuard(backend)
    backend.joints["j1"].init()
    assert guard.silences()["j1"] < DEADMAN_S
    guard.detach()
    assert {n: j.bus for n, j in backend.joints.items()} == buses
    backend.close()


# ------------------------------------------------------ safe stop, final state
def test_safe_stop_disables_every_joint_and_final_state_reads_the_devices(listened: Backend) -> None:
    arm = Arm(listened)
    arm.configure()
    arm.activate()
    report = safe_stop(arm)
    assert report.problems == [] and report.not_confirmed == []
    state = final_state(listened)
    assert {s["source"] for s in state.values()} == {"mock device"}
    assert all(not s["enabled"] and "NOT_ENABLED" in s["flag_names"] for s in state.values())


def test_final_state_falls_back_to_the_last_reply_where_the_device_cannot_be_seen(listened: Backend) -> None:
    listened.joints["j3"] = MockJoint("j3")
    listened.device_flags = lambda name: None  # type: ignore[method-assign]
    state = final_state(listened)
    assert {s["source"] for s in state.values()} == {"last reply"}


def test_hardware_safety_imports_no_gymnasium_mujoco_or_torch() -> None:
    heavy = ("gymnasium", "mujoco", "torch", "stable_baselines3")
    result = run_blocked(
        blocked=heavy,
        code=f"""
        from bioscara_gym.hardware.safety import DeadmanGuard, final_state, safe_stop
        print(sorted(m for m in sys.modules if m.split(".")[0] in {heavy!r}))
        """,
    )
    assert result.returncode == 0, result.stderr
    assert result.stdout.strip() == "[]"


# --------------------------------------------------------------- policy half
class RaisingEnv:
    """Just enough of an env for SafetyLayer: ``step`` raises the given error."""

    def __init__(self, backend: Backend, error: Exception) -> None:
        self.arm = Arm(backend)
        self.action_space = spaces.Box(-1.0, 1.0, shape=(2,), dtype=np.float32)
        self.error = error

    def step(self, action: np.ndarray) -> Any:
        raise self.error


@pytest.mark.parametrize(
    ("error", "reason"),
    [
        (StalledError("stalled", joint="j2", register=Reg.SETRPM), StopReason.STALL),
        (CommError("no reply", joint="j2", register=Reg.SETRPM), StopReason.COMM_ERROR),
        (NotEnabledError("disabled", joint="j2"), StopReason.JOINT_ERROR),
    ],
    ids=["stall", "comm", "joint"],
)
def test_safety_layer_names_the_joint_the_driver_error_carries(
    listened: Backend, error: Exception, reason: StopReason
) -> None:
    layer = SafetyLayer(env := RaisingEnv(listened, error), env.arm, DeadmanGuard(listened))
    with pytest.raises(SafetyStop) as stop:
        layer.step(np.zeros(2))
    assert stop.value.reason is reason and stop.value.joint == "j2"


def test_safety_layer_clamps_and_refuses_non_finite_actions(listened: Backend) -> None:
    layer = SafetyLayer(env := RaisingEnv(listened, RuntimeError()), env.arm, DeadmanGuard(listened))
    clipped, clamped = layer.filter_action([2.0, -0.5])
    assert clamped and clipped.tolist() == [1.0, -0.5]
    with pytest.raises(SafetyStop) as stop:
        layer.filter_action([np.inf, 0.0])
    assert stop.value.reason is StopReason.NAN_ACTION


def test_safe_stop_cuts_the_current_of_a_joint_the_deadman_tripped(gripper_state_file: Path) -> None:
    # The firmware's deadman sets NOT_ENABLED but leaves drive and hold current on
    # (joint.ino: setRPM(0); notEnabled = 1): the flags alone must not end the stop.
    arm = Arm(make_backend("emulated", state_file=gripper_state_file))
    arm.configure()
    arm.activate()
    arm.home(["j4"])
    arm.claim("j4", "velocity")
    arm.set_command("j4", -0.5)
    arm.write()
    arm.backend.step(0.2)  # 200 ms of silence: the deadman trips
    core = arm.backend.sim.cores["j4"]  # type: ignore[union-attr]
    assert core.flags & Flag.NOT_ENABLED and core.drive_current == 20 and core.hold_current == 20
    report = safe_stop(arm)
    assert (core.drive_current, core.hold_current) == (0, 0)
    assert "j4" not in report.not_confirmed


def test_safe_stop_after_an_arm_error_reconnects_and_cuts_every_current(gripper_state_file: Path) -> None:
    arm = Arm(make_backend("emulated", state_file=gripper_state_file))
    arm.configure()
    arm.activate()
    arm.backend.bus.faults = FaultPlan(nack=1.0)  # type: ignore[attr-defined]
    with pytest.raises(CommError):
        arm.read()  # the arm's on-error transition: unconfigured, joints disconnected
    arm.backend.bus.faults = FaultPlan()  # type: ignore[attr-defined]
    report = safe_stop(arm)
    cores = arm.backend.sim.cores  # type: ignore[union-attr]
    assert [(cores[n].drive_current, cores[n].hold_current) for n in arm.names] == [(0, 0)] * 4
    assert report.not_confirmed == []


def test_safe_stop_reports_joints_it_could_not_reach(gripper_state_file: Path) -> None:
    arm = Arm(make_backend("emulated", state_file=gripper_state_file))
    arm.configure()
    arm.activate()
    arm.backend.bus.faults = FaultPlan(nack=1.0)  # type: ignore[attr-defined]
    report = safe_stop(arm)
    assert report.not_confirmed == ["j1", "j2", "j3", "j4"]
    assert any(p.startswith("j1: disable failed") for p in report.problems)


# ----------------------------------- rules a changed line above the drivers would break
def test_deadman_guard_keeps_the_long_gap_when_two_quick_exchanges_follow(listened: Backend) -> None:
    # The longest silence since the last check counts, not the last one.
    clock, j1, j2 = listened.clock, listened.joints["j1"], listened.joints["j2"]
    j1.init()
    j2.init()
    guard = DeadmanGuard(listened)
    j2.get_flags()
    clock.sleep(0.06)
    j1.get_flags()
    j2.get_flags()
    clock.sleep(0.001)
    j1.get_flags()
    j2.get_flags()
    assert guard.silences() == {"j1": pytest.approx(0.06), "j2": pytest.approx(0.06)}
    with pytest.raises(DeadmanError, match=r"went 60\.0 ms without a transaction"):
        guard.check()


def test_deadman_guard_check_starts_anew_and_restart_forgets(listened: Backend) -> None:
    clock, j1 = listened.clock, listened.joints["j1"]
    j1.init()
    guard = DeadmanGuard(listened, limit_s=0.05)
    clock.sleep(0.04)
    j1.get_flags()
    assert guard.check() == pytest.approx(0.04)
    clock.sleep(0.01)
    assert guard.check() == pytest.approx(0.05)  # j2, never talked to: exactly the limit, not more
    clock.sleep(0.02)
    guard.restart()
    assert guard.silences() == {"j1": 0.0, "j2": 0.0}


def test_a_stall_the_env_reports_without_a_joint_still_stops_in_words(listened: Backend) -> None:
    layer = SafetyLayer(env := RaisingEnv(listened, RuntimeError()), env.arm, DeadmanGuard(listened))
    with pytest.raises(SafetyStop) as stop:
        layer._check_stall({"stalled": True})
    assert stop.value.reason is StopReason.STALL and stop.value.joint is None
    assert str(stop.value).startswith("a joint (the env did not say which) stalled")
    layer._check_stall({"stalled": False, "stalled_joint": "j1"})  # no stall: nothing


def test_a_joint_disabled_mid_run_stops_only_while_the_arm_is_active(listened: Backend) -> None:
    env = RaisingEnv(listened, RuntimeError())
    layer = SafetyLayer(env, env.arm, DeadmanGuard(listened))
    arm = env.arm
    arm.configure()
    arm.activate()
    arm.read()
    layer._check_enabled()  # every joint enabled: nothing
    listened.joints["j2"].device_flags |= int(Flag.NOT_ENABLED)  # the firmware's deadman, a power dip
    arm.read()
    with pytest.raises(SafetyStop) as stop:
        layer._check_enabled()
    assert stop.value.reason is StopReason.JOINT_ERROR and stop.value.joint == "j2"
    assert "j2 reports not enabled while the arm is active" in str(stop.value)
    arm.deactivate()
    layer._check_enabled()  # inactive: a disabled joint is what deactivate leaves
