"""Emulation of the joint firmware (``docs/firmware.md``).

Two layers, so the rules exist once:

* :class:`FirmwareCore` holds the firmware's state and rules: the flags, the
  register semantics (``write``/``read`` with decoded values), the 10 ms main
  loop (:meth:`FirmwareCore.tick`) with the set-point ramp, homing against the
  end stop, stall detection and the deadman. It drives a pluggable
  :class:`~bioscara_gym.hardware.motor.Motor`. ``SimJoint`` calls it directly.
* :class:`JointFirmware` puts the I2C byte protocol in front of a core and
  keeps it in step with an injectable clock; ``EmulatedI2CBus`` routes bytes to
  it.

The protocol's numbers (timings, stall-detector constants) are in
:mod:`~bioscara_gym.hardware.registers` with their sources; what is only an
emulation choice stays here.

Units inside the firmware are the motor's: degrees, deg/s, RPM. The PID
error is the uStepper S32 library's (``getPidError()``): the driver's
position counter minus the encoder, in 1/256 microsteps (51,200 per turn),
computed by the library's 1 kHz closed loop, which rewrites the counter to
the encoder whenever the two differ by 15 microsteps or more
(:mod:`~bioscara_gym.hardware.drive`). So the firmware reads the change of
the rotor's lag since the last rewrite, not the lag: about the step rate
times 1 ms while the rotor slips or is blocked, plus the spike of a pole
slip; a following rotor shows only jitter. The limits the firmware passes
on are what the library and the driver chip make of them: the magnitude,
saturated or cut to the chip's registers (:func:`~.drive.position_move_limits`).
"""

from __future__ import annotations

import math
import struct
from dataclasses import dataclass
from enum import Enum

from bioscara_gym.hardware import codec
from bioscara_gym.hardware.clock import Clock
from bioscara_gym.hardware.codec import unpack_bytes
from bioscara_gym.hardware.drive import (
    USTEPS_PER_DEG,
    position_move_limits,
    velocity_mode_acceleration,
    velocity_mode_speed,
)
from bioscara_gym.hardware.motor import Motor
from bioscara_gym.hardware.registers import (
    ACK,
    DEADMAN_MS,
    FLAG_BUSY,
    FLAG_MASK,
    FLAG_NOT_ENABLED,
    FLAG_NOT_HOMED,
    FLAG_STALL,
    FLAGS_SIZE,
    HOMING_POLL_S,
    HOMING_SETTLE_S,
    MAX_PAYLOAD,
    POWER_UP_FLAGS,
    STALL_MID_SPEED_BAND,
    STALL_MID_SPEED_OFFSET,
    STALL_RPM_PER_RAD_S,
    STALL_SLOPE,
    STALL_SPIKE_LIMIT,
    STALL_TAU_S,
    STALL_THRESHOLD_PER_SENSITIVITY,
    TICK_S,
    Flag,
    Reg,
)
from bioscara_gym.hardware.transmission import steps_to_degrees

__all__ = [
    "FIRMWARE_STALL_RULE",
    "MICROSTEPS_PER_DEG",
    "MICROSTEPS_PER_FULL_STEP",
    "FirmwareCore",
    "JointFirmware",
    "Mode",
    "StallRule",
    "stall_threshold",
]

#: PID-error units per full step: the library's 1/256 microsteps (``closedLoopCallback``).
MICROSTEPS_PER_FULL_STEP = 256
#: PID-error units per motor degree: 51,200 a turn.
MICROSTEPS_PER_DEG = USTEPS_PER_DEG
#: Limits before the host sets any: ``configuration.h``'s MAXVEL 10 steps/s and
#: MAXACCEL 100 steps/s^2, which ``setup()`` gives the stepper (docs/firmware.md, "Power-up").
DEFAULT_MAX_VELOCITY_DPS = 18.0
DEFAULT_MAX_ACCELERATION_DPS2 = 180.0
DEFAULT_CURRENT_PCT = 0
#: The firmware stores its limits in steps: deg x 200/360 (SETMAXVELOCITY, SETMAXACCELERATION).
_STEPS_PER_DEG = 200 / 360.0

_HOMING_POLLS_PER_TICK = round(TICK_S / HOMING_POLL_S)


class Mode(Enum):
    """What the set-point generator is doing."""

    IDLE = 0
    VELOCITY = 1
    POSITION = 2


class _Blocking(Enum):
    NONE = 0
    HOME_SETTLE = 1
    HOME_RUN = 2
    ORIENTATION_OUT = 3
    ORIENTATION_BACK = 4


