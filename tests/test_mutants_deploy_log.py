"""Tests that kill mutants mutmut found surviving in ``training/deploy_log.py`` (docs/mutation.md).

Unit level, no arm: a :class:`RunLog` in a temporary folder (the disk filled
at ``os.write``, the clock of its fsyncs set by the test), :class:`BusStats`
over driver counters the test counts up, :class:`CycleTiming` fed periods,
:func:`print_summary` and :func:`disabled_line` of summary records written
here. Expected values are literals from deploy_log.py's and deploy.py's
docstrings (the run log's records, the summary's fields, the tolerance of
10 % over the nominal period, an fsync at least every second) and
:class:`~bioscara_gym.hardware.stats.CommStats`' counters.
"""

from __future__ import annotations

import errno
import io
import json
import os
import stat
from pathlib import Path
from types import SimpleNamespace
from typing import Any

import numpy as np
import pytest
from rich.console import Console
from rigs import FillingDisk, read_log

from bioscara_gym.hardware.clock import ManualClock
from bioscara_gym.hardware.config import load_config
from bioscara_gym.hardware.recording import Recording, RecordingBus
from bioscara_gym.hardware.stats import CommStats
from bioscara_gym.training import deploy_log
from bioscara_gym.training.deploy_log import (
    BusStats,
    CycleTiming,
    RunLog,
    _jsonable,
    describe_record,
    disabled_line,
    print_summary,
    trace_error,
)
from bioscara_gym.training.deploy_safety import SafetyStop, StopReason

ENOSPC = os.strerror(errno.ENOSPC)  # "No space left on device"


# ------------------------------------------------------------------ JSON
def test_records_are_strict_json_with_non_finite_floats_as_strings() -> None:
    record = {
        1: np.array([1.5, np.inf], dtype=np.float32),
        "t": (np.float64(-np.inf), float("nan")),
        "n": [np.int64(3), 4],
        "ok": [True, np.bool_(False)],
        "none": None,
        "s": "x",
        "path": Path("/a/b"),
    }
    assert _jsonable(record) == {
        "1": [1.5, "inf"],
        "t": ["-inf", "nan"],
        "n": [3, 4],
        "ok": [True, False],
        "none": None,
        "s": "x",
        "path": "/a/b",
    }
    # Types as JSON writes them: a bool stays true/false (not 1/0), an int has no ".0".
    assert (
        json.dumps(_jsonable([np.bool_(True), True, np.int32(2), np.float32(0.5)])) == "[true, true, 2, 0.5]"
    )
    assert type(_jsonable(np.int64(7))) is int and type(_jsonable(np.float32(2.0))) is float


# ------------------------------------------------------------------ records lost
@pytest.mark.parametrize(
    ("record", "words"),
    [
        ({"type": "cycle", "cycle": 57, "episode": 2, "phase": "x"}, "cycle 57"),
        ({"type": "episode", "episode": 3}, "episode 3"),
        ({"type": "summary", "episodes": 3}, "summary"),
        ({"type": "phase", "phase": "home", "detail": "d"}, "phase home"),
        ({"type": "bus", "phase": "reset", "episode": 2}, "bus 2"),
        ({"type": "bus", "phase": "deactivate"}, "bus deactivate"),
        ({"type": "stop", "reason": "stall"}, "stop"),
        ({"type": "cycle"}, "cycle"),
        ({"cycle": 5}, "record"),
    ],
)
def test_a_record_lost_is_named_in_a_few_words(record: dict[str, Any], words: str) -> None:
    # deploy_log.py: "cycle 57", "episode 3", "summary"; a bus record by its episode, else its phase.
    assert describe_record(record) == words


# ------------------------------------------------------------------ the bus trace
def test_a_trace_error_names_why_and_from_which_transaction(tmp_path: Path) -> None:
    assert trace_error(SimpleNamespace()) is None  # a backend without a bus (mock)
    assert trace_error(SimpleNamespace(bus=SimpleNamespace())) is None  # a bus that records nothing
    clock = ManualClock(0.0)
    bus = RecordingBus(
        SimpleNamespace(close=lambda: None),
        Recording(tmp_path / "t.jsonl", "deploy"),
        clock,
        "mock",
        load_config(),
    )
    try:
        assert trace_error(SimpleNamespace(bus=bus)) is None  # recording, and every transaction recorded
        bus.error = OSError(errno.ENOSPC, "cannot write the bus trace t.jsonl: No space left on device")
        bus.unrecorded_from = 498
        assert trace_error(SimpleNamespace(bus=bus)) == (
            "cannot write the bus trace t.jsonl: No space left on device; "
            "transactions from 498 on were not recorded"
        )
    finally:
        bus.close()


