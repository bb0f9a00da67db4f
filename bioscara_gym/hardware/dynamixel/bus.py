"""The host side of a Dynamixel bus: transactions with retries, and MH5's sync loops.

:class:`DynamixelBus` owns the SDK's port and protocol 2.0 packet handler.
Every single-servo transaction (PING, READ, WRITE, REBOOT) goes through
:meth:`DynamixelBus.transact`, which retries and counts attempts in the
servo's :class:`~bioscara_gym.hardware.stats.CommStats`. The sync loops
(:class:`SyncLoop`) are the MH5 hardware interface's ``LoopWithCommunicationStats``:

============== ================================== ===========================
``pvl_reader`` SYNC READ 126-135: load, velocity,  100 Hz (MH5 default)
               position
``tv_reader``  SYNC READ 144-146: voltage,         1 Hz
               temperature
``pv_writer``  SYNC WRITE 104-119: goal velocity,  100 Hz
               profile acceleration and velocity,
               goal position (joints with a new
               command only)
``t_writer``   SYNC WRITE 64: Torque Enable        2 Hz
               (joints with a torque request only)
============== ================================== ===========================

:meth:`DynamixelBus.read` runs the readers and :meth:`DynamixelBus.write`
the writers; each loop runs only when its period has passed since its last
run (a call too soon is skipped, as in the MH5), and keeps
:class:`LoopStats`. The SDK is imported lazily: building a bus without it
raises :class:`~bioscara_gym.hardware.errors.MissingExtraError`.

Replies are checked: a protocol 2.0 status packet does not say which request
it answers, so it must come from the servo asked and carry exactly the data
asked for (:func:`status_data`; the SDK's ``readTxRx`` slices whatever packet
came to the length asked). One that does not (a short or long packet, another
ID) is a failed attempt (``malformed``), retried, and in the end a
:class:`~bioscara_gym.hardware.errors.CommError` naming the joint, what was
wrong and the packet's bytes. The SDK flushes the port before each request,
which drops what has arrived but not a reply still on its way; so after an
attempt that got no proper reply, the next request waits until the line has
been quiet for :data:`LATE_REPLY_QUIET_S` and drops what came meanwhile
(:meth:`DynamixelBus._settle`): a late reply to an earlier request is not taken
as the reply to the next one.
"""

from __future__ import annotations

import logging
import threading
import time
from collections.abc import Callable, Mapping
from dataclasses import dataclass, field
from typing import Any, Protocol

from bioscara_gym.hardware.clock import Clock, WallClock
from bioscara_gym.hardware.dynamixel.control_table import (
    ALERT,
    DEFAULT_LOOP_RATES,
    PV_LENGTH,
    PV_START,
    PVL_LENGTH,
    PVL_START,
    TV_LENGTH,
    TV_START,
    to_signed,
    to_unsigned,
)
from bioscara_gym.hardware.errors import CommError, MissingExtraError
from bioscara_gym.hardware.stats import CommStats


class DynamixelJoint(Protocol):
    """What the bus needs of a joint (:class:`~bioscara_gym.hardware.dynamixel.joint.DynamixelJoint`)."""

    name: str
    dxl_id: int
    stats: CommStats

    @property
    def initialized(self) -> bool:
        """Whether the joint was ``init()``-ed (only those take part in the loops)."""
        ...

    def note_status(self, error: int) -> None:
        """Take a status packet's error byte."""
        ...

    def cache_pvl(self, load: int, velocity: int, position: int, now: float) -> None:
        """Values of one ``pvl_reader`` run."""
        ...

    def cache_tv(self, voltage: int, temperature: int) -> None:
        """Values of one ``tv_reader`` run."""
        ...

    def has_pv_command(self) -> bool:
        """Whether a command waits for the ``pv_writer``."""
        ...

    def take_pv_command(self) -> bytes:
        """The ``pv_writer``'s block."""
        ...

    def has_torque_request(self) -> bool:
        """Whether a torque change waits for the ``t_writer``."""
        ...

    def take_torque_request(self) -> bytes:
        """The ``t_writer``'s byte."""
        ...


