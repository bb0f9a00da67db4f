"""Tests that kill mutants mutmut found surviving in ``arm.py`` (docs/mutation.md).

On the mock backend (manual clock, homing in 1 s of clock time). Expected
values are literals from docs/arm.md and the packaged configuration
(``default_config.yaml``, the [URDF] and [PARAM] values of docs/model.md).
"""

from __future__ import annotations

import pytest
from rigs import MakeBackend, spy

from bioscara_gym.hardware.arm import (
    Arm,
    ArmStateError,
    CommandMode,
    Lifecycle,
    homing_timeout_s,
    move_timeout_s,
)
from bioscara_gym.hardware.clock import ManualClock
from bioscara_gym.hardware.config import load_config
from bioscara_gym.hardware.errors import IncorrectStateError, InvalidArgumentError, JointError, NotHomedError
from bioscara_gym.hardware.registers import Reg

CONFIG = load_config()
# default_config.yaml: the end stops every joint homes to (max) and j1's homing speed.
J1_MAX, J2_MAX, J1_MIN = 3.04647, 0.338, -3.04647
J1_HOMING_SPEED = 0.03


def steps(monkeypatch: pytest.MonkeyPatch, arm: Arm) -> list[float]:
    """Record the period of every control cycle the arm runs (``backend.step``)."""
    periods: list[float] = []
    step = arm.backend.step

    def record(dt: float) -> None:
        periods.append(dt)
        step(dt)

    monkeypatch.setattr(arm.backend, "step", record)
    return periods


def stuck(monkeypatch: pytest.MonkeyPatch, arm: Arm, *names: str) -> None:
    """The joints ``names`` take position commands but never move."""
    for name in names:
        monkeypatch.setattr(arm.joints[name], "set_position", lambda pos: None)


# ----------------------------------------------------------- lifecycle rules
def test_disable_is_allowed_on_an_inactive_arm(mock_arm: Arm) -> None:
    mock_arm.configure()
    mock_arm.disable(["j1"])
    assert mock_arm.state is Lifecycle.INACTIVE


def test_disable_of_an_unconfigured_arm_is_refused_naming_the_action(mock_arm: Arm) -> None:
    with pytest.raises(ArmStateError) as err:
        mock_arm.disable(["j1"])
    assert str(err.value) == "cannot disable while unconfigured; the arm must be inactive or active"


def test_move_of_an_unconfigured_arm_is_refused_naming_the_action(mock_arm: Arm) -> None:
    with pytest.raises(ArmStateError) as err:
        mock_arm.move_to({"j1": 0.0})
    assert str(err.value) == "cannot move while unconfigured; the arm must be active"


def test_disable_of_a_homing_joint_leaves_its_homing_state_false(homed_mock_arm: Arm) -> None:
    arm = homed_mock_arm
    arm.start_homing(["j1"])
    arm.disable(["j1"])
    assert arm.joint_states["j1"].homing is False
    assert arm.homing_names() == []


def test_disable_raises_when_only_the_gripper_fails(
    homed_mock_arm: Arm, monkeypatch: pytest.MonkeyPatch
) -> None:
    # docs/arm.md: any JointError in disable(names) is re-raised after every device was tried.
    def fail() -> None:
        raise JointError("servo gone", joint="gripper")

    monkeypatch.setattr(homed_mock_arm.gripper, "disable", fail)
    with pytest.raises(JointError, match="gripper: servo gone"):
        homed_mock_arm.disable(["gripper"])


def test_attach_takes_the_width_the_gripper_was_left_at(make_arm_backend: MakeBackend) -> None:
    backend = make_arm_backend("mock")
    earlier = Arm(backend)  # an earlier process left the gripper driven at 0.1 m
    earlier.configure()
    earlier.enable(["gripper"])
    earlier.set_gripper(0.1)
    earlier.write()
    for joint in backend.joints.values():  # its connections end with it; the devices stay as they were
        joint.deinit()
    arm = Arm(backend)
    arm.configure()
    assert arm.attach()
    assert arm.gripper_command == 0.1


