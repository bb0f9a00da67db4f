"""Bus traces (docs/traces.md): what is recorded, and that replay holds the driver to every byte.

Every trace under ``tests/traces/`` is replayed; a change that alters a byte on
the wire fails here until the traces are re-recorded on purpose
(``python tests/traces/record.py``, tests/traces/README.md).
"""

from __future__ import annotations

import argparse
import json
import re
from pathlib import Path

import pytest

from bioscara_gym.cli import main
from bioscara_gym.console import commands
from bioscara_gym.hardware import codec
from bioscara_gym.hardware.backends import make_backend, mock_gripper
from bioscara_gym.hardware.config import load_config
from bioscara_gym.hardware.recording import (
    TRACE_FORMAT,
    TRACE_VERSION,
    Recording,
    ReplayBus,
    TraceError,
    TraceMismatch,
    read_trace,
)
from bioscara_gym.hardware.registers import Reg
from bioscara_gym.replay import replay

TRACES = Path(__file__).parent / "traces"
SHIPPED = sorted(TRACES.glob("*.jsonl"))


def transactions(path: Path) -> int:
    return sum(len(s.transactions) for s in read_trace(path))


def lines(path: Path) -> list[dict]:
    return [json.loads(line) for line in path.read_text(encoding="utf-8").splitlines()]


def write_lines(path: Path, docs: list[dict]) -> Path:
    path.write_text("".join(json.dumps(d) + "\n" for d in docs), encoding="utf-8")
    return path


# ------------------------------------------------------------ shipped traces


def test_the_shipped_traces_are_there() -> None:
    names = {p.name for p in SHIPPED}
    assert {"deploy_reach_expert.jsonl", "deploy_reach_faults.jsonl", "console_session.jsonl"} <= names


@pytest.mark.parametrize("path", SHIPPED, ids=lambda p: p.stem)
def test_every_shipped_trace_replays_transaction_for_transaction(path: Path) -> None:
    result = replay(path)
    assert result.ok, [str(s.mismatch) for s in result.sessions]
    assert result.matched == transactions(path)


def test_the_console_trace_holds_the_whole_session() -> None:
    commands_recorded = [s.command for s in read_trace(TRACES / "console_session.jsonl")]
    assert commands_recorded[:3] == ["enable", "home", "move"]
    assert {"gripper", "disable"} <= set(commands_recorded)


def test_the_deploy_trace_holds_homing_and_100_cycles() -> None:
    (session,) = read_trace(TRACES / "deploy_reach_expert.jsonl")
    assert session.header["args"]["episodes"] == 2
    writes = [tx.write[0] for tx in session.transactions]
    assert Reg.HOME in writes
    assert writes.count(Reg.SETRPM) >= 100 * 4  # a velocity command per joint and cycle


def test_the_fault_trace_replays_recorded_errors_into_the_drivers_retries() -> None:
    path = TRACES / "deploy_reach_faults.jsonl"
    (session,) = read_trace(path)
    errors = [i for i, tx in enumerate(session.transactions) if tx.read is None]
    assert errors, "the fault trace holds no bus error"
    retried = [i for i in errors if session.transactions[i + 1].request == session.transactions[i].request]
    assert retried, "no recorded error was followed by the same transaction again"
    assert replay(path).errors_replayed == len(errors)


# ------------------------------------------------------------------ header


def test_header_names_format_version_backend_config_and_command(tmp_path: Path) -> None:
    trace = tmp_path / "t.jsonl"
    assert main(["enable", "j1", "--record", str(trace)]) == 0
    header = lines(trace)[0]
    assert header["type"] == "header"
    assert (header["format"], header["version"]) == (TRACE_FORMAT, TRACE_VERSION)
    assert header["backend"] == "emulated"
    assert header["command"] == "enable"
    assert header["args"]["target"] == "j1"
    assert [j["name"] for j in header["config"]["joints"]] == ["j1", "j2", "j3", "j4"]
    assert "bioscara_gym" in header


