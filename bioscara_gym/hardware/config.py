"""Validated configuration of the arm: joints, gripper, joint groups and bus.

The configuration is a tree of frozen dataclasses (:class:`ArmConfig` holding
:class:`JointConfig`, :class:`HomingConfig` and :class:`GripperConfig`). Every
dataclass checks its own invariants when it is built, so an ``ArmConfig`` that
exists is valid; YAML is only the file format. :func:`load_config` reads a YAML
file (or, with no path, the packaged ``default_config.yaml``, whose numbers are
those of the arm's parameter file and URDF, see ``docs/model.md``),
:func:`config_from_dict` builds a configuration from plain data and
:func:`config_to_dict` turns one back into plain data.

Every validation failure raises :class:`~bioscara_gym.hardware.errors.ConfigError`
whose message names the source, the joint, the field and the expectation, e.g.
``"config.yaml: joint j2: homing.speed 5e-05 m/s is -0.75 RPM at the motor;
|RPM| must be strictly between 1 and 250"``.

File format (all joint, homing and gripper fields are required; unknown
fields are errors so that typos cannot pass silently)::

    bus: 1                      # optional, /dev/i2c-N, default 1
    i2c_clock_hz: 100000        # optional, the bus clock, default 100000 (400000: fast mode)
    joints:
      - name: j1
        address: 0x11
        joint_type: revolute    # revolute | prismatic
        reduction: 35.0
        min: -3.04647
        max: 3.04647
        max_velocity: 1.0
        max_acceleration: 2.0
        stall_threshold: 6
        hold_current: 20
        drive_current: 20
        homing: {speed: 0.03, threshold: 30, current: 15, acceleration: 0.01}
      ...
    gripper:
      reduction: 3333.3
      offset: 0.058
      min: 0.04
      max: 0.12
      max_velocity: 1.0
      backup_init_pos: 0.08
      pwm_chip: 0               # optional, default 0
      pwm_channel: 0            # optional, default 0
      state_file: null          # optional, default: chosen by the caller
    groups:                     # optional, default: all, arm, gripper
      all: [j1, j2, j3, j4, gripper]
      arm: [j1, j2, j3, j4]
      gripper: [gripper]

A joint may instead be a Dynamixel servo (``docs/dynamixel.md``): ``type:
dynamixel`` with a ``dynamixel: {id: 1, offset: 0.0}`` block and no
``address`` (``type`` defaults to ``i2c``, the Bioscara's stepper joint). The
port of such joints is the optional top-level block ``dynamixel: {port:
/dev/ttyUSB0, baudrate: 1000000, rs485: false, rates: {pvl_reader: 100, ...}}``.
A group may name groups listed before it (the MH5's nested groups).
"""

from __future__ import annotations

import dataclasses
import math
import os
import reprlib
from collections.abc import Mapping, Sequence
from dataclasses import dataclass, field
from importlib import resources
from types import MappingProxyType
from typing import Any

import yaml

from bioscara_gym.fsutil import read_bytes
from bioscara_gym.hardware.drive import (
    AMAX_PER_DPS2,
    IDEAL_DRIVE,
    VMAX_PER_DPS,
    DriveParams,
    PidNoiseProfile,
    drive_from_dict,
    drive_to_dict,
    noise_from_dict,
    noise_to_dict,
    position_move_limits,
    velocity_mode_acceleration,
)
from bioscara_gym.hardware.errors import ConfigError, UnknownJointError, closest_name
from bioscara_gym.hardware.i2c_timing import (
    WIRE_ONLY,
    TransactionTiming,
    check_clock_hz,
    timing_from_dict,
    timing_to_dict,
)
from bioscara_gym.hardware.registers import (
    CURRENT_MAX_PCT,
    DEADMAN_S,
    DRIVE_CURRENT_MIN_PCT,
    HOMING_RPM_MAX,
    HOMING_RPM_MIN,
    HOMING_THRESHOLD_MIN,
    I2C_ADDRESS_MAX,
    I2C_ADDRESS_MIN,
    I2C_CLOCK_HZ,
    MOTOR_ACCELERATION_MAX_DPS2,
    MOTOR_RPM_MAX,
    SENSITIVITY_MAX,
    STALL_SENSITIVITY_MIN,
    Reg,
)
from bioscara_gym.hardware.registry import DRIVERS
from bioscara_gym.hardware.transmission import rate_to_degrees, velocity_to_rpm

__all__ = [
    "GRIPPER_NAME",
    "JOINT_TYPES",
    "ArmConfig",
    "DynamixelBusConfig",
    "DynamixelJointConfig",
    "GripperConfig",
    "HomingConfig",
    "JointConfig",
    "config_from_dict",
    "config_to_dict",
    "load_config",
]

#: Name under which the gripper appears in joint groups.
GRIPPER_NAME = "gripper"

#: Allowed values of :attr:`JointConfig.joint_type`.
JOINT_TYPES = ("revolute", "prismatic")

#: Allowed values of :attr:`JointConfig.type`: the joint types of the registry
#: (:data:`~bioscara_gym.hardware.registry.DRIVERS`: the Bioscara's I2C stepper joint, a Dynamixel servo).
DRIVER_TYPES = tuple(DRIVERS)
#: Sync loops of a Dynamixel bus and their default rates, Hz (the MH5's defaults; see
#: ``bioscara_gym/hardware/dynamixel/control_table.py``).
DYNAMIXEL_LOOP_RATES = {"pvl_reader": 100.0, "tv_reader": 1.0, "pv_writer": 100.0, "t_writer": 2.0}

_PACKAGE = "bioscara_gym.hardware"
_DEFAULT_CONFIG = "default_config.yaml"
#: Largest configuration file read, bytes (the packaged one is about 10 kB).
MAX_CONFIG_BYTES = 1024 * 1024
#: Most values (mappings, lists and scalars, each counted once for every place it
#: appears) a configuration may expand to. A file of MAX_CONFIG_BYTES without YAML
#: aliases holds fewer values than it has bytes; more can only come from aliases
#: repeating anchors (an "alias bomb": 11 levels of 9 aliases in 10 kB are 3e10
#: values, and printing one in a message ran until killed).
MAX_CONFIG_VALUES = MAX_CONFIG_BYTES
#: A day, s. A speed limit, or an acceleration, with which a move across its joint's
#: whole range takes longer than this is no limit a motion can keep (our floor:
#: ``bioscara move`` waited ~1e300 s on ``max_velocity: 1.0e-300``); the arm's own
#: limits cross their ranges in seconds (docs/model.md).
SLOWEST_MOTION_S = 86_400.0
#: An XL430's fastest speed, rad/s: its Velocity Limit's default, 265 units of 0.229 rev/min
#: (ROBOTIS e-Manual; dynamixel.control_table, where the units are kept with the protocol).
DXL_SPEED_MAX_RAD_S = 265 * 0.023980823922402
#: The servo angles position mode reaches, rad: Goal Position 0..4095 about the centre 2047, 0.088 deg each.
DXL_ANGLE_MIN_RAD = (0 - 2047) * 0.001533980787886
DXL_ANGLE_MAX_RAD = (4095 - 2047) * 0.001533980787886
#: The Baud Rate item's speeds, bit/s (e-Manual).
DXL_BAUD_RATES = (9600, 57600, 115200, 1_000_000, 2_000_000, 3_000_000, 4_000_000, 4_500_000)
_DEFAULT_SOURCE = f"{_PACKAGE}/{_DEFAULT_CONFIG}"