#: Registers ``non_blocking_handler`` has a case for; every other byte goes to
#: its default branch, the blocking handler (firmware).
NON_BLOCKING_REGISTERS = frozenset(
    {
        Reg.PING,
        Reg.SETUP,
        Reg.GETDRIVERRPM,
        Reg.ANGLEMOVED,
        Reg.GETENCODERRPM,
        Reg.SETRPM,
        Reg.MOVESTEPS,
        Reg.MOVETOANGLE,
        Reg.SETCURRENT,
        Reg.SETHOLDCURRENT,
        Reg.SETMAXACCELERATION,
        Reg.SETMAXVELOCITY,
        Reg.ENABLESTALLGUARD,
        Reg.SETBRAKEMODE,
        Reg.DISABLECLOSEDLOOP,
        Reg.STOP,
        Reg.HOMEOFFSET,
        Reg.HOME,
    }
)


@dataclass(frozen=True)
class StallRule:
    """The stall detector's constants: the firmware's, or an older build's.

    The packaged firmware's are :data:`FIRMWARE_STALL_RULE` (``joint.ino``,
    ``stall.h``, ``configuration.h``). Some of the real arm's recordings come
    from earlier builds with other values (a linear slope, another band, a
    much larger spike limit); the validation replays each with its own.

    Attributes:
        spike_limit: An upward jump of |PID error| above this per pass keeps the last value.
        tau_s: Low-pass time constant, s (sample time: the 10 ms pass).
        per_sensitivity: Threshold per unit of ENABLESTALLGUARD sensitivity.
        slope: Threshold per motor rad/s of measured speed.
        band: Motor speeds (rad/s, inclusive) that get ``band_offset`` more.
        band_offset: Extra threshold inside ``band``.
    """

    spike_limit: float = STALL_SPIKE_LIMIT
    tau_s: float = STALL_TAU_S
    per_sensitivity: float = STALL_THRESHOLD_PER_SENSITIVITY
    slope: float = STALL_SLOPE
    band: tuple[float, float] = STALL_MID_SPEED_BAND
    band_offset: float = STALL_MID_SPEED_OFFSET

    def filter(self, raw: float, last: float, state: float) -> tuple[float, float]:
        """One pass of ``loop()``'s filter: |PID error| ``raw`` after ``last``, low-pass at ``state``.

        Returns the value after the one-sided spike filter (a rise of more
        than ``spike_limit`` keeps ``last``) and the low-pass's new state.
        """
        u = last if raw - last > self.spike_limit else raw
        gain = TICK_S / self.tau_s
        return u, (1.0 - gain) * state + gain * u

    def threshold(self, omega_rad_s: float, sensitivity: int) -> float:
        """Speed-adaptive threshold at measured motor speed ``omega_rad_s`` (``stall.h``)."""
        offset = self.per_sensitivity * sensitivity
        lo, hi = self.band
        w = abs(omega_rad_s)
        if w >= lo and w <= hi:  # the firmware's two comparisons, both inclusive
            offset += self.band_offset
        return self.slope * omega_rad_s + offset


#: The stall detector of the firmware source this package follows.
FIRMWARE_STALL_RULE = StallRule()


def stall_threshold(omega_rad_s: float, sensitivity: int) -> float:
    """Speed-adaptive stall threshold in microsteps, as ``stall.h`` computes it.

    Args:
        omega_rad_s: Measured motor speed in rad/s (signed).
        sensitivity: The ENABLESTALLGUARD payload (threshold is 10x it).

    Returns:
        ``slope*omega + 10*sensitivity``, plus 90 when 12 <= |omega| <= 450
        (the constants of :mod:`~bioscara_gym.hardware.registers`).
    """
    return FIRMWARE_STALL_RULE.threshold(omega_rad_s, sensitivity)


def _millis(t: float) -> int:
    """``millis()`` at time ``t`` seconds: whole milliseconds (rounded to 1 us first)."""
    return round(t * 1e6) // 1000


