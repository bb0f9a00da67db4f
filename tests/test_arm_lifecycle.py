"""The arm layer: lifecycle, command interfaces, homing and I/O (SPEC.md "The arm layer").

Behaviour every backend shares is parametrized over the ``mock``, ``sim`` and
``emulated`` backends. Register traffic is observed at each joint's two
register-level primitives (``_command`` / ``_query``), where every backend
meets the shared host rules of :class:`BaseJoint`; for the ``emulated``
backend it is also checked on the bus itself, byte for byte.
"""

from __future__ import annotations

import json
import math
from collections.abc import Callable
from dataclasses import dataclass, field
from pathlib import Path

import pytest
from conftest import ARM_BACKENDS

from bioscara_gym.hardware.arm import Arm, ArmStateError, CommandMode, Lifecycle
from bioscara_gym.hardware.backends import Backend, EmulatedBackend
from bioscara_gym.hardware.codec import pack_bytes
from bioscara_gym.hardware.config import load_config
from bioscara_gym.hardware.emulated_bus import FaultPlan
from bioscara_gym.hardware.errors import (
    CommError,
    IncorrectStateError,
    InvalidArgumentError,
    NotHomedError,
    NotInitError,
    StalledError,
)
from bioscara_gym.hardware.gripper import GripperStateWarning
from bioscara_gym.hardware.registers import Flag, Reg
from bioscara_gym.hardware.sim import ArmSim

MakeBackend = Callable[..., Backend]
NAMES = ("j1", "j2", "j3", "j4")
CONFIG = load_config()
KNOWN_JOINTS = r"known joints: j1, j2, j3, j4"
#: Control period of the tests' cycles, s (25 Hz, as the envs run).
DT = 0.04


# ------------------------------------------------------------------ helpers


@dataclass
class Traffic:
    """Register transactions of every joint, in order: ``(joint, register, value)``.

    ``value`` is the command's payload, or ``None`` for a read.
    """

    log: list[tuple[str, Reg, float | int | None]] = field(default_factory=list)

    def regs(self, name: str) -> list[Reg]:
        """Registers joint ``name`` was sent, in order."""
        return [reg for joint, reg, _ in self.log if joint == name]

    def values(self, name: str, reg: Reg) -> list[float | int | None]:
        """Payloads of ``reg`` commands to joint ``name``."""
        return [value for joint, r, value in self.log if joint == name and r == reg and value is not None]

    def clear(self) -> None:
        """Forget the transactions so far."""
        self.log.clear()


def spy(monkeypatch: pytest.MonkeyPatch, arm: Arm) -> Traffic:
    """Record every joint's register traffic from now on."""
    traffic = Traffic()
    for name, joint in arm.joints.items():
        command, query = joint._command, joint._query

        def recording_command(reg: Reg, value: float | int, _n: str = name, _f: Callable = command) -> int:
            traffic.log.append((_n, Reg(reg), value))
            return _f(reg, value)

        def recording_query(reg: Reg, _n: str = name, _f: Callable = query) -> tuple[float | int, int]:
            traffic.log.append((_n, Reg(reg), None))
            return _f(reg)

        monkeypatch.setattr(joint, "_command", recording_command)
        monkeypatch.setattr(joint, "_query", recording_query)
    return traffic


def cycle_until(arm: Arm, done: Callable[[], bool], max_s: float = 20.0) -> float:
    """Run control cycles of :data:`DT` until ``done()``; return the time it took."""
    start = arm.backend.clock.now()
    while not done():
        assert arm.backend.clock.now() - start < max_s, f"not done after {max_s} s"
        arm.cycle(DT)
    return arm.backend.clock.now() - start


def start_homing(arm: Arm, name: str, speed: float) -> None:
    """Claim the home interface of ``name``, send a home command of ``speed``, read the state."""
    arm.claim(name, "home")
    arm.set_command(name, speed)
    arm.write()
    arm.read()


def motor_rate_deg(name: str, value: float) -> float:
    """A joint-side velocity or acceleration as sent to the joint, deg/s or deg/s^2."""
    return abs(math.degrees(CONFIG.joint(name).reduction * value))


# ----------------------------------------------------------------- fixtures


#: Power-up pose of the simulated arms: 0.3 % of each range inside the end stop
#: homing drives to, so homing takes about a simulated second.
NEAR_END_STOPS = ArmSim.parked_pose(CONFIG, margin=0.003)


