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

from bioscara_gym.hardware.base_joint import BaseJoint
from bioscara_gym.hardware.clock import ManualClock, WallClock
from bioscara_gym.hardware.codec import pack_bytes
from bioscara_gym.hardware.errors import (
    CommError,
    IncorrectStateError,
    InvalidArgumentError,
    JointError,
    NotEnabledError,
    NotHomedError,
    NotInitError,
    StalledError,
)
from bioscara_gym.hardware.joint import Joint
from bioscara_gym.hardware.registers import Reg
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
    scripted_bus.queue(struct.pack("<f", degrees) + flags(READY), struct.pack("<f", degrees) + flags(READY))
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
    scripted_bus.queue(flags(BUSY), *[ack(READY)] * 3)  # CHECKORIENTATION (BUSY), PING: done, twice more
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


# ------------------------------------------- BaseJoint, second mutation run
def test_exchange_listener_is_called_until_removed(scripted_bus: Any, make_j1: Callable[..., Joint]) -> None:
    joint = make_j1()
    calls: list[int] = []
    remove = joint.on_exchange(lambda: calls.append(1))
    scripted_bus.queue(ack(READY))
    joint.get_flags()
    assert calls == [1]
    scripted_bus.queue(flags(READY))
    joint.stop()  # a command: one exchange too
    assert calls == [1, 1]
    remove()
    remove()  # a second remove is harmless
    scripted_bus.queue(ack(READY))
    joint.get_flags()
    assert calls == [1, 1]


def test_deinit_leaves_initialized_false(scripted_bus: Any, make_j1: Callable[..., Joint]) -> None:
    joint = make_j1()
    joint.deinit()
    assert joint.initialized is False


def test_repr_names_the_class_the_joint_and_its_flags(scripted_bus: Any) -> None:
    # docs/protocol.md: power-up flags NOTHOMED | NOTENABLED (0x0c).
    joint = Joint("j1", 0x11, 35.0, -J1_LIMIT, J1_LIMIT, scripted_bus, clock=ManualClock())
    assert repr(joint) == "Joint('j1', flags=<Flag.NOT_HOMED|NOT_ENABLED: 12>)"


def test_position_is_0_when_the_offset_read_in_get_position_is_nan(scripted_bus: Any) -> None:
    # docs/arm.md, "Lost homing offset": a joint that says homed but answers
    # HOMEOFFSET NaN is reported not homed, position 0.0. Here the joint was
    # not homed at init() and says homed in the ANGLEMOVED reply.
    # The joint is not enabled: that flag is kept beside the host's NOTHOMED.
    joint = Joint("j1", 0x11, 35.0, -J1_LIMIT, J1_LIMIT, scripted_bus, clock=ManualClock())
    scripted_bus.queue(ack(NOT_HOMED | NOT_ENABLED))
    joint.init()
    reading = struct.pack("<f", 35.0) + flags(NOT_ENABLED)
    # NOTHOMED gone with no homing of this host's: two PINGs confirm each
    # reading that shows it (the first position reading is read twice).
    pings = (ack(NOT_ENABLED), ack(NOT_ENABLED))
    scripted_bus.queue(reading, *pings, reading, *pings, struct.pack("<f", float("nan")) + flags(NOT_ENABLED))
    assert joint.get_position() == 0.0
    assert joint.flags == NOT_HOMED | NOT_ENABLED


