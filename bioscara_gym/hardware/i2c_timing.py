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
from collections.abc import Mapping
from dataclasses import dataclass, field

from bioscara_gym.hardware.registers import (
    I2C_BITS_PER_BYTE,
    I2C_CONDITION_BITS,
    I2C_MAX_CLOCK_HZ,
    I2C_MIN_CLOCK_HZ,
    Reg,
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


@dataclass(frozen=True)
class TransactionTiming:
    """What a transaction takes on the real bus beyond its bits (``RW_test/``).

    The arm's own measurements (``RW_test/README.md``) split a transaction's
    time into the bits on the wire, the joint's handler (the request
    interrupt runs while the joint stretches the clock: 5 us for ANGLEMOVED,
    351 us for MOVETOANGLE) and the host's overhead, which depends a little
    on the bus speed (about 105 us at 100 kHz, 80 us at 400 kHz). This model
    charges the host a fixed time plus a few clock periods per transaction,
    and the handler by register; the values are fitted by ``bioscara
    calibrate`` and live in the configuration's ``bus_timing`` block.

    Attributes:
        host_overhead_s: Per transaction, before its START (the i2c-dev call), s.
        extra_periods: Clock periods the controller adds per transaction.
        handler_s: The joint's request handler by register byte, s (others: 0).
        program_overhead_s: What the arm's test programs spend per loop pass
            besides their sleep and transactions (printing a line), s; the
            validation replays them with it.
    """

    host_overhead_s: float = 0.0
    extra_periods: float = 0.0
    handler_s: Mapping[int, float] = field(default_factory=dict, hash=False)
    program_overhead_s: float = 0.0

    def __post_init__(self) -> None:
        """Check the values (one line naming the field)."""
        for name in ("host_overhead_s", "extra_periods", "program_overhead_s"):
            v = getattr(self, name)
            if isinstance(v, bool) or not isinstance(v, int | float) or not math.isfinite(v) or v < 0:
                raise ValueError(f"bus_timing: {name}={v!r} must be a finite number >= 0")
        for reg, v in self.handler_s.items():
            if isinstance(v, bool) or not isinstance(v, int | float) or not math.isfinite(v) or v < 0:
                raise ValueError(f"bus_timing: handler time of register {reg:#04x} = {v!r} must be >= 0")

    def phases_s(
        self, write_len: int, read_len: int, clock_hz: float | None, reg: int
    ) -> tuple[float, float]:
        """Seconds before the joint's handler runs and after it, this transaction included.

        The host's overhead and the extra periods come first; the handler's
        time is on the joint's side of the split (it answers once done).
        """
        before = self.host_overhead_s
        after = self.handler_s.get(reg, 0.0)
        if clock_hz:
            wire_before, wire_after = wire_phases_s(write_len, read_len, clock_hz)
            before += wire_before + self.extra_periods / clock_hz
            after += wire_after
        return before, after

    def transaction_s(self, write_len: int, read_len: int, clock_hz: float | None, reg: int) -> float:
        """Seconds the whole transaction takes, host call included."""
        return sum(self.phases_s(write_len, read_len, clock_hz, reg))


#: No time beyond the bits: what the emulator charged before the calibration.
WIRE_ONLY = TransactionTiming()


def timing_from_dict(data: object) -> TransactionTiming:
    """The configuration's ``bus_timing:`` block (microseconds, handlers by register name).

    Raises:
        ValueError: Not a mapping, an unknown field or register, or a bad number.
    """
    allowed = ("host_overhead_us", "extra_periods", "handler_us", "program_overhead_us")
    if not isinstance(data, dict):
        raise ValueError(f"bus_timing must be a mapping of {', '.join(allowed)}")
    for key in data:
        if key not in allowed:
            raise ValueError(f"bus_timing: unknown field {key!r}; allowed: {', '.join(allowed)}")
    handlers = data.get("handler_us", {}) or {}
    if not isinstance(handlers, dict):
        raise ValueError("bus_timing.handler_us must map register names to microseconds")
    handler_s = {}
    for name, us in handlers.items():
        if name not in Reg.__members__:
            raise ValueError(
                f"bus_timing.handler_us: unknown register {name!r} (e.g. ANGLEMOVED, MOVETOANGLE)"
            )
        if isinstance(us, bool) or not isinstance(us, int | float):
            raise ValueError(f"bus_timing.handler_us.{name}={us!r} must be a number of microseconds")
        handler_s[int(Reg[name])] = us * 1e-6
    us = {}
    for key in ("host_overhead_us", "program_overhead_us"):
        value = data.get(key, 0.0)
        if isinstance(value, bool) or not isinstance(value, int | float):
            raise ValueError(f"bus_timing.{key}={value!r} must be a number of microseconds")
        us[key] = value
    return TransactionTiming(
        us["host_overhead_us"] * 1e-6,
        data.get("extra_periods", 0.0),
        handler_s,
        us["program_overhead_us"] * 1e-6,
    )


def timing_to_dict(timing: TransactionTiming) -> dict[str, object]:
    """Plain data of a :class:`TransactionTiming` (see :func:`timing_from_dict`)."""
    return {
        "host_overhead_us": round(timing.host_overhead_s * 1e6, 3),
        "extra_periods": timing.extra_periods,
        "handler_us": {Reg(reg).name: round(s * 1e6, 3) for reg, s in sorted(timing.handler_s.items())},
        "program_overhead_us": round(timing.program_overhead_s * 1e6, 3),
    }
