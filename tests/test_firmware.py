"""The emulated joint firmware, byte by byte (docs/protocol.md, docs/firmware.md).

No driver here: tests write the bytes a master would write to
:meth:`JointFirmware.transfer` and read the bytes it answers. The stall
detector's arithmetic is tested on :class:`FirmwareCore` with a fake motor
whose set point and encoder the test sets directly.
"""

from __future__ import annotations

import math
import struct

import pytest
from rigs import FakeMotor

from bioscara_gym.hardware import firmware as firmware_module
from bioscara_gym.hardware.clock import ManualClock
from bioscara_gym.hardware.firmware import (
    FirmwareCore,
    JointFirmware,
    stall_threshold,
)
from bioscara_gym.hardware.motor import POLE_PITCH_DEG, KinematicStepper
from bioscara_gym.hardware.registers import TICK_S, Flag, Reg

POWER_UP = 0b00001100
#: SPEC j1 homing, at the motor: direction, 10 RPM, sensitivity 30, current 15 % (bytes 0-3).
HOME_POSITIVE = 0x0F1E0A01
HOME_NEGATIVE = 0x0F1E0A00
#: SETUP drive 20 %, hold 20 % (bytes 0-1).
SETUP_20_20 = 0x1414
#: Payload formats as docs/protocol.md lists them (independent of the code's register table).
FORMATS = {
    Reg.PING: "<B",
    Reg.SETUP: "<I",
    Reg.SETRPM: "<f",
    Reg.MOVESTEPS: "<i",
    Reg.MOVETOANGLE: "<f",
    Reg.ANGLEMOVED: "<f",
    Reg.SETCURRENT: "<B",
    Reg.SETHOLDCURRENT: "<B",
    Reg.SETMAXACCELERATION: "<f",
    Reg.SETMAXVELOCITY: "<f",
    Reg.ENABLESTALLGUARD: "<B",
    Reg.SETBRAKEMODE: "<B",
    Reg.DISABLECLOSEDLOOP: "<B",
    Reg.STOP: "<B",
    Reg.CHECKORIENTATION: "<f",
    Reg.GETENCODERRPM: "<f",
    Reg.HOME: "<I",
    Reg.HOMEOFFSET: "<f",
}

# ----------------------------------------------------------------- helpers


def command(fw: JointFirmware, reg: Reg, value: float | int = 0) -> int:
    """Write ``[REG][payload]`` and read the flags byte."""
    data = bytes((reg,)) + struct.pack(FORMATS[reg], value)
    (flags,) = fw.transfer(data, 1)
    return flags


def query(fw: JointFirmware, reg: Reg) -> tuple[float | int, int]:
    """Write ``[REG]``, read payload + flags; return (value, flags)."""
    fmt = FORMATS[reg]
    reply = fw.transfer(bytes((reg,)), struct.calcsize(fmt) + 1)
    return struct.unpack(fmt, reply[:-1])[0], reply[-1]


def ping_flags(fw: JointFirmware) -> int:
    return query(fw, Reg.PING)[1]


def ticks(fw: JointFirmware, n: int = 1) -> None:
    """Let ``n`` main-loop ticks pass without bus traffic."""
    fw.clock.sleep(n * TICK_S)
    fw.update()


def run_until_idle(fw: JointFirmware, timeout_s: float = 10.0) -> None:
    """Poll (PING every tick) until BUSY clears."""
    for _ in range(round(timeout_s / TICK_S)):
        if not ping_flags(fw) & Flag.BUSY:
            return
        ticks(fw)
    raise AssertionError("still BUSY")


def firmware_between_stops(lower: float = -720.0, upper: float = 360.0) -> JointFirmware:
    """Firmware in front of a stepper at 0 deg between two end stops (motor degrees)."""
    motor = KinematicStepper(0.0, lower_stop_deg=lower, upper_stop_deg=upper)
    return JointFirmware(motor, ManualClock())


def enabled(fw: JointFirmware) -> JointFirmware:
    command(fw, Reg.SETUP, SETUP_20_20)
    return fw


def host_limits(fw: JointFirmware) -> JointFirmware:
    """SETMAXVELOCITY 1000 deg/s, SETMAXACCELERATION 2000 deg/s^2: the host sets its own before moving.

    At the power-up limits (18 deg/s, 180 deg/s^2, docs/firmware.md) the
    moves below would take seconds.
    """
    command(fw, Reg.SETMAXVELOCITY, 1000.0)
    command(fw, Reg.SETMAXACCELERATION, 2000.0)
    return fw


def start_blocking(fw: JointFirmware, reg: Reg, value: float | int) -> int:
    """Send a blocking command and stay silent for one main-loop pass, so the loop takes it.

    A transaction before that would cancel the command (``rx_data_ready = 0``).
    Returns the flags of the command's reply.
    """
    flags = command(fw, reg, value)
    ticks(fw)
    return flags


def homed(fw: JointFirmware, payload: int = HOME_POSITIVE) -> JointFirmware:
    """Enable and home against the end stop (positive by default)."""
    enabled(fw)
    start_blocking(fw, Reg.HOME, payload)
    run_until_idle(fw)
    return fw