@pytest.mark.parametrize(
    ("reply", "error", "message"),
    [
        (STALL, "StalledError", "j1: joint stalled; sent STOP; re-enable it to clear the stall"),
        (
            NOT_ENABLED,
            "NotEnabledError",
            "j1: joint reports not enabled (deadman or disable), yet the firmware runs SETRPM anyway; "
            "sent STOP; re-enable it",
        ),
    ],
)
def test_motion_refused_in_the_reply_names_joint_register_and_cure(
    scripted_bus: Any, make_j1: Callable[..., Joint], reply: int, error: str, message: str
) -> None:
    # docs/arm.md: StalledError / NotEnabledError from the reply's flags. The
    # newly set sticky flag is confirmed by two PINGs (docs/protocol.md), and
    # the joint is stopped: the firmware runs the SETRPM anyway.
    joint = make_j1()
    scripted_bus.queue(flags(reply), ack(reply), ack(reply), flags(reply))
    with pytest.raises(JointError) as err:
        joint.set_velocity(0.1)
    assert type(err.value).__name__ == error
    assert str(err.value) == message
    assert err.value.joint == "j1"
    assert err.value.register == 0x11  # SETRPM (docs/protocol.md)


@pytest.mark.parametrize(
    ("call", "message"),
    [
        (lambda j: j.set_position(float("nan")), "j1: position nan must be finite"),
        (lambda j: j.set_velocity(float("inf")), "j1: velocity inf must be finite"),
        (lambda j: j.set_drive_current(101), "j1: drive current 101 must be an integer percent 0-100"),
        (lambda j: j.set_hold_current(-1), "j1: hold current -1 must be an integer percent 0-100"),
        (lambda j: j.enable_stallguard(256), "j1: stall sensitivity 256 must be 0-255"),
        (lambda j: j.set_brake_mode(3), "j1: brake mode 3 must be 0, 1 or 2"),
        (lambda j: j.set_max_acceleration(float("nan")), "j1: max acceleration nan must be finite"),
        (lambda j: j.set_max_velocity(float("-inf")), "j1: max velocity -inf must be finite"),
        (lambda j: j.set_max_velocity(0.0), "j1: max velocity 0.0 must be > 0"),
        (lambda j: j.set_max_acceleration(0.0), "j1: max acceleration 0.0 must be > 0"),
        (lambda j: j.enable(101, 20), "j1: drive current 101 must be an integer percent 0-100"),
        (lambda j: j.enable(20, 101), "j1: hold current 101 must be an integer percent 0-100"),
        (lambda j: j.enable_stallguard(True), "j1: stall sensitivity True must be 0-255"),
        (lambda j: j.start_homing(float("nan"), 30, 15), "j1: homing velocity nan must be finite"),
        (lambda j: j.start_homing(0.03, 256, 15), "j1: homing sensitivity 256 must be 0-255"),
        (lambda j: j.start_homing(0.03, 30, 101), "j1: homing current 101 must be an integer percent 0-100"),
        # docs/arm.md: 1.0 < |rpm| < 250, rpm = rad2deg(35 x 10) / 6 = 3342 RPM.
        (
            lambda j: j.start_homing(10.0, 30, 15),
            "j1: homing speed 10 rad/s is 3.34e+03 RPM at the motor; must be between 1 and 250 RPM",
        ),
    ],
)
def test_refused_argument_is_named_in_the_message(
    make_j1: Callable[..., Joint], call: Callable[[Joint], None], message: str
) -> None:
    joint = make_j1()
    with pytest.raises(InvalidArgumentError) as err:
        call(joint)
    assert str(err.value) == message


class BusyBus:
    """PING: BUSY (at most ``limit`` times); a command: the flags it sets (docs/protocol.md)."""

    def __init__(self, limit: int) -> None:
        self.limit = limit
        self.pings = 0

    def transfer(self, address: int, data: bytes, read_len: int) -> bytes:
        reg = data[0]
        if reg == 0x0F:  # PING (docs/protocol.md)
            self.pings += 1
            if self.pings > self.limit:
                raise AssertionError("still polling past the timeout")
            return ack(BUSY)
        if reg == 0x2E and read_len == 5:  # HOMEOFFSET read by init(): homed at max
            return struct.pack("<f", J1_LIMIT) + flags(READY)
        if reg == 0x2B:  # CHECKORIENTATION sets BUSY in its reply
            return flags(BUSY)
        if reg == 0x2D:  # HOME sets BUSY and NOTHOMED in its reply
            return flags(BUSY | NOT_HOMED)
        return flags(READY)  # STOP clears BUSY

    def close(self) -> None:
        pass


