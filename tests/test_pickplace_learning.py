"""Issue #17's target: the default `bioscara train --env Bioscara-PickPlace` reaches >= 90 % in <= 30 min.

Slow (up to 30 minutes plus a 100-episode evaluation); run with ``make test-slow``.
Wall time depends on the machine's load; benchmarks/train_pickplace.py prints it.
"""

from __future__ import annotations

import importlib.util
from pathlib import Path

import pytest

BENCH = Path(__file__).resolve().parents[1] / "benchmarks" / "train_pickplace.py"


@pytest.mark.slow
@pytest.mark.xfail(
    strict=True,
    reason="issue 17: not reached yet (0 % after 25 min on a loaded CPU); "
    "strict, so reaching it fails this mark and asks for it to be removed",
)
def test_default_pickplace_training_reaches_90_percent_within_30_minutes(tmp_path: Path) -> None:
    spec = importlib.util.spec_from_file_location("train_pickplace", BENCH)
    assert spec is not None and spec.loader is not None
    bench = importlib.util.module_from_spec(spec)
    spec.loader.exec_module(bench)
    outcome = bench.run("SAC+HER+demos", 0, 30.0, tmp_path / "demos_0", None, 100)
    got = f"{outcome.success:.0%} after {outcome.wall_s:.0f} s, {outcome.steps} steps"
    assert outcome.success >= 0.9, got
