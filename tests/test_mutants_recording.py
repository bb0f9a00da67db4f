"""Tests that kill mutants mutmut found surviving in ``hardware/recording.py`` (docs/mutation.md).

Byte level: a :class:`RecordingBus` around a fake bus on a manual clock,
:func:`read_trace` on lines written here, a :class:`ReplayBus` on a session
built here. Expected values are literals from docs/traces.md (the format,
the replay rules) and the module's documented contract (its messages name
the file, the line and the key).
"""

from __future__ import annotations

import contextlib
import dataclasses
import errno
import json
import re
import signal
from collections.abc import Iterator
from pathlib import Path
from typing import Any

import pytest
from rigs import TRACE_HEADER, TRACE_TX

from bioscara_gym.hardware import recording
from bioscara_gym.hardware.clock import ManualClock
from bioscara_gym.hardware.config import load_config
from bioscara_gym.hardware.recording import (
    TRACE_FORMAT,
    Recording,
    RecordingBus,
    ReplayBus,
    SignalNote,
    TraceError,
    TraceMismatch,
    TraceSession,
    Transaction,
    describe,
    jsonable_args,
    read_trace,
)

HEADER = TRACE_HEADER
TX = TRACE_TX


class SlowBus:
    """A bus whose every transfer takes 0.25 s of the clock and answers PING's 'O' with no flag."""

    def __init__(self, clock: ManualClock) -> None:
        self.clock = clock
        self.faults = "the inner bus's faults"
        self.closed = False

    def transfer(self, address: int, data: bytes, read_len: int) -> bytes:
        self.clock.sleep(0.25)
        return b"\x4f\x00"[:read_len]

    def close(self) -> None:
        self.closed = True


class PlainErrorBus(SlowBus):
    """A bus whose transfer raises an ``OSError`` that has a message but no errno or strerror."""

    def transfer(self, address: int, data: bytes, read_len: int) -> bytes:
        self.clock.sleep(0.25)
        raise OSError("the adapter went away")


def record(tmp_path: Path, bus_class: type[SlowBus] = SlowBus, **recording: Any) -> tuple[RecordingBus, Path]:
    clock = ManualClock(1.0)
    path = tmp_path / "t.jsonl"
    bus = RecordingBus(
        bus_class(clock), Recording(path, "ping", **recording), clock, "emulated", load_config()
    )
    return bus, path


def raw_lines(path: Path) -> list[dict[str, Any]]:
    return [json.loads(line) for line in path.read_text(encoding="utf-8").splitlines()]


def trace_of(tmp_path: Path, *docs: dict[str, Any], text: str | None = None) -> Path:
    path = tmp_path / "hand.jsonl"
    path.write_text(
        text if text is not None else "".join(json.dumps(d) + "\n" for d in docs), encoding="utf-8"
    )
    return path


def refusal(tmp_path: Path, *docs: dict[str, Any]) -> str:
    with pytest.raises(TraceError) as caught:
        read_trace(trace_of(tmp_path, *docs), check_digests=False)
    return str(caught.value)


# ---------------------------------------------------------------- recording
def test_each_line_has_its_index_start_and_duration_on_the_backends_clock(tmp_path: Path) -> None:
    bus, path = record(tmp_path)
    assert bus.transfer(0x11, b"\x0f", 2) == b"\x4f\x00"
    assert bus.transfer(0x12, b"\x0f", 2) == b"\x4f\x00"
    bus.close()
    header, first, second, end = raw_lines(path)
    assert header["t0"] == 1.0
    assert (end["type"], end["transactions"], end["t"]) == ("end", 2, 1.5)
    del first["digest"]
    assert first == {
        "type": "tx",
        "i": 0, "t": 1.0, "dur": 0.25, "addr": "0x11", "write": "0f", "read_len": 2, "read": "4f00",
    }  # fmt: skip
    assert (second["i"], second["t"], second["dur"]) == (1, 1.25, 0.25)
    assert bus.transactions == 2