#: SETRPM of the stall helper: -100 RPM = 600 deg/s, so a blocked rotor shows a
#: PID error of 600 deg/s x 1 ms x 51,200/360 = 85 microsteps a pass (the
#: library's closed loop rewrites the counter each 1 ms pass): above the
#: threshold of sensitivity 6 (60) and within the firmware's spike limit
#: (a jump of 100 is dropped), below the 12 rad/s band (+90).
STALL_RPM = -100.0


def stalled(fw: JointFirmware) -> JointFirmware:
    """Home, arm stall detection (sensitivity 6), run at -100 RPM, block the rotor until STALL."""
    host_limits(homed(fw))
    command(fw, Reg.ENABLESTALLGUARD, 6)
    command(fw, Reg.SETRPM, STALL_RPM)
    for _ in range(40):
        ticks(fw)
        ping_flags(fw)
    fw.motor.blocked = True
    for _ in range(60):
        if ping_flags(fw) & Flag.STALL:
            fw.motor.blocked = False
            return fw
        ticks(fw)
    raise AssertionError("never stalled")


@pytest.fixture
def fake_motor() -> FakeMotor:
    return FakeMotor()


@pytest.fixture
def guarded_core(fake_motor: FakeMotor) -> FirmwareCore:
    """A core, enabled, with stall detection at sensitivity 6 (threshold 60 microsteps at rest)."""
    core = FirmwareCore(fake_motor, 0.0)
    core.write(Reg.SETUP, SETUP_20_20, 0.0)
    core.write(Reg.ENABLESTALLGUARD, 6, 0.0)
    return core


def feed(core: FirmwareCore, motor: FakeMotor, errors: list[float]) -> list[bool]:
    """Run one tick per PID error in ``errors``; return whether STALL was set after each."""
    out = []
    for e in errors:
        motor.set_error(e)
        core.tick()
        out.append(bool(core.flags & Flag.STALL))
    return out


# ------------------------------------------------------------ power-up, PING


def test_power_up_flags_are_not_homed_and_not_enabled(firmware: JointFirmware) -> None:
    assert firmware.flags == POWER_UP


def test_ping_replies_ack_then_flags(firmware: JointFirmware) -> None:
    assert firmware.transfer(bytes((Reg.PING,)), 2) == b"O" + bytes((POWER_UP,))


def test_every_command_reply_is_the_flags_byte(firmware: JointFirmware) -> None:
    assert command(firmware, Reg.SETBRAKEMODE, 1) == POWER_UP


# --------------------------------------------------------- blocking commands


def test_home_reply_already_has_busy_and_not_homed(firmware: JointFirmware) -> None:
    enabled(firmware)
    flags = command(firmware, Reg.HOME, HOME_POSITIVE)
    assert flags & Flag.BUSY
    assert flags & Flag.NOT_HOMED


def test_ping_straight_after_home_sees_busy_and_not_homed() -> None:
    fw = homed(firmware_between_stops())
    assert not fw.flags & Flag.NOT_HOMED
    command(fw, Reg.HOME, HOME_POSITIVE)
    flags = ping_flags(fw)
    assert flags & Flag.BUSY
    assert flags & Flag.NOT_HOMED


def test_check_orientation_sets_busy_at_once(firmware: JointFirmware) -> None:
    enabled(firmware)
    assert command(firmware, Reg.CHECKORIENTATION, 2.0) & Flag.BUSY


def test_check_orientation_returns_to_start(firmware: JointFirmware) -> None:
    enabled(firmware)
    start = firmware.motor.position_deg
    start_blocking(firmware, Reg.CHECKORIENTATION, 2.0)
    run_until_idle(firmware)
    assert firmware.motor.position_deg == pytest.approx(start, abs=1e-6)


@pytest.mark.parametrize("reg", [0x21, 0x7F, 0x01, 0xFF])
def test_unknown_register_sets_busy(firmware: JointFirmware, reg: int) -> None:
    (flags,) = firmware.transfer(bytes((reg, 1, 2, 3, 4)), 1)
    assert flags & Flag.BUSY


@pytest.mark.parametrize("reg", [0x21, 0x7F])
def test_unknown_register_without_payload_sets_busy(firmware: JointFirmware, reg: int) -> None:
    (flags,) = firmware.transfer(bytes((reg,)), 1)
    assert flags & Flag.BUSY


@pytest.mark.parametrize("reg", [0x21, 0x7F, 0x01, 0xFF])
def test_unknown_register_busy_clears_after_one_tick(firmware: JointFirmware, reg: int) -> None:
    firmware.transfer(bytes((reg, 1, 2, 3, 4)), 1)
    ticks(firmware)
    assert ping_flags(firmware) == POWER_UP


@pytest.mark.parametrize("reg", [Reg.GETPIDERROR, Reg.MOVETOEND, Reg.CLEARSTALL])
def test_known_unused_register_written_goes_to_blocking_handler(firmware: JointFirmware, reg: Reg) -> None:
    (flags,) = firmware.transfer(bytes((reg, 0, 0, 0, 0)), 1)
    assert flags & Flag.BUSY
    ticks(firmware)
    assert not ping_flags(firmware) & Flag.BUSY


@pytest.mark.parametrize("reg", [0x1F, 0x20, 0x2A])
def test_known_unused_register_without_payload_goes_to_blocking_handler(
    firmware: JointFirmware, reg: int
) -> None:
    (flags,) = firmware.transfer(bytes([reg]), 1)
    assert flags == POWER_UP | Flag.BUSY


