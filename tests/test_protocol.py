"""Byte-level tests of the real joint driver (docs/protocol.md).

The driver :class:`Joint` runs against ``scripted_bus`` (``conftest.py``): a
fake bus that records every transfer as ``(address, written bytes, read
length)`` and answers from a queue of canned replies. Expected bytes are built
here with :mod:`struct` from the formulas in docs/model.md, not with the driver's codec.

A read writes ``[REG]`` and reads payload + flags; a command writes
``[REG][payload]`` and reads the flags byte. Flags: bit 0 STALL, bit 1 BUSY,
bit 2 NOT_HOMED, bit 3 NOT_ENABLED.
"""

from __future__ import annotations

import ctypes
import math
import os
import struct
from collections.abc import Callable
from pathlib import Path
from typing import Any

import pytest
import smbus2
from smbus2.smbus2 import I2C_M_RD

from bioscara_gym.hardware.base_joint import BUSY_POLL_S
from bioscara_gym.hardware.bus import SMBusI2C
from bioscara_gym.hardware.clock import ManualClock
from bioscara_gym.hardware.errors import (
    CommError,
    IncorrectStateError,
    InvalidArgumentError,
    NotEnabledError,
    NotHomedError,
    NotInitError,
    StalledError,
)
from bioscara_gym.hardware.joint import Joint
from bioscara_gym.hardware.registers import BLOCKING_PICKUP_S, Flag, Reg
from bioscara_gym.hardware.transmission import velocity_to_rpm

# docs/model.md kinematics and stepper tables: address, reduction, limits.
JOINTS: dict[str, dict[str, float | int]] = {
    "j1": dict(address=0x11, reduction=35.0, min=-3.04647, max=3.04647),
    "j2": dict(address=0x12, reduction=-1570.7963267948967, min=-0.0016, max=0.338),
    "j3": dict(address=0x13, reduction=24.0, min=-2.62672, max=2.62672),
    "j4": dict(address=0x14, reduction=12.0, min=-3.01069, max=3.01069),
}

# Flags bytes.
READY = 0  # homed and enabled
STALL = 0x01
BUSY = 0x02
NOT_HOMED = 0x04
NOT_ENABLED = 0x08
POWER_UP = NOT_HOMED | NOT_ENABLED

# Register bytes, spelled out from the table in docs/protocol.md.
PING = b"\x0f"
SETUP = b"\x10"
SETRPM = b"\x11"
MOVESTEPS = b"\x13"
MOVETOANGLE = b"\x15"
ANGLEMOVED = b"\x18"
SETCURRENT = b"\x19"
SETHOLDCURRENT = b"\x1a"
SETMAXACCELERATION = b"\x1b"
SETMAXVELOCITY = b"\x1d"
ENABLESTALLGUARD = b"\x1e"
SETBRAKEMODE = b"\x22"
DISABLECLOSEDLOOP = b"\x26"
STOP = b"\x29"
CHECKORIENTATION = b"\x2b"
GETENCODERRPM = b"\x2c"
HOME = b"\x2d"
HOMEOFFSET = b"\x2e"


# HOMEOFFSET's "no valid offset": the float32 quiet NaN 0x7FC00000, written
# before every HOME (docs/arm.md, the driver's rules).
NAN_OFFSET = b"\x00\x00\xc0\x7f"


def f32(value: float) -> bytes:
    return struct.pack("<f", value)


def as_f32(value: float) -> float:
    """``value`` rounded to float32, as it comes back from the joint."""
    return struct.unpack("<f", f32(value))[0]


def flags(value: int) -> bytes:
    """A command's reply: the flags byte alone."""
    return bytes((value,))


def ack(value: int) -> bytes:
    """PING's reply: 'O' and the flags byte."""
    return b"O" + flags(value)


def f32_reply(payload: float, value: int) -> bytes:
    """A float32 register's reply: payload and the flags byte."""
    return f32(payload) + flags(value)


@pytest.fixture
def clock() -> ManualClock:
    return ManualClock()


@pytest.fixture
def make_joint(scripted_bus: Any, clock: ManualClock) -> Callable[..., Joint]:
    """Build an un-initialized driver for one of the arm's joints (docs/model.md) on the scripted bus."""

    def make(name: str = "j1", retries: int = 2) -> Joint:
        spec = JOINTS[name]
        return Joint(
            name,
            address=int(spec["address"]),
            reduction=spec["reduction"],
            min=spec["min"],
            max=spec["max"],
            bus=scripted_bus,
            retries=retries,
            clock=clock,
        )

    return make


@pytest.fixture
def make_ready(scripted_bus: Any, make_joint: Callable[..., Joint]) -> Callable[..., Joint]:
    """Build a driver and ``init()`` it into the state given by the PING reply's flags.

    A homed joint also answers HOMEOFFSET with ``offset``. The log is cleared
    afterwards so each test sees only its own transfers.
    """

    def make(name: str = "j1", state: int = READY, offset: float = 0.0, retries: int = 2) -> Joint:
        joint = make_joint(name, retries=retries)
        scripted_bus.queue(ack(state))
        if not state & NOT_HOMED:
            scripted_bus.queue(f32_reply(offset, state))
        joint.init()
        scripted_bus.clear_log()
        return joint

    return make


def address_of(name: str) -> int:
    return int(JOINTS[name]["address"])


def velocity_for_rpm(rpm: float, reduction: float, exact: bool = False) -> float:
    """The joint velocity whose motor speed computes closest to ``rpm`` (searched by ulps).

    With ``exact`` the motor speed must come out as exactly ``rpm``.
    """
    v = math.radians(rpm * 6.0) / reduction
    best, up, down = v, v, v
    for _ in range(256):
        for candidate in (up, down):
            if abs(velocity_to_rpm(candidate, reduction) - rpm) < abs(velocity_to_rpm(best, reduction) - rpm):
                best = candidate
        up = math.nextafter(up, math.inf)
        down = math.nextafter(down, -math.inf)
    if exact and velocity_to_rpm(best, reduction) != rpm:
        raise AssertionError(f"no velocity gives exactly {rpm} RPM with reduction {reduction}")
    return best