def test_a_failed_transfer_keeps_its_duration_and_a_message_without_strerror(tmp_path: Path) -> None:
    bus, path = record(tmp_path, PlainErrorBus)
    with pytest.raises(OSError, match="the adapter went away"):
        bus.transfer(0x13, b"\x0f", 2)
    bus.close()
    tx = raw_lines(path)[1]
    assert (tx["i"], tx["t"], tx["dur"]) == (0, 1.0, 0.25)
    assert tx["error"] == {"errno": None, "message": "the adapter went away"}
    assert "read" not in tx


def test_the_header_has_its_context_and_an_iso_8601_start(tmp_path: Path) -> None:
    bus, path = record(tmp_path, context={"state": {"j1": "homed"}})
    bus.close()
    header = raw_lines(path)[0]
    assert header["context"] == {"state": {"j1": "homed"}}
    assert re.fullmatch(r"\d{4}-\d{2}-\d{2}T\d{2}:\d{2}:\d{2}[+-]\d{4}", header["started"]), header["started"]


def test_a_trace_that_cannot_be_opened_keeps_the_errno_and_names_the_file(tmp_path: Path) -> None:
    path = tmp_path / "missing" / "t.jsonl"
    clock = ManualClock()
    with pytest.raises(OSError) as caught:
        RecordingBus(SlowBus(clock), Recording(path, "ping"), clock, "emulated", load_config())
    assert caught.value.errno == errno.ENOENT
    assert caught.value.strerror == f"cannot write the bus trace {path} (--record): No such file or directory"


@pytest.mark.parametrize("existing", [False, True])
def test_a_trace_whose_header_cannot_be_written_is_refused_before_any_transaction(
    tmp_path: Path, monkeypatch: pytest.MonkeyPatch, existing: bool
) -> None:
    # Seen: `--record /proc/version` opened, lost every line, and ping said nothing of it.
    path = tmp_path / "t.jsonl"
    earlier = json.dumps({"type": "header", "format": TRACE_FORMAT}) + "\n"  # an earlier session's
    if existing:
        path.write_text(earlier, encoding="utf-8")

    def refuse(fd: int, data: bytes) -> int:
        raise OSError(errno.EINVAL, "Invalid argument")

    monkeypatch.setattr("bioscara_gym.hardware.recording._os_write", refuse)
    clock = ManualClock()
    inner = SlowBus(clock)
    with pytest.raises(OSError) as caught:
        RecordingBus(inner, Recording(path, "ping"), clock, "emulated", load_config())
    assert caught.value.errno == errno.EINVAL
    assert caught.value.strerror == f"cannot write the bus trace {path} (--record): Invalid argument"
    assert clock.now() == 0.0  # nothing sent
    if existing:
        assert path.read_text(encoding="utf-8") == earlier
    else:
        assert not path.exists()


def test_a_ctrl_c_while_a_line_is_written_waits_until_the_line_is_whole(
    tmp_path: Path, monkeypatch: pytest.MonkeyPatch
) -> None:
    # Seen: 2 of 8 deploys stopped in bring-up left a transaction counted and
    # never written, and the signal line named one the trace did not have.
    # Python's own SIGINT handler, whatever an earlier test in this worker left.
    previous = signal.signal(signal.SIGINT, signal.default_int_handler)
    try:
        _ctrl_c_while_a_line_is_written(tmp_path, monkeypatch)
    finally:
        signal.signal(signal.SIGINT, previous)


def _ctrl_c_while_a_line_is_written(tmp_path: Path, monkeypatch: pytest.MonkeyPatch) -> None:
    bus, path = record(tmp_path)
    digest = recording.line_digest
    landed: list[str] = []

    def lands_here(doc: dict[str, Any], previous: str) -> str:
        if doc.get("type") == "tx" and not landed:
            landed.append(doc["write"])
            signal.raise_signal(signal.SIGINT)  # Python's own handler: KeyboardInterrupt
        return digest(doc, previous)

    monkeypatch.setattr(recording, "line_digest", lands_here)
    with pytest.raises(KeyboardInterrupt):
        bus.transfer(0x11, b"\x0f", 2)
    monkeypatch.undo()
    bus.close()
    (session,) = read_trace(path)  # digests checked: every line whole
    assert [tx.read for tx in session.transactions] == [b"\x4f\x00"] and landed == ["0f"]
    assert bus.transactions == 1


