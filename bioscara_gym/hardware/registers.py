"""Register map, flag bits and protocol constants of the joint firmware.

Source: ``stp_reg_t`` in the firmware (``bioscara_joint_firmware``) and in the
host's ``BaseJoint`` (which adds ``NONE``), SPEC.md "The joint's I2C protocol".
Only the registers in :data:`PAYLOAD_FORMAT` are used by the driver; the others
exist in the firmware enum and, when written, go to its blocking handler.
"""

from __future__ import annotations

from enum import IntEnum, IntFlag


class Reg(IntEnum):
    """Every register/command of the firmware enum (``stp_reg_t``)."""

    NONE = 0x00  # host-side only: "no blocking command"
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
    """The flags byte returned as the last byte of every transaction."""

    STALL = 0x01
    BUSY = 0x02
    NOT_HOMED = 0x04
    NOT_ENABLED = 0x08


#: Flags at power-up: not homed, not enabled.
POWER_UP_FLAGS = Flag.NOT_HOMED | Flag.NOT_ENABLED
#: PING's reply payload (ASCII 'O').
ACK = ord("O")
#: Largest payload in bytes (``MAX_BUFFER``); the flags byte comes on top.
MAX_PAYLOAD = 4
#: Size of the flags byte (``RFLAGS_SIZE``).
FLAGS_SIZE = 1

#: struct format (little-endian) of each used register's payload.
PAYLOAD_FORMAT: dict[Reg, str] = {
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

#: Registers the firmware answers with a payload (read when sent without one).
READ_REGISTERS = frozenset({Reg.PING, Reg.ANGLEMOVED, Reg.GETENCODERRPM, Reg.HOMEOFFSET})
#: Commands the firmware runs in its main loop, with BUSY set meanwhile.
BLOCKING_COMMANDS = frozenset({Reg.HOME, Reg.CHECKORIENTATION})


class BrakeMode(IntEnum):
    """Payload of SETBRAKEMODE."""

    FREEWHEEL = 0
    COOLBRAKE = 1
    HARDBRAKE = 2