# ------------------------------------------------------------------ the run log
def test_the_run_log_replaces_a_file_with_one_compact_line_per_record(tmp_path: Path) -> None:
    path = tmp_path / "new" / "folder" / "run.jsonl"  # parents made
    path.parent.mkdir(parents=True)
    path.write_text("an older run's log, much longer than the new one\n" * 10)
    log = RunLog(path)
    log.write({"type": "cycle", "cycle": 0, "q": {"j1": 0.5}})
    log.write({"type": "episode", "success": True})
    assert path.read_bytes() == (
        b'{"type":"cycle","cycle":0,"q":{"j1":0.5}}\n{"type":"episode","success":true}\n'
    )
    assert log.lines == 2 and log.error is None and log.dropped == 0 and log.lost == []
    log.close()


def test_the_run_log_makes_its_folders_and_a_file_others_may_read(tmp_path: Path) -> None:
    path = tmp_path / "a" / "b" / "run.jsonl"
    old_umask = os.umask(0o022)
    try:
        log = RunLog(path)
    finally:
        os.umask(old_umask)
    log.write({"type": "header"})
    log.close()
    assert read_log(path) == [{"type": "header"}]
    assert stat.S_IMODE(path.stat().st_mode) == 0o644  # rw-r--r--


def test_the_run_log_is_fsynced_once_a_second_has_passed_since_the_last(
    tmp_path: Path, monkeypatch: pytest.MonkeyPatch
) -> None:
    now = [100.0]
    synced: list[float] = []
    real_fsync = os.fsync
    monkeypatch.setattr(deploy_log, "time", SimpleNamespace(monotonic=lambda: now[0]))

    def fsync(fd: int) -> None:
        synced.append(now[0])
        real_fsync(fd)

    monkeypatch.setattr(os, "fsync", fsync)
    log = RunLog(tmp_path / "run.jsonl")
    for t in (100.5, 100.999, 101.0, 101.5, 101.999, 102.0, 104.5, 105.0):
        now[0] = t
        log.write({"t": t})
    assert synced == [101.0, 102.0, 104.5]  # 1 s (FSYNC_INTERVAL_S) or more after the previous
    now[0] = 104.6
    log.close()
    assert synced == [101.0, 102.0, 104.5, 104.6]  # and on close


def test_a_record_the_disk_cannot_take_stops_the_run_and_is_cut_off_again(
    tmp_path: Path, monkeypatch: pytest.MonkeyPatch
) -> None:
    disk = FillingDisk(full_for=1)  # one write refused, then space returns
    monkeypatch.setattr(deploy_log, "_os_write", disk)
    path = tmp_path / "run.jsonl"
    log = RunLog(path)
    disk.fd = log._fd
    log.write({"type": "cycle", "cycle": 4})
    disk.full = True
    with pytest.raises(SafetyStop) as caught:
        log.write({"type": "cycle", "cycle": 5, "action": [0.25] * 4})
    assert caught.value.reason is StopReason.LOG_ERROR
    assert str(caught.value) == f"cannot write the run log {path}: {ENOSPC}"
    assert caught.value.__cause__ is log.error and log.error.errno == errno.ENOSPC
    assert (log.dropped, log.lost, log.lines) == (1, ["cycle 5"], 1)
    log.write({"type": "stop", "reason": "log_error"})  # space is back: written after the last whole line
    log.close()
    assert path.read_bytes() == b'{"type":"cycle","cycle":4}\n{"type":"stop","reason":"log_error"}\n'
    assert log.lines == 2


