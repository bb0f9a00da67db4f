"""Bus traces: every I2C transaction of a session as one JSON line, recorded and replayed.

A trace (``docs/traces.md``) is a JSON Lines file of one or more sessions.
Each session is a ``header`` line, then one ``tx`` line per transaction, in
the order the driver sent them, then an ``end`` line when the recording was
closed. Every line carries a ``digest`` of itself chained to the line before
it in its session (:func:`line_digest`), so a changed byte, or a line
removed, is found and named when the trace is read::

    {"type": "header", "format": "bioscara-bus-trace", "version": 1, "bioscara_gym": "0.1.0",
     "backend": "emulated", "config": {...}, "command": "deploy", "args": {...},
     "context": {...}, "t0": 0.0, "started": "2025-01-01T12:00:00+0000"}
    {"type": "tx", "i": 0, "t": 0.0, "dur": 0.0, "addr": "0x11", "write": "0f", "read_len": 2,
     "read": "4f0c"}
    {"type": "tx", "i": 1, ..., "error": {"errno": 121, "message": "Remote I/O error (address 0x11)"}}
    {"type": "tx", "i": 2, ..., "interrupted": "SIGINT"}
    {"type": "signal", "i": 3, "t": 0.012, "signal": "SIGINT", "at": "cycle"}
    {"type": "end", "transactions": 3, "t": 0.015}

A ``signal`` line says where a stop signal (SIGINT, SIGTERM, SIGHUP)
stopped the command, so a replay delivers it at the same place (``at``:
``"cycle"``, it arrived during the transactions before ``i`` and was raised
at the next cycle boundary; ``"once"``, raised before transaction ``i``); a
transaction that one cut short has ``interrupted`` in place of its reply. The ``end`` line
counts the session's transactions: a session of version 4 or later without
one was cut (the recorder killed, the disk full, the file truncated), and a
replay that runs past its last line says so (:class:`TraceCut`) rather than
blaming the driver.

:class:`RecordingBus` writes a session around any :class:`~.bus.I2CBus`;
:func:`read_trace` reads a file back; :class:`ReplayBus` serves a session's
replies to the driver and raises :class:`TraceMismatch` on the first
transaction that differs from the recording.
"""

from __future__ import annotations

import contextlib
import dataclasses
import functools
import hashlib
import json
import math
import os
import signal
import threading
import time
from collections.abc import Callable, Iterator, Mapping, Sequence
from dataclasses import dataclass, field
from pathlib import Path
from types import FrameType
from typing import Any

from bioscara_gym.fsutil import read_bytes
from bioscara_gym.hardware.bus import I2CBus
from bioscara_gym.hardware.clock import Clock, ManualClock
from bioscara_gym.hardware.config import ArmConfig, config_to_dict
from bioscara_gym.hardware.registry import backend_names
from bioscara_gym.stop_signals import STOP_SIGNALS, SignalHandler, put_back

#: ``format`` and ``version`` of a trace header; a reader refuses newer versions.
#: Version 2 added the per-line ``digest``; version 1 traces have none.
#: Version 3 added ``signal`` lines and a transaction's ``interrupted``.
#: Version 4 added the ``end`` line that closes a session.
#: Version 5 added ``SIGHUP`` to the signals a trace names (the terminal closed).
TRACE_FORMAT = "bioscara-bus-trace"
#: Largest trace :func:`read_trace` reads whole, bytes: some 200 bytes a transaction, so an
#: hour's deploy at 25 Hz (1.1 million transactions) is about a fifth of it.
MAX_TRACE_BYTES = 1024**3
TRACE_VERSION = 5
#: The first version whose sessions end with an ``end`` line: one without it was cut.
CLOSING_LINE_VERSION = 4
#: What a session cut short is told by (:class:`TraceCut`, a partial last line).
CUT_REASON = "the recording was cut (killed, disk full, or truncated)"
#: Where a signal line's signal is raised again (:class:`SignalNote`).
SIGNAL_AT = ("cycle", "once")
#: Hex digits of a line's digest kept (64 bits of SHA-256: a changed line is
#: found, not a forgery resisted: anyone can recompute a digest).
DIGEST_HEX = 16
#: The ``type`` of each kind of trace line.
LINE_TYPES = ("header", "tx", "signal", "end")
#: Backends whose joints talk over an I2C bus, so they can be recorded.
RECORDABLE_BACKENDS = backend_names("records")

#: Wraps a backend's bus before its joints get it: ``(bus, clock) -> bus``.
BusWrapper = Callable[[I2CBus, Clock], I2CBus]


class TraceError(ValueError):
    """A trace file that cannot be read; the message names the file and line."""


class TraceMismatch(Exception):
    """The driver sent a transaction other than the recorded one (or one more than recorded).

    Attributes:
        index: The transaction's index in its session, from 0.
        line: Its line in the trace file (``None`` past the end).
        expected: The recorded transaction, ``None`` past the end.
        sent: ``(address, bytes written, read length)`` the driver sent.
    """

    def __init__(
        self, index: int, line: int | None, expected: Transaction | None, sent: tuple[int, bytes, int]
    ) -> None:
        """Describe the first difference."""
        self.index, self.line, self.expected, self.sent = index, line, expected, sent
        where = f"transaction {index}" + (f" (trace line {line})" if line is not None else "")
        expected_text = "the end of the trace" if expected is None else describe(expected.request)
        super().__init__(f"{where}: expected {expected_text}, sent {describe(sent)}")


