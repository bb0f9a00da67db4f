"""The real joint driver: the register protocol over an :class:`I2CBus`."""

from __future__ import annotations

import math
from dataclasses import dataclass

from bioscara_gym.hardware import codec
from bioscara_gym.hardware.base_joint import BaseJoint
from bioscara_gym.hardware.bus import I2CBus
from bioscara_gym.hardware.clock import Clock
from bioscara_gym.hardware.errors import CommError, InvalidArgumentError
from bioscara_gym.hardware.registers import (
    ACK,
    BLOCKING_COMMANDS,
    BLOCKING_PICKUP_S,
    FLAG_NOT_HOMED,
    FLAGS_SIZE,
    I2C_ADDRESS_MAX,
    I2C_ADDRESS_MIN,
    IDEMPOTENT_COMMANDS,
    MAX_PLAUSIBLE_RPM,
    PLAUSIBLE_JUMP_DEG,
    PLAUSIBLE_SPEED_MARGIN,
    PLAUSIBLE_SPEED_MIN_DT_S,
    POSITION_MARGIN_FRACTION,
    POSITION_UNHOMED_EXTRA_DEG,
    REPLY_FLAGS_CLEAR,
    RESERVED_FLAG_BITS,
    STICKY_CONFIRMATIONS,
    Flag,
    Reg,
)
from bioscara_gym.hardware.stats import CommStats
from bioscara_gym.hardware.transmission import rate_to_degrees


class _BadReply(Exception):
    """A reply that cannot be right; ``kind`` is its :data:`~.stats.ERROR_KINDS` entry."""

    def __init__(self, kind: str, message: str) -> None:
        super().__init__(message)
        self.kind = kind


