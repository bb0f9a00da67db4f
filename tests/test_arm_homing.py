"""Homing through the arm (docs/arm.md, "The arm layer"): the home interface, Arm.home and adopt_homing.

Covers the home command's semantics (a signed speed starts homing, 0 aborts it, refused while
another blocking command runs), homing completing in read at the max or min end stop with the
offset stored and the max acceleration restored, the Arm.home convenience and its timeout, and
adopting a homing an earlier process started, through Arm.adopt_homing and BaseJoint.adopt_homing.
"""

from __future__ import annotations

import math

import pytest
from rigs import (
    CONFIG,
    DT,
    KNOWN_JOINTS,
    NAMES,
    MakeBackend,
    cycle_until,
    enable_and_home_elsewhere,
    motor_rate_deg,
    spy,
    start_homing,
    wait_for_homing_end,
)

from bioscara_gym.hardware.arm import Arm, ArmStateError, CommandMode, Lifecycle
from bioscara_gym.hardware.errors import (
    IncorrectStateError,
    InvalidArgumentError,
    NotInitError,
)
from bioscara_gym.hardware.registers import Flag, Reg

# ---------------------------------------------------- home command semantics


def test_home_command_starts_homing(active_arm: Arm) -> None:
    start_homing(active_arm, "j1", 0.03)
    joint = active_arm.joints["j1"]
    assert joint.is_busy()
    assert not joint.is_homed()
    assert joint.current_blocking_command is Reg.HOME
    state = active_arm.read()["j1"]
    assert state.homing
    assert state.flags & Flag.BUSY
    assert state.flags & Flag.NOT_HOMED


def test_home_command_of_zero_starts_nothing(active_arm: Arm, monkeypatch: pytest.MonkeyPatch) -> None:
    active_arm.claim("j1", "home")
    traffic = spy(monkeypatch, active_arm)
    active_arm.write()
    assert traffic.log == []
    assert not active_arm.read()["j1"].homing


def test_home_command_refused_while_another_blocking_command_runs(active_arm: Arm) -> None:
    cfg = CONFIG.joint("j2").homing
    active_arm.joints["j2"].start_homing(cfg.speed, cfg.threshold, cfg.current)  # not through the arm
    active_arm.claim("j2", "home")
    active_arm.set_command("j2", cfg.speed)
    with pytest.raises(IncorrectStateError, match="j2: HOME is running; cannot start homing"):
        active_arm.write()
    assert active_arm.state is Lifecycle.UNCONFIGURED  # a failed write: on_error


def test_joint_refuses_a_second_homing_while_the_arm_homes_it(active_arm: Arm) -> None:
    start_homing(active_arm, "j1", 0.03)
    with pytest.raises(IncorrectStateError, match="j1: HOME is still running; stop it first"):
        active_arm.joints["j1"].start_homing(0.03, 30, 15)


def test_orientation_check_refused_while_the_arm_homes_the_joint(active_arm: Arm) -> None:
    start_homing(active_arm, "j1", 0.03)
    with pytest.raises(IncorrectStateError, match="j1: HOME is still running"):
        active_arm.joints["j1"].check_orientation()


def test_further_home_commands_while_homing_do_not_restart_it(
    active_arm: Arm, monkeypatch: pytest.MonkeyPatch
) -> None:
    start_homing(active_arm, "j1", 0.03)
    traffic = spy(monkeypatch, active_arm)
    active_arm.set_command("j1", 0.05)
    active_arm.write()
    assert Reg.HOME not in traffic.regs("j1")


def test_home_command_zero_aborts_the_homing(active_arm: Arm, monkeypatch: pytest.MonkeyPatch) -> None:
    start_homing(active_arm, "j1", 0.03)
    active_arm.cycle(DT)
    traffic = spy(monkeypatch, active_arm)
    active_arm.set_command("j1", 0.0)
    active_arm.write()
    assert traffic.regs("j1") == [Reg.STOP]
    flags = active_arm.joints["j1"].get_flags()
    assert not flags & Flag.BUSY
    assert flags & Flag.NOT_HOMED