class TraceCut(Exception):
    """The driver went on past the last line of a session that has no closing line: the trace is damaged.

    Seen: a trace cut at a line boundary (the recorder killed with -9, ``head
    -n 1000``) was replayed as the driver's "mismatch ...: expected the end
    of the trace". A session of version 4 or later ends with an ``end`` line
    when its recording is closed; without one, what the driver sends next
    was never written down, so nothing can be said of the driver.

    Attributes:
        index: The transactions the session holds (the index of the one asked for).
        line: The trace line of its last transaction (``None``: it has none).
    """

    def __init__(self, index: int, line: int | None) -> None:
        """Say where the session ends."""
        self.index, self.line = index, line
        where = "its header" if line is None else f"transaction {index - 1} (trace line {line})"
        super().__init__(f"ends after {where} without its closing line: {CUT_REASON}")


def line_digest(record: Mapping[str, Any], previous: str) -> str:
    """The digest of one trace line: SHA-256 of the digest before it and the line's canonical JSON.

    Args:
        record: The line as data; its own ``digest`` key is left out.
        previous: The digest of the line before it in its session (``""`` for the header).
    """
    body = {k: v for k, v in record.items() if k != "digest"}
    text = json.dumps(body, sort_keys=True, separators=(",", ":"))
    return hashlib.sha256((previous + text).encode("utf-8")).hexdigest()[:DIGEST_HEX]


def describe(request: tuple[int, bytes, int]) -> str:
    """``0x11 write 15 00 00 20 41 read 1``: one transaction's request, bytes in hex."""
    address, data, read_len = request
    return f"{address:#04x} write {data.hex(' ') or '(none)'} read {read_len}"


# ------------------------------------------------------------------ recording
@dataclass(frozen=True)
class Recording:
    """Where to record a session and what to write in its header to replay it.

    Attributes:
        path: The trace file; a new session is appended if it exists.
        command: The ``bioscara`` subcommand that runs (``deploy``, ``eval``, ``move``, ...).
        args: Its arguments, as ``bioscara replay`` needs them to run it again.
        context: Anything else the command starts from (the console's ``--state`` document).
    """

    path: Path
    command: str
    args: Mapping[str, Any] = field(default_factory=dict)
    context: Mapping[str, Any] = field(default_factory=dict)

    def __post_init__(self) -> None:
        """Refuse, before the command runs, a file a session cannot be appended to.

        Raises:
            ValueError: ``path`` is not a regular file, or holds something
                other than a trace (seen: ``--record`` appended a session to a
                model's ``metadata.json``, which no longer read).
        """
        problem = _append_problem(Path(self.path))
        if problem is not None:
            raise ValueError(f"--record {self.path}: {problem}")


#: Longest first line read to tell a trace (its header holds the arm's configuration: some 5 kB).
_MAX_HEADER_BYTES = 1024 * 1024


def _append_problem(path: Path) -> str | None:
    """Why a session cannot be appended to ``path``, or ``None`` (it is new, empty or a trace)."""
    if not path.exists():
        return None
    if not path.is_file():
        return "is not a regular file"
    size = path.stat().st_size
    if size == 0:
        return None
    not_a_trace = f"exists and is not a bus trace ({TRACE_FORMAT}); give a new file, or a trace to add to"
    with path.open("rb") as f:
        first = _json_line(f.readline(_MAX_HEADER_BYTES))
        f.seek(max(0, size - _MAX_HEADER_BYTES))
        end = f.read()
    if first is None or first.get("type") != "header" or first.get("format") != TRACE_FORMAT:
        return not_a_trace
    if not end.endswith(b"\n"):  # a new session would be glued onto its last line
        return "does not end with a whole line; it is no trace a session can be added to"
    last = _json_line(end[:-1].rsplit(b"\n", 1)[-1])
    if last is None or last.get("type") not in LINE_TYPES:
        return "does not end with a trace's line; it is no trace a session can be added to"
    return None


def _json_line(raw: bytes) -> Mapping[str, Any] | None:
    """``raw`` as a JSON object, or ``None``."""
    try:
        doc = json.loads(raw)
    except (ValueError, RecursionError):
        return None
    return doc if isinstance(doc, Mapping) else None


def jsonable_args(args: object) -> dict[str, Any]:
    """A command's arguments (a namespace, dataclass or mapping) as JSON data.

    Paths become strings; what is not JSON data (callables, a replay's bus
    objects) and names starting with ``_`` are left out.
    """
    if dataclasses.is_dataclass(args) and not isinstance(args, type):
        items = dataclasses.asdict(args)
    elif isinstance(args, Mapping):
        items = dict(args)
    else:
        items = dict(vars(args))
    out: dict[str, Any] = {}
    for key, value in items.items():
        value = os.fspath(value) if isinstance(value, os.PathLike) else value
        if key.startswith("_"):
            continue
        try:
            json.dumps(value)
        except (TypeError, ValueError):
            continue
        out[key] = value
    return out


#: ``os.write``, looked up here so a test can fill the disk at the OS boundary.
_os_write = os.write