# --------------------------------------------------------------------- init
def test_init_pings_the_joint(scripted_bus: Any, make_joint: Callable[..., Joint]) -> None:
    joint = make_joint("j1")
    scripted_bus.queue(ack(POWER_UP))
    joint.init()
    assert scripted_bus.log == [(0x11, PING, 2)]
    assert joint.initialized
    assert joint.flags == Flag.NOT_HOMED | Flag.NOT_ENABLED


def test_init_leaves_offset_zero_when_joint_not_homed(
    scripted_bus: Any, make_joint: Callable[..., Joint]
) -> None:
    joint = make_joint("j1")
    scripted_bus.queue(ack(POWER_UP))
    joint.init()
    assert joint.offset == 0.0


def test_init_reads_home_offset_when_joint_reports_homed(
    scripted_bus: Any, make_joint: Callable[..., Joint]
) -> None:
    joint = make_joint("j2")
    scripted_bus.queue(ack(NOT_ENABLED), f32_reply(0.338, NOT_ENABLED))
    joint.init()
    assert scripted_bus.log == [(0x12, PING, 2), (0x12, HOMEOFFSET, 5)]
    assert joint.offset == as_f32(0.338)
    assert joint.is_homed()


@pytest.mark.parametrize("reply", [b"X" + flags(POWER_UP), b"\x00" + flags(POWER_UP)], ids=["X", "NUL"])
def test_init_fails_when_ping_does_not_answer_ack(
    scripted_bus: Any, make_joint: Callable[..., Joint], reply: bytes
) -> None:
    joint = make_joint("j1", retries=2)
    scripted_bus.queue(reply, reply, reply)
    with pytest.raises(CommError, match=r"j1.*PING answered"):
        joint.init()
    assert not joint.initialized
    assert len(scripted_bus.log) == 3  # a wrong ack is retried like any bad reply


def test_init_retries_a_corrupted_ping_ack(scripted_bus: Any, make_joint: Callable[..., Joint]) -> None:
    joint = make_joint("j1", retries=2)
    scripted_bus.queue(b"X" + flags(POWER_UP), ack(POWER_UP))
    joint.init()
    assert joint.initialized


def test_init_fails_when_joint_does_not_answer(scripted_bus: Any, make_joint: Callable[..., Joint]) -> None:
    joint = make_joint("j3", retries=2)
    scripted_bus.queue(OSError(121, "Remote I/O error"), OSError(121, "x"), OSError(121, "x"))
    with pytest.raises(CommError, match="PING"):
        joint.init()
    assert not joint.initialized
    assert scripted_bus.log == [(0x13, PING, 2)] * 3


# ------------------------------------------------------------ enable/disable
def test_enable_sends_setup_with_drive_and_hold_current(
    scripted_bus: Any, make_ready: Callable[..., Joint]
) -> None:
    joint = make_ready("j1", state=POWER_UP)
    scripted_bus.queue(flags(NOT_HOMED))
    joint.enable(20, 30)
    assert scripted_bus.log == [(0x11, SETUP + bytes((20, 30, 0, 0)), 1)]
    assert joint.is_enabled()


def test_enable_fails_when_joint_still_reports_not_enabled(
    scripted_bus: Any, make_ready: Callable[..., Joint]
) -> None:
    joint = make_ready("j1", state=POWER_UP)
    scripted_bus.queue(flags(POWER_UP), ack(POWER_UP), ack(POWER_UP))  # SETUP, its 2 confirming PINGs
    with pytest.raises(NotEnabledError, match="j1"):
        joint.enable(20, 30)
    assert len(scripted_bus.log) == 3


@pytest.mark.parametrize(("drive", "hold"), [(101, 20), (20, -1), (20, 100.0)])
def test_enable_rejects_current_outside_percent_before_any_traffic(
    scripted_bus: Any, make_ready: Callable[..., Joint], drive: Any, hold: Any
) -> None:
    joint = make_ready("j1", state=POWER_UP)
    with pytest.raises(InvalidArgumentError):
        joint.enable(drive, hold)
    assert scripted_bus.log == []


def test_disable_stops_then_zeroes_currents_then_freewheels(
    scripted_bus: Any, make_ready: Callable[..., Joint]
) -> None:
    joint = make_ready("j4")
    scripted_bus.queue(flags(READY), flags(NOT_ENABLED), flags(NOT_ENABLED), flags(NOT_ENABLED))
    joint.disable()
    assert scripted_bus.log == [
        (0x14, STOP + b"\x00", 1),
        (0x14, SETHOLDCURRENT + b"\x00", 1),
        (0x14, SETCURRENT + b"\x00", 1),
        (0x14, SETBRAKEMODE + b"\x00", 1),
    ]
    assert not joint.is_enabled()


# ------------------------------------------------------------------ velocity
@pytest.mark.parametrize(
    ("name", "qd", "rpm"),
    [
        ("j1", 0.5, 167.1127),
        ("j2", 0.003, -45.0),
        ("j3", 1.0, 229.1831),
        ("j4", -1.0, -114.5916),
    ],
)
def test_set_velocity_sends_motor_rpm_as_float32(
    scripted_bus: Any, make_ready: Callable[..., Joint], name: str, qd: float, rpm: float
) -> None:
    joint = make_ready(name)
    scripted_bus.queue(flags(READY))
    joint.set_velocity(qd)
    reduction = float(JOINTS[name]["reduction"])
    expected = math.degrees(reduction * qd) / 6.0
    assert scripted_bus.log == [(address_of(name), SETRPM + f32(expected), 1)]
    assert struct.unpack("<f", scripted_bus.log[0][1][1:])[0] == pytest.approx(rpm, abs=1e-4)


def test_get_velocity_reads_encoder_rpm(scripted_bus: Any, make_ready: Callable[..., Joint]) -> None:
    joint = make_ready("j1")
    scripted_bus.queue(f32_reply(60.0, READY))
    qd = joint.get_velocity()
    assert scripted_bus.log == [(0x11, GETENCODERRPM, 5)]
    assert qd == pytest.approx(math.radians(60.0) / 35.0 * 6.0, rel=1e-12)