# --------------------------------------------------------------------------
# Field checks. Each returns the normalised value or raises ConfigError with a
# message that names ``what`` (the field, e.g. "homing.speed"); the caller adds
# the joint and the source in front.
# --------------------------------------------------------------------------


def _type_name(value: object) -> str:
    return type(value).__name__


_SHOW = reprlib.Repr()
_SHOW.maxlevel = 2
_SHOW.maxstring = _SHOW.maxother = _SHOW.maxlong = 40
_SHOW.maxlist = _SHOW.maxtuple = _SHOW.maxdict = _SHOW.maxset = _SHOW.maxfrozenset = 6


def _show(value: object) -> str:
    """A user's value for a message: ``repr`` cut short (a YAML alias bomb is 3e10 values)."""
    try:
        return _SHOW.repr(value)
    except (ValueError, RecursionError):  # an int of more than 4300 digits
        return f"<{_type_name(value)}>"


def _label(text: str) -> str:
    """A user's name (joint, group) for a message, as written, cut short if long."""
    return text if len(text) <= 40 else f"{text[:20]}...{text[-17:]}"


def _fmt(value: float) -> str:
    """Format a float exactly (shortest round-trip form), e.g. ``5e-05``."""
    return repr(float(value))


def _number(value: object, what: str) -> float:
    """Check that ``value`` is a finite real number (not a bool); return a float."""
    if isinstance(value, bool) or not isinstance(value, (int, float)):
        hint = ""
        if isinstance(value, str):
            try:
                float(value)
            except ValueError:
                pass
            else:
                hint = (
                    " (YAML reads an exponent without a dot and a sign, such as 1e-3 or 1.0e12, "
                    "as a string; write 1.0e-3, 1.0e+12)"
                )
        raise ConfigError(f"{what} {_show(value)} ({_type_name(value)}) must be a number{hint}")
    try:
        result = float(value)
    except OverflowError:  # an int of more than 309 digits
        raise ConfigError(f"{what} {_show(value)} is beyond any float (1.8e+308)") from None
    if not math.isfinite(result):
        raise ConfigError(f"{what} {_show(value)} must be finite")
    return result


def _positive(value: object, what: str, unit: str = "") -> float:
    result = _number(value, what)
    if result <= 0.0:
        raise ConfigError(f"{what} {_fmt(result)}{unit} must be > 0")
    return result


def _nonzero(value: object, what: str) -> float:
    result = _number(value, what)
    if result == 0.0:
        raise ConfigError(f"{what} must be non-zero")
    return result


def _int(value: object, what: str) -> int:
    """Check that ``value`` is an int (a bool is not)."""
    if isinstance(value, bool) or not isinstance(value, int):
        raise ConfigError(f"{what} {_show(value)} ({_type_name(value)}) must be an integer")
    return value


def _integer(
    value: object,
    what: str,
    low: int = 0,
    high: int | None = None,
    unit: str = "",
) -> int:
    """Check that ``value`` is an int in ``[low, high]`` (``high=None``: no bound)."""
    result = _int(value, what)
    if high is None:
        if result < low:
            raise ConfigError(f"{what} {result} must be >= {low}")
    elif not low <= result <= high:
        raise ConfigError(f"{what} {result} is outside {low}-{high}{unit}")
    return result


#: The largest joint limit, in motor degrees: the firmware's position is ``float q =
#: stepper.angleMoved()`` (joint.ino), a float32 of degrees, which counts every whole
#: degree up to 2^24 and no further (seen: ``max: 1e308`` passed, and MuJoCo's state went NaN).
POSITION_MAX_DEG = float(2**24)


def _limits(low: object, high: object, unit: str = "") -> tuple[float, float]:
    low_f = _number(low, "min")
    high_f = _number(high, "max")
    if low_f >= high_f:
        raise ConfigError(f"min {_fmt(low_f)}{unit} must be less than max {_fmt(high_f)}{unit}")
    return low_f, high_f


def _check_ramp(name: str, acceleration: float, span: float, unit: str) -> None:
    """Refuse an acceleration that takes more than SLOWEST_MOTION_S to cross the joint's range.

    Whatever the speed limit, a move across ``span`` speeds up half the way and
    slows down the other half: ``2 sqrt(span / acceleration)`` at the least.
    """
    seconds = 2.0 * math.sqrt(span / acceleration)
    if seconds > SLOWEST_MOTION_S:
        raise ConfigError(
            f"{name} {_fmt(acceleration)}{unit}/s² crosses the joint's range ({_fmt(span)}{unit}) in "
            f"{seconds:.3g} s or more; at least {4.0 * span / SLOWEST_MOTION_S**2:.3g}{unit}/s², "
            "the range in a day (config.SLOWEST_MOTION_S: a slower ramp is no acceleration)"
        )


def _unit(joint_type: str) -> str:
    return " m" if joint_type == "prismatic" else " rad"


def _is_list(value: object) -> bool:
    """Tell whether ``value`` is a list-like sequence (strings are not)."""
    return isinstance(value, Sequence) and not isinstance(value, (str, bytes))


def _set(obj: object, name: str, value: object) -> None:
    """Store a normalised value on a frozen dataclass during ``__post_init__``."""
    object.__setattr__(obj, name, value)


# --------------------------------------------------------------------------
# The dataclasses.
# --------------------------------------------------------------------------


