"""The simulated arm against the real arm's recordings: the targets of issue #23, figure by figure.

Runs ``bioscara validate``'s comparisons on the packaged recordings and, if
given, on other folders of the same layout (the recordings the team keeps
aside to check a calibration on data it was not fitted to), and prints per
folder one line per target: how many comparisons meet it, and the worst.

    python benchmarks/validate_real.py [FOLDER ...] [--config FILE]

Also reads the folders named in ``BIOSCARA_HELDOUT`` (``os.pathsep``-separated).
"""

from __future__ import annotations

import argparse
import os
import time
from pathlib import Path

from bioscara_gym.hardware import load_config
from bioscara_gym.validation import Validation, validate
from bioscara_gym.validation.experiments import stall
from bioscara_gym.validation.report import Row

#: Target -> (experiment prefix, quantity test): which rows each target is judged on.
TARGETS = {
    "maxAccel peak speed within 10 %": ("maxAccel/", lambda q: q == "peak speed"),
    "maxAccel step loss where the real lost steps, nowhere else": ("maxAccel/", lambda q: q == "lost steps"),
    "maxAccel position RMS <= 5 % of the move": ("maxAccel/", lambda q: q == "position RMS"),
    "settingMaxVal profiles (peak, ramp, position)": ("settingMaxVal/", lambda q: True),
    "stall signal band medians within 30 %": ("high_speed_stall_test/", lambda q: "worst band" in q),
    "stall flag within 50 ms of the real trip": (
        "high_speed_stall_test/",
        lambda q: q.startswith("stall trip"),
    ),
    "no false stall trips": ("high_speed_stall_test/", lambda q: q == "false stall trips"),
    "after a block: measured speed, raw error": ("high_speed_stall_test/", lambda q: "after the block" in q),
    "tracking steady-state error within 25 % of the README": ("tracking_error/", lambda q: "README" in q),
    "tracking steady-state error vs the recording": ("tracking_error/", lambda q: "recording" in q),
    "tracking: position spread at rest after the ramp": ("tracking_error/", lambda q: "at rest" in q),
    "mean transaction time within 15 %": ("RW_test/", lambda q: q.startswith("mean")),
    "firmware handler times": ("RW_test/", lambda q: q.endswith("handler time")),
}


def _worst(rows: list[Row]) -> str:
    judged = [r for r in rows if r.error_unit]
    if not judged:
        failed = [r for r in rows if not r.passed]
        return f"fails: {', '.join(r.experiment.split('/')[-1] for r in failed)}" if failed else ""
    w = max(judged, key=lambda r: r.error / r.bound if r.bound else r.error)
    return f"worst {w.experiment.split('/')[-1]}: {w.error:.3g} {w.error_unit} (bound {w.bound:g})"


def report(folder: Path | None, config_path: Path | None) -> int:
    """Print the targets for one folder; return the number of failing rows."""
    t0 = time.perf_counter()
    result = validate(folder, load_config(config_path))
    elapsed = time.perf_counter() - t0
    print(f"\n== {result.recordings.root} ({len(result.recordings)} recordings, {elapsed:.1f} s)")
    for target, (prefix, test) in TARGETS.items():
        rows = [r for r in result.rows if r.experiment.startswith(prefix) and test(r.quantity)]
        if rows:
            passed = sum(r.passed for r in rows)
            print(f"  {target:<62} {passed:>3}/{len(rows):<3} {_worst(rows)}")
    failed = [r for r in result.rows if not r.passed]
    print(f"  all rows: {len(result.rows) - len(failed)}/{len(result.rows)} pass")
    stall_reproducibility(result)
    return len(failed)


def stall_reproducibility(result: Validation) -> None:
    """The stall bands of each replay beside the real runs of the same joint against each other.

    The band target (every 5 rad/s band's median within 30 %) asks more of a
    replay than the arm's own runs give against each other: these lines put
    the two side by side, raw |PID error|, both ramp directions.
    """
    signals = result.recordings.stall_signal
    pairs = stall.run_to_run(signals)
    if not pairs:
        return
    print(f"  stall bands within {stall.BAND_BOUND_PCT:g} % (raw |PID error|, both ramps):")
    sims = result.replays.get("stall_signal", {})
    for sig in signals:
        if sig.name in sims and any(sig.name in (p.first, p.second) for p in pairs):
            within, bands, worst = stall.replay_agreement(sig, sims[sig.name])
            print(f"    simulated vs {sig.name:<52} {within:>3}/{bands:<3} worst {worst:.0f} %")
    for p in pairs:
        print(f"    real {p.first} vs real {p.second}: {p.within}/{p.bands}, worst {p.worst:.0f} %")


def main() -> None:
    parser = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    parser.add_argument("folders", nargs="*", type=Path, help="more folders of recordings (held out)")
    parser.add_argument("--config", type=Path, help="configuration to judge (default: the packaged one)")
    args = parser.parse_args()
    held_out = [Path(p) for p in os.environ.get("BIOSCARA_HELDOUT", "").split(os.pathsep) if p]
    report(None, args.config)
    for folder in [*args.folders, *held_out]:
        report(folder, args.config)


if __name__ == "__main__":
    main()