def test_after_the_first_failed_record_the_others_are_only_counted_and_named(
    tmp_path: Path, monkeypatch: pytest.MonkeyPatch
) -> None:
    disk = FillingDisk(full_for=None)  # stays full
    monkeypatch.setattr(deploy_log, "_os_write", disk)
    path = tmp_path / "run.jsonl"
    log = RunLog(path)
    disk.fd = log._fd
    log.write({"type": "header"})
    disk.full = True
    with pytest.raises(SafetyStop):
        log.write({"type": "cycle", "cycle": 5})
    first = log.error
    log.write({"type": "stop"})  # no second SafetyStop
    log.write({"type": "summary"})
    assert log.error is first
    assert (log.dropped, log.lost) == (3, ["cycle 5", "stop", "summary"])
    log.close()
    assert read_log(path) == [{"type": "header"}]  # every line whole


def test_an_error_without_strerror_is_named_by_its_text(
    tmp_path: Path, monkeypatch: pytest.MonkeyPatch
) -> None:
    def broken(fd: int, data: Any) -> int:
        raise OSError("the device went away")

    log = RunLog(tmp_path / "run.jsonl")
    monkeypatch.setattr(deploy_log, "_os_write", broken)
    with pytest.raises(SafetyStop) as caught:
        log.write({"type": "header"})
    assert str(caught.value) == f"cannot write the run log {tmp_path / 'run.jsonl'}: the device went away"
    log.close()


def test_a_closed_run_log_refuses_every_record_as_a_stop(tmp_path: Path) -> None:
    log = RunLog(tmp_path / "run.jsonl")
    log.close()
    log.close()  # a second close does nothing
    with pytest.raises(SafetyStop) as caught:
        log.write({"type": "summary"})
    assert str(caught.value) == f"cannot write the run log {tmp_path / 'run.jsonl'}: the run log is closed"
    assert log.error.errno == errno.EBADF
    assert (log.dropped, log.lost, log.lines) == (1, ["summary"], 0)


def test_a_first_record_the_disk_cannot_take_stops_the_run_even_if_it_cannot_be_cut_off(
    tmp_path: Path, monkeypatch: pytest.MonkeyPatch
) -> None:
    # RunLog.write: "the first record that cannot be written" stops the run. Found through
    # _cut_back's mutants, which no test told apart: when ftruncate failed too, its error
    # became the log's error first, and the write returned as for a later record, so the
    # run went on, unrecorded.
    disk = FillingDisk(full_for=None)
    monkeypatch.setattr(deploy_log, "_os_write", disk)
    log = RunLog(tmp_path / "run.jsonl")
    disk.fd = log._fd

    def refuse(fd: int, length: int) -> None:
        raise OSError(errno.EIO, os.strerror(errno.EIO))

    monkeypatch.setattr(os, "ftruncate", refuse)
    disk.full = True
    with pytest.raises(SafetyStop) as caught:
        log.write({"type": "cycle", "cycle": 0})
    assert caught.value.reason is StopReason.LOG_ERROR
    assert str(caught.value) == f"cannot write the run log {tmp_path / 'run.jsonl'}: {ENOSPC}"
    assert log.error.errno == errno.ENOSPC and (log.dropped, log.lost) == (1, ["cycle 0"])
    assert log.torn
    log.close()


def test_a_failed_fsync_on_close_is_the_logs_error_and_the_file_is_closed(
    tmp_path: Path, monkeypatch: pytest.MonkeyPatch
) -> None:
    log = RunLog(tmp_path / "run.jsonl")
    fd = log._fd

    def fail(fd: int) -> None:
        raise OSError(errno.EIO, os.strerror(errno.EIO))

    monkeypatch.setattr(os, "fsync", fail)
    log.close()
    assert log.error.errno == errno.EIO
    with pytest.raises(OSError) as closed:
        os.fstat(fd)
    assert closed.value.errno == errno.EBADF


def test_a_failed_fsync_on_close_keeps_the_first_error(
    tmp_path: Path, monkeypatch: pytest.MonkeyPatch
) -> None:
    log = RunLog(tmp_path / "run.jsonl")
    first = OSError(errno.ENOSPC, ENOSPC)
    log.error = first

    def fail(fd: int) -> None:
        raise OSError(errno.EIO, os.strerror(errno.EIO))

    monkeypatch.setattr(os, "fsync", fail)
    log.close()
    assert log.error is first


# ------------------------------------------------------------------ bus statistics
def counted(
    retries: int = 0, bus: int = 0, malformed: int = 0, implausible: int = 0, ok: int = 0
) -> CommStats:
    stats = CommStats()
    add(stats, retries, bus, malformed, implausible, ok)
    return stats


