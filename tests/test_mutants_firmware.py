"""Tests that kill mutants mutmut found surviving in the firmware emulator (docs/mutation.md).

Byte-level like ``test_firmware_rules.py``: literal payloads, literal flags
(docs/protocol.md's flags table), physical positions in motor degrees, a
manual clock. Each test is one behaviour a one-token change in
``firmware.py`` broke without any other test noticing.
"""

from __future__ import annotations

import itertools
import struct

import pytest
from rigs import FakeMotor

from bioscara_gym.hardware.clock import ManualClock
from bioscara_gym.hardware.firmware import FirmwareCore, JointFirmware
from bioscara_gym.hardware.motor import KinematicStepper

STALL, BUSY, NOT_HOMED, NOT_ENABLED = 0x01, 0x02, 0x04, 0x08

PING = bytes([0x0F])
SETUP_20_20 = bytes([0x10, 20, 20, 0, 0])
SETRPM_10 = bytes([0x11, 0x00, 0x00, 0x20, 0x41])  # 10.0 RPM
SETRPM_0 = bytes([0x11, 0x00, 0x00, 0x00, 0x00])  # 0.0 RPM
SETCURRENT_0 = bytes([0x19, 0])
TICK = 0.01


class RecordingMotor(KinematicStepper):
    """A kinematic stepper that records every (velocity deg/s, torque fraction) it is sent."""

    def __init__(self, position_deg: float = 0.0) -> None:
        super().__init__(position_deg)
        self.sent: list[tuple[float, float]] = []

    def command(self, velocity_dps: float, torque_fraction: float) -> None:
        self.sent.append((velocity_dps, torque_fraction))
        super().command(velocity_dps, torque_fraction)


def make(lower: float = -720.0, upper: float = 360.0) -> JointFirmware:
    """Firmware in front of a stepper at 0 deg between end stops (motor degrees)."""
    motor = KinematicStepper(0.0, lower_stop_deg=lower, upper_stop_deg=upper)
    return JointFirmware(motor, ManualClock())


def send(fw: JointFirmware, data: bytes) -> int:
    """One transaction: write ``data``, read the flags (PING also its 'O'); return the flags."""
    return fw.transfer(data, 2 if data[0] == 0x0F else 1)[-1]


def ticks(fw: JointFirmware, n: int = 1) -> None:
    fw.clock.sleep(n * TICK)
    fw.update()


def host_limits(fw: JointFirmware) -> None:
    """SETMAXVELOCITY 1000 deg/s, SETMAXACCELERATION 2000 deg/s^2: the host sets its own before moving.

    At the power-up limits (18 deg/s, 180 deg/s^2, docs/firmware.md) the
    moves below would take seconds.
    """
    send(fw, bytes([0x1D]) + struct.pack("<f", 1000.0))
    send(fw, bytes([0x1B]) + struct.pack("<f", 2000.0))


# ------------------------------------------------------- snapshot / restore
def test_restore_brings_back_the_flags_and_set_points_of_the_snapshot() -> None:
    core = FirmwareCore(KinematicStepper(0.0), 0.0)
    core.write(0x10, 0x1414, 0.0)  # SETUP drive 20 %, hold 20 %: flags NOTHOMED only
    core.write(0x11, 10.0, 0.0)  # SETRPM 10
    snap = core.snapshot()
    core.write(0x19, 0, 0.0)  # SETCURRENT 0: NOTENABLED
    core.write(0x11, 0.0, 0.0)
    core.restore(snap)
    assert core.flags == NOT_HOMED
    assert core.qd_set == 10.0
    assert core.drive_current == 20


def test_snapshot_leaves_the_motor_out() -> None:
    motor = KinematicStepper(0.0)
    core = FirmwareCore(motor, 0.0)
    assert "motor" not in core.snapshot()
    core.restore(core.snapshot())
    assert core.motor is motor


def test_restore_sends_the_motor_its_set_point_again() -> None:
    motor = RecordingMotor()
    core = FirmwareCore(motor, 0.0)
    core.write(0x10, 0x1414, 0.0)  # idle at hold current 20 %
    snap = core.snapshot()
    motor.sent.clear()
    core.restore(snap)
    assert motor.sent == [(0.0, 0.2)]