def test_a_closed_recording_refuses_to_write_and_closes_once(tmp_path: Path) -> None:
    bus, path = record(tmp_path)
    bus.close()
    assert bus.inner.closed  # type: ignore[attr-defined]
    with pytest.raises(OSError) as caught:
        bus.transfer(0x11, b"\x0f", 2)
    assert str(caught.value) == f"trace {path} is closed"
    bus.close()  # a second close does nothing
    assert [d["type"] for d in raw_lines(path)] == ["header", "end"]


def test_attributes_the_recording_bus_lacks_are_the_inner_buss(tmp_path: Path) -> None:
    bus, _ = record(tmp_path)
    assert bus.faults == "the inner bus's faults"  # type: ignore[attr-defined]
    with pytest.raises(AttributeError, match="nothing_here"):
        bus.nothing_here  # type: ignore[attr-defined]  # noqa: B018
    bus.close()
    empty = RecordingBus.__new__(RecordingBus)  # `inner` not set: no endless lookup through it
    with pytest.raises(AttributeError, match=r"^inner$"):
        empty.inner  # noqa: B018


@dataclasses.dataclass
class _Limits:
    rate: float


@dataclasses.dataclass
class _Args:
    env: str
    limits: _Limits


def test_jsonable_args_of_a_dataclass_nests_its_dataclasses() -> None:
    assert jsonable_args(_Args("Bioscara-Reach-v0", _Limits(20.0))) == {
        "env": "Bioscara-Reach-v0",
        "limits": {"rate": 20.0},
    }


def test_jsonable_args_turns_paths_into_strings_and_leaves_out_private_names() -> None:
    args = {"_bus": 1, "model": Path("run") / "model.zip", "episodes": 2, "callback": print}
    assert jsonable_args(args) == {"model": "run/model.zip", "episodes": 2}


# ------------------------------------------------------------------ reading
def test_a_transaction_is_read_with_its_line_duration_and_a_blank_line_skipped(tmp_path: Path) -> None:
    tx2 = {**TX, "i": 1, "t": 0.75}
    del tx2["dur"]  # hand-made: no duration means 0
    text = json.dumps(HEADER) + "\n" + json.dumps(TX) + "\n\n" + json.dumps(tx2) + "\n"
    (session,) = read_trace(trace_of(tmp_path, text=text), check_digests=False)
    first, second = session.transactions
    assert (first.line, first.t, first.dur, first.address, first.write, first.read_len, first.read) == (
        2, 0.5, 0.25, 0x11, b"\x0f", 2, b"\x4f\x0c",
    )  # fmt: skip
    assert (second.line, second.t, second.dur) == (4, 0.75, 0.0)


@pytest.mark.parametrize("address", ["0x00", "0x7f"])
def test_every_7_bit_address_is_read(tmp_path: Path, address: str) -> None:
    (session,) = read_trace(trace_of(tmp_path, HEADER, {**TX, "addr": address}), check_digests=False)
    assert session.transactions[0].address == int(address, 16)


def test_a_read_length_of_0_and_a_header_without_t0_of_version_1_are_read(tmp_path: Path) -> None:
    header = {**HEADER, "version": 1}
    (session,) = read_trace(
        trace_of(tmp_path, header, {**TX, "read_len": 0, "read": ""}), check_digests=False
    )
    assert session.transactions[0].read_len == 0


def test_a_recorded_error_without_errno_or_message_is_read(tmp_path: Path) -> None:
    tx = {k: v for k, v in TX.items() if k != "read"}
    (session,) = read_trace(trace_of(tmp_path, HEADER, {**tx, "error": {"errno": None}}), check_digests=False)
    (read,) = session.transactions
    assert (read.read, read.errno, read.message) == (None, None, "")