def add(
    stats: CommStats, retries: int = 0, bus: int = 0, malformed: int = 0, implausible: int = 0, ok: int = 0
) -> None:
    """Count attempts as the driver does: failed ones by kind, retries, successful ones."""
    for kind, n in (("bus", bus), ("malformed", malformed), ("implausible", implausible)):
        for _ in range(n):
            stats.record(False, kind)
    for _ in range(retries):
        stats.record(True, retry=True)
    for _ in range(ok):
        stats.record(True)


def test_bus_statistics_start_from_the_counters_present_totals() -> None:
    j1, j2 = counted(retries=4, bus=3, ok=10), counted(malformed=2)
    bus = BusStats({"j1": j1, "j2": j2})
    assert bus.cycle() == {}
    assert bus.summary() == {
        "j1": {"transactions": 0, "retries": 0, "errors": {"bus": 0, "malformed": 0, "implausible": 0}},
        "j2": {"transactions": 0, "retries": 0, "errors": {"bus": 0, "malformed": 0, "implausible": 0}},
    }


def test_a_cycle_names_only_the_joints_and_kinds_that_had_retries_or_errors() -> None:
    j1, j2, j3 = counted(ok=5), counted(), counted()
    bus = BusStats({"j1": j1, "j2": j2, "j3": j3})
    add(j1, retries=1, bus=1, ok=7)  # transactions alone are no change
    add(j2, ok=3)
    add(j3, malformed=2, implausible=1)
    assert bus.cycle() == {"j1": {"retries": 1, "bus_errors": 1}, "j3": {"malformed": 2, "implausible": 1}}
    assert bus.cycle() == {}  # since the previous call
    add(j2, implausible=1)
    assert bus.cycle() == {"j2": {"implausible": 1}}


def test_the_bus_summary_counts_each_joint_since_the_start() -> None:
    j1, j2 = counted(retries=9, ok=9), counted()
    bus = BusStats({"j1": j1, "j2": j2})
    add(j1, retries=2, bus=3, malformed=1, implausible=4, ok=10)
    bus.cycle()  # a cycle's reading does not reset the run's
    add(j2, ok=1)
    assert bus.summary() == {
        "j1": {"transactions": 20, "retries": 2, "errors": {"bus": 3, "malformed": 1, "implausible": 4}},
        "j2": {"transactions": 1, "retries": 0, "errors": {"bus": 0, "malformed": 0, "implausible": 0}},
    }
    assert BusStats({}).summary() == {} and BusStats({}).cycle() == {}  # mock: no bus


# ------------------------------------------------------------------ cycle timing
def test_a_cycle_overruns_past_10_percent_over_the_nominal_period_on_the_backends_clock() -> None:
    timing = CycleTiming(nominal_s=0.5)
    assert timing.add(0.55, None, 0.001, 0.01, paced_wall=False) is False  # exactly 10 % over: not yet
    assert timing.add(0.56, None, 0.001, 0.01, paced_wall=False) is True
    assert timing.add(None, 9.0, 0.001, 0.01, paced_wall=False) is False  # the wall clock does not pace it
    assert timing.add(None, None, 0.001, 0.01, paced_wall=True) is False  # an episode's first cycle
    assert timing.overruns == 1


def test_where_the_wall_clock_paces_the_loop_its_period_overruns_too() -> None:
    timing = CycleTiming(nominal_s=0.5)
    assert timing.add(0.5, 0.55, 0.0, 0.0, paced_wall=True) is False
    assert timing.add(0.5, 0.56, 0.0, 0.0, paced_wall=True) is True
    assert timing.add(0.56, 0.56, 0.0, 0.0, paced_wall=True) is True  # counted once
    assert timing.add(None, 0.6, 0.0, 0.0, paced_wall=True) is True
    assert timing.overruns == 3


