"""Time to 95 % success on Bioscara-Reach with the default training config.

Runs `bioscara train --env Bioscara-Reach` (SAC + HER, training/configs/sac.yaml)
into a temporary directory, once per seed, and prints the wall-clock time and
env steps at which the periodic evaluation first reached the target on 100
episodes, and the final success rate. Target: >= 95 % within 5 minutes on a
2-core CPU. For scale: SB3's SAC+HER defaults solve Gymnasium-Robotics'
FetchReach (5 cm threshold) in about 3.3 minutes on the same machine.
"""

from __future__ import annotations

import argparse
import statistics
import tempfile
from pathlib import Path

from bioscara_gym.training.train import TrainArgs, TrainResult, train

TARGET_S = 300.0


def run(algo: str, seed: int, timesteps: int | None) -> TrainResult:
    """Train with the defaults into a temporary directory."""
    with tempfile.TemporaryDirectory() as out:
        return train(
            TrainArgs(
                env="Bioscara-Reach", algo=algo, seed=seed, timesteps=timesteps, out=Path(out), progress=False
            )
        )


def main() -> None:
    """Train with the defaults and print the figures."""
    parser = argparse.ArgumentParser(description=__doc__)
    parser.add_argument("--algo", default="sac")
    parser.add_argument("--seeds", type=int, nargs="+", default=[0], help="one run per seed")
    parser.add_argument("--timesteps", type=int, help="budget (default: the config's)")
    args = parser.parse_args()
    times = []
    for seed in args.seeds:
        result = run(args.algo, seed, args.timesteps)
        final = result.final_eval
        final_text = (
            f"final {final.success_rate:.0%} over {final.episodes} episodes, "
            f"{final.mean_final_distance * 1000:.1f} mm mean final distance"
            if final is not None
            else "no final evaluation"
        )
        if result.target_reached_after_s is None:
            times.append(float("inf"))
            spent = f"{result.timesteps} steps ({result.wall_time_s:.0f} s)"
            print(f"seed {seed}: target NOT reached in {spent}; {final_text}")
        else:
            times.append(result.target_reached_after_s)
            print(
                f"seed {seed}: target reached after {result.target_reached_after_s:.0f} s wall, "
                f"{result.target_reached_at} env steps; {final_text}"
            )
    worst = max(times)
    verdict = "met" if worst <= TARGET_S else "NOT met"
    print(
        f"time to 95 %: median {statistics.median(times):.0f} s, worst {worst:.0f} s "
        f"over {len(times)} seed(s) (target <= {TARGET_S:.0f} s: {verdict})"
    )


if __name__ == "__main__":
    main()
