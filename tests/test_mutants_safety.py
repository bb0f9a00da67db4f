"""Tests that kill mutants mutmut found surviving in ``hardware/safety.py`` (docs/mutation.md).

On the mock backend (manual clock) and the emulated bus with every transfer
NACKed. Expected values are literals from the module's documented contract
(``safe_stop``, ``SafeStopReport``, ``flag_names``, ``final_state``),
docs/protocol.md's flag bits and the gripper's state file written here.
"""

from __future__ import annotations

import json
from pathlib import Path

import pytest
from rigs import MakeBackend

from bioscara_gym.hardware.arm import Arm
from bioscara_gym.hardware.backends import Backend, make_backend
from bioscara_gym.hardware.clock import ManualClock
from bioscara_gym.hardware.emulated_bus import FaultPlan
from bioscara_gym.hardware.errors import CommError, DeadmanError, JointError
from bioscara_gym.hardware.mock import MockJoint
from bioscara_gym.hardware.registers import Flag, Reg
from bioscara_gym.hardware.safety import DeadmanGuard, SafeStopReport, final_state, flag_names, safe_stop


class SeeingBackend(Backend):
    """A backend of no name :data:`FLAG_SOURCES` knows that can still look into its devices."""

    name = "bench"

    def close(self) -> None:
        """Nothing to release."""

    def device_flags(self, name: str) -> Flag | None:
        return Flag(self.joints[name].device_flags)  # type: ignore[attr-defined]


@pytest.fixture
def seeing() -> Backend:
    mock = make_backend("mock")
    clock = ManualClock()
    joints = {n: MockJoint(n, clock=clock) for n in ("j1", "j2")}
    return SeeingBackend(mock.config, joints, mock.gripper, clock)


@pytest.fixture
def width_file(gripper_state_file: Path) -> Path:
    """The gripper's state file holding 0.05 m (inside its 0.04-0.12 m limits, not its backup 0.08 m)."""
    gripper_state_file.write_text('{"width_m": 0.05}\n', encoding="utf-8")
    return gripper_state_file


# ------------------------------------------------------------- deadman guard
def test_deadman_guard_names_the_joint_silent_longest_not_the_last_name(seeing: Backend) -> None:
    clock, j1, j2 = seeing.clock, seeing.joints["j1"], seeing.joints["j2"]
    j1.init()
    j2.init()
    guard = DeadmanGuard(seeing, limit_s=0.05)
    clock.sleep(0.06)
    j2.get_flags()  # j2 just talked to (after 60 ms); j1 silent 60 ms and counting
    clock.sleep(0.01)
    j2.get_flags()
    with pytest.raises(DeadmanError) as trip:
        guard.check()
    assert trip.value.joint == "j1"


# ----------------------------------------------------------------- safe stop
def test_safe_stop_reports_the_gripper_width_and_that_it_was_saved(
    make_arm_backend: MakeBackend, width_file: Path
) -> None:
    arm = Arm(make_arm_backend("mock", state_file=width_file))
    arm.configure()
    arm.activate()
    assert arm.gripper.is_enabled
    report = safe_stop(arm)
    assert report.gripper_width_m == 0.05
    assert report.gripper_saved is True
    assert not arm.gripper.is_enabled
    assert json.loads(width_file.read_text(encoding="utf-8")) == {"width_m": 0.05}


def test_safe_stop_does_not_call_a_gripper_saved_that_was_never_driven(
    make_arm_backend: MakeBackend, width_file: Path
) -> None:
    arm = Arm(make_arm_backend("mock", state_file=width_file))
    arm.configure()  # initialized, never enabled: nothing to save
    report = safe_stop(arm)
    assert report.gripper_saved is False
    assert report.gripper_width_m == 0.08  # the backup initial width before the first enable
    assert report.problems == []


def test_safe_stop_after_the_on_error_transition_leaves_the_released_gripper_alone(
    make_arm_backend: MakeBackend, width_file: Path
) -> None:
    arm = Arm(make_arm_backend("mock", state_file=width_file))
    arm.configure()
    arm.activate()
    arm.recover()  # the gripper disabled and disconnected
    report = safe_stop(arm)
    assert report.problems == []
    assert not arm.gripper.is_initialized


def test_safe_stop_does_not_call_a_gripper_saved_whose_disable_failed(
    make_arm_backend: MakeBackend, width_file: Path, monkeypatch: pytest.MonkeyPatch
) -> None:
    arm = Arm(make_arm_backend("mock", state_file=width_file))
    arm.configure()
    arm.activate()

    def fail() -> None:
        raise OSError("PWM channel gone")

    monkeypatch.setattr(arm.gripper, "disable", fail)
    report = safe_stop(arm)
    assert report.gripper_saved is False
    # the arm's shutdown tries the gripper again, and says so too
    assert report.problems == ["gripper: disable failed: PWM channel gone", "shutdown: PWM channel gone"]


def test_safe_stop_reports_a_failed_shutdown(mock_arm: Arm, monkeypatch: pytest.MonkeyPatch) -> None:
    mock_arm.configure()
    mock_arm.activate()

    def fail() -> None:
        raise OSError("bus gone")

    monkeypatch.setattr(mock_arm, "shutdown", fail)
    report = safe_stop(mock_arm)
    assert report.problems == ["shutdown: bus gone"]
    assert report.not_confirmed == []