# ----------------------------------------------------------------- currents
# A current byte above 100 % drives the motor at its full current (our drive
# model's maximum torque, docs/model.md), not at 101 %.
def test_drive_current_above_100_percent_runs_at_full_current() -> None:
    motor = RecordingMotor()
    core = FirmwareCore(motor, 0.0)
    core.write(0x10, 0x1414, 0.0)  # SETUP 20 %, 20 %
    core.write(0x19, 101, 0.0)  # SETCURRENT 101 %
    core.write(0x11, 10.0, 0.0)  # SETRPM 10: the motor runs at the drive current
    core.tick()
    assert motor.sent[-1][1] == 1.0


def test_hold_current_above_100_percent_holds_at_full_current() -> None:
    motor = RecordingMotor()
    core = FirmwareCore(motor, 0.0)
    core.write(0x10, 0x1414, 0.0)  # SETUP 20 %, 20 %: idle, held at the hold current
    core.write(0x1A, 101, 0.0)  # SETHOLDCURRENT 101 %
    assert motor.sent[-1] == (0.0, 1.0)


# ------------------------------------------------------------- JointFirmware
def test_joint_firmware_cancels_a_pending_command_by_default() -> None:
    # docs/firmware.md: the cancellation is on by default.
    fw = JointFirmware(KinematicStepper(0.0, lower_stop_deg=-720.0, upper_stop_deg=360.0), ManualClock())
    send(fw, SETUP_20_20)
    send(fw, bytes([0x2D, 1, 10, 30, 15]))  # HOME +, 10 RPM, sensitivity 30, 15 %
    send(fw, PING)  # before the main loop took HOME: cancels it
    for _ in range(100):
        ticks(fw)
        send(fw, PING)
    assert fw.motor.position_deg == 0.0
    assert send(fw, PING) == BUSY | NOT_HOMED


def test_joint_firmware_needs_a_motor_or_a_core_not_both() -> None:
    motor = KinematicStepper(0.0)
    with pytest.raises(ValueError, match=r"^pass either a motor or an existing core$"):
        JointFirmware(motor, ManualClock(), core=FirmwareCore(motor))
    with pytest.raises(ValueError, match=r"^pass either a motor or an existing core$"):
        JointFirmware(None, ManualClock())


def test_joint_firmware_powers_up_at_the_clock_time() -> None:
    fw = JointFirmware(KinematicStepper(0.0), ManualClock(5.0))
    assert fw.core.time == 5.0
    assert fw.core.last_rx == 5.0


# ------------------------------------------------------------------- limits
# SETMAXVELOCITY / SETMAXACCELERATION in deg/s, deg/s^2 (docs/protocol.md). The
# firmware does not check them; the emulator ignores a value that is not
# finite and positive (our guard, firmware.py) and keeps the previous limit.
def move_for_1_s(limit_reg: int, limit: float) -> float:
    """SETUP, the limit, MOVESTEPS 256,000 (1000 steps, 1800 deg), 1 s of ticks fed each; degrees moved."""
    motor = KinematicStepper(0.0)
    core = FirmwareCore(motor, 0.0)
    core.write(0x10, 0x1414, 0.0)  # SETUP 20 %, 20 %
    core.write(limit_reg, limit, 0.0)
    core.write(0x13, 256_000, 0.0)  # MOVESTEPS counts 1/256 steps
    for _ in range(100):
        core.tick()
        core.touch(core.time)  # the deadman stays fed
    return motor.position_deg


# The library takes a limit's magnitude (uStepper S32 ``setMaxVelocity``,
# ``setMaxAcceleration``: ``abs()``), and moveSteps gives the chip
# VMAX = (uint32)(v x 200/360 x 256 x 1.677) and AMAX = (uint16)(a x 200/360 x 256 x 0.022).
# At the power-up acceleration, AMAX 563 (179.94 deg/s^2, 1.7994 deg/s a pass):
# -30 deg/s is VMAX 7155, 29.999 deg/s, reached in pass 17 having moved
# 0.017994 x (1 + ... + 16) + 0.29999 = 2.7466 deg; 83 passes more: 27.646 deg.
MINUS_30_DEG_PER_S_1_S_DEG = 27.646