class RecordingBus:
    """An :class:`~.bus.I2CBus` that writes every transaction of ``inner`` to a trace.

    Each line is written (one unbuffered ``write``) as the transaction ends,
    so a trace is complete up to a crash or Ctrl-C, and :meth:`close` ends
    the session with its closing line. A line the disk takes
    only in part is cut off again, and from then on nothing more is
    recorded: the trace stays a whole prefix of the session, :attr:`error`
    says why and :attr:`unrecorded_from` from which transaction. A trace that
    cannot be written never fails a transaction: the bus carried it. Attributes
    it does not have are the inner bus's (``bus.faults`` of an emulated bus
    still works).

    Args:
        inner: The bus that carries the transactions.
        recording: Where to write, and the header's command and arguments.
        clock: The backend's clock (the ``t`` of every line).
        backend: The backend's name, for the header.
        config: The arm configuration, for the header.
    """

    def __init__(
        self, inner: I2CBus, recording: Recording, clock: Clock, backend: str, config: ArmConfig
    ) -> None:
        """Open (append to) the trace file and write the session's header."""
        self.inner = inner
        self.clock = clock
        self.path = Path(recording.path)
        self.transactions = 0
        self._previous = ""  # the last line's digest in this session
        #: The write that failed, if one did; nothing is recorded after it.
        self.error: OSError | None = None
        #: The first transaction not recorded (``None``: every one was).
        self.unrecorded_from: int | None = None
        self._cut_by_signal = False  # the last transaction was cut short by a signal
        self._signal_noted = False  # a signal line was written
        self._exchanging = False  # in the exchange: a signal landing now cuts the transaction short
        #: A stop signal's handler call waiting for the next transaction (:func:`signals_noted`).
        self._pending: Callable[[], object] | None = None
        self._fd: int | None = None
        self._size = 0  # bytes of whole lines in the file
        try:
            with _HeldSignals() as held:
                held.hold()
                self._start(recording, backend, config)
        except KeyboardInterrupt as e:  # stopped as the trace began: its replay stops before it starts
            self.record_signal(e)
            self._end_session()
            raise

    def _start(self, recording: Recording, backend: str, config: ArmConfig) -> None:
        """Open the trace file and write the header; remove a file this made if the header is refused."""
        import bioscara_gym

        created = not self.path.exists()
        try:
            self._fd = os.open(self.path, os.O_WRONLY | os.O_CREAT | os.O_APPEND, 0o644)
            self._size = os.fstat(self._fd).st_size
        except OSError as e:
            raise OSError(e.errno, f"cannot write the bus trace {self.path} (--record): {e.strerror}") from e
        self._write(
            {
                "type": "header",
                "format": TRACE_FORMAT,
                "version": TRACE_VERSION,
                "bioscara_gym": bioscara_gym.__version__,
                "backend": backend,
                "config": config_to_dict(config),
                "command": recording.command,
                "args": jsonable_args(recording.args),
                "context": dict(recording.context),
                "t0": self.clock.now(),
                "started": time.strftime("%Y-%m-%dT%H:%M:%S%z"),
            }
        )
        if self.error is not None:  # not even the header: refused before any transaction
            os.close(self._fd)
            self._fd = None
            if created:  # no empty trace left behind
                with contextlib.suppress(OSError):
                    self.path.unlink()
            reason = os.strerror(self.error.errno) if self.error.errno is not None else self.error.strerror
            raise OSError(self.error.errno, f"cannot write the bus trace {self.path} (--record): {reason}")

    def _write(self, record: Mapping[str, Any]) -> None:
        if self._fd is None:
            raise OSError(f"trace {self.path} is closed")
        if self.error is not None:
            return
        digest = line_digest(record, self._previous)
        data = (json.dumps({**record, "digest": digest}) + "\n").encode()
        try:
            view = memoryview(data)
            while view:
                view = view[_os_write(self._fd, view) :]
        except OSError as e:
            self.error = OSError(e.errno, f"cannot write the bus trace {self.path}: {e.strerror or e}")
            self.unrecorded_from = int(record.get("i", 0)) if record.get("type") == "tx" else 0
            with contextlib.suppress(OSError):
                os.ftruncate(self._fd, self._size)  # the line in part: cut off again
            return
        self._size += len(data)
        self._previous = digest

    def transfer(self, address: int, data: bytes, read_len: int) -> bytes:
        """One transaction of the inner bus, recorded with its reply or its error.

        The stop signals are held back (:class:`_HeldSignals`) while the
        transaction's line is made, counted and written, and let through only
        during the exchange itself: a Ctrl-C that landed in the bookkeeping
        left a transaction counted and never written, or written and left out
        of the digest chain, and the trace no longer replayed. One that lands
        in the exchange, or as it ends, cuts it (``interrupted``); one held
        back is raised once its line is written, between two transactions.
        """
        if self._pending is not None:  # landed since the last transaction: raised before this one
            self._raise_pending()
        data = bytes(data)
        t = self.clock.now()
        record: dict[str, Any] = {
            "type": "tx",
            "i": self.transactions,
            "t": t,
            "dur": 0.0,
            "addr": f"{address:#04x}",
            "write": data.hex(),
            "read_len": read_len,
        }
        with _HeldSignals() as held:
            try:
                # First inside the ``try``: from here a signal is this transaction's (``interrupted``),
                # not one :meth:`record_signal` notes before it. No handler runs between the two.
                self._exchanging = True
                try:
                    reply = bytes(self.inner.transfer(address, data, read_len))
                finally:
                    held.hold()
                    self._exchanging = False
            except OSError as e:
                record["error"] = {"errno": e.errno, "message": e.strerror or str(e)}
                self._close_line(record, t)
                raise
            except KeyboardInterrupt as e:  # Ctrl-C (or a deploy's SIGTERM, SIGHUP) cut it short: no reply
                held.hold()  # (again: it may have landed as the hold began)
                self._exchanging = False
                record["interrupted"] = signal_name(e)
                self._close_line(record, t)
                self._cut_by_signal = True
                raise
            record["read"] = reply.hex()
            self._close_line(record, t)
        return reply

    def _raise_pending(self) -> None:
        """Call the handler of the signal that waited for this transaction, noting what it raises."""
        handle, self._pending = self._pending, None
        try:
            if handle is not None:
                handle()
        except KeyboardInterrupt as e:
            self.record_signal(e)
            raise

    def _close_line(self, record: dict[str, Any], t: float) -> None:
        """Count a transaction and write its line, its duration measured to now."""
        record["dur"] = self.clock.now() - t
        self.transactions += 1
        self._write(record)

    def record_signal(self, interrupted: KeyboardInterrupt) -> None:
        """Write where a signal stopped the command (a ``signal`` line), for its replay.

        Nothing when the signal cut a transaction short, or lands in one
        that it will cut short (that line says it: a handler wrapped by
        :func:`signals_noted` calls this from inside the exchange), or when
        a signal line was written already: the first interruption
        ends a session (a deploy shields its safe stop from a second one), and
        the same one may be noted again on its way out of the command.
        A signal the command raised at a cycle boundary (``deferred``, see
        :class:`~bioscara_gym.training.signals.Interrupted`) is ``at`` that
        ``"cycle"``; any other was raised where it landed (``"once"``).
        """
        if self._cut_by_signal or self._exchanging or self._signal_noted or self._fd is None:
            return  # (a closed trace: the session is over)
        self._signal_noted = True
        at = "cycle" if getattr(interrupted, "deferred", False) else "once"
        with _HeldSignals() as held:  # a second signal waits until the line is whole
            held.hold()
            self._write(
                {
                    "type": "signal",
                    "i": self.transactions,
                    "t": self.clock.now(),
                    "signal": signal_name(interrupted),
                    "at": at,
                }
            )

    def close(self) -> None:
        """Close the inner bus, then end the session with its closing line and close the trace file."""
        try:
            self.inner.close()
        finally:
            self._end_session()

    def _end_session(self) -> None:
        """Write the closing line (``end``: the session's transaction count) and close the file; once.

        It tells a session that ended from one cut short: a trace without it
        ends where the recorder was killed, the disk filled (nothing is
        written after a failed line) or the file was truncated, so a replay
        that runs past its last line blames the trace, not the driver.
        """
        if self._fd is None:
            return
        with _HeldSignals() as held:  # a signal waits until the line is whole
            held.hold()
            try:
                self._write({"type": "end", "transactions": self.transactions, "t": self.clock.now()})
            finally:
                os.close(self._fd)
                self._fd = None

    def __getattr__(self, name: str) -> Any:
        """The inner bus's attribute (``faults``, ``update()`` of an emulated bus)."""
        if name == "inner":
            raise AttributeError(name)
        return getattr(self.inner, name)




