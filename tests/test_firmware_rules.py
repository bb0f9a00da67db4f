"""The firmware rules joint.ino enforces (and the ones it lacks), byte by byte.

Every number here is a literal from the firmware source or docs/firmware.md;
payloads are literal bytes. Each test is one behaviour; each of the rules a
one-line change could break has a test that fails on that change.
"""

from __future__ import annotations

import dataclasses
import math
import struct

import pytest
from rigs import FakeMotor

from bioscara_gym.hardware.clock import ManualClock
from bioscara_gym.hardware.drive import IDEAL_DRIVE
from bioscara_gym.hardware.firmware import FIRMWARE_STALL_RULE, FirmwareCore, JointFirmware, StallRule
from bioscara_gym.hardware.motor import POLE_PITCH_DEG, KinematicStepper

STALL, BUSY, NOT_HOMED, NOT_ENABLED = 0x01, 0x02, 0x04, 0x08

PING = bytes([0x0F])
GETENCODERRPM = bytes([0x2C])
SETUP_20_20 = bytes([0x10, 20, 20, 0, 0])
SETRPM_10 = bytes([0x11, 0x00, 0x00, 0x20, 0x41])  # 10.0 RPM
SETRPM_MINUS_10 = bytes([0x11, 0x00, 0x00, 0x20, 0xC1])  # -10.0 RPM
SETRPM_MINUS_100 = bytes([0x11, 0x00, 0x00, 0xC8, 0xC2])  # -100.0 RPM
SETRPM_0 = bytes([0x11, 0x00, 0x00, 0x00, 0x00])
MOVETOANGLE_90 = bytes([0x15, 0x00, 0x00, 0xB4, 0x42])  # 90.0 deg
MOVETOANGLE_MINUS_90 = bytes([0x15, 0x00, 0x00, 0xB4, 0xC2])  # -90.0 deg
MOVESTEPS_MINUS_10 = bytes([0x13]) + struct.pack("<i", -2560)  # -10 full steps, in microsteps
ENABLESTALLGUARD_6 = bytes([0x1E, 6])
STOP = bytes([0x29, 0])
#: HOME: direction, 10 RPM, sensitivity 30, current 15 %.
HOME_PLUS = bytes([0x2D, 1, 10, 30, 15])
HOME_MINUS = bytes([0x2D, 0, 10, 30, 15])
HOME_DIR_2 = bytes([0x2D, 2, 10, 30, 15])
CHECKORIENTATION_2 = bytes([0x2B, 0x00, 0x00, 0x00, 0x40])  # 2.0 deg
SETMAXVELOCITY_1000 = bytes([0x1D, 0x00, 0x00, 0x7A, 0x44])  # 1000.0 deg/s
SETMAXACCELERATION_2000 = bytes([0x1B, 0x00, 0x00, 0xFA, 0x44])  # 2000.0 deg/s^2

TICK = 0.01


# ----------------------------------------------------------------- helpers


def make(lower: float = -720.0, upper: float = 360.0, *, cancel_pending: bool = True) -> JointFirmware:
    """Firmware in front of a stepper at 0 deg between end stops (motor degrees)."""
    motor = KinematicStepper(0.0, lower_stop_deg=lower, upper_stop_deg=upper)
    return JointFirmware(motor, ManualClock(), cancel_pending=cancel_pending)


#: Bytes a register answers before the flags: PING 'O', ANGLEMOVED and GETENCODERRPM a float.
ANSWER_LENGTH = {0x0F: 1, 0x18: 4, 0x2C: 4}


def at_stop(position_deg: float, stop_deg: float) -> bool:
    """Where homing leaves the rotor: thrown back off its stop by its first pole slip, under a pole pitch."""
    return abs(position_deg - stop_deg) < POLE_PITCH_DEG


def send(fw: JointFirmware, data: bytes) -> int:
    """One transaction: write ``data``, read its answer and the flags; return the flags."""
    return fw.transfer(data, ANSWER_LENGTH.get(data[0], 0) + 1)[-1]