def test_max_velocity_is_taken_by_its_magnitude() -> None:
    # The arm's C++ driver sends j2's limits signed (reduction < 0): -30 must run as 30.
    assert move_for_1_s(0x1D, -30.0) == pytest.approx(MINUS_30_DEG_PER_S_1_S_DEG, abs=0.01)


def test_max_velocity_of_zero_stops_moves() -> None:
    # VMAX 0: the chip's positioning ramp has no speed to move with.
    assert move_for_1_s(0x1D, 0.0) == 0.0


def test_max_velocity_below_1_deg_per_s_is_taken() -> None:
    # VMAX (uint32)(0.5 x 238.507) = 119: 0.49894 deg/s, reached in the first pass.
    assert move_for_1_s(0x1D, 0.5) == pytest.approx(0.49894, abs=0.002)


def test_max_acceleration_is_taken_by_its_magnitude() -> None:
    # AMAX (uint16)(30 x 3.12889) = 93: 29.723 deg/s^2, 0.29723 deg/s a pass; the
    # power-up VMAX 17.999 deg/s is reached in pass 61 (61 x 0.29723 = 18.13), so
    # 100 passes move 0.0029723 x (1 + ... + 60) + 40 x 0.17999 = 5.4393 + 7.1996 = 12.639 deg.
    assert move_for_1_s(0x1B, -30.0) == pytest.approx(12.639, abs=0.01)


def test_max_acceleration_of_zero_stops_moves() -> None:
    # AMAX 0: the ramp never starts.
    assert move_for_1_s(0x1B, 0.0) == 0.0


def test_max_acceleration_below_1_deg_per_s2_is_taken() -> None:
    # AMAX (uint16)(0.5 x 3.12889) = 1: 0.31960 deg/s^2 (the 16-bit register's
    # step): 0.0031960 x (1 + ... + 100) x 0.01 = 0.16140 deg.
    assert move_for_1_s(0x1B, 0.5) == pytest.approx(0.16140, abs=0.001)


def test_max_acceleration_above_the_16_bit_register_wraps_in_a_move() -> None:
    # settingMaxVal/accel_test_10000000_200000.csv: the real motor accelerated at
    # 9,021 deg/s^2 when asked 10,000,000: the library's float arithmetic gives
    # 31,288,892, cut to 16 bits 28220: 9019.2 deg/s^2, 90.19 deg/s after the first pass.
    motor = KinematicStepper(0.0)
    core = FirmwareCore(motor, 0.0)
    core.write(0x10, 0x1414, 0.0)
    core.write(0x1D, 200_000.0, 0.0)
    core.write(0x1B, 10_000_000.0, 0.0)
    core.write(0x15, 36_000.0, 0.0)  # MOVETOANGLE
    core.tick()
    assert motor.rotor_velocity_dps == pytest.approx(90.19, abs=0.01)


# ----------------------------------------------------------------- power-up
def test_power_up_brake_is_freewheel_and_currents_are_zero() -> None:
    # docs/firmware.md, power-up: currents 0 %, 0 %, brake freewheel (0).
    core = FirmwareCore(KinematicStepper(0.0), 0.0)
    assert (core.drive_current, core.hold_current, core.brake_mode) == (0, 0, 0)


def test_stall_detection_is_off_at_power_up() -> None:
    # docs/firmware.md, power-up: stall detection off (not only after SETUP).
    motor = FakeMotor()
    core = FirmwareCore(motor, 0.0)
    for n in range(1, 51):  # PID error rising by 50 a pass (under the spike limit) to 2500
        motor.setpoint_deg = motor.position_deg + 50 * n * 1.8 / 16
        core.tick()
    assert not core.flags & STALL


