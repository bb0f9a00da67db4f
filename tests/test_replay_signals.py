"""A deploy stopped by SIGINT, SIGTERM or SIGHUP replays byte for byte (issue #24).

Seen: 8 of 8 deploys stopped with Ctrl-C under ``--record`` failed
``bioscara replay``: the trace did not say where the signal came, so the
replay ran on where the recording had stopped. The trace now has a
``signal`` line (or the transaction the signal cut short says so), and
the replay delivers the signal to the command's handler at that place.
"""

from __future__ import annotations

import json
import signal
from pathlib import Path
from typing import Any

import pytest
from rigs import run_deployment

from bioscara_gym.hardware.arm import Arm
from bioscara_gym.hardware.emulated_bus import EmulatedI2CBus
from bioscara_gym.replay import replay
from bioscara_gym.training.signals import Interrupted

REACH = "Bioscara-Reach-v0"


def deploy_recorded(tmp_path: Path, on_cycle: Any = None) -> tuple[Path, BaseException | None]:
    trace = tmp_path / "trace.jsonl"
    fields = {
        "backend": "emulated",
        "expert": True,
        "env": REACH,
        "episodes": 50,
        "log": tmp_path / "run.jsonl",
        "state_file": tmp_path / "gripper.json",
        "record": trace,
    }
    run = run_deployment(fields, on_cycle=on_cycle, catch=(KeyboardInterrupt,))
    return trace, run.error


def lines_of(trace: Path, kind: str) -> list[dict[str, Any]]:
    docs = [json.loads(line) for line in trace.read_text(encoding="utf-8").splitlines()]
    return [d for d in docs if d["type"] == kind]


def assert_replays_whole(trace: Path) -> None:
    result = replay(trace)
    assert result.ok, result.sessions[-1]
    assert result.matched == len(lines_of(trace, "tx"))
    assert isinstance(result.sessions[0].error, KeyboardInterrupt)


@pytest.mark.parametrize(
    "signum", [signal.SIGINT, signal.SIGTERM, signal.SIGHUP], ids=["INT", "TERM", "HUP"]
)
def test_a_signal_during_a_cycle_is_raised_again_at_the_same_cycle_boundary(
    tmp_path: Path, signum: int, sighup_default: None
) -> None:
    def interrupt(cycle: int, env: Any) -> None:
        if cycle == 30:
            signal.raise_signal(signum)  # inside the cycle: held until its end

    trace, error = deploy_recorded(tmp_path, interrupt)
    assert isinstance(error, Interrupted) and error.signum == signum
    (note,) = lines_of(trace, "signal")
    assert (note["signal"], note["at"]) == (signal.Signals(signum).name, "cycle")
    assert note["i"] < len(lines_of(trace, "tx"))  # the safe stop's transactions follow it
    assert_replays_whole(trace)


def test_a_deploy_stopped_by_sighup_replays_under_nohup_too(tmp_path: Path, sighup_default: None) -> None:
    # A reviewer's find: replayed with SIGHUP ignored, the recorded SIGHUP reached no handler and the
    # replayed deploy ran on past where the recorded one stopped (a mismatch at transaction 1740).
    def hang_up(cycle: int, env: Any) -> None:
        if cycle == 30:
            signal.raise_signal(signal.SIGHUP)

    trace, error = deploy_recorded(tmp_path, hang_up)
    assert isinstance(error, Interrupted) and error.signum == signal.SIGHUP
    signal.signal(signal.SIGHUP, signal.SIG_IGN)  # the fixture puts the default back
    assert_replays_whole(trace)
    assert signal.getsignal(signal.SIGHUP) == signal.SIG_IGN


def test_without_its_signal_line_the_interrupted_deploy_does_not_replay(tmp_path: Path) -> None:
    def interrupt(cycle: int, env: Any) -> None:
        if cycle == 30:
            signal.raise_signal(signal.SIGINT)

    trace, _ = deploy_recorded(tmp_path, interrupt)
    text = trace.read_text(encoding="utf-8").splitlines(keepends=True)
    trace.write_text("".join(line for line in text if '"type": "signal"' not in line), encoding="utf-8")
    assert not replay(trace, check_digests=False).ok


def test_a_signal_before_homing_is_raised_again_before_the_same_transaction(
    tmp_path: Path, monkeypatch: pytest.MonkeyPatch
) -> None:
    home = Arm.home

    def interrupted_home(self: Arm, *args: Any, **kwargs: Any) -> None:
        signal.raise_signal(signal.SIGINT)  # outside the control loop: raised where it lands
        home(self, *args, **kwargs)

    monkeypatch.setattr(Arm, "home", interrupted_home)
    trace, error = deploy_recorded(tmp_path)
    monkeypatch.undo()  # the replay's signal must come from the trace alone
    assert isinstance(error, Interrupted)
    (note,) = lines_of(trace, "signal")
    assert note["at"] == "once"
    assert_replays_whole(trace)