def test_get_velocity_of_the_lift_undoes_its_negative_reduction(
    scripted_bus: Any, make_ready: Callable[..., Joint]
) -> None:
    joint = make_ready("j2")
    scripted_bus.queue(f32_reply(-45.0, READY))
    assert joint.get_velocity() == pytest.approx(0.003, rel=1e-9)
    assert scripted_bus.log == [(0x12, GETENCODERRPM, 5)]


# ------------------------------------------------------------------ position
@pytest.mark.parametrize(("name", "offset", "q"), [("j1", 0.5, 1.0), ("j2", 0.338, 0.1), ("j3", -2.5, 0.0)])
def test_set_position_sends_motor_degrees_relative_to_offset(
    scripted_bus: Any, make_ready: Callable[..., Joint], name: str, offset: float, q: float
) -> None:
    joint = make_ready(name, offset=offset)
    scripted_bus.queue(flags(READY))
    joint.set_position(q)
    reduction = float(JOINTS[name]["reduction"])
    expected = math.degrees(reduction * (q - as_f32(offset)))
    assert scripted_bus.log == [(address_of(name), MOVETOANGLE + f32(expected), 1)]


def test_set_position_of_j1_sends_known_degrees(scripted_bus: Any, make_ready: Callable[..., Joint]) -> None:
    joint = make_ready("j1", offset=0.5)
    scripted_bus.queue(flags(READY))
    joint.set_position(1.0)
    (deg,) = struct.unpack("<f", scripted_bus.log[0][1][1:])
    assert deg == pytest.approx(1002.6761, abs=1e-3)  # rad2deg(35 * 0.5)


def test_get_position_reads_angle_moved_and_adds_offset(
    scripted_bus: Any, make_ready: Callable[..., Joint]
) -> None:
    joint = make_ready("j1", offset=0.5)
    scripted_bus.queue(f32_reply(90.0, READY), f32_reply(90.0, READY))
    q = joint.get_position()
    # the first reading after init() has nothing to compare with: a second one must agree (docs/protocol.md)
    assert scripted_bus.log == [(0x11, ANGLEMOVED, 5)] * 2
    assert q == pytest.approx(math.radians(90.0) / 35.0 + 0.5, rel=1e-12)
    scripted_bus.queue(f32_reply(90.0, READY))
    joint.get_position()
    assert scripted_bus.log == [(0x11, ANGLEMOVED, 5)] * 3  # later ones are compared with it


def test_get_position_is_zero_while_not_homed(scripted_bus: Any, make_ready: Callable[..., Joint]) -> None:
    joint = make_ready("j1", state=NOT_HOMED)
    scripted_bus.queue(f32_reply(90.0, NOT_HOMED))
    assert joint.get_position() == 0.0
    assert scripted_bus.log == [(0x11, ANGLEMOVED, 5)]


def test_get_position_follows_the_reply_flags_not_the_previous_state(
    scripted_bus: Any, make_ready: Callable[..., Joint]
) -> None:
    joint = make_ready("j1", offset=0.5)
    scripted_bus.queue(f32_reply(90.0, NOT_HOMED), ack(NOT_HOMED), ack(NOT_HOMED))  # NOTHOMED confirmed twice
    assert joint.get_position() == 0.0
    assert not joint.is_homed()


# ------------------------------------------------------------------ refusals
MOTION = [
    pytest.param(lambda j: j.set_velocity(0.1), id="set_velocity"),
    pytest.param(lambda j: j.set_position(0.1), id="set_position"),
]


@pytest.mark.parametrize("command", MOTION)
def test_motion_refused_when_not_enabled(
    scripted_bus: Any, make_ready: Callable[..., Joint], command: Callable[[Joint], None]
) -> None:
    joint = make_ready("j1", state=NOT_ENABLED)
    with pytest.raises(NotEnabledError, match="j1"):
        command(joint)
    assert scripted_bus.log == []


@pytest.mark.parametrize("command", MOTION)
def test_motion_refused_when_not_homed(
    scripted_bus: Any, make_ready: Callable[..., Joint], command: Callable[[Joint], None]
) -> None:
    joint = make_ready("j1", state=NOT_HOMED)
    with pytest.raises(NotHomedError, match="j1"):
        command(joint)
    assert scripted_bus.log == []


def test_set_velocity_refused_when_not_homed(scripted_bus: Any, make_ready: Callable[..., Joint]) -> None:
    joint = make_ready("j2", state=NOT_HOMED)
    with pytest.raises(NotHomedError):
        joint.set_velocity(0.01)
    assert scripted_bus.log == []


@pytest.mark.parametrize(
    "command",
    [*MOTION, pytest.param(lambda j: j.move_steps(10), id="move_steps")],
)
def test_motion_raises_stalled_when_reply_says_stall(
    scripted_bus: Any, make_ready: Callable[..., Joint], command: Callable[[Joint], None]
) -> None:
    joint = make_ready("j1")
    # a new STALL is confirmed by two PINGs; the joint is then stopped (MOVESTEPS runs even when stalled)
    scripted_bus.queue(flags(STALL), ack(STALL), ack(STALL), flags(STALL))
    with pytest.raises(StalledError, match="j1"):
        command(joint)
    assert scripted_bus.log[1:] == [(0x11, PING, 2), (0x11, PING, 2), (0x11, bytes((0x29, 0)), 1)]
    assert joint.is_stalled()


def test_set_velocity_raises_not_enabled_when_reply_says_deadman_tripped(
    scripted_bus: Any, make_ready: Callable[..., Joint]
) -> None:
    joint = make_ready("j1")
    # a new NOTENABLED is confirmed by two PINGs; the firmware ran the SETRPM anyway, so STOP follows
    scripted_bus.queue(flags(NOT_ENABLED), ack(NOT_ENABLED), ack(NOT_ENABLED), flags(NOT_ENABLED))
    with pytest.raises(NotEnabledError):
        joint.set_velocity(0.1)
    assert scripted_bus.log[1:] == [(0x11, PING, 2), (0x11, PING, 2), (0x11, bytes((0x29, 0)), 1)]


