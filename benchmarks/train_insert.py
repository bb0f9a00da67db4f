"""Bioscara-Insert on this CPU: the default `bioscara train` (DAgger) vs SAC+HER alone, same budget.

For each seed, runs ``bioscara train --env Bioscara-Insert`` (the packaged
default: DAgger, training/configs/dagger.yaml, its 40 expert episodes
collected in the run) with a wall-time budget of ``--minutes``, then SAC+HER
alone (the packaged sac.yaml entry) for ``--baseline-minutes`` (default: the
same). A run still going at its budget is interrupted (SIGINT: it saves a
checkpoint) and its newest checkpoint is evaluated. Every policy is judged
on ``--eval-episodes`` seeded episodes (seeds 10000...) in the control mode
it was trained in. Target (issue #27): >= 90 % success within 10 minutes,
demonstrations included, in every seed.

Wall-clock figures depend on what else the machine runs: the load average is
printed with the results. The runs themselves are train_pickplace.py's.

    python benchmarks/train_insert.py --seeds 0 1 2
    python benchmarks/train_insert.py --seeds 0 --baseline-minutes 0   # the default only
"""

from __future__ import annotations

import argparse
import os
import sys
import tempfile
from pathlib import Path

sys.path.insert(0, str(Path(__file__).resolve().parent))

from train_pickplace import BASELINE, DEFAULT, Outcome, _row, baseline_config, run

ENV = "Bioscara-Insert-v0"
TARGET = 0.9
MINUTES = 10.0


def main(argv: list[str] | None = None) -> int:
    """Run both methods for every seed and print a table; exit 1 if the default misses the target."""
    parser = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    parser.add_argument("--seeds", type=int, nargs="+", default=[0, 1, 2])
    parser.add_argument("--minutes", type=float, default=MINUTES, help="budget of the default run")
    parser.add_argument("--baseline-minutes", type=float, help="SAC+HER alone (default: --minutes)")
    parser.add_argument("--eval-episodes", type=int, default=100)
    parser.add_argument("--out", type=Path, help="runs go here (default: a temporary directory)")
    args = parser.parse_args(argv)
    baseline_minutes = args.minutes if args.baseline_minutes is None else args.baseline_minutes
    root = args.out or Path(tempfile.mkdtemp(prefix="train_insert_"))
    root.mkdir(parents=True, exist_ok=True)
    loads = [os.getloadavg()]
    outcomes: list[Outcome] = []
    for seed in args.seeds:
        default = run(DEFAULT, seed, args.minutes, root / f"default_{seed}", [], args.eval_episodes, ENV)
        outcomes.append(default)
        loads.append(os.getloadavg())
        print(_row(default), flush=True)
        if baseline_minutes > 0:
            cfg = ["--config", str(baseline_config(root, ENV))]
            out = root / f"sac_her_{seed}"
            base = run(BASELINE, seed, baseline_minutes, out, cfg, args.eval_episodes, ENV)
            outcomes.append(base)
            loads.append(os.getloadavg())
            print(_row(base), flush=True)
    print()
    print(f"{'method':<17} {'seed':>4} {'success':>8} {'env steps':>10} {'wall':>8} {'target':>8}")
    for o in outcomes:
        print(_row(o))
    for method in dict.fromkeys(o.method for o in outcomes):
        rows = [o for o in outcomes if o.method == method]
        hit = sum(o.success >= TARGET for o in rows)
        mean = sum(o.success for o in rows) / len(rows)
        print(f"{method}: mean success {mean:.1%}, >= {TARGET:.0%} in {hit}/{len(rows)} seeds")
    low, high = min(load[0] for load in loads), max(load[0] for load in loads)
    print(f"load average (1 min) {low:.1f}-{high:.1f} during the runs, on {os.cpu_count()} CPUs")
    print(f"runs in {root}")
    default_rows = [o for o in outcomes if o.method == DEFAULT]
    return 0 if all(o.success >= TARGET for o in default_rows) else 1


if __name__ == "__main__":
    sys.exit(main())
