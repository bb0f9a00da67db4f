"""Payload encoding and unit conversions (docs/model.md "Units and transmission", docs/protocol.md).

Payloads are float32, int32, uint32 or uint8, little-endian. Transmission:
``actuator = reduction * (joint - offset)``; position commands are
``rad2deg(reduction * (q - offset))`` degrees, velocity commands
``rad2deg(reduction * qd) / 6`` RPM.
"""

from __future__ import annotations

import math

import pytest
from hypothesis import given
from hypothesis import strategies as st

from bioscara_gym.hardware import codec
from bioscara_gym.hardware.codec import pack_bytes, unpack_bytes
from bioscara_gym.hardware.errors import InvalidArgumentError
from bioscara_gym.hardware.registers import PAYLOAD_FORMAT, Reg
from bioscara_gym.hardware.transmission import (
    actuator_to_joint,
    degrees_to_position,
    joint_to_actuator,
    position_to_degrees,
    rate_to_degrees,
    rpm_to_velocity,
    steps_to_degrees,
    velocity_to_rpm,
)

F32_MAX = 3.4028234663852886e38

# docs/model.md kinematics: reduction, (min, max) limits, max velocity.
REDUCTIONS = {
    "j1": (35.0, (-3.04647, 3.04647), 1.0),
    "j2": (-2 * math.pi / 0.004, (-0.0016, 0.338), 0.03),
    "j3": (24.0, (-2.62672, 2.62672), 5.0),
    "j4": (12.0, (-3.01069, 3.01069), 10.0),
}

bytes_ = st.integers(min_value=0, max_value=255)

#: One register of each payload format.
F32_REG = Reg.SETRPM
I32_REG = Reg.MOVESTEPS
U32_REG = Reg.SETUP
U8_REG = Reg.SETCURRENT


# ------------------------------------------------------------------ codec
def test_every_used_register_has_a_payload_of_at_most_four_bytes() -> None:
    for reg in PAYLOAD_FORMAT:
        assert 1 <= codec.payload_size(reg) <= 4


def test_register_without_a_format_is_the_firmwares_raw_uint32() -> None:
    assert codec.payload_size(Reg.GETDRIVERRPM) == 4
    assert codec.decode(Reg.GETDRIVERRPM, b"\x01\x02\x03\x04") == 0x04030201


@given(st.floats(width=32, allow_nan=False, allow_infinity=False))
def test_f32_round_trips(value: float) -> None:
    data = codec.encode(F32_REG, value)
    assert len(data) == 4
    assert codec.decode(F32_REG, data) == value


@given(st.integers(min_value=-(2**31), max_value=2**31 - 1))
def test_i32_round_trips(value: int) -> None:
    data = codec.encode(I32_REG, value)
    assert len(data) == 4
    assert codec.decode(I32_REG, data) == value


@given(st.integers(min_value=0, max_value=2**32 - 1))
def test_u32_round_trips(value: int) -> None:
    data = codec.encode(U32_REG, value)
    assert len(data) == 4
    assert codec.decode(U32_REG, data) == value


@given(bytes_)
def test_u8_round_trips(value: int) -> None:
    data = codec.encode(U8_REG, value)
    assert len(data) == 1
    assert codec.decode(U8_REG, data) == value


@given(st.binary(min_size=4, max_size=4))
def test_i32_decode_then_encode_gives_the_same_bytes(data: bytes) -> None:
    assert codec.encode(I32_REG, codec.decode(I32_REG, data)) == data


@given(st.one_of(st.integers(max_value=-(2**31) - 1), st.integers(min_value=2**31)))
def test_i32_rejects_out_of_range(value: int) -> None:
    with pytest.raises(InvalidArgumentError, match="MOVESTEPS"):
        codec.encode(I32_REG, value)


@given(st.one_of(st.integers(max_value=-1), st.integers(min_value=2**32)))
def test_u32_rejects_out_of_range(value: int) -> None:
    with pytest.raises(InvalidArgumentError, match="SETUP"):
        codec.encode(U32_REG, value)