class _HeldSignals:
    """The stop signals' Python handlers held back from :meth:`hold` to the end of the ``with`` block.

    Python runs a signal's handler in the main thread, between two bytecodes,
    whichever thread of the process the kernel gave the signal to. Blocking
    the signals in the main thread (``pthread_sigmask``) therefore held back
    nothing once the process had a second thread (seen: 4 of 8 evals Ctrl-C'd
    under ``--record`` left a trace ``replay`` refused; the eval's second
    thread took the signal). So the handlers themselves are held: each
    Python-level handler is replaced by one that only notes the signal, and
    when the block ends the handlers are put back and called for the signals
    noted, in order (a Ctrl-C raises there). A handler that is no Python
    function (``SIG_DFL``, ``SIG_IGN``) is left alone, and outside the main
    thread, where no handler runs, nothing is held.
    """

    def __init__(self) -> None:
        """Hold nothing yet."""
        self._handlers: dict[int, SignalHandler] = {}  # the handlers replaced, to put back
        self._arrived: list[int] = []

    def _note(self, signum: int, frame: FrameType | None) -> None:
        self._arrived.append(signum)

    def hold(self) -> None:
        """From now on note the signals instead of handling them (again: completes a hold cut short)."""
        if threading.current_thread() is not threading.main_thread():
            return
        for signum in STOP_SIGNALS:
            handler = signal.getsignal(signum)
            if callable(handler) and handler != self._note:
                self._handlers[signum] = handler  # kept first: a signal landing here finds it put back
                signal.signal(signum, self._note)

    def __enter__(self) -> _HeldSignals:
        """Start holding nothing: :meth:`hold` says where the signals start to wait."""
        return self

    def __exit__(self, *exc: object) -> None:
        """Put the handlers back, then hand them the signals noted meanwhile."""
        handlers, self._handlers = self._handlers, {}
        put_back(list(handlers.items()))
        arrived, self._arrived = self._arrived, []
        for signum in arrived:
            handlers[signum](signum, None)