def test_check_orientation_gives_up_after_10_s_by_default() -> None:
    # docs/arm.md: check_orientation waits while BUSY, 10 s timeout, STOP sent first.
    bus = BusyBus(limit=1500)
    clock = ManualClock()
    joint = Joint("j1", 0x11, 35.0, -J1_LIMIT, J1_LIMIT, bus, clock=clock)
    bus.pings = -1  # init's PING below does not count
    joint.init()
    with pytest.raises(IncorrectStateError) as err:
        joint.check_orientation()
    assert str(err.value) == "j1: still busy after 10 s; stopped the joint"
    assert 10.0 < clock.now() < 10.2


# docs/arm.md: after a STOP that may abort a blocking command the next HOME
# waits ABORT_SETTLE_S, 0.56 s; after any other STOP it does not wait.
ABORT_SETTLE = 0.56
#: j1 homing at 0.1 rad/s: rad2deg(35 x 0.1) / 6 = 33.4 RPM, inside 1-250.
HOMING = (0.1, 20, 30)


def start_homing(scripted_bus: Any, joint: Joint) -> None:
    scripted_bus.queue(flags(READY), flags(BUSY | NOT_HOMED))  # HOMEOFFSET := NaN, HOME
    joint.start_homing(*HOMING)


def test_stop_of_an_idle_joint_does_not_delay_the_next_homing(
    scripted_bus: Any, make_j1: Callable[..., Joint]
) -> None:
    joint = make_j1()
    scripted_bus.queue(flags(READY))
    joint.stop()
    start_homing(scripted_bus, joint)
    assert joint.clock.now() == 0.0


def test_stop_of_a_joint_busy_with_a_homing_it_did_not_start_delays_the_next(
    scripted_bus: Any, make_j1: Callable[..., Joint]
) -> None:
    joint = make_j1()
    scripted_bus.queue(ack(BUSY), ack(BUSY), ack(BUSY))  # a homing another process started, confirmed
    joint.get_flags()
    scripted_bus.queue(flags(READY))
    joint.stop()
    start_homing(scripted_bus, joint)
    assert joint.clock.now() == pytest.approx(ABORT_SETTLE)


def test_stop_of_an_adopted_homing_not_yet_busy_delays_the_next(
    scripted_bus: Any, make_j1: Callable[..., Joint]
) -> None:
    joint = make_j1()
    joint.adopt_homing(0.1)  # HOME is this object's blocking command; last flags not BUSY
    scripted_bus.queue(flags(READY))
    joint.stop()
    start_homing(scripted_bus, joint)
    assert joint.clock.now() == pytest.approx(ABORT_SETTLE)


def test_adopt_homing_during_another_blocking_command_is_refused_by_name(
    scripted_bus: Any, make_j1: Callable[..., Joint]
) -> None:
    # docs/arm.md: adopt_homing takes over a homing; CHECKORIENTATION is
    # another blocking command. The attempt is made from an exchange
    # listener while CHECKORIENTATION runs.
    joint = make_j1()
    refused: list[Exception] = []

    def adopt() -> None:
        if joint.current_blocking_command == 0x2B and not refused:
            try:
                joint.adopt_homing(0.1)
            except IncorrectStateError as e:
                refused.append(e)

    joint.on_exchange(adopt)
    scripted_bus.queue(flags(BUSY), *[ack(READY)] * 3)  # CHECKORIENTATION, PING: done, twice more
    joint.check_orientation()
    assert [str(e) for e in refused] == ["j1: CHECKORIENTATION is running; cannot adopt a homing"]
    assert refused[0].joint == "j1"  # type: ignore[attr-defined]


