"""The validation's figures: one row per comparison, a table, JSON."""

from __future__ import annotations

import json
import math
import os
from collections.abc import Iterable, Sequence
from dataclasses import asdict, dataclass, fields
from pathlib import Path

from bioscara_gym.errors import one_line

__all__ = ["ROWS_KIND", "Row", "is_rows_json", "one_line", "print_table", "rows_to_json", "summary"]

#: What ``validate --json`` replaces (:func:`~bioscara_gym.fsutil.replace_problem`).
ROWS_KIND = "a validate --json rows file"


@dataclass(frozen=True)
class Row:
    """One comparison of the simulated arm with a recording.

    Attributes:
        experiment: The recording (``maxAccel/j1_3``).
        quantity: What is compared (``peak speed``).
        real: The real arm's figure.
        sim: The simulated arm's figure.
        error: How far apart, in the unit of ``bound``.
        bound: The largest error that passes.
        unit: Unit of ``real`` and ``sim``.
        error_unit: Unit of ``error`` and ``bound`` (``%``, ``ms``, ...).
        passed: Whether ``error <= bound``.
        note: What the figure leaves out, if anything.
    """

    experiment: str
    quantity: str
    real: float | str
    sim: float | str
    error: float
    bound: float
    unit: str = ""
    error_unit: str = "%"
    passed: bool = True
    note: str = ""

    @classmethod
    def compare(
        cls,
        experiment: str,
        quantity: str,
        real: float,
        sim: float,
        bound: float,
        *,
        unit: str = "",
        relative: bool = True,
        scale: float | None = None,
        error_unit: str | None = None,
        note: str = "",
    ) -> Row:
        """Row of ``|sim - real|``: as % of ``scale`` (default ``|real|``) when ``relative``."""
        diff = abs(sim - real)
        if relative:
            base = abs(real) if scale is None else abs(scale)
            error = 100.0 * diff / base if base > 0 else (0.0 if diff == 0 else math.inf)
            error_unit = error_unit or "%"
        else:
            error = diff
            error_unit = error_unit or unit
        passed = bool(error <= bound)
        return cls(experiment, quantity, real, sim, error, bound, unit, error_unit, passed, note)

    @classmethod
    def verdict(
        cls, experiment: str, quantity: str, real: str, sim: str, passed: bool, note: str = ""
    ) -> Row:
        """Row of a yes/no comparison (e.g. whether steps were lost)."""
        return cls(experiment, quantity, real, sim, 0.0 if passed else 1.0, 0.0, "", "", passed, note)


def summary(rows: Sequence[Row]) -> tuple[int, int]:
    """(passed, total)."""
    return sum(r.passed for r in rows), len(rows)


def _fmt(value: float | str) -> str:
    if isinstance(value, str):
        return value
    if math.isinf(value):
        return "inf"
    if value == 0 or 0.01 <= abs(value) < 1e5:
        return f"{value:.4g}"
    return f"{value:.3g}"


def print_table(rows: Iterable[Row], title: str = "Simulated arm against the real arm's recordings") -> None:
    """Print the rows as one table (rich)."""
    from rich.console import Console
    from rich.table import Table

    table = Table(title=title, show_lines=False)
    for name, justify in (
        ("experiment", "left"),
        ("compared", "left"),
        ("real", "right"),
        ("sim", "right"),
        ("error", "right"),
        ("bound", "right"),
        ("", "center"),
    ):
        table.add_column(name, justify=justify)  # type: ignore[arg-type]
    for r in rows:
        unit = f" {r.unit}" if r.unit else ""
        eu = f" {r.error_unit}" if r.error_unit and r.error_unit != "%" else r.error_unit
        error = "" if r.error_unit == "" else f"{_fmt(r.error)}{eu}"
        bound = "" if r.error_unit == "" else f"{_fmt(r.bound)}{eu}"
        verdict = "[green]pass[/]" if r.passed else "[red]FAIL[/]"
        table.add_row(
            one_line(r.experiment),
            r.quantity,
            f"{_fmt(r.real)}{unit}",
            f"{_fmt(r.sim)}{unit}",
            error,
            bound,
            verdict,
        )
    Console(width=160).print(table)


def rows_to_json(rows: Sequence[Row], path: Path | str) -> None:
    """Write the rows as JSON (a list of objects), atomically."""
    from bioscara_gym.fsutil import atomic_write_text

    def clean(v: object) -> object:
        return None if isinstance(v, float) and not math.isfinite(v) else v

    data = [{k: clean(v) for k, v in asdict(r).items()} for r in rows]
    atomic_write_text(Path(path), json.dumps(data, indent=1) + "\n")


def is_rows_json(path: Path | str) -> bool:
    """Whether ``path`` holds rows as :func:`rows_to_json` writes them: a list of objects with a row's keys.

    What ``validate --json`` may replace (besides nothing or an empty file).

    Raises:
        OSError: It cannot be read.
    """
    from bioscara_gym.fsutil import MAX_JSON_BYTES, read_json

    if os.stat(path).st_size > MAX_JSON_BYTES:
        return False
    try:
        data = read_json(path)
    except ValueError:  # not UTF-8, not JSON
        return False
    keys = {f.name for f in fields(Row)}
    return isinstance(data, list) and all(isinstance(d, dict) and set(d) == keys for d in data)