def test_stall_filter_starts_at_zero() -> None:
    # Sensitivity 0: threshold 0, so any filtered error above 0 trips. With a
    # PID error of 0 from power-up the low pass stays at 0: no STALL.
    core = FirmwareCore(FakeMotor(), 0.0)
    core.write(0x10, 0x1414, 0.0)  # SETUP
    core.write(0x1E, 0, 0.0)  # ENABLESTALLGUARD 0 (keeps the filter state)
    for _ in range(10):
        core.tick()
    assert not core.flags & STALL


@pytest.mark.parametrize("reg", [0x11, 0x15])  # SETRPM, MOVETOANGLE
def test_short_float_payload_at_power_up_keeps_zero_upper_bytes(reg: int) -> None:
    # memcpy of 2 bytes into a static that is 0.0 at power-up: 0x0000 + 0x0000 = 0.0.
    fw = make()
    send(fw, bytes([0x19, 20]))  # SETCURRENT 20: the motor is powered (still NOTENABLED)
    send(fw, bytes([reg, 0x00, 0x00]))
    for _ in range(100):
        ticks(fw)
        send(fw, PING)
    assert fw.motor.position_deg == 0.0


# ------------------------------------------------------------------ deadman
def test_deadman_counts_whole_milliseconds() -> None:
    # docs/firmware.md: more than 50 whole ms (millis()) since the last reply.
    # Last reply at 10.0 ms, passes at 10.3, 20.3, ... ms: at 60.3 ms millis()
    # says 60 - 10 = 50 (holds, though 50.3 ms have passed); at 70.3 ms, 60.
    core = FirmwareCore(KinematicStepper(0.0), 0.0003)
    core.write(0x10, 0x1414, 0.0003)  # SETUP
    core.write(0x11, 10.0, 0.0003)  # SETRPM 10
    core.touch(0.0100)  # GETDRIVERRPM at 10.0 ms
    for _ in range(6):  # passes at 10.3 ... 60.3 ms
        core.tick()
    assert not core.flags & NOT_ENABLED
    core.tick()  # 70.3 ms
    assert core.flags & NOT_ENABLED


def test_setbrakemode_stores_the_mode_byte() -> None:
    # docs/protocol.md: SETBRAKEMODE uint8, 0 freewheel, 1 coolbrake, 2 hardbrake.
    fw = make()
    send(fw, bytes([0x22, 2]))
    assert fw.core.brake_mode == 2


# ------------------------------------------------------------------- homing
#: HOME: direction +, 10 RPM, sensitivity 16, current 15 % (bytes 0-3).
HOME_SENSITIVITY_16 = 0x0F100A01


def homing_core() -> tuple[FirmwareCore, FakeMotor]:
    """A core whose homing loop polls (after the 500 ms wait) a PID error the test sets."""
    motor = FakeMotor()
    core = FirmwareCore(motor, 0.0)
    core.write(0x10, 0x1414, 0.0)  # SETUP
    core.write(0x2D, HOME_SENSITIVITY_16, 0.0)  # HOME
    for _ in range(52):  # the loop takes it, 500 ms wait, polling
        core.tick()
    assert core.flags & BUSY
    return core, motor


def test_homing_error_equal_to_the_sensitivity_does_not_end_it() -> None:
    # docs/firmware.md: stop waiting when |error| > sensitivity (strictly).
    core, motor = homing_core()
    motor.setpoint_deg = motor.position_deg + 16 * 360.0 / 51_200  # 16 microsteps
    for _ in range(5):
        core.tick()
    assert core.flags & (BUSY | NOT_HOMED) == BUSY | NOT_HOMED


def test_homing_error_above_the_sensitivity_ends_it_homed() -> None:
    core, motor = homing_core()
    motor.setpoint_deg = motor.position_deg + 3.6  # 32 microsteps
    core.tick()
    assert core.flags == 0


