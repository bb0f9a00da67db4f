"""Per-device control of the arm (docs/arm.md, "The arm layer"): the gripper, enable/disable and attach.

Covers the gripper (enabled at its saved width, the width saved on deactivate and shutdown,
set_gripper clamping and refusing non-finite widths), enabling and disabling a subset of the
joints and the gripper by name, and attach, which takes over devices an earlier process left
enabled without sending them anything.
"""

from __future__ import annotations

import json
import math
from pathlib import Path

import pytest
from conftest import ARM_BACKENDS
from rigs import CONFIG, DT, NAMES, MakeBackend, enable_and_home_elsewhere, motor_rate_deg, spy, start_homing

from bioscara_gym.hardware.arm import Arm, ArmStateError, CommandMode, Lifecycle
from bioscara_gym.hardware.backends import EmulatedBackend
from bioscara_gym.hardware.emulated_bus import FaultPlan
from bioscara_gym.hardware.errors import (
    CommError,
    InvalidArgumentError,
)
from bioscara_gym.hardware.gripper import GripperStateWarning
from bioscara_gym.hardware.registers import Reg

# ------------------------------------------------------------------ gripper


def _saved_width(path: Path) -> float:
    return json.loads(path.read_text(encoding="utf-8"))["width_m"]


@pytest.mark.parametrize("name", ARM_BACKENDS)
def test_activate_enables_the_gripper_at_the_saved_width(
    make_arm_backend: MakeBackend, gripper_state_file: Path, name: str
) -> None:
    gripper_state_file.write_text('{"width_m": 0.1}\n', encoding="utf-8")
    arm = Arm(make_arm_backend(name))
    arm.configure()
    arm.activate()
    assert arm.gripper.is_enabled
    assert arm.gripper.get_position() == 0.1
    assert arm.gripper_command == 0.1


def test_activate_without_a_saved_width_uses_the_backup_width(
    make_arm_backend: MakeBackend, tmp_path: Path
) -> None:
    arm = Arm(make_arm_backend("mock", state_file=tmp_path / "absent.json"))
    arm.configure()
    with pytest.warns(GripperStateWarning, match="does not exist"):
        arm.activate()
    assert arm.gripper_command == CONFIG.gripper.backup_init_pos


def test_deactivate_saves_the_gripper_width(active_arm: Arm, gripper_state_file: Path) -> None:
    active_arm.set_gripper(0.05)
    active_arm.write()
    active_arm.deactivate()
    assert not active_arm.gripper.is_enabled
    assert _saved_width(gripper_state_file) == 0.05


def test_shutdown_saves_the_gripper_width(active_arm: Arm, gripper_state_file: Path) -> None:
    active_arm.set_gripper(0.11)
    active_arm.write()
    active_arm.shutdown()
    assert _saved_width(gripper_state_file) == 0.11


def test_set_gripper_is_sent_on_write(active_arm: Arm) -> None:
    active_arm.set_gripper(0.06)
    assert active_arm.gripper.get_position() == 0.08
    active_arm.write()
    assert active_arm.gripper.get_position() == 0.06


@pytest.mark.parametrize(("width", "clamped"), [(1.0, 0.12), (0.0, 0.04), (-0.5, 0.04), (0.07, 0.07)])
def test_set_gripper_clamps_to_the_width_limits(active_arm: Arm, width: float, clamped: float) -> None:
    active_arm.set_gripper(width)
    assert active_arm.gripper_command == clamped
    active_arm.write()
    assert active_arm.gripper.get_position() == clamped


@pytest.mark.parametrize("width", [math.nan, math.inf])
def test_set_gripper_refuses_a_non_finite_width(mock_arm: Arm, width: float) -> None:
    with pytest.raises(InvalidArgumentError, match=f"gripper: width {width} must be finite"):
        mock_arm.set_gripper(width)


# ------------------------------------------------ per-device enable / disable


def test_enable_a_subset_enables_only_those_joints_and_goes_active(arm: Arm) -> None:
    arm.configure()
    arm.enable(["j1", "j3"])
    assert arm.state is Lifecycle.ACTIVE
    assert [arm.joints[n].is_enabled() for n in NAMES] == [True, False, True, False]
    assert not arm.gripper.is_enabled
    assert set(arm.modes.values()) == {CommandMode.NONE}


def test_enable_sends_what_activate_sends_to_each_named_joint_only(
    mock_arm: Arm, monkeypatch: pytest.MonkeyPatch
) -> None:
    mock_arm.configure()
    traffic = spy(monkeypatch, mock_arm)
    mock_arm.enable(["j2"])
    cfg = CONFIG.joint("j2")
    sent = [(joint, reg) for joint, reg, value in traffic.log if value is not None]
    assert sent == [
        ("j2", Reg.SETUP),
        ("j2", Reg.ENABLESTALLGUARD),
        ("j2", Reg.SETMAXVELOCITY),
        ("j2", Reg.SETMAXACCELERATION),
    ]
    assert traffic.values("j2", Reg.ENABLESTALLGUARD) == [cfg.stall_threshold]
    assert traffic.values("j2", Reg.SETMAXACCELERATION) == [
        pytest.approx(motor_rate_deg("j2", cfg.max_acceleration))
    ]