@pytest.fixture(params=ARM_BACKENDS)
def backend(request: pytest.FixtureRequest, make_arm_backend: MakeBackend) -> Backend:
    """Each backend an arm runs on without hardware, fresh (joints powered up, unhomed).

    The simulated arms power up at :data:`NEAR_END_STOPS`.
    """
    if request.param == "mock":
        return make_arm_backend("mock")
    return make_arm_backend(request.param, initial_qpos=NEAR_END_STOPS)


@pytest.fixture
def arm(backend: Backend) -> Arm:
    """An unconfigured arm on :func:`backend`."""
    return Arm(backend)


@pytest.fixture
def active_arm(arm: Arm) -> Arm:
    """:func:`arm` configured and activated; its joints are not homed."""
    arm.configure()
    arm.activate()
    return arm


@pytest.fixture
def homed_arm(active_arm: Arm) -> Arm:
    """:func:`active_arm` with every joint homed (at its max end stop)."""
    active_arm.home()
    return active_arm


@pytest.fixture
def mock_arm(make_arm_backend: MakeBackend) -> Arm:
    """An unconfigured arm on the mock backend (for rules that involve no joint behaviour)."""
    return Arm(make_arm_backend("mock"))


@pytest.fixture
def homed_mock_arm(mock_arm: Arm) -> Arm:
    """:func:`mock_arm` active with every joint homed (at its max end stop)."""
    mock_arm.configure()
    mock_arm.activate()
    mock_arm.home()
    return mock_arm


# ---------------------------------------------------------------- lifecycle


def test_arm_starts_unconfigured_with_no_interface_claimed(arm: Arm) -> None:
    assert arm.state is Lifecycle.UNCONFIGURED
    assert arm.names == NAMES
    assert set(arm.modes.values()) == {CommandMode.NONE}
    assert not any(j.initialized for j in arm.joints.values())


def test_configure_pings_every_joint_first_and_goes_inactive(
    arm: Arm, monkeypatch: pytest.MonkeyPatch
) -> None:
    traffic = spy(monkeypatch, arm)
    arm.configure()
    assert arm.state is Lifecycle.INACTIVE
    for name in NAMES:
        assert traffic.regs(name)[0] is Reg.PING
        assert arm.joints[name].initialized
    assert arm.gripper.is_initialized
    assert not arm.gripper.is_enabled


def test_configure_pings_every_address_on_the_emulated_bus(
    make_arm_backend: MakeBackend, monkeypatch: pytest.MonkeyPatch
) -> None:
    backend = make_arm_backend("emulated")
    assert isinstance(backend, EmulatedBackend)
    sent: list[tuple[int, bytes]] = []
    transfer = backend.bus.transfer

    def recording_transfer(address: int, data: bytes, read_len: int) -> bytes:
        sent.append((address, bytes(data)))
        return transfer(address, data, read_len)

    monkeypatch.setattr(backend.bus, "transfer", recording_transfer)
    Arm(backend).configure()
    pinged = [address for address, data in sent if data == bytes([Reg.PING])]
    assert pinged == [0x11, 0x12, 0x13, 0x14]
    assert all(device.transactions > 0 for device in backend.devices.values())


def test_configure_does_not_enable_the_joints(arm: Arm) -> None:
    arm.configure()
    assert not any(j.is_enabled() for j in arm.joints.values())


def test_activate_enables_every_joint_and_goes_active(arm: Arm) -> None:
    arm.configure()
    arm.activate()
    assert arm.state is Lifecycle.ACTIVE
    for name, joint in arm.joints.items():
        assert joint.is_enabled(), name
        assert not arm.joint_states[name].flags & Flag.NOT_ENABLED


def test_activate_enables_stall_detection_and_sets_limits(arm: Arm, monkeypatch: pytest.MonkeyPatch) -> None:
    arm.configure()
    traffic = spy(monkeypatch, arm)
    arm.activate()
    for name in NAMES:
        cfg = CONFIG.joint(name)
        assert traffic.regs(name)[:4] == [
            Reg.SETUP,
            Reg.ENABLESTALLGUARD,
            Reg.SETMAXVELOCITY,
            Reg.SETMAXACCELERATION,
        ]
        assert traffic.values(name, Reg.ENABLESTALLGUARD) == [cfg.stall_threshold]
        assert traffic.values(name, Reg.SETMAXVELOCITY) == [
            pytest.approx(motor_rate_deg(name, cfg.max_velocity))
        ]
        assert traffic.values(name, Reg.SETMAXACCELERATION) == [
            pytest.approx(motor_rate_deg(name, cfg.max_acceleration))
        ]