def test_adopted_homing_keeps_its_speed_as_the_home_command(homed_mock_arm: Arm) -> None:
    # docs/arm.md: adopt_homing makes the home interface active with the speed as its command.
    joint = homed_mock_arm.joints["j1"]
    joint._command(Reg.HOME, 0)  # a homing an earlier process started (mock: any payload)
    homed_mock_arm.read()
    homed_mock_arm.adopt_homing("j1", -0.03)
    assert homed_mock_arm.modes["j1"] is CommandMode.HOME
    assert homed_mock_arm.commands["j1"] == -0.03


# ------------------------------------------------------------------- homing
@pytest.mark.parametrize(("direction", "speed"), [(1, 0.03), (-1, -0.03), (None, 0.03)])
def test_start_homing_takes_plus_and_minus_one_as_direction(
    homed_mock_arm: Arm, direction: int | None, speed: float
) -> None:
    # default_config.yaml: j1 homes at 0.03 rad/s, to max.
    assert homed_mock_arm.start_homing(["j1"], direction) == {"j1": speed}


def test_start_homing_refuses_another_direction_naming_it(homed_mock_arm: Arm) -> None:
    # docs/arm.md: the home command's sign picks the end stop, as a panel's +1/-1.
    with pytest.raises(InvalidArgumentError) as err:
        homed_mock_arm.start_homing(["j1"], 2)
    assert str(err.value) == "homing direction 2 must be +1 or -1"


def test_abort_homing_aborts_only_the_named_joint(homed_mock_arm: Arm) -> None:
    arm = homed_mock_arm
    arm.start_homing(["j1", "j2"])
    assert arm.abort_homing(["j1"]) == ["j1"]
    assert arm.homing_names() == ["j2"]
    assert not arm.joints["j1"].is_busy()
    assert arm.joints["j2"].is_busy()


def test_abort_homing_stops_a_homing_the_arm_did_not_start(homed_mock_arm: Arm) -> None:
    arm = homed_mock_arm
    arm.enable(["j1", "j2"])  # the arm's homing left them disabled
    arm.joints["j1"].start_homing(J1_HOMING_SPEED, 30, 15)  # not through the arm
    arm.joints["j2"].start_homing(0.003, 50, 30)
    arm.read()
    assert arm.abort_homing(["j1"]) == ["j1"]
    assert not arm.joints["j1"].is_busy()
    assert arm.joints["j2"].is_busy()


def test_home_cycles_every_40_ms(active_arm_mock: Arm, monkeypatch: pytest.MonkeyPatch) -> None:
    # docs/arm.md: Arm.home() cycles read/write every 40 ms.
    periods = steps(monkeypatch, active_arm_mock)
    active_arm_mock.home(["j1"])
    assert periods and set(periods) == {0.04}


def test_home_that_starts_late_on_the_clock_still_gets_its_whole_timeout(
    make_arm_backend: MakeBackend,
) -> None:
    # The timeout counts from the start of the homing, not from clock 0.
    arm = Arm(make_arm_backend("mock", clock=ManualClock(1000.0)))
    arm.configure()
    arm.activate()
    assert arm.home(["j1"]) == {"j1": J1_HOMING_SPEED}
    assert arm.joint_states["j1"].homed


def test_home_times_out_only_when_more_than_the_timeout_passed_naming_the_joints(
    active_arm_mock: Arm,
) -> None:
    # Homing takes 1 s (mock); cycles of 0.25 s at 0.25, 0.5 (not more than
    # 0.5 s yet) and 0.75 s, then the homings are aborted.
    arm = active_arm_mock
    with pytest.raises(ArmStateError) as err:
        arm.home(["j1", "j2"], period_s=0.25, timeout_s=0.5)
    assert str(err.value) == "homing j1, j2 did not finish within 0.5 s; aborted"
    assert arm.backend.clock.now() == 0.75
    assert arm.homing_names() == []