def signal_name(interrupted: KeyboardInterrupt) -> str:
    """The name of the signal behind a ``KeyboardInterrupt`` (``SIGINT`` for a plain Ctrl-C)."""
    signum = getattr(interrupted, "signum", signal.SIGINT)
    return signal.Signals(signum).name


def recording_bus(backend: object) -> RecordingBus | None:
    """The backend's bus if it is being recorded (``--record``), else ``None``."""
    bus = getattr(backend, "bus", None)
    return bus if isinstance(bus, RecordingBus) else None


def note_signal(backend: object, stopped_by: BaseException | None) -> None:
    """If a signal stopped the command, note where in the backend's bus trace (``--record``).

    Called where the command catches it, before it makes the arm safe, so
    the replay raises it before the same transactions (:meth:`RecordingBus.record_signal`).
    """
    bus = recording_bus(backend)
    if bus is not None and isinstance(stopped_by, KeyboardInterrupt):
        bus.record_signal(stopped_by)


@contextlib.contextmanager
def signals_noted(backend: object) -> Iterator[None]:
    """In the block, a stop signal stops the command where its bus trace says (``--record``).

    :func:`note_signal` where a command catches the interrupt is too late
    when something sends bytes on its way there. Seen: ``eval --record``
    stopped by Ctrl-C in its start-up (configure, activate) left the signal
    line after the transactions of the arm's failed transition (which
    disables the joints before it re-raises), and its replay failed. Noted
    where it lands, it still did not replay: between two transactions it
    can cut the driver's bookkeeping anywhere (a joint pinged but not yet
    counted as connected was not disabled), and a replay can only raise it
    before the next transaction. So the handler of each stop signal is
    wrapped: a signal landing between two transactions waits, and is
    raised (and noted, ``"once"``) just before the next one, exactly where
    its replay raises it; one landing in an exchange cuts it short
    (``interrupted``), as ever. One still waiting as the block ends is
    raised then; a second signal is raised at once, where it lands. A
    handler put in the wrapper's place meanwhile (the CLI's, which ignores
    a second signal during the clean-up) is left there at the end. Nothing
    is wrapped without a trace, for a signal without a Python handler, or
    outside the main thread (where no handler runs).
    """
    bus = recording_bus(backend)
    if bus is None or threading.current_thread() is not threading.main_thread():
        yield
        return
    installed: list[tuple[int, SignalHandler, SignalHandler]] = []
    try:
        for signum in STOP_SIGNALS:
            handler = signal.getsignal(signum)
            if callable(handler):
                waiting = _waiting(handler, bus)
                installed.append((signum, handler, waiting))
                signal.signal(signum, waiting)
        yield
    finally:
        put_back(
            [
                (signum, handler)
                for signum, handler, waiting in installed
                if signal.getsignal(signum) is waiting
            ]
        )
        bus._raise_pending()  # it landed after the last transaction (the trace is closed by now)


def _waiting(handler: SignalHandler, bus: RecordingBus) -> SignalHandler:
    """``handler``, called before ``bus``'s next transaction when its signal lands between two."""

    def waiting(signum: int, frame: FrameType | None) -> Any:
        if not (bus._exchanging or bus._fd is None or bus._pending is not None):
            bus._pending = functools.partial(handler, signum, None)
            return None
        bus._pending = None  # in an exchange, after the trace's end, or a second signal: at once
        try:
            return handler(signum, frame)
        except KeyboardInterrupt as e:
            bus.record_signal(e)  # (nothing in an exchange: the transaction's line says it)
            raise

    return waiting


def recorder(recording: Recording, backend: str, config: ArmConfig) -> BusWrapper:
    """A :data:`BusWrapper` that records the backend's bus into ``recording``."""

    def wrap(bus: I2CBus, clock: Clock) -> I2CBus:
        return RecordingBus(bus, recording, clock, backend, config)

    return wrap


# -------------------------------------------------------------------- reading
@dataclass(frozen=True)
class Transaction:
    """One recorded transaction.

    Attributes:
        line: Its line in the trace file, from 1.
        t: Time on the backend's clock when it started, s.
        dur: Time it took on that clock, s.
        address: 7-bit address.
        write: Bytes written.
        read_len: Bytes asked for.
        read: Bytes read, ``None`` when the transfer raised.
        errno: The ``OSError``'s errno when the transfer raised.
        message: The ``OSError``'s message when the transfer raised.
        interrupted: The signal that cut the transfer short (``SIGINT``), if one did.
    """

    line: int
    t: float
    dur: float
    address: int
    write: bytes
    read_len: int
    read: bytes | None
    errno: int | None = None
    message: str = ""
    interrupted: str | None = None

    @property
    def request(self) -> tuple[int, bytes, int]:
        """``(address, bytes written, read length)``."""
        return (self.address, self.write, self.read_len)


@dataclass(frozen=True)
class SignalNote:
    """Where a signal stopped the recorded command (a ``signal`` line).

    Attributes:
        line: Its line in the trace file, from 1.
        before: The transaction it came before (its index in the session).
        signal: ``SIGINT``, ``SIGTERM`` or ``SIGHUP``.
        at: ``"cycle"``: it arrived during the transactions before
            ``before`` and was raised at the next cycle boundary; ``"once"``:
            raised where it landed, before transaction ``before``.
    """

    line: int
    before: int
    signal: str
    at: str