@pytest.mark.parametrize("name", ["sim", "emulated"])
def test_activate_leaves_stall_detection_and_limits_in_the_firmware(
    make_arm_backend: MakeBackend, name: str
) -> None:
    backend = make_arm_backend(name)
    arm = Arm(backend)
    arm.configure()
    arm.activate()
    for joint in NAMES:
        cfg = CONFIG.joint(joint)
        core = backend.sim.cores[joint]  # type: ignore[union-attr]
        assert core.stallguard
        assert core.stall_sensitivity == cfg.stall_threshold
        assert core.max_velocity == pytest.approx(motor_rate_deg(joint, cfg.max_velocity), rel=1e-6)
        assert core.max_acceleration == pytest.approx(motor_rate_deg(joint, cfg.max_acceleration), rel=1e-6)


def test_activate_holds_the_measured_position_with_no_interface_claimed(homed_arm: Arm) -> None:
    arm = homed_arm
    arm.claim("j1", "position")
    arm.deactivate()
    arm.activate()
    assert set(arm.modes.values()) == {CommandMode.NONE}
    for name in NAMES:
        assert arm.commands[name] == arm.joint_states[name].position
        assert arm.joint_states[name].position == pytest.approx(CONFIG.joint(name).max, abs=1e-3)


def test_nothing_moves_over_cycles_after_activate(homed_arm: Arm) -> None:
    arm = homed_arm
    arm.deactivate()
    arm.activate()
    before = {n: s.position for n, s in arm.read().items()}
    for _ in range(5):
        arm.cycle(DT)
    for name in NAMES:
        assert arm.joint_states[name].position == pytest.approx(before[name], abs=1e-4), name
        assert arm.joint_states[name].velocity == pytest.approx(0.0, abs=1e-3), name


def test_deactivate_disables_every_joint_and_goes_inactive(active_arm: Arm) -> None:
    active_arm.deactivate()
    assert active_arm.state is Lifecycle.INACTIVE
    assert not any(j.is_enabled() for j in active_arm.joints.values())
    assert all(j.initialized for j in active_arm.joints.values())


def test_deactivate_releases_every_interface(homed_arm: Arm) -> None:
    homed_arm.claim("j1", "position")
    homed_arm.claim("j2", "velocity")
    homed_arm.deactivate()
    assert set(homed_arm.modes.values()) == {CommandMode.NONE}


def test_state_keeps_updating_while_inactive(active_arm: Arm, monkeypatch: pytest.MonkeyPatch) -> None:
    active_arm.deactivate()
    traffic = spy(monkeypatch, active_arm)
    states = active_arm.read()
    assert set(states) == set(NAMES)
    assert all(s.flags & Flag.NOT_ENABLED for s in states.values())
    assert traffic.regs("j1") == [Reg.ANGLEMOVED, Reg.GETENCODERRPM]


@pytest.mark.parametrize("name", ["sim", "emulated"])
def test_deactivated_joint_is_back_drivable_and_its_state_updates(
    make_arm_backend: MakeBackend, name: str
) -> None:
    backend = make_arm_backend(name, initial_qpos=NEAR_END_STOPS)
    arm = Arm(backend)
    arm.configure()
    arm.activate()
    arm.home()
    arm.deactivate()
    backend.sim.set_joint_state({"j3": 1.0})  # type: ignore[union-attr]
    arm.read()
    assert arm.joint_states["j3"].position == pytest.approx(1.0, abs=1e-3)


def test_cleanup_goes_unconfigured_and_deinits_the_joints(active_arm: Arm) -> None:
    active_arm.deactivate()
    active_arm.cleanup()
    assert active_arm.state is Lifecycle.UNCONFIGURED
    assert not any(j.initialized for j in active_arm.joints.values())
    assert not active_arm.gripper.is_initialized


def test_arm_can_be_configured_again_after_cleanup(active_arm: Arm) -> None:
    active_arm.deactivate()
    active_arm.cleanup()
    active_arm.configure()
    active_arm.activate()
    assert active_arm.state is Lifecycle.ACTIVE


def test_shutdown_from_active_finalizes_with_joints_disabled(active_arm: Arm) -> None:
    active_arm.shutdown()
    assert active_arm.state is Lifecycle.FINALIZED
    assert not any(j.is_enabled() for j in active_arm.joints.values())
    assert not any(j.initialized for j in active_arm.joints.values())
    assert not active_arm.gripper.is_initialized


def test_shutdown_from_inactive_finalizes_with_joints_disabled(active_arm: Arm) -> None:
    active_arm.deactivate()
    active_arm.shutdown()
    assert active_arm.state is Lifecycle.FINALIZED
    assert not any(j.is_enabled() for j in active_arm.joints.values())
    assert not any(j.initialized for j in active_arm.joints.values())