@dataclass(frozen=True)
class HomingConfig:
    """How a joint homes against its end stop.

    Attributes:
        speed: Signed joint-side homing speed, rad/s (revolute) or m/s
            (prismatic). The sign picks the end stop: positive homes to
            ``max``, negative to ``min``. Never 0.
        threshold: PID-error sensitivity that detects the end stop, 0-255
            (lower is more sensitive).
        current: Motor current while homing, percent 0-100 of 2.5 A.
        acceleration: Joint-side acceleration while homing, rad/s² or m/s²,
            > 0.

    Raises:
        ConfigError: On construction, if a field has the wrong type or range.
    """

    speed: float
    threshold: int
    current: int
    acceleration: float

    def __post_init__(self) -> None:
        """Validate and normalise the fields (ints given for floats become floats)."""
        speed = _number(self.speed, "homing.speed")
        if speed == 0.0:
            raise ConfigError(
                "homing.speed must be non-zero (its sign picks the end stop: + homes to max, - to min)"
            )
        _set(self, "speed", speed)
        threshold = _integer(self.threshold, "homing.threshold", high=SENSITIVITY_MAX)
        if threshold < HOMING_THRESHOLD_MIN:
            raise ConfigError(
                f"homing.threshold {threshold} is below {HOMING_THRESHOLD_MIN}: a free joint's PID error "
                "at rest reaches 17, so the homing would stop where the joint stands "
                "(registers.HOMING_THRESHOLD_MIN)"
            )
        current = _integer(self.current, "homing.current", high=CURRENT_MAX_PCT, unit=" %")
        if current < DRIVE_CURRENT_MIN_PCT:
            raise ConfigError("homing.current 0 % gives the motor no torque: the homing would stop at once")
        _set(self, "acceleration", _positive(self.acceleration, "homing.acceleration"))


@dataclass(frozen=True)
class DynamixelJointConfig:
    """The servo behind a ``type: dynamixel`` joint.

    Attributes:
        id: The servo's ID, 0-252.
        offset: Joint position at the servo's centre (raw 2047), rad or m
            (the MH5's ``offset``).

    Raises:
        ConfigError: On construction, if a field has the wrong type or range.
    """

    id: int
    offset: float = 0.0

    def __post_init__(self) -> None:
        """Validate and normalise."""
        _integer(self.id, "dynamixel.id", high=252)
        _set(self, "offset", _number(self.offset, "dynamixel.offset"))


@dataclass(frozen=True)
class DynamixelBusConfig:
    """The serial port of the Dynamixel joints.

    Attributes:
        port: Device path (a USB-RS485 adapter, the MH5's SC16IS762 UART, or a pty).
        baudrate: Bits per second (the servos' Baud Rate item must match).
        rs485: Put the port in RS-485 mode with ``TIOCSRS485`` (MH5); logged if unsupported.
        rates: Loop name to rate in Hz; missing loops take the MH5's defaults.

    Raises:
        ConfigError: On construction, if a field has the wrong type or range.
    """

    port: str = "/dev/ttyUSB0"
    baudrate: int = 1_000_000
    rs485: bool = False
    rates: Mapping[str, float] = field(default_factory=dict, hash=False)

    def __post_init__(self) -> None:
        """Validate; fill ``rates`` with the defaults."""
        if not isinstance(self.port, str) or not self.port:
            raise ConfigError(f"dynamixel.port {_show(self.port)} must be a non-empty string")
        _integer(self.baudrate, "dynamixel.baudrate", low=9600)
        if self.baudrate not in DXL_BAUD_RATES:  # seen: 10**30 loaded
            rates = ", ".join(str(r) for r in DXL_BAUD_RATES)
            raise ConfigError(f"dynamixel.baudrate {self.baudrate} is none of the servo's {rates} (e-Manual)")
        if not isinstance(self.rs485, bool):
            raise ConfigError(f"dynamixel.rs485 {_show(self.rs485)} must be true or false")
        rates = _mapping(self.rates, "dynamixel.rates")
        for name, rate in rates.items():
            if name not in DYNAMIXEL_LOOP_RATES:
                known = ", ".join(DYNAMIXEL_LOOP_RATES)
                raise ConfigError(f"dynamixel.rates: unknown loop {_show(name)}; known: {known}")
            if _number(rate, f"dynamixel.rates.{name}") < 0:
                raise ConfigError(f"dynamixel.rates.{name} {_show(rate)} must be >= 0 Hz (0: never)")
        merged = {**DYNAMIXEL_LOOP_RATES, **{k: float(v) for k, v in rates.items()}}
        _set(self, "rates", MappingProxyType(merged))