class ScriptedJoint(BaseJoint):
    """A BaseJoint whose commands raise the errors given per register, else answer READY."""

    def __init__(
        self,
        errors: dict[int, JointError],
        reduction: float = 35.0,
        low: float = -1.0,
        high: float = 1.0,
        wall_clock: bool = False,
        ping: int = ord("O"),
    ) -> None:
        super().__init__("jx", reduction, low, high, clock=None if wall_clock else ManualClock())
        self.errors = errors
        self.ping = ping

    def _command(self, reg: Reg, value: float | int) -> int:
        if reg in self.errors:
            raise self.errors[reg]
        return READY

    def _query(self, reg: Reg) -> tuple[float | int, int]:
        return (self.ping, READY) if reg == Reg.PING else (0.0, READY)


def test_disable_with_failures_not_all_comm_errors_raises_a_joint_error_naming_each() -> None:
    stalled = StalledError("stalled", joint="jx", register=Reg.STOP)
    lost = CommError("lost", joint="jx", register=Reg.SETCURRENT)
    joint = ScriptedJoint({Reg.STOP: stalled, Reg.SETCURRENT: lost})
    joint.init()
    with pytest.raises(JointError) as err:
        joint.disable()
    assert type(err.value) is JointError
    assert (
        str(err.value)
        == "jx: disable incomplete, 2 of 4 steps failed: STOP: jx: stalled; SETCURRENT 0: jx: lost"
    )
    assert err.value.joint == "jx"
    assert err.value.register == Reg.STOP
    assert err.value.failures == [("STOP", stalled), ("SETCURRENT 0", lost)]  # type: ignore[attr-defined]


def test_enable_that_leaves_the_joint_not_enabled_says_so(
    scripted_bus: Any, make_j1: Callable[..., Joint]
) -> None:
    # docs/arm.md: enable() raises NotEnabledError if the joint still reports
    # not enabled; the newly set NOTENABLED is confirmed by two PINGs.
    joint = make_j1()
    scripted_bus.queue(flags(NOT_ENABLED), ack(NOT_ENABLED), ack(NOT_ENABLED))
    with pytest.raises(NotEnabledError) as err:
        joint.enable(20, 10)
    assert str(err.value) == "j1: failed to enable; the joint still reports not enabled"
    assert err.value.register == 0x10  # SETUP (docs/protocol.md)


def test_post_homing_of_a_joint_that_did_not_home_says_so(
    scripted_bus: Any, make_j1: Callable[..., Joint]
) -> None:
    # docs/arm.md: post_homing() raises NotHomedError if the joint did not home.
    joint = make_j1()
    joint.adopt_homing(0.1)
    scripted_bus.queue(ack(NOT_HOMED), ack(NOT_HOMED), ack(NOT_HOMED))  # PING, and two confirming NOTHOMED
    with pytest.raises(NotHomedError) as err:
        joint.post_homing()
    assert str(err.value) == "j1: homing did not complete (aborted or failed)"


def test_after_post_homing_positions_need_no_offset_read(
    scripted_bus: Any, make_j1: Callable[..., Joint]
) -> None:
    # docs/arm.md: post_homing() stores the offset; get_position() reads
    # ANGLEMOVED only (twice: the first reading after a homing is confirmed),
    # q = deg2rad(deg)/reduction + offset.
    joint = make_j1()
    joint.adopt_homing(-0.1)  # homes to min
    scripted_bus.queue(ack(READY), flags(READY))  # PING, HOMEOFFSET := -3.04647
    joint.post_homing()
    scripted_bus.clear_log()
    scripted_bus.queue(struct.pack("<f", 0.0) + flags(READY), struct.pack("<f", 0.0) + flags(READY))
    assert joint.get_position() == -J1_LIMIT
    assert scripted_bus.writes() == [bytes([0x18])] * 2  # ANGLEMOVED only