def test_shutdown_from_unconfigured_finalizes(arm: Arm) -> None:
    arm.shutdown()
    assert arm.state is Lifecycle.FINALIZED


def test_shutdown_closes_the_emulated_bus(make_arm_backend: MakeBackend) -> None:
    backend = make_arm_backend("emulated")
    assert isinstance(backend, EmulatedBackend)
    with Arm(backend) as arm:
        assert arm.state is Lifecycle.ACTIVE
    assert arm.state is Lifecycle.FINALIZED
    assert backend.bus.closed


def test_arm_as_context_manager_is_active_inside_and_finalized_after(arm: Arm) -> None:
    with arm:
        assert arm.state is Lifecycle.ACTIVE
    assert arm.state is Lifecycle.FINALIZED
    assert not any(j.is_enabled() for j in arm.joints.values())


def _to(arm: Arm, state: Lifecycle) -> None:
    if state is not Lifecycle.UNCONFIGURED:
        arm.configure()
    if state is Lifecycle.ACTIVE:
        arm.activate()
    if state is Lifecycle.FINALIZED:
        arm.shutdown()


WRONG_STATE = [
    (Lifecycle.UNCONFIGURED, "activate", "cannot activate while unconfigured; the arm must be inactive"),
    (Lifecycle.UNCONFIGURED, "deactivate", "cannot deactivate while unconfigured; the arm must be active"),
    (Lifecycle.UNCONFIGURED, "cleanup", "cannot clean up while unconfigured; the arm must be inactive"),
    (Lifecycle.UNCONFIGURED, "read", "cannot read while unconfigured; the arm must be inactive or active"),
    (Lifecycle.UNCONFIGURED, "write", "cannot write while unconfigured; the arm must be active"),
    (Lifecycle.UNCONFIGURED, "home", "cannot home while unconfigured; the arm must be active"),
    (Lifecycle.INACTIVE, "configure", "cannot configure while inactive; the arm must be unconfigured"),
    (Lifecycle.INACTIVE, "deactivate", "cannot deactivate while inactive; the arm must be active"),
    (Lifecycle.INACTIVE, "write", "cannot write while inactive; the arm must be active"),
    (Lifecycle.INACTIVE, "home", "cannot home while inactive; the arm must be active"),
    (Lifecycle.ACTIVE, "configure", "cannot configure while active; the arm must be unconfigured"),
    (Lifecycle.ACTIVE, "activate", "cannot activate while active; the arm must be inactive"),
    (Lifecycle.ACTIVE, "cleanup", "cannot clean up while active; the arm must be inactive"),
    (Lifecycle.FINALIZED, "configure", "cannot configure while finalized; the arm must be unconfigured"),
    (Lifecycle.FINALIZED, "activate", "cannot activate while finalized; the arm must be inactive"),
    (Lifecycle.FINALIZED, "read", "cannot read while finalized; the arm must be inactive or active"),
]


@pytest.mark.parametrize(
    ("state", "action", "message"), WRONG_STATE, ids=[f"{s.value}-{a}" for s, a, _ in WRONG_STATE]
)
def test_transition_from_the_wrong_state_is_refused_naming_both_states(
    mock_arm: Arm, state: Lifecycle, action: str, message: str
) -> None:
    _to(mock_arm, state)
    with pytest.raises(ArmStateError, match=f"^{message}$"):
        getattr(mock_arm, action)()
    assert mock_arm.state is state


@pytest.mark.parametrize("state", [Lifecycle.UNCONFIGURED, Lifecycle.INACTIVE])
def test_claim_is_refused_unless_active(mock_arm: Arm, state: Lifecycle) -> None:
    _to(mock_arm, state)
    message = f"cannot claim home on j1 while {state.value}; the arm must be active"
    with pytest.raises(ArmStateError, match=message):
        mock_arm.claim("j1", "home")


def test_arm_state_error_is_an_incorrect_state_error(mock_arm: Arm) -> None:
    with pytest.raises(IncorrectStateError):
        mock_arm.activate()


# ----------------------------------------------------------- error recovery


def test_configure_with_a_joint_missing_raises_comm_error_and_stays_unconfigured(
    make_arm_backend: MakeBackend,
) -> None:
    backend = make_arm_backend("emulated")
    assert isinstance(backend, EmulatedBackend)
    del backend.bus.devices[0x13]
    arm = Arm(backend)
    with pytest.raises(CommError, match=r"j3 \(0x13\): PING failed"):
        arm.configure()
    assert arm.state is Lifecycle.UNCONFIGURED
    assert not any(j.initialized for j in arm.joints.values())
    assert not arm.gripper.is_initialized


