"""How long a joint transaction takes on the I2C wire, counted bit by bit.

Every exchange with a joint is one combined transaction (docs/protocol.md):
the master writes ``[REG][payload]``, sends a repeated START, reads
``payload + flags`` and ends with a STOP. On the wire (I2C specification, NXP
UM10204) that is, in clock periods:

======================  =====  =============================================
START                   1      :data:`~.registers.I2C_CONDITION_BITS`
address + W, ACK        9      :data:`~.registers.I2C_BITS_PER_BYTE`
each written byte, ACK  9
repeated START          1
address + R, ACK        9      the joint's ``requestEvent`` runs here
each read byte, ACK     9      NACK after the last one
STOP                    1
======================  =====  =============================================

so ``21 + 9 × (written + read bytes)`` periods: an ANGLEMOVED (1 written, 5
read) or a SETRPM (5 written, 1 read) is 75 periods, 750 us at 100 kHz.
:func:`wire_phases_s` splits a transaction where the joint's handler runs
(it samples a reading or applies a command there), so the emulated bus and
the sim backend put that instant where the wire does.
"""

from __future__ import annotations

import math

from bioscara_gym.hardware.registers import (
    I2C_BITS_PER_BYTE,
    I2C_CONDITION_BITS,
    I2C_MAX_CLOCK_HZ,
    I2C_MIN_CLOCK_HZ,
)


def check_clock_hz(clock_hz: float) -> float:
    """Return ``clock_hz`` as a float if it is a usable bus clock.

    Raises:
        ValueError: Not a number within :data:`~.registers.I2C_MIN_CLOCK_HZ`-
            :data:`~.registers.I2C_MAX_CLOCK_HZ` (one line naming ``i2c_clock_hz``).
    """
    if isinstance(clock_hz, bool) or not isinstance(clock_hz, int | float) or not math.isfinite(clock_hz):
        raise ValueError(f"i2c_clock_hz={clock_hz!r} must be a finite number of Hz (e.g. 100000 or 400000)")
    if not I2C_MIN_CLOCK_HZ <= clock_hz <= I2C_MAX_CLOCK_HZ:
        raise ValueError(
            f"i2c_clock_hz={clock_hz!r} must be within {I2C_MIN_CLOCK_HZ}-{I2C_MAX_CLOCK_HZ} Hz "
            "(100000 standard mode, 400000 fast mode)"
        )
    return float(clock_hz)


def wire_bits(write_len: int, read_len: int) -> tuple[int, int]:
    """Clock periods of a transaction before and after the joint's handler runs.

    Before: START, the address byte and every written byte, and for a read
    phase the repeated START and the address byte again (the slave's
    ``requestEvent`` runs once that address is acknowledged). After: every
    read byte and the STOP. A transaction without a write phase starts with
    the read's address; one without a read phase has nothing after the
    written bytes but the STOP.

    Args:
        write_len: Bytes the master writes (register and payload).
        read_len: Bytes the master reads (payload and flags).

    Raises:
        ValueError: A negative length.
    """
    if write_len < 0 or read_len < 0:
        raise ValueError(f"transaction lengths must be >= 0, got write {write_len}, read {read_len}")
    before = 0
    if write_len or not read_len:
        before += I2C_CONDITION_BITS + I2C_BITS_PER_BYTE * (1 + write_len)
    if read_len:
        before += I2C_CONDITION_BITS + I2C_BITS_PER_BYTE
    return before, I2C_BITS_PER_BYTE * read_len + I2C_CONDITION_BITS


def wire_phases_s(write_len: int, read_len: int, clock_hz: float) -> tuple[float, float]:
    """Seconds of a transaction on the wire before and after the joint's handler (see :func:`wire_bits`)."""
    before, after = wire_bits(write_len, read_len)
    return before / clock_hz, after / clock_hz


def wire_time_s(write_len: int, read_len: int, clock_hz: float) -> float:
    """Seconds a combined write-then-read transaction occupies the bus at ``clock_hz``.

    Args:
        write_len: Bytes written (register and payload).
        read_len: Bytes read (payload and flags).
        clock_hz: The bus clock, Hz (100 000 standard mode, 400 000 fast mode).
    """
    return sum(wire_bits(write_len, read_len)) / clock_hz


def nack_time_s(clock_hz: float) -> float:
    """Seconds a transaction whose address is not acknowledged occupies the bus: START, address, STOP."""
    return (2 * I2C_CONDITION_BITS + I2C_BITS_PER_BYTE) / clock_hz
