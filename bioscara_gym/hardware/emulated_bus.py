"""An I2C bus in memory that serves emulated joint firmware, with fault injection.

It plays the role of pyserial's ``loop://``: the real :class:`Joint` driver
runs unchanged against it, byte for byte.
"""

from __future__ import annotations

import errno
import math
import os
from collections.abc import Mapping
from dataclasses import dataclass, field
from enum import Enum

import numpy as np

from bioscara_gym.hardware.clock import Clock
from bioscara_gym.hardware.firmware import JointFirmware
from bioscara_gym.hardware.registers import I2C_ADDRESS_MAX, I2C_ADDRESS_MIN


class Fault(Enum):
    """A fault the bus can inject into one transaction."""

    NACK = "nack"  # the address is not acknowledged: OSError, nothing delivered
    SHORT_READ = "short_read"  # the command is delivered, the reply comes back short
    CORRUPT = "corrupt"  # the command is delivered, one reply bit is flipped
    LATENCY = "latency"  # the transaction takes ``latency_s`` longer


@dataclass(frozen=True)
class FaultPlan:
    """What faults to inject, by rate and/or by schedule.

    Attributes:
        nack: Probability that a transaction is not acknowledged.
        short_read: Probability that a reply is cut short.
        corrupt: Probability that one bit of a reply is flipped.
        latency_s: Extra time every transaction takes, seconds.
        schedule: Transaction index (bus-wide, from 0) to the fault injected
            there, for deterministic tests.
        seed: Seed of the fault generator.
    """

    nack: float = 0.0
    short_read: float = 0.0
    corrupt: float = 0.0
    latency_s: float = 0.0
    schedule: Mapping[int, Fault] = field(default_factory=dict)
    seed: int | None = 0

    def __post_init__(self) -> None:
        """Validate rates and latency."""
        for name in ("nack", "short_read", "corrupt"):
            rate = getattr(self, name)
            if not 0.0 <= rate <= 1.0:
                raise ValueError(f"fault rate {name}={rate} must be within 0-1")
        if not self.latency_s >= 0.0:
            raise ValueError(f"latency_s={self.latency_s} must be >= 0")

    @classmethod
    def parse(cls, spec: str, seed: int | None = 0) -> FaultPlan:
        """Parse ``"nack=0.01,short_read=0.001,corrupt=0,latency_ms=2"``.

        Raises:
            ValueError: Unknown key or a value that is not a number.
        """
        return cls(seed=seed, **parse_fault_spec(spec, ("nack", "short_read", "corrupt"), "latency"))


def parse_fault_spec(spec: str, rates: tuple[str, ...], duration: str) -> dict[str, float]:
    """Parse ``"KEY=VALUE,..."`` into keyword arguments of a fault plan.

    Args:
        spec: The specification, e.g. ``"nack=0.01,latency_ms=2"``.
        rates: The keys that are probabilities.
        duration: The time fault's name: ``NAME_ms`` and ``NAME_s`` are
            accepted and both give ``NAME_s`` in seconds.

    Raises:
        ValueError: Not KEY=VALUE, a value that is not a finite number, an
            unknown key (the message lists the known ones) or a key given twice.
    """
    known = (*rates, f"{duration}_ms", f"{duration}_s")
    kwargs: dict[str, float] = {}
    for item in filter(None, (s.strip() for s in spec.split(","))):
        key, sep, value = item.partition("=")
        key = key.strip()
        if not sep:
            raise ValueError(f"fault '{item}': expected KEY=VALUE")
        try:
            number = float(value)
        except ValueError as e:
            raise ValueError(f"fault '{key}': '{value}' is not a number") from e
        if not math.isfinite(number):
            raise ValueError(f"fault '{key}': {value} must be finite")
        if key not in known:
            raise ValueError(f"unknown fault '{key}'; expected {', '.join(known)}")
        if key == f"{duration}_ms":
            key, number = f"{duration}_s", number / 1000.0
        if key in kwargs:
            raise ValueError(f"fault '{key}' given twice")
        kwargs[key] = number
    return kwargs


class EmulatedI2CBus:
    """Routes transfers to :class:`JointFirmware` devices by 7-bit address.

    Args:
        devices: Address to firmware.
        faults: Faults to inject (none by default).
        clock: Clock that latency faults advance; defaults to the first
            device's clock.
        record: Keep every transaction in :attr:`history`.

    An absent address raises ``OSError(EREMOTEIO)``, as Linux i2c-dev does
    when no device acknowledges it.
    """

    def __init__(
        self,
        devices: Mapping[int, JointFirmware],
        faults: FaultPlan | None = None,
        clock: Clock | None = None,
        record: bool = False,
    ) -> None:
        """Attach the devices."""
        for address in devices:
            if not I2C_ADDRESS_MIN <= address <= I2C_ADDRESS_MAX:
                raise ValueError(
                    f"device address {address:#04x} is outside {I2C_ADDRESS_MIN:#04x}-{I2C_ADDRESS_MAX:#04x}"
                )
        self.devices = dict(devices)
        self.faults = faults or FaultPlan()
        self._rng = np.random.default_rng(self.faults.seed)
        if clock is None and self.devices:
            clock = next(iter(self.devices.values())).clock
        self.clock = clock
        self.transactions = 0
        self.closed = False
        #: With ``record``: every transaction as ``(time, address, bytes
        #: written, read length)``, the time taken before any latency fault.
        self.history: list[tuple[float, int, bytes, int]] | None = [] if record else None

    def _error(self, address: int) -> OSError:
        return OSError(errno.EREMOTEIO, f"{os.strerror(errno.EREMOTEIO)} (address {address:#04x})")

    def _draw(self, rate: float) -> bool:
        return rate > 0.0 and self._rng.random() < rate

    def transfer(self, address: int, data: bytes, read_len: int) -> bytes:
        """One combined write-then-read transaction (see ``I2CBus``)."""
        if self.closed:
            raise OSError(errno.EBADF, "emulated bus is closed")
        index = self.transactions
        self.transactions += 1
        if self.history is not None:
            self.history.append((self.clock.now() if self.clock else 0.0, address, bytes(data), read_len))
        plan = self.faults
        scheduled = plan.schedule.get(index)
        if plan.latency_s and self.clock is not None:
            self.clock.sleep(plan.latency_s)
        if scheduled is Fault.LATENCY and self.clock is not None:
            self.clock.sleep(max(plan.latency_s, 0.001))
        device = self.devices.get(address)
        if device is None or scheduled is Fault.NACK or self._draw(plan.nack):
            raise self._error(address)
        reply = bytearray(device.transfer(bytes(data), read_len))
        if (scheduled is Fault.SHORT_READ or self._draw(plan.short_read)) and reply:
            return bytes(reply[: int(self._rng.integers(0, len(reply)))])
        if (scheduled is Fault.CORRUPT or self._draw(plan.corrupt)) and reply:
            i = int(self._rng.integers(0, len(reply)))
            reply[i] ^= 1 << int(self._rng.integers(0, 8))
        return bytes(reply)

    def close(self) -> None:
        """Mark the bus closed; later transfers raise ``OSError(EBADF)``."""
        self.closed = True

    def update(self) -> None:
        """Let every device's main loop catch up with the clock."""
        for device in self.devices.values():
            device.update()