@dataclass(frozen=True)
class TraceSession:
    """One session of a trace: its header, its transactions, the signals that stopped it, its end.

    Attributes:
        header: The header line as read.
        transactions: The transactions, in order.
        signals: Where signals stopped the command.
        end_line: The trace line of its closing line (``None``: it has none).
    """

    header: Mapping[str, Any]
    transactions: Sequence[Transaction]
    signals: Sequence[SignalNote] = ()
    end_line: int | None = None

    @property
    def cut(self) -> bool:
        """Whether it lacks the closing line its format version writes: its recording was cut short.

        Sessions of versions before :data:`CLOSING_LINE_VERSION` have none, and are never cut.
        """
        version = self.header.get("version")
        return (
            self.end_line is None
            and isinstance(version, int)
            and not isinstance(version, bool)
            and version >= CLOSING_LINE_VERSION
        )

    @property
    def command(self) -> str:
        """The recorded ``bioscara`` subcommand."""
        return str(self.header.get("command", ""))

    @property
    def backend(self) -> str:
        """The backend it was recorded on."""
        return str(self.header.get("backend", ""))


def _hex(value: object, where: str, key: str) -> bytes:
    if not isinstance(value, str):
        raise TraceError(f"{where}: '{key}' must be a hex string")
    try:
        return bytes.fromhex(value)
    except ValueError as e:
        raise TraceError(f"{where}: '{key}' {value!r} is not hex") from e


def _number(value: object, where: str, key: str) -> float:
    if isinstance(value, bool) or not isinstance(value, (int, float)):
        raise TraceError(f"{where}: '{key}' must be a number")
    try:
        number = float(value)
    except OverflowError:  # an integer beyond float's range
        number = math.inf
    if not math.isfinite(number):  # a replay would wait for ever on it
        raise TraceError(f"{where}: '{key}' must be a finite number, got {value!r}")
    return number


#: Longest a recorded transaction may have taken, s: the driver's timeouts are milliseconds.
MAX_TRANSACTION_S = 60.0


def _duration(value: object, where: str) -> float:
    dur = _number(value, where, "dur")
    if not 0.0 <= dur <= MAX_TRANSACTION_S:  # 1e300 made a replay wait for ever
        raise TraceError(f"{where}: 'dur' {value!r} must be 0-{MAX_TRANSACTION_S:g} s")
    return dur


def _transaction(doc: Mapping[str, Any], line: int, where: str) -> Transaction:
    address = doc.get("addr")
    try:
        addr = int(address, 16) if isinstance(address, str) else -1
    except ValueError:
        addr = -1
    if not 0 <= addr <= 0x7F:
        raise TraceError(f"{where}: 'addr' must be a 7-bit address such as \"0x11\", got {address!r}")
    read_len = doc.get("read_len")
    if isinstance(read_len, bool) or not isinstance(read_len, int) or read_len < 0:
        raise TraceError(f"{where}: 'read_len' must be a whole number >= 0")
    common = {
        "line": line,
        "t": _number(doc.get("t"), where, "t"),
        "dur": _duration(doc.get("dur", 0.0), where),
        "address": addr,
        "write": _hex(doc.get("write"), where, "write"),
        "read_len": read_len,
    }
    error = doc.get("error")
    interrupted = doc.get("interrupted")
    if ("read" in doc) + (error is not None) + (interrupted is not None) != 1:
        raise TraceError(f"{where}: a transaction has one of 'read', 'error' or 'interrupted'")
    if interrupted is not None:
        return Transaction(**common, read=None, interrupted=_signal(interrupted, where, "interrupted"))
    if error is None:
        return Transaction(**common, read=_hex(doc["read"], where, "read"))
    if not isinstance(error, Mapping) or isinstance(error.get("errno"), bool):
        raise TraceError(f"{where}: 'error' must be {{'errno': int, 'message': str}}")
    errno_value = error.get("errno")
    if errno_value is not None and not isinstance(errno_value, int):
        raise TraceError(f"{where}: 'error' must be {{'errno': int, 'message': str}}")
    return Transaction(**common, read=None, errno=errno_value, message=str(error.get("message", "")))


#: The signals a trace may name.
SIGNAL_NAMES = tuple(s.name for s in STOP_SIGNALS)


def _signal(value: object, where: str, key: str) -> str:
    if value not in SIGNAL_NAMES:
        raise TraceError(f'{where}: \'{key}\' must be "SIGINT", "SIGTERM" or "SIGHUP", got {value!r}')
    return str(value)


def _signal_note(doc: Mapping[str, Any], line: int, where: str, transactions: int) -> SignalNote:
    before = doc.get("i")
    if isinstance(before, bool) or not isinstance(before, int) or before != transactions:
        raise TraceError(
            f"{where}: a signal line's 'i' must be the index of the transaction after it ({transactions}), "
            f"got {before!r}"
        )
    at = doc.get("at")
    if at not in SIGNAL_AT:
        raise TraceError(f"{where}: 'at' must be one of {', '.join(SIGNAL_AT)}, got {at!r}")
    return SignalNote(line, before, _signal(doc.get("signal"), where, "signal"), str(at))