def test_enable_gripper_by_name_drives_it_at_the_saved_width(mock_arm: Arm) -> None:
    mock_arm.configure()
    mock_arm.enable(["gripper"])
    assert mock_arm.state is Lifecycle.ACTIVE
    assert mock_arm.gripper.is_enabled
    assert mock_arm.gripper_command == 0.08
    assert not any(j.is_enabled() for j in mock_arm.joints.values())


def test_enable_releases_the_joints_interfaces_and_holds_the_measured_position(
    homed_mock_arm: Arm,
) -> None:
    arm = homed_mock_arm
    arm.claim("j1", "position")
    arm.set_command("j1", 0.5)
    arm.claim("j2", "velocity")
    arm.enable(["j1"])
    assert arm.modes["j1"] is CommandMode.NONE
    assert arm.commands["j1"] == arm.joint_states["j1"].position
    assert arm.modes["j2"] is CommandMode.VELOCITY


def test_enable_of_nothing_leaves_an_inactive_arm_inactive(mock_arm: Arm) -> None:
    mock_arm.configure()
    mock_arm.enable([])
    assert mock_arm.state is Lifecycle.INACTIVE


def test_enable_refuses_an_unknown_name_listing_joints_and_gripper(mock_arm: Arm) -> None:
    mock_arm.configure()
    with pytest.raises(InvalidArgumentError, match="unknown joint 'j9'; known: j1, j2, j3, j4, gripper"):
        mock_arm.enable(["j1", "j9"])
    assert not mock_arm.joints["j1"].is_enabled()


def test_enable_is_refused_while_the_arm_homes_the_joint(active_arm: Arm) -> None:
    start_homing(active_arm, "j1", 0.03)
    with pytest.raises(ArmStateError, match=r"j1: a homing .* is running and enabling would hang it"):
        active_arm.enable(["j1"])
    assert active_arm.joints["j1"].is_busy()


def test_enable_is_refused_while_unconfigured(mock_arm: Arm) -> None:
    with pytest.raises(ArmStateError, match="cannot enable while unconfigured"):
        mock_arm.enable(["j1"])


def test_failed_enable_falls_back_to_unconfigured(make_arm_backend: MakeBackend) -> None:
    backend = make_arm_backend("emulated")
    arm = Arm(backend)
    arm.configure()
    assert isinstance(backend, EmulatedBackend)
    backend.bus.faults = FaultPlan(nack=1.0)
    with pytest.raises(CommError):
        arm.enable(["j3"])
    assert arm.state is Lifecycle.UNCONFIGURED


def test_disable_a_subset_keeps_the_others_enabled_and_the_arm_active(active_arm: Arm) -> None:
    active_arm.disable(["j2", "gripper"])
    assert active_arm.state is Lifecycle.ACTIVE
    assert [active_arm.joints[n].is_enabled() for n in NAMES] == [True, False, True, True]
    assert not active_arm.gripper.is_enabled


def test_disabling_the_last_enabled_device_makes_the_arm_inactive(mock_arm: Arm) -> None:
    mock_arm.configure()
    mock_arm.enable(["j4", "gripper"])
    mock_arm.disable(["j4"])
    assert mock_arm.state is Lifecycle.ACTIVE
    mock_arm.disable(["gripper"])
    assert mock_arm.state is Lifecycle.INACTIVE


def test_disable_releases_the_named_joints_interfaces(homed_mock_arm: Arm) -> None:
    homed_mock_arm.claim("j1", "position")
    homed_mock_arm.claim("j2", "position")
    homed_mock_arm.disable(["j1"])
    assert homed_mock_arm.modes["j1"] is CommandMode.NONE
    assert homed_mock_arm.modes["j2"] is CommandMode.POSITION


def test_disable_stops_a_running_homing_and_finishes_it_not_homed(active_arm: Arm) -> None:
    start_homing(active_arm, "j1", 0.03)
    active_arm.cycle(DT)
    active_arm.disable(["j1"])
    state = active_arm.joint_states["j1"]
    assert not state.homing
    assert not state.homed
    assert active_arm.modes["j1"] is CommandMode.NONE
    assert active_arm.joints["j1"].current_blocking_command is Reg.NONE
    assert not active_arm.joints["j1"].is_busy()


# ------------------------------------------------------------------ attach


def test_attach_over_enabled_joints_keeps_a_running_homing_running(
    arm: Arm, monkeypatch: pytest.MonkeyPatch
) -> None:
    arm.configure()
    enable_and_home_elsewhere(arm, "j1", 0.03)
    traffic = spy(monkeypatch, arm)
    assert arm.attach()
    assert traffic.log == []  # no SETUP, nothing at all
    assert arm.state is Lifecycle.ACTIVE
    assert set(arm.modes.values()) == {CommandMode.NONE}
    for name in NAMES:
        assert arm.commands[name] == arm.joint_states[name].position
    arm.cycle(DT)
    assert arm.joints["j1"].is_busy()
    assert not arm.joints["j2"].is_enabled()


def test_attach_with_nothing_enabled_stays_inactive(mock_arm: Arm) -> None:
    mock_arm.configure()
    assert not mock_arm.attach()
    assert mock_arm.state is Lifecycle.INACTIVE


def test_attach_is_refused_while_active(homed_mock_arm: Arm) -> None:
    with pytest.raises(ArmStateError, match="cannot attach while active; the arm must be inactive"):
        homed_mock_arm.attach()