def test_home_names_every_joint_whose_homing_failed(
    active_arm_mock: Arm, monkeypatch: pytest.MonkeyPatch
) -> None:
    # docs/arm.md: a homing aborted (here a STOP the arm did not send, at
    # 0.5 s) ends with the joint not homed; Arm.home raises naming each.
    arm = active_arm_mock
    step = arm.backend.step

    def step_then_abort(dt: float) -> None:
        step(dt)
        if arm.backend.clock.now() >= 0.5:
            for name in ("j1", "j2"):
                if arm.joints[name].device_flags & 0x02:  # BUSY
                    arm.joints[name]._command(Reg.STOP, 0)  # the register primitive: the driver does not know

    monkeypatch.setattr(arm.backend, "step", step_then_abort)
    with pytest.raises(NotHomedError) as err:
        arm.home(["j1", "j2"])
    assert str(err.value) == "homing failed for j1, j2 (aborted or no end stop found)"


@pytest.mark.parametrize(
    ("name", "speed", "timeout"),
    [
        # docs/arm.md: 0.5 + 1.2 x range/|speed| + 5 s; ranges from default_config.yaml.
        ("j1", 0.03, 249.2176),  # range 6.09294 rad
        ("j2", -0.003, 141.34),  # range 0.3396 m
        ("j3", 0.05, 131.58256),  # range 5.25344 rad
    ],
)
def test_homing_timeout_is_the_whole_range_with_margin(name: str, speed: float, timeout: float) -> None:
    assert homing_timeout_s(CONFIG.joint(name), speed) == pytest.approx(timeout, abs=1e-4)


# ------------------------------------------------------------------- moving
@pytest.mark.parametrize(
    ("name", "distance", "timeout"),
    [
        # Arm.move_to: twice the trapezoid profile (distance/max_velocity +
        # max_velocity/max_acceleration) plus 5 s; limits from default_config.yaml.
        ("j1", 2.0, 10.0),  # 1 rad/s, 2 rad/s^2: 2 x (2 + 0.5) + 5
        ("j1", -1.0, 8.0),  # 2 x (1 + 0.5) + 5
        ("j3", 5.0, 7.7142857),  # 5 rad/s, 14 rad/s^2: 2 x (1 + 5/14) + 5
    ],
)
def test_move_timeout_is_twice_the_trapezoid_plus_5_s(name: str, distance: float, timeout: float) -> None:
    assert move_timeout_s(CONFIG.joint(name), distance) == pytest.approx(timeout, abs=1e-6)


def test_move_cycles_every_40_ms(homed_mock_arm: Arm, monkeypatch: pytest.MonkeyPatch) -> None:
    periods = steps(monkeypatch, homed_mock_arm)
    stuck(monkeypatch, homed_mock_arm, "j1")
    with pytest.raises(ArmStateError):
        homed_mock_arm.move_to({"j1": 1.0}, timeout_s=0.1)
    assert periods and set(periods) == {0.04}


def test_move_of_nothing_returns_at_once(homed_mock_arm: Arm) -> None:
    assert homed_mock_arm.move_to({}) == {}


def test_move_of_an_unhomed_joint_is_refused_by_name(active_arm_mock: Arm) -> None:
    with pytest.raises(NotHomedError) as err:
        active_arm_mock.move_to({"j1": 0.0})
    assert str(err.value) == "j1: not homed; home it before moving it"


def test_move_times_out_after_twice_the_trapezoid_of_the_distance_left(
    homed_mock_arm: Arm, monkeypatch: pytest.MonkeyPatch
) -> None:
    # j1 at max 3.04647 rad to 1.0 rad: distance 2.04647 rad, timeout 2 x (2.04647 + 0.5) + 5 s.
    stuck(monkeypatch, homed_mock_arm, "j1")
    with pytest.raises(ArmStateError) as err:
        homed_mock_arm.move_to({"j1": 1.0})
    assert str(err.value) == "j1: not at 1 rad within 10.0929 s (at 3.0465 rad)"