@pytest.mark.parametrize(
    "command",
    [
        pytest.param(lambda j: j.set_velocity(math.nan), id="set_velocity(nan)"),
        pytest.param(lambda j: j.set_velocity(-math.inf), id="set_velocity(-inf)"),
        pytest.param(lambda j: j.set_position(math.nan), id="set_position(nan)"),
        pytest.param(lambda j: j.set_position(math.inf), id="set_position(inf)"),
    ],
)
def test_motion_rejects_non_finite_values_before_any_traffic(
    scripted_bus: Any, make_ready: Callable[..., Joint], command: Callable[[Joint], None]
) -> None:
    joint = make_ready("j1")
    with pytest.raises(InvalidArgumentError):
        command(joint)
    assert scripted_bus.log == []


@pytest.mark.parametrize(
    "command",
    [
        pytest.param(lambda j: j.set_position(1e38), id="set_position"),
        pytest.param(lambda j: j.set_velocity(1e38), id="set_velocity"),
        pytest.param(lambda j: j.set_max_velocity(1e38), id="set_max_velocity"),
    ],
)
def test_float_payload_beyond_float32_range_rejected_before_any_traffic(
    scripted_bus: Any, make_ready: Callable[..., Joint], command: Callable[[Joint], None]
) -> None:
    joint = make_ready("j1")
    with pytest.raises(InvalidArgumentError):
        command(joint)
    assert scripted_bus.log == []


EVERY_METHOD = [
    pytest.param(lambda j: j.enable(20, 20), id="enable"),
    pytest.param(lambda j: j.disable(), id="disable"),
    pytest.param(lambda j: j.get_position(), id="get_position"),
    pytest.param(lambda j: j.set_position(0.0), id="set_position"),
    pytest.param(lambda j: j.get_velocity(), id="get_velocity"),
    pytest.param(lambda j: j.set_velocity(0.0), id="set_velocity"),
    pytest.param(lambda j: j.move_steps(10), id="move_steps"),
    pytest.param(lambda j: j.stop(), id="stop"),
    pytest.param(lambda j: j.check_orientation(), id="check_orientation"),
    pytest.param(lambda j: j.disable_closed_loop(), id="disable_closed_loop"),
    pytest.param(lambda j: j.set_drive_current(20), id="set_drive_current"),
    pytest.param(lambda j: j.set_hold_current(20), id="set_hold_current"),
    pytest.param(lambda j: j.set_brake_mode(0), id="set_brake_mode"),
    pytest.param(lambda j: j.set_max_acceleration(1.0), id="set_max_acceleration"),
    pytest.param(lambda j: j.set_max_velocity(1.0), id="set_max_velocity"),
    pytest.param(lambda j: j.enable_stallguard(6), id="enable_stallguard"),
    pytest.param(lambda j: j.start_homing(0.03, 30, 15), id="start_homing"),
    pytest.param(lambda j: j.post_homing(), id="post_homing"),
    pytest.param(lambda j: j.home(0.03, 30, 15), id="home"),
    pytest.param(lambda j: j.wait_while_busy(), id="wait_while_busy"),
    pytest.param(lambda j: j.get_flags(), id="get_flags"),
]


@pytest.mark.parametrize("command", EVERY_METHOD)
def test_every_method_refused_before_init(
    scripted_bus: Any, make_joint: Callable[..., Joint], command: Callable[[Joint], object]
) -> None:
    joint = make_joint("j1")
    with pytest.raises(NotInitError, match="j1"):
        command(joint)
    assert scripted_bus.log == []


@pytest.mark.parametrize("command", EVERY_METHOD)
def test_every_method_refused_after_deinit(
    scripted_bus: Any, make_ready: Callable[..., Joint], command: Callable[[Joint], object]
) -> None:
    joint = make_ready("j1")
    joint.deinit()
    with pytest.raises(NotInitError):
        command(joint)
    assert scripted_bus.log == []


# ------------------------------------------------------------- move_steps
@pytest.mark.parametrize("steps", [200, -200, 0, 2**31 - 1, -(2**31)])
def test_move_steps_sends_int32(scripted_bus: Any, make_ready: Callable[..., Joint], steps: int) -> None:
    joint = make_ready("j1")
    scripted_bus.queue(flags(READY))
    joint.move_steps(steps)
    assert scripted_bus.log == [(0x11, MOVESTEPS + struct.pack("<i", steps), 1)]


def test_move_steps_sends_negative_steps_little_endian(
    scripted_bus: Any, make_ready: Callable[..., Joint]
) -> None:
    joint = make_ready("j1")
    scripted_bus.queue(flags(READY))
    joint.move_steps(-200)
    assert scripted_bus.log == [(0x11, b"\x13\x38\xff\xff\xff", 1)]


def test_move_steps_allowed_when_not_homed(scripted_bus: Any, make_ready: Callable[..., Joint]) -> None:
    joint = make_ready("j1", state=NOT_HOMED)
    scripted_bus.queue(flags(NOT_HOMED))
    joint.move_steps(50)
    assert scripted_bus.log == [(0x11, MOVESTEPS + struct.pack("<i", 50), 1)]


def test_move_steps_refused_when_not_enabled(scripted_bus: Any, make_ready: Callable[..., Joint]) -> None:
    joint = make_ready("j1", state=POWER_UP)
    with pytest.raises(NotEnabledError):
        joint.move_steps(50)
    assert scripted_bus.log == []


@pytest.mark.parametrize("steps", [2**31, -(2**31) - 1, 1.5, True])
def test_move_steps_rejects_non_int32_before_any_traffic(
    scripted_bus: Any, make_ready: Callable[..., Joint], steps: Any
) -> None:
    joint = make_ready("j1")
    with pytest.raises(InvalidArgumentError):
        joint.move_steps(steps)
    assert scripted_bus.log == []