@dataclass(frozen=True)
class JointConfig:
    """One stepper joint: bus address, transmission, limits and driver settings.

    Attributes:
        name: Joint name, e.g. ``"j1"``.
        address: 7-bit I2C address, 0x03-0x77.
        joint_type: ``"revolute"`` (rad) or ``"prismatic"`` (m).
        reduction: Actuator units per joint unit (motor rad per joint rad or
            per joint m); negative reverses the direction. Non-zero.
        min: Lower joint limit, rad or m.
        max: Upper joint limit, rad or m; greater than ``min``.
        max_velocity: Joint-side velocity limit, rad/s or m/s, > 0.
        max_acceleration: Joint-side acceleration limit, rad/s² or m/s², > 0.
        stall_threshold: Stall detection sensitivity, 0-255.
        hold_current: Standstill current, percent 0-100 of 2.5 A.
        drive_current: Running current, percent 0-100 of 2.5 A.
        homing: Homing settings; the homing speed must be 1-250 RPM
            (exclusive) at the motor.
        type: The joint's driver: ``"i2c"`` (the Bioscara's stepper joint,
            the default) or ``"dynamixel"`` (a servo; ``address`` is then
            ``None`` and ``dynamixel`` names the servo).
        dynamixel: The servo of a ``dynamixel`` joint, else ``None``.
        drive: The motor and its drive as the real arm's recordings identify
            them (pull-out, friction, PID-error jitter; ``drive.DriveParams``);
            default: an ideal motor that never loses a step.

    Raises:
        ConfigError: On construction, if a field has the wrong type or range;
            the message starts with ``"joint <name>: "``.
    """

    name: str
    address: int
    joint_type: str
    reduction: float
    min: float
    max: float
    max_velocity: float
    max_acceleration: float
    stall_threshold: int
    hold_current: int
    drive_current: int
    homing: HomingConfig
    type: str = "i2c"
    dynamixel: DynamixelJointConfig | None = None
    drive: DriveParams = IDEAL_DRIVE

    def __post_init__(self) -> None:
        """Validate and normalise the fields (ints given for floats become floats)."""
        if not isinstance(self.name, str) or not self.name:
            raise ConfigError(
                f"joint name {_show(self.name)} ({_type_name(self.name)}) must be a non-empty string"
            )
        try:
            self._validate()
        except ConfigError as e:
            raise ConfigError(f"joint {_label(self.name)}: {e}") from None

    def _validate(self) -> None:
        if self.type not in DRIVER_TYPES:
            raise ConfigError(
                f"type {_show(self.type)} must be one of {', '.join(repr(t) for t in DRIVER_TYPES)}"
            )
        if self.type == "dynamixel":
            if not isinstance(self.dynamixel, DynamixelJointConfig):
                raise ConfigError("a dynamixel joint needs a 'dynamixel' block with its servo's id")
        elif self.dynamixel is not None:
            raise ConfigError("a 'dynamixel' block needs type: dynamixel")
        address = None if self.type == "dynamixel" and self.address is None else _int(self.address, "address")
        if address is not None and not I2C_ADDRESS_MIN <= address <= I2C_ADDRESS_MAX:
            raise ConfigError(
                f"address 0x{address:02X} is outside the 7-bit I2C range "
                f"0x{I2C_ADDRESS_MIN:02X}-0x{I2C_ADDRESS_MAX:02X}"
            )
        if not isinstance(self.joint_type, str) or self.joint_type not in JOINT_TYPES:
            allowed = ", ".join(repr(t) for t in JOINT_TYPES)
            raise ConfigError(f"joint_type {_show(self.joint_type)} must be one of {allowed}")
        unit = _unit(self.joint_type)
        _set(self, "reduction", _nonzero(self.reduction, "reduction"))
        low, high = _limits(self.min, self.max, unit)
        for name, value in (("min", low), ("max", high)):
            degrees = abs(rate_to_degrees(value, self.reduction))
            if degrees > POSITION_MAX_DEG:
                raise ConfigError(
                    f"{name} {_fmt(value)}{unit} is {degrees:.4g} deg at the motor; the firmware keeps the "
                    f"motor's angle in a float (angleMoved), whole to a degree up to {POSITION_MAX_DEG:,.0f}"
                )
        _set(self, "min", low)
        _set(self, "max", high)
        _set(
            self,
            "max_velocity",
            _positive(self.max_velocity, "max_velocity", f"{unit}/s"),
        )
        _set(
            self,
            "max_acceleration",
            _positive(self.max_acceleration, "max_acceleration", f"{unit}/s²"),
        )
        span = high - low
        if span / self.max_velocity > SLOWEST_MOTION_S:
            raise ConfigError(
                f"max_velocity {_fmt(self.max_velocity)}{unit}/s crosses the joint's range "
                f"({_fmt(span)}{unit}) in {span / self.max_velocity:.3g} s; "
                f"at least {span / SLOWEST_MOTION_S:.3g}{unit}/s, "
                "the range in a day (config.SLOWEST_MOTION_S: a slower limit is no speed)"
            )
        _check_ramp("max_acceleration", self.max_acceleration, span, unit)
        sensitivity = _integer(self.stall_threshold, "stall_threshold", high=SENSITIVITY_MAX)
        if sensitivity < STALL_SENSITIVITY_MIN:
            raise ConfigError(
                f"stall_threshold {sensitivity} is below {STALL_SENSITIVITY_MIN}: its threshold "
                f"({10 * sensitivity} at standstill) lies under a free joint's PID error at rest (17), "
                "so it would trip standing still (registers.STALL_SENSITIVITY_MIN)"
            )
        _integer(self.hold_current, "hold_current", high=CURRENT_MAX_PCT, unit=" %")
        drive = _integer(self.drive_current, "drive_current", high=CURRENT_MAX_PCT, unit=" %")
        if drive < DRIVE_CURRENT_MIN_PCT:
            raise ConfigError("drive_current 0 % gives the motor no torque: the joint could not move")
        if not isinstance(self.homing, HomingConfig):
            raise ConfigError(f"homing must be a HomingConfig, got {_type_name(self.homing)}")
        _check_ramp("homing.acceleration", self.homing.acceleration, high - low, unit)
        if self.type == "i2c":
            self._check_motor_limits(unit)
        elif self.type == "dynamixel":
            self._check_servo_limits(unit)
        rpm = self.homing_rpm()
        if not HOMING_RPM_MIN < abs(rpm) < HOMING_RPM_MAX:
            raise ConfigError(
                f"homing.speed {_fmt(self.homing.speed)}{unit}/s is {rpm:.2f} RPM at "
                f"the motor; |RPM| must be strictly between {HOMING_RPM_MIN:g} "
                f"and {HOMING_RPM_MAX:g}"
            )

    def _check_servo_limits(self, unit: str) -> None:
        """Refuse limits an XL430 cannot keep: a speed beyond its Velocity Limit, a range beyond its turn.

        Seen (a hostile test): ``max_velocity: 1.0e+6`` and limits of ±100 rad loaded.
        """
        assert self.dynamixel is not None  # _validate checked it for a dynamixel joint
        speed = abs(self.max_velocity * self.reduction)
        if speed > DXL_SPEED_MAX_RAD_S * (1 + 1e-12):
            raise ConfigError(
                f"max_velocity {_fmt(self.max_velocity)}{unit}/s is {speed:.4g} rad/s at the servo, beyond "
                f"its Velocity Limit ({DXL_SPEED_MAX_RAD_S:.4g} rad/s: 265 units of 0.229 rev/min, "
                "the XL430's default; e-Manual)"
            )
        for name, q in (("min", self.min), ("max", self.max)):
            angle = (q - self.dynamixel.offset) * self.reduction
            if not DXL_ANGLE_MIN_RAD <= angle <= DXL_ANGLE_MAX_RAD:
                raise ConfigError(
                    f"{name} {_fmt(q)}{unit} is servo angle {angle:.4g} rad, beyond the servo's turn "
                    f"({DXL_ANGLE_MIN_RAD:.6g}..{DXL_ANGLE_MAX_RAD:.6g} rad: Goal Position 0-4095 about "
                    "its centre 2047, position mode; e-Manual)"
                )

    def _check_motor_limits(self, unit: str) -> None:
        """Refuse a speed or acceleration limit the stepper motor cannot honour (registers.MOTOR_*)."""
        rpm = abs(velocity_to_rpm(self.max_velocity, self.reduction))
        if rpm > MOTOR_RPM_MAX * (1 + 1e-12):  # the bound itself, converted there and back, is accepted
            raise ConfigError(
                f"max_velocity {_fmt(self.max_velocity)}{unit}/s is {rpm:.4g} RPM at the motor; the motors "
                f"were measured to 1639 RPM, so at most {MOTOR_RPM_MAX:g} RPM "
                f"({_fmt(self.max_velocity * MOTOR_RPM_MAX / rpm)}{unit}/s)"
            )
        dps = abs(rate_to_degrees(self.max_velocity, self.reduction))
        if position_move_limits(dps, MOTOR_ACCELERATION_MAX_DPS2)[0] == 0.0:
            raise ConfigError(
                f"max_velocity {_fmt(self.max_velocity)}{unit}/s is {dps:.4g} deg/s at the motor; the driver "
                f"chip's speed register (VMAX, whole steps of 1/{VMAX_PER_DPS:.4g} deg/s) holds 0 there and "
                f"the joint would not move: at least {1 / VMAX_PER_DPS:.4g} deg/s (drive.VMAX_PER_DPS)"
            )
        limits = (
            ("max_acceleration", self.max_acceleration),
            ("homing.acceleration", self.homing.acceleration),
        )
        for name, value in limits:
            dps2 = abs(rate_to_degrees(value, self.reduction))
            if velocity_mode_acceleration(dps2) == 0.0:  # position moves ramp with the same AMAX
                raise ConfigError(
                    f"{name} {_fmt(value)}{unit}/s² is {dps2:.4g} deg/s² at the motor; the driver chip's "
                    f"acceleration register (AMAX, whole steps of 1/{AMAX_PER_DPS2:.4g} deg/s²) holds 0 "
                    f"there and the joint would not ramp: at least {1 / AMAX_PER_DPS2:.4g} deg/s² "
                    "(drive.AMAX_PER_DPS2)"
                )
            if dps2 > MOTOR_ACCELERATION_MAX_DPS2 * (1 + 1e-12):
                most = _fmt(value * MOTOR_ACCELERATION_MAX_DPS2 / dps2)
                raise ConfigError(
                    f"{name} {_fmt(value)}{unit}/s² is {dps2:.4g} deg/s² at the motor; the driver chip's "
                    f"16-bit acceleration register wraps above 20,945 deg/s², so at most "
                    f"{MOTOR_ACCELERATION_MAX_DPS2:g} ({most}{unit}/s²)"
                )

    def homing_rpm(self) -> float:
        """Return the signed motor speed of homing in RPM.

        Returns:
            ``rad2deg(reduction × homing.speed) / 6``, as the velocity
            command (:func:`~bioscara_gym.hardware.transmission.velocity_to_rpm`);
            the sign is the motor's direction.
        """
        return velocity_to_rpm(self.homing.speed, self.reduction)