def test_move_timeout_names_only_the_late_joints_with_their_units(
    homed_mock_arm: Arm, monkeypatch: pytest.MonkeyPatch
) -> None:
    # Cycles of 0.25 s: at 0.5 s not more than the timeout yet, at 0.75 s it is.
    stuck(monkeypatch, homed_mock_arm, "j1", "j2")
    start = homed_mock_arm.backend.clock.now()
    with pytest.raises(ArmStateError) as err:
        homed_mock_arm.move_to({"j1": 1.0, "j2": 0.1, "j3": 0.0}, period_s=0.25, timeout_s=0.5)
    assert str(err.value) == (
        "j1: not at 1 rad within 0.5 s (at 3.0465 rad); j2: not at 0.1 m within 0.5 s (at 0.3380 m)"
    )
    assert homed_mock_arm.backend.clock.now() - start == pytest.approx(0.75, abs=1e-9)


def test_move_gives_back_the_interfaces_claimed_before(homed_mock_arm: Arm) -> None:
    # Arm.move_to: a velocity interface is claimed again at 0; an unclaimed joint is released.
    arm = homed_mock_arm
    arm.claim("j1", "velocity")
    arm.move_to({"j1": 1.0, "j3": 0.5})
    assert arm.modes["j1"] is CommandMode.VELOCITY
    assert arm.commands["j1"] == 0.0
    assert arm.modes["j3"] is CommandMode.NONE


@pytest.mark.parametrize(("name", "value"), [("j1", J1_MIN), ("j1", J1_MAX), ("j2", -0.0016), ("j2", J2_MAX)])
def test_targets_on_the_limits_are_accepted(homed_mock_arm: Arm, name: str, value: float) -> None:
    homed_mock_arm.check_targets({name: value})


def test_target_of_the_lift_outside_its_limits_is_refused_in_metres(homed_mock_arm: Arm) -> None:
    with pytest.raises(InvalidArgumentError) as err:
        homed_mock_arm.check_targets({"j2": 0.5})
    assert str(err.value) == "j2: 0.5 m is outside the joint limits [-0.0016, 0.338] m"


def test_a_joint_at_its_target_moving_slower_than_a_tenth_of_the_tolerance_is_there(
    homed_mock_arm: Arm, monkeypatch: pytest.MonkeyPatch
) -> None:
    # Arm.move_to: there within 1e-3 rad of the target and slower than a tenth of that per second.
    monkeypatch.setattr(homed_mock_arm.joints["j1"], "get_velocity", lambda: 0.95e-4)
    homed_mock_arm.read()
    assert homed_mock_arm.move_to({"j1": J1_MAX}, timeout_s=0.1) == {"j1": J1_MAX}


# ------------------------------------------------------------------ bring_up
def test_bring_up_homes_and_claims_only_the_named_joints(
    mock_arm: Arm, monkeypatch: pytest.MonkeyPatch
) -> None:
    mock_arm.bring_up("position", ["j1"])
    assert mock_arm.joint_states["j1"].homed
    assert not mock_arm.joint_states["j2"].homed
    assert mock_arm.modes == {
        "j1": CommandMode.POSITION,
        "j2": CommandMode.NONE,
        "j3": CommandMode.NONE,
        "j4": CommandMode.NONE,
    }
    traffic = spy(monkeypatch, mock_arm)
    mock_arm.bring_up("position", ["j1"])  # homed already: not homed again
    assert Reg.HOME not in traffic.regs("j1")


@pytest.fixture
def active_arm_mock(mock_arm: Arm) -> Arm:
    """:func:`mock_arm` configured and activated, nothing homed, at clock 0."""
    mock_arm.configure()
    mock_arm.activate()
    return mock_arm


