"""Loop timing of a 25 Hz Reach deploy on the emulated bus, with and without bus faults.

Runs ``bioscara deploy`` (``Deployment``) with the scripted expert on
``Bioscara-Reach-v0`` over the emulated bus: once without faults (the
reference) and once with ``--faults`` (default ``latency_ms=2,jitter_ms=3``),
each for ``--cycles`` cycles (episodes of 50 cycles at 25 Hz). From each run's
JSONL log (records ``type: cycle``) it prints the period error (``period_s``
on the backend clock minus the nominal 40 ms) at p50 and p99, the share of
overruns, the longest joint silence and how the run ended (a deadman trip
would stop it). Every transaction takes its wire time at the configured bus
clock (100 kHz) plus the faults' latency and jitter; the deadline scheduler
takes that out of the period. Figures only, no pass/fail.

    python benchmarks/deploy_timing.py
    python benchmarks/deploy_timing.py --faults latency_ms=0.5 --cycles 500
"""

from __future__ import annotations

import argparse
import json
import math
import tempfile
import time
from pathlib import Path

import numpy as np
from rich.console import Console

from bioscara_gym.training.deploy import DeployArgs, Deployment

ENV_ID = "Bioscara-Reach-v0"
#: Control cycles per Reach episode (its ``max_episode_steps``, 2 s at 25 Hz).
CYCLES_PER_EPISODE = 50
NOMINAL_S = 1.0 / 25.0


def run(faults: str | None, cycles: int, folder: Path) -> dict[str, object]:
    """Deploy the expert for ``cycles`` cycles; the timing figures of its log."""
    tag = faults.replace(",", "_").replace("=", "") if faults else "none"
    log = folder / f"deploy-{tag}.jsonl"
    args = DeployArgs(
        expert=True,
        env=ENV_ID,
        backend="emulated",
        faults=faults,
        episodes=math.ceil(cycles / CYCLES_PER_EPISODE),
        log=log,
        state_file=folder / f"gripper-{tag}.json",
    )
    start = time.perf_counter()
    try:
        summary = Deployment(args, console=Console(quiet=True)).run()
    except Exception as e:  # a safety stop (e.g. the deadman) is a result here
        summary = {"stop_reason": f"{type(e).__name__}: {e}"}
    wall = time.perf_counter() - start
    records = [json.loads(line) for line in log.read_text(encoding="utf-8").splitlines()]
    summary = next((r for r in records if r["type"] == "summary"), summary)
    done = [r for r in records if r["type"] == "cycle" and not r.get("stopped")]
    periods = np.array([r["period_s"] for r in done if r.get("period_s") is not None])
    silence = max((r["silence_s"] for r in done if r.get("silence_s") is not None), default=math.nan)
    error = (periods - NOMINAL_S) * 1000.0
    return {
        "faults": faults or "none",
        "cycles": len(done),
        "p50_ms": float(np.percentile(error, 50)),
        "p99_ms": float(np.percentile(error, 99)),
        "overruns": float(np.mean(error > 1e-6)),
        "silence_ms": silence * 1000.0,
        "ended": summary.get("stop_reason"),
        "wall_s": wall,
    }


def main() -> None:
    """Run the reference and the faulty deploy, print one line each."""
    fmt = argparse.RawDescriptionHelpFormatter
    parser = argparse.ArgumentParser(description=__doc__, formatter_class=fmt)
    parser.add_argument("--faults", default="latency_ms=2,jitter_ms=3")
    parser.add_argument("--cycles", type=int, default=1000)
    args = parser.parse_args()
    with tempfile.TemporaryDirectory() as folder:
        results = [run(None, args.cycles, Path(folder)), run(args.faults, args.cycles, Path(folder))]
    print(f"25 Hz {ENV_ID} deploy on the emulated bus (100 kHz), period error = period - 40 ms")
    for r in results:
        print(
            f"faults {r['faults']:<26}: {r['cycles']} cycles, period error p50 {r['p50_ms']:+.2f} ms, "
            f"p99 {r['p99_ms']:+.2f} ms, overruns {r['overruns']:.0%}, longest joint silence "
            f"{r['silence_ms']:.1f} ms, ended: {r['ended']} ({r['wall_s']:.0f} s wall)"
        )


if __name__ == "__main__":
    main()