@pytest.mark.parametrize("data", [bytes([0x12]), bytes([0x12, 0, 0, 0, 0])], ids=["bare", "payload"])
def test_getdriverrpm_is_a_no_op_replying_the_flags(firmware: JointFirmware, data: bytes) -> None:
    assert firmware.transfer(data, 1) == bytes([POWER_UP])


# ------------------------------------------------------- lengths and padding


def test_short_setup_reads_the_hold_current_from_a_stale_buffer_byte(firmware: JointFirmware) -> None:
    firmware.transfer(bytes([0x2E, 0x0A, 0x0B, 0x0C, 0x0D]), 1)  # HOMEOFFSET fills the buffer
    firmware.transfer(bytes([0x10, 20]), 1)  # SETUP with byte0 only: byte1 is still 0x0B
    assert (firmware.core.drive_current, firmware.core.hold_current) == (20, 0x0B)


def test_short_float_payload_keeps_the_old_value_s_upper_bytes(firmware: JointFirmware) -> None:
    firmware.transfer(bytes([0x2E, 0x00, 0x00, 0xC0, 0x3F]), 1)  # HOMEOFFSET 1.5
    firmware.transfer(bytes([0x2E, 0x01, 0x02, 0x03]), 1)  # three bytes: memcpy of 3
    assert firmware.transfer(bytes([0x2E]), 5) == bytes([0x01, 0x02, 0x03, 0x3F, POWER_UP])


def test_long_payload_extra_bytes_are_dropped(firmware: JointFirmware) -> None:
    firmware.transfer(bytes((Reg.HOMEOFFSET,)) + struct.pack("<f", 1.5) + b"\x12\x34\x56", 1)
    assert query(firmware, Reg.HOMEOFFSET)[0] == 1.5


def test_long_payload_of_one_byte_register_uses_first_byte(firmware: JointFirmware) -> None:
    enabled(firmware)
    firmware.transfer(bytes((Reg.ENABLESTALLGUARD, 6, 0xFF, 0xFF, 0xFF, 0xFF)), 1)
    assert firmware.core.stall_sensitivity == 6


def test_bare_read_at_power_up_runs_register_0_as_a_blocking_command(firmware: JointFirmware) -> None:
    # ``uint8_t reg = 0``: no write phase, so requestEvent runs register 0x00, an unknown one.
    assert firmware.transfer(b"", 1) == bytes([POWER_UP | Flag.BUSY])


def test_bare_read_runs_the_last_command_again(firmware: JointFirmware) -> None:
    host_limits(enabled(firmware))
    firmware.transfer(bytes([0x13, 0x0A, 0x00, 0x00, 0x00]), 1)  # MOVESTEPS 10
    ticks(firmware, 100)
    firmware.transfer(b"", 1)  # no write phase: MOVESTEPS 10 once more
    ticks(firmware, 100)
    assert firmware.motor.position_deg == pytest.approx(20 * 360 / 51200, abs=1e-6)  # 20 microsteps


def test_bare_read_of_a_command_answers_the_previous_reply_before_the_flags(firmware: JointFirmware) -> None:
    # requestEvent appends the flags at tx_length, which only receiveEvent (a write
    # phase) and set_flags_for_blocking_handler set to 0 (joint.ino): a command's
    # handler writes no value, so each bare read answers the last reply plus the flags.
    assert firmware.transfer(bytes([Reg.SETUP, 20, 20, 0, 0]), 1) == bytes([Flag.NOT_HOMED])
    assert firmware.transfer(b"", 3) == bytes([Flag.NOT_HOMED, Flag.NOT_HOMED, 0xFF])
    assert firmware.transfer(b"", 3) == bytes([Flag.NOT_HOMED] * 3)


def test_bare_read_of_an_answering_register_starts_the_reply_over(firmware: JointFirmware) -> None:
    # writeValue sets tx_length to the value's size (joint.h).
    assert firmware.transfer(bytes([Reg.PING]), 3) == b"O" + bytes([POWER_UP]) + b"\xff"
    assert firmware.transfer(b"", 3) == b"O" + bytes([POWER_UP]) + b"\xff"


def test_write_phase_starts_the_reply_over(firmware: JointFirmware) -> None:
    # receiveEvent: ``tx_length = 0`` (joint.ino), so a command after a PING answers only the flags.
    firmware.transfer(bytes([Reg.PING]), 2)
    assert firmware.transfer(bytes([Reg.SETUP, 20, 20, 0, 0]), 2) == bytes([Flag.NOT_HOMED, 0xFF])


def test_bare_read_of_a_blocking_register_answers_only_the_flags(firmware: JointFirmware) -> None:
    # set_flags_for_blocking_handler: ``tx_length = 0`` (joint.ino).
    firmware.transfer(bytes([0x30]), 1)  # an unknown register: blocking
    assert firmware.transfer(b"", 2) == bytes([POWER_UP | Flag.BUSY, 0xFF])


def test_write_without_read_phase_is_not_executed(firmware: JointFirmware) -> None:
    enabled(firmware)
    firmware.transfer(bytes([0x13, 0x0A, 0x00, 0x00, 0x00]), 0)  # MOVESTEPS 10, no read
    ticks(firmware, 100)
    assert query(firmware, Reg.ANGLEMOVED)[0] == 0.0