def test_configure_on_a_dead_bus_names_the_first_joint(make_arm_backend: MakeBackend) -> None:
    arm = Arm(make_arm_backend("emulated", faults=FaultPlan(nack=1.0)))
    with pytest.raises(CommError, match=r"j1 \(0x11\): PING failed after 3 attempts"):
        arm.configure()
    assert arm.state is Lifecycle.UNCONFIGURED


def test_arm_configures_once_the_bus_is_healthy_again(make_arm_backend: MakeBackend) -> None:
    backend = make_arm_backend("emulated", faults=FaultPlan(nack=1.0))
    assert isinstance(backend, EmulatedBackend)
    arm = Arm(backend)
    with pytest.raises(CommError):
        arm.configure()
    backend.bus.faults = FaultPlan()
    arm.configure()
    assert arm.state is Lifecycle.INACTIVE


def test_recover_from_active_disables_the_joints_and_goes_unconfigured(active_arm: Arm) -> None:
    active_arm.recover()
    assert active_arm.state is Lifecycle.UNCONFIGURED
    assert not any(j.is_enabled() for j in active_arm.joints.values())
    assert not any(j.initialized for j in active_arm.joints.values())
    assert not active_arm.gripper.is_initialized


def test_recover_leaves_a_finalized_arm_finalized(mock_arm: Arm) -> None:
    mock_arm.shutdown()
    mock_arm.recover()
    assert mock_arm.state is Lifecycle.FINALIZED


@pytest.fixture
def emulated_homed_arm(make_arm_backend: MakeBackend) -> Arm:
    """An active, homed arm on the emulated backend (its bus is ``arm.backend.bus``)."""
    arm = Arm(make_arm_backend("emulated", initial_qpos=NEAR_END_STOPS))
    arm.configure()
    arm.activate()
    arm.home()
    return arm


def test_failed_read_raises_and_deactivates_the_arm(emulated_homed_arm: Arm) -> None:
    arm = emulated_homed_arm
    arm.claim("j1", "position")
    arm.backend.bus.faults = FaultPlan(nack=1.0)  # type: ignore[attr-defined]
    with pytest.raises(CommError, match=r"j1 \(0x11\): ANGLEMOVED failed"):
        arm.read()
    assert arm.state is Lifecycle.INACTIVE
    assert set(arm.modes.values()) == {CommandMode.NONE}


def test_failed_write_raises_and_deactivates_the_arm(emulated_homed_arm: Arm) -> None:
    arm = emulated_homed_arm
    arm.claim("j2", "position")
    arm.backend.bus.faults = FaultPlan(nack=1.0)  # type: ignore[attr-defined]
    with pytest.raises(CommError, match=r"j2 \(0x12\): MOVETOANGLE failed"):
        arm.write()
    assert arm.state is Lifecycle.INACTIVE


def test_state_updates_again_after_a_failed_read_once_the_bus_recovers(emulated_homed_arm: Arm) -> None:
    arm = emulated_homed_arm
    arm.backend.bus.faults = FaultPlan(nack=1.0)  # type: ignore[attr-defined]
    with pytest.raises(CommError):
        arm.read()
    arm.backend.bus.faults = FaultPlan()  # type: ignore[attr-defined]
    arm.read()
    assert arm.joint_states["j1"].position == pytest.approx(CONFIG.joint("j1").max, abs=1e-3)
    arm.activate()
    assert arm.state is Lifecycle.ACTIVE


def test_failed_activate_falls_back_to_unconfigured(make_arm_backend: MakeBackend) -> None:
    backend = make_arm_backend("emulated")
    assert isinstance(backend, EmulatedBackend)
    arm = Arm(backend)
    arm.configure()
    backend.bus.faults = FaultPlan(nack=1.0)
    with pytest.raises(CommError, match=r"j1 \(0x11\): SETUP failed"):
        arm.activate()
    assert arm.state is Lifecycle.UNCONFIGURED
    assert not any(j.initialized for j in arm.joints.values())
    assert not arm.gripper.is_initialized


@pytest.mark.parametrize("name", ["sim", "emulated"])
def test_stall_in_velocity_mode_raises_on_write_and_deactivates_the_arm(
    make_arm_backend: MakeBackend, name: str
) -> None:
    arm = Arm(make_arm_backend(name, initial_qpos=NEAR_END_STOPS))
    arm.configure()
    arm.activate()
    arm.home()
    arm.claim("j1", "velocity")
    arm.set_command("j1", 0.5)  # into the max end stop it homed against
    with pytest.raises(StalledError, match="j1: joint stalled"):
        cycle_until(arm, lambda: False, max_s=2.0)
    assert arm.state is Lifecycle.INACTIVE