def test_the_timing_summary_has_mean_max_and_jitter_of_each_series() -> None:
    timing = CycleTiming(nominal_s=0.04)
    timing.add(None, None, 0.002, 0.010, paced_wall=False)  # the first cycle: no periods
    timing.add(0.04, 0.03, 0.004, 0.030, paced_wall=False)
    timing.add(0.05, 0.05, 0.003, 0.020, paced_wall=False)
    assert timing.periods == [0.04, 0.05] and timing.wall_periods == [0.03, 0.05]
    assert timing.work == [0.002, 0.004, 0.003] and timing.silences == [0.010, 0.030, 0.020]
    assert timing.summary() == pytest.approx(
        {
            "rate_hz": 25.0,
            "period_mean_s": 0.045,
            "period_max_s": 0.05,
            "period_jitter_s": 0.005,
            "wall_period_mean_s": 0.04,
            "wall_period_max_s": 0.05,
            "wall_period_jitter_s": 0.01,
            "work_mean_s": 0.003,
            "work_max_s": 0.004,
            "max_silence_s": 0.030,
            "overruns": 1,
        }
    )


def test_the_timing_summary_of_no_cycle_has_no_statistics() -> None:
    assert CycleTiming(nominal_s=0.05).summary() == {
        "rate_hz": 20.0,
        "period_mean_s": None,
        "period_max_s": None,
        "period_jitter_s": None,
        "wall_period_mean_s": None,
        "wall_period_max_s": None,
        "wall_period_jitter_s": None,
        "work_mean_s": None,
        "work_max_s": None,
        "max_silence_s": None,
        "overruns": 0,
    }


# ------------------------------------------------------------------ the printed summary
def summary_record(**changes: Any) -> dict[str, Any]:
    """A summary record (deploy.py's fields) of a two-joint run."""
    s: dict[str, Any] = {
        "episodes": 3,
        "successes": 2,
        "cycles": 150,
        "success_rate": 2 / 3,
        "rate_hz": 25.0,
        "period_mean_s": 0.04,
        "period_max_s": 0.0415,
        "period_jitter_s": 0.00025,
        "wall_period_mean_s": 0.012,
        "wall_period_jitter_s": 0.003,
        "work_mean_s": 0.0105,
        "work_max_s": 0.02,
        "max_silence_s": 0.0315,
        "overruns": 4,
        "bus": {
            "j1": {"transactions": 600, "retries": 3, "errors": {"bus": 2, "malformed": 1, "implausible": 0}},
            "j2": {"transactions": 598, "retries": 0, "errors": {"bus": 0, "malformed": 0, "implausible": 0}},
        },
        "stop_reason": "completed",
        "message": "completed",
        "final_state": {"j1": {"flag_names": "NOT_ENABLED"}, "j2": {"flag_names": "NOT_ENABLED|HOMED"}},
        "trace_error": None,
    }
    s.update(changes)
    return s


def printed(s: dict[str, Any], log: Any) -> tuple[list[str], dict[str, str]]:
    """The lines :func:`print_summary` prints, and its table as metric -> value."""
    out = io.StringIO()
    print_summary(Console(file=out, width=200), s, log)
    lines = out.getvalue().splitlines()
    (header,) = [line for line in lines if line.startswith("┃")]
    assert [c.strip() for c in header.split("┃")[1:-1]] == ["metric", "value"]
    rows = {}
    for line in lines:
        cells = line.split("│")[1:-1]
        if len(cells) == 2:
            metric, value = cells
            assert value.endswith(value.strip() + " "), f"not right-aligned: {line}"
            rows[metric.strip()] = value.strip()
    return lines, rows


def test_the_summary_table_shows_each_figure_in_its_unit(tmp_path: Path) -> None:
    log = SimpleNamespace(path=tmp_path / "run.jsonl", error=None, lost=[], dropped=0)
    lines, rows = printed(summary_record(), log)
    assert lines[0].strip() == "deploy summary (completed)"
    assert rows == {
        "episodes (successes)": "2/3 (67%)",
        "cycles": "150",
        "rate": "25 Hz",
        "period mean / max (backend clock)": "40.00 ms / 41.50 ms",
        "jitter (std, backend clock)": "0.25 ms",
        "host loop mean / jitter (wall)": "12.00 ms / 3.00 ms",
        "host work per cycle mean / max": "10.50 ms / 20.00 ms",
        "longest joint silence": "31.50 ms",
        "overruns": "4",
        "bus j1: transactions / retries / errors": "600 / 3 / bus 2, malformed 1, implausible 0",
        "bus j2: transactions / retries / errors": "598 / 0 / bus 0, malformed 0, implausible 0",
        "stop": "completed",
        "final flags": "j1 NOT_ENABLED, j2 NOT_ENABLED|HOMED",
    }
    assert lines[-1] == f"log        {tmp_path / 'run.jsonl'}"
    assert lines[-2].startswith("└")  # nothing after the log's line: it is complete, the trace too