def test_read_after_an_abort_reports_not_homed_and_keeps_the_arm_active(active_arm: Arm) -> None:
    start_homing(active_arm, "j1", 0.03)
    active_arm.cycle(DT)
    active_arm.set_command("j1", 0.0)
    active_arm.write()
    state = active_arm.read()["j1"]
    assert active_arm.state is Lifecycle.ACTIVE
    assert not state.homed
    assert not state.homing
    assert state.flags & Flag.NOT_HOMED
    assert active_arm.commands["j1"] == 0.0
    active_arm.release("j1")


@pytest.mark.parametrize("name", ["j1", "j2"])
def test_homing_completes_in_read_at_max_for_a_positive_speed(active_arm: Arm, name: str) -> None:
    speed = CONFIG.joint(name).homing.speed
    start_homing(active_arm, name, speed)
    cycle_until(active_arm, lambda: not active_arm.joint_states[name].homing)
    state = active_arm.joint_states[name]
    assert state.homed
    assert not state.flags & Flag.BUSY
    assert active_arm.commands[name] == 0.0
    assert active_arm.modes[name] is CommandMode.HOME
    assert active_arm.joints[name].current_blocking_command is Reg.NONE
    assert state.position == pytest.approx(CONFIG.joint(name).max, abs=1e-3)
    assert active_arm.state is Lifecycle.ACTIVE


def test_homing_completes_at_min_for_a_negative_speed(mock_arm: Arm) -> None:
    mock_arm.configure()
    mock_arm.activate()
    start_homing(mock_arm, "j1", -0.03)
    cycle_until(mock_arm, lambda: not mock_arm.joint_states["j1"].homing)
    assert mock_arm.joint_states["j1"].position == CONFIG.joint("j1").min


def test_homing_takes_the_mock_homing_time(mock_arm: Arm) -> None:
    mock_arm.configure()
    mock_arm.activate()
    start_homing(mock_arm, "j1", 0.03)
    took = cycle_until(mock_arm, lambda: not mock_arm.joint_states["j1"].homing)
    assert took == pytest.approx(1.0, abs=DT + 1e-9)


def test_homing_stores_the_offset_on_the_joint(active_arm: Arm, monkeypatch: pytest.MonkeyPatch) -> None:
    start_homing(active_arm, "j3", 0.05)
    traffic = spy(monkeypatch, active_arm)
    cycle_until(active_arm, lambda: not active_arm.joint_states["j3"].homing)
    assert traffic.values("j3", Reg.HOMEOFFSET) == [pytest.approx(CONFIG.joint("j3").max)]


def test_homing_restores_the_max_acceleration_afterwards(
    active_arm: Arm, monkeypatch: pytest.MonkeyPatch
) -> None:
    traffic = spy(monkeypatch, active_arm)
    start_homing(active_arm, "j4", 0.1)
    cycle_until(active_arm, lambda: not active_arm.joint_states["j4"].homing)
    cfg = CONFIG.joint("j4")
    assert traffic.values("j4", Reg.SETMAXACCELERATION) == [
        pytest.approx(motor_rate_deg("j4", cfg.max_acceleration)),  # enabling first (start_homing)
        pytest.approx(motor_rate_deg("j4", cfg.homing.acceleration)),
        pytest.approx(motor_rate_deg("j4", cfg.max_acceleration)),  # restored (stop_homing)
    ]


def test_home_convenience_homes_every_unhomed_joint_and_leaves_no_interface_claimed(
    active_arm: Arm,
) -> None:
    active_arm.home()
    assert active_arm.state is Lifecycle.ACTIVE
    assert set(active_arm.modes.values()) == {CommandMode.NONE}
    for name in NAMES:
        state = active_arm.joint_states[name]
        assert state.homed, name
        assert not state.homing, name
        assert active_arm.commands[name] == 0.0
        assert state.position == pytest.approx(CONFIG.joint(name).max, abs=1e-3)


def test_home_convenience_skips_homed_joints(homed_arm: Arm, monkeypatch: pytest.MonkeyPatch) -> None:
    traffic = spy(monkeypatch, homed_arm)
    homed_arm.home()
    assert all(reg is not Reg.HOME for _, reg, _ in traffic.log)