log = logging.getLogger(__name__)

#: The SDK's "success" result code (``COMM_SUCCESS``).
COMM_SUCCESS = 0
#: The SDK's "no status packet" result code (``COMM_RX_TIMEOUT``).
COMM_RX_TIMEOUT = -3001
#: The SDK's "incorrect status packet" result code (``COMM_RX_CORRUPT``).
COMM_RX_CORRUPT = -3002
#: Instruction bytes (protocol 2.0): PING, READ, WRITE, REBOOT, and a status packet's.
INST_PING, INST_READ, INST_WRITE, INST_REBOOT, INST_STATUS = 0x01, 0x02, 0x03, 0x08, 0x55
#: Data bytes of a PING's status packet: model number (2) and firmware version (1).
PING_DATA_LENGTH = 3
#: After a failed exchange, how long the line must stay quiet before the next request, s.
#: A late status packet (one that came after the SDK gave up on it: a slow servo,
#: an emulator catching up) arrives within this and is dropped, instead of being
#: taken as the reply to the next request. Beyond the SDK's own wait (34 ms at 1 Mbps).
LATE_REPLY_QUIET_S = 0.05
#: The longest wait for the line to go quiet, s (a line that keeps talking is not waited out).
LATE_REPLY_MAX_S = 0.5


class BadReply(Exception):
    """A status packet that is not the reply to the request sent: short, long, another ID, truncated.

    The message says what was wrong and shows the packet's bytes.

    Attributes:
        packet: The packet as received (after the SDK removed the byte stuffing).
    """

    def __init__(self, reason: str, packet: bytes | list[int] | None = None) -> None:
        """Say what was wrong; the packet's bytes are appended."""
        self.packet = bytes(packet or b"")
        shown = self.packet.hex(" ").upper() if self.packet else "none"
        super().__init__(f"{reason}; reply {shown}")


def status_data(packet: bytes | list[int], dxl_id: int, size: int) -> tuple[bytes, int]:
    """The data and error byte of ``dxl_id``'s status packet that must carry exactly ``size`` data bytes.

    ``packet`` is what the SDK's ``rxPacket`` returned (CRC checked, byte
    stuffing removed): ``FF FF FD 00 | ID | LEN_L LEN_H | 55 | ERR | data… | CRC``.
    A protocol 2.0 status packet does not say which request it answers; its
    ID and length are all there is to tell a late reply to an earlier request
    (a PING's 3 bytes, a READ of another size) from the one expected.

    Raises:
        BadReply: Another ID, not a status packet, shorter than its LEN, or
            not ``size`` data bytes.
    """
    raw = bytes(packet)
    if len(raw) < 11:
        raise BadReply(f"a status packet of {len(raw)} bytes, shorter than any (11)", raw)
    if raw[4] != dxl_id:
        raise BadReply(f"a status packet from ID {raw[4]}, not ID {dxl_id}", raw)
    if raw[7] != INST_STATUS:
        raise BadReply(f"a packet with instruction {raw[7]:#04x}, not a status packet (0x55)", raw)
    length = raw[5] | raw[6] << 8
    if length < 4 or len(raw) < 7 + length:
        raise BadReply(f"a truncated status packet (LEN {length}, {len(raw)} bytes)", raw)
    got = length - 4  # LEN counts INST, ERR, the data and the CRC
    if got != size:
        raise BadReply(
            f"a status packet with {got} data byte{'s' if got != 1 else ''} where {size} "
            f"{'were' if size != 1 else 'was'} expected (a late reply to an earlier request?)",
            raw,
        )
    return raw[9 : 9 + size], raw[8]


