"""Wall time of rollouts with 1 and with 2 workers (``n_envs``), in one run.

Two measurements, each with one env in this process and with two envs in
subprocesses (stable-baselines3's ``SubprocVecEnv``, :mod:`bioscara_gym.training.parallel`):

* DAgger's rollouts: the PickPlace observation expert labelling the same
  seeded episodes (``label_episodes`` against ``label_rollouts``);
* DAgger's evaluation: the same seeded episodes acted by that expert alone
  (``run_episodes`` against ``run_episodes_on``; the stats must agree);
* PPO on Reach: ``bioscara train --algo ppo`` for the same number of env
  steps, ``--n-envs 1`` against ``--n-envs 2`` (so 2 x ``n_steps`` a rollout).

Prints the seconds, the env steps a second and the ratio (2 workers over 1).
On a machine with two idle cores the ratio is the speed-up; the load average
is printed beside it.

    python benchmarks/parallel_rollouts.py --episodes 10 --ppo-steps 4096
"""

from __future__ import annotations

import argparse
import os
import sys
import tempfile
import time
from pathlib import Path

import gymnasium as gym
import numpy as np
import yaml
from rich.console import Console
from rich.table import Table

import bioscara_gym  # noqa: F401 - registers the tasks
from bioscara_gym.cli import main as bioscara
from bioscara_gym.tasks import task
from bioscara_gym.training.dagger import label_episodes
from bioscara_gym.training.evaluate import run_episodes
from bioscara_gym.training.parallel import label_rollouts, make_vec_envs, run_episodes_on

PICK = "Bioscara-PickPlace-v1"
REACH = "Bioscara-Reach-v0"
PICK_KWARGS = {"control_mode": "cartesian"}


def dagger_rollouts(episodes: int, seed: int) -> dict[str, dict[int, tuple[float, int]]]:
    """Seconds and env steps of ``episodes`` expert episodes labelled and evaluated, 1 and 2 workers."""
    env = gym.make(PICK, **PICK_KWARGS)
    rollouts, evaluations = {}, {}
    try:
        expert = task(PICK).make_observation_expert(env.unwrapped)
        env.reset(seed=seed)  # bring-up and homing outside the timed part
        start = time.perf_counter()
        one = label_episodes(env, expert, expert, episodes, seed, 0, 1.0)
        rollouts[1] = (time.perf_counter() - start, len(one.data))
        start = time.perf_counter()
        stats = run_episodes(env, expert, episodes, seed=seed)
        evaluations[1] = (time.perf_counter() - start, round(stats.mean_length * stats.episodes))
        venv = make_vec_envs(PICK, 2, PICK_KWARGS)
        try:
            venv.env_method("reset", seed=seed)  # the workers' bring-up, untimed as above
            start = time.perf_counter()
            rows, _, _ = label_rollouts(venv, expert, expert, episodes, seed, 1.0, np.random.default_rng(0))
            rollouts[2] = (time.perf_counter() - start, len(rows))
            start = time.perf_counter()
            on_two = run_episodes_on(venv, expert, episodes, seed=seed)
            evaluations[2] = (time.perf_counter() - start, round(on_two.mean_length * on_two.episodes))
        finally:
            venv.close()
    finally:
        env.close()
    if on_two != stats:
        raise SystemExit(f"parallel_rollouts: 2 workers evaluated {on_two}, one env {stats}")
    return {"rollouts": rollouts, "evaluation": evaluations}


def ppo_training(steps: int) -> dict[int, tuple[float, int]]:
    """Seconds of ``bioscara train --algo ppo`` for ``steps`` env steps, with 1 and 2 envs."""
    entry = {
        "n_timesteps": steps,
        "policy": "MultiInputPolicy",
        "n_steps": 512,
        "batch_size": 128,
        "n_epochs": 2,
        "env_kwargs": {"control_mode": "cartesian"},
        "eval_freq": 10**9,  # no evaluation inside the timed part
        "eval_episodes": 1,
    }
    out = {}
    with tempfile.TemporaryDirectory() as tmp:
        config = Path(tmp) / "ppo.yaml"
        config.write_text(yaml.safe_dump({REACH: entry}), encoding="utf-8")
        for n in (1, 2):
            start = time.perf_counter()
            argv = ["train", "--algo", "ppo", "--env", REACH, "--config", str(config), "--n-envs", str(n)]
            rc = bioscara([*argv, "--out", str(Path(tmp) / f"run{n}"), "--no-progress"])
            if rc != 0:
                raise SystemExit(f"parallel_rollouts: bioscara train --n-envs {n} failed ({rc})")
            out[n] = (time.perf_counter() - start, steps)
    return out


def main(argv: list[str] | None = None) -> int:
    parser = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    parser.add_argument("--episodes", type=int, default=10, help="DAgger rollout episodes (PickPlace)")
    parser.add_argument("--ppo-steps", type=int, default=4096, help="PPO env steps (Reach)")
    parser.add_argument("--seed", type=int, default=10_000)
    args = parser.parse_args(argv)
    con = Console(highlight=False)
    table = Table(title=f"1 and 2 workers, one run (load average {os.getloadavg()[0]:.1f})")
    for column in ("what", "workers", "s", "env steps/s", "2 / 1"):
        table.add_column(column, justify="right")
    dagger = dagger_rollouts(args.episodes, args.seed)
    for what, rows in (
        (f"DAgger rollouts, {args.episodes} PickPlace episodes", dagger["rollouts"]),
        (f"DAgger evaluation, {args.episodes} PickPlace episodes", dagger["evaluation"]),
        (f"PPO on Reach, {args.ppo_steps} steps (incl. start-up)", ppo_training(args.ppo_steps)),
    ):
        rate = {n: steps / seconds for n, (seconds, steps) in rows.items()}
        for n, (seconds, _) in rows.items():
            ratio = f"{rate[2] / rate[1]:.2f}" if n == 2 else ""
            table.add_row(what if n == 1 else "", str(n), f"{seconds:.1f}", f"{rate[n]:.0f}", ratio)
    con.print(table)
    return 0


if __name__ == "__main__":
    sys.exit(main())