# --------------------------------------------------------- simple commands
@pytest.mark.parametrize(
    ("command", "written"),
    [
        pytest.param(lambda j: j.stop(), STOP + b"\x00", id="stop"),
        pytest.param(
            lambda j: j.disable_closed_loop(), DISABLECLOSEDLOOP + b"\x00", id="disable_closed_loop"
        ),
        pytest.param(lambda j: j.set_drive_current(40), SETCURRENT + bytes((40,)), id="set_drive_current"),
        pytest.param(lambda j: j.set_hold_current(30), SETHOLDCURRENT + bytes((30,)), id="set_hold_current"),
        pytest.param(lambda j: j.set_brake_mode(0), SETBRAKEMODE + b"\x00", id="brake_freewheel"),
        pytest.param(lambda j: j.set_brake_mode(1), SETBRAKEMODE + b"\x01", id="brake_coolbrake"),
        pytest.param(lambda j: j.set_brake_mode(2), SETBRAKEMODE + b"\x02", id="brake_hardbrake"),
        pytest.param(lambda j: j.enable_stallguard(6), ENABLESTALLGUARD + b"\x06", id="enable_stallguard"),
        pytest.param(lambda j: j.enable_stallguard(255), ENABLESTALLGUARD + b"\xff", id="stallguard_255"),
    ],
)
def test_command_writes_register_and_uint8_and_reads_flags(
    scripted_bus: Any, make_ready: Callable[..., Joint], command: Callable[[Joint], None], written: bytes
) -> None:
    joint = make_ready("j3")
    scripted_bus.queue(flags(READY))
    command(joint)
    assert scripted_bus.log == [(0x13, written, 1)]


def test_stop_allowed_when_not_enabled(scripted_bus: Any, make_ready: Callable[..., Joint]) -> None:
    joint = make_ready("j1", state=POWER_UP)
    scripted_bus.queue(flags(POWER_UP))
    joint.stop()
    assert scripted_bus.log == [(0x11, STOP + b"\x00", 1)]


@pytest.mark.parametrize(
    "command",
    [
        pytest.param(lambda j: j.set_drive_current(101), id="drive_current"),
        pytest.param(lambda j: j.set_hold_current(-1), id="hold_current"),
        pytest.param(lambda j: j.set_brake_mode(3), id="brake_mode"),
        pytest.param(lambda j: j.enable_stallguard(256), id="stallguard"),
        pytest.param(lambda j: j.set_max_velocity(0.0), id="max_velocity_zero"),
        pytest.param(lambda j: j.set_max_acceleration(-1.0), id="max_acceleration_negative"),
    ],
)
def test_command_rejects_out_of_range_argument_before_any_traffic(
    scripted_bus: Any, make_ready: Callable[..., Joint], command: Callable[[Joint], None]
) -> None:
    joint = make_ready("j1")
    with pytest.raises(InvalidArgumentError, match="j1"):
        command(joint)
    assert scripted_bus.log == []


@pytest.mark.parametrize(
    ("name", "method", "register", "value", "degrees"),
    [
        ("j1", "set_max_acceleration", SETMAXACCELERATION, 2.0, 4010.7046),  # rad2deg(35 * 2)
        ("j1", "set_max_velocity", SETMAXVELOCITY, 1.0, 2005.3523),  # rad2deg(35 * 1)
        ("j2", "set_max_acceleration", SETMAXACCELERATION, 0.2, 18000.0),
        ("j2", "set_max_velocity", SETMAXVELOCITY, 0.03, 2700.0),
        ("j4", "set_max_velocity", SETMAXVELOCITY, 10.0, 6875.4935),  # rad2deg(12 * 10)
    ],
)
def test_max_rate_sent_as_magnitude_in_motor_degrees(
    scripted_bus: Any,
    make_ready: Callable[..., Joint],
    name: str,
    method: str,
    register: bytes,
    value: float,
    degrees: float,
) -> None:
    joint = make_ready(name)
    scripted_bus.queue(flags(READY))
    getattr(joint, method)(value)
    reduction = float(JOINTS[name]["reduction"])
    assert scripted_bus.log == [(address_of(name), register + f32(abs(math.degrees(reduction * value))), 1)]
    (sent,) = struct.unpack("<f", scripted_bus.log[0][1][1:])
    assert sent > 0
    assert sent == pytest.approx(degrees, abs=1e-3)


def test_get_flags_pings_and_returns_reply_flags(scripted_bus: Any, make_ready: Callable[..., Joint]) -> None:
    joint = make_ready("j1")
    # the new NOTHOMED read twice more (registers.STICKY_CONFIRMATIONS)
    scripted_bus.queue(ack(BUSY | NOT_HOMED), ack(BUSY | NOT_HOMED), ack(BUSY | NOT_HOMED))
    assert joint.get_flags() == Flag.BUSY | Flag.NOT_HOMED
    assert scripted_bus.log == [(0x11, PING, 2)] * 3
    assert joint.is_busy()
    assert not joint.is_homed()


# --------------------------------------------------------- check_orientation
def test_check_orientation_sends_degrees_then_pings_until_not_busy(
    scripted_bus: Any, make_ready: Callable[..., Joint], clock: ManualClock
) -> None:
    joint = make_ready("j1")
    # BUSY gone is read twice more (STICKY_CONFIRMATIONS): one flipped bit could fake the end
    scripted_bus.queue(flags(BUSY), ack(BUSY), ack(READY), ack(READY), ack(READY))
    joint.check_orientation(2.0)
    assert scripted_bus.log == [
        (0x11, CHECKORIENTATION + b"\x00\x00\x00\x40", 1),
        (0x11, PING, 2),
        (0x11, PING, 2),
        (0x11, PING, 2),
        (0x11, PING, 2),
    ]
    assert clock.now() == pytest.approx(BLOCKING_PICKUP_S + BUSY_POLL_S)
    assert joint.current_blocking_command is Reg.NONE
    assert not joint.is_busy()


def test_check_orientation_refused_when_not_enabled(
    scripted_bus: Any, make_ready: Callable[..., Joint]
) -> None:
    joint = make_ready("j1", state=POWER_UP)
    with pytest.raises(NotEnabledError):
        joint.check_orientation()
    assert scripted_bus.log == []