def test_empty_write_with_zero_read_returns_nothing(firmware: JointFirmware) -> None:
    assert firmware.transfer(b"", 0) == b""


def test_read_longer_than_reply_is_padded_with_ff(firmware: JointFirmware) -> None:
    assert firmware.transfer(bytes((Reg.PING,)), 5) == b"O" + bytes((POWER_UP,)) + b"\xff\xff\xff"


def test_command_read_longer_than_flags_is_padded_with_ff(firmware: JointFirmware) -> None:
    assert firmware.transfer(bytes((Reg.STOP, 0)), 3) == bytes((POWER_UP,)) + b"\xff\xff"


def test_read_shorter_than_reply_is_cut(firmware: JointFirmware) -> None:
    firmware.transfer(bytes((Reg.HOMEOFFSET,)) + struct.pack("<f", -2.25), 1)
    assert firmware.transfer(bytes((Reg.HOMEOFFSET,)), 2) == struct.pack("<f", -2.25)[:2]


def test_zero_length_read_returns_nothing(firmware: JointFirmware) -> None:
    assert firmware.transfer(bytes((Reg.PING,)), 0) == b""


def test_non_finite_float_payload_is_stored_as_sent(firmware: JointFirmware) -> None:
    firmware.transfer(bytes([0x2E, 0x00, 0x00, 0xC0, 0x7F]), 1)  # HOMEOFFSET NaN
    assert firmware.transfer(bytes([0x2E]), 5) == bytes([0x00, 0x00, 0xC0, 0x7F, POWER_UP])


# ------------------------------------------------------------------ motion


def test_setrpm_runs_while_not_homed(firmware: JointFirmware) -> None:
    enabled(firmware)
    command(firmware, Reg.SETRPM, 10.0)
    for _ in range(20):
        ticks(firmware)
        ping_flags(firmware)
    assert firmware.motor.position_deg > 0.0


def test_setrpm_runs_after_disableclosedloop() -> None:
    fw = homed(firmware_between_stops())
    command(fw, Reg.DISABLECLOSEDLOOP, 0)
    command(fw, Reg.SETRPM, -10.0)
    ticks(fw, 20)
    assert query(fw, Reg.ANGLEMOVED)[0] < 0.0


def test_setrpm_ignored_while_stalled() -> None:
    fw = stalled(firmware_between_stops())
    before = fw.motor.position_deg
    flags = command(fw, Reg.SETRPM, -10.0)
    ticks(fw, 20)
    assert flags & Flag.STALL
    assert fw.motor.position_deg == before


def test_setrpm_runs_at_the_commanded_speed_when_homed() -> None:
    # VMAX = int(60 deg/s x 238.507) = 14310, 59.998 deg/s (the library's conversion);
    # the encoder's estimate has settled after 1 s at that speed.
    fw = host_limits(homed(firmware_between_stops()))
    command(fw, Reg.SETRPM, -10.0)
    for _ in range(100):
        ticks(fw)
        ping_flags(fw)
    assert query(fw, Reg.GETENCODERRPM)[0] == pytest.approx(-59.998 / 6.0, abs=1e-4)


def test_movetoangle_is_absolute_from_the_encoder_zero() -> None:
    fw = host_limits(homed(firmware_between_stops()))
    command(fw, Reg.MOVETOANGLE, -90.0)
    for _ in range(200):
        ticks(fw)
    assert query(fw, Reg.ANGLEMOVED)[0] == pytest.approx(-90.0, abs=1e-3)


def test_movesteps_allowed_while_not_homed(firmware: JointFirmware) -> None:
    host_limits(enabled(firmware))
    command(firmware, Reg.MOVESTEPS, -12800)  # microsteps: a quarter turn
    ticks(firmware, 100)
    assert query(firmware, Reg.ANGLEMOVED)[0] == pytest.approx(-90.0, abs=1e-3)


def test_movesteps_does_not_turn_an_unpowered_motor(firmware: JointFirmware) -> None:
    command(firmware, Reg.MOVESTEPS, -50)
    ticks(firmware, 100)
    assert firmware.motor.position_deg == 0.0


def test_stop_halts_velocity_mode() -> None:
    # STOP is setRPM(0): the chip ramps the 5.4 deg/s of three passes down within one.
    fw = homed(firmware_between_stops())
    command(fw, Reg.SETRPM, -10.0)
    ticks(fw, 3)
    command(fw, Reg.STOP, 0)
    ticks(fw, 3)
    before = fw.motor.position_deg
    ticks(fw, 10)
    assert fw.motor.position_deg == before


# ------------------------------------------------------- power-up limits
# docs/firmware.md, "Power-up": configuration.h's MAXVEL 10 steps/s = 18 deg/s and
# MAXACCEL 100 steps/s^2 = 180 deg/s^2, until the host sends SETMAXVELOCITY /
# SETMAXACCELERATION. Nothing below writes either. At 180 deg/s^2 each 10 ms
# main-loop pass adds 1.8 deg/s; 18 deg/s is reached after 10 passes, having
# moved 0.018 x (1 + 2 + ... + 10) = 0.99 deg, then it moves 0.18 deg a pass.


def run_passes(fw: JointFirmware, n: int) -> None:
    """``n`` main-loop passes with a PING after each (the deadman stays fed)."""
    for _ in range(n):
        ticks(fw)
        ping_flags(fw)