BAD_TX = [
    ("addr", 17, "'addr' must be a 7-bit address such as \"0x11\", got 17"),
    ("addr", "zz", "'addr' must be a 7-bit address such as \"0x11\", got 'zz'"),
    ("addr", "0x80", "'addr' must be a 7-bit address such as \"0x11\", got '0x80'"),
    ("read_len", -1, "'read_len' must be a whole number >= 0"),
    ("read_len", True, "'read_len' must be a whole number >= 0"),
    ("read_len", "2", "'read_len' must be a whole number >= 0"),
    ("t", "x", "'t' must be a number"),
    ("t", True, "'t' must be a number"),
    ("dur", "x", "'dur' must be a number"),
    ("write", 15, "'write' must be a hex string"),
    ("write", "zz", "'write' 'zz' is not hex"),
    ("read", "zz", "'read' 'zz' is not hex"),
    ("error", {"errno": 121, "message": "NACK"}, "a transaction has one of 'read', 'error' or 'interrupted'"),
    ("interrupted", "SIGINT", "a transaction has one of 'read', 'error' or 'interrupted'"),
]


@pytest.mark.parametrize(("key", "value", "message"), BAD_TX, ids=[f"{k}-{v!r}" for k, v, _ in BAD_TX])
def test_a_bad_transaction_line_is_named_with_file_line_and_key(
    tmp_path: Path, key: str, value: object, message: str
) -> None:
    assert refusal(tmp_path, HEADER, {**TX, key: value}) == f"hand.jsonl line 2: {message}"


@pytest.mark.parametrize("error", ["NACK", {"errno": True}, {"errno": "121"}], ids=["text", "bool", "string"])
def test_a_bad_recorded_error_is_named(tmp_path: Path, error: object) -> None:
    tx = {k: v for k, v in TX.items() if k != "read"}
    message = "hand.jsonl line 2: 'error' must be {'errno': int, 'message': str}"
    assert refusal(tmp_path, HEADER, {**tx, "error": error}) == message


BAD_HEADER = [
    ("format", "other", "not a bioscara bus trace (format 'other', expected 'bioscara-bus-trace')"),
    ("version", "2", "'version' must be a whole number >= 1"),
    ("version", True, "'version' must be a whole number >= 1"),
    ("version", 0, "'version' must be a whole number >= 1"),
    ("backend", None, "the header has no 'backend'"),
    ("config", [], "the header's 'config' must be an object"),
]


@pytest.mark.parametrize(
    ("key", "value", "message"), BAD_HEADER, ids=[f"{k}-{v!r}" for k, v, _ in BAD_HEADER]
)
def test_a_bad_header_is_named_with_file_line_and_key(
    tmp_path: Path, key: str, value: object, message: str
) -> None:
    assert refusal(tmp_path, {**HEADER, key: value}) == f"hand.jsonl line 1: {message}"


@pytest.mark.parametrize(
    ("text", "message"),
    [
        ("[1]\n", "hand.jsonl line 1: not a JSON object"),
        (
            '{"type": "note"}\n',
            "hand.jsonl line 1: 'type' must be 'header', 'tx', 'signal' or 'end', got 'note'",
        ),
        ("\n\n", "hand.jsonl: empty; a trace starts with a header line"),
        ("[" * 100_000 + "]" * 100_000 + "\n", "hand.jsonl line 1: nested too deeply to be a trace line"),
    ],
    ids=["list", "type", "empty", "deep"],
)
def test_a_line_that_is_no_trace_line_is_named(tmp_path: Path, text: str, message: str) -> None:
    with pytest.raises(TraceError) as caught:
        read_trace(trace_of(tmp_path, text=text), check_digests=False)
    assert str(caught.value) == message