def _f32(raw: bytes) -> float:
    return struct.unpack("<f", raw)[0]


def wait(fw: JointFirmware, seconds: float) -> None:
    """Silence on the bus for ``seconds``."""
    fw.clock.sleep(seconds)
    fw.update()


def ticks(fw: JointFirmware, n: int = 1) -> None:
    wait(fw, n * TICK)


def talk(fw: JointFirmware, n: int) -> None:
    """``n`` ticks with a PING after each (the deadman stays fed)."""
    for _ in range(n):
        ticks(fw)
        send(fw, PING)


def host_limits(fw: JointFirmware) -> None:
    """SETMAXVELOCITY 1000 deg/s, SETMAXACCELERATION 2000 deg/s^2: the host sets its own before moving.

    At the power-up limits (18 deg/s, 180 deg/s^2, docs/firmware.md) the
    moves below would take seconds.
    """
    send(fw, SETMAXVELOCITY_1000)
    send(fw, SETMAXACCELERATION_2000)


def home(fw: JointFirmware, payload: bytes = HOME_PLUS, timeout_ticks: int = 2000) -> None:
    """SETUP, HOME, one silent tick for the main loop to take it, PING until BUSY clears."""
    send(fw, SETUP_20_20)
    send(fw, payload)
    ticks(fw)
    for _ in range(timeout_ticks):
        if not send(fw, PING) & BUSY:
            return
        ticks(fw)
    raise AssertionError("still BUSY")


def stall(fw: JointFirmware) -> None:
    """Homed, stall detection at 6, running at -100 RPM, rotor blocked until STALL.

    -100 RPM (600 deg/s): a blocked rotor shows 85 microsteps a pass (the
    library's closed loop rewrites its counter each 1 ms), above the
    threshold 60 and within the spike filter's 100.
    """
    home(fw)
    host_limits(fw)
    send(fw, ENABLESTALLGUARD_6)
    send(fw, SETRPM_MINUS_100)
    talk(fw, 40)
    fw.motor.blocked = True
    for _ in range(100):
        ticks(fw)
        if send(fw, PING) & STALL:
            fw.motor.blocked = False
            return
    raise AssertionError("never stalled")


# ------------------------------------------------- what blocks motion: STALL only


def test_movetoangle_ignored_while_stalled() -> None:
    fw = make()
    stall(fw)
    before = fw.motor.position_deg
    send(fw, MOVETOANGLE_90)
    talk(fw, 50)
    assert fw.motor.position_deg == before


def test_setrpm_ignored_while_stalled() -> None:
    fw = make()
    stall(fw)
    before = fw.motor.position_deg
    send(fw, SETRPM_10)
    talk(fw, 50)
    assert fw.motor.position_deg == before


def test_movesteps_runs_while_stalled() -> None:
    fw = make()
    stall(fw)
    host_limits(fw)
    before = fw.motor.position_deg
    send(fw, MOVESTEPS_MINUS_10)
    talk(fw, 50)
    assert fw.motor.position_deg == pytest.approx(before - 18.0, abs=1e-3)


def test_movetoangle_runs_while_not_homed() -> None:
    fw = make()
    send(fw, SETUP_20_20)
    host_limits(fw)
    send(fw, MOVETOANGLE_MINUS_90)
    talk(fw, 100)
    assert fw.motor.position_deg == pytest.approx(-90.0, abs=1e-3)


def test_movetoangle_moves_the_joint_after_the_deadman_tripped() -> None:
    fw = make()
    home(fw)
    zero = fw.motor.position_deg
    host_limits(fw)
    send(fw, SETRPM_MINUS_10)
    ticks(fw, 10)  # silence: the deadman trips, the currents stay on
    assert send(fw, PING) & NOT_ENABLED
    send(fw, MOVETOANGLE_MINUS_90)
    talk(fw, 200)
    assert fw.motor.position_deg == pytest.approx(zero - 90.0, abs=1e-3)