def test_a_transaction_cut_short_by_a_signal_is_recorded_so_and_replayed(
    tmp_path: Path, monkeypatch: pytest.MonkeyPatch
) -> None:
    transfer = EmulatedI2CBus.transfer
    count = {"n": 0}

    def cut(self: EmulatedI2CBus, address: int, data: bytes, read_len: int) -> bytes:
        count["n"] += 1
        if count["n"] == 40:  # during bring-up: the handler raises inside the transfer
            signal.raise_signal(signal.SIGINT)
        return transfer(self, address, data, read_len)

    monkeypatch.setattr(EmulatedI2CBus, "transfer", cut)
    trace, error = deploy_recorded(tmp_path)
    monkeypatch.undo()
    assert isinstance(error, Interrupted)
    txs = lines_of(trace, "tx")
    cut_short = [tx for tx in txs if "interrupted" in tx]
    assert [tx["i"] for tx in cut_short] == [39] and cut_short[0]["interrupted"] == "SIGINT"
    assert "read" not in cut_short[0]
    assert lines_of(trace, "signal") == []  # the transaction says it
    assert_replays_whole(trace)


def test_a_stop_that_no_signal_caused_writes_no_signal_line(tmp_path: Path) -> None:
    class NanAt3:
        """The policy returns NaN at cycle 3: a safety stop, no signal."""

        def __init__(self) -> None:
            self.calls = 0

        def __call__(self, obs: Any) -> Any:
            import numpy as np

            self.calls += 1
            return np.full(4, np.nan if self.calls > 3 else 0.0, dtype=np.float32)

    trace = tmp_path / "trace.jsonl"
    fields = {
        "backend": "emulated",
        "expert": False,
        "env": REACH,
        "episodes": 1,
        "log": tmp_path / "run.jsonl",
        "state_file": tmp_path / "gripper.json",
        "record": trace,
    }
    run = run_deployment(fields, policy=NanAt3(), metadata=None)
    assert run.summary["stop_reason"] == "nan_action"
    assert lines_of(trace, "signal") == []  # (a policy passed in-process is not replayable itself)


def test_a_second_ctrl_c_within_a_cycle_is_raised_again_at_once(tmp_path: Path) -> None:
    # The first SIGINT of a cycle waits for its end; a second raises where it lands.
    def interrupt_twice(cycle: int, env: Any) -> None:
        if cycle == 30:
            signal.raise_signal(signal.SIGINT)
            signal.raise_signal(signal.SIGINT)

    trace, error = deploy_recorded(tmp_path, interrupt_twice)
    assert isinstance(error, Interrupted)
    (note,) = lines_of(trace, "signal")
    assert note["at"] == "once"
    assert_replays_whole(trace)


def test_a_ctrl_c_before_the_arm_is_touched_replays_as_nothing_sent(
    tmp_path: Path, monkeypatch: pytest.MonkeyPatch
) -> None:
    # Seen (a Ctrl-C 0.38 s into a recorded deploy): the trace held its header
    # alone, and the replay ran the whole deploy against it.
    from bioscara_gym.training.deploy import Deployment

    check = Deployment._check

    def interrupted_check(self: Deployment, *args: Any) -> None:
        check(self, *args)
        raise KeyboardInterrupt  # Ctrl-C after the env was made, before the run

    monkeypatch.setattr(Deployment, "_check", interrupted_check)
    trace, error = deploy_recorded(tmp_path)
    monkeypatch.undo()
    assert type(error) is KeyboardInterrupt
    assert lines_of(trace, "tx") == []
    (note,) = lines_of(trace, "signal")
    assert (note["i"], note["at"]) == (0, "once")
    result = replay(trace)
    assert result.ok and result.matched == 0
    assert isinstance(result.sessions[0].error, KeyboardInterrupt)


def interrupt_the_nth_read(monkeypatch: pytest.MonkeyPatch, n: int) -> None:
    """``Arm.read`` raises KeyboardInterrupt on its ``n``-th call: a Ctrl-C between two transactions."""
    calls = {"n": 0}
    read = Arm.read

    def interrupted_read(self: Arm, *args: Any, **kwargs: Any) -> Any:
        calls["n"] += 1
        if calls["n"] == n:
            raise KeyboardInterrupt
        return read(self, *args, **kwargs)

    monkeypatch.setattr(Arm, "read", interrupted_read)