def test_a_transaction_cut_short_and_a_signal_line_are_read(tmp_path: Path) -> None:
    tx = {k: v for k, v in TX.items() if k != "read"}
    note = {"type": "signal", "i": 1, "t": 0.5, "signal": "SIGTERM", "at": "cycle"}
    (session,) = read_trace(
        trace_of(tmp_path, HEADER, {**tx, "interrupted": "SIGINT"}, note), check_digests=False
    )
    assert session.transactions[0].interrupted == "SIGINT" and session.transactions[0].read is None
    assert session.signals == (SignalNote(line=3, before=1, signal="SIGTERM", at="cycle"),)


BAD_SIGNAL = [
    ("i", 0, "a signal line's 'i' must be the index of the transaction after it (1), got 0"),
    ("i", True, "a signal line's 'i' must be the index of the transaction after it (1), got True"),
    ("signal", "SIGKILL", "'signal' must be \"SIGINT\", \"SIGTERM\" or \"SIGHUP\", got 'SIGKILL'"),
    ("at", "later", "'at' must be one of cycle, once, got 'later'"),
]


@pytest.mark.parametrize(
    ("key", "value", "message"), BAD_SIGNAL, ids=[f"{k}-{v!r}" for k, v, _ in BAD_SIGNAL]
)
def test_a_bad_signal_line_is_named_with_file_line_and_key(
    tmp_path: Path, key: str, value: object, message: str
) -> None:
    note = {"type": "signal", "i": 1, "t": 0.5, "signal": "SIGINT", "at": "once", key: value}
    assert refusal(tmp_path, HEADER, TX, note) == f"hand.jsonl line 3: {message}"


def test_a_signal_line_before_the_first_header_is_named(tmp_path: Path) -> None:
    note = {"type": "signal", "i": 0, "t": 0.5, "signal": "SIGINT", "at": "once"}
    with pytest.raises(TraceError, match=r"^hand.jsonl line 1: a signal before the first header$"):
        read_trace(trace_of(tmp_path, note), check_digests=False)


def test_a_trace_that_is_not_utf_8_cannot_be_read_naming_the_file(tmp_path: Path) -> None:
    path = tmp_path / "binary.jsonl"
    path.write_bytes(b"\xff\xfe\x00")
    with pytest.raises(TraceError) as caught:
        read_trace(path)
    assert str(caught.value).startswith(f"{path}: cannot be read (")


def test_a_changed_line_is_refused_with_the_whole_message(tmp_path: Path) -> None:
    bus, path = record(tmp_path)
    bus.transfer(0x11, b"\x0f", 2)
    bus.close()
    docs = raw_lines(path)
    docs[1]["read"] = "4f04"
    with pytest.raises(TraceError) as caught:
        read_trace(trace_of(tmp_path, *docs))
    assert str(caught.value) == (
        "hand.jsonl line 2: its digest does not match its contents: the line was changed after it was "
        "recorded (or a line was removed just before it); replay it with --unchecked to use it anyway"
    )


# ------------------------------------------------------------------- replay
def session_of(*transactions: Transaction) -> TraceSession:
    return TraceSession(dict(HEADER), transactions)


PING = Transaction(line=2, t=0.5, dur=0.25, address=0x11, write=b"\x0f", read_len=2, read=b"\x4f\x0c")


def test_describe_says_none_for_no_bytes_written() -> None:
    assert describe((0x11, b"", 1)) == "0x11 write (none) read 1"


def test_a_mismatch_names_the_transaction_and_its_trace_line_only_when_there_is_one() -> None:
    sent = (0x11, b"\x0f", 2)
    past_end = TraceMismatch(3, None, None, sent)
    assert str(past_end) == "transaction 3: expected the end of the trace, sent 0x11 write 0f read 2"
    wrong = TraceMismatch(0, 2, PING, (0x12, b"\x0f", 2))
    assert (
        str(wrong) == "transaction 0 (trace line 2): expected 0x11 write 0f read 2, sent 0x12 write 0f read 2"
    )


