"""Time to 95 % success on Bioscara-Reach with the default training config.

Runs `bioscara train --env Bioscara-Reach` (SAC + HER, training/configs/sac.yaml)
into a temporary directory and prints the wall-clock time and env steps at
which the periodic evaluation first reached the target on 100 episodes, and
the final success rate. Target: >= 95 % within 5 minutes on a 2-core CPU.
"""

from __future__ import annotations

import argparse
import tempfile
from pathlib import Path

from training.train import TrainArgs, train


def main() -> None:
    """Train with the defaults and print the figures."""
    parser = argparse.ArgumentParser(description=__doc__)
    parser.add_argument("--algo", default="sac")
    parser.add_argument("--seed", type=int, default=0)
    parser.add_argument("--timesteps", type=int, help="budget (default: the config's)")
    args = parser.parse_args()
    with tempfile.TemporaryDirectory() as out:
        result = train(
            TrainArgs(
                env="Bioscara-Reach",
                algo=args.algo,
                seed=args.seed,
                timesteps=args.timesteps,
                out=Path(out),
                progress=False,
            )
        )
    final = result.final_eval
    if result.target_reached_at is None:
        print(f"target not reached within {result.timesteps} steps ({result.wall_time_s:.0f} s)")
    else:
        print(
            f"time to target : {result.target_reached_after_s:.0f} s wall, "
            f"{result.target_reached_at} env steps"
        )
    if final is not None:
        print(
            f"final success  : {final.success_rate:.1%} over {final.episodes} episodes, "
            f"mean final distance {final.mean_final_distance * 1000:.1f} mm"
        )
    print(f"total          : {result.timesteps} steps in {result.wall_time_s:.0f} s")


if __name__ == "__main__":
    main()