def _check_header(doc: Mapping[str, Any], where: str) -> None:
    if doc.get("format") != TRACE_FORMAT:
        raise TraceError(
            f"{where}: not a bioscara bus trace (format {doc.get('format')!r}, expected {TRACE_FORMAT!r})"
        )
    version = doc.get("version")
    if isinstance(version, bool) or not isinstance(version, int) or version < 1:
        raise TraceError(f"{where}: 'version' must be a whole number >= 1")
    if version > TRACE_VERSION:
        raise TraceError(
            f"{where}: trace format version {version} is newer than this bioscara_gym reads "
            f"({TRACE_VERSION}); upgrade bioscara_gym"
        )
    for key in ("backend", "command"):
        if not isinstance(doc.get(key), str):
            raise TraceError(f"{where}: the header has no '{key}'")
    for key in ("config", "args"):
        if not isinstance(doc.get(key), Mapping):
            raise TraceError(f"{where}: the header's '{key}' must be an object")
    if "context" in doc and not isinstance(doc["context"], Mapping):
        raise TraceError(f"{where}: the header's 'context' must be an object")
    t0 = doc.get("t0", 0.0)
    if isinstance(t0, bool) or not isinstance(t0, (int, float)) or not math.isfinite(t0):
        raise TraceError(f"{where}: the header's 't0' must be a finite number of seconds, got {t0!r}")


def _check_digest(doc: Mapping[str, Any], previous: str, where: str) -> str:
    """The line's recorded digest, if it matches its contents; else :class:`TraceError`."""
    digest = doc.get("digest")
    if not isinstance(digest, str):
        raise TraceError(
            f"{where}: no digest (a trace of format version 1, or made by hand); "
            "replay it with --unchecked if you trust it"
        )
    if digest != line_digest(doc, previous):
        raise TraceError(
            f"{where}: its digest does not match its contents: the line was changed after it was "
            "recorded (or a line was removed just before it); replay it with --unchecked to use it anyway"
        )
    return digest


def read_trace(path: str | os.PathLike[str], check_digests: bool = True) -> list[TraceSession]:
    """Read and check a trace file: its sessions, in order.

    Args:
        path: The trace.
        check_digests: Refuse a line whose digest is missing or does not
            match (``False``: a hand-made or hand-edited trace, ``--unchecked``).

    Raises:
        TraceError: Missing or unreadable, a line that is not JSON or not a
            header or transaction, a header of another format or of a newer
            version, a line changed after recording; the message names the
            file and line.
    """
    path = Path(path)
    name = path.name
    try:
        text = read_bytes(path, MAX_TRACE_BYTES).decode("utf-8")
    except FileNotFoundError as e:
        raise TraceError(f"{path}: no such trace file") from e
    except OSError as e:
        raise TraceError(f"{path}: cannot be read ({e.strerror or e})") from e
    except UnicodeDecodeError as e:
        raise TraceError(f"{path}: cannot be read (not UTF-8 text: {e})") from e
    sessions: list[_SessionLines] = []
    previous = ""
    lines = text.splitlines()
    for number, raw in enumerate(lines, start=1):
        if not raw.strip():
            continue
        where = f"{name} line {number}"
        try:
            doc = json.loads(raw)
        except json.JSONDecodeError:
            if number == len(lines) and not text.endswith("\n"):  # a write cut short, or `head -c`
                raise TraceError(f"{where}: a last line cut off mid-line (not JSON): {CUT_REASON}") from None
            raise TraceError(f"{where}: not JSON") from None
        except ValueError:  # Python's limit on the digits of an int (4300)
            raise TraceError(f"{where}: holds a number too long to be a trace's") from None
        except RecursionError:
            raise TraceError(f"{where}: nested too deeply to be a trace line") from None
        if not isinstance(doc, Mapping):
            raise TraceError(f"{where}: not a JSON object")
        kind = doc.get("type")
        if kind == "header":
            _check_header(doc, where)
            sessions.append(_SessionLines(doc))
            previous = ""
        elif kind in _SESSION_LINES:
            if not sessions:
                raise TraceError(f"{where}: a {_SESSION_LINES[kind]} before the first header")
            sessions[-1].add(kind, doc, number, where)
        else:
            types = ", ".join(f"'{t}'" for t in LINE_TYPES[:-1])
            raise TraceError(f"{where}: 'type' must be {types} or '{LINE_TYPES[-1]}', got {kind!r}")
        if check_digests:
            previous = _check_digest(doc, previous, where)
    if not sessions:
        raise TraceError(f"{name}: empty; a trace starts with a header line")
    return [s.session() for s in sessions]


#: The lines of a session after its header, by ``type``, as a message names them.
_SESSION_LINES = {"tx": "transaction", "signal": "signal", "end": "closing line"}


@dataclass
class _SessionLines:
    """A session as :func:`read_trace` reads it, line by line."""

    header: Mapping[str, Any]
    transactions: list[Transaction] = field(default_factory=list)
    signals: list[SignalNote] = field(default_factory=list)
    end_line: int | None = None

    def add(self, kind: str, doc: Mapping[str, Any], line: int, where: str) -> None:
        """Add a ``tx``, ``signal`` or ``end`` line; none after the closing line."""
        if self.end_line is not None:
            raise TraceError(f"{where}: a {_SESSION_LINES[kind]} after its session's closing line")
        if kind == "tx":
            self.transactions.append(_transaction(doc, line, where))
        elif kind == "signal":
            self.signals.append(_signal_note(doc, line, where, len(self.transactions)))
        else:
            count = doc.get("transactions")
            if isinstance(count, bool) or count != len(self.transactions):
                raise TraceError(
                    f"{where}: the closing line counts {count!r} transactions; "
                    f"its session has {len(self.transactions)}"
                )
            self.end_line = line

    def session(self) -> TraceSession:
        """The session read."""
        return TraceSession(self.header, tuple(self.transactions), tuple(self.signals), self.end_line)