def test_setrpm_without_payload_runs_the_stored_value_again() -> None:
    fw = make()
    home(fw)
    host_limits(fw)
    send(fw, SETRPM_MINUS_10)
    send(fw, STOP)
    talk(fw, 10)
    send(fw, bytes([0x11]))  # memcpy of 0 bytes: qd_set is still -10 RPM
    talk(fw, 100)
    # VMAX int(60 x 238.507) = 14310: 59.998 deg/s; the encoder's estimate settled after 1 s.
    assert _f32(fw.transfer(GETENCODERRPM, 5)[:4]) == pytest.approx(-59.998 / 6.0, abs=1e-4)


@pytest.mark.parametrize(
    ("payload", "speed_dps"),
    [
        # +inf: the Cortex-M4 saturates, VMAX stops at 0x7FFE00 = 8,388,096 / 238.507 (the SITL firmware)
        (bytes([0x00, 0x00, 0x80, 0x7F]), 35_169.0),
        (bytes([0x00, 0x00, 0x80, 0xFF]), -35_169.0),  # -inf
        (bytes([0x00, 0x00, 0xC0, 0x7F]), 0.0),  # NaN converts to 0
    ],
)
def test_setrpm_of_a_non_finite_value_runs_as_the_chip_converts_it(payload: bytes, speed_dps: float) -> None:
    fw = make()
    home(fw)
    send(fw, bytes([0x1B]) + struct.pack("<f", 20_000.0))  # under the 16-bit AMAX's top, 20,945
    send(fw, bytes([0x11]) + payload)
    talk(fw, 200)  # 1.8 s to the top speed; the field runs on past the end stop
    assert fw.motor.field_velocity_dps == pytest.approx(speed_dps, abs=1.0)


# ---------------------------------------------------------------- deadman


def test_deadman_trips_after_50_ms_of_silence_with_a_nonzero_setrpm() -> None:
    fw = make()
    home(fw)
    send(fw, SETRPM_MINUS_10)
    ticks(fw, 6)
    assert fw.flags & NOT_ENABLED


def test_deadman_holds_at_exactly_50_ms_of_silence() -> None:
    # Transaction on a tick: the passes 10, 20, ... 50 ms later see diff <= 50.
    fw = make()
    home(fw)
    send(fw, SETRPM_MINUS_10)
    ticks(fw, 5)
    assert not fw.flags & NOT_ENABLED


def test_deadman_trips_on_the_pass_55_ms_after_the_last_transaction() -> None:
    # Transaction 5 ms after a pass: the passes see 5, 15, ... 45, 55 ms; 55 > 50.
    fw = make()
    home(fw)
    wait(fw, 0.005)
    send(fw, SETRPM_MINUS_10)
    wait(fw, 0.045)
    assert not fw.flags & NOT_ENABLED
    wait(fw, 0.010)
    assert fw.flags & NOT_ENABLED


def test_deadman_cuts_a_position_move_after_a_nonzero_setrpm() -> None:
    fw = make()
    home(fw)
    send(fw, SETRPM_MINUS_10)
    send(fw, MOVETOANGLE_MINUS_90)  # qd_set stays -10: the deadman still watches
    ticks(fw, 200)
    assert fw.flags & NOT_ENABLED
    assert fw.motor.position_deg > 360.0 - 90.0 + 1.0


def test_deadman_watches_after_a_stop() -> None:
    fw = make()
    home(fw)
    send(fw, SETRPM_MINUS_10)
    send(fw, STOP)  # setRPM(0) but qd_set is kept
    ticks(fw, 10)
    assert fw.flags & NOT_ENABLED


def test_deadman_ignores_a_zero_setrpm() -> None:
    fw = make()
    home(fw)
    send(fw, SETRPM_MINUS_10)
    send(fw, SETRPM_0)
    ticks(fw, 100)
    assert not fw.flags & NOT_ENABLED