@dataclass(frozen=True)
class GripperConfig:
    """The servo gripper: width transmission, limits and PWM output.

    Attributes:
        reduction: Servo degrees per metre of width (α = r·(w − o)); non-zero.
        offset: Width at servo angle 0, m.
        min: Smallest width, m.
        max: Largest width, m; greater than ``min``.
        max_velocity: Width velocity limit from the original parameter file,
            > 0.
        backup_init_pos: Width assumed at enable when no saved width can be
            read back, m; within ``[min, max]``.
        pwm_chip: Linux PWM chip number (``/sys/class/pwm/pwmchipN``), >= 0.
        pwm_channel: PWM channel on that chip (``pwmM``), >= 0.
        state_file: File that keeps the last width across restarts; ``None``
            lets the caller choose a default under the user's state directory.

    Raises:
        ConfigError: On construction, if a field has the wrong type or range;
            the message starts with ``"gripper: "``.
    """

    reduction: float
    offset: float
    min: float
    max: float
    max_velocity: float
    backup_init_pos: float
    pwm_chip: int = 0
    pwm_channel: int = 0
    state_file: str | None = None

    def __post_init__(self) -> None:
        """Validate and normalise the fields (ints given for floats become floats)."""
        try:
            self._validate()
        except ConfigError as e:
            raise ConfigError(f"{GRIPPER_NAME}: {e}") from None

    def _validate(self) -> None:
        _set(self, "reduction", _nonzero(self.reduction, "reduction"))
        _set(self, "offset", _number(self.offset, "offset"))
        low, high = _limits(self.min, self.max, " m")
        _set(self, "min", low)
        _set(self, "max", high)
        _set(self, "max_velocity", _positive(self.max_velocity, "max_velocity"))
        init = _number(self.backup_init_pos, "backup_init_pos")
        if not low <= init <= high:
            raise ConfigError(
                f"backup_init_pos {_fmt(init)} m must be within [min, max] = [{_fmt(low)}, {_fmt(high)}] m"
            )
        _set(self, "backup_init_pos", init)
        _integer(self.pwm_chip, "pwm_chip")
        _integer(self.pwm_channel, "pwm_channel")
        if self.state_file is not None and (not isinstance(self.state_file, str) or not self.state_file):
            raise ConfigError(
                f"state_file {_show(self.state_file)} ({_type_name(self.state_file)}) "
                "must be a non-empty string or null"
            )


