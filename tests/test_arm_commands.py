"""The arm's command interfaces and I/O (docs/arm.md, "The arm layer").

Covers claiming and releasing the position, velocity and home interfaces of each joint (one per
joint, motion only on homed joints), set_command (unknown joints, non-finite values, clamping to
the joint limits and max velocity), the order read asks each joint's position and velocity
(checked byte for byte on the emulated bus), write sending only the claimed interfaces, and cycle.
"""

from __future__ import annotations

import errno
import math
from collections.abc import Callable

import pytest
from rigs import (
    CONFIG,
    DT,
    KNOWN_JOINTS,
    NAMES,
    NEAR_END_STOPS,
    MakeBackend,
    cycle_until,
    spy,
    start_homing,
    wait_for_homing_end,
)

from bioscara_gym.hardware.arm import Arm, ArmStateError, CommandMode, Lifecycle
from bioscara_gym.hardware.backends import EmulatedBackend
from bioscara_gym.hardware.errors import (
    CommError,
    InvalidArgumentError,
    NotHomedError,
)
from bioscara_gym.hardware.registers import Reg

# ------------------------------------------------------------ command modes


def test_claiming_position_starts_at_the_measured_position(homed_arm: Arm) -> None:
    homed_arm.claim("j3", CommandMode.POSITION)
    assert homed_arm.modes["j3"] is CommandMode.POSITION
    assert homed_arm.commands["j3"] == homed_arm.joint_states["j3"].position


def test_claiming_velocity_starts_at_zero(homed_mock_arm: Arm) -> None:
    homed_mock_arm.claim("j3", "velocity")
    assert homed_mock_arm.commands["j3"] == 0.0


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


def turn_j3(homed_arm: Arm) -> None:
    """j3 turning at some 4 rad/s, the other joints powered and holding (an unclaimed joint freewheels)."""
    for name in ("j1", "j2", "j4"):
        homed_arm.claim(name, "position")
    homed_arm.claim("j3", "velocity")
    homed_arm.set_command("j3", -4.0)  # away from the max end stop it homed to
    for _ in range(15):
        homed_arm.cycle(DT)
    assert homed_arm.joint_states["j3"].velocity < -2.0


def test_deactivate_brakes_a_turning_joint_before_its_current_is_cut(homed_arm: Arm) -> None:
    # Seen (a hostile test, through the safe stop): STOP then currents 0 a millisecond
    # later; the firmware's STOP ramps the speed down, which takes current, so the
    # unbraked arm coasted on. Deactivate brakes first, as the safe stop does.
    sim = getattr(homed_arm.backend, "sim", None)
    if sim is None:
        pytest.skip("the mock has no rotor to coast")
    turn_j3(homed_arm)
    homed_arm.deactivate()
    before = sim.joint_positions().copy()
    homed_arm.backend.step(2.0)
    assert abs(sim.joint_positions() - before).max() < 1e-3


def test_a_configure_failed_on_one_joint_brakes_a_turning_joint_before_its_current_is_cut(
    make_arm_backend: MakeBackend, monkeypatch: pytest.MonkeyPatch
) -> None:
    # An earlier process left j3 turning; now j1 does not answer. The failed
    # configure disables the joints that answered, and it had read no speed,
    # so it sent STOP and cut j3's current a millisecond later: j3 coasted on.
    backend = make_arm_backend("emulated", initial_qpos=NEAR_END_STOPS)
    assert isinstance(backend, EmulatedBackend)
    homed_arm = Arm(backend)
    homed_arm.configure()
    homed_arm.activate()
    homed_arm.home()
    turn_j3(homed_arm)
    for joint in backend.joints.values():
        joint.deinit()  # the process ends; the firmware keeps turning j3
    transfer = backend.bus.transfer

    def j1_deaf(address: int, data: bytes, read_len: int) -> bytes:
        if address == 0x11:  # its line broken; its firmware still holds j1
            raise OSError(errno.EREMOTEIO, "Remote I/O error")
        return transfer(address, data, read_len)

    monkeypatch.setattr(backend.bus, "transfer", j1_deaf)
    arm = Arm(backend)
    with pytest.raises(CommError, match=r"j1 \(0x11\): PING failed"):
        arm.configure()
    before = backend.sim.joint_positions().copy()
    backend.step(2.0)
    assert abs(backend.sim.joint_positions() - before).max() < 1e-3


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


@pytest.mark.parametrize(("value", "stored"), [(-0.03, -1.0), (5.0, 1.0), (1.0, 1.0), (0.0, 0.0)])
def test_home_command_counts_by_its_sign(active_arm: Arm, value: float, stored: float) -> None:
    active_arm.claim("j1", "home")
    active_arm.set_command("j1", value)
    assert active_arm.commands["j1"] == stored


@pytest.mark.parametrize(
    ("name", "command", "home_bytes"),
    [
        # HOME payload: direction (1 = positive), RPM, sensitivity, current. The configured
        # homing speed, whatever the command's size (SPEC's parameter table):
        # j1 0.03 rad/s x 35 = 10.03 RPM, threshold 30, current 15.
        ("j1", 1.0, bytes([0x2D, 1, 10, 30, 15])),
        ("j1", 250.0, bytes([0x2D, 1, 10, 30, 15])),
        # j3 0.05 rad/s x 24 = 11.46 RPM, threshold 25, current 10; -1 homes to the min stop.
        ("j3", -1.0, bytes([0x2D, 0, 11, 25, 10])),
    ],
)
def test_home_command_sends_the_configured_homing_on_the_wire(
    make_arm_backend: MakeBackend, name: str, command: float, home_bytes: bytes
) -> None:
    arm = Arm(make_arm_backend("emulated"))
    arm.configure()
    arm.activate()
    sent: list[bytes] = []
    transfer = arm.backend.bus.transfer

    def recording(address: int, data: bytes, read_len: int) -> bytes:
        sent.append(bytes(data))
        return transfer(address, data, read_len)

    arm.backend.bus.transfer = recording  # type: ignore[method-assign]
    arm.claim(name, "home")
    arm.set_command(name, command)
    arm.write()
    assert [d for d in sent if d[0] == 0x2D] == [home_bytes]


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
    wait_for_homing_end(active_arm, "j1")
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
    homed_arm.cycle(DT)  # on the schedule: each cycle now starts DT after the last
    start = clock.now()
    states = homed_arm.cycle(DT)
    assert clock.now() - start == pytest.approx(DT, abs=1e-9)
    assert states is homed_arm.joint_states
