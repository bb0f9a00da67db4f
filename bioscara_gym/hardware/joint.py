"""The real joint driver: the register protocol over an :class:`I2CBus`."""

from __future__ import annotations

import math

from bioscara_gym.hardware import codec
from bioscara_gym.hardware.base_joint import BaseJoint
from bioscara_gym.hardware.bus import I2CBus
from bioscara_gym.hardware.clock import Clock
from bioscara_gym.hardware.errors import CommError, InvalidArgumentError
from bioscara_gym.hardware.registers import (
    ACK,
    FLAGS_SIZE,
    I2C_ADDRESS_MAX,
    I2C_ADDRESS_MIN,
    RESERVED_FLAG_BITS,
    Reg,
)
from bioscara_gym.hardware.stats import CommStats


class _BadReply(Exception):
    """A reply that cannot be right (wrong length, reserved bits, NaN)."""


class Joint(BaseJoint):
    """A joint on the I2C bus (address 0x11-0x14 on the Bioscara, see the configuration).

    Every call is one combined write-then-read transaction: a read writes
    ``[REG]`` and reads ``payload + 1`` bytes, a command writes
    ``[REG][payload]`` and reads the flags byte. A failed attempt (``OSError``
    from the bus, a short reply, a flags byte with reserved bits set, a
    non-finite float) is retried ``retries`` times, then :class:`CommError`
    names the joint and the register. :attr:`stats` counts every attempt.

    Args:
        name: Joint name for messages.
        address: 7-bit I2C address.
        reduction: Signed reduction (motor turns per joint unit).
        min: Lower joint limit (rad or m).
        max: Upper joint limit (rad or m).
        bus: The bus (``SMBusI2C`` on the arm, ``EmulatedI2CBus`` in tests).
        retries: Extra attempts after a failed transaction.
        clock: Time source for waiting on blocking commands.
    """

    def __init__(
        self,
        name: str,
        address: int,
        reduction: float,
        min: float,  # noqa: A002 - the C++ API's parameter name
        max: float,  # noqa: A002
        bus: I2CBus,
        retries: int = 2,
        clock: Clock | None = None,
    ) -> None:
        """Create the driver; nothing is sent before :meth:`init`."""
        super().__init__(name, reduction, min, max, clock)
        if not I2C_ADDRESS_MIN <= address <= I2C_ADDRESS_MAX:
            raise InvalidArgumentError(
                f"I2C address {address:#04x} is outside {I2C_ADDRESS_MIN:#04x}-{I2C_ADDRESS_MAX:#04x}",
                joint=name,
            )
        if retries < 0:
            raise InvalidArgumentError(f"retries {retries} must be >= 0", joint=name)
        self.address = address
        self.bus = bus
        self.retries = retries
        self.stats = CommStats()

    def _transfer(self, reg: Reg, data: bytes, read_payload: bool) -> tuple[float | int, int]:
        """One transaction with retries; returns the decoded payload (0 if none) and flags."""
        size = codec.payload_size(reg) if read_payload else 0
        read_len = size + FLAGS_SIZE
        last: Exception | None = None
        for _ in range(self.retries + 1):
            try:
                reply = self.bus.transfer(self.address, data, read_len)
                if len(reply) != read_len:
                    raise _BadReply(f"reply of {len(reply)} bytes, expected {read_len}")
                if reply[-1] & RESERVED_FLAG_BITS:
                    raise _BadReply(f"flags byte {reply[-1]:#04x} has reserved bits set")
                value = codec.decode(reg, reply[:size]) if read_payload else 0
                if isinstance(value, float) and not math.isfinite(value):
                    raise _BadReply(f"value {value} is not finite")
                if reg == Reg.PING and read_payload and value != ACK:
                    raise _BadReply(f"PING answered {value!r}, expected {ACK!r} ('O')")
            except (OSError, _BadReply) as e:
                self.stats.record(ok=False)
                last = e
                continue
            self.stats.record(ok=True)
            return value, reply[-1]
        raise CommError(
            f"{reg.name} failed after {self.retries + 1} attempts: {last}. "
            "Check wiring, power and the address",
            joint=self.name,
            register=reg,
            address=self.address,
        ) from last

    def _command(self, reg: Reg, value: float | int) -> int:
        """Write ``[REG][payload]``, read the flags byte."""
        payload = codec.encode(reg, value, joint=self.name)
        return self._transfer(reg, bytes((reg,)) + payload, read_payload=False)[1]

    def _query(self, reg: Reg) -> tuple[float | int, int]:
        """Write ``[REG]``, read the payload and the flags byte."""
        return self._transfer(reg, bytes((reg,)), read_payload=True)
