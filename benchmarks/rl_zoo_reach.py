"""rl-zoo3 on Bioscara-Reach with the shipped hyperparameters: success rate and wall time.

Runs, in subprocesses and a temporary log folder, exactly what a user of
rl-zoo3 would::

    python -m rl_zoo3.train --algo sac --env Bioscara-Reach-v0 --gym-packages bioscara_gym \\
        -conf training/configs/sac.yaml --seed 0 --device cpu --num-threads 1
    python -m rl_zoo3.enjoy --algo sac --env Bioscara-Reach-v0 --gym-packages bioscara_gym \\
        --no-render -n 5000 --device cpu

once per seed (``--seeds``, default 0 1 2), training for the entry's own
``n_timesteps`` (the entry's SuccessEvalCallback stops it early once its own
100 episodes reach ``target_success``, 98 %: a margin above the target),
then prints the success rate of rl-zoo3's ``enjoy`` over the first 100
episodes, the wall time of each step, and the range over the seeds.
Target: >= 95 % in every seed. One torch thread: the env steps in the same process, and on a
2-core machine a second thread only contends with it.
"""

from __future__ import annotations

import argparse
import re
import subprocess
import sys
import tempfile
import time
from pathlib import Path

import gymnasium as gym

import bioscara_gym  # noqa: F401 - registers the tasks

ROOT = Path(__file__).resolve().parents[1]
ENV_ID = "Bioscara-Reach-v0"
TARGET = 0.95
SUCCESS_LINE = re.compile(r"^Success\? (\S+)$", re.MULTILINE)
EVAL_LINE = re.compile(r"^\[eval\] .*$", re.MULTILINE)


def zoo(command: str, *args: str) -> tuple[str, float]:
    """Run ``python -m rl_zoo3.COMMAND ARGS``; its stdout and wall time (raises if it fails)."""
    start = time.perf_counter()
    done = subprocess.run(
        [sys.executable, "-m", f"rl_zoo3.{command}", *args],
        capture_output=True,
        text=True,
        check=False,
    )
    wall = time.perf_counter() - start
    if done.returncode != 0:
        sys.stderr.write(done.stdout[-4000:] + done.stderr[-4000:])
        raise SystemExit(f"rl_zoo3.{command} failed with exit code {done.returncode}")
    return done.stdout, wall


def truthy(text: str) -> bool:
    """``is_success`` as enjoy prints it (``True``, ``1.0``, ``[ True]`` ...)."""
    text = text.strip("[]() ")
    return text in ("True", "true") or (text.replace(".", "", 1).isdigit() and float(text) > 0)


def run_seed(args: argparse.Namespace, seed: int) -> float:
    """rl-zoo3's train, then enjoy, for one seed; prints the figures, returns enjoy's success rate."""
    config = ROOT / "training" / "configs" / f"{args.algo}.yaml"
    common = ["--algo", args.algo, "--env", ENV_ID, "--gym-packages", "bioscara_gym", "--device", "cpu"]
    with tempfile.TemporaryDirectory() as tmp:
        folder = str(args.log_folder / f"seed{seed}" if args.log_folder else tmp)
        train_out, train_s = zoo(
            "train", *common, "-conf", str(config), "-f", folder, "--seed", str(seed), "--num-threads", "1"
        )
        evals = EVAL_LINE.findall(train_out)
        steps = int(gym.spec(ENV_ID).max_episode_steps or 0) * args.episodes
        enjoy_out, enjoy_s = zoo(
            "enjoy",
            *common,
            "-f",
            folder,
            "--no-render",
            "-n",
            str(steps),
            "--verbose",
            "2",
            "--num-threads",
            "1",
        )
    outcomes = [truthy(s) for s in SUCCESS_LINE.findall(enjoy_out)][: args.episodes]
    if len(outcomes) < args.episodes:
        raise SystemExit(f"seed {seed}: enjoy finished only {len(outcomes)} of {args.episodes} episodes")
    rate = sum(outcomes) / len(outcomes)
    print(f"rl-zoo3 {args.algo} on {ENV_ID}, seed {seed}, config {config.relative_to(ROOT)}")
    for line in evals:
        print(f"  train {line}")
    print(f"  train: {train_s:.0f} s wall (incl. start-up and the callback's evaluations)")
    print(f"  enjoy: {rate:.0%} success over {len(outcomes)} episodes ({enjoy_s:.0f} s wall)")
    return rate


def main() -> None:
    """Train with rl-zoo3 and enjoy, seed by seed; print the figures and the range."""
    parser = argparse.ArgumentParser(
        description=__doc__, formatter_class=argparse.RawDescriptionHelpFormatter
    )
    parser.add_argument("--algo", default="sac", choices=["sac", "td3", "ppo"])
    parser.add_argument("--seeds", type=int, nargs="+", default=[0, 1, 2], help="one run per seed")
    parser.add_argument("--episodes", type=int, default=100, help="enjoy episodes counted")
    parser.add_argument(
        "--log-folder", type=Path, help="keep rl-zoo3's logs here, one folder per seed (default: temporary)"
    )
    args = parser.parse_args()
    if args.episodes < 1:
        parser.error(f"--episodes must be at least 1, got {args.episodes}")
    rates = [run_seed(args, seed) for seed in args.seeds]
    met = sum(rate >= TARGET for rate in rates)
    spread = ", ".join(f"{rate:.0%}" for rate in rates)
    seeds = " ".join(map(str, args.seeds))
    print(f"enjoy over seeds {seeds}: {spread} (range {min(rates):.0%}-{max(rates):.0%})")
    print(f"target {TARGET:.0%}: met in {met} of {len(rates)} seeds")
    if met < len(rates):
        raise SystemExit(1)


if __name__ == "__main__":
    main()