# ------------------------------------------------------------------- homing
@pytest.mark.parametrize(
    ("name", "velocity", "sensitivity", "current", "home_bytes"),
    [
        ("j1", 0.03, 30, 15, (1, 10, 30, 15)),  # +10.03 RPM
        ("j1", -0.03, 30, 15, (0, 10, 30, 15)),
        ("j2", 0.003, 50, 30, (0, 45, 50, 30)),  # negative reduction: -45 RPM
        ("j2", -0.003, 50, 30, (1, 45, 50, 30)),
        ("j3", 0.05, 25, 10, (1, 11, 25, 10)),  # 11.46 RPM
        ("j4", 0.1, 30, 10, (1, 11, 30, 10)),
    ],
)
def test_start_homing_sends_direction_speed_sensitivity_current(
    scripted_bus: Any,
    make_ready: Callable[..., Joint],
    name: str,
    velocity: float,
    sensitivity: int,
    current: int,
    home_bytes: tuple[int, int, int, int],
) -> None:
    joint = make_ready(name, state=NOT_HOMED)
    scripted_bus.queue(flags(NOT_HOMED), flags(BUSY | NOT_HOMED))
    joint.start_homing(velocity, sensitivity, current)
    assert scripted_bus.log == [
        (address_of(name), HOMEOFFSET + NAN_OFFSET, 1),
        (address_of(name), HOME + bytes(home_bytes), 1),
    ]
    assert joint.current_blocking_command is Reg.HOME
    assert joint.is_busy()


@pytest.mark.parametrize(
    ("name", "velocity", "offset"),
    [
        ("j1", 0.03, 3.04647),
        ("j1", -0.03, -3.04647),
        ("j2", 0.003, 0.338),
        ("j2", -0.003, -0.0016),
    ],
)
def test_post_homing_pings_then_writes_limit_as_home_offset(
    scripted_bus: Any, make_ready: Callable[..., Joint], name: str, velocity: float, offset: float
) -> None:
    joint = make_ready(name, state=NOT_HOMED)
    scripted_bus.queue(flags(NOT_HOMED), flags(BUSY | NOT_HOMED))
    joint.start_homing(velocity, 30, 15)
    scripted_bus.queue(ack(BUSY))  # a poll while it runs: the end stop reached, the handler finishing
    joint.get_flags()
    scripted_bus.clear_log()
    scripted_bus.queue(ack(READY), flags(READY))
    joint.post_homing()
    address = address_of(name)
    assert scripted_bus.log == [(address, PING, 2), (address, HOMEOFFSET + f32(offset), 1)]
    assert joint.offset == offset
    assert joint.current_blocking_command is Reg.NONE


def test_the_end_of_a_homing_clears_stall_and_not_homed_without_a_second_reading(
    scripted_bus: Any, make_joint: Callable[..., Joint]
) -> None:
    # joint.ino, HOME: at the end stop, notHomed = 0 and isStalled = 0 while
    # isBusy stays set until the handler has stopped the motor and restored its
    # current: a reading then shows BUSY alone, and both flags are gone for real.
    joint = make_joint("j1")
    scripted_bus.queue(*[ack(STALL | NOT_HOMED)] * 3)  # init's PING; STALL is confirmed by two more
    joint.init()
    scripted_bus.queue(flags(STALL | NOT_HOMED), flags(BUSY | NOT_HOMED | STALL))
    joint.start_homing(0.03, 30, 15)
    scripted_bus.clear_log()
    scripted_bus.queue(ack(BUSY))
    assert joint.get_flags() == Flag.BUSY
    assert scripted_bus.log == [(0x11, PING, 2)]


def test_a_new_session_believes_the_flags_of_its_first_reading(
    scripted_bus: Any, make_ready: Callable[..., Joint]
) -> None:
    # Between two sessions another host may have enabled the joint: the first
    # reading after init() is not compared with the last session's flags.
    joint = make_ready("j1", state=NOT_HOMED | NOT_ENABLED)
    joint.deinit()
    scripted_bus.queue(ack(NOT_HOMED))
    joint.init()
    assert scripted_bus.log == [(0x11, PING, 2)]
    assert joint.flags == Flag.NOT_HOMED


@pytest.mark.parametrize(
    "replies",
    [
        (ack(NOT_HOMED),),
        # NOTHOMED gone in post_homing's reading, though no poll saw the homing end: read
        # again. An aborted homing leaves NOTHOMED set (joint.ino: "Homing has been
        # cancled"); one flipped bit there would make the joint homed at the end stop's
        # offset wherever it stands.
        (ack(READY), ack(NOT_HOMED), ack(NOT_HOMED)),
    ],
    ids=["still-not-homed", "not-homed-gone-in-one-reading"],
)
def test_post_homing_fails_when_joint_still_not_homed(
    scripted_bus: Any, make_ready: Callable[..., Joint], replies: tuple[bytes, ...]
) -> None:
    joint = make_ready("j1", state=NOT_HOMED)
    scripted_bus.queue(flags(NOT_HOMED), flags(BUSY | NOT_HOMED))
    joint.start_homing(0.03, 30, 15)
    scripted_bus.clear_log()
    scripted_bus.queue(*replies)
    with pytest.raises(NotHomedError, match="j1"):
        joint.post_homing()
    assert scripted_bus.log == [(0x11, PING, 2)] * len(replies)
    assert joint.offset == 0.0
    assert joint.current_blocking_command is Reg.NONE


def test_home_waits_while_busy_then_stores_offset(
    scripted_bus: Any, make_ready: Callable[..., Joint], clock: ManualClock
) -> None:
    joint = make_ready("j1", state=NOT_HOMED)
    scripted_bus.queue(
        flags(NOT_HOMED),  # HOMEOFFSET := NaN
        flags(BUSY | NOT_HOMED),  # HOME
        ack(BUSY | NOT_HOMED),  # wait_while_busy
        ack(READY),
        ack(READY),  # BUSY gone, read twice more
        ack(READY),
        ack(READY),  # post_homing
        flags(READY),  # HOMEOFFSET
    )
    joint.home(-0.03, 30, 15)
    assert scripted_bus.writes() == [
        HOMEOFFSET + NAN_OFFSET,
        HOME + bytes((0, 10, 30, 15)),
        PING,
        PING,
        PING,
        PING,
        PING,
        HOMEOFFSET + f32(-3.04647),
    ]
    assert joint.offset == -3.04647
    assert clock.now() == pytest.approx(BLOCKING_PICKUP_S + BUSY_POLL_S)