# -------------------------------------------------------------------- replay
class ReplayClock(ManualClock):
    """Time during a replay: ``sleep`` advances at once; a replayed transaction sets it forward.

    The :class:`ReplayBus` moves it to each transaction's recorded time, so the
    driver's waits and timeouts see the times the recording saw.

    Args:
        start: The session's start time (the header's ``t0``), s.
    """


class ReplayBus:
    """An :class:`~.bus.I2CBus` that serves a recorded session's replies, in order.

    Each transfer must ask for exactly the recorded address, bytes and read
    length; the recorded reply is returned, or the recorded error raised as
    the same ``OSError``. Before each transaction the clock is moved to its
    recorded time (if behind), after it by its recorded duration. A recorded
    signal is delivered to the signal's handler where it was recorded
    (:class:`SignalNote`; a transaction it cut short raises it after its
    bytes are checked), so an interrupted command stops as it did. The first
    difference raises :class:`TraceMismatch` (kept in :attr:`mismatch`, and
    raised again by every later transfer, so a driver that catches it cannot
    go on as if nothing happened). A transfer past the last line of a
    session that was cut (:attr:`TraceSession.cut`) raises :class:`TraceCut`
    instead (kept in :attr:`cut_off`, and raised again the same way).

    Args:
        session: The recorded session.
        clock: The clock to keep on the recorded times (set later with :meth:`bind`).
    """

    def __init__(self, session: TraceSession, clock: Clock | None = None) -> None:
        """Start before the session's first transaction."""
        self.session = session
        self.clock = clock
        self.served = 0
        self.errors_served = 0
        self.mismatch: TraceMismatch | None = None
        self.cut_off: TraceCut | None = None
        self.closed = False
        self._signals = {note.before: note for note in session.signals}
        #: Recorded signals handed to their handlers so far.
        self.signals_delivered = 0

    def bind(self, bus: I2CBus, clock: Clock) -> ReplayBus:
        """Take the backend's clock in place of its bus (a :data:`BusWrapper`)."""
        self.clock = clock
        return self

    @property
    def remaining(self) -> int:
        """Recorded transactions not served yet."""
        return len(self.session.transactions) - self.served

    def transfer(self, address: int, data: bytes, read_len: int) -> bytes:
        """Serve the next recorded transaction if the driver asks for exactly it."""
        if self.mismatch is not None:
            raise self.mismatch
        if self.cut_off is not None:
            raise self.cut_off
        sent = (address, bytes(data), read_len)
        self._deliver("once")  # raised where it landed, before this transaction
        txs = self.session.transactions
        if self.served >= len(txs) and self.session.cut:  # what came next was never written down
            self.cut_off = TraceCut(self.served, txs[-1].line if txs else None)
            raise self.cut_off
        if self.served >= len(txs):
            self.mismatch = TraceMismatch(self.served, None, None, sent)
            raise self.mismatch
        tx = txs[self.served]
        if tx.request != sent:
            self.mismatch = TraceMismatch(self.served, tx.line, tx, sent)
            raise self.mismatch
        self.served += 1
        if self.clock is not None:
            self.clock.sleep(tx.t - self.clock.now())
            self.clock.sleep(tx.dur)
        if tx.interrupted is not None:
            self.signals_delivered += 1
            _raise_signal(tx.interrupted, at_once=True)
        self._deliver("cycle")  # arrived during this transaction: pending until the next cycle
        if tx.read is None:
            self.errors_served += 1
            raise OSError(tx.errno, tx.message)
        return tx.read

    def start(self) -> None:
        """Before the command runs: a signal that stopped it before it sent anything is raised now.

        A session with no transaction and a signal before the first was
        interrupted before the bus was used (a deploy's checks): the replay
        stops it before it starts, which sends the same nothing.
        """
        if not self.session.transactions:
            self._deliver("once")

    def _deliver(self, at: str) -> None:
        """Hand the signal recorded before the next transaction to its handler, if it is ``at`` here."""
        note = self._signals.get(self.served)
        if note is None or note.at != at:
            return
        del self._signals[self.served]
        self.signals_delivered += 1
        _raise_signal(note.signal, at_once=at == "once")

    def close(self) -> None:
        """Mark the bus closed (the trace stays readable)."""
        self.closed = True


def _raise_signal(name: str, at_once: bool) -> None:
    """Call the handler of signal ``name`` as the signal would, in this thread.

    The command's own handler (a deploy's :class:`~bioscara_gym.training.signals.SignalGuard`)
    raises or records it; with none installed, as Python does by default: ``KeyboardInterrupt``.
    A signal recorded as raised where it landed (``at_once``) must raise: a handler
    that held it back (a deploy's cycle defers the first) is called once more, as
    the second Ctrl-C that raised it then was, and ``KeyboardInterrupt`` is raised
    if it still lets it pass.
    """
    signum = signal.Signals[name]
    handler = signal.getsignal(signum)
    if callable(handler):
        handler(signum, None)
        if at_once:
            handler(signum, None)
    elif handler != signal.SIG_IGN:
        raise KeyboardInterrupt(name)
    if at_once:
        raise KeyboardInterrupt(name)