def test_deadman_keeps_the_currents_on() -> None:
    fw = make()
    home(fw)
    send(fw, SETRPM_MINUS_10)
    ticks(fw, 100)
    assert fw.motor.torque_fraction > 0.0


# ----------------------------------------------------------------- homing


def test_homing_stays_still_for_500_ms_after_the_loop_takes_it() -> None:
    fw = make()
    send(fw, SETUP_20_20)
    send(fw, HOME_PLUS)
    ticks(fw, 1)  # the pass that takes HOME
    ticks(fw, 49)
    assert fw.motor.position_deg == 0.0


def test_homing_moves_within_530_ms_after_the_loop_takes_it() -> None:
    fw = make()
    send(fw, SETUP_20_20)
    send(fw, HOME_PLUS)
    ticks(fw, 1)
    ticks(fw, 53)
    assert fw.motor.position_deg > 0.0


def test_homing_runs_at_the_homing_current() -> None:
    fw = make()
    send(fw, SETUP_20_20)
    send(fw, HOME_PLUS)
    ticks(fw, 100)
    assert fw.motor.torque_fraction == 0.15


def test_homing_restores_the_drive_current_after() -> None:
    fw = make()
    home(fw)
    send(fw, MOVETOANGLE_MINUS_90)
    ticks(fw, 2)
    assert fw.motor.torque_fraction == 0.20


def test_homing_energises_a_joint_that_was_never_enabled() -> None:
    fw = make()
    send(fw, HOME_PLUS)
    ticks(fw, 1)
    for _ in range(2000):
        if not send(fw, PING) & BUSY:
            break
        ticks(fw)
    assert at_stop(fw.motor.position_deg, 360.0)


def test_homing_stops_a_running_motor_before_its_wait() -> None:
    fw = make()
    send(fw, SETUP_20_20)
    send(fw, SETRPM_MINUS_10)
    talk(fw, 20)
    send(fw, HOME_PLUS)
    ticks(fw, 1)  # the pass that takes HOME: hard stop
    before = fw.motor.position_deg
    ticks(fw, 40)
    assert fw.motor.position_deg == before


@pytest.mark.parametrize(
    ("payload", "stop"),
    [(HOME_PLUS, 360.0), (HOME_DIR_2, 360.0), (HOME_MINUS, -240.0)],
    ids=["dir-1", "dir-2", "dir-0"],
)
def test_homing_direction_byte_nonzero_is_positive(payload: bytes, stop: float) -> None:
    fw = make(lower=-240.0, upper=360.0)
    home(fw, payload)
    assert at_stop(fw.motor.position_deg, stop)


class SoftStopMotor:
    """A motor whose PID error grows at 30 deg/s once the rotor passes ``stop`` (a soft end stop).

    A test double at the Motor boundary: the rotor follows the set point up to
    the stop and then gives way at half its speed; the error the firmware
    reads is set point minus rotor, without the library's closed loop.
    """

    def __init__(self, stop: float) -> None:
        self.stop = stop
        self.setpoint_deg = 0.0
        self.position_deg = 0.0
        self.velocity_dps = 0.0
        self._command = 0.0
        self._torque = 0.0

    @property
    def pid_error_deg(self) -> float:
        return self.setpoint_deg - self.position_deg

    @property
    def pid_jitter_usteps(self) -> float:
        return 0.0

    def command(self, velocity_dps: float, torque_fraction: float) -> None:
        self._command, self._torque = velocity_dps, torque_fraction

    def hold_here(self) -> None:
        self.setpoint_deg = self.position_deg

    def advance(self, dt: float) -> None:
        if self._torque <= 0.0:
            return
        self.setpoint_deg += self._command * dt
        sp = self.setpoint_deg
        new = sp if sp <= self.stop else max(self.position_deg, self.stop + (sp - self.stop) / 2)
        self.velocity_dps = (new - self.position_deg) / dt
        self.position_deg = new