def test_a_transaction_line_has_time_address_bytes_and_reply(tmp_path: Path) -> None:
    trace = tmp_path / "t.jsonl"
    assert main(["ping", "--record", str(trace)]) == 0
    tx = lines(trace)[1]
    assert tx == {**tx, "type": "tx", "addr": "0x11", "write": "0f", "read_len": 2, "read": "4f0c"}
    assert isinstance(tx["t"], float)


def test_record_is_refused_on_a_backend_without_a_bus(tmp_path: Path, capsys: pytest.CaptureFixture) -> None:
    assert main(["status", "--backend", "mock", "--record", str(tmp_path / "t.jsonl")]) != 0
    err = capsys.readouterr().err.strip()
    assert err.count("\n") == 0
    assert "--record needs a backend with an I2C bus" in err


# --------------------------------------------------------------- mismatches


def test_a_one_byte_change_in_a_command_fails_with_index_and_bytes(
    monkeypatch: pytest.MonkeyPatch, capsys: pytest.CaptureFixture
) -> None:
    encode = codec.encode

    def setup_with_more_hold_current(reg: Reg, value: float | int, joint: str | None = None) -> bytes:
        payload = encode(reg, value, joint=joint)
        return payload[:1] + bytes([payload[1] + 1]) + payload[2:] if reg == Reg.SETUP else payload

    monkeypatch.setattr(codec, "encode", setup_with_more_hold_current)
    path = TRACES / "console_session.jsonl"
    first_setup = next(i for i, tx in enumerate(read_trace(path)[0].transactions) if tx.write[0] == Reg.SETUP)
    result = replay(path)
    mismatch = result.sessions[-1].mismatch
    assert isinstance(mismatch, TraceMismatch)
    assert mismatch.index == first_setup
    assert mismatch.sent[1] != mismatch.expected.write
    assert main(["replay", str(path)]) == 1
    err = capsys.readouterr().err
    assert f"transaction {first_setup}" in err
    assert mismatch.expected.write.hex(" ") in err and mismatch.sent[1].hex(" ") in err


def test_a_changed_register_number_fails(monkeypatch: pytest.MonkeyPatch) -> None:
    monkeypatch.setattr(codec, "encode", lambda reg, value, joint=None: b"\x00\x00\x00\x00")
    assert not replay(TRACES / "console_session.jsonl").ok


def test_a_truncated_trace_fails_when_the_driver_sends_more(tmp_path: Path) -> None:
    docs = lines(TRACES / "deploy_reach_expert.jsonl")
    short = write_lines(tmp_path / "short.jsonl", docs[:-10])
    result = replay(short)
    mismatch = result.sessions[-1].mismatch
    assert mismatch is not None and mismatch.expected is None
    assert "expected the end of the trace" in str(mismatch)


def test_a_trace_longer_than_the_driver_sends_fails(tmp_path: Path, capsys: pytest.CaptureFixture) -> None:
    trace = tmp_path / "ping.jsonl"
    assert main(["ping", "--record", str(trace)]) == 0
    *docs, end = lines(trace)  # the header, the transactions, the closing line
    n = len(docs) - 1
    extra = {**docs[-1], "i": n}  # one more transaction, and the closing line counting it
    longer = write_lines(tmp_path / "longer.jsonl", [*docs, extra, {**end, "transactions": n + 1}])
    result = replay(longer, check_digests=False)  # the added line is made by hand: its digest is wrong
    assert result.sessions[-1].stopped_early
    assert main(["replay", "--unchecked", str(longer)]) == 1
    assert f"stopped after {n} of {n + 1} transactions" in capsys.readouterr().err


def test_a_recorded_error_is_raised_again_as_the_same_oserror() -> None:
    path = TRACES / "deploy_reach_faults.jsonl"
    (session,) = read_trace(path)
    bus = ReplayBus(session)
    for tx in session.transactions:
        if tx.read is None:
            with pytest.raises(OSError) as e:
                bus.transfer(*tx.request)
            assert (e.value.errno, e.value.strerror) == (tx.errno, tx.message)
            return
        assert bus.transfer(*tx.request) == tx.read
    pytest.fail("no recorded error")