def test_start_homing_refused_while_another_blocking_command_runs(
    scripted_bus: Any, make_ready: Callable[..., Joint]
) -> None:
    joint = make_ready("j1", state=NOT_HOMED)
    scripted_bus.queue(flags(NOT_HOMED), flags(BUSY | NOT_HOMED))
    joint.start_homing(0.03, 30, 15)
    scripted_bus.clear_log()
    with pytest.raises(IncorrectStateError, match="HOME"):
        joint.start_homing(0.03, 30, 15)
    assert scripted_bus.log == []


def test_start_homing_refused_when_not_enabled(scripted_bus: Any, make_ready: Callable[..., Joint]) -> None:
    joint = make_ready("j1", state=POWER_UP)
    with pytest.raises(NotEnabledError):
        joint.start_homing(0.03, 30, 15)
    assert scripted_bus.log == []


@pytest.mark.parametrize("name", ["j1", "j2"])
@pytest.mark.parametrize("rpm", [1.001, 249.999, -1.001, -249.999, 1.5, 249.0])
def test_homing_rpm_just_inside_bounds_is_sent(
    scripted_bus: Any, make_ready: Callable[..., Joint], name: str, rpm: float
) -> None:
    joint = make_ready(name, state=NOT_HOMED)
    velocity = velocity_for_rpm(rpm, float(JOINTS[name]["reduction"]))
    scripted_bus.queue(flags(NOT_HOMED), flags(BUSY | NOT_HOMED))
    joint.start_homing(velocity, 30, 15)
    direction = 1 if rpm > 0 else 0
    home = HOME + bytes((direction, int(abs(rpm)), 30, 15))
    assert scripted_bus.writes() == [HOMEOFFSET + NAN_OFFSET, home]


@pytest.mark.parametrize("name", ["j1", "j2"])
@pytest.mark.parametrize("rpm", [0.999, 250.001, -0.999, -250.001, 0.0, 1000.0])
def test_homing_rpm_outside_bounds_rejected_before_any_traffic(
    scripted_bus: Any, make_ready: Callable[..., Joint], name: str, rpm: float
) -> None:
    joint = make_ready(name, state=NOT_HOMED)
    velocity = velocity_for_rpm(rpm, float(JOINTS[name]["reduction"]))
    with pytest.raises(InvalidArgumentError, match=f"{name}.*RPM"):
        joint.start_homing(velocity, 30, 15)
    assert scripted_bus.log == []
    assert joint.current_blocking_command is Reg.NONE


# Only j1's reduction reaches both bounds exactly in float64.
@pytest.mark.parametrize("rpm", [1.0, 250.0, -1.0, -250.0])
def test_homing_rpm_exactly_on_bounds_rejected_before_any_traffic(
    scripted_bus: Any, make_ready: Callable[..., Joint], rpm: float
) -> None:
    joint = make_ready("j1", state=NOT_HOMED)
    velocity = velocity_for_rpm(rpm, 35.0, exact=True)
    with pytest.raises(InvalidArgumentError, match=r"j1.*RPM"):
        joint.start_homing(velocity, 30, 15)
    assert scripted_bus.log == []


# ------------------------------------------------------------------- retries
def test_transaction_retried_after_bus_error(scripted_bus: Any, make_ready: Callable[..., Joint]) -> None:
    joint = make_ready("j1")
    joint.stats.reset()
    scripted_bus.queue(OSError(121, "Remote I/O error"), flags(READY))
    joint.set_velocity(0.5)
    assert scripted_bus.writes() == [SETRPM + f32(math.degrees(17.5) / 6.0)] * 2
    assert joint.stats.transactions == 2
    assert joint.stats.errors == 1


@pytest.mark.parametrize("retries", [0, 1, 2, 4])
def test_comm_error_after_retries_plus_one_failures_names_joint_and_register(
    scripted_bus: Any, make_ready: Callable[..., Joint], retries: int
) -> None:
    joint = make_ready("j1", retries=retries)
    joint.stats.reset()
    scripted_bus.queue(*[OSError(121, "Remote I/O error") for _ in range(retries + 1)])
    with pytest.raises(CommError, match="j1") as info:
        joint.set_velocity(0.5)
    assert "SETRPM" in str(info.value)
    assert isinstance(info.value.__cause__, OSError)
    assert len(scripted_bus.log) == retries + 1
    assert joint.stats.transactions == retries + 1
    assert joint.stats.errors == retries + 1


@pytest.mark.parametrize(
    "bad_reply",
    [flags(0x80), flags(0x10), b"", flags(READY) * 2],
    ids=["reserved_bit7", "reserved_bit4", "empty", "too_long"],
)
def test_malformed_command_reply_counts_as_failed_attempt(
    scripted_bus: Any, make_ready: Callable[..., Joint], bad_reply: bytes
) -> None:
    joint = make_ready("j1")
    joint.stats.reset()
    scripted_bus.queue(bad_reply, flags(READY))
    joint.set_velocity(0.5)
    assert len(scripted_bus.log) == 2
    assert joint.stats.transactions == 2
    assert joint.stats.errors == 1


@pytest.mark.parametrize(
    "bad_reply",
    [f32(90.0) + flags(0x80), f32(90.0), f32(90.0) + b"\x00\x00", f32(math.nan) + flags(READY)],
    ids=["reserved_bit7", "short", "too_long", "nan"],
)
def test_malformed_read_reply_counts_as_failed_attempt(
    scripted_bus: Any, make_ready: Callable[..., Joint], bad_reply: bytes
) -> None:
    joint = make_ready("j1", offset=0.5)
    joint.stats.reset()
    scripted_bus.queue(bad_reply, f32_reply(90.0, READY), f32_reply(90.0, READY))  # the last: confirmation
    assert joint.get_position() == pytest.approx(math.radians(90.0) / 35.0 + 0.5)
    assert joint.stats.transactions == 3
    assert joint.stats.errors == 1
    assert joint.stats.retries == 1


