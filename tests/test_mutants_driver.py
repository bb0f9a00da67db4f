"""Tests that kill mutants mutmut found surviving in the driver layer (docs/mutation.md).

Codec, ``Joint`` and ``BaseJoint``: expected values are docs/protocol.md's
and docs/arm.md's, written as literals (bytes on the wire, motor degrees),
on the byte-level ``scripted_bus`` of ``conftest.py``.
"""

from __future__ import annotations

import struct
from collections.abc import Callable
from typing import Any

import pytest

from bioscara_gym.hardware.clock import ManualClock
from bioscara_gym.hardware.codec import pack_bytes
from bioscara_gym.hardware.errors import CommError, InvalidArgumentError
from bioscara_gym.hardware.joint import Joint
from bioscara_gym.hardware.transmission import actuator_to_joint, joint_to_actuator

# docs/model.md: j1 reduction 35, limits +-3.04647 rad.
J1_LIMIT = 3.04647
READY, STALL, BUSY, NOT_HOMED, NOT_ENABLED = 0x00, 0x01, 0x02, 0x04, 0x08


def flags(value: int) -> bytes:
    return bytes((value,))


def ack(value: int) -> bytes:
    return b"O" + flags(value)


@pytest.fixture
def make_j1(scripted_bus: Any) -> Callable[..., Joint]:
    """j1 on the scripted bus, ``init()``-ed homed and ready (offset ``max``), log cleared."""

    def make(retries: int = 2) -> Joint:
        joint = Joint(
            "j1", 0x11, 35.0, -J1_LIMIT, J1_LIMIT, scripted_bus, retries=retries, clock=ManualClock()
        )
        scripted_bus.queue(ack(READY), struct.pack("<f", J1_LIMIT) + flags(READY))
        joint.init()
        scripted_bus.clear_log()
        return joint

    return make


# ------------------------------------------------------------------ codec
def test_pack_bytes_of_byte0_alone_is_that_byte() -> None:
    # docs/protocol.md: SETUP byte0 = drive current; bytes 1-3 default to 0.
    assert pack_bytes(20) == 20


def test_transmission_offset_defaults_to_zero() -> None:
    # docs/model.md: actuator = reduction x (joint - offset); j1 reduction 35.
    assert joint_to_actuator(2.0, 35.0) == 70.0
    assert actuator_to_joint(70.0, 35.0) == 2.0


# ------------------------------------------------------------ reply checks
def test_comm_error_names_the_flag_a_command_reply_lacks(
    scripted_bus: Any, make_j1: Callable[..., Joint]
) -> None:
    # docs/protocol.md: SETCURRENT 0 sets NOTENABLED in its own reply.
    joint = make_j1()
    scripted_bus.queue(flags(NOT_HOMED), flags(NOT_HOMED), flags(NOT_HOMED))
    with pytest.raises(CommError) as err:
        joint.set_drive_current(0)
    assert "lack <Flag.NOT_ENABLED: 8>, which SETCURRENT sets" in str(err.value)


def test_comm_error_names_the_flag_a_command_reply_shows(
    scripted_bus: Any, make_j1: Callable[..., Joint]
) -> None:
    # docs/protocol.md: STOP clears BUSY in its own reply; NOTHOMED is not STOP's business.
    joint = make_j1()
    scripted_bus.queue(flags(BUSY | NOT_HOMED), flags(BUSY | NOT_HOMED), flags(BUSY | NOT_HOMED))
    with pytest.raises(CommError) as err:
        joint.stop()
    assert "show <Flag.BUSY: 2>, which STOP clears" in str(err.value)


def test_payload_out_of_range_error_names_the_joint(make_j1: Callable[..., Joint]) -> None:
    joint = make_j1()
    with pytest.raises(InvalidArgumentError) as err:
        joint.move_steps(2**31)  # beyond int32
    assert err.value.joint == "j1"