def drain_port(port: Any, since: float, quiet_s: float, max_s: float) -> tuple[int, bool]:
    """Read and drop bytes until none came for ``quiet_s``, counted from ``since`` at the earliest.

    ``since`` is the :func:`time.monotonic` time the exchange failed. Gives
    up after ``max_s`` of a line that keeps talking.

    Returns:
        The bytes dropped, and whether the line went quiet.
    """
    start = last = time.monotonic()
    last = min(last, since)
    dropped = 0
    while True:
        now = time.monotonic()
        waiting = port.getBytesAvailable()
        if waiting:
            dropped += len(port.readPort(waiting))
            last = now
        elif now - last >= quiet_s:
            return dropped, True
        if now - start >= max_s:
            return dropped, False
        if not waiting:
            time.sleep(0.001)


def load_sdk() -> Any:
    """Import ``dynamixel_sdk``, or raise the one-line :class:`MissingExtraError`."""
    try:
        import dynamixel_sdk
    except ModuleNotFoundError as e:
        if e.name is not None and e.name.split(".")[0] not in ("dynamixel_sdk", "serial"):
            raise
        raise MissingExtraError("Dynamixel joints (the dynamixel-sdk package)", "dynamixel") from e
    return dynamixel_sdk


def packet_handler(sdk: Any) -> Any:
    """The SDK's Protocol 2.0 packet handler, with its byte stuffing of what it sends made to take effect.

    dynamixel-sdk's ``Protocol2PacketHandler.txPacket`` calls
    ``addStuffing(txpacket)`` and drops the result; when stuffing lengthens
    the packet, ``addStuffing`` builds a new list and the caller's goes out
    unstuffed, LEN too. Any ``FF FF FD`` in the data (a Homing Offset of
    ``0x00FDFFFF``; a negative Goal Velocity beside a Profile Acceleration
    whose low byte is ``FD`` in a SYNC WRITE) then reaches the servo one
    byte short: a WRITE is refused with a Data Length Error, a SYNC WRITE
    dropped without a word. This handler's ``addStuffing`` writes the
    stuffed packet back into the caller's list, which ``txPacket`` sends.
    """
    base = type(sdk.PacketHandler(2.0))

    class StuffingPacketHandler(base):  # type: ignore[misc, valid-type]
        def addStuffing(self, packet: list[int]) -> list[int]:  # the SDK's name
            packet[:] = super().addStuffing(packet)
            return packet

    return StuffingPacketHandler()


def port_module() -> Any:
    """The :mod:`~bioscara_gym.hardware.dynamixel.port` module (needs the SDK)."""
    load_sdk()
    from bioscara_gym.hardware.dynamixel import port

    return port


