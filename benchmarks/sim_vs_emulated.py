"""Success rate of one policy on ``sim`` and on ``emulated``, and the gap between them.

``sim`` drives the firmware cores directly (``SimJoint``); ``emulated`` runs the
real ``Joint`` driver, byte for byte, over ``EmulatedI2CBus`` into the same
firmware and MuJoCo arm: the rehearsal ``bioscara deploy --backend emulated``
gives. Both run the same seeded episodes (seeds ``--seed`` .. ``--seed + N - 1``).
The policy is a trained model (``--model``, SB3 ``.zip`` or ``.onnx``) or,
by default, the scripted expert of ``--env``. Target: gap <= 5 points
(exit code 1 above it).

    python benchmarks/sim_vs_emulated.py                      # expert, 50 episodes
    python benchmarks/sim_vs_emulated.py --model runs/reach/model.zip
    python benchmarks/sim_vs_emulated.py --faults nack=0.01,latency_ms=0.5
"""

from __future__ import annotations

import argparse
import sys
import time
from collections.abc import Callable
from pathlib import Path
from typing import Any

import gymnasium as gym
from rich.console import Console
from rich.table import Table

import bioscara_gym  # noqa: F401 - registers the tasks
from bioscara_gym.hardware.emulated_bus import FaultPlan
from bioscara_gym.training.evaluate import EvalStats, make_eval_env, run_episodes
from bioscara_gym.training.metadata import check_metadata

TARGET_GAP_POINTS = 5.0


def _policy_and_env(args: argparse.Namespace, backend: str) -> tuple[Any, gym.Env, Callable[[], None] | None]:
    options: dict[str, Any] = {}
    if backend == "emulated" and args.faults:
        options["faults"] = FaultPlan.parse(args.faults)
    if args.model is None:
        from bioscara_gym.experts import expert_for

        env = gym.make(args.env, backend=backend, backend_options=options)
        expert = expert_for(env.unwrapped)
        return expert, env, expert.reset
    if Path(args.model).suffix == ".onnx":
        from bioscara_gym.training.export import OnnxPolicy

        policy: Any = OnnxPolicy(args.model)
        metadata = policy.metadata
    else:
        from bioscara_gym.training.evaluate import load_model, sb3_policy

        model, metadata = load_model(Path(args.model))
        policy = sb3_policy(model)
    env = make_eval_env(metadata, backend, backend_options=options)
    check_metadata(metadata, env, metadata["env_id"])
    return policy, env, None


def evaluate(args: argparse.Namespace, backend: str) -> tuple[EvalStats, float]:
    """Stats of ``args.episodes`` seeded episodes on ``backend`` and the wall time they took."""
    policy, env, on_reset = _policy_and_env(args, backend)
    try:
        start = time.perf_counter()
        stats = run_episodes(env, policy, args.episodes, seed=args.seed, on_reset=on_reset)
        return stats, time.perf_counter() - start
    finally:
        env.close()


def main(argv: list[str] | None = None) -> int:
    parser = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    parser.add_argument("--model", type=Path, help="model.zip or .onnx (default: the scripted expert)")
    parser.add_argument("--env", default="Bioscara-Reach-v0", help="env id for the expert")
    parser.add_argument("--episodes", type=int, default=50)
    parser.add_argument("--seed", type=int, default=10_000, help="seed of the first episode")
    parser.add_argument("--faults", help="faults on the emulated bus, e.g. nack=0.01,latency_ms=0.5")
    args = parser.parse_args(argv)

    results = {backend: evaluate(args, backend) for backend in ("sim", "emulated")}
    source = args.model or "scripted expert"
    table = Table(title=f"{source}: {args.episodes} episodes, seeds from {args.seed}")
    for column in ("backend", "success rate", "mean final distance", "stalls", "wall time"):
        table.add_column(column, justify="left" if column == "backend" else "right")
    for backend, (stats, wall) in results.items():
        table.add_row(
            backend + (f" ({args.faults})" if backend == "emulated" and args.faults else ""),
            f"{stats.success_rate:.1%}",
            f"{stats.mean_final_distance * 1000:.2f} mm",
            str(stats.stalls),
            f"{wall:.1f} s",
        )
    con = Console(highlight=False)
    con.print(table)
    gap = abs(results["sim"][0].success_rate - results["emulated"][0].success_rate) * 100
    ok = gap <= TARGET_GAP_POINTS
    con.print(f"gap {gap:.1f} points (target <= {TARGET_GAP_POINTS:g}): {'PASS' if ok else 'FAIL'}")
    return 0 if ok else 1


if __name__ == "__main__":
    sys.exit(main())