def test_homing_polls_the_pid_error_every_millisecond() -> None:
    # Past the soft stop the error grows at 30 deg/s. Sensitivity 30 (1/256 microsteps,
    # 30 x 360/51200 = 0.2109 deg) is passed 0.2109 deg past the stop; at 1 ms polls
    # the encoder is zeroed within 0.03 deg (1 ms of rotor travel) of that, at 10 ms
    # within 0.3 deg.
    motor = SoftStopMotor(90.0)
    fw = JointFirmware(motor, ManualClock())
    home(fw)
    assert 90.0 + 0.2109 < motor.position_deg <= 90.0 + 0.2109 + 0.031


class NoZeroStepMotor(KinematicStepper):
    """A stepper that refuses to be advanced by no time at all."""

    def advance(self, dt: float) -> None:
        assert dt > 0.0
        super().advance(dt)


@pytest.mark.parametrize("start_deg", [356.0 + 0.06 * k for k in range(10)])
def test_homing_that_ends_on_any_millisecond_of_a_tick_completes(start_deg: float) -> None:
    # Starting 0.06 deg (1 ms at 10 RPM) apart, the homing returns on each of a tick's ten polls.
    motor = NoZeroStepMotor(start_deg, upper_stop_deg=360.0)
    fw = JointFirmware(motor, ManualClock())
    home(fw)
    assert at_stop(motor.position_deg, 360.0)


def test_stop_during_homing_ends_it_aborted() -> None:
    fw = make()
    send(fw, SETUP_20_20)
    send(fw, HOME_PLUS)
    ticks(fw, 70)
    send(fw, STOP)
    ticks(fw, 2)
    assert send(fw, PING) == NOT_HOMED


def test_setup_during_homing_stops_the_motor_but_leaves_busy() -> None:
    fw = make()
    send(fw, SETUP_20_20)
    send(fw, HOME_PLUS)
    ticks(fw, 70)  # running toward the end stop
    send(fw, SETUP_20_20)
    before = fw.motor.position_deg
    talk(fw, 300)
    # moveSteps(0): the chip brakes and comes back to where the counter stood.
    assert fw.motor.position_deg == pytest.approx(before, abs=1e-9)
    assert send(fw, PING) == BUSY | NOT_HOMED


def test_stop_ends_a_homing_that_setup_left_busy() -> None:
    fw = make()
    send(fw, SETUP_20_20)
    send(fw, HOME_PLUS)
    ticks(fw, 70)
    send(fw, SETUP_20_20)
    talk(fw, 10)
    send(fw, STOP)
    ticks(fw, 1)
    assert send(fw, PING) == NOT_HOMED


# ------------------------------------- a transaction cancels a pending command


def test_ping_before_the_loop_takes_home_cancels_it() -> None:
    fw = make()
    send(fw, SETUP_20_20)
    send(fw, HOME_PLUS)
    send(fw, PING)  # rx_data_ready = 0 before the main loop looked
    talk(fw, 200)
    assert fw.motor.position_deg == 0.0


def test_cancelled_home_leaves_busy_and_not_homed_set() -> None:
    fw = make()
    send(fw, SETUP_20_20)
    send(fw, HOME_PLUS)
    send(fw, PING)
    talk(fw, 200)
    assert send(fw, PING) == BUSY | NOT_HOMED


def test_stop_clears_the_busy_of_a_cancelled_home() -> None:
    fw = make()
    send(fw, SETUP_20_20)
    send(fw, HOME_PLUS)
    send(fw, PING)
    send(fw, STOP)
    assert send(fw, PING) == NOT_HOMED


def test_transaction_after_the_loop_took_home_does_not_cancel_it() -> None:
    fw = make()
    send(fw, SETUP_20_20)
    send(fw, HOME_PLUS)
    ticks(fw, 1)
    talk(fw, 1000)
    assert at_stop(fw.motor.position_deg, 360.0)
    assert send(fw, PING) == 0