@dataclass
class LoopStats:
    """One sync loop's communication statistics, since the last reset and in total.

    The MH5's ``packets``/``errors`` and ``tot_packets``/``tot_errors``, plus
    timeouts (an error with no status packet at all) and the rate the loop
    achieved. ``transactions`` is the MH5's ``packets`` (one SYNC READ or
    SYNC WRITE, whatever the number of servos), so that the console shows
    loops and joints alike.

    Attributes:
        rate_hz: Configured rate (0: the loop never runs).
        transactions: Executions since the last reset.
        errors: Failed executions since the last reset.
        timeouts: Failed executions with no answer at all, since the last reset.
        total_transactions: Executions since start.
        total_errors: Failed executions since start.
        total_timeouts: Timeouts since start.
        skipped: Calls that came too soon since the last reset.
        first_s: Clock time of the first execution since the last reset.
        last_s: Clock time of the last execution.
    """

    rate_hz: float = 0.0
    transactions: int = 0
    errors: int = 0
    timeouts: int = 0
    total_transactions: int = 0
    total_errors: int = 0
    total_timeouts: int = 0
    skipped: int = 0
    first_s: float | None = None
    last_s: float | None = None

    @property
    def packets(self) -> int:
        """The MH5's name for :attr:`transactions`."""
        return self.transactions

    def record(self, now: float, ok: bool, timeout: bool = False) -> None:
        """Count one execution at ``now``."""
        self.transactions += 1
        self.total_transactions += 1
        if self.first_s is None:
            self.first_s = now
        self.last_s = now
        if not ok:
            self.errors += 1
            self.total_errors += 1
            if timeout:
                self.timeouts += 1
                self.total_timeouts += 1

    def reset(self) -> None:
        """Zero the since-reset counters (MH5 ``resetStats``); totals are kept."""
        self.transactions = self.errors = self.timeouts = self.skipped = 0
        self.first_s = None

    def reset_all(self) -> None:
        """Zero everything, totals included (MH5 ``resetAllStats``)."""
        self.reset()
        self.total_transactions = self.total_errors = self.total_timeouts = 0
        self.last_s = None

    @property
    def error_rate(self) -> float:
        """Errors per execution since the last reset (0.0 when idle)."""
        return self.errors / self.transactions if self.transactions else 0.0

    @property
    def achieved_hz(self) -> float:
        """Executions per second since the last reset (0.0 before two executions)."""
        if (
            self.transactions < 2
            or self.first_s is None
            or self.last_s is None
            or self.last_s <= self.first_s
        ):
            return 0.0
        return (self.transactions - 1) / (self.last_s - self.first_s)

    def as_dict(self) -> dict[str, float]:
        """The counters and rates as a plain dict (for logs)."""
        return {
            "rate_hz": self.rate_hz,
            "achieved_hz": self.achieved_hz,
            "packets": self.transactions,
            "errors": self.errors,
            "timeouts": self.timeouts,
            "skipped": self.skipped,
            "total_packets": self.total_transactions,
            "total_errors": self.total_errors,
            "total_timeouts": self.total_timeouts,
            "error_rate": self.error_rate,
        }


@dataclass
class SyncLoop:
    """A communication that runs at its own rate and keeps statistics (MH5 ``LoopWithCommunicationStats``).

    Attributes:
        name: Loop name (``pvl_reader``…).
        rate_hz: Execution rate; 0 or less never runs.
        communicate: Does the work; returns the SDK result code of the execution.
        stats: The loop's statistics.
    """

    name: str
    rate_hz: float
    communicate: Callable[[], int | None]
    stats: LoopStats = field(default_factory=LoopStats)
    _last: float | None = None

    def __post_init__(self) -> None:
        """Copy the rate into the statistics."""
        self.stats.rate_hz = self.rate_hz

    @property
    def period_s(self) -> float:
        """Seconds between executions."""
        return 1.0 / self.rate_hz if self.rate_hz > 0 else float("inf")

    def execute(self, now: float) -> bool | None:
        """Run if a period has passed since the last run; None if skipped, else whether it succeeded.

        The schedule advances by one period per run (as the MH5's
        ``last_execution_time_ += period``) and restarts from ``now`` after a
        gap of more than a period, so a late call does not cause a burst.
        """
        if self.rate_hz <= 0:
            return None
        if self._last is not None and now - self._last < self.period_s - 1e-9:
            self.stats.skipped += 1
            return None
        self._last = (
            now if self._last is None or now - self._last >= 2 * self.period_s else self._last + self.period_s
        )
        result = self.communicate()
        if result is None:  # nothing to send (no new command): not a packet
            return True
        ok = result == COMM_SUCCESS
        self.stats.record(now, ok, timeout=result == COMM_RX_TIMEOUT)
        return ok