@pytest.mark.parametrize("offset", [-3.0, 3.0])
def test_home_offset_exactly_a_tenth_of_the_range_beyond_a_limit_is_accepted(
    scripted_bus: Any, offset: float
) -> None:
    # docs/protocol.md: HOMEOFFSET beyond [min, max] by MORE than 10 % of the
    # range is implausible. Limits +-2.5 (range 5): +-3.0 is exactly on the bound.
    joint = Joint("j1", 0x11, 35.0, -2.5, 2.5, scripted_bus, clock=ManualClock())
    scripted_bus.queue(ack(READY), struct.pack("<f", offset) + flags(READY))
    joint.init()
    assert joint.offset == offset
    assert joint.stats.total_errors == 0


#: A joint whose conversions are exact in binary: one motor degree per joint
#: degree (reduction pi/180 motor rad per rad), limits +-2.5 (range 5, margin 0.5).
EXACT_REDUCTION = 0.017453292519943295


def exact_joint(scripted_bus: Any, state: int) -> Joint:
    joint = Joint("jx", 0x11, EXACT_REDUCTION, -2.5, 2.5, scripted_bus, clock=ManualClock())
    scripted_bus.queue(ack(state))
    if not state & NOT_HOMED:
        scripted_bus.queue(struct.pack("<f", 2.5) + flags(state))  # HOMEOFFSET: homed at max
    joint.init()
    return joint


@pytest.mark.parametrize(("degrees", "position"), [(-5.5, -3.0), (0.5, 3.0)])
def test_homed_position_exactly_a_tenth_of_the_range_beyond_a_stop_is_accepted(
    scripted_bus: Any, degrees: float, position: float
) -> None:
    # docs/protocol.md: a homed position beyond [min, max] by MORE than 10 % of the range is implausible.
    joint = exact_joint(scripted_bus, READY)
    scripted_bus.queue(struct.pack("<f", degrees) + flags(READY))
    assert joint.get_position() == position
    assert joint.stats.total_errors == 0


@pytest.mark.parametrize("degrees", [-365.5, 365.5])
def test_unhomed_angle_exactly_the_travel_plus_one_turn_is_accepted(
    scripted_bus: Any, degrees: float
) -> None:
    # docs/protocol.md: not homed, MORE than the range (+ margin) plus one motor
    # turn from 0 is implausible: here 5.5 deg + 360 deg.
    joint = exact_joint(scripted_bus, NOT_HOMED)
    scripted_bus.queue(struct.pack("<f", degrees) + flags(NOT_HOMED))
    assert joint.get_position() == 0.0
    assert joint.stats.total_errors == 0


def test_encoder_speed_of_exactly_4500_rpm_is_accepted(
    scripted_bus: Any, make_j1: Callable[..., Joint]
) -> None:
    # docs/protocol.md: MORE than 4500 motor RPM is implausible. 4500 RPM =
    # 27000 deg/s = 471.239 rad/s at the motor, / 35 = 13.464 rad/s at j1.
    joint = make_j1()
    scripted_bus.queue(struct.pack("<f", 4500.0) + flags(READY))
    assert joint.get_velocity() == pytest.approx(13.46397, abs=1e-5)
    assert joint.stats.total_errors == 0


@pytest.mark.parametrize(
    ("reply", "problem"),
    [
        (b"\x00", "reply of 1 bytes, expected 5 (reply 00)"),
        (b"", "reply of 0 bytes, expected 5 (reply empty)"),
        (struct.pack("<f", 0.0) + b"\xff", "flags byte 0xff has reserved bits set"),
        (struct.pack("<f", float("inf")) + flags(READY), "value inf is not finite"),
    ],
)
def test_comm_error_says_what_was_wrong_with_the_reply(
    scripted_bus: Any, make_j1: Callable[..., Joint], reply: bytes, problem: str
) -> None:
    joint = make_j1()
    scripted_bus.queue(reply, reply, reply)
    with pytest.raises(CommError) as err:
        joint.get_velocity()  # GETENCODERRPM: float32 + flags
    assert problem in str(err.value)