class FirmwareCore:
    """State and rules of one joint's firmware, independent of the bus.

    Every call of :meth:`write`, :meth:`read` or :meth:`touch` is one I2C
    transaction's request handler; :meth:`tick` is one main-loop pass.

    Args:
        motor: The motor model the firmware drives.
        start_time: Time of power-up in seconds (for the deadman).
        cancel_pending: Follow the firmware in letting any transaction cancel
            a blocking command the main loop has not picked up yet (BUSY, and
            for HOME NOTHOMED, then stay set until a STOP). On by default;
            off only to run host code that does not yet wait
            :data:`~bioscara_gym.hardware.registers.BLOCKING_PICKUP_S`.
        stall_rule: The stall detector's constants (default: the firmware's).

    Attributes:
        stall_log: None, or a list that each stall-detection pass appends
            what the firmware prints over serial in that pass (``loop()``:
            raw |PID error|, spikes removed, low-pass filtered, measured and
            set speed in motor rad/s, threshold, stall 0/1) with the time.
    """

    def __init__(
        self,
        motor: Motor,
        start_time: float = 0.0,
        *,
        cancel_pending: bool = True,
        stall_rule: StallRule = FIRMWARE_STALL_RULE,
    ) -> None:
        """Power the firmware up in front of ``motor``."""
        self.motor = motor
        self.cancel_pending = cancel_pending
        self.stall_rule = stall_rule
        self.stall_log: list[tuple[float, ...]] | None = None
        self.power_cycle(start_time)

    # ------------------------------------------------------------------ state
    def power_cycle(self, now: float = 0.0) -> None:
        """Cut and restore power: flags, offset, encoder zero and limits reset.

        The motor keeps its physical position; the encoder counts from there.
        """
        self.flags = int(POWER_UP_FLAGS)
        self.time = now
        self.last_rx = now
        self.drive_current = DEFAULT_CURRENT_PCT  # the firmware's driveCurrent
        self.hold_current = DEFAULT_CURRENT_PCT
        self.motor_current = DEFAULT_CURRENT_PCT  # what the stepper runs at (homing changes it)
        self.brake_mode = 0
        self.max_velocity = DEFAULT_MAX_VELOCITY_DPS  # the firmware's maxVel, deg/s as sent
        self.max_acceleration = DEFAULT_MAX_ACCELERATION_DPS2  # maxAccel, deg/s² as sent
        # The driver chip's ramp registers, deg/s and deg/s²: setup()'s
        # checkOrientation and stop() leave AMAX at the power-up limit and VMAX
        # at 0 (the next SETRPM or move writes it).
        self.vmax = 0.0
        self.amax = velocity_mode_acceleration(self.max_acceleration)
        self.qd_set = 0.0  # last SETRPM value (the deadman watches it)
        self.q_set = 0.0  # last MOVETOANGLE value
        self.mode = Mode.IDLE
        self.target_rpm = 0.0
        self.target_deg = 0.0  # absolute motor degrees in POSITION mode
        self.sp_velocity = 0.0  # ramped set-point velocity, deg/s
        self.encoder_zero = self.motor.position_deg
        self.home_offset = 0.0
        self.stallguard = False
        self.stall_sensitivity = 0
        self._filter_x = 0.0
        self._filter_last = 0.0
        self._pending = False  # rx_data_ready
        self._pending_reg = int(Reg.NONE)  # blk_reg
        self._pending_arg = 0.0
        self._blocking = _Blocking.NONE
        self._blocking_arg = 0.0
        self._blocking_until = 0.0
        self._homing = (1, 0.0, 0, 0)  # direction sign, rpm, sensitivity, current
        self._sent = (0.0, 0.0)  # last (velocity, torque) sent to the motor
        self.motor.command(0.0, 0.0)
        self.motor.hold_here()

    def snapshot(self) -> dict[str, object]:
        """The firmware's state, for :meth:`restore` (not the motor, the stall rule, the serial log)."""
        return {k: v for k, v in vars(self).items() if k not in ("motor", "stall_rule", "stall_log")}

    def restore(self, snapshot: dict[str, object]) -> None:
        """Return to a :meth:`snapshot` and re-send the motor its set point and torque."""
        self.__dict__.update(snapshot)
        self._sent = (math.nan, math.nan)
        self._apply()

    def _set(self, flag: int, on: bool = True) -> None:
        if on:
            self.flags |= flag
        else:
            self.flags &= ~flag & FLAG_MASK

    @property
    def pid_error(self) -> float:
        """Set point minus encoder, in 1/16 microsteps."""
        return self.motor.pid_error_deg * MICROSTEPS_PER_DEG

    @property
    def angle_moved(self) -> float:
        """ANGLEMOVED: motor degrees since the encoder was zeroed."""
        return self.motor.position_deg - self.encoder_zero

    @property
    def encoder_rpm(self) -> float:
        """GETENCODERRPM: measured motor speed in RPM."""
        return self.motor.velocity_dps / 6.0

    @property
    def busy(self) -> bool:
        """Whether a blocking command is running in the main loop."""
        return self._blocking is not _Blocking.NONE

    @property
    def pending(self) -> bool:
        """Whether a blocking command waits for the main loop (``rx_data_ready``)."""
        return self._pending

    @property
    def homing_runs(self) -> bool:
        """Whether the homing loop is polling the PID error (after its 500 ms wait)."""
        return self._blocking is _Blocking.HOME_RUN

    # --------------------------------------------------------------- commands
    def _begin(self, now: float) -> None:
        """What every request handler does first: ``rx_data_ready = 0``; deadman fed."""
        self.last_rx = now  # deadman = millis() at the end of the handler: the same instant
        if self.cancel_pending:
            self._pending = False

    def write(self, reg: int, value: float | int, now: float) -> None:
        """Handle a command the way the firmware's receive/request ISRs do.

        Non-blocking commands take effect at once; every register without a
        case in ``non_blocking_handler`` (HOME's main part, CHECKORIENTATION,
        anything unknown) sets BUSY now and runs in the main loop.

        Args:
            reg: Register byte.
            value: Decoded payload (0 where the register has none).
            now: Time of the transaction in seconds.
        """
        self._begin(now)
        handler = self._WRITE_HANDLERS.get(reg)
        if handler is None:
            self._set_flags_for_blocking_handler(reg, value)
        else:
            handler(self, value)

    def read(self, reg: int, now: float) -> float | int | None:
        """Answer a read request; ``None`` for registers without a payload."""
        self._begin(now)
        if reg == Reg.PING:
            return ACK
        if reg == Reg.ANGLEMOVED:
            return self.angle_moved
        if reg == Reg.GETENCODERRPM:
            return self.encoder_rpm
        if reg == Reg.HOMEOFFSET:
            return self.home_offset
        return None

    def touch(self, now: float) -> None:
        """A transaction whose handler does nothing (GETDRIVERRPM): feeds the deadman."""
        self._begin(now)

    def _hard_stop(self) -> None:
        """``stepper.stop(HARD)``: stopped at once, AMAX restored, VMAX left at 0."""
        self.mode = Mode.IDLE
        self.target_rpm = 0.0
        self.sp_velocity = 0.0
        self.vmax = 0.0
        self.amax = velocity_mode_acceleration(self.max_acceleration)
        self.motor.hold_here()
        self._apply()

    def _set_rpm(self, rpm: float) -> None:
        """``stepper.setRPM``: velocity mode at VMAX := |rpm| (never clamped to the max velocity)."""
        self.mode = Mode.VELOCITY
        self.target_rpm = 0.0 if math.isnan(rpm) else float(rpm)  # ±inf: the top speed
        self.vmax = abs(velocity_mode_speed(self.target_rpm))

    def _start_move(self, target_deg: float) -> None:
        """``moveSteps``: a positioning move with AMAX/DMAX cut to 16 bits and VMAX := max velocity."""
        self.mode = Mode.POSITION
        self.target_deg = target_deg
        self.vmax, self.amax = position_move_limits(self.max_velocity, self.max_acceleration)

    def _apply(self) -> None:
        """Send the current set-point velocity and torque to the motor."""
        if self.sp_velocity == 0.0 and self.mode is Mode.IDLE:
            torque = self.hold_current / 100.0
        else:
            torque = self.motor_current / 100.0
        sent = (self.sp_velocity, torque)
        if sent != self._sent or torque <= 0.0:  # unpowered motors re-follow their rotor
            self._sent = sent
            self.motor.command(*sent)

    def _cmd_setup(self, value: float | int) -> None:
        drive, hold, _, _ = unpack_bytes(int(value))
        self.drive_current = self.motor_current = min(drive, 100)
        self.hold_current = min(hold, 100)
        self.stallguard = False
        self._set(FLAG_STALL | FLAG_NOT_ENABLED, False)
        self.qd_set = 0.0
        # moveSteps(0): a positioning move to where the driver's counter is, with
        # AMAX/DMAX cut to 16 bits (so a later SETRPM ramps at the cut value).
        # A motor at rest is there already: idle, at its hold current.
        self._start_move(self.motor.setpoint_deg)
        if self.sp_velocity == 0.0:
            self.mode = Mode.IDLE
        self._apply()

    def _cmd_set_rpm(self, value: float | int) -> None:
        self.qd_set = float(value)
        if not self.flags & FLAG_STALL:
            self._set_rpm(self.qd_set)

    def _cmd_move_steps(self, value: float | int) -> None:
        self._start_move(self.motor.setpoint_deg + steps_to_degrees(int(value)))

    def _cmd_move_to_angle(self, value: float | int) -> None:
        self.q_set = float(value)
        if not self.flags & FLAG_STALL and math.isfinite(self.q_set):
            self._start_move(self.encoder_zero + self.q_set)

    def _cmd_set_current(self, value: float | int) -> None:
        self.drive_current = self.motor_current = min(int(value), 100)
        if self.drive_current == 0:
            self._set(FLAG_NOT_ENABLED)
        self._apply()

    def _cmd_set_hold_current(self, value: float | int) -> None:
        self.hold_current = min(int(value), 100)
        if self.hold_current == 0:
            self._set(FLAG_NOT_ENABLED)
        self._apply()

    def _cmd_set_max_acceleration(self, value: float | int) -> None:
        # setMaxAcceleration and setMaxDeceleration take the magnitude and write
        # AMAX/DMAX at once, saturated (a running ramp changes its rate).
        self.max_acceleration = float(value)
        self.amax = velocity_mode_acceleration(self.max_acceleration)

    def _cmd_set_max_velocity(self, value: float | int) -> None:
        # setMaxVelocity takes the magnitude and writes VMAX at once: a running
        # move changes its top speed, and so does a SETRPM run (VMAX is its speed).
        self.max_velocity = float(value)
        self.vmax = position_move_limits(self.max_velocity, self.max_acceleration)[0]

    def _cmd_enable_stallguard(self, value: float | int) -> None:
        # Threshold 10 x sensitivity, enabled, STALL cleared; the filter state is kept.
        self.stallguard = True
        self.stall_sensitivity = int(value)
        self._set(FLAG_STALL, False)

    def _cmd_set_brake_mode(self, value: float | int) -> None:
        self.brake_mode = int(value)

    def _cmd_disable_closed_loop(self, value: float | int) -> None:
        self._set(FLAG_NOT_ENABLED)

    def _cmd_stop(self, value: float | int) -> None:
        # setRPM(0) (a ramped stop; qd_set is kept) and BUSY cleared: a running
        # homing sees that at its next poll and ends as aborted.
        self._set_rpm(0.0)
        self._set(FLAG_BUSY, False)

    def _cmd_home_offset(self, value: float | int) -> None:
        self.home_offset = float(value)

    def _cmd_home(self, value: float | int) -> None:
        # NOTHOMED at once, so a reader never takes an old "homed" for the end of this homing.
        self._set(FLAG_NOT_HOMED)
        self._set_flags_for_blocking_handler(Reg.HOME, value)

    def _cmd_no_op(self, value: float | int) -> None:
        """PING, ANGLEMOVED, GETENCODERRPM written, GETDRIVERRPM: nothing to execute."""

    _WRITE_HANDLERS = {
        Reg.SETUP: _cmd_setup,
        Reg.SETRPM: _cmd_set_rpm,
        Reg.MOVESTEPS: _cmd_move_steps,
        Reg.MOVETOANGLE: _cmd_move_to_angle,
        Reg.SETCURRENT: _cmd_set_current,
        Reg.SETHOLDCURRENT: _cmd_set_hold_current,
        Reg.SETMAXACCELERATION: _cmd_set_max_acceleration,
        Reg.SETMAXVELOCITY: _cmd_set_max_velocity,
        Reg.ENABLESTALLGUARD: _cmd_enable_stallguard,
        Reg.SETBRAKEMODE: _cmd_set_brake_mode,
        Reg.DISABLECLOSEDLOOP: _cmd_disable_closed_loop,
        Reg.STOP: _cmd_stop,
        Reg.HOMEOFFSET: _cmd_home_offset,
        Reg.HOME: _cmd_home,
        Reg.PING: _cmd_no_op,
        Reg.ANGLEMOVED: _cmd_no_op,
        Reg.GETENCODERRPM: _cmd_no_op,
        Reg.GETDRIVERRPM: _cmd_no_op,
    }

    # --------------------------------------------------------------- blocking
    def _set_flags_for_blocking_handler(self, reg: int, value: float | int) -> None:
        """BUSY now; the main loop's next pass runs the command (the latest one wins)."""
        self._pending_reg = int(reg)
        self._pending_arg = value
        self._set(FLAG_BUSY)
        self._pending = True

    def _blocking_handler(self) -> None:
        """The main loop takes the pending command: BUSY, then start it."""
        self._pending = False
        self._set(FLAG_BUSY)
        reg, value = self._pending_reg, self._pending_arg
        if reg == Reg.HOME:
            direction, rpm, sensitivity, current = unpack_bytes(int(value))
            self._homing = (1 if direction else -1, float(rpm), sensitivity, current)
            self._hard_stop()
            self._blocking = _Blocking.HOME_SETTLE
            self._blocking_until = self.time + HOMING_SETTLE_S
        elif reg == Reg.CHECKORIENTATION:
            self._blocking_arg = float(value) if math.isfinite(value) else 0.0
            self._blocking = _Blocking.ORIENTATION_OUT
            self._start_move(self.motor.setpoint_deg + self._blocking_arg)
        else:
            self._end_blocking()  # "UNKOWN REGISTER": returns at once

    def _end_blocking(self) -> None:
        self._blocking = _Blocking.NONE
        self._set(FLAG_BUSY, False)

    def _run_blocking(self) -> None:
        """One main-loop tick of the running blocking command."""
        state = self._blocking
        if state is _Blocking.HOME_SETTLE:
            if self.time >= self._blocking_until - 1e-9:
                direction, rpm, _, current = self._homing
                self._set_rpm(direction * rpm)
                self.motor_current = current
                self._blocking = _Blocking.HOME_RUN
                self.poll_homing()  # the first poll comes right after setRPM
        elif state is _Blocking.ORIENTATION_OUT:
            if self.mode is not Mode.POSITION or self._arrived():
                self._blocking = _Blocking.ORIENTATION_BACK
                self._start_move(self.motor.setpoint_deg - self._blocking_arg)
        elif state is _Blocking.ORIENTATION_BACK and (self.mode is not Mode.POSITION or self._arrived()):
            self.mode = Mode.IDLE
            self._end_blocking()

    def poll_homing(self) -> None:
        """One pass of the homing loop (every 1 ms): stop at ``|error| > sensitivity`` or a STOP.

        :meth:`tick` polls ten times a tick between 1 ms motor advances; the
        simulated arm also calls it after each physics step.
        """
        if self._blocking is not _Blocking.HOME_RUN:
            return
        if self.flags & FLAG_BUSY:
            if not abs(self.pid_error) > self._homing[2]:
                return
            self.motor.hold_here()  # encoder and driver zeroed here
            self.encoder_zero = self.motor.position_deg
            self._set(FLAG_NOT_HOMED | FLAG_STALL, False)
        else:  # cancelled by STOP
            self._set(FLAG_NOT_HOMED)
        self._hard_stop()
        self.motor_current = self.drive_current
        self._end_blocking()
        self._apply()

    def _arrived(self) -> bool:
        return self.sp_velocity == 0.0 and abs(self.motor.setpoint_deg - self.target_deg) < 1e-6

    # -------------------------------------------------------------- main loop
    def tick(self) -> None:
        """Run one 10 ms main-loop pass and advance the motor by a tick.

        As the firmware's ``loop()``: stall detection, the blocking handler
        (a running one blocks the pass: no stall detection, no deadman), the
        deadman; the motor's step generator runs meanwhile.
        """
        self.time += TICK_S
        if self._blocking is _Blocking.NONE:
            if self.stallguard and not self.flags & FLAG_STALL:
                self._detect_stall()
            if self._pending:
                self._blocking_handler()
        else:
            self._run_blocking()
        if self._blocking is _Blocking.NONE:
            self._deadman()
        self._ramp()
        if self._blocking is _Blocking.HOME_RUN:
            for i in range(_HOMING_POLLS_PER_TICK):
                self.motor.advance(HOMING_POLL_S)
                self.poll_homing()
                if self._blocking is not _Blocking.HOME_RUN:
                    rest = _HOMING_POLLS_PER_TICK - 1 - i
                    if rest:  # the rest of the tick after the homing returned
                        self.motor.advance(rest * HOMING_POLL_S)
                    break
        else:
            self.motor.advance(TICK_S)

    def _deadman(self) -> None:
        silent_ms = _millis(self.time) - _millis(self.last_rx)
        if silent_ms > DEADMAN_MS and not self.flags & FLAG_NOT_ENABLED and self.qd_set:
            self._set_rpm(0.0)
            self._set(FLAG_NOT_ENABLED)

    def _detect_stall(self) -> None:
        rule = self.stall_rule
        raw = max(abs(self.pid_error), self.motor.pid_jitter_usteps)  # the rotor's jitter (motor.py)
        u, x = rule.filter(raw, self._filter_last, self._filter_x)
        self._filter_x = x
        omega = self.encoder_rpm / STALL_RPM_PER_RAD_S
        threshold = rule.threshold(omega, self.stall_sensitivity)
        stalled = x > threshold
        if self.stall_log is not None:
            set_speed = self.qd_set / STALL_RPM_PER_RAD_S
            self.stall_log.append((self.time, raw, u, x, omega, set_speed, threshold, float(stalled)))
        if stalled:
            self._set(FLAG_STALL)
            self._hard_stop()
            self._filter_x = self._filter_last = 0.0
        else:
            self._filter_last = u

    def _ramp(self) -> None:
        """Advance the ramped set-point velocity (trapezoidal profile)."""
        acc_step = self.amax * TICK_S
        v = self.sp_velocity
        if self.mode is Mode.VELOCITY:
            # The chip runs at VMAX in the direction setRPM chose (SETMAXVELOCITY rewrites VMAX too).
            target = math.copysign(self.vmax, self.target_rpm) if self.target_rpm else 0.0
        elif self.mode is Mode.POSITION:
            remaining = self.target_deg - self.motor.setpoint_deg
            if abs(remaining) < 1e-9 and abs(v) <= acc_step:
                self.sp_velocity = 0.0
                self.mode = Mode.IDLE if self._blocking is _Blocking.NONE else self.mode
                self._apply()
                return
            brake = math.sqrt(2.0 * self.amax * abs(remaining))
            target = math.copysign(min(self.vmax, brake, abs(remaining) / TICK_S), remaining)
        else:
            target = 0.0
        if target > v + acc_step:
            v += acc_step
        elif target < v - acc_step:
            v -= acc_step
        else:
            v = target
        if self.motor_current == 0:
            v = 0.0  # unpowered: the set point follows the rotor
        self.sp_velocity = v
        self._apply()

    def run_until(self, now: float) -> None:
        """Run main-loop ticks until the firmware's time reaches ``now``."""
        while self.time + TICK_S <= now + 1e-12:
            self.tick()