class DynamixelBus:
    """One RS-485 bus of Dynamixel servos seen from the host (protocol 2.0).

    Args:
        port: An SDK port handler, not yet opened (:class:`RS485PortHandler`,
            :class:`EmulatedPortHandler`).
        baudrate: Bits per second.
        rs485: Put the port in RS-485 mode (``TIOCSRS485``); failure is logged, not raised.
        clock: Time source of the loops and of waits.
        rates: Loop name to rate in Hz (defaults: :data:`DEFAULT_LOOP_RATES`).
        retries: Extra attempts of a failed single-servo transaction.

    Attributes:
        late_reply_s: How long the line must stay quiet after a failed
            exchange before the next request (:data:`LATE_REPLY_QUIET_S`).
        late_bytes: Bytes dropped so far while waiting for the line to go quiet.
    """

    def __init__(
        self,
        port: Any,
        baudrate: int = 1_000_000,
        rs485: bool = False,
        clock: Clock | None = None,
        rates: Mapping[str, float] | None = None,
        retries: int = 2,
    ) -> None:
        """Keep the port; it is opened by :meth:`open` (or the first joint's ``init``)."""
        sdk = load_sdk()
        unknown = set(rates or {}) - set(DEFAULT_LOOP_RATES)
        if unknown:
            raise ValueError(f"unknown loops {sorted(unknown)}; known: {', '.join(DEFAULT_LOOP_RATES)}")
        self.sdk = sdk
        self.port = port
        self.packet_handler = packet_handler(sdk)
        self.baudrate = baudrate
        self.rs485 = rs485
        self.clock: Clock = clock if clock is not None else WallClock()
        self.retries = retries
        self.lock = threading.RLock()
        self.joints: dict[int, DynamixelJoint] = {}
        self.opened = False
        self.synced = False
        self.late_reply_s = LATE_REPLY_QUIET_S
        self.late_bytes = 0
        # monotonic time of the last exchange after which a reply may still be on its way, or None
        self._unsettled_since: float | None = None
        rates = {**DEFAULT_LOOP_RATES, **(rates or {})}
        self.loops: dict[str, SyncLoop] = {
            "pvl_reader": SyncLoop("pvl_reader", rates["pvl_reader"], self._read_pvl),
            "tv_reader": SyncLoop("tv_reader", rates["tv_reader"], self._read_tv),
            "pv_writer": SyncLoop("pv_writer", rates["pv_writer"], self._write_pv),
            "t_writer": SyncLoop("t_writer", rates["t_writer"], self._write_torque),
        }

    # ------------------------------------------------------------ port
    def open(self) -> None:
        """Open the port at the baud rate (and RS-485 mode if asked); idempotent."""
        with self.lock:
            if self.opened:
                return
            try:
                ok = self.port.openPort()
            except Exception as e:  # pyserial raises SerialException (an OSError subclass) or ValueError
                raise CommError(f"cannot open {self.port.getPortName()}: {e}") from e
            if not ok or not self.port.setBaudRate(self.baudrate):
                raise CommError(f"cannot open {self.port.getPortName()} at {self.baudrate} bps")
            if self.rs485:
                self.port.set_rs485()
            self.opened = True

    def close(self) -> None:
        """Close the port."""
        with self.lock:
            if self.opened:
                self.port.closePort()
                self.opened = False

    def attach(self, joint: DynamixelJoint) -> None:
        """Register a joint (by its servo ID) for the sync loops."""
        other = self.joints.get(joint.dxl_id)
        if other is not None and other is not joint and other.name != joint.name:
            raise ValueError(f"ID {joint.dxl_id} is used by {other.name} and {joint.name}")
        self.joints[joint.dxl_id] = joint

    # ------------------------------------------------------------ late replies
    def _unsettle(self) -> None:
        """An exchange failed: a reply to it may still come; drop it before the next request."""
        self._unsettled_since = time.monotonic()

    def _settle(self) -> None:
        """Before a request: after a failed exchange, wait for the line to go quiet and drop what came.

        The SDK flushes the port's input before every request
        (``Protocol2PacketHandler.txPacket`` calls ``clearPort``), which drops
        what has arrived, not a status packet still on its way: one that comes
        after the SDK stopped waiting for it would be taken as the reply to
        the next request to the same ID. So after a failure the line must be
        quiet for :attr:`late_reply_s` first. A port whose replies cannot come
        late (:class:`~.port.EmulatedPortHandler`) says so with
        ``discard_late_replies``.
        """
        since = self._unsettled_since
        if since is None:
            return
        self._unsettled_since = None
        discard = getattr(self.port, "discard_late_replies", None)
        try:
            if discard is not None:
                dropped, quiet = discard(), True
            else:
                dropped, quiet = drain_port(self.port, since, self.late_reply_s, LATE_REPLY_MAX_S)
        except OSError:  # the device went away: the request that follows fails and says so
            dropped, quiet = 0, True
        if dropped:
            self.late_bytes += dropped
            log.debug("%s: dropped %d bytes of late replies", self.port.getPortName(), dropped)
        if not quiet:
            self._unsettled_since = time.monotonic()

    # ------------------------------------------------------------ single servo
    def transact(
        self, joint: DynamixelJoint, what: str, call: Callable[[], tuple[Any, int, int]]
    ) -> tuple[Any, int]:
        """Run an SDK call ``() -> (value, result, error)`` with retries; return ``(value, error byte)``.

        A status packet with an error number (bits 0-6) counts as a failed
        attempt; the Alert bit alone does not (the servo did what it was
        told and reports its hardware error; the caller reads the flags).
        A status packet that is not the reply to the request (``call``
        raises :class:`BadReply`) is a failed attempt counted ``malformed``.
        After an attempt with no proper reply, the next request waits for the
        line to go quiet (:meth:`_settle`).

        Raises:
            CommError: Every attempt failed; the message names the joint, ID and reason.
        """
        self.open()
        last = ""
        unsettled = False  # an attempt of this transaction may have a reply still on its way
        with self.lock:
            self._settle()  # what an earlier transaction left on its way
            late_before = self.late_bytes
            for attempt in range(self.retries + 1):
                self._settle()
                retry = attempt > 0
                try:
                    value, result, error = call()
                except BadReply as e:
                    joint.stats.record(ok=False, kind="malformed", retry=retry)
                    self._unsettle()
                    unsettled, last = True, str(e)
                    continue
                except OSError as e:  # pyserial's SerialException: the device went away
                    self.port.is_using = False
                    joint.stats.record(ok=False, retry=retry)
                    self._unsettle()
                    unsettled, last = True, f"the port failed: {e}"
                    continue
                if result == COMM_SUCCESS and not error & ~ALERT & 0xFF:
                    joint.stats.record(ok=True, retry=retry)
                    joint.note_status(error)
                    if unsettled:  # the reply taken may be an earlier attempt's: this one's may follow
                        self._unsettle()
                    return value, error
                joint.stats.record(ok=False, retry=retry)
                if result != COMM_SUCCESS:
                    self._unsettle()
                    unsettled = True
                    last = self.packet_handler.getTxRxResult(result)
                else:
                    joint.note_status(error)
                    last = self.packet_handler.getRxPacketError(error)
            if unsettled:  # the last attempt's reply may still come: drop it now, and say so
                self._settle()
            late = self.late_bytes - late_before
            if late:
                last = f"{last}; {late} bytes came after the wait and were dropped"
        raise CommError(
            f"{what} failed after {self.retries + 1} attempts: {last}. "
            "Check the cable, power, ID and baud rate",
            joint=joint.name,
        )

    def exchange(self, dxl_id: int, instruction: int, params: list[int], size: int) -> tuple[bytes, int, int]:
        """One request and its status packet, checked: ``(data, SDK result, error byte)``.

        The SDK's ``txRxPacket`` with its timeouts, except that the status
        packet must come from ``dxl_id`` and carry exactly ``size`` data
        bytes (:func:`status_data`); the SDK's ``readTxRx`` takes any packet
        from the ID and slices it to the length asked, so that a late PING
        reply (3 bytes) became a short READ, and a late 7-byte READ's first
        byte a 1-byte one.

        Raises:
            BadReply: A status packet that is not the reply to this request, or
                only other IDs' packets before the SDK stopped waiting.
        """
        ph, port = self.packet_handler, self.port
        txpacket = [0] * (10 + len(params))
        length = len(params) + 3  # INST, the parameters, CRC
        txpacket[4], txpacket[5], txpacket[6], txpacket[7] = dxl_id, length & 0xFF, length >> 8, instruction
        txpacket[8 : 8 + len(params)] = params
        result = ph.txPacket(port, txpacket)
        if result != COMM_SUCCESS:
            return b"", result, 0
        # as txRxPacket: READ waits for its data, other instructions for a bare status packet
        port.setPacketTimeout(size + 11 if instruction == INST_READ else 11)
        return self._receive(dxl_id, size)

    def _receive(self, dxl_id: int, size: int, name_others: bool = True) -> tuple[bytes, int, int]:
        """``dxl_id``'s status packet of ``size`` data bytes (the SDK's ``readRx``, checked).

        Packets from other IDs are passed over, as the SDK does; if no packet
        from ``dxl_id`` follows, that is what was wrong (``name_others``),
        else the SDK's timeout is returned.

        Raises:
            BadReply: See :meth:`exchange`.
        """
        others: list[int] = []
        other: list[int] = []
        while True:
            packet, result = self.packet_handler.rxPacket(self.port, False)
            if result != COMM_SUCCESS:
                if others and name_others:
                    ids = ", ".join(str(i) for i in dict.fromkeys(others))
                    raise BadReply(f"no status packet from ID {dxl_id}, one from ID {ids} instead", other)
                return b"", result, 0
            if packet[4] == dxl_id:
                data, error = status_data(packet, dxl_id, size)
                return data, COMM_SUCCESS, error
            others.append(packet[4])
            other = packet

    def ping(self, joint: DynamixelJoint, tries: int | None = None) -> int:
        """PING the joint's servo; return its model number."""
        i = joint.dxl_id
        saved = self.retries
        if tries is not None:
            self.retries = tries - 1
        try:
            data, _ = self.transact(joint, "PING", lambda: self.exchange(i, INST_PING, [], PING_DATA_LENGTH))
        finally:
            self.retries = saved
        return int.from_bytes(data[:2], "little")

    def read(self, joint: DynamixelJoint, address: int, size: int, signed: bool = False) -> int:
        """READ ``size`` bytes at ``address`` as one little-endian value (see :meth:`read_block`)."""
        value = int.from_bytes(self.read_block(joint, address, size), "little")
        return to_signed(value, size) if signed else value

    def read_block(self, joint: DynamixelJoint, address: int, size: int) -> bytes:
        """READ ``size`` raw bytes at ``address``: exactly ``size`` bytes, or CommError."""
        params = [address & 0xFF, address >> 8, size & 0xFF, size >> 8]
        data, _ = self.transact(
            joint, f"READ {address}", lambda: self.exchange(joint.dxl_id, INST_READ, params, size)
        )
        if len(data) != size:  # exchange() checked it: never padded, never cut
            raise CommError(f"READ {address}: {len(data)} bytes where {size} were asked", joint=joint.name)
        return bytes(data)

    def write(self, joint: DynamixelJoint, address: int, size: int, value: int) -> int:
        """WRITE one value; return the status packet's error byte."""
        data = list(to_unsigned(int(value), size).to_bytes(size, "little"))
        params = [address & 0xFF, address >> 8, *data]
        return self.transact(
            joint, f"WRITE {address}", lambda: self.exchange(joint.dxl_id, INST_WRITE, params, 0)
        )[1]

    def reboot(self, joint: DynamixelJoint) -> None:
        """REBOOT the joint's servo."""
        self.transact(joint, "REBOOT", lambda: self.exchange(joint.dxl_id, INST_REBOOT, [], 0))

    # ------------------------------------------------------------ loops
    def start_loops(self) -> None:
        """From now on joints take positions from ``pvl_reader`` and send commands through ``pv_writer``."""
        self.synced = True

    def stop_loops(self) -> None:
        """Back to one transaction per call."""
        self.synced = False

    def read_loops(self, now: float | None = None) -> None:
        """Run ``pvl_reader`` and ``tv_reader`` if due (the MH5's ``read``)."""
        now = self.clock.now() if now is None else now
        self.loops["pvl_reader"].execute(now)
        self.loops["tv_reader"].execute(now)

    def write_loops(self, now: float | None = None) -> None:
        """Run ``pv_writer`` and ``t_writer`` if due (the MH5's ``write``)."""
        now = self.clock.now() if now is None else now
        self.loops["pv_writer"].execute(now)
        self.loops["t_writer"].execute(now)

    def loop_stats(self) -> dict[str, LoopStats]:
        """Statistics of every loop, by name."""
        return {name: loop.stats for name, loop in self.loops.items()}

    def _present(self) -> list[DynamixelJoint]:
        return [j for j in self.joints.values() if j.initialized]

    def _sync_read(
        self, start: int, length: int, store: Callable[[DynamixelJoint, bytes, int], None]
    ) -> int | None:
        joints = self._present()
        if not joints:
            return None
        self.open()
        ph, port = self.packet_handler, self.port
        with self.lock:
            self._settle()
            params = [j.dxl_id for j in joints]
            try:
                result = ph.syncReadTx(port, start, length, params, len(params), False)
                if result != COMM_SUCCESS:
                    self._unsettle()
                    return result
                final = COMM_SUCCESS
                for j in joints:
                    try:
                        data, result, error = self._receive(j.dxl_id, length, name_others=False)
                    except BadReply as e:
                        log.debug("%s: SYNC READ %d: %s", j.name, start, e)
                        result = COMM_RX_CORRUPT
                    if result != COMM_SUCCESS:
                        final = result
                        self._unsettle()
                        continue  # the others may still have answered
                    store(j, data, error)
            except OSError:  # pyserial's SerialException: the device went away
                self._unsettle()
                final = COMM_RX_CORRUPT
            port.is_using = False
            return final

    def _read_pvl(self) -> int | None:
        def store(j: DynamixelJoint, data: bytes, error: int) -> None:
            j.note_status(error)
            j.cache_pvl(
                to_signed(int.from_bytes(data[0:2], "little"), 2),
                to_signed(int.from_bytes(data[2:6], "little"), 4),
                to_signed(int.from_bytes(data[6:10], "little"), 4),
                self.clock.now(),
            )

        return self._sync_read(PVL_START, PVL_LENGTH, store)

    def _read_tv(self) -> int | None:
        def store(j: DynamixelJoint, data: bytes, error: int) -> None:
            j.note_status(error)
            j.cache_tv(int.from_bytes(data[0:2], "little"), data[2])

        return self._sync_read(TV_START, TV_LENGTH, store)

    def _sync_write(self, start: int, length: int, items: dict[int, bytes]) -> int | None:
        if not items:
            return None
        self.open()
        ph, port = self.packet_handler, self.port
        params: list[int] = []
        for i, data in items.items():
            params.append(i)
            params.extend(data)
        with self.lock:
            return ph.syncWriteTxOnly(port, start, length, params, len(params))

    def _write_pv(self) -> int | None:
        items = {j.dxl_id: j.take_pv_command() for j in self._present() if j.has_pv_command()}
        assert all(len(d) == PV_LENGTH for d in items.values())
        return self._sync_write(PV_START, PV_LENGTH, items)

    def _write_torque(self) -> int | None:
        items = {j.dxl_id: j.take_torque_request() for j in self._present() if j.has_torque_request()}
        return self._sync_write(64, 1, items)