@dataclass(frozen=True)
class ArmConfig:
    """The whole arm: joints, gripper, named joint groups and the I2C bus.

    Attributes:
        joints: The joints in order (j1 first); names and addresses are
            unique, and no joint may be called ``"gripper"``.
        gripper: The gripper.
        groups: Named groups of joint names (read-only mapping); members are
            joint names or ``"gripper"``, each at most once per group.
        bus: I2C bus number (``/dev/i2c-N``), >= 0.
        i2c_clock_hz: The I2C bus clock, Hz, 10 000 to 1 000 000: 100 000 (standard mode,
            the Raspberry Pi's default) or 400 000 (fast mode). The real
            bus's is set on the Pi (``dtparam=i2c_arm_baudrate``); here it
            sets the wire time the emulated bus and the sim backend charge
            per transaction (docs/protocol.md, "Wire time").
        bus_timing: What a transaction takes beyond its bits (the host's call,
            the joint's handler), as the real bus measured it (``RW_test/``).

    Raises:
        ConfigError: On construction, if the parts are inconsistent.
    """

    joints: tuple[JointConfig, ...]
    gripper: GripperConfig
    groups: Mapping[str, tuple[str, ...]] = field(hash=False)
    bus: int = 1
    dynamixel: DynamixelBusConfig | None = None
    i2c_clock_hz: float = I2C_CLOCK_HZ
    bus_timing: TransactionTiming = WIRE_ONLY

    def __post_init__(self) -> None:
        """Validate the parts; freeze ``joints`` (tuple) and ``groups`` (read-only)."""
        if not _is_list(self.joints):
            raise ConfigError(f"joints must be a sequence of JointConfig, got {_type_name(self.joints)}")
        joints = tuple(self.joints)
        if not joints:
            raise ConfigError("joints must list at least one joint")
        by_name: dict[str, JointConfig] = {}
        by_address: dict[int, JointConfig] = {}
        by_id: dict[int, JointConfig] = {}
        for index, joint in enumerate(joints):
            if not isinstance(joint, JointConfig):
                raise ConfigError(f"joints[{index}] must be a JointConfig, got {_type_name(joint)}")
            if joint.name == GRIPPER_NAME:
                raise ConfigError(
                    f"joint {_label(joint.name)}: the name {GRIPPER_NAME!r} is reserved "
                    "for the gripper in joint groups"
                )
            if joint.name in by_name:
                raise ConfigError(
                    f"joint {_label(joint.name)}: defined more than once; joint names must be unique"
                )
            if joint.dynamixel is not None:
                twin = by_id.setdefault(joint.dynamixel.id, joint)
                if twin is not joint:
                    raise ConfigError(
                        f"joint {joint.name}: dynamixel.id {joint.dynamixel.id} is already used by "
                        f"joint {twin.name}; servo IDs must be unique"
                    )
            other = by_address.get(joint.address) if joint.address is not None else None
            if other is not None:
                raise ConfigError(
                    f"joint {joint.name}: address 0x{joint.address:02X} is already "
                    f"used by joint {other.name}; addresses must be unique"
                )
            by_name[joint.name] = joint
            by_address[joint.address] = joint
        _set(self, "joints", joints)
        if not isinstance(self.gripper, GripperConfig):
            raise ConfigError(f"gripper must be a GripperConfig, got {_type_name(self.gripper)}")
        _set(self, "groups", MappingProxyType(self._checked_groups()))
        _integer(self.bus, "bus")
        clock_hz = _positive(self.i2c_clock_hz, "i2c_clock_hz", " Hz")
        try:
            _set(self, "i2c_clock_hz", check_clock_hz(clock_hz))
        except ValueError as e:
            raise ConfigError(str(e)) from e
        if self.dynamixel is not None and not isinstance(self.dynamixel, DynamixelBusConfig):
            raise ConfigError(f"dynamixel must be a DynamixelBusConfig, got {_type_name(self.dynamixel)}")
        self._check_bus_timing()

    def _check_bus_timing(self) -> None:
        """Refuse a ``bus_timing`` part longer than the firmware's deadman (registers.DEADMAN_S).

        The firmware stops a joint in velocity mode that hears nothing for 50 ms
        (docs/firmware.md, "Deadman"), so a transaction, and each part of it,
        must fit in that window, or talking to one joint starves the others. The
        arm's own parts take at most 0.36 ms (MOVETOANGLE's handler, RW_test/); the bound is generous.
        Seen: ``host_overhead_us: 1.0e+9`` charged 1000 s a transaction.
        """
        timing = self.bus_timing
        if not isinstance(timing, TransactionTiming):
            raise ConfigError(f"bus_timing must be a TransactionTiming, got {_type_name(timing)}")
        most_us = DEADMAN_S * 1e6
        parts = [
            ("host_overhead_us", timing.host_overhead_s),
            ("program_overhead_us", timing.program_overhead_s),
        ]
        for reg, seconds in timing.handler_s.items():
            try:
                name = Reg(reg).name
            except ValueError:  # built in code, not read from a file (timing_from_dict takes names)
                name = _show(reg)
            parts.append((f"handler_us.{name}", seconds))
        for name, seconds in parts:
            if seconds > DEADMAN_S:
                raise ConfigError(
                    f"bus_timing.{name} {_fmt(round(seconds * 1e6, 3))} us is longer than the "
                    f'firmware\'s deadman, {most_us:g} us (docs/firmware.md, "Deadman"): '
                    "a transaction must fit in it"
                )
        periods_s = timing.extra_periods / self.i2c_clock_hz
        if periods_s > DEADMAN_S:
            raise ConfigError(
                f"bus_timing.extra_periods {_fmt(timing.extra_periods)} clock periods are "
                f"{periods_s * 1e6:.6g} us at {self.i2c_clock_hz:g} Hz, longer than the firmware's deadman, "
                f'{most_us:g} us (docs/firmware.md, "Deadman"): a transaction must fit in it; '
                f"at most {DEADMAN_S * self.i2c_clock_hz:g}"
            )

    def _checked_groups(self) -> dict[str, tuple[str, ...]]:
        if not isinstance(self.groups, Mapping):
            raise ConfigError(
                "groups must be a mapping of group name to a list of joint "
                f"names, got {_type_name(self.groups)}"
            )
        known = (*self.names, GRIPPER_NAME)
        groups: dict[str, tuple[str, ...]] = {}
        for group, members in self.groups.items():
            if not isinstance(group, str) or not group:
                raise ConfigError(f"groups: group name {_show(group)} must be a non-empty string")
            where = f"groups.{_label(group)}"
            if not _is_list(members):
                raise ConfigError(f"{where}: {_show(members)} must be a list of joint names")
            if not members:
                raise ConfigError(f"{where}: must name at least one joint")
            for member in members:
                if not isinstance(member, str):
                    raise ConfigError(
                        f"{where}: member {_show(member)} ({_type_name(member)}) "
                        "must be a joint or group name"
                    )
            # A joint's name, and "gripper", mean the joint (the gripper) wherever a
            # name is taken (console.targets.resolve_target): a group so named is never used.
            if group in self.names:
                raise ConfigError(
                    f"{where}: the name {_show(group)} is joint {_label(group)}'s and means that joint "
                    "alone; give the group a name of its own"
                )
            if group == GRIPPER_NAME and tuple(members) != (GRIPPER_NAME,):
                raise ConfigError(
                    f"{where}: the name {GRIPPER_NAME!r} means the gripper alone; its group may only "
                    f"be [{GRIPPER_NAME}]; give the group a name of its own"
                )
            nested = [m for m in members if m in groups and m not in known]  # MH5: earlier groups nest
            if nested:
                members = [n for m in members for n in (groups[m] if m in nested else [m])]
            for member in members:
                if member not in known:
                    raise ConfigError(f"{where}: unknown joint {_show(member)}; known: {', '.join(known)}")
            if len(set(members)) != len(members):
                raise ConfigError(f"{where}: lists a joint more than once")
            groups[group] = tuple(members)
        return groups

    @property
    def names(self) -> tuple[str, ...]:
        """The joint names in order (the gripper is not a joint)."""
        return tuple(joint.name for joint in self.joints)

    def with_drives(self, **values: object) -> ArmConfig:
        """A copy whose every joint's drive has these values (``DriveParams`` fields, ``noise``)."""
        joints = tuple(
            dataclasses.replace(j, drive=dataclasses.replace(j.drive, **values)) for j in self.joints
        )
        return dataclasses.replace(self, joints=joints)

    def joint(self, name: str) -> JointConfig:
        """Return the configuration of one joint.

        Args:
            name: Joint name, e.g. ``"j2"``.

        Returns:
            The joint's configuration.

        Raises:
            UnknownJointError: If there is no joint called ``name`` (a
                :class:`~bioscara_gym.hardware.errors.ConfigError` and an
                :class:`~bioscara_gym.hardware.errors.InvalidArgumentError`);
                the message lists the known joints.
        """
        for joint in self.joints:
            if joint.name == name:
                return joint
        raise UnknownJointError(f"unknown joint {name!r}; known joints: {', '.join(self.names)}")


# --------------------------------------------------------------------------
# Plain data <-> dataclasses.
# --------------------------------------------------------------------------