def test_replay_keeps_the_clock_on_the_recorded_times(tmp_path: Path) -> None:
    clock = ManualClock(0.125)
    bus = ReplayBus(session_of(PING), clock)
    assert bus.transfer(0x11, b"\x0f", 2) == b"\x4f\x0c"
    assert clock.now() == 0.75  # moved to t = 0.5, then on by dur = 0.25


def test_bind_takes_the_backends_clock() -> None:
    bus = ReplayBus(session_of(PING))
    clock = ManualClock()
    assert bus.bind(object(), clock) is bus  # type: ignore[arg-type]
    bus.transfer(0x11, b"\x0f", 2)
    assert clock.now() == 0.75


def test_a_replay_bus_is_open_until_closed() -> None:
    bus = ReplayBus(session_of(PING))
    assert bus.closed is False
    bus.close()
    assert bus.closed is True


@contextlib.contextmanager
def no_interrupt() -> Iterator[None]:
    """A KeyboardInterrupt here fails the test (left alone, pytest would stop the whole run)."""
    try:
        yield
    except KeyboardInterrupt as e:
        pytest.fail(f"unexpected KeyboardInterrupt: {e}")


def test_a_plain_ctrl_c_is_recorded_as_sigint_raised_where_it_landed(tmp_path: Path) -> None:
    bus, path = record(tmp_path)
    bus.transfer(0x11, b"\x0f", 2)
    bus.clock.sleep(0.5)  # type: ignore[attr-defined]
    bus.record_signal(KeyboardInterrupt())
    bus.close()
    note = raw_lines(path)[2]
    del note["digest"]
    assert note == {"type": "signal", "i": 1, "t": 1.75, "signal": "SIGINT", "at": "once"}


def test_one_signal_line_a_session_and_none_once_the_trace_is_closed(tmp_path: Path) -> None:
    bus, path = record(tmp_path)
    bus.transfer(0x11, b"\x0f", 2)
    first = KeyboardInterrupt()
    bus.record_signal(first)
    bus.transfer(0x11, b"\x0f", 2)  # the safe stop's
    bus.record_signal(KeyboardInterrupt())  # the same interruption, raised again on its way out
    bus.close()
    bus.record_signal(KeyboardInterrupt())  # after the arm was shut down: nothing, no error
    assert [d["type"] for d in raw_lines(path)] == ["header", "tx", "signal", "tx", "end"]


def test_every_recorded_signal_is_counted(sigterm_calls: list[int]) -> None:
    notes = (
        SignalNote(line=3, before=1, signal="SIGTERM", at="cycle"),
        SignalNote(line=5, before=2, signal="SIGTERM", at="cycle"),
    )
    bus = ReplayBus(TraceSession(dict(HEADER), (PING, PING, PING), notes))
    with no_interrupt():
        for _ in range(3):
            bus.transfer(0x11, b"\x0f", 2)
    assert sigterm_calls == [signal.SIGTERM] * 2 and bus.signals_delivered == 2


@pytest.fixture
def sigterm_calls() -> Iterator[list[int]]:
    """SIGTERM's handler records each call and lets it pass; the previous handler is restored."""
    calls: list[int] = []
    previous = signal.signal(signal.SIGTERM, lambda signum, frame: calls.append(signum))
    try:
        yield calls
    finally:
        signal.signal(signal.SIGTERM, previous)


def test_a_signal_raised_at_a_cycle_boundary_is_handed_to_its_handler_once(sigterm_calls: list[int]) -> None:
    # "cycle": it arrived during transaction 0 and waited for the cycle's end.
    note = SignalNote(line=3, before=1, signal="SIGTERM", at="cycle")
    bus = ReplayBus(TraceSession(dict(HEADER), (PING, PING, PING), (note,)))
    with no_interrupt():
        bus.transfer(0x11, b"\x0f", 2)
        assert sigterm_calls == [signal.SIGTERM]
        for _ in range(2):  # the handler held it back: the command goes on to its boundary
            bus.transfer(0x11, b"\x0f", 2)
    assert sigterm_calls == [signal.SIGTERM] and bus.signals_delivered == 1