# ------------------------------------------------- refusals and state values
def test_enabling_a_busy_joint_to_claim_it_is_refused_naming_the_action(homed_mock_arm: Arm) -> None:
    # docs/arm.md: no SETUP reaches a joint that runs a blocking command. Here
    # j1 is homed and disabled (after its homing) and reports BUSY: a blocking
    # command another process started.
    arm = homed_mock_arm
    arm.joints["j1"].device_flags |= 0x02  # BUSY
    arm.read()
    with pytest.raises(ArmStateError) as err:
        arm.claim("j1", "position")
    assert str(err.value) == (
        "j1: a homing (or another blocking command) is running and enabling would hang it; "
        "abort it (home command 0) first"
    )


def test_a_single_device_name_may_be_given_as_a_string(homed_mock_arm: Arm) -> None:
    homed_mock_arm.enable("j1")
    assert homed_mock_arm.joints["j1"].is_enabled()
    assert not homed_mock_arm.joints["j2"].is_enabled()


def test_unknown_command_mode_is_refused_listing_the_modes(homed_mock_arm: Arm) -> None:
    # docs/arm.md: the command interfaces are position, velocity and home.
    with pytest.raises(InvalidArgumentError) as err:
        homed_mock_arm.claim("j1", "torque")
    assert str(err.value) == "j1: unknown command mode 'torque'; expected position, velocity, home"


def test_finished_homing_leaves_the_joint_at_rest_in_the_state(homed_mock_arm: Arm) -> None:
    assert homed_mock_arm.joint_states["j1"].velocity == 0.0


def test_aborted_homing_reads_position_0_without_asking_the_joint(
    homed_mock_arm: Arm, monkeypatch: pytest.MonkeyPatch
) -> None:
    # docs/arm.md: 0.0 while not homed; the homing's end disables the joint (SETBRAKEMODE last).
    arm = homed_mock_arm
    arm.start_homing(["j1"])
    traffic = spy(monkeypatch, arm)
    arm.set_command("j1", 0.0)
    arm.write()  # STOP: aborts the homing
    arm.read()  # finishes it: stop, limits, post_homing, disable
    state = arm.joint_states["j1"]
    assert (state.homed, state.position) == (False, 0.0)
    assert traffic.regs("j1")[-1] == Reg.SETBRAKEMODE


def test_a_disabled_gripper_is_sent_no_width(homed_mock_arm: Arm) -> None:
    # docs/arm.md: write() sends the gripper width if it changed, to an enabled gripper.
    arm = homed_mock_arm
    arm.enable(["j1"])  # keeps the arm active
    arm.disable(["gripper"])
    arm.set_gripper(0.1)
    arm.write()
    assert arm.state is Lifecycle.ACTIVE
    assert arm.gripper.get_position() == 0.08


def test_home_command_refused_while_an_unknown_blocking_command_runs(homed_mock_arm: Arm) -> None:
    # docs/arm.md: a non-zero home command while another blocking command runs
    # (BUSY; this process did not start it) is an IncorrectStateError.
    arm = homed_mock_arm
    arm.enable(["j2"])
    arm.joints["j2"]._command(Reg.HOME, 0)  # the register primitive: the driver does not know
    arm.read()
    arm.claim("j2", "home")
    arm.set_command("j2", 1.0)
    with pytest.raises(IncorrectStateError) as err:
        arm.write()
    assert str(err.value) == "j2: a blocking command is running; cannot start homing"


def test_a_new_arm_commands_0_and_the_gripper_backup_width(mock_arm: Arm) -> None:
    # docs/arm.md: the gripper's backup initial width is 0.08 m; nothing is claimed yet.
    assert mock_arm.commands == {"j1": 0.0, "j2": 0.0, "j3": 0.0, "j4": 0.0}
    assert mock_arm.gripper_command == 0.08