def test_comm_error_says_what_ping_answered(scripted_bus: Any, make_j1: Callable[..., Joint]) -> None:
    joint = make_j1()
    scripted_bus.queue(b"N\x00", b"N\x00", b"N\x00")
    with pytest.raises(CommError) as err:
        joint.get_flags()
    assert "PING answered 78, expected 79 ('O')" in str(err.value)


def test_stats_count_a_retry_after_a_bus_error(scripted_bus: Any, make_j1: Callable[..., Joint]) -> None:
    # Two NACKs, then the reply: 3 attempts, the 2nd and 3rd are retries, 2 bus errors.
    joint = make_j1()
    joint.stats.reset()
    scripted_bus.queue(OSError(121, "NACK"), OSError(121, "NACK"), struct.pack("<f", 0.0) + flags(READY))
    joint.get_velocity()
    assert (joint.stats.transactions, joint.stats.retries, joint.stats.bus_errors) == (3, 2, 2)


def test_stats_count_a_retry_after_a_malformed_reply(
    scripted_bus: Any, make_j1: Callable[..., Joint]
) -> None:
    joint = make_j1()
    joint.stats.reset()
    short = b"\x00"
    scripted_bus.queue(short, short, struct.pack("<f", 0.0) + flags(READY))
    joint.get_velocity()
    assert (joint.stats.transactions, joint.stats.retries, joint.stats.malformed) == (3, 2, 2)


@pytest.mark.parametrize("address", [0x03, 0x77])
def test_driver_accepts_the_first_and_last_usable_address(scripted_bus: Any, address: int) -> None:
    # docs/protocol.md: the driver accepts any address 0x03-0x77.
    joint = Joint("j1", address, 35.0, -J1_LIMIT, J1_LIMIT, scripted_bus, clock=ManualClock())
    assert joint.address == address


def test_driver_tries_a_read_three_times_by_default(scripted_bus: Any) -> None:
    # docs/protocol.md: a rejected reply is read again, 2 retries by default.
    joint = Joint("j1", 0x11, 35.0, -J1_LIMIT, J1_LIMIT, scripted_bus, clock=ManualClock())
    scripted_bus.queue(OSError(121, "NACK"), OSError(121, "NACK"), OSError(121, "NACK"))
    with pytest.raises(CommError):
        joint.init()
    assert len(scripted_bus.log) == 3


@pytest.mark.parametrize("address", [0x02, 0x78])
def test_driver_refuses_a_reserved_address_naming_it_and_the_joint(scripted_bus: Any, address: int) -> None:
    with pytest.raises(InvalidArgumentError) as err:
        Joint("j1", address, 35.0, -J1_LIMIT, J1_LIMIT, scripted_bus, clock=ManualClock())
    assert str(err.value).endswith(f"I2C address {address:#04x} is outside 0x03-0x77")
    assert err.value.joint == "j1"


def test_driver_refuses_negative_retries_naming_the_joint(scripted_bus: Any) -> None:
    with pytest.raises(InvalidArgumentError) as err:
        Joint("j1", 0x11, 35.0, -J1_LIMIT, J1_LIMIT, scripted_bus, retries=-1, clock=ManualClock())
    assert str(err.value).endswith("retries -1 must be >= 0")
    assert err.value.joint == "j1"


# -------------------------------------------------------------- BaseJoint
def test_adopt_homing_refuses_zero_velocity_naming_the_joint(make_j1: Callable[..., Joint]) -> None:
    joint = make_j1()
    with pytest.raises(InvalidArgumentError) as err:
        joint.adopt_homing(0.0)
    assert str(err.value).endswith("homing velocity must be non-zero; its sign picks the end stop")
    assert err.value.joint == "j1"