# How ``readValue``/``memcpy`` fill each command's value from the receive
# buffer: ``memcpy(&val, rx_buf, rx_length)`` copies exactly the bytes that
# arrived. Fewer than the value's size leave the rest of the value as it was:
# the previous value for the firmware's static variables (read back from the
# core below), stack garbage for locals (we use zero bytes). SETUP and HOME
# copy fixed bytes of the buffer whatever arrived, so a short one reads stale
# bytes of an earlier transaction. More bytes than the value holds overrun
# memory next to it (undefined; the emulator keeps the value's own bytes).
#: register -> (struct format of the value, previous value of a static, or None for a local)
_READ_VALUE: dict[int, tuple[str, object]] = {
    Reg.SETRPM: ("<f", lambda c: c.qd_set),
    Reg.MOVETOANGLE: ("<f", lambda c: c.q_set),
    Reg.HOMEOFFSET: ("<f", lambda c: c.home_offset),
    # Limits are stored in steps (x 200/360) and converted after the memcpy.
    Reg.SETMAXACCELERATION: ("<f", lambda c: c.max_acceleration * _STEPS_PER_DEG),
    Reg.SETMAXVELOCITY: ("<f", lambda c: c.max_velocity * _STEPS_PER_DEG),
    Reg.SETCURRENT: ("<B", lambda c: c.drive_current),
    Reg.SETHOLDCURRENT: ("<B", lambda c: c.hold_current),
    Reg.MOVESTEPS: ("<i", None),
    Reg.CHECKORIENTATION: ("<f", None),
    Reg.ENABLESTALLGUARD: ("<B", None),
    Reg.SETBRAKEMODE: ("<B", None),
    Reg.DISABLECLOSEDLOOP: ("<B", None),
    Reg.STOP: ("<B", None),
}
#: Registers that answer a value (``writeValue``) whatever was written with them.
_ANSWERING = frozenset({Reg.PING, Reg.ANGLEMOVED, Reg.GETENCODERRPM})