def test_homing_starts_moving_on_the_pass_500_ms_after_the_loop_took_it() -> None:
    # docs/firmware.md: hard stop, then delay(500), then run at +speed.
    fw = make()
    send(fw, SETUP_20_20)
    send(fw, bytes([0x2D, 1, 10, 30, 15]))  # HOME +, 10 RPM
    ticks(fw)  # the pass at 10 ms takes it
    ticks(fw, 49)  # up to 500 ms: still waiting
    assert fw.motor.position_deg == 0.0
    ticks(fw)  # the pass at 510 ms: 500 ms after the one that took it
    assert fw.motor.position_deg > 0.0


# -------------------------------------------------------- check orientation
def test_check_orientation_ends_idle_at_the_hold_current() -> None:
    # SETUP drive 30 %, hold 10 %; after CHECKORIENTATION the motor idles at the hold current.
    fw = make()
    send(fw, bytes([0x10, 30, 10, 0, 0]))
    send(fw, bytes([0x2B, 0x00, 0x00, 0x00, 0x40]))  # CHECKORIENTATION 2.0 deg
    ticks(fw)
    for _ in range(200):
        if not send(fw, PING) & BUSY:
            break
        ticks(fw)
    ticks(fw)
    assert fw.motor.position_deg == pytest.approx(0.0, abs=1e-9)
    assert fw.motor.torque_fraction == 0.1


def test_check_orientation_by_nan_degrees_runs_as_zero() -> None:
    # Emulator choice (firmware.py): a non-finite angle turns by 0 deg and ends.
    fw = make()
    send(fw, SETUP_20_20)
    send(fw, bytes([0x2B, 0x00, 0x00, 0xC0, 0x7F]))  # CHECKORIENTATION NaN
    seen = []
    for _ in range(5):
        ticks(fw)
        seen.append(fw.motor.position_deg)
    assert send(fw, PING) == NOT_HOMED
    assert seen == [0.0] * 5


def test_homing_towards_the_lower_stop_runs_at_minus_the_speed() -> None:
    # docs/firmware.md: dir ? +speed : -speed; HOME 10 RPM with direction 0 runs at -10 RPM.
    # The homing ramps at the acceleration the host set last (as the arm does).
    fw = make()
    send(fw, SETUP_20_20)
    send(fw, bytes([0x1B]) + struct.pack("<f", 2000.0))  # SETMAXACCELERATION 2000
    send(fw, bytes([0x2D, 0, 10, 30, 15]))
    ticks(fw, 160)  # the pass that takes it, the 500 ms wait, 1.09 s of running
    reply = fw.transfer(bytes([0x2C]), 5)  # GETENCODERRPM
    # VMAX int(60 x 238.507) = 14310: 59.998 deg/s; the encoder's estimate has settled.
    assert struct.unpack("<f", reply[:4])[0] == pytest.approx(-59.998 / 6.0, abs=1e-4)


@pytest.mark.parametrize("payload", [bytes([0x00, 0x00, 0xC0, 0x7F]), bytes([0x01, 0x00, 0xC0, 0xFF])])
def test_setrpm_nan_runs_as_zero(payload: bytes) -> None:
    # The Cortex-M4 converts a NaN to 0 (±inf: tests/test_firmware_rules.py).
    fw = make()
    send(fw, SETUP_20_20)
    send(fw, bytes([0x11]) + payload)
    for _ in range(20):
        ticks(fw)
        send(fw, PING)
    assert fw.motor.position_deg == 0.0


class ClockedMotor(KinematicStepper):
    """A kinematic stepper that adds up the time it is advanced by."""

    def __init__(self, position_deg: float, lower_stop_deg: float, upper_stop_deg: float) -> None:
        super().__init__(position_deg, lower_stop_deg=lower_stop_deg, upper_stop_deg=upper_stop_deg)
        self.advanced_s = 0.0

    def advance(self, dt: float) -> None:
        self.advanced_s += dt
        super().advance(dt)