def test_ping_before_the_loop_takes_checkorientation_leaves_it_busy() -> None:
    fw = make()
    send(fw, SETUP_20_20)
    send(fw, CHECKORIENTATION_2)
    send(fw, PING)
    talk(fw, 100)
    assert send(fw, PING) == BUSY | NOT_HOMED


def test_ping_before_the_loop_takes_an_unknown_register_leaves_it_busy() -> None:
    fw = make()
    send(fw, bytes([0x21, 0, 0, 0, 0]))
    send(fw, PING)
    talk(fw, 100)
    assert send(fw, PING) == NOT_HOMED | NOT_ENABLED | BUSY


def test_cancellation_can_be_switched_off() -> None:
    fw = make(cancel_pending=False)
    send(fw, SETUP_20_20)
    send(fw, HOME_PLUS)
    send(fw, PING)
    talk(fw, 1000)
    assert at_stop(fw.motor.position_deg, 360.0)


# ------------------------------------------------------------ stall detector


def feed(core: FirmwareCore, motor: FakeMotor, microsteps: list[float]) -> list[bool]:
    """One pass per PID error (the library's 1/256 microsteps, 51,200 a turn); STALL after each."""
    out = []
    for e in microsteps:
        motor.setpoint_deg = motor.position_deg + e * 360.0 / 51_200
        core.tick()
        out.append(bool(core.flags & STALL))
    return out


@pytest.fixture
def guarded() -> tuple[FirmwareCore, FakeMotor]:
    """Enabled, stall detection at sensitivity 6 (threshold 60; 150 inside 12-450 rad/s)."""
    motor = FakeMotor()
    core = FirmwareCore(motor, 0.0)
    core.write(0x10, 0x1414, 0.0)
    core.write(0x1E, 6, 0.0)
    return core, motor


# Encoder speeds (deg/s) that the firmware's RPM / 9.549296596425384 makes exactly
# 12.0 and 450.0 rad/s, the edges of the +90 window.
EDGE_SPEEDS = {"12": 687.5493549426277, "450": 25783.100810348532}


@pytest.mark.parametrize("edge", sorted(EDGE_SPEEDS))
def test_stall_window_edge_speed_gets_the_extra_90(
    guarded: tuple[FirmwareCore, FakeMotor], edge: str
) -> None:
    core, motor = guarded
    motor.velocity_dps = EDGE_SPEEDS[edge]
    # Ramped to 100 (no spikes): x -> 100, above 60 but below 150.
    assert not any(feed(core, motor, [20.0, 40.0, 60.0, 80.0] + [100.0] * 100))


def test_stall_without_the_window_trips_at_60(guarded: tuple[FirmwareCore, FakeMotor]) -> None:
    core, motor = guarded
    motor.velocity_dps = 600.0  # 10.5 rad/s, below the window
    assert any(feed(core, motor, [20.0, 40.0, 60.0, 80.0] + [100.0] * 100))


def test_enablestallguard_keeps_the_filter_state(guarded: tuple[FirmwareCore, FakeMotor]) -> None:
    core, motor = guarded
    # x = 100 (1 - 0.9^8) = 56.95 after eight passes at 100: below 60.
    assert not any(feed(core, motor, [100.0] * 8))
    core.write(0x1E, 6, core.time)  # the firmware does not reset the low pass
    assert feed(core, motor, [100.0]) == [True]  # x = 61.26


def test_sustained_jump_above_100_stays_filtered_after_it_settles(
    guarded: tuple[FirmwareCore, FakeMotor],
) -> None:
    core, motor = guarded
    # 50 for a while (x -> 50), then a jump to 400 held: 400 - 50 > 100, filtered every pass.
    assert not any(feed(core, motor, [50.0] * 100 + [400.0] * 300))


