"""Bioscara-PickPlace on this CPU: the default `bioscara train` (DAgger) vs SAC+HER alone, and BC alone.

For each seed, runs ``bioscara train --env Bioscara-PickPlace`` (the packaged
default: DAgger, training/configs/dagger.yaml, its expert episodes collected
in the run) with a wall-time budget of ``--minutes``; then, in the same run,
SAC+HER alone (the packaged sac.yaml entry without its demonstration
callback) for ``--baseline-minutes``; then behaviour cloning alone
(``--algo bc``, 100 expert episodes collected in the run) unless
``--no-bc``. A run still going at its budget is interrupted (SIGINT: it saves
a checkpoint) and its newest checkpoint is evaluated. Every policy is judged
on ``--eval-episodes`` seeded episodes (seeds 10000...), in the control mode
it was trained in (from its metadata or config). Target: >= 90 % success
within 30 minutes, collecting included.

Wall-clock figures depend on what else the machine runs: the load average is
printed with the results.

    python benchmarks/train_pickplace.py --seeds 0 1 2
    python benchmarks/train_pickplace.py --seeds 0 --minutes 30 --baseline-minutes 30
    python benchmarks/train_pickplace.py --seeds 0 --minutes 10 --baseline-minutes 0 --no-bc   # default only
"""

from __future__ import annotations

import argparse
import json
import os
import re
import signal
import subprocess
import sys
import tempfile
import time
from dataclasses import dataclass, field
from pathlib import Path
from typing import Any

import yaml

ENV = "Bioscara-PickPlace-v1"
TARGET = 0.9
DEMO_CALLBACK = "bioscara_gym.training.zoo.DemonstrationCallback"
EVAL_RE = re.compile(r"\[eval\] step\s+(\d+)\s+(\d+) s\s+success\s+([\d.]+)% over (\d+)")
REACHED_RE = re.compile(r"target reached after (\d+) steps")
DEFAULT = "DAgger (default)"
BASELINE = "SAC+HER"
BC = "BC"


@dataclass
class Outcome:
    """One run: its policy's success, env steps, wall time and the time the target was reached."""

    method: str
    seed: int
    success: float
    steps: int
    wall_s: float
    reached_at_s: float | None
    curve: list[tuple[int, int, float]] = field(default_factory=list)


def baseline_config(directory: Path, env: str = ENV) -> Path:
    """The packaged SAC entry of ``env`` without its demonstration callback."""
    from bioscara_gym.training.hyperparams import default_config_path

    entry = yaml.safe_load(default_config_path("sac").read_text(encoding="utf-8"))[env]
    entry["callback"] = [c for c in entry.get("callback", []) if DEMO_CALLBACK not in c]
    path = directory / "sac_her_baseline.yaml"
    path.write_text(yaml.safe_dump({env: entry}), encoding="utf-8")
    return path


def run(
    method: str, seed: int, minutes: float, out: Path, extra: list[str], episodes: int, env: str = ENV
) -> Outcome:
    """One ``bioscara train`` run of ``env`` with ``extra``, stopped at ``minutes``; its policy evaluated."""
    cmd = [sys.executable, "-m", "bioscara_gym", "train", "--env", env, "--seed", str(seed)]
    cmd += ["--out", str(out), "--no-progress", *extra]
    start = time.perf_counter()
    log = out.with_suffix(".log")
    out.parent.mkdir(parents=True, exist_ok=True)
    with open(log, "w", encoding="utf-8") as f:
        proc = subprocess.Popen(cmd, stdout=f, stderr=subprocess.STDOUT)
        try:
            proc.wait(timeout=minutes * 60)
        except subprocess.TimeoutExpired:
            proc.send_signal(signal.SIGINT)  # bioscara train saves a checkpoint and exits 130
            proc.wait()
    wall = time.perf_counter() - start
    text = log.read_text(encoding="utf-8")
    curve = [(int(m[1]), int(m[2]), float(m[3]) / 100) for m in EVAL_RE.finditer(text)]
    reached = REACHED_RE.search(text)
    reached_s = re.search(r"target reached after \d+ steps, (\d+) s", text)
    at = float(reached_s.group(1)) if reached_s else (wall if reached else None)
    success, steps = evaluate(out, episodes, env)
    return Outcome(method, seed, success, steps, wall, at, curve)


def _env_kwargs(out: Path, env: str = ENV) -> dict[str, Any]:
    """The env the run trained on: its metadata's, else its config's (an interrupted run has no metadata)."""
    from bioscara_gym.training.methods import method_spec

    meta = out / "metadata.json"
    if meta.exists():
        return dict(json.loads(meta.read_text(encoding="utf-8"))["env_kwargs"])
    state = json.loads((out / "train_state.json").read_text(encoding="utf-8"))
    spec = method_spec(state["algo"])
    config = Path(state["config"]) if state["config"] else spec.default_config()
    return dict(spec.load_config(config, env).env_kwargs)