def test_setrpm_at_power_up_ramps_at_180_deg_per_s2(firmware: JointFirmware) -> None:
    # AMAX at power-up: (uint16)(100 steps x 256 x 0.022) = 563, 179.94 deg/s^2
    # (SETUP's moveSteps(0) cuts it to 16 bits; 563 fits). After 5 passes:
    # 5 x 1.7994 = 8.997 deg/s, 0.017994 x (1 + ... + 5) = 0.26991 deg.
    enabled(firmware)
    command(firmware, Reg.SETRPM, 10.0)
    run_passes(firmware, 5)
    assert firmware.motor.rotor_velocity_dps == pytest.approx(8.997, abs=1e-3)
    assert query(firmware, Reg.ANGLEMOVED)[0] == pytest.approx(0.26991, abs=1e-4)


def test_setrpm_at_power_up_is_not_held_to_the_power_up_max_velocity(firmware: JointFirmware) -> None:
    # setRPM writes the chip's VMAX itself (uStepper S32 library), so SETRPM 10
    # runs at 60 deg/s (VMAX int(60 x 238.507) = 14310: 59.998 deg/s) although
    # the power-up max velocity is 18 deg/s. At 1.7994 deg/s a pass it gets
    # there in pass 34: 0.017994 x (1 + ... + 33) + 17 x 0.59998 = 20.294 deg after 50.
    enabled(firmware)
    command(firmware, Reg.SETRPM, 10.0)
    run_passes(firmware, 50)
    assert firmware.motor.rotor_velocity_dps == pytest.approx(59.998, abs=1e-3)
    assert query(firmware, Reg.ANGLEMOVED)[0] == pytest.approx(20.294, abs=1e-3)


def test_movetoangle_at_power_up_runs_at_no_more_than_18_deg_per_s() -> None:
    # Homed at the upper stop; MOVETOANGLE -90. moveSteps sets VMAX from the
    # power-up max velocity: (uint32)(10 steps x 256 x 1.677) = 4293, 17.999
    # deg/s; AMAX 563, 179.94 deg/s^2, reached in 10 passes having moved
    # 0.017994 x (1 + ... + 10) = 0.98967 deg (the 10th pass is capped at
    # 17.999). After 100 passes: 0.98965 + 90 x 0.17999 = 17.188 deg.
    fw = homed(firmware_between_stops())
    command(fw, Reg.MOVETOANGLE, -90.0)
    run_passes(fw, 100)
    assert query(fw, Reg.ANGLEMOVED)[0] == pytest.approx(-17.188, abs=2e-3)
    assert fw.motor.rotor_velocity_dps == pytest.approx(-17.999, abs=1e-3)
    run_passes(fw, 500)
    assert query(fw, Reg.ANGLEMOVED)[0] == pytest.approx(-90.0, abs=1e-3)


def test_movesteps_at_power_up_runs_at_no_more_than_18_deg_per_s(firmware: JointFirmware) -> None:
    # MOVESTEPS 25600 microsteps = 180 deg, at VMAX 17.999 deg/s as above: 17.188 deg after 100 passes.
    enabled(firmware)
    command(firmware, Reg.MOVESTEPS, 25600)
    run_passes(firmware, 100)
    assert query(firmware, Reg.ANGLEMOVED)[0] == pytest.approx(17.188, abs=2e-3)


def test_power_up_max_velocity_is_stored_as_10_steps_per_s(firmware: JointFirmware) -> None:
    # The limits cannot be read (no read case in joint.ino). But ``static float
    # maxVel = MAXVEL`` holds 10 (steps/s) and SETMAXVELOCITY memcpy's its payload
    # over it, then multiplies by 200/360: with no payload the stored 10 is taken
    # as deg/s (docs/firmware.md, payload memcpy). A move then runs at VMAX
    # (uint32)(10 deg/s x 200/360 x 256 x 1.677) = 2385: 9.9997 deg/s.
    enabled(firmware)
    firmware.transfer(bytes([0x1D]), 1)  # SETMAXVELOCITY, no payload
    command(firmware, Reg.MOVESTEPS, 100 * 256)  # 100 full steps (MOVESTEPS counts 1/256 steps)
    run_passes(firmware, 50)
    assert firmware.motor.rotor_velocity_dps == pytest.approx(9.9997, abs=1e-3)


def test_power_up_max_acceleration_is_stored_as_100_steps_per_s2(firmware: JointFirmware) -> None:
    # ``static float maxAccel = MAXACCEL`` holds 100 (steps/s^2); a SETMAXACCELERATION
    # with no payload takes it as deg/s^2: AMAX (uint32)(100 x 200/360 x 256 x
    # 0.022) = 312, 99.716 deg/s^2, 0.99716 deg/s a pass. After 5 passes of
    # SETRPM 10: 4.9858 deg/s, 0.0099716 x (1 + ... + 5) = 0.14957 deg.
    enabled(firmware)
    firmware.transfer(bytes([0x1B]), 1)  # SETMAXACCELERATION, no payload
    command(firmware, Reg.SETRPM, 10.0)
    run_passes(firmware, 5)
    assert firmware.motor.rotor_velocity_dps == pytest.approx(4.9858, abs=1e-3)
    assert query(firmware, Reg.ANGLEMOVED)[0] == pytest.approx(0.14957, abs=1e-4)


