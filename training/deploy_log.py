"""What a deployment records: the JSON Lines run log, the loop's timing, the bus's errors.

:class:`RunLog` writes one line per record straight to the file (no buffer),
so the log is complete after Ctrl-C; a record it cannot write (disk full)
stops the run, the part of it that reached the disk is cut off again (every
line in the file stays a whole JSON record), the stop and summary records are
then written where they still can be, and the records lost are named.
:class:`CycleTiming` gathers period, jitter, host work and overruns for the
summary, :class:`BusStats` each joint's transactions, retries and errors, and
:func:`print_summary` shows the summary record to the operator.
"""

from __future__ import annotations

import errno
import json
import math
import os
import time
from dataclasses import dataclass, field
from pathlib import Path
from typing import Any

import numpy as np
from rich.console import Console
from rich.markup import escape
from rich.table import Table

from bioscara_gym.fsutil import read_first_line
from bioscara_gym.hardware.stats import CommStats
from bioscara_gym.training.deploy_safety import SafetyStop, StopReason

#: fsync the log at least this often (every line is flushed), s.
FSYNC_INTERVAL_S = 1.0
#: A cycle is an overrun when its period exceeds the nominal one by this fraction.
OVERRUN_TOLERANCE = 0.1


def _jsonable(value: Any) -> Any:
    """Numbers, arrays and dicts as strict JSON (non-finite floats as strings)."""
    if isinstance(value, dict):
        return {str(k): _jsonable(v) for k, v in value.items()}
    if isinstance(value, list | tuple | np.ndarray):
        return [_jsonable(v) for v in value]
    if isinstance(value, bool | np.bool_):
        return bool(value)
    if isinstance(value, int | np.integer):
        return int(value)
    if isinstance(value, float | np.floating):
        f = float(value)
        return f if math.isfinite(f) else str(f)
    if value is None or isinstance(value, str):
        return value
    return str(value)


#: ``os.write``, looked up here so a test can fill the disk at the OS boundary.
_os_write = os.write
#: Longest first line read to tell a run log (its header is a few hundred bytes).
_MAX_HEADER_BYTES = 64 * 1024


def is_deploy_log(path: Path) -> bool:
    """Whether ``path`` starts with a run log's header (what :class:`RunLog` may replace).

    A bus trace's header (``format``) is no run log's.

    Raises:
        OSError: It cannot be read.
    """
    try:
        doc = json.loads(read_first_line(path, _MAX_HEADER_BYTES))
    except (ValueError, RecursionError):
        return False
    return (
        isinstance(doc, dict)
        and doc.get("type") == "header"
        and {"policy", "env_id", "backend"} <= doc.keys()
        and "format" not in doc
    )


def trace_error(backend: Any) -> str | None:
    """Why the backend's bus trace (``--record``) stops short, if it does."""
    from bioscara_gym.hardware.recording import recording_bus

    bus = recording_bus(backend)
    if bus is None or bus.error is None:
        return None
    return f"{bus.error.strerror}; transactions from {bus.unrecorded_from} on were not recorded"


def note_signal(backend: Any, stopped_by: BaseException) -> None:
    """:func:`~bioscara_gym.hardware.recording.note_signal`, imported when a run stops."""
    from bioscara_gym.hardware.recording import note_signal as note

    note(backend, stopped_by)


def describe_record(record: dict[str, Any]) -> str:
    """A record in a few words, for the list of records lost: ``cycle 57``, ``episode 3``, ``summary``."""
    kind = str(record.get("type", "record"))
    for key in ("cycle", "episode", "phase"):
        if kind in (key, "bus") and key in record:
            return f"{kind} {record[key]}"
    return kind