def evaluate(out: Path, episodes: int, env_id: str = ENV) -> tuple[float, int]:
    """Success over ``episodes`` of the final model, else the newest checkpoint; and its env steps."""
    import gymnasium as gym

    import bioscara_gym  # noqa: F401
    from bioscara_gym.training.algos import ALGOS, sb3_policy
    from bioscara_gym.training.checkpoints import newest_checkpoint
    from bioscara_gym.training.evaluate import run_episodes

    path = out / "model.zip"
    if not path.exists():
        ckpt = newest_checkpoint(out / "checkpoints")
        if ckpt is None:
            return 0.0, 0
        path = ckpt
    act_only = {"replay_buffer_class": None, "replay_buffer_kwargs": {}, "buffer_size": 1}
    model = ALGOS["sac"].load(path, env=None, device="cpu", custom_objects=act_only)
    meta = out / "metadata.json"
    steps = int(model.num_timesteps)
    if meta.exists():  # DAgger and BC count env steps in their metadata, not in the model
        steps = int(json.loads(meta.read_text(encoding="utf-8")).get("timesteps") or steps)
    env = gym.make(env_id, **_env_kwargs(out, env_id))
    try:
        stats = run_episodes(env, sb3_policy(model), episodes, seed=10_000)
    finally:
        env.close()
    return stats.success_rate, steps


def main(argv: list[str] | None = None) -> int:
    """Run the methods for every seed and print a table; exit 1 if the default misses the target."""
    parser = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    parser.add_argument("--seeds", type=int, nargs="+", default=[0, 1, 2])
    parser.add_argument("--minutes", type=float, default=30.0, help="budget of the default run")
    parser.add_argument("--baseline-minutes", type=float, help="SAC+HER alone (default: --minutes)")
    parser.add_argument("--no-bc", action="store_true", help="skip behaviour cloning alone")
    parser.add_argument("--eval-episodes", type=int, default=100)
    parser.add_argument("--out", type=Path, help="runs go here (default: a temporary directory)")
    args = parser.parse_args(argv)
    baseline_minutes = args.minutes if args.baseline_minutes is None else args.baseline_minutes
    root = args.out or Path(tempfile.mkdtemp(prefix="train_pickplace_"))
    root.mkdir(parents=True, exist_ok=True)
    load_before = os.getloadavg()
    outcomes: list[Outcome] = []
    for seed in args.seeds:
        outcomes.append(run(DEFAULT, seed, args.minutes, root / f"default_{seed}", [], args.eval_episodes))
        print(_row(outcomes[-1]), flush=True)
        if baseline_minutes > 0:
            cfg = ["--config", str(baseline_config(root))]
            base = run(BASELINE, seed, baseline_minutes, root / f"sac_her_{seed}", cfg, args.eval_episodes)
            outcomes.append(base)
            print(_row(base), flush=True)
        if not args.no_bc:
            bc = run(BC, seed, args.minutes, root / f"bc_{seed}", ["--algo", "bc"], args.eval_episodes)
            outcomes.append(bc)
            print(_row(bc), flush=True)
    load_after = os.getloadavg()
    print()
    print(f"{'method':<17} {'seed':>4} {'success':>8} {'env steps':>10} {'wall':>8} {'target':>8}")
    for o in outcomes:
        print(_row(o))
    for method in dict.fromkeys(o.method for o in outcomes):
        rows = [o for o in outcomes if o.method == method]
        hit = sum(o.success >= TARGET for o in rows)
        mean = sum(o.success for o in rows) / len(rows)
        print(f"{method}: mean success {mean:.1%}, >= {TARGET:.0%} in {hit}/{len(rows)} seeds")
    cpus = os.cpu_count()
    print(f"load average (1 min) {load_before[0]:.1f} before, {load_after[0]:.1f} after, on {cpus} CPUs")
    print(f"runs in {root}")
    default_rows = [o for o in outcomes if o.method == DEFAULT]
    return 0 if all(o.success >= TARGET for o in default_rows) else 1


def _row(o: Outcome) -> str:
    reached = f"{o.reached_at_s:.0f} s" if o.reached_at_s is not None else "-"
    return f"{o.method:<17} {o.seed:>4} {o.success:>8.1%} {o.steps:>10} {o.wall_s:>6.0f} s {reached:>8}"


if __name__ == "__main__":
    sys.exit(main())