def test_only_malformed_replies_give_comm_error(scripted_bus: Any, make_ready: Callable[..., Joint]) -> None:
    joint = make_ready("j2", retries=1)
    scripted_bus.queue(f32(1.0) + flags(0x80), f32(1.0) + flags(0x80))
    with pytest.raises(CommError, match=r"j2.*ANGLEMOVED"):
        joint.get_position()


def test_stats_reset_keeps_totals(scripted_bus: Any, make_ready: Callable[..., Joint]) -> None:
    joint = make_ready("j1", state=POWER_UP)  # 1 transaction so far
    scripted_bus.queue(OSError(5, "I/O error"), flags(POWER_UP))
    joint.stop()
    assert (joint.stats.transactions, joint.stats.errors) == (3, 1)
    joint.stats.reset()
    assert (joint.stats.transactions, joint.stats.errors) == (0, 0)
    assert (joint.stats.total_transactions, joint.stats.total_errors) == (3, 1)
    assert joint.stats.error_rate == 0.0


# -------------------------------------------------------------------- SMBus
class FakeSMBus:
    """Stands in for ``smbus2.SMBus``: records ``i2c_rdwr`` calls, fills read buffers."""

    instances: list[FakeSMBus] = []
    reply = b"O\x0c"

    def __init__(self, bus: int) -> None:
        self.bus = bus
        self.calls: list[list[tuple[int, int, int, bytes]]] = []
        self.closed = False
        FakeSMBus.instances.append(self)

    def i2c_rdwr(self, *msgs: smbus2.i2c_msg) -> None:
        self.calls.append([(m.addr, m.flags, m.len, bytes(m)) for m in msgs])
        for m in msgs:
            if m.flags & I2C_M_RD:
                ctypes.memmove(m.buf, self.reply.ljust(m.len, b"\x00"), m.len)

    def close(self) -> None:
        self.closed = True


@pytest.fixture
def fake_smbus(monkeypatch: pytest.MonkeyPatch) -> type[FakeSMBus]:
    monkeypatch.setattr(FakeSMBus, "instances", [])
    monkeypatch.setattr(smbus2, "SMBus", FakeSMBus)
    return FakeSMBus


@pytest.mark.skipif(os.path.exists("/dev/i2c-250"), reason="/dev/i2c-250 exists here")
def test_smbus_open_missing_bus_raises_comm_error_naming_device() -> None:
    with pytest.raises(CommError, match="/dev/i2c-250") as info:
        SMBusI2C(250)
    assert isinstance(info.value.__cause__, FileNotFoundError)


def test_smbus_open_without_permission_raises_comm_error_with_hint(monkeypatch: pytest.MonkeyPatch) -> None:
    def denied(bus: int) -> None:
        raise PermissionError(13, "Permission denied", f"/dev/i2c-{bus}")

    monkeypatch.setattr(smbus2, "SMBus", denied)
    with pytest.raises(CommError, match=r"/dev/i2c-1.*i2c"):
        SMBusI2C(1)


def test_smbus_open_of_a_regular_file_names_the_device(
    tmp_path: Path, monkeypatch: pytest.MonkeyPatch
) -> None:
    # Seen: "[Errno 25] Inappropriate ioctl for device", without the path.
    device = tmp_path / "i2c-1"
    device.write_bytes(b"")
    monkeypatch.setattr("bioscara_gym.hardware.bus.DEVICE_PATH", str(tmp_path / "i2c-{bus}"))
    with pytest.raises(CommError, match=rf"^{device}: Inappropriate ioctl for device: not an I2C adapter"):
        SMBusI2C(1)


def test_smbus_transfer_error_names_the_device_and_address(fake_smbus: type[FakeSMBus]) -> None:
    bus = SMBusI2C(1)

    def refuse(*msgs: smbus2.i2c_msg) -> None:
        raise OSError(25, "Inappropriate ioctl for device")

    fake_smbus.instances[0].i2c_rdwr = refuse  # type: ignore[method-assign]
    with pytest.raises(OSError, match=r"Inappropriate ioctl for device \(/dev/i2c-1, address 0x11\)") as info:
        bus.transfer(0x11, PING, 2)
    assert info.value.errno == 25


def test_smbus_transfer_is_one_combined_write_then_read(fake_smbus: type[FakeSMBus]) -> None:
    bus = SMBusI2C(1)
    reply = bus.transfer(0x12, b"\x18", 5)
    (device,) = fake_smbus.instances
    assert device.bus == "/dev/i2c-1"
    assert len(device.calls) == 1
    (write, read) = device.calls[0]
    assert write[:3] == (0x12, 0, 1)  # addr, flags (write), len
    assert write[3] == b"\x18"
    assert read[:3] == (0x12, I2C_M_RD, 5)
    assert reply == b"O\x0c\x00\x00\x00"


def test_smbus_transfer_returns_the_read_bytes(fake_smbus: type[FakeSMBus]) -> None:
    bus = SMBusI2C(1)
    assert bus.transfer(0x11, PING, 2) == b"O\x0c"


def test_smbus_closes_device_on_leaving_with_block(fake_smbus: type[FakeSMBus]) -> None:
    with SMBusI2C(1):
        pass
    assert fake_smbus.instances[0].closed


def test_joint_over_smbus_pings_with_one_rdwr(fake_smbus: type[FakeSMBus]) -> None:
    joint = Joint("j1", address=0x11, reduction=35.0, min=-3.04647, max=3.04647, bus=SMBusI2C(1))
    joint.init()
    (device,) = fake_smbus.instances
    assert [[m[:3] for m in call] for call in device.calls] == [[(0x11, 0, 1), (0x11, I2C_M_RD, 2)]]
    assert joint.flags == Flag.NOT_HOMED | Flag.NOT_ENABLED