_HOMING_FIELDS = tuple(f.name for f in dataclasses.fields(HomingConfig))
_JOINT_FIELDS = tuple(f.name for f in dataclasses.fields(JointConfig) if f.default is dataclasses.MISSING)
_JOINT_OPTIONAL = ("type", "dynamixel", "drive")
_GRIPPER_REQUIRED = tuple(
    f.name for f in dataclasses.fields(GripperConfig) if f.default is dataclasses.MISSING
)
_GRIPPER_OPTIONAL = tuple(
    f.name for f in dataclasses.fields(GripperConfig) if f.default is not dataclasses.MISSING
)
_TOP_REQUIRED = ("joints", "gripper")
_TOP_OPTIONAL = ("groups", "bus", "dynamixel", "i2c_clock_hz", "bus_timing", "pid_noise")


def _check_fields(
    data: Mapping[Any, Any],
    required: Sequence[str],
    optional: Sequence[str] = (),
    prefix: str = "",
) -> None:
    """Raise ConfigError for unknown fields first (typos), then missing ones."""
    allowed = (*required, *optional)
    for key in data:
        if key not in allowed:
            close = closest_name(key, allowed)
            hint = (
                f" (did you mean {prefix + close!r}?)"
                if close
                else f"; allowed: {', '.join(prefix + a for a in allowed)}"
            )
            raise ConfigError(f"unknown field {_show(prefix + str(key))}{hint}")
    missing = [f"{prefix}{name}" for name in required if name not in data]
    if missing:
        plural = "s" if len(missing) > 1 else ""
        raise ConfigError(f"missing field{plural} {', '.join(repr(m) for m in missing)}")


def _mapping(value: object, what: str) -> Mapping[Any, Any]:
    if not isinstance(value, Mapping):
        raise ConfigError(f"{what} must be a mapping, got {_type_name(value)}")
    return value


def _homing_from_dict(data: object) -> HomingConfig:
    homing = _mapping(data, "homing")
    _check_fields(homing, _HOMING_FIELDS, prefix="homing.")
    return HomingConfig(**{name: homing[name] for name in _HOMING_FIELDS})


def _joint_from_dict(data: object, index: int, noise: PidNoiseProfile | None = None) -> JointConfig:
    joint = _mapping(data, f"joints[{index}]")
    name = joint.get("name")
    where = f"joint {_label(name)}" if isinstance(name, str) and name else f"joints[{index}]"
    try:
        dxl = joint.get("type") == "dynamixel"
        required = tuple(k for k in _JOINT_FIELDS if not (dxl and k == "address"))
        _check_fields(joint, required, (*_JOINT_OPTIONAL, *(("address",) if dxl else ())))
        if not isinstance(name, str) or not name:
            raise ConfigError(f"name {_show(name)} ({_type_name(name)}) must be a non-empty string")
        values = {key: joint.get(key) for key in _JOINT_FIELDS}
        values["homing"] = _homing_from_dict(joint["homing"])
        values["type"] = joint.get("type", "i2c")
        if joint.get("dynamixel") is not None:
            block = _mapping(joint["dynamixel"], "dynamixel")
            _check_fields(block, ("id",), ("offset",), prefix="dynamixel.")
            values["dynamixel"] = DynamixelJointConfig(**dict(block))
        if joint.get("drive") is not None:
            try:
                values["drive"] = drive_from_dict(dict(_mapping(joint["drive"], "drive")), noise)
            except ValueError as e:
                raise ConfigError(str(e)) from None
    except ConfigError as e:
        raise ConfigError(f"{where}: {e}") from None
    # JointConfig names itself ("joint <name>: ...") in its own errors.
    return JointConfig(**values)


def _gripper_from_dict(data: object) -> GripperConfig:
    try:
        gripper = _mapping(data, "section")
        _check_fields(gripper, _GRIPPER_REQUIRED, _GRIPPER_OPTIONAL)
    except ConfigError as e:
        raise ConfigError(f"{GRIPPER_NAME}: {e}") from None
    # GripperConfig names itself ("gripper: ...") in its own errors.
    return GripperConfig(**dict(gripper))


def _check_expansion(data: object) -> None:
    """Refuse data that repeats itself through YAML aliases beyond MAX_CONFIG_VALUES, or contains itself.

    Each distinct mapping or list is visited once (its size remembered), so an
    alias bomb is measured at once, never walked.
    """
    sizes: dict[int, int] = {}
    open_: set[int] = set()

    def size(node: object) -> int:
        if isinstance(node, Mapping):
            children: Any = node.values()
        elif isinstance(node, (list, tuple)):
            children = node
        else:
            return 1
        key = id(node)
        if key in sizes:
            return sizes[key]
        if key in open_:
            raise ConfigError("a value contains itself (a YAML alias inside its own anchor)")
        open_.add(key)
        total = 1 + len(node) if isinstance(node, Mapping) else 1
        for child in children:
            total = min(total + size(child), MAX_CONFIG_VALUES + 1)
        open_.discard(key)
        sizes[key] = total
        return total

    try:
        total = size(data)
    except RecursionError:
        raise ConfigError("nested too deeply to be an arm configuration") from None
    if total > MAX_CONFIG_VALUES:
        raise ConfigError(
            f"expands to more than {MAX_CONFIG_VALUES:,} values through YAML aliases (*name); a file "
            f"without aliases has fewer values than bytes, at most {MAX_CONFIG_BYTES:,} "
            "(config.MAX_CONFIG_VALUES)"
        )


def _default_groups(names: Sequence[str]) -> dict[str, tuple[str, ...]]:
    """``all``, ``arm`` and ``gripper``, less a group named like a joint (that name means the joint)."""
    groups = {"all": (*names, GRIPPER_NAME), "arm": tuple(names), GRIPPER_NAME: (GRIPPER_NAME,)}
    return {name: members for name, members in groups.items() if name not in names}