@pytest.mark.parametrize("stop_deg", [3.0, 3.25, 3.5, 3.75])
def test_motor_time_runs_one_tick_a_pass_also_when_a_homing_ends_mid_pass(stop_deg: float) -> None:
    # The homing loop polls every 1 ms; when it ends inside a 10 ms pass the
    # motor still runs the rest of that pass: 10 ms of motor time per pass.
    motor = ClockedMotor(0.0, -720.0, stop_deg)
    core = FirmwareCore(motor, 0.0)
    core.write(0x10, 0x1414, 0.0)  # SETUP
    core.write(0x2D, 0x0F1E0A01, 0.0)  # HOME +, 10 RPM, sensitivity 30, 15 %
    for n in range(1, 101):
        core.tick()
        core.touch(core.time)
        assert motor.advanced_s == pytest.approx(n * 0.01, abs=1e-9)
    assert core.flags == 0  # homed within the second


def test_position_move_ends_idle_at_the_hold_current() -> None:
    # SETUP drive 30 %, hold 10 %; MOVESTEPS 2560 microsteps (10 full steps,
    # 18 deg) runs at the drive current and, arrived, idles at the hold current.
    fw = make()
    send(fw, bytes([0x10, 30, 10, 0, 0]))
    host_limits(fw)
    send(fw, bytes([0x13]) + struct.pack("<i", 2560))  # MOVESTEPS 2560 microsteps
    ticks(fw)
    assert fw.motor.torque_fraction == 0.3
    for _ in range(100):
        ticks(fw)
        send(fw, PING)
    assert fw.motor.position_deg == pytest.approx(18.0)
    assert fw.motor.torque_fraction == 0.1


def track_move(limit_reg: int, limit: float, steps: int, passes: int) -> list[float]:
    """SETUP, one limit, MOVESTEPS ``steps`` microsteps; the motor position (deg) after each pass."""
    fw = make(-3600.0, 3600.0)
    send(fw, SETUP_20_20)
    send(fw, bytes([limit_reg]) + struct.pack("<f", limit))
    send(fw, bytes([0x13]) + struct.pack("<i", steps))
    out = []
    for _ in range(passes):
        ticks(fw)
        send(fw, PING)
        out.append(fw.motor.position_deg)
    return out


def test_position_move_brakes_in_time_and_passes_its_target_by_less_than_a_step() -> None:
    # 180 deg/s^2 (the power-up MAXACCEL, docs/firmware.md), 2560 microsteps = 18 deg.
    # Braking from sqrt(2 a d), the 10 ms ramp passes the target by 0.29 deg
    # (an emulator artefact), well under one full step (1.8 deg).
    path = track_move(0x1B, 180.0, 2560, 300)
    assert max(path) < 18.0 + 1.8
    assert path[-1] == pytest.approx(18.0)


def test_position_move_keeps_to_the_max_velocity() -> None:
    # 18 deg/s (the power-up MAXVEL): 25600 microsteps = 180 deg take 10 s; after 1 s at most 18 deg.
    path = track_move(0x1D, 18.0, 25600, 100)
    assert path[-1] <= 18.0 + 1e-9
    assert max(b - a for a, b in itertools.pairwise(path)) <= 0.18 + 1e-9  # deg per 10 ms pass


def test_unloaded_motor_turns_at_1_percent_drive_current() -> None:
    fw = make()
    send(fw, bytes([0x10, 1, 1, 0, 0]))  # SETUP drive 1 %, hold 1 %
    host_limits(fw)
    send(fw, SETRPM_10)
    for _ in range(100):
        ticks(fw)
        send(fw, PING)
    assert fw.motor.position_deg == pytest.approx(59.4, abs=0.5)  # 60 deg/s after a 0.03 s ramp


def test_setup_currents_above_100_percent_run_at_full_current() -> None:
    motor = RecordingMotor()
    core = FirmwareCore(motor, 0.0)
    core.write(0x10, 0x6565, 0.0)  # SETUP drive 101 %, hold 101 %: idle at the hold current
    assert motor.sent[-1] == (0.0, 1.0)
    core.write(0x11, 10.0, 0.0)  # SETRPM 10: runs at the drive current
    core.tick()
    assert motor.sent[-1][1] == 1.0


