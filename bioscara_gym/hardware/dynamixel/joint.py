"""A joint driven by a Dynamixel XL430 servo, behind the same :class:`BaseJoint` API.

How the Bioscara joint's API maps onto the servo (``docs/dynamixel.md``):

================================ =============================================
``init()``                        PING with retries (5 tries, as the MH5), read
                                  Torque Enable, Hardware Error Status and the
                                  Operating Mode
``enable(drive, hold)``           Torque Enable := 1 (the currents are checked
                                  but an XL430 has no current setting)
``disable()``                     Torque Enable := 0
``set_position(q)``               Goal Position (position mode)
``set_velocity(v)``               Goal Velocity (velocity mode; switching mode
                                  turns torque off and on again, as the servo
                                  requires)
``get_position/get_velocity()``   Present Position / Present Velocity, or the
                                  ``pvl_reader`` loop's values while the bus
                                  runs its sync loops
``set_max_velocity/acceleration`` Profile Velocity / Profile Acceleration
``stop()``                        hold the present position (velocity 0)
``move_steps(n)``                 a relative move of ``n`` position units
``home()`` and friends            no motion: the servo's encoder is absolute,
                                  the joint is always homed
``reboot()``                      REBOOT (clears a hardware error; torque off)
================================ =============================================

The flags are the Bioscara's, derived from the servo: NOT_ENABLED while
torque is off, STALL while the Hardware Error Status is not 0 (every status
packet's Alert bit says so; an overload turns torque off as well), never
NOT_HOMED or BUSY. Positions follow the MH5:
``q = ((raw - 2047) * 0.001533980787886) / reduction + offset``.
"""

from __future__ import annotations

import math

from bioscara_gym.hardware.base_joint import BaseJoint
from bioscara_gym.hardware.clock import Clock
from bioscara_gym.hardware.dynamixel.bus import DynamixelBus
from bioscara_gym.hardware.dynamixel.control_table import (
    ACCELERATION_RADS2_PER_UNIT,
    ADDR_GOAL_POSITION,
    ADDR_GOAL_VELOCITY,
    ADDR_OPERATING_MODE,
    ADDR_PRESENT_POSITION,
    ADDR_PRESENT_VELOCITY,
    ADDR_PROFILE_ACCELERATION,
    ADDR_PROFILE_VELOCITY,
    ADDR_TORQUE_ENABLE,
    ALERT,
    MODEL_NUMBER,
    PING_TRIES,
    REBOOT_S,
    STATUS_LENGTH,
    STATUS_START,
    HardwareError,
    OperatingMode,
    effort_from_raw,
    position_from_raw,
    position_to_raw,
    temperature_from_raw,
    to_unsigned,
    velocity_from_raw,
    velocity_to_raw,
    voltage_from_raw,
)
from bioscara_gym.hardware.errors import (
    CommError,
    InvalidArgumentError,
    JointError,
    NotEnabledError,
    StalledError,
)
from bioscara_gym.hardware.registers import FLAG_NOT_ENABLED, FLAG_STALL, BrakeMode, Flag, Reg
from bioscara_gym.hardware.stats import CommStats

#: Flags of a servo with torque off and no hardware error.
_TORQUE_OFF = FLAG_NOT_ENABLED
#: How long the pvl_reader's values count as current, in loop periods.
_FRESH_PERIODS = 3.0


