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

Units inside the firmware are the motor's: degrees, deg/s, RPM. The firmware
and its documentation do not name the PID error's unit; we read it as 1/16
microsteps (3200 per revolution). That is the reading under which the arm's own parameters are
coherent: homing thresholds of 25-50 are 1.6-3 full steps, just past the
stepper's pull-out lag of one full step, so homing trips when the motor slips
against the end stop, and stall thresholds of 60-150 (3.75-9.4 full steps)
trip on lost steps, never on the lag of normal motion. In 1/256 microsteps
the same numbers would trip during ordinary acceleration.
"""

from __future__ import annotations

import math
from enum import Enum

from bioscara_gym.hardware import codec
from bioscara_gym.hardware.clock import Clock
from bioscara_gym.hardware.codec import unpack_bytes
from bioscara_gym.hardware.motor import FULL_STEP_DEG, Motor
from bioscara_gym.hardware.registers import (
    ACK,
    BLOCKING_COMMANDS,
    DEADMAN_S,
    FLAG_BUSY,
    FLAG_MASK,
    FLAG_NOT_ENABLED,
    FLAG_NOT_HOMED,
    FLAG_STALL,
    HOMING_SETTLE_S,
    MAX_PAYLOAD,
    POWER_UP_FLAGS,
    READ_REGISTERS,
    STALL_MID_SPEED_BAND,
    STALL_MID_SPEED_OFFSET,
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
    # Timings re-exported for older imports; their home is registers.
    "DEADMAN_S",
    "HOMING_SETTLE_S",
    "MICROSTEPS_PER_DEG",
    "MICROSTEPS_PER_FULL_STEP",
    "TICK_S",
    "FirmwareCore",
    "JointFirmware",
    "Mode",
    "stall_threshold",
]

#: PID-error units per full step: 1/16 microsteps (our reading, see the module docstring).
MICROSTEPS_PER_FULL_STEP = 16
#: PID-error units (1/16 microsteps) per motor degree: 200 full steps x 16 per turn.
MICROSTEPS_PER_DEG = MICROSTEPS_PER_FULL_STEP / FULL_STEP_DEG
#: Defaults before the host sets limits (not documented; our choice).
DEFAULT_MAX_VELOCITY_DPS = 1000.0
DEFAULT_MAX_ACCELERATION_DPS2 = 2000.0
DEFAULT_CURRENT_PCT = 0

_LOWPASS_GAIN = TICK_S / STALL_TAU_S
_LOWPASS_KEEP = 1.0 - _LOWPASS_GAIN
_RAD_PER_DEG = math.pi / 180.0


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
    UNKNOWN = 5


def stall_threshold(omega_rad_s: float, sensitivity: int) -> float:
    """Speed-adaptive stall threshold in microsteps, as the stall detector uses it.

    Args:
        omega_rad_s: Measured motor speed in rad/s.
        sensitivity: The ENABLESTALLGUARD payload (threshold is 10x it).

    Returns:
        ``slope*|omega| + 10*sensitivity``, plus 90 inside 12-450 rad/s
        (the constants of :mod:`~bioscara_gym.hardware.registers`).
    """
    w = abs(omega_rad_s)
    threshold = STALL_SLOPE * w + STALL_THRESHOLD_PER_SENSITIVITY * sensitivity
    lo, hi = STALL_MID_SPEED_BAND
    if lo <= w <= hi:
        threshold += STALL_MID_SPEED_OFFSET
    return threshold


class FirmwareCore:
    """State and rules of one joint's firmware, independent of the bus.

    Args:
        motor: The motor model the firmware drives.
        start_time: Time of power-up in seconds (for the deadman).
    """

    def __init__(self, motor: Motor, start_time: float = 0.0) -> None:
        """Power the firmware up in front of ``motor``."""
        self.motor = motor
        self.power_cycle(start_time)

    # ------------------------------------------------------------------ state
    def power_cycle(self, now: float = 0.0) -> None:
        """Cut and restore power: flags, offset, encoder zero and limits reset.

        The motor keeps its physical position; the encoder counts from there.
        """
        self.flags = int(POWER_UP_FLAGS)
        self.time = now
        self.last_rx = now
        self.drive_current = DEFAULT_CURRENT_PCT
        self.hold_current = DEFAULT_CURRENT_PCT
        self.brake_mode = 0
        self.max_velocity = DEFAULT_MAX_VELOCITY_DPS
        self.max_acceleration = DEFAULT_MAX_ACCELERATION_DPS2
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
        self._blocking = _Blocking.NONE
        self._blocking_reg = Reg.NONE
        self._blocking_arg = 0.0
        self._blocking_until = 0.0
        self._homing = (1, 0.0, 0, 0)  # direction, rpm, sensitivity, current
        self._sent = (0.0, 0.0)  # last (velocity, torque) sent to the motor
        self.motor.command(0.0, 0.0)
        self.motor.hold_here()

    def snapshot(self) -> dict[str, object]:
        """The firmware's state (everything but the motor), for :meth:`restore`."""
        return {k: v for k, v in vars(self).items() if k != "motor"}

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
        """Whether a blocking command is running."""
        return self._blocking is not _Blocking.NONE

    # --------------------------------------------------------------- commands
    def write(self, reg: int, value: float | int, now: float) -> None:
        """Handle a command the way the firmware's receive/request ISRs do.

        Non-blocking commands take effect at once; blocking ones (HOME,
        CHECKORIENTATION, anything unknown) set BUSY now and run in the main
        loop.

        Args:
            reg: Register byte.
            value: Decoded payload (0 where the register has none).
            now: Time of the transaction in seconds.
        """
        self.last_rx = now
        handler = self._WRITE_HANDLERS.get(reg)
        if handler is None:
            self._start_blocking(reg, value)
        else:
            handler(self, value)

    def read(self, reg: int, now: float) -> float | int | None:
        """Answer a read request; ``None`` for registers without a payload."""
        self.last_rx = now
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
        """Record a transaction that carried no command (feeds the deadman)."""
        self.last_rx = now

    def _may_move(self) -> bool:
        return not self.flags & (FLAG_STALL | FLAG_NOT_ENABLED)

    def _hard_stop(self) -> None:
        self.mode = Mode.IDLE
        self.target_rpm = 0.0
        self.sp_velocity = 0.0
        self.motor.hold_here()
        self._apply()

    def _apply(self) -> None:
        """Send the current set-point velocity and torque to the motor."""
        if self.flags & FLAG_NOT_ENABLED and self.drive_current == 0:
            torque = 0.0
        elif self._blocking is _Blocking.HOME_RUN:
            torque = self._homing[3] / 100.0
        elif self.sp_velocity == 0.0 and self.mode is Mode.IDLE:
            torque = self.hold_current / 100.0
        else:
            torque = self.drive_current / 100.0
        sent = (self.sp_velocity, torque)
        if sent != self._sent or torque <= 0.0:  # unpowered motors re-follow their rotor
            self._sent = sent
            self.motor.command(*sent)

    def _cmd_setup(self, value: float | int) -> None:
        drive, hold, _, _ = unpack_bytes(int(value))
        self.drive_current = min(drive, 100)
        self.hold_current = min(hold, 100)
        self.stallguard = False
        self._set(FLAG_STALL | FLAG_NOT_ENABLED, False)
        self._hard_stop()

    def _cmd_set_rpm(self, value: float | int) -> None:
        if not self._may_move() or self.flags & FLAG_NOT_HOMED or self.busy:
            return
        self.mode = Mode.VELOCITY
        self.target_rpm = float(value)

    def _cmd_move_steps(self, value: float | int) -> None:
        if not self._may_move() or self.busy:
            return
        self.mode = Mode.POSITION
        self.target_deg = self.motor.setpoint_deg + steps_to_degrees(int(value))

    def _cmd_move_to_angle(self, value: float | int) -> None:
        if not self._may_move() or self.flags & FLAG_NOT_HOMED or self.busy:
            return
        self.mode = Mode.POSITION
        self.target_deg = self.encoder_zero + float(value)

    def _cmd_set_current(self, value: float | int) -> None:
        self.drive_current = min(int(value), 100)
        if self.drive_current == 0:
            self._set(FLAG_NOT_ENABLED)
        self._apply()

    def _cmd_set_hold_current(self, value: float | int) -> None:
        self.hold_current = min(int(value), 100)
        if self.hold_current == 0:
            self._set(FLAG_NOT_ENABLED)
        self._apply()

    def _cmd_set_max_acceleration(self, value: float | int) -> None:
        if math.isfinite(value) and value > 0:
            self.max_acceleration = float(value)

    def _cmd_set_max_velocity(self, value: float | int) -> None:
        if math.isfinite(value) and value > 0:
            self.max_velocity = float(value)

    def _cmd_enable_stallguard(self, value: float | int) -> None:
        self.stallguard = True
        self.stall_sensitivity = int(value)
        self._filter_x = self._filter_last = 0.0
        self._set(FLAG_STALL, False)

    def _cmd_set_brake_mode(self, value: float | int) -> None:
        self.brake_mode = int(value)

    def _cmd_disable_closed_loop(self, value: float | int) -> None:
        self._set(FLAG_NOT_ENABLED)

    def _cmd_stop(self, value: float | int) -> None:
        if self._blocking in (_Blocking.HOME_SETTLE, _Blocking.HOME_RUN):
            self._set(FLAG_NOT_HOMED)  # homing ends as aborted
        self._end_blocking()
        self._hard_stop()

    def _cmd_home_offset(self, value: float | int) -> None:
        self.home_offset = float(value)

    def _cmd_read_only(self, value: float | int) -> None:
        """A read register written with a payload: the firmware ignores it."""

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
        Reg.PING: _cmd_read_only,
        Reg.ANGLEMOVED: _cmd_read_only,
        Reg.GETENCODERRPM: _cmd_read_only,
    }

    # --------------------------------------------------------------- blocking
    def _start_blocking(self, reg: int, value: float | int) -> None:
        """``set_flags_for_blocking_handler``: BUSY now, work in the main loop."""
        self._set(FLAG_BUSY)
        self._blocking_reg = reg
        self._blocking_arg = value
        if reg == Reg.HOME:
            self._set(FLAG_NOT_HOMED)
            direction, rpm, sensitivity, current = unpack_bytes(int(value))
            self._homing = (1 if direction == 1 else -1, float(rpm), sensitivity, current)
            self._blocking = _Blocking.HOME_SETTLE
            self._blocking_until = math.inf  # set when the main loop picks it up
        elif reg == Reg.CHECKORIENTATION:
            self._blocking = _Blocking.ORIENTATION_OUT
            self._blocking_until = math.inf
        else:
            self._blocking = _Blocking.UNKNOWN

    def _end_blocking(self) -> None:
        self._blocking = _Blocking.NONE
        self._blocking_reg = Reg.NONE
        self._set(FLAG_BUSY, False)

    def _run_blocking(self) -> None:
        """One main-loop tick of the running blocking command."""
        state = self._blocking
        if state is _Blocking.UNKNOWN:
            self._end_blocking()
        elif state is _Blocking.HOME_SETTLE:
            if self._blocking_until == math.inf:
                self._hard_stop()
                self._blocking_until = self.time + HOMING_SETTLE_S
            elif self.time >= self._blocking_until - 1e-9:
                direction, rpm, _, _ = self._homing
                self._blocking = _Blocking.HOME_RUN
                self.mode = Mode.VELOCITY
                self.target_rpm = direction * rpm
        elif state is _Blocking.HOME_RUN:
            if abs(self.pid_error) > self._homing[2]:
                self.motor.hold_here()
                self.encoder_zero = self.motor.position_deg
                self._set(FLAG_NOT_HOMED | FLAG_STALL, False)
                self._end_blocking()
                self._hard_stop()
        elif state is _Blocking.ORIENTATION_OUT:
            if self._blocking_until == math.inf:
                self._blocking_until = 0.0
                self.mode = Mode.POSITION
                self.target_deg = self.motor.setpoint_deg + float(self._blocking_arg)
            elif self.mode is Mode.IDLE or self._arrived():
                self._blocking = _Blocking.ORIENTATION_BACK
                self.target_deg -= float(self._blocking_arg)
                self.mode = Mode.POSITION
        elif state is _Blocking.ORIENTATION_BACK and (self.mode is Mode.IDLE or self._arrived()):
            self.mode = Mode.IDLE
            self._end_blocking()

    def _arrived(self) -> bool:
        return self.sp_velocity == 0.0 and abs(self.motor.setpoint_deg - self.target_deg) < 1e-6

    # -------------------------------------------------------------- main loop
    def tick(self) -> None:
        """Run one 10 ms main-loop iteration and advance the motor by a tick.

        Order as in the firmware's ``loop()``: deadman and stall detection
        (skipped while a blocking command runs, since it blocks the loop), the
        blocking handler, then the step generator.
        """
        self.time += TICK_S
        if self._blocking is _Blocking.NONE:
            if (
                self.mode is Mode.VELOCITY
                and self.target_rpm != 0.0
                and not self.flags & FLAG_NOT_ENABLED
                and self.time - self.last_rx > DEADMAN_S + 1e-9
            ):
                self.target_rpm = 0.0
                self._set(FLAG_NOT_ENABLED)
            if self.stallguard and not self.flags & FLAG_STALL:
                self._detect_stall()
        else:
            self._run_blocking()
        self._ramp()
        self.motor.advance(TICK_S)

    def _detect_stall(self) -> None:
        u = abs(self.pid_error)
        last = self._filter_last
        self._filter_last = u
        if abs(u - last) > STALL_SPIKE_LIMIT:
            u = last  # spike filter: keep the previous sample
        x = self._filter_x = _LOWPASS_KEEP * self._filter_x + _LOWPASS_GAIN * u
        if x > stall_threshold(self.motor.velocity_dps * _RAD_PER_DEG, self.stall_sensitivity):
            self._set(FLAG_STALL)
            self._filter_x = self._filter_last = 0.0
            self._hard_stop()

    def _ramp(self) -> None:
        """Advance the ramped set-point velocity (trapezoidal profile)."""
        acc_step = self.max_acceleration * TICK_S
        v = self.sp_velocity
        if self.mode is Mode.VELOCITY:
            target = self.target_rpm * 6.0
            if self._blocking is not _Blocking.HOME_RUN:
                target = max(-self.max_velocity, min(self.max_velocity, target))
        elif self.mode is Mode.POSITION:
            remaining = self.target_deg - self.motor.setpoint_deg
            if abs(remaining) < 1e-9 and abs(v) <= acc_step:
                self.sp_velocity = 0.0
                self.mode = Mode.IDLE if self._blocking is _Blocking.NONE else self.mode
                self._apply()
                return
            brake = math.sqrt(2.0 * self.max_acceleration * abs(remaining))
            target = math.copysign(min(self.max_velocity, brake, abs(remaining) / TICK_S), remaining)
        else:
            target = 0.0
        if target > v + acc_step:
            v += acc_step
        elif target < v - acc_step:
            v -= acc_step
        else:
            v = target
        if self.flags & FLAG_NOT_ENABLED and self.drive_current == 0:
            v = 0.0
        self.sp_velocity = v
        self._apply()

    def run_until(self, now: float) -> None:
        """Run main-loop ticks until the firmware's time reaches ``now``."""
        while self.time + TICK_S <= now + 1e-12:
            self.tick()