def test_home_convenience_gives_back_a_claimed_motion_interface(mock_arm: Arm) -> None:
    mock_arm.configure()
    mock_arm.activate()
    mock_arm.home()
    mock_arm.claim("j1", "position")
    mock_arm.home(["j1"], only_unhomed=False)
    assert mock_arm.modes["j1"] is CommandMode.POSITION
    assert mock_arm.commands["j1"] == mock_arm.joint_states["j1"].position


def test_home_convenience_timeout_stops_the_homing(make_arm_backend: MakeBackend) -> None:
    arm = Arm(make_arm_backend("mock", homing_time_s=100.0))
    arm.configure()
    arm.activate()
    with pytest.raises(ArmStateError, match=r"homing j1 did not finish within 0.5 s"):
        arm.home(["j1"], timeout_s=0.5)
    flags = arm.joints["j1"].get_flags()
    assert not flags & Flag.BUSY
    assert flags & Flag.NOT_HOMED


def test_read_after_a_home_timeout_keeps_the_arm_active(make_arm_backend: MakeBackend) -> None:
    arm = Arm(make_arm_backend("mock", homing_time_s=100.0))
    arm.configure()
    arm.activate()
    with pytest.raises(ArmStateError):
        arm.home(["j1"], timeout_s=0.5)
    arm.read()
    assert arm.state is Lifecycle.ACTIVE


# ---------------------------------------------------------- adopt_homing


def test_adopted_homing_finishes_at_max_for_a_positive_speed(
    arm: Arm, monkeypatch: pytest.MonkeyPatch
) -> None:
    arm.configure()
    speed = CONFIG.joint("j1").homing.speed
    enable_and_home_elsewhere(arm, "j1", speed)
    arm.attach()
    arm.adopt_homing("j1", speed)
    assert arm.modes["j1"] is CommandMode.HOME
    assert arm.joint_states["j1"].homing
    traffic = spy(monkeypatch, arm)
    cycle_until(arm, lambda: not arm.joint_states["j1"].homing)
    assert Reg.HOME not in traffic.regs("j1")  # tracked, not restarted
    assert traffic.values("j1", Reg.HOMEOFFSET) == [pytest.approx(CONFIG.joint("j1").max)]
    state = arm.joint_states["j1"]
    assert state.homed
    assert state.position == pytest.approx(CONFIG.joint("j1").max, abs=1e-3)
    assert arm.commands["j1"] == 0.0
    assert arm.joints["j1"].current_blocking_command is Reg.NONE


def test_adopted_homing_finishes_at_min_for_a_negative_speed(mock_arm: Arm) -> None:
    mock_arm.configure()
    enable_and_home_elsewhere(mock_arm, "j1", -0.03)
    mock_arm.attach()
    mock_arm.adopt_homing("j1", -0.03)
    cycle_until(mock_arm, lambda: not mock_arm.joint_states["j1"].homing)
    assert mock_arm.joint_states["j1"].homed
    assert mock_arm.joint_states["j1"].position == CONFIG.joint("j1").min


def test_adopted_homing_is_aborted_by_a_home_command_of_zero(active_arm: Arm) -> None:
    arm = active_arm
    arm.deactivate()
    enable_and_home_elsewhere(arm, "j1", 0.03)
    arm.attach()
    arm.adopt_homing("j1", 0.03)
    arm.set_command("j1", 0.0)
    arm.write()
    state = arm.read()["j1"]
    assert not state.homing
    assert not state.homed
    assert not arm.joints["j1"].is_busy()


def test_adopting_a_homing_that_already_ended_finishes_it_on_the_next_read(mock_arm: Arm) -> None:
    mock_arm.configure()
    enable_and_home_elsewhere(mock_arm, "j1", 0.03)
    mock_arm.backend.step(2.0)  # the homing ends while nobody watches
    mock_arm.read()
    mock_arm.attach()
    mock_arm.adopt_homing("j1", 0.03)
    mock_arm.read()
    assert not mock_arm.joint_states["j1"].homing
    assert mock_arm.joint_states["j1"].position == CONFIG.joint("j1").max


def test_adopt_homing_is_refused_unless_active(mock_arm: Arm) -> None:
    mock_arm.configure()
    with pytest.raises(ArmStateError, match="cannot adopt a homing on j1 while inactive"):
        mock_arm.adopt_homing("j1", 0.03)