def test_power_cycle_restores_the_power_up_limits(firmware: JointFirmware) -> None:
    # The host's limits are lost with the power: a move at 17.999 deg/s and
    # 179.94 deg/s^2 again, 17.188 deg after 100 passes of MOVESTEPS 25600 (as above).
    host_limits(enabled(firmware))
    firmware.power_cycle()
    enabled(firmware)
    command(firmware, Reg.MOVESTEPS, 25_600)
    run_passes(firmware, 100)
    assert query(firmware, Reg.ANGLEMOVED)[0] == pytest.approx(17.188, abs=2e-3)


# ------------------------------------------------------------------ homing


def test_homing_waits_half_a_second_before_moving() -> None:
    fw = enabled(firmware_between_stops())
    command(fw, Reg.HOME, HOME_POSITIVE)
    ticks(fw, 45)
    assert fw.motor.position_deg == 0.0


def test_homing_runs_at_the_homing_speed() -> None:
    # 10 RPM through setRPM: VMAX int(60 x 238.507) = 14310, 59.998 deg/s.
    fw = enabled(firmware_between_stops())
    command(fw, Reg.HOME, HOME_POSITIVE)
    ticks(fw, 100)
    assert fw.motor.rotor_velocity_dps == pytest.approx(59.998, abs=1e-3)


@pytest.mark.parametrize(
    ("payload", "stop"), [(HOME_POSITIVE, 360.0), (HOME_NEGATIVE, -240.0)], ids=["positive", "negative"]
)
def test_homing_direction_byte_picks_the_end_stop(payload: int, stop: float) -> None:
    # Homing trips in the millisecond of the first pole slip, the rotor thrown
    # back off the stop by less than a pole pitch (four full steps, 7.2 deg).
    fw = homed(firmware_between_stops(lower=-240.0, upper=360.0), payload)
    assert 0.0 < abs(fw.motor.position_deg - stop) < POLE_PITCH_DEG


def test_homing_zeroes_the_encoder_at_the_end_stop() -> None:
    fw = homed(firmware_between_stops())
    assert query(fw, Reg.ANGLEMOVED)[0] == 0.0


def test_homing_clears_not_homed_busy_and_stall() -> None:
    fw = stalled(firmware_between_stops())
    start_blocking(fw, Reg.HOME, HOME_POSITIVE)
    run_until_idle(fw)
    assert ping_flags(fw) == 0


def test_stop_during_homing_clears_busy_and_leaves_not_homed() -> None:
    fw = enabled(firmware_between_stops())
    command(fw, Reg.HOME, HOME_POSITIVE)
    ticks(fw, 70)  # past the 0.5 s settle: running toward the end stop
    flags = command(fw, Reg.STOP, 0)
    assert not flags & Flag.BUSY
    assert flags & Flag.NOT_HOMED


def test_stop_during_homing_settle_clears_busy_and_leaves_not_homed() -> None:
    fw = enabled(firmware_between_stops())
    command(fw, Reg.HOME, HOME_POSITIVE)
    ticks(fw, 10)
    command(fw, Reg.STOP, 0)
    ticks(fw, 100)
    assert ping_flags(fw) == Flag.NOT_HOMED
    assert fw.motor.position_deg == 0.0


def test_stop_during_homing_of_a_homed_joint_leaves_not_homed() -> None:
    fw = homed(firmware_between_stops())
    command(fw, Reg.HOME, HOME_NEGATIVE)
    ticks(fw, 70)
    command(fw, Reg.STOP, 0)
    assert ping_flags(fw) & Flag.NOT_HOMED


# -------------------------------------------------------------- HOMEOFFSET


def test_homeoffset_round_trip(firmware: JointFirmware) -> None:
    command(firmware, Reg.HOMEOFFSET, 3.04647)
    assert query(firmware, Reg.HOMEOFFSET)[0] == pytest.approx(3.04647, rel=1e-7)


def test_homeoffset_is_zero_at_power_up(firmware: JointFirmware) -> None:
    assert query(firmware, Reg.HOMEOFFSET)[0] == 0.0


def test_homeoffset_kept_across_time_and_commands(firmware: JointFirmware) -> None:
    command(firmware, Reg.HOMEOFFSET, -0.0016)
    enabled(firmware)
    command(firmware, Reg.STOP, 0)
    ticks(firmware, 1000)
    assert query(firmware, Reg.HOMEOFFSET)[0] == pytest.approx(-0.0016, rel=1e-7)


def test_homeoffset_lost_on_power_cycle(firmware: JointFirmware) -> None:
    command(firmware, Reg.HOMEOFFSET, 3.04647)
    firmware.power_cycle()
    assert query(firmware, Reg.HOMEOFFSET)[0] == 0.0


def test_power_cycle_restores_power_up_flags() -> None:
    fw = homed(firmware_between_stops())
    fw.power_cycle()
    assert fw.flags == POWER_UP


def test_power_cycle_keeps_the_rotor_and_zeroes_the_encoder_there() -> None:
    fw = homed(firmware_between_stops())
    rotor = fw.motor.position_deg
    fw.power_cycle()
    assert fw.motor.position_deg == rotor
    assert query(fw, Reg.ANGLEMOVED)[0] == 0.0


# --------------------------------------------------------- SETUP and stall


