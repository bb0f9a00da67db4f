"""The XL430-W250 control table and protocol 2.0 numbers, as data, with their sources.

Every address, size, access, default and unit of the servo lives here once,
as :mod:`bioscara_gym.hardware.registers` does for the Bioscara joints. The
sources, named in the comments:

* *e-Manual*: the ROBOTIS e-Manual page of the XL430-W250 (control table,
  EEPROM and RAM areas, hardware error bits, baud rate values, units).
* *protocol*: the ROBOTIS e-Manual page of DYNAMIXEL Protocol 2.0 (packet
  layout, instructions, status error field, CRC).
* *MH5*: the MH5 humanoid's hardware documentation (raw-to-SI conversions,
  register initialisation, sync loops and their default rates). The default
  loop rates are those of the MH5 hardware interface's source
  (``setupDynamixelLoops``), the documentation only says that they exist.
* *our choice*: no number in a source.

``docs/dynamixel.md`` describes the servo, the emulator and the driver in prose.
"""

from __future__ import annotations

from dataclasses import dataclass
from enum import IntEnum, IntFlag


@dataclass(frozen=True)
class Field:
    """One item of the control table.

    Attributes:
        name: The e-Manual's name.
        address: First byte.
        size: Bytes (1, 2 or 4), little-endian.
        writable: Whether the host may write it.
        eeprom: In the EEPROM area (0-63): writable only while torque is off.
        default: Value at power-up (EEPROM: as shipped); ``None``: follows the state.
        signed: Whether the value is two's complement.
    """

    name: str
    address: int
    size: int
    writable: bool
    eeprom: bool
    default: int | None = 0
    signed: bool = False


def _f(
    name: str, address: int, size: int, access: str, default: int | None = 0, signed: bool = False
) -> Field:
    return Field(name, address, size, access == "RW", address < 64, default, signed)


#: The control table of the XL430-W250 (e-Manual, "Control Table"; defaults as shipped).
CONTROL_TABLE: tuple[Field, ...] = (
    # ---- EEPROM area (e-Manual): written only while Torque Enable is 0
    _f("Model Number", 0, 2, "R", 1060),
    _f("Model Information", 2, 4, "R", 0),
    _f("Firmware Version", 6, 1, "R", 46),  # our choice of version byte
    _f("ID", 7, 1, "RW", 1),
    _f("Baud Rate", 8, 1, "RW", 1),  # 1 = 57600 bps as shipped
    _f("Return Delay Time", 9, 1, "RW", 250),  # 2 us per unit
    _f("Drive Mode", 10, 1, "RW", 0),
    _f("Operating Mode", 11, 1, "RW", 3),  # 3 = position control
    _f("Secondary ID", 12, 1, "RW", 255),
    _f("Protocol Type", 13, 1, "RW", 2),
    _f("Homing Offset", 20, 4, "RW", 0, signed=True),
    _f("Moving Threshold", 24, 4, "RW", 10),
    _f("Temperature Limit", 31, 1, "RW", 72),  # deg C
    _f("Max Voltage Limit", 32, 2, "RW", 140),  # 0.1 V
    _f("Min Voltage Limit", 34, 2, "RW", 60),  # 0.1 V
    _f("PWM Limit", 36, 2, "RW", 885),
    _f("Velocity Limit", 44, 4, "RW", 265),  # 0.229 rev/min
    _f("Max Position Limit", 48, 4, "RW", 4095),
    _f("Min Position Limit", 52, 4, "RW", 0),
    _f("Startup Configuration", 60, 1, "RW", 0),
    _f("Shutdown", 63, 1, "RW", 52),  # overheating, electrical shock, overload
    # ---- RAM area (e-Manual): reset at power-up and by REBOOT
    _f("Torque Enable", 64, 1, "RW", 0),
    _f("LED", 65, 1, "RW", 0),
    _f("Status Return Level", 68, 1, "RW", 2),
    _f("Registered Instruction", 69, 1, "R", 0),
    _f("Hardware Error Status", 70, 1, "R", 0),
    _f("Velocity I Gain", 76, 2, "RW", 1000),
    _f("Velocity P Gain", 78, 2, "RW", 100),
    _f("Position D Gain", 80, 2, "RW", 4000),
    _f("Position I Gain", 82, 2, "RW", 0),
    _f("Position P Gain", 84, 2, "RW", 640),
    _f("Feedforward 2nd Gain", 88, 2, "RW", 0),
    _f("Feedforward 1st Gain", 90, 2, "RW", 0),
    _f("Bus Watchdog", 98, 1, "RW", 0),
    _f("Goal PWM", 100, 2, "RW", 885, signed=True),
    _f("Goal Velocity", 104, 4, "RW", 0, signed=True),
    _f("Profile Acceleration", 108, 4, "RW", 0),  # 214.577 rev/min^2; 0 = unlimited
    _f("Profile Velocity", 112, 4, "RW", 0),  # 0.229 rev/min; 0 = unlimited
    _f("Goal Position", 116, 4, "RW", None, signed=True),  # power-up: the present position
    _f("Realtime Tick", 120, 2, "R", None),
    _f("Moving", 122, 1, "R", 0),
    _f("Moving Status", 123, 1, "R", 0),
    _f("Present PWM", 124, 2, "R", 0, signed=True),
    _f("Present Load", 126, 2, "R", 0, signed=True),  # 0.1 % of the stall torque
    _f("Present Velocity", 128, 4, "R", 0, signed=True),  # 0.229 rev/min
    _f("Present Position", 132, 4, "R", None, signed=True),  # 0.088 deg
    _f("Velocity Trajectory", 136, 4, "R", 0, signed=True),
    _f("Position Trajectory", 140, 4, "R", None, signed=True),
    _f("Present Input Voltage", 144, 2, "R", 120),  # 0.1 V; our emulator's supply
    _f("Present Temperature", 146, 1, "R", 30),  # deg C; our emulator's
)

