"""The joint driver API and the host-side rules every backend shares."""

from __future__ import annotations

import abc
import contextlib
import math
from collections.abc import Callable
from typing import ClassVar, NamedTuple

from bioscara_gym.hardware.clock import Clock, WallClock
from bioscara_gym.hardware.codec import pack_bytes
from bioscara_gym.hardware.errors import (
    AlreadyInitializedError,
    CommError,
    IncorrectStateError,
    InvalidArgumentError,
    JointError,
    NotEnabledError,
    NotHomedError,
    NotInitError,
    StalledError,
)
from bioscara_gym.hardware.registers import (
    ACK,
    BLOCKING_PICKUP_S,
    CURRENT_MAX_PCT,
    FLAG_BUSY,
    FLAG_NOT_ENABLED,
    FLAG_NOT_HOMED,
    FLAG_STALL,
    FLAGS_CLEARED_BY,
    HOMING_RPM_MAX,
    HOMING_RPM_MIN,
    HOMING_SETTLE_S,
    POWER_UP_FLAGS,
    REPLY_FLAGS_SET,
    SENSITIVITY_MAX,
    STICKY_FLAGS,
    BrakeMode,
    Flag,
    Reg,
)
from bioscara_gym.hardware.transmission import (
    degrees_to_position,
    position_to_degrees,
    rate_to_degrees,
    rpm_to_velocity,
    velocity_to_rpm,
)

#: Poll period of :meth:`BaseJoint.home` while the joint is BUSY, seconds.
BUSY_POLL_S = 0.01
#: After a STOP that aborts a blocking command, how long the host waits before
#: it sends the next one, seconds. STOP clears BUSY at once, but the aborted
#: handler returns only when it next looks at BUSY: a homing after its 500 ms
#: wait (``delay(500)``), then within 1 ms. A new HOME sent before that sets
#: BUSY again, and the old homing loop, seeing BUSY, keeps waiting for an end
#: stop with its motor stopped: the joint hangs until the next STOP
#: (firmware source; docs/firmware.md). The 500 ms plus one pick-up window.
ABORT_SETTLE_S = HOMING_SETTLE_S + BLOCKING_PICKUP_S


class Doubts(NamedTuple):
    """The flags of one reply that the driver reads again before it believes them.

    Each is a mask; a further reading (PING) must show the same, or the
    reply's flags byte was corrupted (``Joint._confirm_sticky_flags``).
    """

    #: A sticky flag (:data:`~.registers.STICKY_FLAGS`) newly set that the
    #: command does not set, or BUSY in a reading while no blocking command of
    #: this host runs: the PINGs must show it set.
    appeared: int
    #: BUSY gone while HOME or CHECKORIENTATION runs (the firmware clears it
    #: once: at the command's end or on STOP): the PINGs must show it clear.
    ended: int
    #: NOT_ENABLED still set in SETUP's reply (SETUP clears it): the PINGs must show it set.
    kept: int
    #: A sticky flag the joint showed last, gone although neither the command
    #: (:data:`~.registers.FLAGS_CLEARED_BY`) nor a homing clears it: the PINGs must show it clear.
    cleared: int