class JointFirmware:
    """One joint's firmware behind its I2C address: bytes in, bytes out.

    Args:
        motor: The motor model (e.g. :class:`~bioscara_gym.hardware.motor.KinematicStepper`).
        clock: Time source; the firmware catches up on its 10 ms ticks to
            ``clock.now()`` before every transaction and on :meth:`update`.
    """

    def __init__(self, motor: Motor | None, clock: Clock, core: FirmwareCore | None = None) -> None:
        """Power up a joint in front of ``motor``, or wrap an existing ``core``.

        A core passed in is ticked by its owner (the simulated arm steps
        physics and firmware together), so :meth:`update` leaves it alone.
        """
        if (motor is None) == (core is None):
            raise ValueError("pass either a motor or an existing core")
        self.clock = clock
        self._owns_ticks = core is None
        self.core = core if core is not None else FirmwareCore(motor, clock.now())
        self.transactions = 0

    @property
    def motor(self) -> Motor:
        """The motor model behind the firmware."""
        return self.core.motor

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

    def transfer(self, data: bytes, read_len: int) -> bytes:
        """Serve one combined write-then-read transaction.

        ``receiveEvent`` takes the register and up to four payload bytes (more
        are dropped, fewer are zero-padded as ``memcpy`` into a zeroed value
        would leave them); ``requestEvent`` answers the payload of a read
        register followed by the flags. Like an Arduino Wire slave, a longer
        read is padded with 0xFF and a shorter one is cut.

        Args:
            data: Bytes the master wrote; ``data[0]`` is the register.
            read_len: Bytes the master reads back.

        Returns:
            Exactly ``read_len`` bytes.
        """
        self.update()
        now = self.clock.now()
        self.transactions += 1
        core = self.core
        tx = b""
        if not data:
            core.touch(now)
        else:
            reg = data[0]
            payload = data[1 : 1 + MAX_PAYLOAD]
            if len(data) == 1 and reg in READ_REGISTERS:
                tx = codec.encode(Reg(reg), core.read(reg, now))
            elif len(data) == 1 and reg not in BLOCKING_COMMANDS and reg in _KNOWN:
                core.touch(now)  # a known command without payload: nothing to do
            else:
                core.write(reg, _decode(reg, payload), now)
        reply = tx + bytes((core.flags,))
        if read_len <= len(reply):
            return reply[:read_len]
        return reply + b"\xff" * (read_len - len(reply))


_KNOWN = frozenset(int(r) for r in Reg if r is not Reg.NONE)  # NONE is host-only


def _decode(reg: int, payload: bytes) -> float | int:
    """Decode a payload as the firmware's ``readValue`` (memcpy into a zeroed value) would."""
    size = codec.payload_size(reg)
    value = codec.decode(reg, (payload + bytes(size))[:size])
    if isinstance(value, float) and not math.isfinite(value):
        return 0.0
    return value