#: Field by name.
FIELDS: dict[str, Field] = {f.name: f for f in CONTROL_TABLE}
#: Size of the table the emulator keeps, bytes: up to Present Temperature (e-Manual
#: lists indirect addresses beyond it, which the emulator does not implement).
TABLE_SIZE = 147
#: First RAM address (e-Manual: EEPROM is 0-63).
RAM_START = 64
#: XL430-W250's model number (e-Manual).
MODEL_NUMBER = 1060


def field(name: str) -> Field:
    """The control-table item called ``name`` (e-Manual spelling).

    Raises:
        KeyError: No such item; the message lists the known ones.
    """
    try:
        return FIELDS[name]
    except KeyError:
        raise KeyError(f"no control-table item {name!r}; known: {', '.join(FIELDS)}") from None


# Addresses used on hot paths, as ints.
ADDR_ID = FIELDS["ID"].address
ADDR_OPERATING_MODE = FIELDS["Operating Mode"].address
ADDR_TORQUE_ENABLE = FIELDS["Torque Enable"].address
ADDR_LED = FIELDS["LED"].address
ADDR_HARDWARE_ERROR = FIELDS["Hardware Error Status"].address
ADDR_GOAL_VELOCITY = FIELDS["Goal Velocity"].address
ADDR_PROFILE_ACCELERATION = FIELDS["Profile Acceleration"].address
ADDR_PROFILE_VELOCITY = FIELDS["Profile Velocity"].address
ADDR_GOAL_POSITION = FIELDS["Goal Position"].address
ADDR_PRESENT_LOAD = FIELDS["Present Load"].address
ADDR_PRESENT_VELOCITY = FIELDS["Present Velocity"].address
ADDR_PRESENT_POSITION = FIELDS["Present Position"].address
ADDR_PRESENT_VOLTAGE = FIELDS["Present Input Voltage"].address
ADDR_PRESENT_TEMPERATURE = FIELDS["Present Temperature"].address

#: PVL block read by the ``pvl_reader`` loop: Present Load, Velocity, Position,
#: 126-135, 10 bytes (MH5's PVLReader: start 126, length 10).
PVL_START, PVL_LENGTH = 126, 10
#: TV block read by the ``tv_reader`` loop: Present Input Voltage and
#: Temperature, 144-146 (MH5's TVReader: start 144, length 3).
TV_START, TV_LENGTH = 144, 3
#: Block written by the ``pv_writer`` loop: Goal Velocity, Profile
#: Acceleration, Profile Velocity, Goal Position, 104-119 (our choice: MH5 writes
#: 108-119; we add Goal Velocity so that one SYNC WRITE serves both modes).
PV_START, PV_LENGTH = 104, 16
#: Torque Enable through Hardware Error Status, 64-70, read by ``get_flags``.
STATUS_START, STATUS_LENGTH = 64, 7


class OperatingMode(IntEnum):
    """Operating Mode (11) values the driver uses (e-Manual)."""

    VELOCITY = 1
    POSITION = 3
    EXTENDED_POSITION = 4
    PWM = 16


class HardwareError(IntFlag):
    """Hardware Error Status (70) bits (e-Manual)."""

    INPUT_VOLTAGE = 0x01
    OVERHEATING = 0x04
    MOTOR_ENCODER = 0x08
    ELECTRICAL_SHOCK = 0x10
    OVERLOAD = 0x20


#: Baud Rate (8) value to bits per second (e-Manual).
BAUD_RATES = {
    0: 9600,
    1: 57600,
    2: 115200,
    3: 1_000_000,
    4: 2_000_000,
    5: 3_000_000,
    6: 4_000_000,
    7: 4_500_000,
}


# ------------------------------------------------------------ protocol 2.0
class Instruction(IntEnum):
    """Instruction byte of an instruction packet (protocol)."""

    PING = 0x01
    READ = 0x02
    WRITE = 0x03
    REG_WRITE = 0x04
    ACTION = 0x05
    FACTORY_RESET = 0x06
    REBOOT = 0x08
    CLEAR = 0x10
    STATUS = 0x55
    SYNC_READ = 0x82
    SYNC_WRITE = 0x83
    FAST_SYNC_READ = 0x8A
    BULK_READ = 0x92
    BULK_WRITE = 0x93