class JointFirmware:
    """One joint's firmware behind its I2C address: bytes in, bytes out.

    Args:
        motor: The motor model (e.g. :class:`~bioscara_gym.hardware.motor.KinematicStepper`).
        clock: Time source; the firmware catches up on its 10 ms ticks to
            ``clock.now()`` before every transaction and on :meth:`update`.
        core: An existing core instead of ``motor`` (the simulated arm's).
        cancel_pending: Passed to a new :class:`FirmwareCore`.
        stall_rule: Passed to a new :class:`FirmwareCore`.
    """

    def __init__(
        self,
        motor: Motor | None,
        clock: Clock,
        core: FirmwareCore | None = None,
        *,
        cancel_pending: bool = True,
        stall_rule: StallRule = FIRMWARE_STALL_RULE,
    ) -> None:
        """Power up a joint in front of ``motor``, or wrap an existing ``core``.

        A core passed in is ticked by its owner (the simulated arm steps
        physics and firmware together), so :meth:`update` leaves it alone.
        """
        if (motor is None) == (core is None):
            raise ValueError("pass either a motor or an existing core")
        self.clock = clock
        self._owns_ticks = core is None
        if core is None:
            core = FirmwareCore(
                motor,  # type: ignore[arg-type]
                clock.now(),
                cancel_pending=cancel_pending,
                stall_rule=stall_rule,
            )
        self.core = core
        self.transactions = 0
        self._power_up_buffers()

    def _power_up_buffers(self) -> None:
        self._reg = 0  # ``uint8_t reg = 0``: a bare read at power-up runs register 0x00
        self._rx_buf = bytearray(MAX_PAYLOAD)
        self._rx_length = 0
        self._tx_buf = bytearray(MAX_PAYLOAD + FLAGS_SIZE)  # ``tx_buf[MAX_BUFFER + RFLAGS_SIZE]``
        self._tx_length = 0

    @property
    def motor(self) -> Motor:
        """The motor model behind the firmware."""
        return self.core.motor

    @property
    def last_register(self) -> int:
        """The register the last write phase named (a bare read runs it again)."""
        return self._reg

    @property
    def flags(self) -> Flag:
        """The flags byte as it stands now."""
        return Flag(self.core.flags)

    def update(self) -> None:
        """Run the main loop up to the clock's current time."""
        if self._owns_ticks:
            self.core.run_until(self.clock.now())

    def power_cycle(self) -> None:
        """Cut and restore the joint's power (HOMEOFFSET and homing are lost)."""
        self.update()
        self.core.power_cycle(self.clock.now())
        self._power_up_buffers()

    def transfer(self, data: bytes, read_len: int) -> bytes:
        """Serve one combined write-then-read transaction.

        The write phase (``receiveEvent``) stores the register and copies the
        payload into the persistent 4-byte receive buffer; the read phase
        (``requestEvent``) runs the stored register's handler on it and
        answers its value (if any) and the flags. No read phase (``read_len``
        0): nothing is executed. No write phase (empty ``data``): the last
        register runs again on the buffer as it stands, and since only the
        write phase (and a blocking command) starts the reply buffer over, a
        register that answers no value answers the previous reply before the
        flags. Like an Arduino Wire slave, a longer read is padded with 0xFF
        and a shorter one is cut.

        Args:
            data: Bytes the master wrote; ``data[0]`` is the register.
            read_len: Bytes the master reads back.

        Returns:
            Exactly ``read_len`` bytes.
        """
        self.update()
        now = self.clock.now()
        self.transactions += 1
        if data:
            self._reg = data[0]
            payload = data[1:]
            self._rx_buf[: len(payload[:MAX_PAYLOAD])] = payload[:MAX_PAYLOAD]
            self._rx_length = len(payload)
            self._tx_length = 0  # receiveEvent: ``tx_length = 0``
        if read_len <= 0:
            return b""
        self._request(now)
        # ``tx_buf[tx_length++] = state``: past the 5-byte buffer (bare reads of a
        # command, again and again) the firmware overwrites what follows it; the
        # emulator answers as if the buffer went on.
        if self._tx_length >= len(self._tx_buf):
            self._tx_buf.extend(bytes(self._tx_length + 1 - len(self._tx_buf)))
        self._tx_buf[self._tx_length] = self.core.flags
        self._tx_length += 1
        reply = bytes(self._tx_buf[: self._tx_length])
        if read_len <= len(reply):
            return reply[:read_len]
        return reply + b"\xff" * (read_len - len(reply))

    def _request(self, now: float) -> None:
        """``requestEvent``: the stored register's handler; a value it answers goes to the reply buffer."""
        core, reg = self.core, self._reg
        if reg in _ANSWERING:
            self._answer(codec.encode(Reg(reg), core.read(reg, now)))
        elif reg == Reg.HOMEOFFSET and not self._rx_length:
            self._answer(codec.encode(Reg.HOMEOFFSET, core.read(reg, now)))
        elif reg == Reg.GETDRIVERRPM:
            core.touch(now)
        else:
            core.write(reg, self._read_value(reg), now)
            if reg == Reg.HOME or reg not in NON_BLOCKING_REGISTERS:
                self._tx_length = 0  # set_flags_for_blocking_handler: ``tx_length = 0``

    def _answer(self, value: bytes) -> None:
        """``writeValue``: the reply buffer starts over with ``value``."""
        self._tx_buf[: len(value)] = value
        self._tx_length = len(value)

    def _read_value(self, reg: int) -> float | int:
        """The value the firmware's handler ``memcpy``'s out of the receive buffer."""
        spec = _READ_VALUE.get(reg)
        if spec is None:  # SETUP, HOME, unknown registers: the whole buffer, stale bytes included
            return int.from_bytes(self._rx_buf, "little")
        fmt, previous = spec
        size = struct.calcsize(fmt)
        old = struct.pack(fmt, previous(self.core)) if previous is not None else bytes(size)
        n = min(self._rx_length, size)
        return struct.unpack(fmt, bytes(self._rx_buf[:n]) + old[n:])[0]
