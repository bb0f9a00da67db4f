"""Control steps per second of the ``sitl`` backend beside the ``emulated`` one, in one run.

Both run the scripted expert of Bioscara-Reach on the same seeded episodes
(the real ``Joint`` driver over the emulated bus): ``emulated`` into the
emulator's firmware cores, ``sitl`` into the joint firmware's own source
built for the host (physics at 1 ms, every joint's chip, encoder and
firmware each millisecond). The table shows steps/s (the episodes' wall
time, each episode's reset included; the first bring-up and homing not),
their ratio, and each backend's success rate. Needs the firmware: ``--firmware DIR`` or ``BIOSCARA_FIRMWARE``
(without it, says so and exits 0, as ``make bench`` runs every benchmark).

    python benchmarks/sitl_speed.py --episodes 10
"""

from __future__ import annotations

import argparse
import os
import sys
import time

import gymnasium as gym
from rich.console import Console
from rich.table import Table

import bioscara_gym  # noqa: F401 - registers the tasks
from bioscara_gym.experts import expert_for
from bioscara_gym.hardware.sitl.build import FIRMWARE_ENV
from bioscara_gym.training.evaluate import run_episodes


def measure(backend: str, episodes: int, seed: int, options: dict[str, object]) -> tuple[float, float, int]:
    """Success rate, steps/s and steps of ``episodes`` expert episodes on ``backend``."""
    env = gym.make("Bioscara-Reach-v0", backend=backend, backend_options=options)
    try:
        expert = expert_for(env.unwrapped)
        env.reset(seed=seed)  # bring-up (homing) outside the timed part
        start = time.perf_counter()
        stats = run_episodes(env, expert, episodes, seed=seed, on_reset=expert.reset)
        elapsed = time.perf_counter() - start
        steps = round(stats.mean_length * stats.episodes)
        return stats.success_rate, steps / elapsed, steps
    finally:
        env.close()


def main(argv: list[str] | None = None) -> int:
    parser = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    parser.add_argument("--episodes", type=int, default=10)
    parser.add_argument("--seed", type=int, default=10_000, help="seed of the first episode")
    parser.add_argument("--firmware", help=f"the joint firmware's folder (default ${FIRMWARE_ENV})")
    args = parser.parse_args(argv)
    firmware = args.firmware or os.environ.get(FIRMWARE_ENV)
    con = Console(highlight=False)
    if not firmware:
        con.print(f"sitl_speed: skipped, no firmware (pass --firmware DIR or set {FIRMWARE_ENV})")
        return 0
    rows = {}
    for backend, options in (("emulated", {}), ("sitl", {"firmware": firmware})):
        rows[backend] = measure(backend, args.episodes, args.seed, options)
    table = Table(title=f"Bioscara-Reach, scripted expert, {args.episodes} episodes, one run")
    for column in ("backend", "success", "steps", "steps/s"):
        table.add_column(column, justify="right")
    for backend, (success, rate, steps) in rows.items():
        table.add_row(backend, f"{success:.0%}", str(steps), f"{rate:.0f}")
    con.print(table)
    con.print(f"sitl / emulated: {rows['sitl'][1] / rows['emulated'][1]:.2f}")
    return 0


if __name__ == "__main__":
    sys.exit(main())