def test_the_summary_of_a_run_stopped_before_its_loop_shows_dashes(tmp_path: Path) -> None:
    s = summary_record(
        episodes=0,
        successes=0,
        cycles=0,
        success_rate=None,
        rate_hz=12.5,
        period_mean_s=None,
        period_max_s=None,
        period_jitter_s=None,
        wall_period_mean_s=None,
        wall_period_jitter_s=None,
        work_mean_s=None,
        work_max_s=None,
        max_silence_s=None,
        overruns=0,
        bus={},
        stop_reason="stall",
        message="j2 stalled [at 0.5 rad]",
    )
    lines, rows = printed(
        s, SimpleNamespace(path=tmp_path / "r.jsonl", error=None, lost=[], dropped=0, torn=False)
    )
    assert lines[0].strip() == "deploy summary (stall)"
    assert rows == {
        "episodes (successes)": "0/0",
        "cycles": "0",
        "rate": "12.5 Hz",
        "period mean / max (backend clock)": "- / -",
        "jitter (std, backend clock)": "-",
        "host loop mean / jitter (wall)": "- / -",
        "host work per cycle mean / max": "- / -",
        "longest joint silence": "-",
        "overruns": "0",
        "stop": "j2 stalled [at 0.5 rad]",  # brackets are text, not markup
        "final flags": "j1 NOT_ENABLED, j2 NOT_ENABLED|HOMED",
    }


def test_an_incomplete_log_and_trace_are_named_after_the_table(tmp_path: Path) -> None:
    path = tmp_path / "[run].jsonl"
    log = SimpleNamespace(
        path=path, error=OSError(errno.ENOSPC, ENOSPC), lost=["cycle 5", "summary"], dropped=2, torn=False
    )
    lines, _ = printed(summary_record(trace_error="cannot write the bus trace [t]: full"), log)
    assert lines[-3:] == [
        f"log        {path}",
        f"log incomplete: 2 record(s) not written: cycle 5, summary ({ENOSPC}); "
        "every line in it is a whole record",
        "trace      incomplete: cannot write the bus trace [t]: full",
    ]
    log = SimpleNamespace(path=path, error=OSError("closed [early]"), lost=[], dropped=0, torn=False)
    lines, _ = printed(summary_record(), log)
    assert (
        lines[-1]
        == "log incomplete: 0 record(s) not written (closed [early]); every line in it is a whole record"
    )
    # The failed record's part could not be cut off again: the summary does not claim whole lines.
    log.torn = True
    lines, _ = printed(summary_record(), log)
    assert lines[-1] == (
        "log incomplete: 0 record(s) not written (closed [early]); "
        "its last line may be torn (cutting the failed record off failed too)"
    )


# ------------------------------------------------------------------ the disabled line
def test_a_disabled_arm_names_every_joint_that_acknowledged() -> None:
    s = {"final_state": {"j1": {}, "j2": {}, "j3": {}}, "arm_disabled": True}
    assert disabled_line(s) == (
        "arm disabled: j1, j2, j3 acknowledged their disable (currents 0); arm shut down, bus closed"
    )


def test_joints_not_confirmed_disabled_are_named_with_those_that_were() -> None:
    s = {
        "final_state": {"j1": {}, "j2": {}, "j3": {}, "j4": {}},
        "arm_disabled": False,
        "not_confirmed_disabled": ["j2", "j4"],
        "not_confirmed_warnings": [
            "j2: no answer, still powered as far as we know: cut the power",
            "j4: [error] EIO",
        ],
    }
    assert disabled_line(s) == (
        "[red]arm NOT confirmed disabled[/red]: "
        "j2: no answer, still powered as far as we know: cut the power; "
        "j4: \\[error] EIO; confirmed disabled: j1, j3"
    )
    s["not_confirmed_disabled"] = ["j1", "j2", "j3", "j4"]
    s["not_confirmed_warnings"] = ["j1: no answer"]
    assert (
        disabled_line(s)
        == "[red]arm NOT confirmed disabled[/red]: j1: no answer; no joint confirmed disabled"
    )