def test_a_different_read_length_is_a_mismatch_naming_both() -> None:
    (session,) = read_trace(TRACES / "deploy_reach_expert.jsonl")
    first = session.transactions[0]
    bus = ReplayBus(session)
    with pytest.raises(TraceMismatch) as caught:
        bus.transfer(first.address, first.write, first.read_len + 1)
    assert f"read {first.read_len}, sent" in str(caught.value)
    assert str(caught.value).endswith(f"read {first.read_len + 1}")


class _Failing:
    """A bus whose every transfer raises ``OSError(errno, message)``."""

    def __init__(self, errno: int, message: str) -> None:
        self.errno, self.message = errno, message

    def transfer(self, address: int, data: bytes, read_len: int) -> bytes:
        raise OSError(self.errno, self.message)

    def close(self) -> None:
        pass


def test_a_bus_error_is_recorded_with_its_errno_and_message_and_raised_unchanged(tmp_path: Path) -> None:
    from bioscara_gym.hardware.clock import ManualClock
    from bioscara_gym.hardware.recording import Recording, RecordingBus

    recording = Recording(tmp_path / "t.jsonl", "x")
    bus = RecordingBus(_Failing(121, "Remote I/O error"), recording, ManualClock(), "i2c", load_config())
    with pytest.raises(OSError) as caught:
        bus.transfer(0x12, b"\x18", 5)
    assert (caught.value.errno, caught.value.strerror) == (121, "Remote I/O error")
    bus.close()
    (session,) = read_trace(tmp_path / "t.jsonl")
    (tx,) = session.transactions
    assert (tx.address, tx.write, tx.read_len, tx.read) == (0x12, b"\x18", 5, None)
    assert (tx.errno, tx.message) == (121, "Remote I/O error")


def test_after_a_mismatch_every_transfer_raises_it_again() -> None:
    (session,) = read_trace(TRACES / "deploy_reach_expert.jsonl")
    bus = ReplayBus(session)
    with pytest.raises(TraceMismatch):
        bus.transfer(0x11, b"\x00", 1)
    first = session.transactions[0]
    with pytest.raises(TraceMismatch):
        bus.transfer(*first.request)


# --------------------------------------------------- a trace of the real arm


class PoweredArm:
    """The emulated arm's bus, left open when a command closes its backend (the arm stays powered)."""

    def __init__(self, bus: object) -> None:
        self.bus = bus

    def transfer(self, address: int, data: bytes, read_len: int) -> bytes:
        return self.bus.transfer(address, data, read_len)

    def close(self) -> None:
        pass


def test_an_i2c_trace_replays_on_the_replay_clock(tmp_path: Path) -> None:
    """A session of the ``i2c`` backend (as on the arm) replays without sysfs or a wall clock.

    The "arm" is the emulated one's bus and clock behind the ``i2c`` backend,
    so the trace's header says ``i2c``, as a golden trace from the arm does.
    """
    arm = make_backend("emulated")
    trace = tmp_path / "arm.jsonl"
    config = load_config()
    for command, extra in (("enable", {"target": None}), ("home", {"target": "j1", "direction": None})):
        options = {"bus": PoweredArm(arm.bus), "clock": arm.clock, "gripper": mock_gripper(config)}
        ns = argparse.Namespace(
            command=command, backend="i2c", config=None, bus=None, state=None, record=trace,
            backend_options=options, abort=False, no_wait=False, timeout=None, **extra,
        )  # fmt: skip
        assert getattr(commands, f"cmd_{command}")(ns) == 0
    sessions = read_trace(trace)
    assert [s.backend for s in sessions] == ["i2c", "i2c"]
    result = replay(trace)
    assert result.ok, [str(s.mismatch) for s in result.sessions]
    assert result.matched == transactions(trace)


# --------------------------------------------------------------- bad input


def _replay_error(path: Path, capsys: pytest.CaptureFixture, *options: str) -> tuple[int, str]:
    code = main(["replay", *options, str(path)])
    err = capsys.readouterr().err.strip()
    assert "\n" not in err and "Traceback" not in err
    return code, err


def test_a_missing_trace_is_one_line(tmp_path: Path, capsys: pytest.CaptureFixture) -> None:
    code, err = _replay_error(tmp_path / "none.jsonl", capsys)
    assert code == 2
    assert err.startswith("bioscara replay: error:") and "no such trace file" in err