def assert_stopped_midway_and_replays(trace: Path) -> None:
    (note,) = lines_of(trace, "signal")
    assert note["at"] == "once" and 0 < note["i"] < len(lines_of(trace, "tx"))
    result = replay(trace)
    assert result.ok, result.sessions[-1]
    assert result.matched == len(lines_of(trace, "tx"))


def test_a_console_command_ctrl_ced_between_transactions_replays(
    tmp_path: Path, monkeypatch: pytest.MonkeyPatch, capsys: pytest.CaptureFixture[str]
) -> None:
    # `bioscara home` Ctrl-C'd while it waits on a homing: the console disables
    # the arm (its on-error transition); the trace says where the signal came.
    from bioscara_gym.cli import main

    trace, state = tmp_path / "home.jsonl", tmp_path / "state.json"
    assert main(["enable", "--backend", "emulated", "--state", str(state)]) == 0
    interrupt_the_nth_read(monkeypatch, 20)
    assert main(["home", "--backend", "emulated", "--state", str(state), "--record", str(trace)]) == 130
    monkeypatch.undo()
    capsys.readouterr()
    assert_stopped_midway_and_replays(trace)


def eval_ctrl_ced(
    tmp_path: Path, monkeypatch: pytest.MonkeyPatch, capsys: pytest.CaptureFixture[str]
) -> Path:
    """The trace of ``bioscara eval --expert --backend emulated`` Ctrl-C'd at its 40th read."""
    from bioscara_gym.cli import main

    trace = tmp_path / "eval.jsonl"
    interrupt_the_nth_read(monkeypatch, 40)
    argv = ["eval", "--expert", "--env", REACH, "--backend", "emulated", "--episodes", "2"]
    assert main([*argv, "--record", str(trace)]) == 130
    monkeypatch.undo()
    capsys.readouterr()
    return trace


def test_an_evaluation_ctrl_ced_mid_episode_replays(
    tmp_path: Path, monkeypatch: pytest.MonkeyPatch, capsys: pytest.CaptureFixture[str]
) -> None:
    # `bioscara eval --expert --backend emulated --record`: the env's shutdown
    # after the Ctrl-C sends the arm's disable; the trace says where it came.
    assert_stopped_midway_and_replays(eval_ctrl_ced(tmp_path, monkeypatch, capsys))


@pytest.mark.parametrize(
    ("signum", "code", "line"),
    [
        (signal.SIGINT, 130, "bioscara replay: interrupted"),
        (signal.SIGTERM, 143, "bioscara replay: interrupted by SIGTERM"),
    ],
    ids=["INT", "TERM"],
)
def test_a_replay_stopped_by_its_own_signal_says_interrupted_not_mismatch(
    monkeypatch: pytest.MonkeyPatch, capsys: pytest.CaptureFixture[str], signum: int, code: int, line: str
) -> None:
    # Seen (a hostile test): Ctrl-C to `bioscara replay` of a deploy: the deploy's safe stop sent
    # what the trace did not have, reported as "mismatch at transaction 111", exit 1.
    import os

    from bioscara_gym.cli import main
    from bioscara_gym.hardware.recording import ReplayBus

    transfer = ReplayBus.transfer
    count = [0]

    def transfer_then_signal(self: ReplayBus, address: int, data: bytes, read_len: int) -> bytes:
        count[0] += 1
        if count[0] == 400:  # in the deploy's control loop: its guard takes the signal
            os.kill(os.getpid(), signum)
        return transfer(self, address, data, read_len)

    monkeypatch.setattr(ReplayBus, "transfer", transfer_then_signal)
    trace = Path(__file__).parent / "traces" / "deploy_reach_expert.jsonl"
    assert main(["replay", str(trace)]) == code
    assert capsys.readouterr().err.strip() == line
    assert count[0] > 400  # the command went on to its safe stop: the interrupt came after it


def test_a_replayed_signal_leaves_the_replays_own_handlers_as_they_were(
    tmp_path: Path, monkeypatch: pytest.MonkeyPatch, capsys: pytest.CaptureFixture[str]
) -> None:
    # Seen (a review): the recorded Ctrl-C of an eval called the CLI's handler, which noted every
    # later signal: a real Ctrl-C during the next session of the replay was ignored.
    from bioscara_gym.cli import _signals_as_interrupt

    trace = eval_ctrl_ced(tmp_path, monkeypatch, capsys)
    with _signals_as_interrupt():
        before = signal.getsignal(signal.SIGINT)
        assert replay(trace).ok
        assert signal.getsignal(signal.SIGINT) is before