def test_failed_deactivate_falls_back_to_unconfigured(emulated_homed_arm: Arm) -> None:
    arm = emulated_homed_arm
    arm.backend.bus.faults = FaultPlan(nack=1.0)  # type: ignore[attr-defined]
    with pytest.raises(CommError, match=r"j1 \(0x11\): STOP failed"):
        arm.deactivate()
    assert arm.state is Lifecycle.UNCONFIGURED


# ------------------------------------------------------------ command modes


def test_claiming_position_starts_at_the_measured_position(homed_arm: Arm) -> None:
    homed_arm.claim("j3", CommandMode.POSITION)
    assert homed_arm.modes["j3"] is CommandMode.POSITION
    assert homed_arm.commands["j3"] == homed_arm.joint_states["j3"].position


def test_claiming_velocity_starts_at_zero(homed_mock_arm: Arm) -> None:
    homed_mock_arm.claim("j3", "velocity")
    assert homed_mock_arm.commands["j3"] == 0.0


def test_claiming_the_active_interface_again_is_a_no_op(homed_mock_arm: Arm) -> None:
    homed_mock_arm.claim("j1", "position")
    homed_mock_arm.set_command("j1", 1.0)
    homed_mock_arm.claim("j1", "position")
    assert homed_mock_arm.modes["j1"] is CommandMode.POSITION
    assert homed_mock_arm.commands["j1"] == 1.0


@pytest.mark.parametrize(
    ("first", "second"), [("position", "velocity"), ("velocity", "home"), ("home", "position")]
)
def test_second_interface_on_a_joint_is_refused(homed_mock_arm: Arm, first: str, second: str) -> None:
    homed_mock_arm.claim("j2", first)
    with pytest.raises(
        ArmStateError, match=f"j2: {first} interface is active; release it before claiming {second}"
    ):
        homed_mock_arm.claim("j2", second)
    assert homed_mock_arm.modes["j2"] is CommandMode(first)


def test_another_interface_may_be_claimed_after_release(homed_mock_arm: Arm) -> None:
    homed_mock_arm.claim("j2", "position")
    homed_mock_arm.release("j2")
    homed_mock_arm.claim("j2", "velocity")
    assert homed_mock_arm.modes["j2"] is CommandMode.VELOCITY


def test_interfaces_on_different_joints_are_independent(homed_mock_arm: Arm) -> None:
    homed_mock_arm.claim("j1", "position")
    homed_mock_arm.claim("j2", "velocity")
    homed_mock_arm.claim("j3", "home")
    assert [homed_mock_arm.modes[n] for n in NAMES] == [
        CommandMode.POSITION,
        CommandMode.VELOCITY,
        CommandMode.HOME,
        CommandMode.NONE,
    ]


@pytest.mark.parametrize("mode", ["position", "velocity"])
def test_motion_interface_refused_on_an_unhomed_joint(active_arm: Arm, mode: str) -> None:
    with pytest.raises(NotHomedError, match=f"j4: cannot command {mode} on an unhomed joint; home it first"):
        active_arm.claim("j4", mode)
    assert active_arm.modes["j4"] is CommandMode.NONE


def test_home_interface_allowed_on_an_unhomed_joint(active_arm: Arm) -> None:
    active_arm.claim("j4", "home")
    assert active_arm.modes["j4"] is CommandMode.HOME
    assert active_arm.commands["j4"] == 0.0


def test_set_command_without_a_claimed_interface_is_refused(homed_mock_arm: Arm) -> None:
    with pytest.raises(ArmStateError, match="j1: no command interface is active; claim one first"):
        homed_mock_arm.set_command("j1", 0.5)


def test_release_home_while_homing_is_refused(active_arm: Arm) -> None:
    start_homing(active_arm, "j1", 0.03)
    with pytest.raises(ArmStateError, match=r"j1: homing is running; abort it \(home command 0\)"):
        active_arm.release("j1")
    assert active_arm.modes["j1"] is CommandMode.HOME


def test_release_velocity_stops_the_joint(homed_arm: Arm) -> None:
    homed_arm.claim("j1", "velocity")
    homed_arm.set_command("j1", -0.2)  # away from the max end stop it homed to
    for _ in range(5):
        homed_arm.cycle(DT)
    assert homed_arm.joint_states["j1"].velocity < -0.01
    homed_arm.release("j1")
    for _ in range(10):
        homed_arm.cycle(DT)
    assert homed_arm.joint_states["j1"].velocity == pytest.approx(0.0, abs=1e-3)
    assert homed_arm.state is Lifecycle.ACTIVE