def test_a_device_is_not_read_as_a_trace(capsys: pytest.CaptureFixture) -> None:
    # /dev/zero never ends: read whole, it grew to 24 GB before the kernel killed it.
    code, err = _replay_error(Path("/dev/zero"), capsys)
    assert code == 2
    assert err == "bioscara replay: error: /dev/zero: cannot be read (not a regular file)"


def test_a_line_that_is_not_json_names_the_line(tmp_path: Path, capsys: pytest.CaptureFixture) -> None:
    docs = lines(TRACES / "console_session.jsonl")[:8]
    path = tmp_path / "trace.jsonl"
    text = "".join(json.dumps(d) + "\n" for d in docs[:6]) + "{not json\n"
    path.write_text(text, encoding="utf-8")
    code, err = _replay_error(path, capsys)
    assert (code, err) == (2, "bioscara replay: error: trace.jsonl line 7: not JSON")


def test_a_number_beyond_pythons_digit_limit_names_the_line(
    tmp_path: Path, capsys: pytest.CaptureFixture
) -> None:
    # Seen (a hostile test): 5000 digits of episodes gave a ValueError and exit 1, as a mismatch.
    docs = lines(TRACES / "console_session.jsonl")[:8]
    path = tmp_path / "trace.jsonl"
    text = "".join(json.dumps(d) + "\n" for d in docs[:6]) + '{"type": "tx", "t": ' + "9" * 5000 + "}\n"
    path.write_text(text, encoding="utf-8")
    code, err = _replay_error(path, capsys)
    assert (code, err) == (
        2,
        "bioscara replay: error: trace.jsonl line 7: holds a number too long to be a trace's",
    )


def test_a_header_of_another_format_is_refused(tmp_path: Path, capsys: pytest.CaptureFixture) -> None:
    path = write_lines(tmp_path / "log.jsonl", [{"type": "header", "policy": "x"}])
    code, err = _replay_error(path, capsys)
    assert code == 2 and "not a bioscara bus trace" in err


@pytest.mark.parametrize(
    ("key", "value", "message"),
    [
        ("context", [1], "line 1: the header's 'context' must be an object"),
        ("t0", "x", "line 1: the header's 't0' must be a finite number of seconds, got 'x'"),
        ("t0", True, "line 1: the header's 't0' must be a finite number of seconds, got True"),
    ],
)
def test_a_hand_edited_header_is_one_line(
    tmp_path: Path, capsys: pytest.CaptureFixture, key: str, value: object, message: str
) -> None:
    docs = lines(TRACES / "console_session.jsonl")[:3]
    docs[0][key] = value
    code, err = _replay_error(write_lines(tmp_path / "edited.jsonl", docs), capsys)
    assert (code, err) == (2, f"bioscara replay: error: edited.jsonl {message}")


def test_a_trace_of_a_newer_format_version_is_refused(tmp_path: Path, capsys: pytest.CaptureFixture) -> None:
    docs = lines(TRACES / "console_session.jsonl")[:3]
    docs[0]["version"] = TRACE_VERSION + 1
    code, err = _replay_error(write_lines(tmp_path / "new.jsonl", docs), capsys)
    assert code == 2 and f"version {TRACE_VERSION + 1} is newer" in err


def test_a_monitor_session_is_refused_with_the_reason(tmp_path: Path, capsys: pytest.CaptureFixture) -> None:
    docs = lines(TRACES / "console_session.jsonl")[:3]
    docs[0]["command"] = "monitor"
    code, err = _replay_error(write_lines(tmp_path / "monitor.jsonl", docs), capsys, "--unchecked")
    assert code == 1 and "wall clock" in err


def test_a_hand_edited_episode_count_is_named(tmp_path: Path, capsys: pytest.CaptureFixture) -> None:
    # Seen (a hostile test): "TypeError: '<' not supported between instances of 'str' and 'int'".
    docs = lines(TRACES / "eval_reach_expert.jsonl")
    docs[0]["args"]["episodes"] = "abc"
    code, err = _replay_error(write_lines(tmp_path / "edited.jsonl", docs), capsys, "--unchecked")
    assert code == 1
    assert err.endswith("the trace's header gives episodes 'abc'; expected a whole number")