class RunLog:
    """JSON Lines, one unbuffered ``write`` per record, fsync'd every second and on close.

    Every line in the file is a whole record: a write the disk takes only in
    part is cut off again (``ftruncate`` to the last whole line).

    Args:
        path: The log file (parents created; an existing file is replaced:
            ``bioscara deploy`` lets it replace only an earlier run log or an
            empty file, :func:`is_deploy_log`).

    Attributes:
        error: The first write that failed, if one did.
        dropped: Records not written because of it.
        lost: Those records, each in a few words (:func:`describe_record`).
        torn: A part of a failed record could not be cut off again (its last line may be torn).
    """

    def __init__(self, path: Path) -> None:
        """Open ``path`` for writing."""
        self.path = Path(path)
        self.path.parent.mkdir(parents=True, exist_ok=True)
        self._fd: int | None = os.open(self.path, os.O_WRONLY | os.O_CREAT | os.O_TRUNC, 0o644)
        self._size = 0  # bytes of whole records in the file
        self._synced = time.monotonic()
        self.lines = 0
        self.error: OSError | None = None
        self.dropped = 0
        self.lost: list[str] = []
        self.torn = False

    def write(self, record: dict[str, Any]) -> None:
        """Append one record as a line.

        Raises:
            SafetyStop: The first record that cannot be written (``LOG_ERROR``):
                a run that can no longer be recorded is stopped. Later records
                (the stop, the summary) are tried and, if they fail too, counted
                in :attr:`dropped` and named in :attr:`lost`.
        """
        data = (json.dumps(_jsonable(record), allow_nan=False, separators=(",", ":")) + "\n").encode()
        try:
            if self._fd is None:
                raise OSError(errno.EBADF, "the run log is closed")
            view = memoryview(data)
            while view:
                view = view[_os_write(self._fd, view) :]
            now = time.monotonic()
            if now - self._synced >= FSYNC_INTERVAL_S:
                os.fsync(self._fd)
                self._synced = now
        except OSError as e:
            first = self.error is None  # before the cut, which may fail too
            self._cut_back()
            self.dropped += 1
            self.lost.append(describe_record(record))
            if not first:
                return
            self.error = e
            raise SafetyStop(
                StopReason.LOG_ERROR, f"cannot write the run log {self.path}: {e.strerror or e}"
            ) from e
        self._size += len(data)
        self.lines += 1

    def _cut_back(self) -> None:
        """Remove the part of a record that reached the file before the write failed."""
        if self._fd is None:
            return
        try:
            os.ftruncate(self._fd, self._size)
            os.lseek(self._fd, self._size, os.SEEK_SET)
        except OSError:
            self.torn = True  # the summary says so instead of "every line is whole"

    def close(self) -> None:
        """Fsync and close (after a failed write, as far as the file system lets it)."""
        if self._fd is None:
            return
        fd, self._fd = self._fd, None
        try:
            os.fsync(fd)
        except OSError as e:
            self.error = self.error or e
        finally:
            os.close(fd)


class BusStats:
    """Each joint's transactions, retries and errors by kind, per cycle and for the run.

    Reads the drivers' :class:`~bioscara_gym.hardware.stats.CommStats` (the
    same counters ``bioscara status`` shows) as differences of their totals,
    so a retry the driver recovered from still shows in the cycle it happened.

    Args:
        stats: Joint name to its driver's counters (``Backend.comm_stats()``;
            empty on ``mock``, which has no bus).
    """

    #: Counters reported, from the ``total_`` fields of ``CommStats``.
    FIELDS = ("transactions", "retries", "bus_errors", "malformed", "implausible")

    def __init__(self, stats: dict[str, CommStats]) -> None:
        """Start counting from the counters' present totals."""
        self._stats = stats
        self._start = self._totals()
        self._last = self._start

    def _totals(self) -> dict[str, dict[str, int]]:
        return {n: {f: getattr(s, f"total_{f}") for f in self.FIELDS} for n, s in self._stats.items()}

    def cycle(self) -> dict[str, dict[str, int]]:
        """The retries and errors since the previous call, for the joints that had any."""
        now = self._totals()
        changes = {}
        for name, counts in now.items():
            delta = {f: counts[f] - self._last[name][f] for f in self.FIELDS[1:]}
            if any(delta.values()):
                changes[name] = {k: v for k, v in delta.items() if v}
        self._last = now
        return changes

    def summary(self) -> dict[str, dict[str, Any]]:
        """Per joint since the start: transactions, retries and errors by kind."""
        now = self._totals()
        out = {}
        for name, counts in now.items():
            d = {f: counts[f] - self._start[name][f] for f in self.FIELDS}
            errors = {"bus": d["bus_errors"], "malformed": d["malformed"], "implausible": d["implausible"]}
            out[name] = {"transactions": d["transactions"], "retries": d["retries"], "errors": errors}
        return out