# ------------------------------------------ the spike filter's blind spot
def _blocked_at(rpm: float, rule: StallRule, swing: bool = True) -> float | None:
    """Seconds from blocking the rotor at ``rpm`` until STALL (None: not within 3 s).

    ``swing=False``: homed as usual, the rotor is then held without the
    pole-slip swing (``kick_accel`` 0), so its PID error grows by the field's
    travel each pass. (With the swing it rises in smaller steps as well, and
    the packaged rule trips after 0.12 s.)
    """
    fw = JointFirmware(KinematicStepper(0.0, -1e9, 360.0), ManualClock(), stall_rule=rule)
    home(fw)
    host_limits(fw)
    send(fw, ENABLESTALLGUARD_6)
    send(fw, bytes([0x11]) + struct.pack("<f", rpm))
    talk(fw, 60)
    if not swing:
        fw.motor.drive = IDEAL_DRIVE.with_values(kick_accel=0.0)
    fw.motor.blocked = True
    for i in range(300):
        ticks(fw)
        if send(fw, PING) & STALL:
            return (i + 1) * 0.01
    return None


def test_a_rotor_blocked_at_more_than_100_microsteps_a_pass_is_not_detected() -> None:
    # -150 RPM is 900 deg/s: the blocked rotor shows 900 x 0.001 x 51,200/360 = 128
    # microsteps a pass (the library's closed loop), a jump of more than the spike
    # limit of 100 from the following rotor's error: dropped, and so every pass after.
    assert _blocked_at(-150.0, FIRMWARE_STALL_RULE, swing=False) is None


def test_the_recorded_builds_spike_limit_detects_the_same_block_within_50_ms() -> None:
    # The real arm's stall recordings came from builds that let jumps of up to 404
    # through (high_speed_stall_test/j4_STALL_adaptive_stall_threshold.csv); with a
    # limit of 1000 the same block trips within 50 ms, as the real j4 did at 26 rad/s.
    old_build = dataclasses.replace(FIRMWARE_STALL_RULE, spike_limit=1000.0)
    tripped = _blocked_at(-150.0, old_build)
    assert tripped is not None and tripped <= 0.05


def test_a_rotor_blocked_at_85_microsteps_a_pass_is_detected() -> None:
    # -100 RPM (600 deg/s): 85 microsteps a pass, above the threshold 60, below the
    # limit. The low-pass alone would cross 60 after 0.12 s; the pole slips' spikes
    # are dropped and the rotor's swing back lowers the passes between them.
    tripped = _blocked_at(-100.0, FIRMWARE_STALL_RULE)
    assert tripped is not None and 0.12 < tripped <= 0.5


@pytest.mark.parametrize(
    ("value", "expected"), [(1e39, float("inf")), (-1e39, float("-inf")), (3.0e38, 3.0e38)]
)
def test_a_value_beyond_floats_range_is_infinite_as_the_c_cast_makes_it_without_a_warning(
    value: float, expected: float
) -> None:
    """The library computes in C float: a double beyond FLT_MAX (3.4028235e38) casts to infinity."""
    import warnings

    from bioscara_gym.hardware.drive import _f32

    with warnings.catch_warnings():
        warnings.simplefilter("error")
        assert _f32(value) == pytest.approx(expected, rel=1e-7)


@pytest.mark.parametrize(
    ("value", "expected"),
    [
        (0.1, 0.10000000149011612),  # to nearest: up
        (1 / 3, 0.3333333432674408),
        (16777217.0, 16777216.0),  # a tie: to even
        (3.40282356e38, 3.4028234663852886e38),  # above FLT_MAX, below the half step: FLT_MAX
        (3.4028236e38, float("inf")),  # past the half step: infinity
        (1e-46, 0.0),  # below the smallest denormal's half
        (-1e-46, -0.0),
    ],
)
def test_a_double_rounds_to_the_nearest_float_as_the_c_cast_does(value: float, expected: float) -> None:
    from bioscara_gym.hardware.drive import _f32

    result = _f32(value)
    assert result == expected and math.copysign(1.0, result) == math.copysign(1.0, expected)


def test_nan_stays_nan_in_float() -> None:
    from bioscara_gym.hardware.drive import _f32

    assert math.isnan(_f32(float("nan")))
