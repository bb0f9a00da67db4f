"""The peer reference for Bioscara-Push: SAC+HER on Gymnasium-Robotics' FetchPush-v4 for the same wall time.

Trains stable-baselines3's SAC with HER on ``FetchPush-v4`` for ``--minutes``
of wall time (the environment's collection included), with rl-zoo3's
published FetchPush settings (``hyperparams/tqc.yml``'s ``her-defaults``:
batch 2048, three layers of 512, gamma 0.95, tau 0.05, learning rate 1e-3,
``future`` goals, 4 per transition; SAC in place of TQC), then reports the
deterministic policy's success over ``--eval-episodes`` seeded episodes as
one JSON line (``benchmarks/train_task.py --fetch-minutes`` reads it).

gymnasium-robotics (the ``[robotics]`` extra) 1.4.2 needs MuJoCo 3: under
MuJoCo 4 its ``set_joint_qpos`` compares joint types with MuJoCo's enums in
a way MuJoCo 4 no longer allows (``np.int32(2) in (mjJNT_HINGE, mjJNT_SLIDE)``
is False), and FetchPush fails on reset. Give it a prefix of its own:

    pip install --target .fetch --no-deps gymnasium-robotics==1.4.2 pettingzoo mujoco==3.4.0 \
        glfw absl-py etils
    PYTHONPATH=.fetch python benchmarks/fetch_push_reference.py --minutes 10 --seed 0
"""

from __future__ import annotations

import argparse
import json
import os
import sys
import time
from typing import Any


def _refuse(message: str) -> int:
    print(f"fetch_push_reference: error: {message}", file=sys.stderr)
    return 2


def _make_env() -> Any:
    import gymnasium as gym
    import gymnasium_robotics

    gym.register_envs(gymnasium_robotics)
    return gym.make("FetchPush-v4")


def _train(minutes: float, seed: int) -> tuple[Any, int]:
    """SAC+HER on FetchPush-v4 until ``minutes`` of wall time have passed; the model and its env steps."""
    from stable_baselines3 import SAC, HerReplayBuffer
    from stable_baselines3.common.callbacks import BaseCallback

    class WallClock(BaseCallback):
        """Stops training once the wall-time budget is spent."""

        def __init__(self, seconds: float) -> None:
            super().__init__()
            self.deadline = time.perf_counter() + seconds

        def _on_step(self) -> bool:
            return time.perf_counter() < self.deadline

    model = SAC(
        "MultiInputPolicy",
        _make_env(),
        buffer_size=1_000_000,
        batch_size=2048,
        gamma=0.95,
        learning_rate=1e-3,
        tau=0.05,
        replay_buffer_class=HerReplayBuffer,
        replay_buffer_kwargs={"goal_selection_strategy": "future", "n_sampled_goal": 4},
        policy_kwargs={"net_arch": [512, 512, 512]},
        seed=seed,
        device="cpu",
    )
    model.learn(total_timesteps=10**9, callback=WallClock(minutes * 60))
    return model, int(model.num_timesteps)


def _success(model: Any, episodes: int, seed: int) -> float:
    env = _make_env()
    successes = 0
    for ep in range(episodes):
        obs, _ = env.reset(seed=seed + ep)
        done, info = False, {}
        while not done:
            action, _ = model.predict(obs, deterministic=True)
            obs, _, terminated, truncated, info = env.step(action)
            done = terminated or truncated
        successes += bool(info.get("is_success", False))
    env.close()
    return successes / episodes


def main(argv: list[str] | None = None) -> int:
    """Train, evaluate, print one JSON line; exit 2 with one line if FetchPush cannot run here."""
    parser = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    parser.add_argument("--minutes", type=float, default=10.0)
    parser.add_argument("--seed", type=int, default=0)
    parser.add_argument("--eval-episodes", type=int, default=100)
    args = parser.parse_args(argv)
    if args.minutes <= 0 or args.eval_episodes < 1 or args.seed < 0:
        return _refuse("--minutes must be > 0, --eval-episodes >= 1 and --seed >= 0")
    try:
        import gymnasium_robotics  # noqa: F401
        import mujoco
    except ModuleNotFoundError as e:
        return _refuse(f"{e.name} is not installed: pip install 'bioscara-gym[robotics]' (see --help)")
    if int(mujoco.__version__.split(".")[0]) >= 4:
        return _refuse(
            f"gymnasium-robotics 1.4.2 fails on MuJoCo {mujoco.__version__} (joint-type enums); "
            "run with a prefix holding mujoco 3, e.g. PYTHONPATH=.fetch (see this script's help)"
        )
    start, load = time.perf_counter(), os.getloadavg()
    model, steps = _train(args.minutes, args.seed)
    wall = time.perf_counter() - start
    success = _success(model, args.eval_episodes, 10_000 + args.seed)
    result = {
        "env": "FetchPush-v4",
        "method": "SAC+HER",
        "seed": args.seed,
        "success": success,
        "env_steps": steps,
        "wall_s": round(wall, 1),
        "mujoco": mujoco.__version__,
        "load_before": load[0],
        "load_after": os.getloadavg()[0],
    }
    print(json.dumps(result), flush=True)
    return 0


if __name__ == "__main__":
    sys.exit(main())
