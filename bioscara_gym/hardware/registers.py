"""The joint protocol's numbers as data: registers, flag bits, payloads, timings.

Every number of the I2C protocol between the host and a joint lives here once,
with its source beside it (compare LeRobot's ``motors/feetech/tables.py``).
The sources, named in the comments:

* *firmware*: the joint firmware ``joint.ino`` in the public repository
  DALSA-Lab/bioscara (``lib/joint_firmware/joint``); where it differs from
  the documentation, it wins (the emulator does what the firmware does).
* *C++ API*: the Bioscara C++ API reference, ``BaseJoint`` page (the host
  driver this package re-implements; its register table and rules).
* *parameter file*: the arm's parameter file (addresses, currents, thresholds).
* *I2C specification*: the I2C-bus specification (reserved addresses).

``docs/protocol.md`` and ``docs/firmware.md`` describe the protocol and the
firmware's behaviour in prose.

Only the registers in :data:`PAYLOAD_FORMAT` are used by the driver; the
others exist in the firmware enum and, when written, go to its blocking
handler.
"""

from __future__ import annotations

from enum import IntEnum, IntFlag


class Reg(IntEnum):
    """Every register/command of the firmware enum ``stp_reg_t`` (firmware; C++ API)."""

    NONE = 0x00  # host-side only (C++ API): "no blocking command"
    PING = 0x0F
    SETUP = 0x10
    SETRPM = 0x11
    GETDRIVERRPM = 0x12
    MOVESTEPS = 0x13
    MOVEANGLE = 0x14
    MOVETOANGLE = 0x15
    GETMOTORSTATE = 0x16
    RUNCOTINOUS = 0x17  # sic, the firmware's spelling
    ANGLEMOVED = 0x18
    SETCURRENT = 0x19
    SETHOLDCURRENT = 0x1A
    SETMAXACCELERATION = 0x1B
    SETMAXDECELERATION = 0x1C
    SETMAXVELOCITY = 0x1D
    ENABLESTALLGUARD = 0x1E
    DISABLESTALLGUARD = 0x1F
    CLEARSTALL = 0x20
    SETBRAKEMODE = 0x22
    ENABLEPID = 0x23
    DISABLEPID = 0x24
    ENABLECLOSEDLOOP = 0x25
    DISABLECLOSEDLOOP = 0x26
    SETCONTROLTHRESHOLD = 0x27
    MOVETOEND = 0x28
    STOP = 0x29
    GETPIDERROR = 0x2A
    CHECKORIENTATION = 0x2B
    GETENCODERRPM = 0x2C
    HOME = 0x2D
    HOMEOFFSET = 0x2E


class Flag(IntFlag):
    """The flags byte, the last byte of every reply (firmware; C++ API).

    Bit 0 is the least significant; bits 4-7 are reserved and always 0.
    """

    STALL = 0x01
    BUSY = 0x02
    NOT_HOMED = 0x04
    NOT_ENABLED = 0x08


# The flag bits as plain ints, for the per-tick hot paths of the firmware
# emulation and the drivers (IntFlag arithmetic is slow there).
#: :attr:`Flag.STALL` as an int.
FLAG_STALL = int(Flag.STALL)
#: :attr:`Flag.BUSY` as an int.
FLAG_BUSY = int(Flag.BUSY)
#: :attr:`Flag.NOT_HOMED` as an int.
FLAG_NOT_HOMED = int(Flag.NOT_HOMED)
#: :attr:`Flag.NOT_ENABLED` as an int.
FLAG_NOT_ENABLED = int(Flag.NOT_ENABLED)
#: Every defined flag bit (0x0F).
FLAG_MASK = FLAG_STALL | FLAG_BUSY | FLAG_NOT_HOMED | FLAG_NOT_ENABLED
#: Bits 4-7 of the flags byte: reserved, 0 in every valid reply (firmware).
RESERVED_FLAG_BITS = 0xFF & ~FLAG_MASK

#: Flags at power-up, ``0b00001100``: not homed, not enabled (firmware).
POWER_UP_FLAGS = Flag.NOT_HOMED | Flag.NOT_ENABLED
#: PING's reply payload, ASCII 'O'; anything else fails the check (C++ API).
ACK = ord("O")
#: Largest payload in bytes, ``MAX_BUFFER``; the flags byte comes on top (firmware).
MAX_PAYLOAD = 4
#: Size of the flags byte, ``RFLAGS_SIZE`` (firmware).
FLAGS_SIZE = 1