def test_unpowered_motor_ramps_up_from_rest_when_current_comes_on() -> None:
    # SETRPM runs on a joint never enabled (only STALL blocks it), but with no
    # current the rotor stays and the ramp stays at 0. Powered, it starts from
    # rest: one 10 ms pass at AMAX (uint16)(180 x 3.12889) = 563, 179.94 deg/s^2,
    # is 1.7994 deg/s, 0.017994 deg.
    fw = make()
    send(fw, bytes([0x1B]) + struct.pack("<f", 180.0))  # SETMAXACCELERATION 180
    send(fw, SETRPM_10)
    for _ in range(10):
        ticks(fw)
        send(fw, PING)
    assert fw.motor.position_deg == 0.0
    send(fw, bytes([0x19, 20]))  # SETCURRENT 20
    ticks(fw)
    assert fw.motor.position_deg == pytest.approx(0.017994, abs=1e-6)


def test_every_transfer_counts_as_a_transaction() -> None:
    fw = make()
    fw.transfer(PING, 2)
    fw.transfer(SETUP_20_20, 0)  # a write without a read phase is still a transaction
    fw.transfer(b"", 1)  # a bare read
    assert fw.transactions == 3


def test_firmware_core_powers_up_at_time_zero_by_default() -> None:
    assert FirmwareCore(KinematicStepper(0.0)).time == 0.0


def test_velocity_mode_at_0_rpm_is_driven_at_the_drive_current() -> None:
    # Only an idle motor (no mode, at rest) gets the hold current.
    fw = make()
    send(fw, bytes([0x10, 30, 10, 0, 0]))  # SETUP drive 30 %, hold 10 %
    assert fw.motor.torque_fraction == 0.1
    send(fw, SETRPM_0)
    ticks(fw)
    assert fw.motor.torque_fraction == 0.3


# The motor is sent its (velocity, torque) when they change and, unpowered,
# on every pass: an unpowered motor's set point follows its rotor (firmware.py).
def test_unpowered_motor_is_sent_its_command_every_pass() -> None:
    motor = RecordingMotor()
    core = FirmwareCore(motor, 0.0)
    motor.sent.clear()
    for _ in range(3):
        core.tick()
    assert motor.sent == [(0.0, 0.0)] * 3


def test_powered_idle_motor_is_not_sent_the_same_command_again() -> None:
    motor = RecordingMotor()
    core = FirmwareCore(motor, 0.0)
    core.write(0x10, 0x1414, 0.0)  # SETUP 20 %, 20 %
    motor.sent.clear()
    for _ in range(3):
        core.tick()
    assert motor.sent == []


def test_firmware_core_cancels_a_pending_command_by_default() -> None:
    motor = KinematicStepper(0.0, lower_stop_deg=-720.0, upper_stop_deg=360.0)
    core = FirmwareCore(motor)
    core.write(0x10, 0x1414, 0.0)  # SETUP
    core.write(0x2D, 0x0F1E0A01, 0.0)  # HOME +
    core.read(0x0F, 0.0)  # PING before the main loop took HOME
    for _ in range(100):
        core.tick()
        core.read(0x0F, core.time)
    assert motor.position_deg == 0.0
    assert core.flags == BUSY | NOT_HOMED


def test_power_cycle_without_a_time_restarts_the_clock_at_zero() -> None:
    core = FirmwareCore(KinematicStepper(0.0), 5.0)
    core.power_cycle()
    assert core.time == 0.0


def test_power_up_motor_is_idle_and_held_at_the_hold_current() -> None:
    # Currents set without SETUP (NOTENABLED stays): the idle motor is held at the hold current.
    fw = make()
    send(fw, bytes([0x19, 20]))  # SETCURRENT 20
    send(fw, bytes([0x1A, 10]))  # SETHOLDCURRENT 10
    assert fw.motor.torque_fraction == 0.1


def test_power_up_sends_the_motor_zero_speed_and_no_torque() -> None:
    # docs/firmware.md, power-up: currents 0 %, freewheel.
    motor = RecordingMotor()
    FirmwareCore(motor, 0.0)
    assert motor.sent == [(0.0, 0.0)]