@given(st.one_of(st.integers(max_value=-1), st.integers(min_value=256)))
def test_u8_rejects_out_of_range(value: int) -> None:
    with pytest.raises(InvalidArgumentError, match="SETCURRENT"):
        codec.encode(U8_REG, value)


@given(st.floats(min_value=3.5e38, allow_infinity=False) | st.floats(max_value=-3.5e38, allow_infinity=False))
def test_f32_rejects_values_beyond_float32_range(value: float) -> None:
    with pytest.raises(InvalidArgumentError):
        codec.encode(F32_REG, value)


def test_f32_accepts_largest_float32() -> None:
    assert codec.decode(F32_REG, codec.encode(F32_REG, F32_MAX)) == F32_MAX
    assert codec.decode(F32_REG, codec.encode(F32_REG, -F32_MAX)) == -F32_MAX


def test_encode_error_names_joint_and_register() -> None:
    with pytest.raises(InvalidArgumentError, match=r"^j3: MOVESTEPS payload 1.5") as info:
        codec.encode(Reg.MOVESTEPS, 1.5, joint="j3")  # type: ignore[arg-type]
    assert info.value.joint == "j3"
    assert info.value.register is Reg.MOVESTEPS


@pytest.mark.parametrize(
    ("reg", "value", "data"),
    [
        (F32_REG, 1.0, b"\x00\x00\x80\x3f"),
        (F32_REG, -2.0, b"\x00\x00\x00\xc0"),
        (F32_REG, 0.5, b"\x00\x00\x00\x3f"),
        (I32_REG, 1, b"\x01\x00\x00\x00"),
        (I32_REG, -200, b"\x38\xff\xff\xff"),
        (I32_REG, -1, b"\xff\xff\xff\xff"),
        (U32_REG, 0x04030201, b"\x01\x02\x03\x04"),
        (U32_REG, 7700, b"\x14\x1e\x00\x00"),  # SETUP drive 20, hold 30
        (U8_REG, 0x2A, b"\x2a"),
    ],
    ids=["f32_1", "f32_-2", "f32_0.5", "i32_1", "i32_-200", "i32_-1", "u32_bytes", "u32_setup", "u8"],
)
def test_encoding_is_little_endian(reg: Reg, value: float, data: bytes) -> None:
    assert codec.encode(reg, value) == data


@given(bytes_, bytes_, bytes_, bytes_)
def test_pack_bytes_round_trips(b0: int, b1: int, b2: int, b3: int) -> None:
    assert unpack_bytes(pack_bytes(b0, b1, b2, b3)) == (b0, b1, b2, b3)


@given(st.integers(min_value=0, max_value=2**32 - 1))
def test_unpack_bytes_round_trips(value: int) -> None:
    assert pack_bytes(*unpack_bytes(value)) == value


@given(bytes_, bytes_, bytes_, bytes_)
def test_pack_bytes_puts_byte0_first_on_the_wire(b0: int, b1: int, b2: int, b3: int) -> None:
    assert codec.encode(Reg.HOME, pack_bytes(b0, b1, b2, b3)) == bytes((b0, b1, b2, b3))


def test_pack_bytes_defaults_missing_bytes_to_zero() -> None:
    assert pack_bytes(20, 30) == 20 + 30 * 256


@pytest.mark.parametrize("args", [(256,), (0, -1), (0, 0, 300), (0, 0, 0, 256)])
def test_pack_bytes_rejects_a_byte_outside_uint8(args: tuple[int, ...]) -> None:
    with pytest.raises(InvalidArgumentError, match="uint8"):
        pack_bytes(*args)


# ----------------------------------------------------------- transmission
def joint_parametrize() -> pytest.MarkDecorator:
    return pytest.mark.parametrize("name", list(REDUCTIONS))


def in_limits(name: str) -> st.SearchStrategy[float]:
    lo, hi = REDUCTIONS[name][1]
    return st.floats(min_value=lo, max_value=hi)


def in_velocity(name: str) -> st.SearchStrategy[float]:
    vmax = REDUCTIONS[name][2]
    return st.floats(min_value=-vmax, max_value=vmax)


