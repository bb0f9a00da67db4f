"""A trace says where each session ends; one cut short is damaged, not the driver's fault.

Seen (a hostile tester, 4 times): a trace cut at a line boundary (the
recorder killed with -9, ``head -n 1000 t.jsonl > cut.jsonl``) made
``bioscara replay`` report "mismatch at transaction 999: expected the end of
the trace" (exit 1), blaming the driver for a damaged trace. A session
closed normally now ends with a closing line (``"type": "end"``); one of
format version 4 without it was cut, and its replay says so (exit 2).

Seen too: ``bioscara eval --record`` stopped by Ctrl-C during its start-up
(configure, activate) left a trace whose replay failed (exit 1): the arm's
failed transition disabled the joints before the eval noted the signal, so
the signal line came after those transactions.
"""

from __future__ import annotations

import contextlib
import io
import json
import signal
from collections.abc import Iterator
from pathlib import Path
from typing import Any

import pytest
from rigs import TRACE_HEADER, TRACE_TX

from bioscara_gym.cli import main
from bioscara_gym.hardware import recording
from bioscara_gym.hardware.clock import ManualClock
from bioscara_gym.hardware.config import load_config
from bioscara_gym.hardware.recording import (
    TRACE_VERSION,
    Recording,
    RecordingBus,
    ReplayBus,
    TraceError,
    TraceMismatch,
    TraceSession,
    Transaction,
    read_trace,
)
from bioscara_gym.hardware.registers import FLAG_NOT_ENABLED
from bioscara_gym.replay import replay

EVAL = ["eval", "--expert", "--env", "Bioscara-Reach-v0", "--backend", "emulated"]
CUT = "without its closing line: the recording was cut (killed, disk full, or truncated)"


class PingBus:
    """A bus whose every transfer takes 0.25 s of the clock and answers PING's 'O' with no flag."""

    def __init__(self, clock: ManualClock) -> None:
        self.clock = clock

    def transfer(self, address: int, data: bytes, read_len: int) -> bytes:
        self.clock.sleep(0.25)
        return b"\x4f\x00"[:read_len]

    def close(self) -> None:
        pass


def raw_lines(path: Path) -> list[dict[str, Any]]:
    return [json.loads(line) for line in path.read_text(encoding="utf-8").splitlines()]


def write_text_lines(path: Path, lines: list[str]) -> Path:
    path.write_text("".join(lines), encoding="utf-8")
    return path


def replay_cli(path: Path, capsys: pytest.CaptureFixture[str], *options: str) -> tuple[int, str, str]:
    capsys.readouterr()
    code = main(["replay", *options, str(path)])
    out, err = capsys.readouterr()
    return code, out, err


def header(version: int) -> dict[str, Any]:
    return {**TRACE_HEADER, "version": version}


TX = TRACE_TX
PING = Transaction(line=2, t=0.5, dur=0.25, address=0x11, write=b"\x0f", read_len=2, read=b"\x4f\x0c")


def hand_trace(tmp_path: Path, *docs: dict[str, Any]) -> Path:
    path = tmp_path / "hand.jsonl"
    path.write_text("".join(json.dumps(d) + "\n" for d in docs), encoding="utf-8")
    return path


# ------------------------------------------------------------- the closing line
def test_a_recording_closed_normally_ends_with_a_closing_line_in_the_digest_chain(tmp_path: Path) -> None:
    clock = ManualClock(1.0)
    path = tmp_path / "t.jsonl"
    bus = RecordingBus(PingBus(clock), Recording(path, "ping"), clock, "emulated", load_config())
    bus.transfer(0x11, b"\x0f", 2)
    bus.transfer(0x12, b"\x0f", 2)
    bus.close()
    docs = raw_lines(path)
    assert docs[0]["version"] == TRACE_VERSION >= 4
    assert [d["type"] for d in docs] == ["header", "tx", "tx", "end"]
    end = docs[-1]
    assert (end["transactions"], end["t"]) == (2, 1.5)
    (session,) = read_trace(path)  # digests checked: the closing line is chained like every line
    assert session.end_line == 4 and not session.cut


def test_a_second_close_writes_no_second_closing_line(tmp_path: Path) -> None:
    clock = ManualClock()
    path = tmp_path / "t.jsonl"
    bus = RecordingBus(PingBus(clock), Recording(path, "ping"), clock, "emulated", load_config())
    bus.close()
    bus.close()
    assert [d["type"] for d in raw_lines(path)] == ["header", "end"]


def test_a_session_is_appended_after_a_closing_line_and_each_replays(
    tmp_path: Path, capsys: pytest.CaptureFixture[str]
) -> None:
    trace = tmp_path / "t.jsonl"
    assert main(["ping", "--record", str(trace)]) == 0
    assert main(["ping", "--record", str(trace)]) == 0
    assert [d["type"] for d in raw_lines(trace)] == ["header", *["tx"] * 4, "end"] * 2
    code, out, err = replay_cli(trace, capsys)
    assert (code, err) == (0, "")
    assert out.strip() == "8 transactions matched (2 sessions)"


