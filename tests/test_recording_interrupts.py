"""A SIGINT or SIGTERM at any moment of a recorded transaction leaves a trace that replays.

Seen (a hostile test, 4 of 8 tries): ``bioscara eval --record`` Ctrl-C'd
2.5-3.2 s in left a trace ``bioscara replay`` refused, either "line 9331: its
digest does not match its contents" (the last transaction's line written, the
digest chain not moved on to it) or "a signal line's 'i' must be the index of
the transaction after it (11956), got 11957" (a transaction counted, its line
never written). The eval process has a second thread: the kernel gave it the
signal, which the main thread's mask did not hold back, and Python ran the
handler in the main thread in the middle of the trace's bookkeeping.

Here the signal is sent to a second thread of this process whose mask blocks
nothing (``pthread_kill``), at each point of the bookkeeping of one
transaction; its handler raises in the main thread, as in the eval.
"""

from __future__ import annotations

import json
import signal
import threading
from collections.abc import Callable, Iterator
from pathlib import Path
from typing import Any

import pytest

from bioscara_gym.hardware import recording
from bioscara_gym.hardware.clock import ManualClock
from bioscara_gym.hardware.config import load_config
from bioscara_gym.hardware.recording import Recording, RecordingBus, read_trace
from bioscara_gym.replay import replay
from bioscara_gym.training.signals import Interrupted, SignalGuard

SIGNALS = pytest.mark.parametrize("signum", [signal.SIGINT, signal.SIGTERM], ids=["INT", "TERM"])


class SecondThread:
    """A thread of this process whose signal mask blocks nothing: the kernel's pick for a signal.

    :meth:`signal` hands it a signal and waits until its C-level handler has
    run there; the Python handler then runs in the main thread at its next
    bytecode boundary, wherever that is.
    """

    def __init__(self) -> None:
        self._signum = 0
        self._go = threading.Event()
        self._done = threading.Event()
        self._thread = threading.Thread(target=self._run, name="second", daemon=True)
        self._thread.start()  # now, while the main thread blocks nothing: its mask is inherited

    def _run(self) -> None:
        self._go.wait()
        signal.pthread_kill(threading.get_ident(), self._signum)  # handled in this thread
        self._done.set()

    def signal(self, signum: int) -> None:
        self._signum = signum
        self._go.set()
        assert self._done.wait(5.0)


@pytest.fixture
def second_thread() -> Iterator[SecondThread]:
    thread = SecondThread()
    yield thread
    thread._go.set()  # a test that did not use it lets it end
    thread._thread.join(5.0)


@pytest.fixture
def raising_handlers() -> Iterator[list[int]]:
    """SIGINT and SIGTERM raise :class:`Interrupted` where they land; yields the signals handled."""
    handled: list[int] = []
    with SignalGuard() as guard:
        handle = guard._handle

        def counted(signum: int, frame: Any) -> None:
            handled.append(signum)
            guard.pending = None  # each signal raises afresh
            handle(signum, frame)

        for signum in guard.signals:
            signal.signal(signum, counted)
        yield handled


class PingBus:
    """A bus whose every transfer takes 0.25 s of the clock and answers PING; ``during`` runs in it."""

    def __init__(self, clock: ManualClock) -> None:
        self.clock = clock
        self.during: Callable[[], None] | None = None

    def transfer(self, address: int, data: bytes, read_len: int) -> bytes:
        self.clock.sleep(0.25)
        if self.during is not None:
            during, self.during = self.during, None
            during()
        return b"\x4f\x00"[:read_len]

    def close(self) -> None:
        pass


def record(tmp_path: Path) -> tuple[RecordingBus, PingBus, Path]:
    clock = ManualClock(1.0)
    inner = PingBus(clock)
    path = tmp_path / "t.jsonl"
    return RecordingBus(inner, Recording(path, "ping"), clock, "emulated", load_config()), inner, path


def raw_lines(path: Path) -> list[dict[str, Any]]:
    return [json.loads(line) for line in path.read_text(encoding="utf-8").splitlines()]


# Where in one transaction's bookkeeping the signal lands: a hook in the recorder that sends it.
def at_the_duration(monkeypatch: pytest.MonkeyPatch, bus: RecordingBus, send: Callable[[], None]) -> None:
    now = bus.clock.now
    calls = {"n": 0}

    def now_then_signal() -> float:
        calls["n"] += 1
        t = now()
        if calls["n"] == 2:  # the second of the transaction: its duration, before it is counted
            send()
        return t

    monkeypatch.setattr(bus.clock, "now", now_then_signal)