class StatusError(IntEnum):
    """Error number, bits 0-6 of a status packet's error byte (protocol)."""

    NONE = 0x00
    RESULT_FAIL = 0x01
    INSTRUCTION = 0x02
    CRC = 0x03
    DATA_RANGE = 0x04
    DATA_LENGTH = 0x05
    DATA_LIMIT = 0x06
    ACCESS = 0x07


#: Bit 7 of a status packet's error byte: the device has a hardware error (protocol).
ALERT = 0x80
#: The broadcast ID: every device executes, none replies except to PING/SYNC/BULK READ (protocol).
BROADCAST_ID = 0xFE
#: Highest device ID (protocol).
MAX_ID = 0xFC
#: Packet header and reserved byte (protocol).
HEADER = b"\xff\xff\xfd\x00"
#: CRC-16 polynomial of protocol 2.0 (protocol: CRC-16-IBM, x^16 + x^15 + x^2 + 1, not reflected).
CRC_POLYNOMIAL = 0x8005

# ------------------------------------------------------------ conversions
#: rad per Present/Goal Position unit: 2*pi/4096 (MH5: 0.001533980787886).
POSITION_RAD_PER_UNIT = 0.001533980787886
#: Raw position of the servo's centre, rad 0 (MH5: 2047).
POSITION_CENTER = 2047
#: rad/s per velocity unit: 0.229 rev/min (MH5: 0.023980823922402).
VELOCITY_RADS_PER_UNIT = 0.023980823922402
#: N*m per Present Load unit: 0.1 % of 1.4 N*m stall torque (MH5: 0.0014).
EFFORT_NM_PER_UNIT = 0.0014
#: V per Present Input Voltage unit (MH5: raw / 100, as it is documented there).
VOLTS_PER_UNIT = 0.01
#: rev/min^2 per Profile Acceleration unit (e-Manual).
ACCELERATION_RPM2_PER_UNIT = 214.577
#: rad/s^2 per Profile Acceleration unit: 214.577 rev/min^2 * 2*pi / 3600.
ACCELERATION_RADS2_PER_UNIT = 214.577 * 2 * 3.141592653589793 / 3600.0


def position_from_raw(raw: int, offset: float = 0.0) -> float:
    """Servo angle, rad: ``(raw - 2047) * 0.001533980787886 + offset`` (MH5)."""
    return (raw - POSITION_CENTER) * POSITION_RAD_PER_UNIT + offset


def position_to_raw(rad: float, offset: float = 0.0) -> int:
    """Raw Goal Position of a servo angle: ``(rad - offset) / 0.001533980787886 + 2047``, rounded (MH5)."""
    return round((rad - offset) / POSITION_RAD_PER_UNIT + POSITION_CENTER)


def velocity_from_raw(raw: int) -> float:
    """rad/s: ``raw * 0.023980823922402`` (MH5)."""
    return raw * VELOCITY_RADS_PER_UNIT


def velocity_to_raw(rad_s: float) -> int:
    """Raw velocity (Goal Velocity, Profile Velocity) of rad/s, rounded."""
    return round(rad_s / VELOCITY_RADS_PER_UNIT)


def effort_from_raw(raw: int) -> float:
    """N*m: ``raw * 0.0014`` (MH5)."""
    return raw * EFFORT_NM_PER_UNIT


def voltage_from_raw(raw: int) -> float:
    """V: ``raw / 100`` (MH5)."""
    return raw / 100.0


def temperature_from_raw(raw: int) -> float:
    """Degrees Celsius: the raw value (MH5)."""
    return float(raw)


def to_signed(value: int, size: int) -> int:
    """Two's complement of a ``size``-byte unsigned value."""
    bits = 8 * size
    return value - (1 << bits) if value & (1 << (bits - 1)) else value


def to_unsigned(value: int, size: int) -> int:
    """The ``size``-byte unsigned pattern of a (possibly negative) value."""
    return value & ((1 << (8 * size)) - 1)


# ------------------------------------------------------------ MH5 loops
#: Default rates of the sync loops, Hz (MH5's ``setupDynamixelLoops``):
#: position/velocity/load read, temperature/voltage read, position/velocity
#: write, torque write.
DEFAULT_LOOP_RATES = {"pvl_reader": 100.0, "tv_reader": 1.0, "pv_writer": 100.0, "t_writer": 2.0}
#: Tries of a PING before a servo counts as absent (MH5: 5 in ``initJoints``).
PING_TRIES = 5
#: Overload (Present Load beyond 100 %) lasting this long sets the Overload
#: bit and, with Shutdown bit 5, turns torque off, s (our choice for the
#: emulator: the e-Manual gives no time).
OVERLOAD_TRIP_S = 0.3
#: A REBOOT leaves the servo silent this long, s (our choice for the emulator).
REBOOT_S = 0.05
