"""Bioscara-Reach steps/s against Gymnasium's Reacher-v5, measured in the same run.

Single process, random actions, episodes reset as they end (resets included
in the time, after a first reset that homes the arm). Reacher-v5 is the
reference: a 2-link MuJoCo arm with frame_skip 2 (two mj_step per env step);
Bioscara-Reach runs 20 physics steps and four 10 ms firmware ticks per 25 Hz
control step, plus the joint driver calls. Target: ratio >= 1.0.
"""

from __future__ import annotations

import argparse
import time

import gymnasium as gym

import bioscara_gym  # noqa: F401 - registers the tasks


def steps_per_second(env_id: str, steps: int, **kwargs: object) -> float:
    """Env steps per second with random actions (resets included)."""
    env = gym.make(env_id, **kwargs)
    env.reset(seed=0)
    env.action_space.seed(0)
    start = time.perf_counter()
    for _ in range(steps):
        _, _, terminated, truncated, _ = env.step(env.action_space.sample())
        if terminated or truncated:
            env.reset()
    rate = steps / (time.perf_counter() - start)
    env.close()
    return rate


def reacher_rate(steps: int) -> float:
    """Reacher-v5's steps/s, the better of two runs (its rate varies run to run)."""
    return max(steps_per_second("Reacher-v5", steps) for _ in range(2))


def yardstick(steps: int = 2000) -> str:
    """This machine's speed as Reacher-v5's steps/s (best of two), for wall-clock figures.

    Wall times measured on different machines differ as much as the machines
    do (3.6x between two of this project's 2-core VMs, where the steps a
    training needed did not change); a figure printed beside this rate can be
    scaled to another machine.
    """
    return f"this machine: Gymnasium's Reacher-v5 at {reacher_rate(steps):.0f} random-action steps/s"


def main() -> None:
    """Measure both and print the ratio."""
    parser = argparse.ArgumentParser(description=__doc__)
    parser.add_argument("--steps", type=int, default=5000)
    args = parser.parse_args()
    reacher = reacher_rate(args.steps)
    reach = max(steps_per_second("Bioscara-Reach-v0", args.steps) for _ in range(2))
    print(f"Reacher-v5          : {reacher:8.0f} steps/s")
    print(f"Bioscara-Reach-v0   : {reach:8.0f} steps/s  (velocity mode, sim backend)")
    print(f"ratio Reach/Reacher : {reach / reacher:8.3f}  (target >= 1.0)")


if __name__ == "__main__":
    main()