class BaseJoint(abc.ABC):
    """One joint of the arm: the C++ ``BaseJoint`` API, with exceptions.

    Units on the joint side: rad, rad/s, rad/s^2 for revolute joints and m,
    m/s, m/s^2 for the prismatic lift. Currents are percent (0-100) of the
    driver's 2.5 A output. Every method that talks to the joint raises
    :class:`~bioscara_gym.hardware.errors.NotInitError` before ``init()`` and
    :class:`~bioscara_gym.hardware.errors.CommError` when the transaction
    fails; the flags of the last transaction are kept and read by
    :meth:`is_homed`, :meth:`is_enabled`, :meth:`is_stalled`, :meth:`is_busy`.

    Subclasses provide the two register-level primitives :meth:`_command` and
    :meth:`_query`; the host rules of the C++ API's ``BaseJoint`` (refusals
    before any traffic, homing bounds and offsets, positions 0.0 while not
    homed; see ``docs/arm.md``) live here once.

    Args:
        name: Joint name used in messages (``"j1"``).
        reduction: Motor turns per joint unit, signed (see ``docs/model.md``).
        min: Lower joint limit (rad or m); the offset after homing negative.
        max: Upper joint limit (rad or m); the offset after homing positive.
        clock: Time source for waiting on blocking commands.
    """

    #: Whether a stepper's field drives the joint, one that can run away from
    #: its rotor: the arm then watches it (:mod:`~bioscara_gym.hardware.field_watch`).
    #: False for a joint that mirrors its commands or closes its own loop.
    has_field: ClassVar[bool] = True

    def __init__(
        self,
        name: str,
        reduction: float,
        min: float,  # noqa: A002 - the C++ API's parameter name
        max: float,  # noqa: A002
        clock: Clock | None = None,
    ) -> None:
        """Create the joint object; nothing is sent before :meth:`init`."""
        if not math.isfinite(reduction) or reduction == 0.0:
            raise InvalidArgumentError(f"reduction {reduction} must be finite and non-zero", joint=name)
        if not min < max:
            raise InvalidArgumentError(f"min {min} must be below max {max}", joint=name)
        self.name = name
        self.reduction = float(reduction)
        self.min = float(min)
        self.max = float(max)
        self.clock: Clock = clock if clock is not None else WallClock()
        self.offset = 0.0
        self._offset_known = False
        self._flags = int(POWER_UP_FLAGS)
        # The flags of the joint's last reply as it sent them (None: none read
        # in this session yet, so a flag cleared since the last session is believed).
        self._device_flags: int | None = None
        # A reply said NOT_ENABLED and no enable() has succeeded since: motion
        # is refused even if a later reply's flags claim otherwise (only SETUP
        # clears the firmware's NOT_ENABLED, so such a reply is corrupted).
        self._enable_needed = False
        self._current_b_cmd = Reg.NONE
        self._homing_offset = 0.0
        self._initialized = False
        # The joint says homed but its HOMEOFFSET is NaN: a homing ended and
        # no host stored its offset (a crash in between). Reported as not
        # homed until the next homing starts.
        self._offset_lost = False
        # Clock time before which a blocking command sent to the joint may
        # still be waiting for the firmware's main loop (None: nothing pending).
        self._pickup_until: float | None = None
        self._listeners: list[Callable[[], None]] = []
        # Clock time before which no new blocking command is sent, because an
        # aborted one may still be winding down in the firmware.
        self._abort_until: float | None = None

    # ----------------------------------------------------------- primitives
    @abc.abstractmethod
    def _command(self, reg: Reg, value: float | int) -> int:
        """Send a command register with its payload; return the flags byte."""

    @abc.abstractmethod
    def _query(self, reg: Reg) -> tuple[float | int, int]:
        """Read a register; return its payload value and the flags byte."""

    def forget_position(self) -> None:  # noqa: B027 - optional hook
        """Compare no later position reading with an earlier one (the bus driver's check, docs/protocol.md).

        Called on ``init()`` and around a homing, where the encoder's zero
        may change, and by a simulation that teleports the joint: the next
        reading is then confirmed by a second one instead.
        """

    def _open(self) -> None:  # noqa: B027 - optional hook
        """Acquire the connection (bus handle); called by :meth:`init`."""

    def _close(self) -> None:  # noqa: B027 - optional hook
        """Release the connection; called by :meth:`deinit`."""

    # --------------------------------------------------------------- helpers
    def _require_init(self) -> None:
        if not self._initialized:
            raise NotInitError("joint not initialized; call init() first", joint=self.name)

    def _require_enabled(self) -> None:
        self._require_init()
        if self._flags & FLAG_NOT_ENABLED or self._enable_needed:
            raise NotEnabledError("joint not enabled; call enable() first", joint=self.name)

    def _require_homed(self) -> None:
        self._require_enabled()
        if self._flags & FLAG_NOT_HOMED:
            raise NotHomedError("joint not homed; home it before moving", joint=self.name)

    def _require_no_blocking(self) -> None:
        if self._current_b_cmd is not Reg.NONE and self._flags & FLAG_BUSY:
            raise IncorrectStateError(
                f"{self._current_b_cmd.name} is still running; stop it first",
                joint=self.name,
            )

    #: The joint's bus address where it has one (the I2C driver's, e.g. 0x11); ``None`` elsewhere.
    address: int | None = None
    #: Whether the subclass reports each delivered bus transfer itself (retries included).
    _reports_transfers = False
    #: Extra attempts after a failed transaction (bus drivers set it; simulated joints never fail).
    retries = 0
    #: True while a blocking command that did not start is sent again (counted as a retry).
    _resending = False

    def on_exchange(self, listener: Callable[[], None]) -> Callable[[], None]:
        """Call ``listener`` after every exchange the joint's device received.

        On a bus, every transfer that came back counts, a rejected reply's
        and a retry's included (the device saw it, so its deadman timer was
        reset); a NACK or a bus error does not. Elsewhere, every command
        and query.

        Returns:
            A function that stops the calls.
        """
        self._listeners.append(listener)

        def remove() -> None:
            if listener in self._listeners:
                self._listeners.remove(listener)

        return remove

    def _exchanged(self) -> None:
        """Tell the :meth:`on_exchange` listeners that the device received an exchange."""
        for listener in tuple(self._listeners):
            listener()

    @property
    def picking_up(self) -> bool:
        """Whether a blocking command sent to the joint may still wait for the firmware's main loop.

        The next transaction to the joint would wait for it (see
        :data:`~.registers.BLOCKING_PICKUP_S`); a control loop can leave the
        joint alone for a cycle instead.
        """
        return self._pickup_until is not None and self.clock.now() < self._pickup_until

    def _wait_for_pickup(self, reg: Reg) -> None:
        """Leave the joint alone until a blocking command sent to it was picked up.

        The firmware's transaction handler cancels a blocking command its main
        loop has not started yet (BUSY then stays set until a STOP;
        docs/firmware.md), so the first transaction after HOME or
        CHECKORIENTATION waits until :data:`BLOCKING_PICKUP_S` has passed
        since it. A STOP does not wait: it ends the command either way.
        """
        until, self._pickup_until = self._pickup_until, None
        if until is not None and reg != Reg.STOP:
            self._sleep_until(until)

    def _wait_for_abort(self) -> None:
        """Before a blocking command: wait until an aborted one has surely returned."""
        until, self._abort_until = self._abort_until, None
        if until is not None:
            self._sleep_until(until)

    def _sleep_until(self, until: float) -> None:
        # Only forward: a simulation clock's sleep() does not ignore negative times.
        remaining = until - self.clock.now()
        if remaining > 0:
            self.clock.sleep(remaining)

    @staticmethod
    def _flags_set_by(reg: Reg, sent: float | int) -> int:
        """The flags a command's handler sets in its own reply (:data:`REPLY_FLAGS_SET`)."""
        must_set = REPLY_FLAGS_SET.get(reg, 0)
        if reg in (Reg.SETCURRENT, Reg.SETHOLDCURRENT) and sent == 0:
            must_set |= FLAG_NOT_ENABLED
        return must_set

    def _doubtful_flags(self, reg: Reg, sent: float | int, flags: int, read: bool) -> Doubts:
        """What in a reply's ``flags`` is read again before it is believed (:class:`Doubts`).

        :class:`~bioscara_gym.hardware.joint.Joint` reads them again
        (``_confirm_sticky_flags``); the simulated joint takes the same
        readings' time, so both backends keep one clock.
        """
        may_set = self._flags_set_by(reg, sent) | (FLAG_NOT_ENABLED if reg == Reg.DISABLECLOSEDLOOP else 0)
        appeared = flags & ~self._flags & STICKY_FLAGS & ~may_set
        running = self._current_b_cmd is not Reg.NONE and reg is not Reg.STOP
        ended = FLAG_BUSY if running and self._flags & ~flags & FLAG_BUSY else 0
        # SETUP clears NOT_ENABLED: a reply still showing it is read again before
        # enable() believes it (one flipped bit stopped 7 of 120 bring-ups at corrupt=0.05).
        kept = FLAG_NOT_ENABLED if reg is Reg.SETUP and flags & FLAG_NOT_ENABLED else 0
        # BUSY in a reading while no blocking command of this host's runs: the arm would
        # refuse to enable or home a joint it believes busy (3 of 120 bring-ups at
        # corrupt=0.05). Not in a command's reply: the firmware shows BUSY while it
        # handles some commands, and sending one again shows it again.
        if read and self._current_b_cmd is Reg.NONE:
            appeared |= flags & ~self._flags & FLAG_BUSY
        # A sticky flag the joint last showed, gone although nothing that clears it
        # ran: a flipped NOT_ENABLED bit after a disable made the arm skip a joint's
        # enable (1 of 40 bring-ups at corrupt=0.05). Compared with the joint's own
        # last flags, not the driver's view (which adds NOT_HOMED for a lost offset).
        cleared = 0
        if self._device_flags is not None:
            cleared = self._device_flags & ~flags & STICKY_FLAGS & ~self._flags_cleared_by(reg)
        return Doubts(appeared, ended, kept, cleared)

    def _flags_cleared_by(self, reg: Reg) -> int:
        """The sticky flags a reply to ``reg`` may show cleared (firmware ``joint.ino``).

        SETUP clears STALL and NOT_ENABLED, ENABLESTALLGUARD clears STALL, and
        the end of a homing clears NOT_HOMED and STALL: any reply while a
        homing of this host runs may show it.
        """
        cleared = FLAGS_CLEARED_BY.get(reg, 0)
        if self._current_b_cmd is Reg.HOME:
            cleared |= FLAG_NOT_HOMED | FLAG_STALL
        return cleared

    def _accept_flags(self, flags: int) -> int:
        self._device_flags = flags
        self._flags = flags | FLAG_NOT_HOMED if self._offset_lost else flags
        if flags & FLAG_NOT_ENABLED:
            self._enable_needed = True
        return self._flags

    def _send(self, reg: Reg, value: float | int) -> int:
        self._require_init()
        self._wait_for_pickup(reg)
        flags = self._command(reg, value)
        if not self._reports_transfers:
            self._exchanged()
        return self._accept_flags(flags)

    def _get(self, reg: Reg) -> float | int:
        self._require_init()
        self._wait_for_pickup(reg)
        value, flags = self._query(reg)
        if not self._reports_transfers:
            self._exchanged()
        self._accept_flags(flags)
        return value

    def _send_blocking(self, reg: Reg, value: float | int) -> None:
        """Send HOME or CHECKORIENTATION; on a lost reply, learn from BUSY whether it started.

        A reply lost on the bus may follow a command the joint took, so the
        command is not simply sent again: after the pick-up window the flags
        are read. BUSY means it started (success). Not BUSY means it did not
        start, and only then is it sent again, up to :attr:`retries` times
        (homing lasts seconds: a joint not busy 60 ms after the command has
        not run it). If the flags cannot be read either, or every attempt
        was lost, :class:`CommError` is raised and no blocking command is running.
        """
        self._current_b_cmd = reg
        self._wait_for_abort()
        for attempt in range(self.retries + 1):
            try:
                self._send_once(reg, value, resend=attempt > 0)
            except CommError as lost:
                self._pickup_until = self.clock.now() + BLOCKING_PICKUP_S
                try:
                    started = bool(self.get_flags() & FLAG_BUSY)
                except CommError:
                    self._current_b_cmd = Reg.NONE
                    raise lost from None
                if started:
                    return
                last = lost
                continue
            self._pickup_until = self.clock.now() + BLOCKING_PICKUP_S
            return
        self._current_b_cmd = Reg.NONE
        raise CommError(
            f"{reg.name}: the reply was lost and the joint is not busy, so it did not start; "
            f"sent {self.retries + 1} time(s) ({last})",
            joint=self.name,
            register=reg,
        ) from last

    def _send_once(self, reg: Reg, value: float | int, resend: bool) -> None:
        """Send a blocking command; ``resend`` counts it as a retry in the bus statistics."""
        self._resending = resend
        try:
            self._send(reg, value)
        finally:
            self._resending = False

    def _send_motion(self, reg: Reg, value: float | int) -> None:
        """Send a motion command; if the reply says it should not have run, stop the joint and raise.

        The firmware refuses SETRPM and MOVETOANGLE only while stalled: after
        its deadman tripped (NOT_ENABLED set, currents kept) it still runs
        them, and no longer watches (docs/firmware.md, deadman); MOVESTEPS
        runs even when stalled. So a reply showing NOT_ENABLED or STALL is
        followed at once by a STOP of this joint, before the error is raised:
        no motor is left turning unwatched. Later motion is refused before
        any traffic until :meth:`enable` succeeds.
        """
        flags = self._send(reg, value)
        if not flags & (FLAG_STALL | FLAG_NOT_ENABLED):
            return
        stopped = self._stop_after_refusal()
        if flags & FLAG_STALL:
            raise StalledError(
                f"joint stalled; {stopped}; re-enable it to clear the stall", joint=self.name, register=reg
            )
        raise NotEnabledError(
            f"joint reports not enabled (deadman or disable), yet the firmware runs {reg.name} "
            f"anyway; {stopped}; re-enable it",
            joint=self.name,
            register=reg,
        )

    def _stop_after_refusal(self) -> str:
        """STOP after a motion reply that says the motion should not run; the outcome in words."""
        try:
            self.stop()
        except JointError as e:
            return f"the STOP sent after it failed ({e}): the motor may still turn, cut the power"
        return "sent STOP"

    def _check_percent(self, what: str, value: int) -> int:
        if isinstance(value, bool) or not isinstance(value, int) or not 0 <= value <= CURRENT_MAX_PCT:
            raise InvalidArgumentError(
                f"{what} {value!r} must be an integer percent 0-{CURRENT_MAX_PCT}", joint=self.name
            )
        return value

    def _check_sensitivity(self, what: str, value: int) -> int:
        if isinstance(value, bool) or not isinstance(value, int) or not 0 <= value <= SENSITIVITY_MAX:
            raise InvalidArgumentError(f"{what} {value!r} must be 0-{SENSITIVITY_MAX}", joint=self.name)
        return value

    def _check_finite(self, what: str, value: float) -> float:
        value = float(value)
        if not math.isfinite(value):
            raise InvalidArgumentError(f"{what} {value} must be finite", joint=self.name)
        return value

    # ------------------------------------------------------------ lifecycle
    def init(self) -> None:
        """Open the connection, PING the joint and restore the homing offset (:meth:`_init`).

        If the joint reports homed (it kept power while the host restarted),
        the offset is read back from HOMEOFFSET so positions stay valid. A
        failed ``init()`` leaves the joint uninitialized.

        Raises:
            AlreadyInitializedError: The joint is initialized already (``deinit()`` first);
                nothing is sent.
            CommError: No answer, or PING did not answer ``'O'``.
        """
        if self._initialized:
            raise AlreadyInitializedError(
                "joint already initialized; call deinit() before init() again", joint=self.name
            )
        self._init()

    def _init(self) -> None:
        """The driver's connection: open, PING, restore the homing offset (see :meth:`init`)."""
        self._open()
        self._initialized = True
        self._enable_needed = False  # a new session: the joint's own flags decide
        self._device_flags = None
        self.forget_position()
        try:
            ack = self._get(Reg.PING)
            if ack != ACK:
                raise CommError(
                    f"PING answered {ack!r}, expected {ACK!r} ('O')", joint=self.name, register=Reg.PING
                )
            self._offset_known = False
            self._offset_lost = False
            self._pickup_until = None
            self._load_offset()
        except BaseException:
            self._initialized = False
            self._close()
            raise

    def _load_offset(self) -> None:
        """Read HOMEOFFSET once the joint reports homed and the offset is not known.

        Called by :meth:`init` and again before positions are used, so a homed
        joint whose first reply lost its flags still gets its offset. A NaN
        offset on a joint that says homed means a homing ended but no host
        stored its offset (:meth:`start_homing` writes NaN first): the joint
        is reported not homed from then on, until it is homed again.
        """
        if self._current_b_cmd is Reg.HOME:
            return  # a homing this object runs: its offset is _homing_offset, NaN on the joint
        if not self._offset_known and not self._flags & FLAG_NOT_HOMED:
            offset = float(self._get(Reg.HOMEOFFSET))
            if math.isnan(offset):
                self._offset_lost = True
                self._flags |= FLAG_NOT_HOMED
                return
            self.offset = offset
            self._offset_known = True

    def _homed_offset(self) -> float | None:
        """The offset a homed joint's ANGLEMOVED counts from, if the host knows it.

        While a homing this object started (or adopted) has not been finished
        by :meth:`post_homing`, a joint that says homed has just zeroed its
        encoder at that homing's end stop: its offset is that end stop's.
        """
        if self._current_b_cmd is Reg.HOME:
            return self._homing_offset
        return self.offset if self._offset_known else None

    def deinit(self) -> None:
        """Release the connection; the joint itself is left as it is."""
        if self._initialized:
            self._initialized = False
            self._close()

    @property
    def initialized(self) -> bool:
        """Whether :meth:`init` succeeded and :meth:`deinit` was not called."""
        return self._initialized

    def __enter__(self) -> BaseJoint:
        """``init()`` and return the joint."""
        self.init()
        return self

    def __exit__(self, *exc: object) -> None:
        """Disable (best effort) and ``deinit()``: leave the joint safe."""
        try:
            if self._initialized:
                self.disable()
        finally:
            self.deinit()

    def enable(self, drive_current: int, hold_current: int) -> None:
        """Engage the motor with drive and hold current (percent 0-100).

        Clears STALL and disables stall detection (re-enable it with
        :meth:`enable_stallguard` afterwards).

        Raises:
            InvalidArgumentError: A current outside 0-100.
            NotEnabledError: The joint still reports not enabled afterwards.
        """
        self._check_percent("drive current", drive_current)
        self._check_percent("hold current", hold_current)
        flags = self._send(Reg.SETUP, pack_bytes(drive_current, hold_current))
        if flags & FLAG_NOT_ENABLED:
            raise NotEnabledError(
                "failed to enable; the joint still reports not enabled", joint=self.name, register=Reg.SETUP
            )
        self._enable_needed = False

    def disable(self) -> None:
        """Stop, set hold and drive current to 0 and let the joint freewheel.

        Every step is tried even when an earlier one failed: a lost reply does
        not mean the command was lost, and a joint left with its currents on
        is worse than a second error. One error is raised at the end, naming
        every failed step (its ``failures`` attribute lists ``(step,
        error)``); a single failure is re-raised as it is.

        Raises:
            NotInitError: Called before :meth:`init`.
            JointError: A step failed (usually :class:`CommError`).
        """
        self._require_init()
        steps = (
            ("STOP", self.stop),
            ("SETHOLDCURRENT 0", lambda: self.set_hold_current(0)),
            ("SETCURRENT 0", lambda: self.set_drive_current(0)),
            ("SETBRAKEMODE freewheel", lambda: self.set_brake_mode(BrakeMode.FREEWHEEL)),
        )
        failures: list[tuple[str, JointError]] = []
        for step, run in steps:
            try:
                run()
            except JointError as e:
                failures.append((step, e))
        if not failures:
            return
        first = failures[0][1]
        if len(failures) > 1:
            listed = "; ".join(f"{step}: {e}" for step, e in failures)
            message = f"disable incomplete, {len(failures)} of {len(steps)} steps failed: {listed}"
            if all(isinstance(e, CommError) for _, e in failures):
                error: JointError = CommError(
                    message, joint=self.name, register=first.register, address=getattr(first, "address", None)
                )
            else:
                error = JointError(message, joint=self.name, register=first.register)
            error.failures = failures  # type: ignore[attr-defined]
            raise error from first
        first.failures = failures  # type: ignore[attr-defined]
        raise first

    # --------------------------------------------------------------- homing
    def homing_rpm(self, velocity: float) -> float:
        """Motor RPM of a joint-side homing velocity (rad/s or m/s)."""
        return velocity_to_rpm(velocity, self.reduction)

    def start_homing(self, velocity: float, sensitivity: int, current: int) -> None:
        """Start homing against the end stop and return at once.

        The joint runs at ``velocity`` until the PID error exceeds
        ``sensitivity``, zeros its encoder there and clears NOT_HOMED. The end
        stop becomes the joint's ``max`` for a positive velocity and its
        ``min`` for a negative one (applied by :meth:`post_homing`).

        Args:
            velocity: Signed homing velocity, rad/s or m/s. The motor speed
                ``rad2deg(reduction * velocity) / 6`` must satisfy
                ``1.0 < |rpm| < 250.0``.
            sensitivity: PID-error threshold 0-255 (lower trips earlier).
            current: Homing current, percent 0-100.

        Raises:
            InvalidArgumentError: Speed, sensitivity or current out of bounds.
            NotEnabledError: The joint is not enabled.
            IncorrectStateError: Another blocking command is running.
        """
        velocity = self._check_finite("homing velocity", velocity)
        rpm = self.homing_rpm(velocity)
        if not HOMING_RPM_MIN < abs(rpm) < HOMING_RPM_MAX:
            unit = "m/s" if abs(self.reduction) > 500 else "rad/s"
            raise InvalidArgumentError(
                f"homing speed {velocity:g} {unit} is {abs(rpm):.3g} RPM at the "
                f"motor; must be between {HOMING_RPM_MIN:g} and {HOMING_RPM_MAX:g} RPM",
                joint=self.name,
            )
        self._check_sensitivity("homing sensitivity", sensitivity)
        self._check_percent("homing current", current)
        self._require_enabled()
        self._require_no_blocking()
        direction = 1 if rpm > 0 else 0
        self._wait_for_abort()
        # No valid offset on the joint until post_homing() stores the new
        # one: a host that dies in between leaves NaN, which init() reads as
        # "home again" rather than trusting the joint's homed flag.
        self._send(Reg.HOMEOFFSET, math.nan)
        self.forget_position()
        self._offset_lost = False
        self._homing_offset = self.max if velocity > 0 else self.min
        self._send_blocking(Reg.HOME, pack_bytes(direction, int(abs(rpm)), sensitivity, current))

    def adopt_homing(self, velocity: float) -> None:
        """Take over a homing that another process started on the joint; send nothing.

        A homing has two halves: the firmware runs it and clears NOT_HOMED
        at the end stop, while the host remembers that HOME is the blocking
        command and which end stop the encoder zero will be (the offset
        :meth:`post_homing` stores). A process that did not call
        :meth:`start_homing` (a console command after ``home --no-wait``, a
        host restart) has only the firmware half, and the firmware does not
        report the homing's direction, so the caller passes the velocity the
        homing was started with. Its sign picks the offset as in
        :meth:`start_homing`: ``max`` for positive, ``min`` for negative.

        Afterwards :meth:`current_blocking_command` is ``Reg.HOME``; wait
        while BUSY and call :meth:`post_homing` as after :meth:`start_homing`.
        If the homing already ended, :meth:`post_homing` finishes it at once
        (storing the offset if the joint homed).

        Args:
            velocity: Signed homing velocity the homing was started with,
                rad/s or m/s; only its sign is used.

        Raises:
            InvalidArgumentError: ``velocity`` is zero or not finite.
            NotInitError: Called before :meth:`init`.
            IncorrectStateError: Another blocking command was started by
                this object and has not finished.
        """
        velocity = self._check_finite("homing velocity", velocity)
        if velocity == 0.0:
            raise InvalidArgumentError(
                "homing velocity must be non-zero; its sign picks the end stop",
                joint=self.name,
            )
        self._require_init()
        if self._current_b_cmd not in (Reg.NONE, Reg.HOME):
            raise IncorrectStateError(
                f"{self._current_b_cmd.name} is running; cannot adopt a homing",
                joint=self.name,
            )
        self._homing_offset = self.max if velocity > 0 else self.min
        self._current_b_cmd = Reg.HOME
        self.forget_position()
        self._offset_lost = False

    def post_homing(self) -> None:
        """Finish a homing: clear the blocking command, check, store the offset.

        Raises:
            NotHomedError: The joint did not home (aborted or failed).
        """
        # Not counted as the homing's own reading: one that first shows NOT_HOMED gone
        # (no poll saw the homing end) is read again, since after an aborted homing a
        # flipped bit would make the joint homed at the end stop's offset.
        self._current_b_cmd = Reg.NONE
        self.get_flags()
        if self._flags & FLAG_NOT_HOMED:
            raise NotHomedError("homing did not complete (aborted or failed)", joint=self.name)
        self.offset = self._homing_offset
        self._offset_known = True
        self.forget_position()
        self._send(Reg.HOMEOFFSET, self.offset)

    def wait_while_busy(self, period_s: float = BUSY_POLL_S, timeout_s: float | None = None) -> None:
        """Poll the flags every ``period_s`` until BUSY clears.

        Raises:
            IncorrectStateError: Still busy after ``timeout_s`` (the joint is
                stopped first).
        """
        start = self.clock.now()
        while self.get_flags() & FLAG_BUSY:
            if timeout_s is not None and self.clock.now() - start > timeout_s:
                self.stop()
                raise IncorrectStateError(
                    f"still busy after {timeout_s:g} s; stopped the joint",
                    joint=self.name,
                )
            self.clock.sleep(period_s)

    def home(self, velocity: float, sensitivity: int, current: int, timeout_s: float | None = 600.0) -> None:
        """Home and wait: :meth:`start_homing`, wait while BUSY, :meth:`post_homing`.

        Raises:
            The errors of :meth:`start_homing` and :meth:`post_homing`, and
            IncorrectStateError when it takes longer than ``timeout_s``. A
            homing this call can no longer watch (the bus failed while it
            waited) is stopped first, best effort: a joint left homing turns
            on until its end stop with nobody watching.
        """
        self.start_homing(velocity, sensitivity, current)
        try:
            self.wait_while_busy(timeout_s=timeout_s)
        except IncorrectStateError:
            self._current_b_cmd = Reg.NONE
            raise
        except JointError:
            with contextlib.suppress(JointError):
                self.stop()
            raise
        self.post_homing()

    # --------------------------------------------------------------- motion
    def get_position(self) -> float:
        """Joint position in rad or m; 0.0 (no error) while not homed."""
        deg = self._get(Reg.ANGLEMOVED)
        if self._flags & FLAG_NOT_HOMED:
            return 0.0
        self._load_offset()
        offset = self._homed_offset()
        if offset is None:  # homed, but the offset was lost (NaN): reported not homed
            return 0.0
        return degrees_to_position(float(deg), self.reduction, offset)

    def set_position(self, pos: float) -> None:
        """Move to ``pos`` (rad or m) with the configured velocity and acceleration.

        Raises:
            NotEnabledError, NotHomedError: Refused before any bus traffic.
            StalledError: The reply says the joint is stalled.
            InvalidArgumentError: ``pos`` is not finite.
        """
        pos = self._check_finite("position", pos)
        self._require_homed()
        self._load_offset()
        self._require_homed()  # the offset read may have found it lost
        offset = self._homed_offset()
        if offset is None:
            raise NotHomedError("joint's homing offset is unknown; home it again", joint=self.name)
        self._send_motion(Reg.MOVETOANGLE, position_to_degrees(pos, self.reduction, offset))

    def get_velocity(self) -> float:
        """Measured joint velocity in rad/s or m/s."""
        return rpm_to_velocity(float(self._get(Reg.GETENCODERRPM)), self.reduction)

    def set_velocity(self, vel: float) -> None:
        """Run at ``vel`` (rad/s or m/s) until told otherwise.

        In velocity mode the host must talk to the joint at least every 50 ms,
        or the firmware's deadman stops it and sets NOT_ENABLED.

        Raises:
            NotEnabledError, NotHomedError: Refused before any bus traffic.
            StalledError: The reply says the joint is stalled.
            InvalidArgumentError: ``vel`` is not finite.
        """
        vel = self._check_finite("velocity", vel)
        self._require_homed()
        self._send_motion(Reg.SETRPM, velocity_to_rpm(vel, self.reduction))

    def move_steps(self, steps: int) -> None:
        """Move ``steps`` motor microsteps (1/256 of a full step, 51,200 a turn); allowed while not homed.

        Raises:
            NotEnabledError: The joint is not enabled.
            StalledError: The reply says the joint is stalled.
        """
        if isinstance(steps, bool) or not isinstance(steps, int):
            raise InvalidArgumentError(f"steps {steps!r} must be an integer", joint=self.name)
        self._require_enabled()
        self._send_motion(Reg.MOVESTEPS, steps)

    def stop(self) -> None:
        """Stop the motor (speed 0); aborts a running homing.

        A STOP that may abort a blocking command (one this object started, or
        BUSY in the last flags) makes the next blocking command wait
        :data:`ABORT_SETTLE_S` (see there). It is sent at once, even inside
        the pick-up window of a blocking command: it ends that command too.
        """
        aborts = self._current_b_cmd is not Reg.NONE or bool(self._flags & FLAG_BUSY)
        try:
            self._send(Reg.STOP, 0)
        finally:
            if aborts:
                self._abort_until = self.clock.now() + ABORT_SETTLE_S

    def check_orientation(self, angle: float = 2.0, timeout_s: float | None = 10.0) -> None:
        """Turn the motor ``angle`` degrees and back to check its wiring (blocking).

        Raises:
            IncorrectStateError: Another blocking command runs, or still busy
                after ``timeout_s`` (stopped).
        """
        angle = self._check_finite("orientation angle", angle)
        self._require_enabled()
        self._require_no_blocking()
        try:
            self._send_blocking(Reg.CHECKORIENTATION, angle)
            self.wait_while_busy(timeout_s=timeout_s)
        finally:
            self._current_b_cmd = Reg.NONE

    def disable_closed_loop(self) -> None:
        """Disable the encoder closed loop (the joint reports not enabled)."""
        self._send(Reg.DISABLECLOSEDLOOP, 0)

    def set_drive_current(self, current: int) -> None:
        """Drive current, percent 0-100; 0 sets NOT_ENABLED."""
        self._send(Reg.SETCURRENT, self._check_percent("drive current", current))

    def set_hold_current(self, current: int) -> None:
        """Hold current, percent 0-100; 0 sets NOT_ENABLED."""
        self._send(Reg.SETHOLDCURRENT, self._check_percent("hold current", current))

    def set_brake_mode(self, mode: int) -> None:
        """Brake mode when idle: 0 freewheel, 1 coolbrake, 2 hardbrake."""
        try:
            mode = BrakeMode(mode)
        except ValueError as e:
            raise InvalidArgumentError(f"brake mode {mode!r} must be 0, 1 or 2", joint=self.name) from e
        self._send(Reg.SETBRAKEMODE, int(mode))

    def set_max_acceleration(self, acceleration: float) -> None:
        """Maximum acceleration and deceleration, rad/s^2 or m/s^2 (> 0).

        Sent as ``|rad2deg(reduction * acceleration)|`` deg/s^2; the magnitude
        is used because the lift's reduction is negative.
        """
        acceleration = self._check_finite("max acceleration", acceleration)
        if acceleration <= 0:
            raise InvalidArgumentError(f"max acceleration {acceleration} must be > 0", joint=self.name)
        self._send(Reg.SETMAXACCELERATION, abs(rate_to_degrees(acceleration, self.reduction)))

    def set_max_velocity(self, velocity: float) -> None:
        """Maximum velocity, rad/s or m/s (> 0); sent as deg/s like the acceleration."""
        velocity = self._check_finite("max velocity", velocity)
        if velocity <= 0:
            raise InvalidArgumentError(f"max velocity {velocity} must be > 0", joint=self.name)
        self._send(Reg.SETMAXVELOCITY, abs(rate_to_degrees(velocity, self.reduction)))

    def enable_stallguard(self, sensitivity: int) -> None:
        """Enable stall detection with threshold 10 x ``sensitivity`` (0-255); clears STALL."""
        self._send(Reg.ENABLESTALLGUARD, self._check_sensitivity("stall sensitivity", sensitivity))

    # ---------------------------------------------------------------- flags
    def get_flags(self) -> Flag:
        """Refresh the flags from the joint (a PING) and return them."""
        self._get(Reg.PING)
        return Flag(self._flags)

    @property
    def flags(self) -> Flag:
        """Flags of the last transaction (no bus traffic)."""
        return Flag(self._flags)

    def is_homed(self) -> bool:
        """Homed, per the last transaction's flags."""
        return not self._flags & FLAG_NOT_HOMED

    def is_enabled(self) -> bool:
        """Enabled, per the last transaction's flags (check STALL too)."""
        return not self._flags & FLAG_NOT_ENABLED

    def is_stalled(self) -> bool:
        """Stalled, per the last transaction's flags."""
        return bool(self._flags & FLAG_STALL)

    def is_busy(self) -> bool:
        """A blocking command runs, per the last transaction's flags."""
        return bool(self._flags & FLAG_BUSY)

    @property
    def current_blocking_command(self) -> Reg:
        """The blocking command the host started and has not finished (``Reg.NONE``)."""
        return self._current_b_cmd

    def __repr__(self) -> str:
        """Name and flags."""
        return f"{type(self).__name__}({self.name!r}, flags={Flag(self._flags)!r})"