def test_a_signal_raised_where_it_landed_stops_the_command_there(sigterm_calls: list[int]) -> None:
    # "once": the recorded command stopped before transaction 1, so the replay
    # must too. A handler that holds the first back (a deploy's cycle) is called
    # again, as the second signal that raised it then was.
    note = SignalNote(line=3, before=1, signal="SIGTERM", at="once")
    bus = ReplayBus(TraceSession(dict(HEADER), (PING, PING), (note,)))
    with no_interrupt():
        bus.transfer(0x11, b"\x0f", 2)
    with pytest.raises(KeyboardInterrupt, match="SIGTERM"):
        bus.transfer(0x11, b"\x0f", 2)
    assert sigterm_calls == [signal.SIGTERM] * 2 and bus.signals_delivered == 1


def test_a_signal_raised_before_a_transaction_is_not_raised_again_by_the_next_one() -> None:
    # Raised where it landed, the signal stops the command before transaction 1;
    # the safe stop's first transaction then asks for transaction 1 again.
    note = SignalNote(line=3, before=1, signal="SIGTERM", at="once")
    bus = ReplayBus(TraceSession(dict(HEADER), (PING, PING), (note,)))

    def raise_it(signum: int, frame: object) -> None:
        raise KeyboardInterrupt("SIGTERM")

    previous = signal.signal(signal.SIGTERM, raise_it)
    try:
        with no_interrupt():
            bus.transfer(0x11, b"\x0f", 2)
        with pytest.raises(KeyboardInterrupt):
            bus.transfer(0x11, b"\x0f", 2)
        with no_interrupt():
            assert bus.transfer(0x11, b"\x0f", 2) == b"\x4f\x0c"
    finally:
        signal.signal(signal.SIGTERM, previous)
    assert bus.signals_delivered == 1 and bus.remaining == 0


def test_a_transaction_cut_short_raises_even_when_the_handler_lets_the_signal_pass(
    sigterm_calls: list[int],
) -> None:
    cut = dataclasses.replace(PING, read=None, interrupted="SIGTERM")
    bus = ReplayBus(session_of(cut))
    with pytest.raises(KeyboardInterrupt, match="SIGTERM"):
        bus.transfer(0x11, b"\x0f", 2)
    assert sigterm_calls == [signal.SIGTERM] * 2


@pytest.mark.parametrize(("handler", "raises"), [(signal.SIG_DFL, True), (signal.SIG_IGN, False)])
def test_a_signal_without_a_python_handler_is_a_keyboard_interrupt_unless_ignored(
    handler: Any, raises: bool
) -> None:
    # A replayed SIGTERM must never reach the default action: that would end the replay's process.
    note = SignalNote(line=3, before=1, signal="SIGTERM", at="cycle")
    bus = ReplayBus(TraceSession(dict(HEADER), (PING, PING), (note,)))
    previous = signal.signal(signal.SIGTERM, handler)
    try:
        if raises:
            with pytest.raises(KeyboardInterrupt, match="SIGTERM"):
                bus.transfer(0x11, b"\x0f", 2)
        else:
            with no_interrupt():
                assert bus.transfer(0x11, b"\x0f", 2) == b"\x4f\x0c"
    finally:
        signal.signal(signal.SIGTERM, previous)


def test_a_mismatch_past_the_end_and_one_on_a_line_carry_index_and_line() -> None:
    bus = ReplayBus(session_of(PING))
    bus.transfer(0x11, b"\x0f", 2)
    with pytest.raises(TraceMismatch) as past_end:
        bus.transfer(0x11, b"\x0f", 2)
    assert (past_end.value.index, past_end.value.line) == (1, None)
    assert str(past_end.value).startswith("transaction 1: expected the end of the trace")
    other = ReplayBus(session_of(PING))
    with pytest.raises(TraceMismatch) as wrong:
        other.transfer(0x12, b"\x0f", 2)
    assert (wrong.value.index, wrong.value.line) == (0, 2)
    assert str(wrong.value).startswith("transaction 0 (trace line 2): ")
