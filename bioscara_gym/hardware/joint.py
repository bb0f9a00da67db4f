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
    FLAG_NOT_ENABLED,
    FLAG_NOT_HOMED,
    FLAGS_SIZE,
    I2C_ADDRESS_MAX,
    I2C_ADDRESS_MIN,
    IDEMPOTENT_COMMANDS,
    MAX_PLAUSIBLE_RPM,
    POSITION_MARGIN_FRACTION,
    POSITION_UNHOMED_EXTRA_DEG,
    REPLY_FLAGS_CLEAR,
    REPLY_FLAGS_SET,
    RESERVED_FLAG_BITS,
    STICKY_CONFIRMATIONS,
    STICKY_FLAGS,
    Flag,
    Reg,
)
from bioscara_gym.hardware.stats import CommStats


class _BadReply(Exception):
    """A reply that cannot be right; ``kind`` is its :data:`~.stats.ERROR_KINDS` entry."""

    def __init__(self, kind: str, message: str) -> None:
        super().__init__(message)
        self.kind = kind


class Joint(BaseJoint):
    """A joint on the I2C bus (address 0x11-0x14 on the Bioscara, see the configuration).

    Every call is one combined write-then-read transaction: a read writes
    ``[REG]`` and reads ``payload + 1`` bytes, a command writes
    ``[REG][payload]`` and reads the flags byte. A failed attempt (``OSError``
    from the bus; a reply of the wrong length, with reserved flag bits set, a
    non-finite value, PING not ``'O'``; or an implausible reply, see
    ``docs/protocol.md``) is retried ``retries`` times for reads and
    idempotent commands (:data:`~.registers.IDEMPOTENT_COMMANDS`); MOVESTEPS,
    HOME and CHECKORIENTATION are sent once. Then :class:`CommError` names
    the joint, the register and the raw reply. :attr:`stats` counts every
    attempt, retry and error by kind.

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

    _reports_transfers = True

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

    # -------------------------------------------------------- reply checks
    def _margin(self) -> float:
        """Plausibility margin of positions, joint units."""
        return POSITION_MARGIN_FRACTION * (self.max - self.min)

    def _implausible_value(self, reg: Reg, value: float | int, flags: int) -> str | None:
        """Why a decoded, finite read value cannot be what the joint has, or ``None``."""
        if not isinstance(value, float):
            return None
        if reg == Reg.HOMEOFFSET:
            m = self._margin()
            if not self.min - m <= value <= self.max + m:
                return (
                    f"HOMEOFFSET {value:g} is beyond the limits {self.min:g}..{self.max:g} "
                    f"by more than {m:g}"
                )
            return None
        if reg == Reg.ANGLEMOVED:
            m = self._margin()
            offset = self._homed_offset()
            if offset is not None and not flags & FLAG_NOT_HOMED:
                q = math.radians(value) / self.reduction + offset
                if not self.min - m <= q <= self.max + m:
                    return (
                        f"ANGLEMOVED {value:g} deg is position {q:g}, beyond the end stops "
                        f"{self.min:g}..{self.max:g} by more than {m:g}"
                    )
            else:
                travel = math.degrees(abs(self.reduction) * (self.max - self.min + m))
                bound = travel + POSITION_UNHOMED_EXTRA_DEG
                if abs(value) > bound:
                    return f"ANGLEMOVED {value:g} deg is beyond the joint's travel ({bound:.6g} deg)"
        elif reg == Reg.GETENCODERRPM and abs(value) > MAX_PLAUSIBLE_RPM:
            return f"GETENCODERRPM {value:g} RPM is beyond the motor's {MAX_PLAUSIBLE_RPM:g} RPM"
        return None

    @staticmethod
    def _flags_set_by(reg: Reg, sent: float | int) -> int:
        """The flags a command's handler sets in its own reply (:data:`REPLY_FLAGS_SET`)."""
        must_set = REPLY_FLAGS_SET.get(reg, 0)
        if reg in (Reg.SETCURRENT, Reg.SETHOLDCURRENT) and sent == 0:
            must_set |= FLAG_NOT_ENABLED
        return must_set

    def _implausible_flags(self, reg: Reg, sent: float | int, flags: int) -> str | None:
        """Why a command's reply flags cannot follow that command, or ``None``."""
        must_set = self._flags_set_by(reg, sent)
        must_clear = REPLY_FLAGS_CLEAR.get(reg, 0)
        if flags & must_set != must_set:
            return f"flags {Flag(flags)!r} lack {Flag(must_set & ~flags)!r}, which {reg.name} sets"
        if flags & must_clear:
            return f"flags {Flag(flags)!r} show {Flag(flags & must_clear)!r}, which {reg.name} clears"
        return None

    def _check(
        self, reg: Reg, reply: bytes, read_len: int, size: int, read_payload: bool, sent: float | int
    ) -> float | int:
        """Decode ``reply`` or raise :class:`_BadReply` saying what is wrong with it."""
        if len(reply) != read_len:
            raise _BadReply("malformed", f"reply of {len(reply)} bytes, expected {read_len}")
        flags = reply[-1]
        if flags & RESERVED_FLAG_BITS:
            raise _BadReply("malformed", f"flags byte {flags:#04x} has reserved bits set")
        if not read_payload:
            problem = self._implausible_flags(reg, sent, flags)
            if problem:
                raise _BadReply("implausible", problem)
            return 0
        value = codec.decode(reg, reply[:size])
        if reg == Reg.PING and value != ACK:
            raise _BadReply("malformed", f"PING answered {value!r}, expected {ACK!r} ('O')")
        if isinstance(value, float) and math.isnan(value) and reg == Reg.HOMEOFFSET:
            return value  # "no valid offset": written before every homing (BaseJoint.start_homing)
        if isinstance(value, float) and not math.isfinite(value):
            raise _BadReply("malformed", f"value {value} is not finite")
        problem = self._implausible_value(reg, value, flags)
        if problem:
            raise _BadReply("implausible", problem)
        return value

    def _confirm_sticky_flags(self, reg: Reg, sent: float | int, flags: int) -> None:
        """Read the flags again if ``flags`` shows a sticky flag newly set (:data:`STICKY_FLAGS`).

        The flag counts as real only when :data:`STICKY_CONFIRMATIONS` further
        readings (PINGs) all show it: one flipped bit in the reply and another
        in a single confirming PING would otherwise stop a run on a stall or
        deadman trip that never happened.

        Raises:
            _BadReply: ``implausible``: a later reading lacks it, so the
                first reply's flags byte was corrupted.
        """
        may_set = self._flags_set_by(reg, sent) | (FLAG_NOT_ENABLED if reg == Reg.DISABLECLOSEDLOOP else 0)
        appeared = flags & ~self._flags & STICKY_FLAGS & ~may_set
        if not appeared:
            return
        for _ in range(STICKY_CONFIRMATIONS):
            _, confirmed = self._transfer(Reg.PING, bytes((Reg.PING,)), read_payload=True, confirm=False)
            if appeared & ~confirmed:
                raise _BadReply(
                    "implausible",
                    f"flags {Flag(flags)!r} show {Flag(appeared & ~confirmed)!r}, which the flags read "
                    f"right after ({Flag(confirmed)!r}) do not, and it cannot clear by itself",
                )

    # ------------------------------------------------------------ transfer
    def _transfer(
        self, reg: Reg, data: bytes, read_payload: bool, sent: float | int = 0, confirm: bool = True
    ) -> tuple[float | int, int]:
        """One transaction with retries; returns the decoded payload (0 if none) and flags.

        Reads and :data:`~.registers.IDEMPOTENT_COMMANDS` are tried
        ``retries + 1`` times, any other command once. With ``confirm``, a
        sticky flag newly set in the reply is confirmed by a second reading
        (:meth:`_confirm_sticky_flags`).
        """
        size = codec.payload_size(reg) if read_payload else 0
        read_len = size + FLAGS_SIZE
        resend = read_payload or reg in IDEMPOTENT_COMMANDS
        attempts = self.retries + 1 if resend else 1
        last: Exception | None = None
        for attempt in range(attempts):
            reply = b""
            try:
                reply = self.bus.transfer(self.address, data, read_len)
                self._exchanged()  # delivered: the device reset its deadman timer
                value = self._check(reg, reply, read_len, size, read_payload, sent)
                if confirm:
                    self._confirm_sticky_flags(reg, sent, reply[-1])
            except OSError as e:
                self.stats.record(ok=False, kind="bus", retry=attempt > 0 or self._resending)
                last = e
                continue
            except _BadReply as e:
                self.stats.record(ok=False, kind=e.kind, retry=attempt > 0 or self._resending)
                last = _BadReply(e.kind, f"{e} (reply {reply.hex(' ') or 'empty'})")
                continue
            self.stats.record(ok=True, retry=attempt > 0 or self._resending)
            return value, reply[-1]
        what = (
            f"{reg.name} failed after {attempts} attempts: {last}. Check wiring, power and the address"
            if resend
            else f"{reg.name} failed: {last}. Not sent again: the joint may have run it"
        )
        raise CommError(what, joint=self.name, register=reg, address=self.address) from last

    def _command(self, reg: Reg, value: float | int) -> int:
        """Write ``[REG][payload]``, read the flags byte."""
        payload = codec.encode(reg, value, joint=self.name)
        return self._transfer(reg, bytes((reg,)) + payload, read_payload=False, sent=value)[1]

    def _query(self, reg: Reg) -> tuple[float | int, int]:
        """Write ``[REG]``, read the payload and the flags byte."""
        return self._transfer(reg, bytes((reg,)), read_payload=True)