@pytest.mark.parametrize(
    ("key", "value"), [("dur", 1e300), ("dur", -1.0), ("t", float("inf")), ("t", float("nan"))]
)
def test_a_time_a_replay_would_wait_for_ever_on_is_refused(
    tmp_path: Path, capsys: pytest.CaptureFixture, key: str, value: float
) -> None:
    # Seen (a second hostile pass): "dur": 1e300 or Infinity, "t": 1e400 hung replay --unchecked.
    docs = lines(TRACES / "eval_reach_expert.jsonl")
    tx = next(i for i, d in enumerate(docs) if d.get("type") == "tx")
    docs[tx][key] = value
    code, err = _replay_error(write_lines(tmp_path / "edited.jsonl", docs), capsys, "--unchecked")
    assert code == 2
    assert re.search(rf"edited\.jsonl line {tx + 1}: '{key}' ", err), err


# ------------------------------------------------------------- tampering


def test_a_changed_reply_byte_is_found_and_its_line_named(
    tmp_path: Path, capsys: pytest.CaptureFixture
) -> None:
    # Seen: a changed reply byte still replayed as "2056 transactions matched": the
    # driver sends the same bytes whatever most replies say.
    docs = lines(TRACES / "eval_reach_expert.jsonl")
    changed = next(i for i, d in enumerate(docs) if d["type"] == "tx" and d["write"] == "18" and i > 100)
    reply = bytearray.fromhex(docs[changed]["read"])
    reply[2] ^= 0x01
    docs[changed]["read"] = reply.hex()
    path = write_lines(tmp_path / "tampered.jsonl", docs)
    code, err = _replay_error(path, capsys)
    assert code == 2
    where = f"tampered.jsonl line {changed + 1}"
    assert err.startswith(f"bioscara replay: error: {where}: its digest does not match its contents")
    with pytest.raises(TraceError, match=f"line {changed + 1}: its digest"):
        read_trace(path)
    assert read_trace(path, check_digests=False)  # --unchecked reads it


def test_a_removed_line_is_found_at_the_line_after_it(tmp_path: Path) -> None:
    docs = lines(TRACES / "eval_reach_expert.jsonl")
    path = write_lines(tmp_path / "gap.jsonl", docs[:50] + docs[51:])
    with pytest.raises(TraceError, match="line 51: its digest does not match its contents"):
        read_trace(path)


def test_a_hand_made_trace_needs_unchecked(tmp_path: Path, capsys: pytest.CaptureFixture) -> None:
    trace = tmp_path / "ping.jsonl"
    assert main(["ping", "--record", str(trace)]) == 0
    capsys.readouterr()
    stripped = [{k: v for k, v in d.items() if k != "digest"} for d in lines(trace)]
    hand_made = write_lines(tmp_path / "hand.jsonl", stripped)
    code, err = _replay_error(hand_made, capsys)
    assert (code, err) == (
        2,
        "bioscara replay: error: hand.jsonl line 1: no digest (a trace of format version 1, or made by "
        "hand); replay it with --unchecked if you trust it",
    )
    assert main(["replay", "--unchecked", str(hand_made)]) == 0
    assert "transactions matched" in capsys.readouterr().out


def test_read_trace_refuses_a_transaction_before_any_header(tmp_path: Path) -> None:
    docs = lines(TRACES / "console_session.jsonl")[1:3]
    with pytest.raises(TraceError, match="line 1: a transaction before the first header"):
        read_trace(write_lines(tmp_path / "t.jsonl", docs))


def test_recording_a_path_alone_writes_a_bare_header(tmp_path: Path) -> None:
    with make_backend("emulated", record=tmp_path / "t.jsonl") as backend:
        backend.joints["j1"].init()
    (session,) = read_trace(tmp_path / "t.jsonl")
    assert session.command == "" and len(session.transactions) >= 1
    assert isinstance(Recording(tmp_path / "new.jsonl", "x").args, dict)