def test_adopt_homing_refuses_a_non_finite_velocity_by_name(make_j1: Callable[..., Joint]) -> None:
    joint = make_j1()
    with pytest.raises(InvalidArgumentError) as err:
        joint.adopt_homing(float("nan"))
    assert str(err.value).endswith("homing velocity nan must be finite")


@pytest.mark.parametrize(("velocity", "offset"), [(1.0, J1_LIMIT), (-0.5, -J1_LIMIT)])
def test_adopted_homing_stores_the_end_stop_of_its_sign(
    scripted_bus: Any, make_j1: Callable[..., Joint], velocity: float, offset: float
) -> None:
    # docs/arm.md: positive homes to max, negative to min; post_homing writes it as HOMEOFFSET.
    joint = make_j1()
    joint.adopt_homing(velocity)
    assert joint.current_blocking_command == 0x2D  # HOME
    scripted_bus.queue(ack(READY), flags(READY))  # PING (homed), HOMEOFFSET write
    joint.post_homing()
    assert scripted_bus.writes()[-1] == bytes([0x2E]) + struct.pack("<f", offset)


def test_move_steps_refuses_a_non_integer_naming_the_joint(make_j1: Callable[..., Joint]) -> None:
    joint = make_j1()
    with pytest.raises(InvalidArgumentError) as err:
        joint.move_steps(1.5)  # type: ignore[arg-type]
    assert str(err.value).endswith("steps 1.5 must be an integer")
    assert err.value.joint == "j1"


def test_check_orientation_turns_2_degrees_by_default(
    scripted_bus: Any, make_j1: Callable[..., Joint]
) -> None:
    # docs/arm.md: check_orientation(angle=2.0); CHECKORIENTATION float32 degrees.
    joint = make_j1()
    scripted_bus.queue(flags(BUSY), ack(READY))  # CHECKORIENTATION (BUSY), PING: done
    joint.check_orientation()
    assert scripted_bus.writes()[0] == bytes([0x2B, 0x00, 0x00, 0x00, 0x40])


def test_check_orientation_refuses_a_non_finite_angle_by_name(make_j1: Callable[..., Joint]) -> None:
    joint = make_j1()
    with pytest.raises(InvalidArgumentError) as err:
        joint.check_orientation(float("inf"))
    assert str(err.value).endswith("orientation angle inf must be finite")


NACK = OSError(121, "NACK")


def test_disable_with_two_failed_steps_lists_both(scripted_bus: Any, make_j1: Callable[..., Joint]) -> None:
    joint = make_j1()
    scripted_bus.queue(flags(READY))  # STOP
    scripted_bus.queue(NACK, NACK, NACK)  # SETHOLDCURRENT 0: lost
    scripted_bus.queue(NACK, NACK, NACK)  # SETCURRENT 0: lost
    scripted_bus.queue(flags(READY))  # SETBRAKEMODE 0
    with pytest.raises(CommError) as err:
        joint.disable()
    message = str(err.value)
    assert "disable incomplete, 2 of 4 steps failed: SETHOLDCURRENT 0: " in message
    assert "; SETCURRENT 0: " in message
    assert [step for step, _ in err.value.failures] == ["SETHOLDCURRENT 0", "SETCURRENT 0"]


def test_disable_with_one_failed_step_raises_that_error(
    scripted_bus: Any, make_j1: Callable[..., Joint]
) -> None:
    joint = make_j1()
    scripted_bus.queue(
        flags(READY), flags(NOT_ENABLED), flags(NOT_ENABLED)
    )  # STOP, SETHOLDCURRENT, SETCURRENT
    scripted_bus.queue(NACK, NACK, NACK)  # SETBRAKEMODE 0: lost
    with pytest.raises(CommError) as err:
        joint.disable()
    assert "disable incomplete" not in str(err.value)
    assert "SETBRAKEMODE failed after 3 attempts" in str(err.value)
    assert [step for step, _ in err.value.failures] == ["SETBRAKEMODE freewheel"]