@pytest.mark.parametrize(
    "call",
    [
        pytest.param(lambda arm: arm.claim("j9", "position"), id="claim"),
        pytest.param(lambda arm: arm.release("j9"), id="release"),
        pytest.param(lambda arm: arm.set_command("j9", 0.0), id="set_command"),
    ],
)
def test_unknown_joint_name_is_refused_listing_the_known_joints(
    homed_mock_arm: Arm, call: Callable[[Arm], None]
) -> None:
    with pytest.raises(InvalidArgumentError, match=f"unknown joint 'j9'; {KNOWN_JOINTS}"):
        call(homed_mock_arm)


def test_home_of_an_unknown_joint_is_refused_listing_the_known_joints(homed_mock_arm: Arm) -> None:
    with pytest.raises(InvalidArgumentError, match=f"unknown joint 'j9'; {KNOWN_JOINTS}"):
        homed_mock_arm.home(["j9"])


@pytest.mark.parametrize("mode", ["position", "velocity", "home"])
@pytest.mark.parametrize("value", [math.nan, math.inf, -math.inf])
def test_non_finite_command_is_refused(homed_mock_arm: Arm, mode: str, value: float) -> None:
    homed_mock_arm.claim("j1", mode)
    before = homed_mock_arm.commands["j1"]
    with pytest.raises(InvalidArgumentError, match=f"j1: {mode} command {value} must be finite"):
        homed_mock_arm.set_command("j1", value)
    assert homed_mock_arm.commands["j1"] == before


@pytest.mark.parametrize("name", NAMES)
def test_position_command_is_clamped_to_the_joint_limits(homed_mock_arm: Arm, name: str) -> None:
    cfg = CONFIG.joint(name)
    homed_mock_arm.claim(name, "position")
    homed_mock_arm.set_command(name, cfg.max + 1.0)
    assert homed_mock_arm.commands[name] == cfg.max
    homed_mock_arm.set_command(name, cfg.min - 1.0)
    assert homed_mock_arm.commands[name] == cfg.min
    inside = (cfg.min + cfg.max) / 2 + 0.001
    homed_mock_arm.set_command(name, inside)
    assert homed_mock_arm.commands[name] == inside


@pytest.mark.parametrize("name", NAMES)
def test_velocity_command_is_clamped_to_max_velocity(homed_mock_arm: Arm, name: str) -> None:
    cfg = CONFIG.joint(name)
    homed_mock_arm.claim(name, "velocity")
    homed_mock_arm.set_command(name, 10 * cfg.max_velocity)
    assert homed_mock_arm.commands[name] == cfg.max_velocity
    homed_mock_arm.set_command(name, -10 * cfg.max_velocity)
    assert homed_mock_arm.commands[name] == -cfg.max_velocity
    homed_mock_arm.set_command(name, cfg.max_velocity / 2)
    assert homed_mock_arm.commands[name] == cfg.max_velocity / 2


def test_home_command_is_a_signed_speed_and_not_clamped(active_arm: Arm) -> None:
    active_arm.claim("j1", "home")
    active_arm.set_command("j1", -0.03)
    assert active_arm.commands["j1"] == -0.03


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
    assert active_arm.state is Lifecycle.INACTIVE  # a failed write deactivates the arm


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
        pytest.approx(motor_rate_deg("j4", cfg.homing.acceleration)),
        pytest.approx(motor_rate_deg("j4", cfg.max_acceleration)),
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


# --------------------------------------------------------------- read order


def test_read_asks_position_then_velocity_of_each_joint_in_order(
    homed_arm: Arm, monkeypatch: pytest.MonkeyPatch
) -> None:
    traffic = spy(monkeypatch, homed_arm)
    homed_arm.read()
    assert [(name, reg) for name, reg, _ in traffic.log] == [
        (name, reg) for name in NAMES for reg in (Reg.ANGLEMOVED, Reg.GETENCODERRPM)
    ]


def test_read_finishes_a_homing_after_position_and_velocity(
    active_arm: Arm, monkeypatch: pytest.MonkeyPatch
) -> None:
    start_homing(active_arm, "j1", 0.03)
    joint = active_arm.joints["j1"]
    while joint.is_busy():
        active_arm.backend.step(DT)
        joint.get_flags()
    traffic = spy(monkeypatch, active_arm)
    active_arm.read()
    j1 = [(reg, value) for name, reg, value in traffic.log if name == "j1"]
    position = j1.index((Reg.ANGLEMOVED, None))
    velocity = j1.index((Reg.GETENCODERRPM, None))
    post_homing = j1.index((Reg.PING, None))
    offset_written = next(i for i, (reg, v) in enumerate(j1) if reg is Reg.HOMEOFFSET and v is not None)
    assert position < velocity < post_homing < offset_written
    assert active_arm.joint_states["j1"].homed