class LeapClock(ManualClock):
    """A manual clock whose every sleep lasts ``leap`` seconds, whatever was asked."""

    def __init__(self, start: float, leap: float) -> None:
        super().__init__(start)
        self.leap = leap

    def sleep(self, dt: float) -> None:
        super().sleep(self.leap)


def busy_j1(clock: ManualClock, limit: int = 1500) -> tuple[Joint, BusyBus]:
    bus = BusyBus(limit=limit)
    joint = Joint("j1", 0x11, 35.0, -J1_LIMIT, J1_LIMIT, bus, clock=clock)
    bus.pings = -1  # init's PING does not count
    joint.init()
    return joint, bus


def test_home_gives_up_after_600_s_by_default_and_forgets_the_homing() -> None:
    # docs/arm.md: home() raises IncorrectStateError after the timeout (600 s
    # by default; STOP sent first). Each poll here lasts 100 s.
    joint, _ = busy_j1(LeapClock(0.0, 100.0), limit=20)
    with pytest.raises(IncorrectStateError) as err:
        joint.home(*HOMING)
    assert str(err.value) == "j1: still busy after 600 s; stopped the joint"
    assert joint.current_blocking_command == Reg.NONE


def test_wait_while_busy_gives_up_only_when_more_than_the_timeout_passed() -> None:
    # Polls every 0.25 s from t = 1.0; busy at 1.0, 1.25, 1.5 (0.5 s: not
    # more than the timeout yet) and 1.75, then STOP.
    clock = ManualClock(1.0)
    joint, bus = busy_j1(clock)
    with pytest.raises(IncorrectStateError):
        joint.wait_while_busy(period_s=0.25, timeout_s=0.5)
    # 4 polls; BUSY with no blocking command of its own is read twice more where it
    # appears: after init's PING and after HOMEOFFSET's READY (2 + 2)
    assert bus.pings == 4 + 4
    assert clock.now() == 1.75


def test_lift_homing_speed_out_of_bounds_is_given_in_metres_per_second(scripted_bus: Any) -> None:
    # docs/model.md: j2 reduction -2 pi / 0.004 m; 0.1 m/s = rad2deg(157.08) / 6 = 1500 RPM.
    joint = Joint("j2", 0x12, -1570.7963267948967, -0.0016, 0.338, scripted_bus, clock=ManualClock())
    with pytest.raises(InvalidArgumentError) as err:
        joint.start_homing(0.1, 50, 30)
    assert str(err.value) == (
        "j2: homing speed 0.1 m/s is 1.5e+03 RPM at the motor; must be between 1 and 250 RPM"
    )


@pytest.mark.parametrize(("reduction", "unit"), [(500.0, "rad/s"), (-500.5, "m/s")])
def test_homing_speed_unit_is_metres_only_above_a_reduction_of_500(reduction: float, unit: str) -> None:
    # start_homing's message: |reduction| above 500 (motor rad per joint unit) is a
    # lift (docs/model.md: revolute 12-35, the lift 1570.8).
    joint = ScriptedJoint({}, reduction=reduction)
    joint.init()
    with pytest.raises(InvalidArgumentError) as err:
        joint.start_homing(1000.0, 30, 15)
    assert f"homing speed 1000 {unit} is " in str(err.value)


@pytest.mark.parametrize(
    ("reduction", "low", "high", "message"),
    [
        (0.0, -1.0, 1.0, "jx: reduction 0.0 must be finite and non-zero"),
        (float("inf"), -1.0, 1.0, "jx: reduction inf must be finite and non-zero"),
        (35.0, 1.0, 1.0, "jx: min 1.0 must be below max 1.0"),
    ],
)
def test_constructor_refuses_a_bad_reduction_or_range_naming_the_joint(
    reduction: float, low: float, high: float, message: str
) -> None:
    with pytest.raises(InvalidArgumentError) as err:
        ScriptedJoint({}, reduction=reduction, low=low, high=high)
    assert str(err.value) == message
    assert err.value.joint == "jx"