def test_safe_stop_says_no_answer_for_joints_that_nack_their_disable(gripper_state_file: Path) -> None:
    arm = Arm(make_backend("emulated", state_file=gripper_state_file))
    arm.configure()
    arm.activate()
    arm.backend.bus.faults = FaultPlan(nack=1.0)  # type: ignore[attr-defined]
    report = safe_stop(arm)
    assert report.why_not_confirmed == dict.fromkeys(("j1", "j2", "j3", "j4"), "no answer")
    assert report.warnings()[0] == "j1: no answer, still powered as far as we know: cut the power"


def test_safe_stop_keeps_every_step_problem_of_joints_it_cannot_reconnect(gripper_state_file: Path) -> None:
    arm = Arm(make_backend("emulated", state_file=gripper_state_file))
    arm.configure()
    arm.activate()
    arm.backend.bus.faults = FaultPlan(nack=1.0)  # type: ignore[attr-defined]
    with pytest.raises(CommError):
        arm.read()  # the on-error transition disconnects every joint
    report = safe_stop(arm)  # still NACKed: no joint can be connected again
    reconnect = [p for p in report.problems if "not reachable, its current could not be cut: " in p]
    assert [p.split(":")[0] for p in reconnect] == ["j1", "j2", "j3", "j4"]
    assert report.not_confirmed == ["j1", "j2", "j3", "j4"]
    assert report.why_not_confirmed == dict.fromkeys(("j1", "j2", "j3", "j4"), "no answer")


def test_a_disable_with_one_nacked_and_one_malformed_step_is_no_valid_answer(
    mock_arm: Arm, monkeypatch: pytest.MonkeyPatch
) -> None:
    # BaseJoint.disable's contract: more than one failed step raises one error
    # (from the first) whose `failures` lists every (step, error).
    mock_arm.configure()
    mock_arm.activate()
    nack = CommError("no reply", joint="j1", register=Reg.STOP)
    nack.__cause__ = OSError(121, "Remote I/O error")
    malformed = CommError("reply flags byte has reserved bits set", joint="j1", register=Reg.SETCURRENT)
    both = CommError("disable incomplete, 2 of 4 steps failed", joint="j1", register=Reg.STOP)
    both.__cause__ = nack
    both.failures = [("STOP", nack), ("SETCURRENT 0", malformed)]  # type: ignore[attr-defined]

    def fail() -> None:
        raise both

    monkeypatch.setattr(mock_arm.joints["j1"], "disable", fail)
    report = safe_stop(mock_arm)
    assert report.not_confirmed == ["j1"]
    assert report.why_not_confirmed == {"j1": "no valid answer"}


def test_a_report_without_a_reason_says_disable_not_acknowledged() -> None:
    report = SafeStopReport(problems=[], not_confirmed=["j2"], gripper_width_m=None, gripper_saved=False)
    (line,) = report.warnings()
    assert line == "j2: disable not acknowledged, still powered as far as we know: cut the power"


def test_a_disable_failure_not_from_the_bus_is_named_with_the_error(
    mock_arm: Arm, monkeypatch: pytest.MonkeyPatch
) -> None:
    mock_arm.configure()
    mock_arm.activate()

    def fail() -> None:
        raise JointError("driver fault", joint="j3")

    monkeypatch.setattr(mock_arm.joints["j3"], "disable", fail)
    report = safe_stop(mock_arm)
    assert report.why_not_confirmed["j3"].startswith("disable not acknowledged (")
    assert "driver fault" in report.why_not_confirmed["j3"]


# --------------------------------------------------------------- final state
@pytest.mark.parametrize(
    ("flags", "names"),
    [
        (0, "-"),
        (12, "NOT_HOMED|NOT_ENABLED"),
        (0x01, "STALL"),
        (0x0F, "STALL|BUSY|NOT_HOMED|NOT_ENABLED"),
    ],
)
def test_flag_names_as_documented(flags: int, names: str) -> None:
    assert flag_names(flags) == names


def test_final_state_of_a_backend_it_has_no_source_name_for_says_device(seeing: Backend) -> None:
    state = final_state(seeing)
    assert {s["source"] for s in state.values()} == {"device"}


def test_final_state_calls_an_enabled_joint_enabled(mock_arm: Arm) -> None:
    mock_arm.configure()
    mock_arm.activate()
    state = final_state(mock_arm.backend)
    assert state["j1"]["enabled"] is True
    assert state["j1"]["flag_names"] == "NOT_HOMED"  # enabled, not homed yet


def test_final_state_reads_drive_and_hold_current_from_the_emulator(gripper_state_file: Path) -> None:
    arm = Arm(make_backend("emulated", state_file=gripper_state_file))
    arm.configure()
    arm.activate()
    arm.joints["j1"].set_drive_current(30)
    arm.joints["j1"].set_hold_current(10)
    state = final_state(arm.backend)
    assert (state["j1"]["drive_current"], state["j1"]["hold_current"]) == (30, 10)
    assert state["j1"]["source"] == "emulator"
    arm.shutdown()