def test_home_state_is_the_flags_of_the_newest_transaction(homed_arm: Arm) -> None:
    state = homed_arm.read()["j2"]
    assert state.flags == homed_arm.joints["j2"].flags
    assert state.homed == homed_arm.joints["j2"].is_homed()


def test_read_on_the_emulated_bus_is_position_then_velocity_per_address(
    emulated_homed_arm: Arm, monkeypatch: pytest.MonkeyPatch
) -> None:
    bus = emulated_homed_arm.backend.bus  # type: ignore[attr-defined]
    devices = emulated_homed_arm.backend.devices  # type: ignore[attr-defined]
    counts = {address: d.transactions for address, d in devices.items()}
    sent: list[tuple[int, bytes]] = []
    transfer = bus.transfer

    def recording_transfer(address: int, data: bytes, read_len: int) -> bytes:
        sent.append((address, bytes(data)))
        return transfer(address, data, read_len)

    monkeypatch.setattr(bus, "transfer", recording_transfer)
    emulated_homed_arm.read()
    assert sent == [
        (address, bytes([reg]))
        for address in (0x11, 0x12, 0x13, 0x14)
        for reg in (Reg.ANGLEMOVED, Reg.GETENCODERRPM)
    ]
    assert {a: d.transactions - counts[a] for a, d in devices.items()} == dict.fromkeys(counts, 2)


# ------------------------------------------------------------------- writes


def test_write_sends_only_the_active_interfaces(homed_arm: Arm, monkeypatch: pytest.MonkeyPatch) -> None:
    homed_arm.claim("j1", "position")
    homed_arm.claim("j2", "velocity")
    traffic = spy(monkeypatch, homed_arm)
    homed_arm.write()
    assert traffic.regs("j1") == [Reg.MOVETOANGLE]
    assert traffic.regs("j2") == [Reg.SETRPM]
    assert traffic.regs("j3") == []
    assert traffic.regs("j4") == []


def test_write_calls_no_motion_method_of_an_unclaimed_joint(
    homed_arm: Arm, monkeypatch: pytest.MonkeyPatch
) -> None:
    calls: list[str] = []
    for name, joint in homed_arm.joints.items():
        monkeypatch.setattr(joint, "set_position", lambda q, _n=name: calls.append(f"{_n}.set_position"))
        monkeypatch.setattr(joint, "set_velocity", lambda v, _n=name: calls.append(f"{_n}.set_velocity"))
    homed_arm.claim("j3", "velocity")
    homed_arm.write()
    assert calls == ["j3.set_velocity"]


def test_write_with_nothing_claimed_sends_nothing(homed_arm: Arm, monkeypatch: pytest.MonkeyPatch) -> None:
    traffic = spy(monkeypatch, homed_arm)
    homed_arm.write()
    assert traffic.log == []


def test_position_command_moves_the_joint(homed_arm: Arm) -> None:
    homed_arm.claim("j3", "position")
    homed_arm.set_command("j3", 2.0)
    cycle_until(homed_arm, lambda: abs(homed_arm.joint_states["j3"].position - 2.0) < 1e-3, max_s=5.0)


def test_cycle_writes_lets_time_pass_and_reads(homed_arm: Arm) -> None:
    clock = homed_arm.backend.clock
    start = clock.now()
    states = homed_arm.cycle(DT)
    assert clock.now() - start == pytest.approx(DT, abs=1e-9)
    assert states is homed_arm.joint_states


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
    with pytest.raises(ArmStateError, match="j1: homing is running and enabling would stop it"):
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


# ---------------------------------------------- attach and adopt_homing


def enable_and_home_elsewhere(arm: Arm, name: str, speed: float) -> None:
    """Leave ``name`` as an earlier process would have: enabled and homing at ``speed``.

    The homing is started through the joint's register primitive, so this
    process's driver knows nothing of it (no blocking command, no offset);
    then the arm reads the state, as :meth:`Arm.configure` would.
    """
    cfg = CONFIG.joint(name)
    joint = arm.joints[name]
    joint.enable(cfg.drive_current, cfg.hold_current)
    rpm = joint.homing_rpm(speed)
    joint._command(
        Reg.HOME, pack_bytes(int(rpm > 0), int(abs(rpm)), cfg.homing.threshold, cfg.homing.current)
    )
    arm.read()


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
