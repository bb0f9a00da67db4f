"""Time to target on Bioscara-Reach with the default training config, and SAC+HER alone.

Runs `bioscara train --env Bioscara-Reach` (SAC + HER with demonstrations,
training/configs/sac.yaml) into a temporary directory, once per seed, and
prints the wall-clock time and env steps at which the periodic evaluation
first reached the config's ``target_success`` (98 %) on 100 episodes, and the
final success rate. With ``--no-demos``: the same entry without its
demonstration callback and with the target set to 95 % (SAC + HER alone,
which rarely reaches 98 %). Target (issue #27): time to 95 % a median of at
most 20 s over 5 seeds, worst at most 40 s, on a 2-core CPU. For scale: SB3's
SAC+HER defaults solve Gymnasium-Robotics' FetchReach (5 cm threshold) in
about 3.3 minutes on the same machine.
"""

from __future__ import annotations

import argparse
import statistics
import tempfile
from pathlib import Path

import yaml
from env_step import yardstick

from bioscara_gym.training.hyperparams import default_config_path
from bioscara_gym.training.train import TrainArgs, TrainResult, train

ENV_ID = "Bioscara-Reach-v0"
MEDIAN_S = 20.0
WORST_S = 40.0
DEMO_CALLBACK = "bioscara_gym.training.zoo.DemonstrationCallback"
EVAL_CALLBACK = "bioscara_gym.training.zoo.SuccessEvalCallback"


def sac_her_alone(directory: Path) -> Path:
    """The packaged Reach entry without its demonstration callback, stopping at 95 %."""
    entry = yaml.safe_load(default_config_path("sac").read_text(encoding="utf-8"))[ENV_ID]
    callbacks = [c for c in entry.get("callback", []) if DEMO_CALLBACK not in c]
    for callback in callbacks:
        if EVAL_CALLBACK in callback:
            callback[EVAL_CALLBACK]["target_success"] = 0.95
            # at eval_freq, as SAC + HER alone has no cloned actor to judge at the first step
            callback[EVAL_CALLBACK].pop("first_eval", None)
    entry["callback"] = callbacks
    path = directory / "sac_her_alone.yaml"
    path.write_text(yaml.safe_dump({ENV_ID: entry}), encoding="utf-8")
    return path


def run(algo: str, seed: int, timesteps: int | None, demos: bool) -> TrainResult:
    """Train with the defaults (``demos``) or SAC + HER alone into a temporary directory."""
    with tempfile.TemporaryDirectory() as out:
        config = None if demos else sac_her_alone(Path(out))
        return train(
            TrainArgs(
                env="Bioscara-Reach",
                algo=algo,
                config=config,
                seed=seed,
                timesteps=timesteps,
                out=Path(out) / "run",
                progress=False,
            )
        )


def main() -> None:
    """Train with the defaults and print the figures."""
    parser = argparse.ArgumentParser(description=__doc__)
    parser.add_argument("--algo", default="sac")
    parser.add_argument("--seeds", type=int, nargs="+", default=[0], help="one run per seed")
    parser.add_argument("--timesteps", type=int, help="budget (default: the config's)")
    parser.add_argument("--no-demos", action="store_true", help="SAC + HER alone, to 95 %%")
    args = parser.parse_args()
    if args.no_demos and args.algo != "sac":
        parser.error("--no-demos changes the SAC entry; use it with --algo sac")
    print(yardstick(), flush=True)
    times = []
    for seed in args.seeds:
        result = run(args.algo, seed, args.timesteps, demos=not args.no_demos)
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
    median, worst = statistics.median(times), max(times)
    verdict = "met" if median <= MEDIAN_S and worst <= WORST_S else "NOT met"
    print(
        f"time to target: median {median:.0f} s, worst {worst:.0f} s over {len(times)} seed(s) "
        f"(target: median <= {MEDIAN_S:.0f} s, worst <= {WORST_S:.0f} s: {verdict})"
    )


if __name__ == "__main__":
    main()