def test_enablestallguard_clears_stall() -> None:
    fw = stalled(firmware_between_stops())
    assert not command(fw, Reg.ENABLESTALLGUARD, 6) & Flag.STALL


def test_setup_clears_stall_and_not_enabled() -> None:
    fw = stalled(firmware_between_stops())
    command(fw, Reg.DISABLECLOSEDLOOP, 0)
    assert command(fw, Reg.SETUP, SETUP_20_20) & (Flag.STALL | Flag.NOT_ENABLED) == 0


def test_setup_disables_stall_detection() -> None:
    fw = stalled(firmware_between_stops())
    command(fw, Reg.SETUP, SETUP_20_20)
    command(fw, Reg.SETRPM, STALL_RPM)
    fw.motor.blocked = True
    for _ in range(50):
        ticks(fw)
        ping_flags(fw)
    assert not fw.flags & Flag.STALL


def test_stall_stops_the_motor() -> None:
    fw = stalled(firmware_between_stops())
    before = fw.motor.position_deg
    ticks(fw, 20)
    assert fw.motor.position_deg == before
    assert fw.motor.rotor_velocity_dps == 0.0


@pytest.mark.parametrize("reg", [Reg.SETCURRENT, Reg.SETHOLDCURRENT])
def test_zero_current_sets_not_enabled(reg: Reg) -> None:
    fw = enabled(firmware_between_stops())
    assert command(fw, reg, 0) & Flag.NOT_ENABLED


def test_disableclosedloop_sets_not_enabled() -> None:
    fw = enabled(firmware_between_stops())
    assert command(fw, Reg.DISABLECLOSEDLOOP, 0) & Flag.NOT_ENABLED


# ----------------------------------------------------------------- deadman


def velocity_mode(fw: JointFirmware, rpm: float = -10.0) -> JointFirmware:
    homed(fw)
    command(fw, Reg.SETRPM, rpm)
    return fw


def test_deadman_sets_not_enabled_after_silence_in_velocity_mode() -> None:
    fw = velocity_mode(firmware_between_stops())
    ticks(fw, 6)
    assert fw.flags & Flag.NOT_ENABLED


def test_deadman_tolerates_40ms_of_silence() -> None:
    fw = velocity_mode(firmware_between_stops())
    ticks(fw, 4)
    assert not fw.flags & Flag.NOT_ENABLED


def test_deadman_is_fed_by_any_transaction() -> None:
    fw = velocity_mode(firmware_between_stops())
    for _ in range(20):
        ticks(fw, 4)
        fw.transfer(b"", 1)
    assert not fw.flags & Flag.NOT_ENABLED


def test_deadman_stops_the_motor() -> None:
    fw = velocity_mode(firmware_between_stops())
    ticks(fw, 100)
    assert fw.motor.rotor_velocity_dps == 0.0


def test_deadman_ignores_zero_velocity_set_point() -> None:
    fw = velocity_mode(firmware_between_stops(), rpm=0.0)
    ticks(fw, 100)
    assert not fw.flags & Flag.NOT_ENABLED


def test_deadman_ignores_a_position_move_after_setup() -> None:
    fw = homed(firmware_between_stops())
    command(fw, Reg.MOVETOANGLE, -600.0)
    ticks(fw, 100)
    assert not fw.flags & Flag.NOT_ENABLED
    assert fw.motor.velocity_dps != 0.0


def test_deadman_ignores_idle_joint() -> None:
    fw = homed(firmware_between_stops())
    ticks(fw, 100)
    assert not fw.flags & Flag.NOT_ENABLED


def test_deadman_does_not_interrupt_homing() -> None:
    fw = enabled(firmware_between_stops())
    command(fw, Reg.HOME, HOME_POSITIVE)
    ticks(fw, 800)  # 0.5 s settle + 360 deg at 60 deg/s, all in silence
    assert fw.flags == 0


# ------------------------------------------------- stall detection: the rules


@pytest.mark.parametrize(
    ("omega", "sensitivity", "expected"),
    [
        (0.0, 6, 60.0),
        (11.99, 6, 60.0),
        (12.0, 6, 150.0),
        (100.0, 6, 150.0),
        (450.0, 6, 150.0),
        (450.01, 6, 60.0),
        (-12.0, 6, 150.0),
        (-450.0, 6, 150.0),
        (-451.0, 6, 60.0),
        (0.0, 0, 0.0),
        (200.0, 255, 2640.0),
    ],
)
def test_stall_threshold_is_10x_sensitivity_plus_90_in_mid_band(
    omega: float, sensitivity: int, expected: float
) -> None:
    assert stall_threshold(omega, sensitivity) == expected


def test_live_stall_detector_uses_stall_threshold(
    guarded_core: FirmwareCore, fake_motor: FakeMotor, monkeypatch: pytest.MonkeyPatch
) -> None:
    """The rule tested above is the one the main loop applies, with the motor's speed in rad/s."""
    seen: list[tuple[float, int]] = []
    rule_threshold = firmware_module.StallRule.threshold

    def spy(rule: firmware_module.StallRule, omega_rad_s: float, sensitivity: int) -> float:
        seen.append((omega_rad_s, sensitivity))
        return rule_threshold(rule, omega_rad_s, sensitivity)

    monkeypatch.setattr(firmware_module.StallRule, "threshold", spy)
    fake_motor.velocity_dps = math.degrees(20.0)
    feed(guarded_core, fake_motor, [0.0])
    assert seen == [(pytest.approx(20.0), 6)]