def at_the_digest(monkeypatch: pytest.MonkeyPatch, bus: RecordingBus, send: Callable[[], None]) -> None:
    digest = recording.line_digest

    def digest_then_signal(record: Any, previous: str) -> str:
        if record.get("type") == "tx":  # counted, not yet written
            send()
        return digest(record, previous)

    monkeypatch.setattr(recording, "line_digest", digest_then_signal)


def before_the_write(monkeypatch: pytest.MonkeyPatch, bus: RecordingBus, send: Callable[[], None]) -> None:
    write = recording._os_write

    def signal_then_write(fd: int, data: Any) -> int:
        send()
        return write(fd, data)

    monkeypatch.setattr(recording, "_os_write", signal_then_write)


def after_the_write(monkeypatch: pytest.MonkeyPatch, bus: RecordingBus, send: Callable[[], None]) -> None:
    write = recording._os_write

    def write_then_signal(fd: int, data: Any) -> int:
        n = write(fd, data)
        send()  # the line is on disk; the digest chain has not moved on yet
        return n

    monkeypatch.setattr(recording, "_os_write", write_then_signal)


BOOKKEEPING = pytest.mark.parametrize(
    "lands", [at_the_duration, at_the_digest, before_the_write, after_the_write], ids=lambda f: f.__name__
)


def interrupted_session(
    tmp_path: Path, monkeypatch: pytest.MonkeyPatch, lands: Any, send: Callable[[], None]
) -> tuple[RecordingBus, Path, BaseException]:
    """Two transactions, the signal landing in the bookkeeping of the second, then the command's stop.

    As a command does: the signal noted where it stopped it, then one transaction of its safe stop.
    """
    bus, _, path = record(tmp_path)
    bus.transfer(0x11, b"\x0f", 2)
    lands(monkeypatch, bus, send)
    with pytest.raises(KeyboardInterrupt) as caught:
        bus.transfer(0x12, b"\x0f", 2)
    monkeypatch.undo()
    bus.record_signal(caught.value)
    bus.transfer(0x13, b"\x0f", 2)  # the safe stop's
    bus.close()
    return bus, path, caught.value


@SIGNALS
@BOOKKEEPING
def test_a_signal_in_a_lines_bookkeeping_is_raised_once_the_line_is_written(
    tmp_path: Path,
    monkeypatch: pytest.MonkeyPatch,
    second_thread: SecondThread,
    raising_handlers: list[int],
    signum: int,
    lands: Any,
) -> None:
    bus, path, error = interrupted_session(tmp_path, monkeypatch, lands, lambda: second_thread.signal(signum))
    assert isinstance(error, Interrupted) and error.signum == signum
    assert raising_handlers == [signum]  # the command's handler took it, once
    (session,) = read_trace(path)  # digests checked, and the signal line's index
    assert [tx.write for tx in session.transactions] == [b"\x0f"] * 3
    assert [tx.address for tx in session.transactions] == [0x11, 0x12, 0x13]
    assert [tx.read for tx in session.transactions] == [b"\x4f\x00"] * 3  # the interrupted one is whole
    (note,) = session.signals
    assert (note.before, note.signal, note.at) == (2, signal.Signals(signum).name, "once")
    assert bus.transactions == 3
    assert [d["i"] for d in raw_lines(path) if d["type"] == "tx"] == [0, 1, 2]


@SIGNALS
def test_a_signal_in_the_exchange_still_cuts_it_short(
    tmp_path: Path, second_thread: SecondThread, raising_handlers: list[int], signum: int
) -> None:
    bus, inner, path = record(tmp_path)
    inner.during = lambda: second_thread.signal(signum)
    with pytest.raises(Interrupted) as caught:
        bus.transfer(0x11, b"\x0f", 2)
    bus.record_signal(caught.value)  # nothing: the transaction says it
    bus.close()
    (session,) = read_trace(path)
    (tx,) = session.transactions
    assert (tx.interrupted, tx.read, session.signals) == (signal.Signals(signum).name, None, ())