# ------------------------------------------------------------------ cut traces
def test_an_eval_trace_cut_at_a_line_boundary_is_a_damaged_trace(
    tmp_path: Path, capsys: pytest.CaptureFixture[str]
) -> None:
    # The hostile tester's `head -n 1000 t.jsonl > cut.jsonl`.
    trace = tmp_path / "t.jsonl"
    assert main([*EVAL, "--episodes", "1", "--record", str(trace)]) == 0
    lines = trace.read_text(encoding="utf-8").splitlines(keepends=True)
    cut = write_text_lines(tmp_path / "cut.jsonl", lines[:1000])
    code, out, err = replay_cli(cut, capsys)
    assert code == 2
    assert err.count("\n") == 1, err
    assert err == (
        f"bioscara replay: error: {cut}: session 1 (eval) ends after transaction 998 (trace line 1000) "
        f"{CUT}\n"
    )
    assert "mismatch" not in out + err


def test_a_recorder_that_never_closed_left_a_damaged_trace(
    tmp_path: Path, capsys: pytest.CaptureFixture[str]
) -> None:
    # A recorder killed with -9: the bus is never closed, the lines written are whole.
    trace = tmp_path / "t.jsonl"
    assert main(["enable", "--record", str(trace)]) == 0
    docs = raw_lines(trace)
    assert docs[-1]["type"] == "end" and docs[-1]["transactions"] == len(docs) - 2
    lines = trace.read_text(encoding="utf-8").splitlines(keepends=True)
    killed = write_text_lines(tmp_path / "killed.jsonl", lines[:21])
    code, _, err = replay_cli(killed, capsys)
    assert code == 2
    assert err.strip().endswith(f"session 1 (enable) ends after transaction 19 (trace line 21) {CUT}")


def test_a_cut_session_followed_by_an_appended_one_is_named(
    tmp_path: Path, capsys: pytest.CaptureFixture[str]
) -> None:
    trace = tmp_path / "t.jsonl"
    assert main(["ping", "--record", str(trace)]) == 0
    lines = trace.read_text(encoding="utf-8").splitlines(keepends=True)
    write_text_lines(trace, lines[:3])  # header, transactions 0 and 1: killed there
    assert main(["ping", "--record", str(trace)]) == 0  # the next command appends its session
    code, _, err = replay_cli(trace, capsys)
    assert code == 2
    assert err.strip().endswith(f"session 1 (ping) ends after transaction 1 (trace line 3) {CUT}")


def test_a_session_cut_after_its_header_is_damaged(
    tmp_path: Path, capsys: pytest.CaptureFixture[str]
) -> None:
    trace = tmp_path / "t.jsonl"
    assert main(["ping", "--record", str(trace)]) == 0
    lines = trace.read_text(encoding="utf-8").splitlines(keepends=True)
    code, _, err = replay_cli(write_text_lines(trace, lines[:1]), capsys)
    assert code == 2
    assert err.strip().endswith(f"session 1 (ping) ends after its header {CUT}")


def test_a_partial_last_line_is_a_damaged_trace(tmp_path: Path, capsys: pytest.CaptureFixture[str]) -> None:
    # A process killed mid-write (or `head -c`): the last line is cut off.
    trace = tmp_path / "t.jsonl"
    assert main(["enable", "--record", str(trace)]) == 0
    lines = trace.read_text(encoding="utf-8").splitlines(keepends=True)
    partial = write_text_lines(tmp_path / "partial.jsonl", [*lines[:20], lines[20][:40]])
    code, out, err = replay_cli(partial, capsys)
    assert (code, out) == (2, "")
    assert err.count("\n") == 1, err
    assert err.startswith("bioscara replay: error: partial.jsonl line 21: ")
    assert "the recording was cut (killed, disk full, or truncated)" in err


def test_a_trace_without_its_last_lines_but_the_closing_one_still_replays(
    tmp_path: Path, capsys: pytest.CaptureFixture[str]
) -> None:
    # Only the closing line missing: every recorded transaction and nothing else was sent.
    trace = tmp_path / "t.jsonl"
    assert main(["ping", "--record", str(trace)]) == 0
    lines = trace.read_text(encoding="utf-8").splitlines(keepends=True)
    code, _, err = replay_cli(write_text_lines(trace, lines[:-1]), capsys)
    assert (code, err) == (0, "")