def test_sustained_error_trips_when_the_low_pass_crosses_the_threshold(
    guarded_core: FirmwareCore, fake_motor: FakeMotor
) -> None:
    # x_n = 100 (1 - 0.9^n) with Ts/tau = 0.1 crosses 60 at n = 9 (0.9^8 = 0.43, 0.9^9 = 0.387).
    tripped = feed(guarded_core, fake_motor, [100.0] * 10)
    assert tripped.index(True) == 8


def test_error_at_the_threshold_never_trips(guarded_core: FirmwareCore, fake_motor: FakeMotor) -> None:
    assert not any(feed(guarded_core, fake_motor, [60.0] * 300))


def test_mid_band_speed_raises_the_threshold(guarded_core: FirmwareCore, fake_motor: FakeMotor) -> None:
    fake_motor.velocity_dps = math.degrees(20.0)  # 20 rad/s: threshold 150
    assert not any(feed(guarded_core, fake_motor, [100.0] * 100))


def test_single_jump_above_100_is_ignored_for_that_tick(
    guarded_core: FirmwareCore, fake_motor: FakeMotor
) -> None:
    # Fed to the low pass, 1000 would make x = 100 > 60 at once.
    assert feed(guarded_core, fake_motor, [0.0, 0.0, 1000.0]) == [False, False, False]


@pytest.mark.parametrize(("jump", "taken"), [(100.0, True), (100.5, False)])
def test_spike_filter_limit_is_a_jump_of_more_than_100(
    guarded_core: FirmwareCore, fake_motor: FakeMotor, jump: float, taken: bool
) -> None:
    # Threshold 0 (sensitivity 0): any sample the low pass takes trips at once.
    guarded_core.write(Reg.ENABLESTALLGUARD, 0, 0.0)
    assert feed(guarded_core, fake_motor, [jump]) == [taken]


def test_sustained_jump_above_100_is_never_let_through(
    guarded_core: FirmwareCore, fake_motor: FakeMotor
) -> None:
    # One-sided filter remembering the filtered value: 0 -> 1000 held stays u = 0 for ever.
    assert not any(feed(guarded_core, fake_motor, [1000.0] * 300))


def test_stall_trip_resets_the_filter_and_holds_the_motor(
    guarded_core: FirmwareCore, fake_motor: FakeMotor
) -> None:
    feed(guarded_core, fake_motor, [100.0] * 9)
    assert guarded_core.flags & Flag.STALL
    assert guarded_core._filter_x == 0.0  # internal state: not observable over the bus
    assert guarded_core._filter_last == 0.0
    assert guarded_core.pid_error == 0.0


def test_stall_detection_off_until_enabled(fake_motor: FakeMotor) -> None:
    core = FirmwareCore(fake_motor, 0.0)
    core.write(Reg.SETUP, SETUP_20_20, 0.0)
    assert not any(feed(core, fake_motor, [5000.0] * 50))


def test_stall_detection_paused_while_a_blocking_command_runs(
    guarded_core: FirmwareCore, fake_motor: FakeMotor
) -> None:
    guarded_core.write(Reg.CHECKORIENTATION, 2.0, 0.0)
    fake_motor.set_error(100.0)
    for _ in range(20):
        guarded_core.tick()
        fake_motor.set_error(100.0)
    assert not guarded_core.flags & Flag.STALL


# ------------------------------------ what the arm's original driver found
def test_signed_limits_of_the_original_driver_run_by_their_magnitude(firmware: JointFirmware) -> None:
    # The arm's C++ driver sends j2's limits signed (its reduction is negative):
    # SETMAXVELOCITY 1d 00 c0 28 c5 is -2700 deg/s. The library takes the magnitude
    # (uStepper S32 setMaxVelocity: abs()), so a move runs at VMAX (uint32)(2700 x
    # 238.507) = 643969: 2700.0 deg/s (ramping at SETMAXACCELERATION -18000: 17,999
    # deg/s^2, reached within two passes).
    enabled(firmware)
    firmware.transfer(bytes.fromhex("1d00c028c5"), 1)
    firmware.transfer(bytes([0x1B]) + struct.pack("<f", -18000.0), 1)
    command(firmware, Reg.MOVESTEPS, 100_000)
    run_passes(firmware, 20)
    assert firmware.motor.rotor_velocity_dps == pytest.approx(2700.0, abs=0.01)


def test_the_kinematic_stepper_runs_as_fast_as_the_configuration_asks_of_j3() -> None:
    # The packaged configuration's j3 and j4 run at 6875 deg/s at the motor (5 rad/s x 24,
    # 10 rad/s x 12); the real j4 reached 14.3 rad/s (maxAccel/j4_5: 9830 deg/s).
    motor = KinematicStepper(0.0)
    assert motor.max_speed_dps >= 9830.0
    fw = JointFirmware(motor, ManualClock())
    enabled(fw)
    command(fw, Reg.SETMAXACCELERATION, 20_000.0)
    command(fw, Reg.SETRPM, 6875.0 / 6.0)
    run_passes(fw, 100)
    assert motor.rotor_velocity_dps == pytest.approx(6875.0, rel=1e-3)