def test_adopt_homing_is_refused_over_another_interface(homed_mock_arm: Arm) -> None:
    homed_mock_arm.claim("j1", "position")
    with pytest.raises(ArmStateError, match="j1: position interface is active; release it"):
        homed_mock_arm.adopt_homing("j1", 0.03)


@pytest.mark.parametrize("speed", [0.0, math.nan, math.inf])
def test_adopt_homing_refuses_a_zero_or_non_finite_speed(homed_mock_arm: Arm, speed: float) -> None:
    with pytest.raises(InvalidArgumentError, match=r"j1: homing speed .* must be finite and non-zero"):
        homed_mock_arm.adopt_homing("j1", speed)
    assert homed_mock_arm.modes["j1"] is CommandMode.NONE


def test_adopt_homing_of_an_unknown_joint_is_refused_listing_the_known_joints(
    homed_mock_arm: Arm,
) -> None:
    with pytest.raises(InvalidArgumentError, match=KNOWN_JOINTS):
        homed_mock_arm.adopt_homing("j9", 0.03)


# ----------------------------------------------------- BaseJoint.adopt_homing


@pytest.mark.parametrize(("speed", "end"), [(0.03, "max"), (-0.03, "min")])
def test_joint_adopt_homing_sets_home_and_the_offset_from_the_sign(
    mock_arm: Arm, monkeypatch: pytest.MonkeyPatch, speed: float, end: str
) -> None:
    mock_arm.configure()
    joint = mock_arm.joints["j3"]
    enable_and_home_elsewhere(mock_arm, "j3", speed)
    traffic = spy(monkeypatch, mock_arm)
    joint.adopt_homing(speed)
    assert traffic.log == []
    assert joint.current_blocking_command is Reg.HOME
    mock_arm.backend.step(2.0)
    joint.wait_while_busy()
    joint.post_homing()
    assert joint.offset == getattr(CONFIG.joint("j3"), end)
    assert traffic.values("j3", Reg.HOMEOFFSET) == [getattr(CONFIG.joint("j3"), end)]


@pytest.mark.parametrize("velocity", [0.0, math.nan])
def test_joint_adopt_homing_refuses_a_zero_or_non_finite_velocity(mock_arm: Arm, velocity: float) -> None:
    mock_arm.configure()
    with pytest.raises(InvalidArgumentError, match="j1: homing velocity"):
        mock_arm.joints["j1"].adopt_homing(velocity)
    assert mock_arm.joints["j1"].current_blocking_command is Reg.NONE


def test_joint_adopt_homing_refused_before_init(mock_arm: Arm) -> None:
    with pytest.raises(NotInitError):
        mock_arm.joints["j1"].adopt_homing(0.03)


# ------------------------------------- the seed's start_homing / stop_homing
# Seed 000, BioscaraArmHardwareInterface::start_homing: "Activate the joint, set homing
# acceleration and start homing"; ::stop_homing: "Stop the homing. Reset acceleration and
# velocity and perform the postHoming cleanup, then deactivate the joint."

#: What disable() sends: STOP, hold current 0, drive current 0, brake mode freewheel.
DISABLE_REGS = [Reg.STOP, Reg.SETHOLDCURRENT, Reg.SETCURRENT, Reg.SETBRAKEMODE]


def test_homing_a_disabled_joint_enables_it_first(active_arm: Arm, monkeypatch: pytest.MonkeyPatch) -> None:
    active_arm.disable(["j1"])
    traffic = spy(monkeypatch, active_arm)
    active_arm.claim("j1", "home")
    active_arm.set_command("j1", 1.0)
    active_arm.write()
    regs = [r for r in traffic.regs("j1") if r is not Reg.HOMEOFFSET]  # (the offset guard, if any)
    assert regs == [
        Reg.SETUP,
        Reg.ENABLESTALLGUARD,
        Reg.SETMAXVELOCITY,
        Reg.SETMAXACCELERATION,
        Reg.SETMAXACCELERATION,
        Reg.HOME,
    ]
    # The second is the homing acceleration: j1 0.01 rad/s^2 x 35 = 20.05 deg/s^2.
    assert traffic.values("j1", Reg.SETMAXACCELERATION)[-1] == pytest.approx(20.0535, abs=1e-3)