#: struct format (little-endian) of each used register's payload (C++ API
#: register table; the firmware ``memcpy``'s the bytes into the value).
#: Registers without an entry carry no payload the driver uses.
PAYLOAD_FORMAT: dict[Reg, str] = {
    Reg.PING: "<B",  # 'O' (ACK)
    Reg.SETUP: "<I",  # byte0 drive current %, byte1 hold current %
    Reg.SETRPM: "<f",  # motor RPM
    Reg.MOVESTEPS: "<i",  # full steps
    Reg.MOVETOANGLE: "<f",  # motor degrees, absolute
    Reg.ANGLEMOVED: "<f",  # motor degrees since the encoder was zeroed
    Reg.SETCURRENT: "<B",  # drive current %
    Reg.SETHOLDCURRENT: "<B",  # hold current %
    Reg.SETMAXACCELERATION: "<f",  # deg/s^2, also the deceleration
    Reg.SETMAXVELOCITY: "<f",  # deg/s
    Reg.ENABLESTALLGUARD: "<B",  # sensitivity
    Reg.SETBRAKEMODE: "<B",  # BrakeMode
    Reg.DISABLECLOSEDLOOP: "<B",  # 0
    Reg.STOP: "<B",  # mode (read and unused by the firmware)
    Reg.CHECKORIENTATION: "<f",  # motor degrees
    Reg.GETENCODERRPM: "<f",  # motor RPM measured by the encoder
    Reg.HOME: "<I",  # byte0 direction, byte1 RPM, byte2 sensitivity, byte3 current %
    Reg.HOMEOFFSET: "<f",  # joint-side offset the host stores after homing
}
#: Registers the firmware answers with a payload (read when sent without one).
READ_REGISTERS = frozenset({Reg.PING, Reg.ANGLEMOVED, Reg.GETENCODERRPM, Reg.HOMEOFFSET})
#: Commands the firmware runs in its main loop, with BUSY set meanwhile (firmware).
BLOCKING_COMMANDS = frozenset({Reg.HOME, Reg.CHECKORIENTATION})


class BrakeMode(IntEnum):
    """Payload of SETBRAKEMODE (C++ API)."""

    FREEWHEEL = 0
    COOLBRAKE = 1
    HARDBRAKE = 2


# ------------------------------------------------------------ addresses
#: Lowest 7-bit address a device may use; 0x00-0x02 are reserved (I2C specification).
I2C_ADDRESS_MIN = 0x03
#: Highest 7-bit address a device may use; 0x78-0x7F are reserved (I2C specification).
I2C_ADDRESS_MAX = 0x77

# ------------------------------------------------------ payload ranges
#: Currents are percent of the driver's 2.5 A output, 0-100 (C++ API; parameter file).
CURRENT_MAX_PCT = 100
#: Stall and homing sensitivities are one unsigned byte, 0-255, lower trips
#: earlier (C++ API; parameter file).
SENSITIVITY_MAX = 255
#: Homing speed bounds in motor RPM, exclusive: ``1.0 < |rpm| < 250.0``, else
#: INVALID_ARGUMENT (C++ API ``BaseJoint::home``; HOME carries the speed as
#: one unsigned byte).
HOMING_RPM_MIN = 1.0
HOMING_RPM_MAX = 250.0

# --------------------------------------------------- firmware timings
#: Main-loop period in seconds: stall detection and the deadman run once per
#: 10 ms tick (firmware).
TICK_S = 0.01
#: Deadman: an enabled joint with a non-zero SETRPM set point stops (speed 0,
#: NOT_ENABLED) after this silence on the bus, seconds (firmware: 50 ms).
DEADMAN_S = 0.05
#: Homing stops hard and waits this long before it runs, seconds (firmware: 500 ms).
HOMING_SETTLE_S = 0.5

# ------------------------------------------------------ stall detection
# The firmware's stall detector, once per tick while enabled and not stalled:
# u = |PID error|; an upward jump above STALL_SPIKE_LIMIT keeps the last value;
# x <- (1 - Ts/tau) x + (Ts/tau) u; STALL when x exceeds
# STALL_SLOPE * |omega| + STALL_THRESHOLD_PER_SENSITIVITY * sensitivity, plus
# STALL_MID_SPEED_OFFSET while omega (motor rad/s) is inside STALL_MID_SPEED_BAND.
#: Spike filter: a jump of |PID error| above this per tick is ignored (firmware: 100).
STALL_SPIKE_LIMIT = 100.0
#: Time constant of the stall detector's low-pass filter, seconds (firmware: tau = 0.1 s).
STALL_TAU_S = 0.1
#: Threshold per unit of ENABLESTALLGUARD sensitivity (firmware and C++ API: 10x).
STALL_THRESHOLD_PER_SENSITIVITY = 10.0
#: Slope of the speed-adaptive threshold per motor rad/s (firmware: 0).
STALL_SLOPE = 0.0
#: Extra threshold inside the mid-speed band (firmware: +90).
STALL_MID_SPEED_OFFSET = 90.0
#: Motor speed band in rad/s, inclusive, that gets the extra threshold (firmware: 12-450).
STALL_MID_SPEED_BAND = (12.0, 450.0)