# -------------------------------------------------------- reading closing lines
@pytest.mark.parametrize(
    ("docs", "message"),
    [
        (
            [header(4), TX, {"type": "end", "transactions": 2}],
            "hand.jsonl line 3: the closing line counts 2 transactions; its session has 1",
        ),
        (
            [header(4), TX, {"type": "end", "transactions": True}],
            "hand.jsonl line 3: the closing line counts True transactions; its session has 1",
        ),
        (
            [header(4), {"type": "end", "transactions": 0}, TX],
            "hand.jsonl line 3: a transaction after its session's closing line",
        ),
        (
            [header(4), {"type": "end", "transactions": 0}, {"type": "end", "transactions": 0}],
            "hand.jsonl line 3: a closing line after its session's closing line",
        ),
        ([{"type": "end", "transactions": 0}], "hand.jsonl line 1: a closing line before the first header"),
    ],
    ids=["count", "bool", "tx-after", "end-after", "before-header"],
)
def test_a_bad_closing_line_is_named_with_file_and_line(
    tmp_path: Path, docs: list[dict[str, Any]], message: str
) -> None:
    with pytest.raises(TraceError) as caught:
        read_trace(hand_trace(tmp_path, *docs), check_digests=False)
    assert str(caught.value) == message


def test_an_earlier_version_session_without_a_closing_line_replays_as_before() -> None:
    # Version 3 and earlier wrote no closing line: going on past the end is the driver's difference.
    for version in (1, 2, 3):
        session = TraceSession(header(version), (PING,))
        assert not session.cut
        bus = ReplayBus(session)
        bus.transfer(0x11, b"\x0f", 2)
        with pytest.raises(TraceMismatch, match="expected the end of the trace"):
            bus.transfer(0x11, b"\x0f", 2)


def test_a_cut_session_raises_trace_cut_to_the_driver_and_again_after() -> None:
    session = TraceSession(header(4), (PING,))
    assert session.cut
    bus = ReplayBus(session)
    bus.transfer(0x11, b"\x0f", 2)
    with pytest.raises(recording.TraceCut) as caught:
        bus.transfer(0x11, b"\x0f", 2)
    assert str(caught.value) == f"ends after transaction 0 (trace line 2) {CUT}"
    assert bus.cut_off is caught.value and bus.mismatch is None
    with pytest.raises(recording.TraceCut):
        bus.transfer(0x12, b"\x0f", 2)


def test_a_closed_session_going_on_past_its_end_is_still_a_mismatch() -> None:
    session = TraceSession(header(4), (PING,), end_line=3)
    bus = ReplayBus(session)
    bus.transfer(0x11, b"\x0f", 2)
    with pytest.raises(TraceMismatch, match="expected the end of the trace"):
        bus.transfer(0x11, b"\x0f", 2)


# ------------------------------------------------ an eval stopped in its start-up
@contextlib.contextmanager
def signal_before(index: int, signum: int) -> Iterator[list[RecordingBus]]:
    """Deliver ``signum`` once, in the main thread, just before transaction ``index``: between two.

    Yields the recording buses made meanwhile, to look at the emulated joints afterwards.
    """
    transfer = RecordingBus.transfer
    init = RecordingBus.__init__
    buses: list[RecordingBus] = []

    def made(self: RecordingBus, *args: Any, **kwargs: Any) -> None:
        init(self, *args, **kwargs)
        buses.append(self)

    def lands_before(self: RecordingBus, address: int, data: bytes, read_len: int) -> bytes:
        if self.transactions == index and not getattr(self, "_test_signalled", False):
            self._test_signalled = True  # type: ignore[attr-defined]
            signal.raise_signal(signum)  # the handler runs here, as a Ctrl-C between two transactions
        return transfer(self, address, data, read_len)

    with pytest.MonkeyPatch.context() as mp:
        mp.setattr(RecordingBus, "__init__", made)
        mp.setattr(RecordingBus, "transfer", lands_before)
        yield buses


@pytest.mark.parametrize(
    ("index", "signum", "code"),
    [
        (1, signal.SIGINT, 130),  # configure: after the first PING
        (12, signal.SIGINT, 130),  # activate: before j1's SETUP
        (35, signal.SIGTERM, 143),  # activate: its last transaction
        (60, signal.SIGINT, 130),  # homing
    ],
    ids=["configure", "activate", "activate-end-TERM", "homing"],
)
def test_an_eval_stopped_in_its_start_up_replays_and_leaves_every_joint_disabled(
    tmp_path: Path, index: int, signum: int, code: int
) -> None:
    trace = tmp_path / "t.jsonl"
    with signal_before(index, signum) as buses, contextlib.redirect_stderr(io.StringIO()):
        assert main([*EVAL, "--episodes", "5", "--record", str(trace)]) == code
    docs = raw_lines(trace)
    notes = [d for d in docs if d["type"] == "signal"]
    assert [(n["i"], n["signal"], n["at"]) for n in notes] == [(index, signal.Signals(signum).name, "once")]
    result = replay(trace)
    assert result.ok, result.sessions[-1]
    assert result.matched == sum(d["type"] == "tx" for d in docs) > index
    (bus,) = buses
    enabled = [f"{a:#04x}" for a, d in bus.inner.devices.items() if not d.core.flags & FLAG_NOT_ENABLED]
    assert enabled == [], "an interrupted eval left joints enabled"