def test_homing_after_a_disable_succeeds(active_arm: Arm) -> None:
    active_arm.disable(["j3"])
    active_arm.home(["j3"])
    assert active_arm.joint_states["j3"].homed


def test_end_of_homing_stops_restores_limits_stores_the_offset_then_disables(
    active_arm: Arm, monkeypatch: pytest.MonkeyPatch
) -> None:
    start_homing(active_arm, "j1", 0.03)
    wait_for_homing_end(active_arm, "j1")
    joint = active_arm.joints["j1"]
    traffic = spy(monkeypatch, active_arm)
    active_arm.read()
    regs = [r for r in traffic.regs("j1") if r not in (Reg.ANGLEMOVED, Reg.GETENCODERRPM)]
    # post_homing refreshes the flags (PING) before it stores the offset.
    assert regs == [
        Reg.STOP,
        Reg.SETMAXACCELERATION,
        Reg.SETMAXVELOCITY,
        Reg.PING,
        Reg.HOMEOFFSET,
        *DISABLE_REGS,
    ]
    cfg = CONFIG.joint("j1")
    assert traffic.values("j1", Reg.SETMAXVELOCITY) == [pytest.approx(math.degrees(35 * cfg.max_velocity))]
    assert not joint.is_enabled()
    assert active_arm.joint_states["j1"].homed
    assert active_arm.commands["j1"] == 0.0


@pytest.mark.parametrize("mode", ["position", "velocity"])
def test_claiming_motion_on_a_homed_disabled_joint_enables_it(
    active_arm: Arm, mode: str, monkeypatch: pytest.MonkeyPatch
) -> None:
    active_arm.home(["j1"])
    assert not active_arm.joints["j1"].is_enabled()
    traffic = spy(monkeypatch, active_arm)
    active_arm.claim("j1", mode)
    assert traffic.regs("j1")[:4] == [
        Reg.SETUP,
        Reg.ENABLESTALLGUARD,
        Reg.SETMAXVELOCITY,
        Reg.SETMAXACCELERATION,
    ]
    assert active_arm.joints["j1"].is_enabled()
    expected = active_arm.joint_states["j1"].position if mode == "position" else 0.0
    assert active_arm.commands["j1"] == expected


@pytest.mark.parametrize("mode", ["position", "velocity", "home"])
def test_claiming_an_interface_that_is_already_active_is_refused(homed_arm: Arm, mode: str) -> None:
    homed_arm.claim("j1", mode)
    with pytest.raises(ArmStateError, match=rf"j1: the {mode} interface is already active"):
        homed_arm.claim("j1", mode)


# -------------------------------------------------- no SETUP during a homing
# The firmware's SETUP stops the motor but never clears BUSY: a homing then waits
# forever for its end stop (docs/firmware.md). The host must never send it.


def test_no_setup_reaches_a_joint_between_its_home_and_the_end_of_that_homing(
    active_arm: Arm, monkeypatch: pytest.MonkeyPatch
) -> None:
    traffic = spy(monkeypatch, active_arm)
    active_arm.start_homing(["j1"])
    attempts = [
        lambda: active_arm.enable(["j1"]),
        lambda: active_arm.enable(["j1", "j2"]),
        lambda: active_arm.claim("j1", "position"),
    ]
    while "j1" in active_arm.homing_names():
        for attempt in attempts:
            with pytest.raises(ArmStateError):
                attempt()
        active_arm.cycle(DT)
    regs = traffic.regs("j1")
    home, stop = regs.index(Reg.HOME), regs.index(Reg.STOP, regs.index(Reg.HOME))
    assert Reg.SETUP not in regs[home:stop]
    assert active_arm.joint_states["j1"].homed


def test_enable_refuses_a_joint_busy_with_a_homing_the_arm_did_not_start(
    active_arm: Arm, monkeypatch: pytest.MonkeyPatch
) -> None:
    cfg = CONFIG.joint("j2").homing
    active_arm.joints["j2"].start_homing(cfg.speed, cfg.threshold, cfg.current)  # another process's
    active_arm.read()
    traffic = spy(monkeypatch, active_arm)
    with pytest.raises(ArmStateError, match=r"j2: a homing .* is running and enabling would hang it"):
        active_arm.enable(["j2"])
    assert traffic.log == []