@joint_parametrize()
@given(data=st.data())
def test_position_to_degrees_round_trips_with_offset(name: str, data: st.DataObject) -> None:
    reduction = REDUCTIONS[name][0]
    q = data.draw(in_limits(name), label="q")
    offset = data.draw(in_limits(name), label="offset")
    deg = position_to_degrees(q, reduction, offset)
    assert degrees_to_position(deg, reduction, offset) == pytest.approx(q, rel=1e-9, abs=1e-12)


@joint_parametrize()
@given(data=st.data())
def test_joint_to_actuator_round_trips_with_offset(name: str, data: st.DataObject) -> None:
    reduction = REDUCTIONS[name][0]
    q = data.draw(in_limits(name), label="q")
    offset = data.draw(in_limits(name), label="offset")
    actuator = joint_to_actuator(q, reduction, offset)
    assert actuator_to_joint(actuator, reduction, offset) == pytest.approx(q, rel=1e-9, abs=1e-12)


@joint_parametrize()
@given(data=st.data())
def test_velocity_to_rpm_round_trips(name: str, data: st.DataObject) -> None:
    reduction = REDUCTIONS[name][0]
    qd = data.draw(in_velocity(name), label="qd")
    assert rpm_to_velocity(velocity_to_rpm(qd, reduction), reduction) == pytest.approx(
        qd, rel=1e-12, abs=1e-15
    )


@joint_parametrize()
@given(data=st.data())
def test_offset_cancels_out_of_degrees_difference(name: str, data: st.DataObject) -> None:
    reduction = REDUCTIONS[name][0]
    q = data.draw(in_limits(name), label="q")
    offset = data.draw(in_limits(name), label="offset")
    expected = math.degrees(reduction * q) - math.degrees(reduction * offset)
    assert position_to_degrees(q, reduction, offset) == pytest.approx(expected, rel=1e-9, abs=1e-9)


@joint_parametrize()
def test_position_at_offset_is_zero_degrees(name: str) -> None:
    reduction, (lo, hi), _ = REDUCTIONS[name]
    assert position_to_degrees(hi, reduction, hi) == 0.0
    assert degrees_to_position(0.0, reduction, lo) == lo


@joint_parametrize()
def test_rate_to_degrees_is_reduction_times_rate_in_degrees(name: str) -> None:
    reduction, _, vmax = REDUCTIONS[name]
    assert rate_to_degrees(vmax, reduction) == pytest.approx(math.degrees(reduction * vmax), rel=1e-12)
    assert math.copysign(1.0, rate_to_degrees(vmax, reduction)) == math.copysign(1.0, reduction)


def test_j1_one_rad_per_second_is_334_rpm() -> None:
    assert velocity_to_rpm(1.0, 35.0) == pytest.approx(334.2254, abs=1e-4)
    assert velocity_to_rpm(1.0, 35.0) == pytest.approx(math.degrees(35.0) / 6.0, rel=1e-15)


def test_j2_three_mm_per_second_is_minus_45_rpm() -> None:
    assert velocity_to_rpm(0.003, -2 * math.pi / 0.004) == pytest.approx(-45.0, rel=1e-12)


def test_j2_positive_motor_turn_moves_the_lift_down() -> None:
    # One motor turn (360 degrees) is 4 mm of lift travel, downwards.
    assert degrees_to_position(360.0, -2 * math.pi / 0.004, 0.0) == pytest.approx(-0.004, rel=1e-12)


def test_rpm_to_velocity_known_value() -> None:
    assert rpm_to_velocity(60.0, 35.0) == pytest.approx(math.radians(60.0) / 35.0 * 6.0, rel=1e-15)


def test_one_motor_turn_is_51200_microsteps() -> None:
    # The library's moveSteps counts 1/256 steps: 200 full steps of 256 a turn (UstepperS32.cpp).
    assert steps_to_degrees(51200) == pytest.approx(360.0, rel=1e-15)
    assert steps_to_degrees(256) == pytest.approx(1.8, rel=1e-15)