def config_from_dict(data: Mapping[str, Any], source: str = "<dict>") -> ArmConfig:
    """Build and validate an :class:`ArmConfig` from plain data.

    Args:
        data: A mapping in the file format of this module (see the module
            docstring), e.g. what ``yaml.safe_load`` returns. ``groups`` and
            ``bus`` and ``i2c_clock_hz`` may be left out (defaults: groups
            ``all``, ``arm`` and ``gripper``; bus 1; 100 000 Hz).
        source: Where the data came from; starts every error message.

    Returns:
        The validated configuration.

    Raises:
        ConfigError: If a field is missing, unknown, of the wrong type or out
            of range; the message reads ``"<source>: joint <name>: <field>
            <value> <expectation>"``.
    """
    try:
        top = _mapping(data, "the top level")
        _check_expansion(top)
        _check_fields(top, _TOP_REQUIRED, _TOP_OPTIONAL)
        joints_data = top["joints"]
        if not _is_list(joints_data):
            raise ConfigError(f"joints must be a list of joint mappings, got {_type_name(joints_data)}")
        noise = None
        try:
            if top.get("pid_noise") is not None:
                noise = noise_from_dict(dict(_mapping(top["pid_noise"], "pid_noise")))
            timing = (
                timing_from_dict(dict(_mapping(top["bus_timing"], "bus_timing")))
                if top.get("bus_timing") is not None
                else WIRE_ONLY
            )
        except ValueError as e:
            raise ConfigError(str(e)) from None
        joints = tuple(_joint_from_dict(item, i, noise) for i, item in enumerate(joints_data))
        gripper = _gripper_from_dict(top["gripper"])
        groups = top["groups"] if "groups" in top else _default_groups([joint.name for joint in joints])
        dxl_bus = None
        if top.get("dynamixel") is not None:
            block = _mapping(top["dynamixel"], "dynamixel")
            allowed = tuple(f.name for f in dataclasses.fields(DynamixelBusConfig))
            _check_fields(block, (), allowed, prefix="dynamixel.")
            dxl_bus = DynamixelBusConfig(**dict(block))
        bus = top.get("bus", 1)
        clock_hz = top.get("i2c_clock_hz", I2C_CLOCK_HZ)
        return ArmConfig(
            joints=joints,
            gripper=gripper,
            groups=groups,
            bus=bus,
            dynamixel=dxl_bus,
            i2c_clock_hz=clock_hz,
            bus_timing=timing,
        )
    except ConfigError as e:
        raise ConfigError(f"{source}: {e}") from None


def config_to_dict(cfg: ArmConfig) -> dict[str, Any]:
    """Turn a configuration into plain data (dicts, lists, numbers, strings).

    The result can be written with ``yaml.safe_dump`` and read back with
    :func:`config_from_dict` to an equal :class:`ArmConfig`.

    Args:
        cfg: The configuration.

    Returns:
        A new dict with the keys ``bus``, ``i2c_clock_hz``, ``joints``,
        ``gripper`` and ``groups`` (and ``dynamixel`` where there is one).
    """
    joints = []
    noise = None
    for joint in cfg.joints:
        data = dataclasses.asdict(joint)
        del data["drive"]
        for key, unset in (("type", "i2c"), ("dynamixel", None), ("address", None)):
            if data[key] == unset:
                del data[key]  # an I2C joint's file has neither; a Dynamixel joint's has no address
        if joint.drive != IDEAL_DRIVE:
            data["drive"] = drive_to_dict(joint.drive)
            noise = noise or joint.drive.noise
        joints.append(data)
    out: dict[str, Any] = {
        "bus": cfg.bus,
        "i2c_clock_hz": cfg.i2c_clock_hz,
        "joints": joints,
        "gripper": dataclasses.asdict(cfg.gripper),
        "groups": {group: list(members) for group, members in cfg.groups.items()},
    }
    if cfg.dynamixel is not None:
        d = cfg.dynamixel
        out["dynamixel"] = {"port": d.port, "baudrate": d.baudrate, "rs485": d.rs485, "rates": dict(d.rates)}
    if noise is not None:
        out["pid_noise"] = noise_to_dict(noise)
    if cfg.bus_timing != WIRE_ONLY:
        out["bus_timing"] = timing_to_dict(cfg.bus_timing)
    return out


class StrictSafeLoader(yaml.SafeLoader):
    """``yaml.SafeLoader`` that refuses duplicate keys in a mapping.

    Plain YAML keeps the last of two equal keys silently, so a doubled
    ``address:`` line would go unnoticed.
    """

    def construct_mapping(self, node: yaml.MappingNode, deep: bool = False) -> dict:  # type: ignore[override]
        """Construct a mapping after checking its keys are unique."""
        seen: set[tuple[str, str]] = set()
        for key_node, _ in node.value:
            if not isinstance(key_node, yaml.ScalarNode):
                continue
            if key_node.tag == "tag:yaml.org,2002:merge":
                continue
            key = (key_node.tag, key_node.value)
            if key in seen:
                raise yaml.constructor.ConstructorError(
                    "while constructing a mapping",
                    node.start_mark,
                    f"found duplicate key {_show(key_node.value)}",
                    key_node.start_mark,
                )
            seen.add(key)
        return super().construct_mapping(node, deep=deep)


def _parse_yaml(text: str, source: str) -> Any:
    try:
        # Safe loading (no arbitrary objects), plus a duplicate-key check.
        return yaml.load(text, Loader=StrictSafeLoader)
    except yaml.YAMLError as e:
        raise ConfigError(f"{source}: not valid YAML: {' '.join(str(e).split())}") from e
    except RecursionError as e:
        raise ConfigError(f"{source}: nested too deeply to be an arm configuration") from e
    except (ValueError, OverflowError) as e:  # a date such as 2024-13-45, an int of 5000 digits
        raise ConfigError(
            f"{source}: not valid YAML: a value cannot be read: {' '.join(str(e).split())}"
        ) from e


def load_config(path: str | os.PathLike[str] | None = None) -> ArmConfig:
    """Load and validate a YAML configuration file.

    Args:
        path: The file to read; ``None`` loads the packaged
            ``default_config.yaml`` (the arm's own values).

    Returns:
        The validated configuration.

    Raises:
        ConfigError: If the file cannot be read, is not YAML, its top level is
            not a mapping, or any value is invalid; the message starts with
            the path. Read and parse errors are chained (``__cause__``).
    """
    if path is None:
        source = _DEFAULT_SOURCE
        try:
            text = resources.files(_PACKAGE).joinpath(_DEFAULT_CONFIG).read_text(encoding="utf-8")
        except (OSError, ModuleNotFoundError) as e:
            raise ConfigError(
                f"{source}: cannot read the packaged default configuration ({e}); reinstall bioscara_gym"
            ) from e
    else:
        if not isinstance(path, (str, os.PathLike)):
            raise ConfigError(
                f"config {_show(path)} must be the path of a YAML file (or None: the packaged one)"
            )
        source = os.fspath(path)
        if not source:
            raise ConfigError("'': cannot read config file: an empty path; name the configuration file")
        try:
            text = read_bytes(path, MAX_CONFIG_BYTES).decode("utf-8")
        except OSError as e:
            raise ConfigError(f"{source}: cannot read config file: {e.strerror or e}") from e
        except UnicodeDecodeError as e:
            raise ConfigError(f"{source}: not a UTF-8 text file: {e}") from e
    data = _parse_yaml(text, source)
    if not isinstance(data, Mapping):
        found = "an empty document" if data is None else _type_name(data)
        raise ConfigError(f"{source}: top level must be a mapping with 'joints' and 'gripper', found {found}")
    return config_from_dict(data, source)
