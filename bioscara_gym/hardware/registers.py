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
    Reg.MOVESTEPS: "<i",  # microsteps, 1/256 full step (the library's moveSteps)
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

# ------------------------------------------------------------- bus timing
# What a transaction costs on the wire; the count is in docs/protocol.md
# ("Wire time") and the formula in ``i2c_timing.py``.
#: Standard-mode bus clock, Hz: the Raspberry Pi's default (``i2c_arm_baudrate``,
#: Raspberry Pi device-tree documentation) and ours; Standard-mode is "up to
#: 100 kbit/s" (I2C specification, NXP UM10204).
I2C_STANDARD_MODE_HZ = 100_000
#: Fast-mode bus clock, Hz, the other common setting: "up to 400 kbit/s" (UM10204).
I2C_FAST_MODE_HZ = 400_000
#: Fast-mode Plus, "up to 1 Mbit/s" (UM10204): the highest clock accepted, Hz.
I2C_MAX_CLOCK_HZ = 1_000_000
#: The lowest clock accepted, Hz: SMBus's minimum (System Management Bus
#: specification 3.1, f_SMB 10 kHz); slower is a typo, not a setting.
I2C_MIN_CLOCK_HZ = 10_000
#: Default bus clock of the emulated bus and the sim backend's wire time, Hz (the Pi's default).
I2C_CLOCK_HZ = I2C_STANDARD_MODE_HZ
#: Clock periods per byte on the wire: 8 data bits, most significant first, then
#: the receiver's ACK (or the master's NACK after the last byte it reads); the
#: address byte is 7 address bits and R/W (UM10204, "Byte format",
#: "Acknowledge (ACK) and Not Acknowledge (NACK)", "The slave address and R/W bit").
I2C_BITS_PER_BYTE = 9
#: Clock periods counted for each START, repeated START and STOP condition
#: (our model: UM10204's set-up and hold times of a condition, 4.0-4.7 us in
#: Standard-mode and 0.6-1.3 us in Fast-mode, are about one clock period).
I2C_CONDITION_BITS = 1

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

# ---------------------------------- what a configuration may ask of a joint
# Values the motor or the firmware cannot honour are refused when the
# configuration is loaded (hardware/config.py), with these bounds.

#: Lowest homing sensitivity: the homing stops at the first PID-error sample
#: above it (firmware, polled every 1 ms), and the PID error of a free joint
#: at rest reaches 17 (high_speed_stall_test/J3_UP_ramp.csv, ``data 0``); a
#: lower threshold ends the homing where the joint stands: threshold 0
#: "homed" j1 at once, believed 3.0465 rad, true 2.9246 (issue #24). The arm
#: uses 25-50 (parameter file); 20 leaves room above the noise (our choice).
HOMING_THRESHOLD_MIN = 20
#: Lowest stall sensitivity a configuration may ask for: the stall threshold
#: is 10 x the sensitivity at standstill (firmware), so below 2 it lies under
#: the PID error of a free joint at rest (17, as above) and trips standing still.
STALL_SENSITIVITY_MIN = 2
#: Lowest homing and drive current, percent: at 0 % the motor has no torque,
#: so a homing "finds its stop" where it stands and a drive cannot move.
DRIVE_CURRENT_MIN_PCT = 1
#: Fastest motor speed a joint may be configured for, RPM. The fastest the
#: real motors were measured to turn is 1639 RPM (maxAccel/j4_5: j4 at
#: 14.3 rad/s, reduction 12, commanded 20 rad/s); 2000 RPM, 1.2 times that,
#: is beyond what they can do (our choice). A limit above it (j4 at
#: 1e6 rad/s was accepted) clamps nothing.
MOTOR_RPM_MAX = 2000.0
#: Largest motor acceleration a joint may be configured for, deg/s^2: what the
#: driver chip's 16-bit AMAX field holds (0xFFFF / (200/360 x 256 x 0.0220),
#: 20,945; ``drive.velocity_mode_acceleration``), rounded down. Above it the
#: library's cast wraps, and the joint ramps at a fraction of its limit:
#: 20,946 deg/s^2 becomes 0.32. The real arm shows it: ``maxAccel/j4_4`` set
#: 23,377 and ramped at 2,431 (j4 reached 1.9 rad/s of 10), ``j2_5`` set
#: 27,000 and ramped at 6,055. (Before, 30,000 was accepted.)
MOTOR_ACCELERATION_MAX_DPS2 = 20_900.0