@dataclass
class CycleTiming:
    """Period, jitter and overruns of the control loop.

    ``period`` is on the backend's clock (simulated on ``mock``/``emulated``,
    the wall clock on ``i2c``), ``wall_period`` on the host's wall clock,
    ``work`` the host time the policy and the step took. The first cycle of
    each episode has no period (it follows a reset).
    """

    nominal_s: float
    periods: list[float] = field(default_factory=list)
    wall_periods: list[float] = field(default_factory=list)
    work: list[float] = field(default_factory=list)
    silences: list[float] = field(default_factory=list)
    overruns: int = 0

    def add(
        self, period: float | None, wall_period: float | None, work: float, silence: float, paced_wall: bool
    ) -> bool:
        """Add one cycle's timing; return whether it overran.

        A cycle overruns when its period on the backend's clock (what the
        joints see), or on the wall clock where the loop is paced by it, is
        more than ``OVERRUN_TOLERANCE`` over the nominal period.
        """
        limit = self.nominal_s * (1 + OVERRUN_TOLERANCE)
        overrun = period is not None and period > limit
        overrun |= paced_wall and wall_period is not None and wall_period > limit
        if period is not None:
            self.periods.append(period)
        if wall_period is not None:
            self.wall_periods.append(wall_period)
        self.work.append(work)
        self.silences.append(silence)
        self.overruns += overrun
        return overrun

    def summary(self) -> dict[str, float | int | None]:
        """Mean, max and standard deviation (jitter) of each series."""

        def stats(xs: list[float], name: str) -> dict[str, float | None]:
            a = np.asarray(xs)
            if a.size == 0:
                return {f"{name}_mean_s": None, f"{name}_max_s": None, f"{name}_jitter_s": None}
            return {
                f"{name}_mean_s": float(a.mean()),
                f"{name}_max_s": float(a.max()),
                f"{name}_jitter_s": float(a.std()),
            }

        return {
            "rate_hz": 1.0 / self.nominal_s,
            **stats(self.periods, "period"),
            **stats(self.wall_periods, "wall_period"),
            "work_mean_s": float(np.mean(self.work)) if self.work else None,
            "work_max_s": float(np.max(self.work)) if self.work else None,
            "max_silence_s": float(np.max(self.silences)) if self.silences else None,
            "overruns": self.overruns,
        }


def print_summary(console: Console, s: dict[str, Any], log: RunLog) -> None:
    """The summary record as a table, where the log is, and which records it lacks."""

    def ms(key: str) -> str:
        v = s.get(key)
        return "-" if v is None else f"{v * 1000:.2f} ms"

    table = Table(title=f"deploy summary ({s['stop_reason']})")
    table.add_column("metric")
    table.add_column("value", justify="right")
    rate = f"{s['successes']}/{s['episodes']}"
    if s["success_rate"] is not None:
        rate += f" ({s['success_rate']:.0%})"
    table.add_row("episodes (successes)", rate)
    table.add_row("cycles", str(s["cycles"]))
    table.add_row("rate", f"{s['rate_hz']:g} Hz")
    table.add_row("period mean / max (backend clock)", f"{ms('period_mean_s')} / {ms('period_max_s')}")
    table.add_row("jitter (std, backend clock)", ms("period_jitter_s"))
    table.add_row(
        "host loop mean / jitter (wall)", f"{ms('wall_period_mean_s')} / {ms('wall_period_jitter_s')}"
    )
    table.add_row("host work per cycle mean / max", f"{ms('work_mean_s')} / {ms('work_max_s')}")
    table.add_row("longest joint silence", ms("max_silence_s"))
    table.add_row("overruns", str(s["overruns"]))
    for name, bus in s["bus"].items():
        errors = ", ".join(f"{k} {v}" for k, v in bus["errors"].items())
        table.add_row(
            f"bus {name}: transactions / retries / errors",
            f"{bus['transactions']} / {bus['retries']} / {errors}",
        )
    table.add_row("stop", escape(s["message"]))
    flags = ", ".join(f"{n} {st['flag_names']}" for n, st in s["final_state"].items())
    table.add_row("final flags", flags)
    console.print(table)
    console.print(f"log        {log.path}", markup=False)
    if log.error is not None:
        lost = f": {', '.join(log.lost)}" if log.lost else ""
        lines = (
            "its last line may be torn (cutting the failed record off failed too)"
            if log.torn
            else "every line in it is a whole record"
        )
        console.print(
            f"log incomplete: {log.dropped} record(s) not written{lost} "
            f"({log.error.strerror or log.error}); {lines}",
            markup=False,
        )
    if s.get("trace_error"):
        console.print(f"trace      incomplete: {s['trace_error']}", markup=False)


def disabled_line(s: dict[str, Any]) -> str:
    """Which joints acknowledged their disable, and each one that did not, named (the summary's words)."""
    names = list(s["final_state"])
    if s["arm_disabled"]:
        return (
            f"arm disabled: {', '.join(names)} acknowledged their disable (currents 0); "
            "arm shut down, bus closed"
        )
    confirmed = [n for n in names if n not in s["not_confirmed_disabled"]]
    lines = "; ".join(s["not_confirmed_warnings"])
    done = f"confirmed disabled: {', '.join(confirmed)}" if confirmed else "no joint confirmed disabled"
    done = f"; {done}"
    return f"[red]arm NOT confirmed disabled[/red]: {escape(lines)}{done}"