def test_reduction_of_one_is_accepted_and_the_default_clock_is_wall_time() -> None:
    joint = ScriptedJoint({}, reduction=1.0, wall_clock=True)
    assert isinstance(joint.clock, WallClock)
    assert joint.initialized is False


def test_init_that_pings_something_else_than_o_fails_naming_joint_and_register() -> None:
    # docs/protocol.md: PING (0x0F) answers 'O' (0x4F).
    joint = ScriptedJoint({}, ping=0x4E)
    with pytest.raises(CommError) as err:
        joint.init()
    assert str(err.value) == "jx: PING answered 78, expected 79 ('O')"
    assert err.value.joint == "jx"
    assert err.value.register == 0x0F
    assert joint.initialized is False


def test_use_before_init_and_motion_while_disabled_are_refused_by_name(
    scripted_bus: Any, make_j1: Callable[..., Joint]
) -> None:
    joint = Joint("j1", 0x11, 35.0, -J1_LIMIT, J1_LIMIT, scripted_bus, clock=ManualClock())
    with pytest.raises(NotInitError) as err:
        joint.get_flags()
    assert str(err.value) == "j1: joint not initialized; call init() first"
    joint = make_j1()
    scripted_bus.queue(ack(NOT_ENABLED), ack(NOT_ENABLED), ack(NOT_ENABLED))  # PING, 2 confirming NOTENABLED
    joint.get_flags()
    with pytest.raises(NotEnabledError) as err2:
        joint.move_steps(10)
    assert str(err2.value) == "j1: joint not enabled; call enable() first"


def test_a_blocking_command_refused_while_homing_names_the_joint(
    scripted_bus: Any, make_j1: Callable[..., Joint]
) -> None:
    joint = make_j1()
    start_homing(scripted_bus, joint)
    with pytest.raises(IncorrectStateError) as err:
        joint.check_orientation()
    assert str(err.value) == "j1: HOME is still running; stop it first"
    assert err.value.joint == "j1"


@pytest.mark.parametrize("current", [0, 100])
def test_currents_of_0_and_100_percent_are_accepted(
    scripted_bus: Any, make_j1: Callable[..., Joint], current: int
) -> None:
    # docs/protocol.md: SETCURRENT uint8 drive current %, 0-100; 0 sets NOTENABLED.
    joint = make_j1()
    scripted_bus.queue(flags(NOT_ENABLED if current == 0 else READY))
    joint.set_drive_current(current)
    assert scripted_bus.writes() == [bytes([0x19, current])]


@pytest.mark.parametrize("sensitivity", [0, 255])
def test_stall_sensitivities_0_and_255_are_accepted(
    scripted_bus: Any, make_j1: Callable[..., Joint], sensitivity: int
) -> None:
    # docs/protocol.md: ENABLESTALLGUARD uint8 sensitivity.
    joint = make_j1()
    scripted_bus.queue(flags(READY))
    joint.enable_stallguard(sensitivity)
    assert scripted_bus.writes() == [bytes([0x1E, sensitivity])]


def test_blocking_command_lost_every_time_says_so_with_the_last_error(
    scripted_bus: Any, make_j1: Callable[..., Joint]
) -> None:
    # docs/arm.md: after a lost reply to CHECKORIENTATION the driver reads the
    # flags; not BUSY: it did not start, sent again (2 retries by default).
    joint = make_j1()
    for _ in range(3):
        scripted_bus.queue(NACK, ack(READY))  # CHECKORIENTATION lost; PING: not busy
    with pytest.raises(CommError) as err:
        joint.check_orientation()
    message = str(err.value)
    assert message.startswith(
        "j1: CHECKORIENTATION: the reply was lost and the joint is not busy, so it did not start; "
        "sent 3 time(s) (j1 (0x11): CHECKORIENTATION failed: "
    )
    assert err.value.register == 0x2B