# --------------------------------------------------- firmware timings
#: Main-loop period in seconds: stall detection and the deadman run once per
#: 10 ms tick (firmware).
TICK_S = 0.01
#: Deadman: an enabled joint whose last SETRPM value is non-zero (in any mode)
#: stops (RPM 0, NOT_ENABLED) after more than this silence on the bus, seconds
#: (firmware: 50 ms; see :data:`DEADMAN_MS`).
DEADMAN_S = 0.05
#: Deadman in whole milliseconds of ``millis()``: it fires when more than this
#: has passed since the last transaction's reply, checked once per main-loop
#: pass (firmware: ``diff > 50``).
DEADMAN_MS = 50
#: Homing stops hard and waits this long before it runs, seconds (firmware: 500 ms).
HOMING_SETTLE_S = 0.5
#: The homing loop reads the PID error this often, seconds (firmware: ``delay(1)``).
HOMING_POLL_S = 0.001
#: Divisor from encoder RPM to rad/s in the stall detector, as written in the
#: firmware (60/2pi would be 9.549296585513721; firmware: 9.549296596425384).
STALL_RPM_PER_RAD_S = 9.549296596425384
#: How long the host must leave a joint alone after HOME, CHECKORIENTATION (or
#: any other blocking command), seconds, so the main loop picks the command up
#: first: any transaction before that cancels it while BUSY stays set until a
#: STOP (firmware: ``non_blocking_handler`` begins with ``rx_data_ready = 0``).
#: Worst case the command arrives just after the loop looked: the rest of that
#: pass, ``delay(10)``, then the next pass's stall-detection branch, which
#: prints about 40 characters at 9600 baud (about 42 ms if the serial port
#: blocks, unmeasured; docs/firmware.md). 10 + 42 ms, rounded up with margin
#: for the interrupt and library calls: 60 ms, i.e. six 10 ms ticks of the
#: emulator, which picks a command up at the next tick (our choice).
BLOCKING_PICKUP_S = 0.06

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

# ------------------------------------------- host: retries and reply checks
# The protocol has no checksum and no sequence number (docs/protocol.md), so
# the host decides per register whether a failed transaction may be sent
# again, and checks every reply against what the firmware can produce.

#: Commands the driver may send again after a failed transaction (a NACK, a
#: short, malformed or implausible reply), because running one twice leaves
#: the joint as running it once does (firmware semantics, docs/firmware.md).
#: Reads (PING, ANGLEMOVED, GETENCODERRPM, HOMEOFFSET without payload) change
#: nothing but the deadman timer and are always retried. Not in the set, so
#: sent at most once: MOVESTEPS (relative: a second run moves as far again),
#: HOME (a second one restarts the 0.5 s stop-and-run, or runs a second
#: homing after the first) and CHECKORIENTATION (turns the motor again); the
#: original C++ driver retries nothing.
IDEMPOTENT_COMMANDS = frozenset(
    {
        # currents := the payload, moveSteps(0) (stops where the motor is),
        # stall detection off, STALL/NOTENABLED cleared, SETRPM memory 0:
        # a second run finds the motor already stopped there.
        Reg.SETUP,
        Reg.SETRPM,  # an absolute speed, stored and applied (unless STALL)
        Reg.MOVETOANGLE,  # an absolute target (from the encoder's home)
        Reg.SETCURRENT,  # drive current := payload (0 also sets NOTENABLED)
        Reg.SETHOLDCURRENT,  # hold current := payload (0 also sets NOTENABLED)
        Reg.SETMAXACCELERATION,  # limit := payload
        Reg.SETMAXVELOCITY,  # limit := payload
        # threshold := 10 x payload, detection on, STALL cleared. A second run
        # clears STALL again: only a stall detected in the few ms between the
        # two attempts (the motor is then already stopped) would go unreported.
        Reg.ENABLESTALLGUARD,
        Reg.SETBRAKEMODE,  # mode := payload
        Reg.DISABLECLOSEDLOOP,  # closed loop off, NOTENABLED set; once off it stays off
        Reg.STOP,  # setRPM(0), BUSY cleared; a second STOP finds it stopped
        Reg.HOMEOFFSET,  # offset := payload (the firmware never uses it)
    }
)

#: Flags a command's reply must show set / clear whatever the joint's state,
#: because the command's handler sets / clears them in the interrupt before
#: the flags byte is appended (firmware ``requestEvent``): a reply without
#: them is corrupted. SETCURRENT 0 and SETHOLDCURRENT 0 also set NOTENABLED
#: (checked by the driver, the payload decides). Left out on purpose: SETUP's
#: reply with NOTENABLED raises NotEnabledError as the C++ API's enable does
#: (only STALL is checked), once two PINGs agree with it (a flipped bit does
#: not: ``Joint._confirm_sticky_flags``), and DISABLECLOSEDLOOP's reply is not checked.
REPLY_FLAGS_SET: dict[Reg, int] = {
    Reg.HOME: int(Flag.BUSY | Flag.NOT_HOMED),
    Reg.CHECKORIENTATION: int(Flag.BUSY),
}
#: Flags that, once set, stay set until a command clears them: STALL (SETUP,
#: ENABLESTALLGUARD), NOTENABLED (SETUP), NOTHOMED (the end of a homing, which
#: only a HOME starts). The stall detector, the deadman and a power cycle set
#: them between transactions, so one may appear in any reply; a corrupted flags
#: byte can show one too. A reply showing one newly set, that its own command
#: does not set, is confirmed by reading the flags again (a PING): if the
#: second reading lacks it, the first was corrupted (docs/protocol.md).
STICKY_FLAGS = int(Flag.STALL | Flag.NOT_ENABLED | Flag.NOT_HOMED)
#: The sticky flags a command's handler clears (firmware ``joint.ino``: SETUP
#: sets ``notEnabled = 0`` and ``isStalled = 0``, ENABLESTALLGUARD
#: ``isStalled = 0``); the end of a homing clears NOTHOMED and STALL. A reply
#: showing one gone that its command (or a homing running) does not clear is
#: confirmed by reading the flags again, as a newly set one is.
FLAGS_CLEARED_BY: dict[Reg, int] = {
    Reg.SETUP: int(Flag.STALL | Flag.NOT_ENABLED),
    Reg.ENABLESTALLGUARD: int(Flag.STALL),
}
#: Readings of the flags (PINGs) that must all show a newly set sticky flag
#: (or one gone, or BUSY gone while HOME or CHECKORIENTATION runs) before the driver
#: believes it. With one, a flipped bit in the reply and the same bit
#: flipped in its confirming PING ended a deploy on a false NOT_ENABLED at
#: ``corrupt=0.05`` (issue #24); with two, a false flag needs
#: three flips of the same bit in a row, while a real stall or deadman trip
#: costs two PINGs once (our choice).
STICKY_CONFIRMATIONS = 2