@BOOKKEEPING
def test_the_handlers_are_the_commands_again_after_a_held_signal(
    tmp_path: Path,
    monkeypatch: pytest.MonkeyPatch,
    second_thread: SecondThread,
    raising_handlers: list[int],
    lands: Any,
) -> None:
    before = {s: signal.getsignal(s) for s in (signal.SIGINT, signal.SIGTERM)}
    interrupted_session(tmp_path, monkeypatch, lands, lambda: second_thread.signal(signal.SIGINT))
    assert {s: signal.getsignal(s) for s in before} == before


def test_a_deploy_cycles_signal_in_the_bookkeeping_waits_for_the_cycle_boundary(
    tmp_path: Path, monkeypatch: pytest.MonkeyPatch, second_thread: SecondThread
) -> None:
    # Inside a deploy's cycle the guard only notes the first signal: the transfer goes on.
    bus, _, path = record(tmp_path)
    with SignalGuard() as guard, guard.deferred():
        after_the_write(monkeypatch, bus, lambda: second_thread.signal(signal.SIGINT))
        assert bus.transfer(0x11, b"\x0f", 2) == b"\x4f\x00"
        monkeypatch.undo()
        assert guard.pending == signal.SIGINT
    bus.close()
    (session,) = read_trace(path)
    assert len(session.transactions) == 1 == bus.transactions


def test_a_signal_while_the_signal_line_is_written_leaves_the_chain_whole(
    tmp_path: Path, monkeypatch: pytest.MonkeyPatch, second_thread: SecondThread, raising_handlers: list[int]
) -> None:
    bus, _, path = record(tmp_path)
    bus.transfer(0x11, b"\x0f", 2)
    after_the_write(monkeypatch, bus, lambda: second_thread.signal(signal.SIGTERM))
    with pytest.raises(Interrupted):  # a second signal, raised once the signal line is whole
        bus.record_signal(KeyboardInterrupt())
    monkeypatch.undo()
    bus.transfer(0x12, b"\x0f", 2)
    bus.close()
    (session,) = read_trace(path)
    assert len(session.transactions) == 2 and [n.before for n in session.signals] == [1]


def test_a_signal_as_the_header_is_written_is_noted_before_any_transaction(
    tmp_path: Path, monkeypatch: pytest.MonkeyPatch, second_thread: SecondThread, raising_handlers: list[int]
) -> None:
    # The bus is never handed to the command, which cannot note where it stopped: the recorder does.
    after_the_write(monkeypatch, None, lambda: second_thread.signal(signal.SIGINT))  # type: ignore[arg-type]
    with pytest.raises(Interrupted):
        record(tmp_path)
    monkeypatch.undo()
    (session,) = read_trace(tmp_path / "t.jsonl")
    assert session.transactions == ()
    assert [(n.before, n.signal, n.at) for n in session.signals] == [(0, "SIGINT", "once")]
    result = replay(tmp_path / "t.jsonl")  # stopped before it starts, as it was
    assert result.ok and result.matched == 0


# ------------------------------------------------------------- end to end
@pytest.mark.parametrize(
    ("signum", "code"), [(signal.SIGINT, 130), (signal.SIGTERM, 143)], ids=["INT", "TERM"]
)
def test_an_eval_interrupted_after_a_line_is_written_replays(
    tmp_path: Path,
    monkeypatch: pytest.MonkeyPatch,
    capsys: pytest.CaptureFixture[str],
    second_thread: SecondThread,
    signum: int,
    code: int,
) -> None:
    # The hostile test's `bioscara eval --record`, the signal given to its second thread.
    from bioscara_gym.cli import main

    write = recording._os_write
    lines = {"n": 0}

    def write_then_signal(fd: int, data: Any) -> int:
        n = write(fd, data)
        lines["n"] += 1
        if lines["n"] == 300:  # mid-episode, the line on disk, the chain not moved on
            second_thread.signal(signum)
        return n

    monkeypatch.setattr(recording, "_os_write", write_then_signal)
    trace = tmp_path / "eval.jsonl"
    argv = ["eval", "--expert", "--env", "Bioscara-Reach-v0", "--backend", "emulated", "--episodes", "2"]
    assert main([*argv, "--record", str(trace)]) == code
    monkeypatch.undo()
    capsys.readouterr()
    result = replay(trace)  # a trace it refuses raises TraceError
    assert result.ok, result.sessions[-1]
    txs = [d for d in raw_lines(trace) if d["type"] == "tx"]
    assert result.matched == len(txs) > 300