class DynamixelJoint(BaseJoint):
    """One joint on a Dynamixel servo (XL430-W250, protocol 2.0).

    Args:
        name: Joint name.
        dxl_id: The servo's ID (0-252).
        bus: The host-side bus (shared by the servos on one port).
        reduction: Servo turns per joint unit (1.0: the servo is the joint);
            negative reverses the direction.
        min: Lower joint limit (rad or m).
        max: Upper joint limit (rad or m).
        offset: Joint position at the servo's centre (raw 2047), rad or m (the MH5's offset).
        clock: Time source (waits after REBOOT).
    """

    has_field = False  # it closes its own loop: no field to run away from the rotor

    def __init__(
        self,
        name: str,
        dxl_id: int,
        bus: DynamixelBus,
        reduction: float = 1.0,
        min: float = -math.pi,  # noqa: A002 - the C++ API's parameter name
        max: float = math.pi,  # noqa: A002
        offset: float = 0.0,
        clock: Clock | None = None,
    ) -> None:
        """Create the driver; nothing is sent before :meth:`init`."""
        super().__init__(name, reduction, min, max, clock if clock is not None else bus.clock)
        if isinstance(dxl_id, bool) or not isinstance(dxl_id, int) or not 0 <= dxl_id <= 252:
            raise InvalidArgumentError(f"Dynamixel ID {dxl_id!r} must be 0-252", joint=name)
        if not math.isfinite(offset):
            raise InvalidArgumentError(f"offset {offset} must be finite", joint=name)
        self.dxl_id = dxl_id
        self.bus = bus
        self.offset = float(offset)
        self._offset_known = True
        self.stats = CommStats()
        self.mode = OperatingMode.POSITION
        self.hardware_error = 0
        self.model_number: int | None = None
        # values of the sync loops (raw), and when the pvl_reader last saw them
        self.load_raw = 0
        self.velocity_raw = 0
        self.position_raw = 2047
        self.voltage_raw = 0
        self.temperature_raw = 0
        self._pvl_at: float | None = None
        # the pv_writer's command block: goal velocity, profile acc., profile vel., goal position
        self._goal_velocity = 0
        self._profile_acceleration = 0
        self._profile_velocity = 0
        self._goal_position = 2047
        self._pv_pending = False
        self._torque_request: bool | None = None
        bus.attach(self)

    # ------------------------------------------------------------ status
    def note_status(self, error: int) -> None:
        """Take the Alert bit of a status packet: a hardware error means STALL and torque off."""
        if error & ALERT:
            self._flags |= FLAG_STALL | FLAG_NOT_ENABLED
        elif self._flags & FLAG_STALL:
            self._flags &= ~FLAG_STALL  # the error was cleared (REBOOT)

    def cache_pvl(self, load: int, velocity: int, position: int, now: float) -> None:
        """Values of one ``pvl_reader`` run (raw)."""
        self.load_raw, self.velocity_raw, self.position_raw = load, velocity, position
        self._pvl_at = now

    def cache_tv(self, voltage: int, temperature: int) -> None:
        """Values of one ``tv_reader`` run (raw)."""
        self.voltage_raw, self.temperature_raw = voltage, temperature

    def _fresh(self) -> bool:
        """Whether the bus runs its loops and the ``pvl_reader`` values are recent."""
        if not self.bus.synced or self._pvl_at is None:
            return False
        period = self.bus.loops["pvl_reader"].period_s
        return self.clock.now() - self._pvl_at <= _FRESH_PERIODS * period

    def has_pv_command(self) -> bool:
        """Whether a command waits for the ``pv_writer``."""
        return self._pv_pending

    def take_pv_command(self) -> bytes:
        """The 16-byte block 104-119 for the ``pv_writer``; clears the pending flag."""
        self._pv_pending = False
        return b"".join(
            to_unsigned(v, 4).to_bytes(4, "little")
            for v in (
                self._goal_velocity,
                self._profile_acceleration,
                self._profile_velocity,
                self._goal_position,
            )
        )

    def has_torque_request(self) -> bool:
        """Whether a torque change waits for the ``t_writer``."""
        return self._torque_request is not None

    def take_torque_request(self) -> bytes:
        """Torque Enable for the ``t_writer``; the flags follow at once (the MH5's active command)."""
        on = bool(self._torque_request)
        self._torque_request = None
        self._flags = (self._flags & ~FLAG_NOT_ENABLED) if on else (self._flags | FLAG_NOT_ENABLED)
        return bytes((int(on),))

    def request_torque(self, on: bool) -> None:
        """Ask the ``t_writer`` loop to switch torque (asynchronous, as the MH5's torque controller)."""
        self._require_init()
        self._torque_request = bool(on)

    # ------------------------------------------------------------ primitives
    def _command(self, reg: Reg, value: float | int) -> int:
        raise JointError(f"{reg.name}: a Dynamixel joint has no Bioscara registers", joint=self.name)

    def _query(self, reg: Reg) -> tuple[float | int, int]:
        raise JointError(f"{reg.name}: a Dynamixel joint has no Bioscara registers", joint=self.name)

    def _write(self, address: int, size: int, value: int) -> int:
        self._require_init()
        return self.bus.write(self, address, size, value)

    def _read(self, address: int, size: int, signed: bool = False) -> int:
        self._require_init()
        return self.bus.read(self, address, size, signed)

    def _to_raw(self, q: float) -> int:
        return position_to_raw((q - self.offset) * self.reduction)

    def _from_raw(self, raw: int) -> float:
        return position_from_raw(raw) / self.reduction + self.offset

    # ------------------------------------------------------------ lifecycle
    def _init(self) -> None:
        """Open the port, PING (5 tries), then read torque, hardware error and operating mode.

        Raises:
            CommError: No answer, or the servo is not an XL430-W250.
        """
        self.bus.open()
        self.model_number = self.bus.ping(self, tries=PING_TRIES)
        if self.model_number != MODEL_NUMBER:
            raise CommError(
                f"ID {self.dxl_id} is model {self.model_number}, expected XL430-W250 ({MODEL_NUMBER})",
                joint=self.name,
            )
        self._initialized = True
        try:
            self.get_flags()
            self.mode = self._read_mode()
            self._goal_position = self._read(ADDR_PRESENT_POSITION, 4, signed=True)
            profile = self.bus.read_block(self, ADDR_PROFILE_ACCELERATION, 8)
            self._profile_acceleration = int.from_bytes(profile[:4], "little")
            self._profile_velocity = int.from_bytes(profile[4:], "little")
        except BaseException:
            self._initialized = False
            raise

    def _read_mode(self) -> OperatingMode:
        """Read the Operating Mode.

        Raises:
            CommError: A value an XL430-W250 does not have (1, 3, 4, 16), naming the joint.
        """
        raw = self._read(ADDR_OPERATING_MODE, 1)
        try:
            return OperatingMode(raw)
        except ValueError:
            known = ", ".join(f"{m.value} ({m.name.lower().replace('_', ' ')})" for m in OperatingMode)
            raise CommError(
                f"the servo reports Operating Mode {raw}, which an XL430-W250 does not have ({known})",
                joint=self.name,
            ) from None

    def get_flags(self) -> Flag:
        """Read Torque Enable and Hardware Error Status (64-70) and return the flags."""
        self._require_init()
        block = self.bus.read_block(self, STATUS_START, STATUS_LENGTH)
        torque, self.hardware_error = block[0], block[STATUS_LENGTH - 1]
        flags = 0 if torque else FLAG_NOT_ENABLED
        if self.hardware_error:
            flags |= FLAG_STALL
        self._flags = flags
        return Flag(flags)

    def enable(self, drive_current: int, hold_current: int) -> None:
        """Torque on. The currents are checked (0-100) but an XL430 has no current setting.

        Raises:
            NotEnabledError: The servo kept torque off: it has a hardware error
                (``reboot()`` clears it) or did not take the write.
        """
        self._check_percent("drive current", drive_current)
        self._check_percent("hold current", hold_current)
        self._write(ADDR_TORQUE_ENABLE, 1, 1)
        flags = self.get_flags()
        if flags & Flag.NOT_ENABLED:
            why = (
                f"hardware error {HardwareError(self.hardware_error)!r}; reboot the joint to clear it"
                if self.hardware_error
                else "the servo kept torque off"
            )
            raise NotEnabledError(f"failed to enable: {why}", joint=self.name)
        self._goal_position = self._read(ADDR_GOAL_POSITION, 4, signed=True)

    def disable(self) -> None:
        """Torque off: the servo is back-drivable."""
        self._torque_request = None
        self._pv_pending = False
        self._write(ADDR_TORQUE_ENABLE, 1, 0)
        self._flags |= FLAG_NOT_ENABLED

    def reboot(self) -> None:
        """REBOOT the servo (clears a hardware error; torque comes back off), then PING until it answers."""
        self._require_init()
        self.bus.reboot(self)
        self.clock.sleep(REBOOT_S)
        self.bus.ping(self, tries=PING_TRIES)
        self.get_flags()
        self.mode = self._read_mode()
        self._pv_pending = False
        self._torque_request = None

    # ------------------------------------------------------------ homing: the encoder is absolute
    def start_homing(self, velocity: float, sensitivity: int, current: int) -> None:
        """No motion: the servo's encoder is absolute, so the joint is homed already.

        The arguments are checked as far as they mean anything here (a
        non-zero finite velocity, sensitivity 0-255, current 0-100), then the
        joint must be enabled; :meth:`post_homing` finishes at once.
        """
        velocity = self._check_finite("homing velocity", velocity)
        if velocity == 0.0:
            raise InvalidArgumentError("homing velocity must be non-zero", joint=self.name)
        self._check_sensitivity("homing sensitivity", sensitivity)
        self._check_percent("homing current", current)
        self._require_enabled()
        self._current_b_cmd = Reg.HOME

    def adopt_homing(self, velocity: float) -> None:
        """Nothing to adopt: a Dynamixel joint never homes."""
        self._require_init()
        self._current_b_cmd = Reg.HOME

    def post_homing(self) -> None:
        """Finish a (motionless) homing; the offset stays the configured one."""
        self._current_b_cmd = Reg.NONE
        self.get_flags()

    def home(self, velocity: float, sensitivity: int, current: int, timeout_s: float | None = 600.0) -> None:
        """:meth:`start_homing` then :meth:`post_homing`: nothing moves."""
        self.start_homing(velocity, sensitivity, current)
        self.post_homing()

    def check_orientation(self, angle: float = 2.0, timeout_s: float | None = 10.0) -> None:
        """Nothing to check: the servo's direction is its Drive Mode. Refreshes the flags."""
        self._check_finite("orientation angle", angle)
        self._require_enabled()
        self.get_flags()

    # ------------------------------------------------------------ motion
    def _check_motion_reply(self) -> None:
        if self._flags & FLAG_STALL:
            raise StalledError(
                f"hardware error {HardwareError(self.hardware_error or HardwareError.OVERLOAD)!r}; "
                "reboot the joint to clear it",
                joint=self.name,
            )
        if self._flags & FLAG_NOT_ENABLED:
            raise NotEnabledError("the servo reports torque off; enable it", joint=self.name)

    def _require_enabled(self) -> None:
        """Refuse before any traffic: a hardware error first (torque is off then too), then torque off."""
        self._require_init()
        if self._flags & FLAG_STALL:
            self._check_motion_reply()
        super()._require_enabled()

    def _set_mode(self, mode: OperatingMode) -> None:
        """Switch the Operating Mode; EEPROM, so torque goes off for the write and on again."""
        if self.mode == mode:
            return
        self._write(ADDR_TORQUE_ENABLE, 1, 0)
        self._write(ADDR_OPERATING_MODE, 1, int(mode))
        self.mode = mode
        self._write(ADDR_TORQUE_ENABLE, 1, 1)
        self._check_motion_reply()

    def get_position(self) -> float:
        """Joint position (rad or m) from Present Position."""
        raw = self.position_raw if self._fresh() else self._read(ADDR_PRESENT_POSITION, 4, signed=True)
        self.position_raw = raw
        return self._from_raw(raw)

    def get_velocity(self) -> float:
        """Joint velocity (rad/s or m/s) from Present Velocity."""
        raw = self.velocity_raw if self._fresh() else self._read(ADDR_PRESENT_VELOCITY, 4, signed=True)
        self.velocity_raw = raw
        return velocity_from_raw(raw) / self.reduction

    def get_effort(self) -> float:
        """Servo torque, N*m, from the last Present Load (the ``pvl_reader``'s)."""
        return effort_from_raw(self.load_raw)

    def get_voltage(self) -> float:
        """Supply voltage, V, from the last ``tv_reader`` run."""
        return voltage_from_raw(self.voltage_raw)

    def get_temperature(self) -> float:
        """Servo temperature, deg C, from the last ``tv_reader`` run."""
        return temperature_from_raw(self.temperature_raw)

    def set_position(self, pos: float) -> None:
        """Move to ``pos`` (rad or m) with the profile velocity and acceleration.

        Raises:
            NotEnabledError: Torque is off (refused before any traffic).
            StalledError: The servo reports a hardware error.
            InvalidArgumentError: ``pos`` is not finite, or beyond the servo's range.
        """
        pos = self._check_finite("position", pos)
        self._require_enabled()
        raw = self._to_raw(pos)
        if not 0 <= raw <= 4095:
            raise InvalidArgumentError(f"position {pos:g} is outside the servo's range", joint=self.name)
        self._set_mode(OperatingMode.POSITION)
        self._goal_position, self._goal_velocity = raw, 0
        if self.bus.synced:
            self._pv_pending = True
            self._check_motion_reply()
            return
        self._write(ADDR_GOAL_POSITION, 4, raw)
        self._check_motion_reply()

    def set_velocity(self, vel: float) -> None:
        """Run at ``vel`` (rad/s or m/s) in velocity mode (no deadman: it runs until told otherwise).

        Raises:
            NotEnabledError: Torque is off (refused before any traffic).
            StalledError: The servo reports a hardware error.
            InvalidArgumentError: ``vel`` is not finite.
        """
        vel = self._check_finite("velocity", vel)
        self._require_enabled()
        raw = velocity_to_raw(vel * self.reduction)
        self._set_mode(OperatingMode.VELOCITY)
        self._goal_velocity = raw
        if self.bus.synced:
            self._pv_pending = True
            self._check_motion_reply()
            return
        self._write(ADDR_GOAL_VELOCITY, 4, raw)
        self._check_motion_reply()

    def move_steps(self, steps: int) -> None:
        """Move ``steps`` position units (0.088 degrees of the servo) from where it is.

        Raises:
            NotEnabledError: Torque is off.
        """
        if isinstance(steps, bool) or not isinstance(steps, int):
            raise InvalidArgumentError(f"steps {steps!r} must be an integer", joint=self.name)
        self._require_enabled()
        self._set_mode(OperatingMode.POSITION)
        raw = self._read(ADDR_PRESENT_POSITION, 4, signed=True) + steps
        self._goal_position = raw
        self._write(ADDR_GOAL_POSITION, 4, raw)
        self._check_motion_reply()

    def stop(self) -> None:
        """Stop: velocity 0 in velocity mode, the present position as goal in position mode."""
        self._require_init()
        if self.mode == OperatingMode.VELOCITY:
            self._goal_velocity = 0
            self._write(ADDR_GOAL_VELOCITY, 4, 0)
        elif not self._flags & FLAG_NOT_ENABLED:
            raw = self._read(ADDR_PRESENT_POSITION, 4, signed=True)
            self._goal_position = raw
            self._write(ADDR_GOAL_POSITION, 4, raw)
        self._pv_pending = False

    def disable_closed_loop(self) -> None:
        """Torque off (the servo has no open loop)."""
        self.disable()

    def set_drive_current(self, current: int) -> None:
        """0 turns torque off (as the Bioscara's SETCURRENT 0 disables); other values are checked only."""
        if self._check_percent("drive current", current) == 0:
            self.disable()

    def set_hold_current(self, current: int) -> None:
        """0 turns torque off; other values are checked only."""
        if self._check_percent("hold current", current) == 0:
            self.disable()

    def set_brake_mode(self, mode: int) -> None:
        """Checked only: with torque off the servo freewheels."""
        try:
            BrakeMode(mode)
        except ValueError as e:
            raise InvalidArgumentError(f"brake mode {mode!r} must be 0, 1 or 2", joint=self.name) from e
        self._require_init()

    def set_max_acceleration(self, acceleration: float) -> None:
        """Profile Acceleration (units of 214.577 rev/min², at least 1)."""
        acceleration = self._check_finite("max acceleration", acceleration)
        if acceleration <= 0:
            raise InvalidArgumentError(f"max acceleration {acceleration} must be > 0", joint=self.name)
        raw = max(1, round(abs(acceleration * self.reduction) / ACCELERATION_RADS2_PER_UNIT))
        self._profile_acceleration = raw
        self._write(ADDR_PROFILE_ACCELERATION, 4, raw)

    def set_max_velocity(self, velocity: float) -> None:
        """Profile Velocity (units of 0.229 rev/min, at least 1)."""
        velocity = self._check_finite("max velocity", velocity)
        if velocity <= 0:
            raise InvalidArgumentError(f"max velocity {velocity} must be > 0", joint=self.name)
        raw = max(1, abs(velocity_to_raw(velocity * self.reduction)))
        self._profile_velocity = raw
        self._write(ADDR_PROFILE_VELOCITY, 4, raw)

    def enable_stallguard(self, sensitivity: int) -> None:
        """Checked only: the servo's overload protection is always on (its Shutdown item)."""
        self._check_sensitivity("stall sensitivity", sensitivity)
        self._require_init()

    def is_homed(self) -> bool:
        """Always: the encoder is absolute."""
        return True

    def __repr__(self) -> str:
        """Name, ID and flags."""
        return f"DynamixelJoint({self.name!r}, id={self.dxl_id}, flags={Flag(self._flags)!r})"