#: See :data:`REPLY_FLAGS_SET`: flags the reply to a command must show clear.
REPLY_FLAGS_CLEAR: dict[Reg, int] = {
    Reg.SETUP: int(Flag.STALL),
    Reg.ENABLESTALLGUARD: int(Flag.STALL),
    Reg.STOP: int(Flag.BUSY),
}

#: Plausibility of a position read (ANGLEMOVED), as a fraction of the joint's
#: range (max - min). The joint cannot pass its end stops, which are its
#: limits (the homing zero is one of them, docs/arm.md), so a homed joint
#: reads within [min, max] but for the encoder's lag and the stops'
#: compliance; 10 % of the range (j1 0.61 rad, j2 34 mm) is far beyond that
#: and still catches a flipped sign or high exponent bit of a position far
#: from the zero (our choice). A joint that is not homed counts from wherever
#: it was at power-up: it reads within one range (plus the margin) of 0, plus
#: :data:`POSITION_UNHOMED_EXTRA_DEG`.
POSITION_MARGIN_FRACTION = 0.1
#: Extra motor degrees allowed on a joint that is not homed: the encoder is
#: absolute within one motor turn and may count from its angle at power-up
#: rather than from 0 (uStepper S32 encoder; our caution).
POSITION_UNHOMED_EXTRA_DEG = 360.0
#: Plausibility of an encoder speed read (GETENCODERRPM), motor RPM. Just
#: above the top of the firmware's own stall-detection speed window, 450 rad/s
#: = 4297 RPM (``configuration.h``, :data:`STALL_MID_SPEED_BAND`), the fastest
#: speed the firmware's configuration anticipates; about four times the
#: fastest configured joint speed (j3, j4: 120 rad/s = 1146 RPM at the motor),
#: and beyond what a NEMA17 hybrid stepper turns under its own power
#: (15 000 full steps/s) (our choice).
MAX_PLAUSIBLE_RPM = 4500.0

# ------------------------------------- host: believing a position reading
# A position read (ANGLEMOVED) of a homed joint is compared with the last one
# the driver believed: a reading that implies a move faster than the joint can
# make in the time between is read again before anyone sees it
# (docs/protocol.md, "Positions are read again when they jump"). A flipped
# mantissa or exponent bit that leaves the value within the end stops is
# caught this way; the range checks above cannot see it.

#: Factor on the joint's speed and acceleration limits (the ones the driver
#: sent: SETMAXVELOCITY, SETMAXACCELERATION, or the configuration's) before a
#: move counts as too fast. The real joints exceed their limits: j4 reached
#: 14.3 rad/s, 1.43 times its configured 10 rad/s, when commanded 20
#: (maxAccel/j4_5), and accelerated at up to 37 rad/s^2, 1.24 times the 30 set
#: (maxAccel/j4_5, column qdd); 2 leaves room above both (our choice).
PLAUSIBLE_SPEED_MARGIN = 2.0
#: Motor degrees a reading may lie beyond the predicted reach: encoder noise,
#: the rotor's lag and lurches behind its ramped set point, and the timing of
#: the samples. Over every pair of successive readings in the real arm's
#: recordings (maxAccel/, settingMaxVal/, tracking_error/), the largest lurch
#: beyond the ramp the limits allow (with the margin above) is 3.9 motor
#: degrees (maxAccel/j1_3: j1 at 3 rad/s^2, where it skips steps audibly);
#: 5 degrees, under 3 full steps (our choice). A reading of j1 off by bit 13
#: of its float (4 degrees at 4100) is then still believed: 0.11 degrees at
#: the joint.
PLAUSIBLE_JUMP_DEG = 5.0
#: Readings at least this far apart in time give a speed the next bound may
#: use (the firmware's main-loop period: closer readings see the same sample).
PLAUSIBLE_SPEED_MIN_DT_S = TICK_S