@dataclass(frozen=True)
class _Reading:
    """One ANGLEMOVED reading: motor degrees, the clock when it came back, the retry flag of its attempt."""

    deg: float
    t: float
    retry: bool = False


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

    A homed joint's position reading is believed only if it lies within what
    the joint can have moved since the last reading believed (its speed and
    acceleration limits times :data:`~.registers.PLAUSIBLE_SPEED_MARGIN`, plus
    :data:`~.registers.PLAUSIBLE_JUMP_DEG`), or if a second reading right
    after it agrees with it; the first reading after ``init()`` or a homing
    is always read twice. A reading neither explains is read again and
    counted ``implausible`` (docs/protocol.md).

    Args:
        name: Joint name for messages.
        address: 7-bit I2C address.
        reduction: Signed reduction (motor turns per joint unit).
        min: Lower joint limit (rad or m).
        max: Upper joint limit (rad or m).
        bus: The bus (``SMBusI2C`` on the arm, ``EmulatedI2CBus`` in tests).
        retries: Extra attempts after a failed transaction.
        clock: Time source for waiting on blocking commands.
        max_velocity: The joint's speed limit, rad/s or m/s, until
            :meth:`set_max_velocity` sends one (the configuration's; a process
            that attaches to an enabled joint sends none).
        max_acceleration: Likewise, rad/s^2 or m/s^2.
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
        *,
        max_velocity: float | None = None,
        max_acceleration: float | None = None,
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
        # What the joint can do, motor deg/s and deg/s^2 (None: unknown), and the
        # last speed commanded (SETRPM, deg/s): see _reach_deg.
        self._max_dps = None if max_velocity is None else abs(rate_to_degrees(max_velocity, reduction))
        self._max_dps2 = (
            None if max_acceleration is None else abs(rate_to_degrees(max_acceleration, reduction))
        )
        self._command_dps = 0.0
        # The last position reading believed, its speed (deg/s, None: unknown),
        # and the last encoder speed read (deg/s, clock time).
        self._belief: _Reading | None = None
        self._belief_speed: float | None = None
        self._encoder: tuple[float, float] | None = None

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
                    f"HOMEOFFSET {value:g} is beyond the limits {self.min:g}..{self.max:g} by more than {m:g}"
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

    def _confirm_sticky_flags(self, reg: Reg, sent: float | int, flags: int, read: bool) -> None:
        """Read the flags again when the reply shows a change the driver must not take on one reading.

        A sticky flag (:data:`STICKY_FLAGS`) newly set or gone, BUSY gone
        while HOME or CHECKORIENTATION runs, or NOT_ENABLED still set in
        SETUP's reply (:class:`~bioscara_gym.hardware.base_joint.Doubts`)
        counts as real only when :data:`STICKY_CONFIRMATIONS` further readings
        (PINGs) all show it: one flipped bit in the reply and another in a
        single confirming PING would otherwise stop a run on a stall or
        deadman trip that never happened, one flipped BUSY bit ended a homing
        half-way (``corrupt=0.05``: the arm took the homing for aborted and
        stopped j3 on its way), and one flipped NOT_ENABLED bit made the arm
        skip a disabled joint's enable.

        Raises:
            _BadReply: ``implausible``: a later reading does not show it, so
                the first reply's flags byte was corrupted.
        """
        doubts = self._doubtful_flags(reg, sent, flags, read)
        if not any(doubts):
            return
        if reg in BLOCKING_COMMANDS:
            # The firmware cancels a blocking command its main loop has not picked up
            # yet (BaseJoint._wait_for_pickup): a PING at once would end the homing.
            self._sleep_until(self.clock.now() + BLOCKING_PICKUP_S)
        for _ in range(STICKY_CONFIRMATIONS):
            _, confirmed = self._transfer(Reg.PING, bytes((Reg.PING,)), read_payload=True, confirm=False)
            if doubts.appeared & ~confirmed:
                raise _BadReply(
                    "implausible",
                    f"flags {Flag(flags)!r} show {Flag(doubts.appeared & ~confirmed)!r}, which the flags "
                    f"read right after ({Flag(confirmed)!r}) do not, and it cannot clear by itself",
                )
            if doubts.kept & ~confirmed:
                raise _BadReply(
                    "implausible",
                    f"flags {Flag(flags)!r} after SETUP still show NOT_ENABLED, which SETUP clears and the "
                    f"flags read right after ({Flag(confirmed)!r}) do not",
                )
            if doubts.ended & confirmed:
                raise _BadReply(
                    "implausible",
                    f"flags {Flag(flags)!r} lack BUSY while {self._current_b_cmd.name} runs, but the "
                    f"flags read right after ({Flag(confirmed)!r}) show it, and it cannot come back",
                )
            if doubts.cleared & confirmed:
                raise _BadReply(
                    "implausible",
                    f"flags {Flag(flags)!r} lack {Flag(doubts.cleared & confirmed)!r}, which the flags read "
                    f"right after ({Flag(confirmed)!r}) show, and {reg.name} does not clear it",
                )

    # ------------------------------------------------------------ transfer
    def _transfer(
        self, reg: Reg, data: bytes, read_payload: bool, sent: float | int = 0, confirm: bool = True
    ) -> tuple[float | int, int]:
        """One transaction with retries; returns the decoded payload (0 if none) and flags.

        Reads and :data:`~.registers.IDEMPOTENT_COMMANDS` are tried until
        ``retries + 1`` attempts have failed, any other command once. With
        ``confirm``, a sticky flag newly set in the reply is confirmed by
        further readings (:meth:`_confirm_sticky_flags`). A position reading
        not believed yet (:meth:`_judge_position`) is read again; it counts as
        a failed attempt once it is shown wrong, not while it is only unconfirmed.
        """
        size = codec.payload_size(reg) if read_payload else 0
        read_len = size + FLAGS_SIZE
        resend = read_payload or reg in IDEMPOTENT_COMMANDS
        budget = self.retries if resend else 0
        gate = read_payload and reg == Reg.ANGLEMOVED
        pending: list[_Reading] = []  # position readings not believed yet
        failed = tries = 0
        last: Exception | None = None
        previous_failed = False
        while failed <= budget:
            tries += 1
            # A retry repeats a failed attempt; this one counts as failed until it succeeds.
            retry, previous_failed = previous_failed or self._resending, True
            reply = b""
            try:
                reply = self.bus.transfer(self.address, data, read_len)
                self._exchanged()  # delivered: the device reset its deadman timer
                value = self._check(reg, reply, read_len, size, read_payload, sent)
                if confirm:
                    self._confirm_sticky_flags(reg, sent, reply[-1], read_payload)
            except OSError as e:
                self.stats.record(ok=False, kind="bus", retry=retry)
                failed, last = failed + 1, e
                continue
            except _BadReply as e:
                self.stats.record(ok=False, kind=e.kind, retry=retry)
                failed, last = failed + 1, _BadReply(e.kind, f"{e} (reply {reply.hex(' ') or 'empty'})")
                continue
            if gate:
                reading = _Reading(float(value), self.clock.now(), retry)
                doubt = self._judge_position(reading, reply[-1], pending)
                if doubt is not None:
                    pending.append(reading)
                    if doubt:  # shown implausible, not only unconfirmed
                        failed += 1
                        last = _BadReply("implausible", f"{doubt} (reply {reply.hex(' ')})")
                    else:  # only unconfirmed: the next reading is a confirmation, not a retry
                        previous_failed = False
                    continue
                self._settle(pending, reading)
            self.stats.record(ok=True, retry=retry)
            if read_payload:
                self._took(reg, value)
            return value, reply[-1]
        for reading in pending:
            self.stats.record(ok=False, kind="implausible", retry=reading.retry)
        # Every attempt answered, and the answer could not be the joint's: a bus rarely garbles
        # the same way each time (seen: a configuration's j2 max 0.2 m, the lift at 0.3 m).
        check = (
            "Check the configuration's limits and reduction against the joint, then wiring and power"
            if isinstance(last, _BadReply) and last.kind == "implausible"
            else "Check wiring, power and the address"
        )
        what = (
            f"{reg.name} failed after {tries} attempt{'s' if tries != 1 else ''}: {last}. {check}"
            if resend
            else f"{reg.name} failed: {last}. Not sent again: the joint may have run it"
        )
        raise CommError(what, joint=self.name, register=reg, address=self.address) from last

    # ------------------------------------------------ believing positions
    def forget_position(self) -> None:
        """See :meth:`BaseJoint.forget_position`."""
        self._belief = None
        self._belief_speed = None

    def _reach_deg(self, dt: float, speed_dps: float | None) -> float:
        """How far the motor can have turned in ``dt`` seconds, degrees (margin and tolerance included).

        The speed limit is the larger of the joint's limit and the speed last
        commanded; with the speed at the last reading known, the acceleration
        limit bounds it further: ``margin * (speed * dt + acc * dt^2 / 2)``.
        """
        limit = self._max_dps if self._max_dps is not None else MAX_PLAUSIBLE_RPM * 6.0
        reach = PLAUSIBLE_SPEED_MARGIN * max(limit, self._command_dps) * dt
        if speed_dps is not None and self._max_dps2 is not None:
            reach = min(reach, PLAUSIBLE_SPEED_MARGIN * (speed_dps * dt + 0.5 * self._max_dps2 * dt * dt))
        return reach + PLAUSIBLE_JUMP_DEG

    def _agree(self, a: _Reading, b: _Reading) -> bool:
        """Whether two readings can both be true (speed limit only)."""
        return abs(b.deg - a.deg) <= self._reach_deg(abs(b.t - a.t), None)

    def _judge_position(self, reading: _Reading, flags: int, pending: list[_Reading]) -> str | None:
        """``None`` if the reading is believed; else ``""`` (unconfirmed) or why it is doubted.

        Believed: the joint is not homed or a blocking command runs (then the
        reading gives no position and the encoder's zero may move: nothing is
        compared), the reading lies within reach of the last one believed, or
        it agrees with the reading just before it (two readings in a row).
        """
        if flags & FLAG_NOT_HOMED or self._offset_lost or self._current_b_cmd is not Reg.NONE:
            self.forget_position()
            return None
        belief = self._belief
        if belief is not None and reading.t < belief.t:  # the clock went back (a simulation restored)
            self.forget_position()
            belief = None
        if belief is not None:
            reach = self._reach_deg(reading.t - belief.t, self._belief_speed_now(belief))
            if abs(reading.deg - belief.deg) <= reach:
                return None
        if pending and self._agree(pending[-1], reading):
            return None
        if belief is None:
            return (
                ""
                if not pending
                else (
                    f"ANGLEMOVED {reading.deg:g} deg disagrees with the reading just before it "
                    f"({pending[-1].deg:g} deg)"
                )
            )
        return (
            f"ANGLEMOVED {reading.deg:g} deg is {abs(reading.deg - belief.deg):.6g} deg from the last "
            f"reading believed ({belief.deg:g} deg, {(reading.t - belief.t) * 1000:.1f} ms before): "
            f"the joint can turn the motor {reach:.6g} deg at most in that time"
        )

    def _belief_speed_now(self, belief: _Reading) -> float | None:
        """The speed at the last reading believed: from the readings before it, or the encoder after it."""
        speeds = [s for s in (self._belief_speed,) if s is not None]
        if self._encoder is not None and self._encoder[1] >= belief.t:
            speeds.append(self._encoder[0])
        return max(speeds) if speeds else None

    def _settle(self, pending: list[_Reading], believed: _Reading) -> None:
        """Count the readings read before ``believed`` (wrong unless they agree with it); believe it."""
        for reading in pending:
            agrees = self._agree(reading, believed)
            self.stats.record(ok=agrees, kind="implausible", retry=reading.retry)
        previous = self._belief
        dt = believed.t - previous.t if previous is not None else 0.0
        measured = previous is not None and dt >= PLAUSIBLE_SPEED_MIN_DT_S
        self._belief_speed = abs(believed.deg - previous.deg) / dt if measured else None  # type: ignore[union-attr]
        self._belief = believed

    def _took(self, reg: Reg, value: float | int) -> None:
        """Remember what a read tells the position check (the encoder's speed)."""
        if reg == Reg.GETENCODERRPM:
            self._encoder = (abs(float(value)) * 6.0, self.clock.now())

    def _command(self, reg: Reg, value: float | int) -> int:
        """Write ``[REG][payload]``, read the flags byte."""
        payload = codec.encode(reg, value, joint=self.name)
        flags = self._transfer(reg, bytes((reg,)) + payload, read_payload=False, sent=value)[1]
        if reg == Reg.SETMAXVELOCITY:
            self._max_dps = abs(float(value))
        elif reg == Reg.SETMAXACCELERATION:
            self._max_dps2 = abs(float(value))
        elif reg == Reg.SETRPM:
            self._command_dps = abs(float(value)) * 6.0
        return flags

    def _query(self, reg: Reg) -> tuple[float | int, int]:
        """Write ``[REG]``, read the payload and the flags byte."""
        return self._transfer(reg, bytes((reg,)), read_payload=True)
