"""Train a policy with stable-baselines3 on CPU: ``bioscara train``.

Reads top to bottom: resolve the env and its hyperparameters, build the envs,
build (or resume) the model, learn with periodic success evaluation, early
stop and checkpoints, then save ``model.zip`` next to ``metadata.json``.
"""

from __future__ import annotations

import json
import re
import time
from dataclasses import dataclass
from pathlib import Path
from typing import Any

import gymnasium as gym
import numpy as np

import bioscara_gym  # noqa: F401 - registers the tasks
from bioscara_gym.errors import HyperparamError, TrainingError
from bioscara_gym.fsutil import atomic_write_text
from bioscara_gym.training.evaluate import EvalStats
from bioscara_gym.training.extras import needs_train
from bioscara_gym.training.hyperparams import Hyperparams, default_config_path, load_hyperparams
from bioscara_gym.training.metadata import build_metadata, resolve_env_id, write_metadata

with needs_train():
    import torch
    from stable_baselines3 import HerReplayBuffer
    from stable_baselines3.common.base_class import BaseAlgorithm
    from stable_baselines3.common.callbacks import BaseCallback, CallbackList
    from stable_baselines3.common.env_util import make_vec_env
    from stable_baselines3.common.noise import NormalActionNoise, OrnsteinUhlenbeckActionNoise
    from stable_baselines3.common.off_policy_algorithm import OffPolicyAlgorithm

    from bioscara_gym.training.algos import ALGOS
    from bioscara_gym.training.zoo import SuccessEvalCallback

REPLAY_BUFFERS = {"HerReplayBuffer": HerReplayBuffer}
#: Keys whose value may be one of rl-zoo3's schedule strings ``lin_<initial value>``.
SCHEDULE_KEYS = ("learning_rate", "clip_range", "clip_range_vf")
STATE_NAME = "train_state.json"
CHECKPOINT_RE = re.compile(r"ckpt_(\d+)_steps\.zip$")


@dataclass
class TrainArgs:
    """Arguments of ``bioscara train`` (the CLI flags map one to one).

    Attributes:
        env: Env id (``Bioscara-Reach`` or a versioned id).
        algo: ``sac``, ``td3`` or ``ppo``.
        config: Hyperparameter file (rl-zoo3 format); default the packaged one.
        timesteps: Training budget; default the config's ``n_timesteps``.
        seed: Seed of the model, the envs and the evaluation episodes.
        out: Output directory (model, metadata, checkpoints, TensorBoard logs).
        resume: Continue from the newest checkpoint in ``out``.
        progress: Show a progress bar.
        checkpoint_freq: Env steps between checkpoints.
        threads: Torch CPU threads. Default 1: the env steps in the same
            process, and on a 2-core machine a second torch thread only
            contends with it (measured 20x slower matrix products).
        verbose: Print each evaluation.
    """

    env: str = "Bioscara-Reach"
    algo: str = "sac"
    config: Path | None = None
    timesteps: int | None = None
    seed: int = 0
    out: Path = Path("runs/reach")
    resume: bool = False
    progress: bool = True
    checkpoint_freq: int = 10_000
    threads: int | None = None
    verbose: int = 1


@dataclass(frozen=True)
class TrainResult:
    """What a run produced."""

    model_path: Path
    metadata_path: Path
    timesteps: int
    wall_time_s: float
    final_eval: EvalStats | None
    target_reached_at: int | None
    target_reached_after_s: float | None


def load_run_hyperparams(args: TrainArgs, env_id: str) -> Hyperparams:
    """The hyperparameters of this run (config file or packaged defaults)."""
    if args.algo not in ALGOS:
        raise TrainingError(f"unknown algo {args.algo!r}; choose one of {', '.join(ALGOS)}")
    path = Path(args.config) if args.config else default_config_path(args.algo)
    try:
        return load_hyperparams(path, env_id)
    except HyperparamError as e:
        raise TrainingError(str(e)) from e


class CheckpointEvery(BaseCallback):
    """Save the model (and replay buffer) every ``freq`` env steps."""

    def __init__(self, directory: Path, freq: int) -> None:
        """Checkpoints go to ``directory``."""
        super().__init__()
        self.directory = directory
        self.freq = freq
        self._next = freq

    def _on_training_start(self) -> None:
        self._next = (self.num_timesteps // self.freq + 1) * self.freq

    def _on_step(self) -> bool:
        if self.num_timesteps >= self._next:
            self._next += self.freq
            save_checkpoint(self.model, self.directory)
        return True


def save_checkpoint(model: BaseAlgorithm, directory: Path) -> Path:
    """Save ``model`` (and its replay buffer) as ``ckpt_<steps>_steps.zip``."""
    directory.mkdir(parents=True, exist_ok=True)
    path = directory / f"ckpt_{model.num_timesteps}_steps.zip"
    if isinstance(model, OffPolicyAlgorithm):
        model.save_replay_buffer(directory / f"ckpt_{model.num_timesteps}_steps_replay.pkl")
    model.save(path)  # written last: a checkpoint exists only once complete
    return path


def newest_checkpoint(directory: Path) -> Path | None:
    """The checkpoint with the most steps in ``directory``."""
    found = [
        (int(m.group(1)), p)
        for p in directory.glob("ckpt_*_steps.zip")
        if (m := CHECKPOINT_RE.search(p.name))
    ]
    return max(found)[1] if found else None


def _linear_schedule(initial: float) -> Any:
    """rl-zoo3's ``lin_<initial>``: from ``initial`` at the start down to 0 at the end."""

    def schedule(progress_remaining: float) -> float:
        return progress_remaining * initial

    return schedule


def _algo_kwargs(hp: Hyperparams, env: Any, algo: str) -> dict[str, Any]:
    kwargs = dict(hp.algo_kwargs)
    for key in SCHEDULE_KEYS:
        value = kwargs.get(key)
        if isinstance(value, str):
            kind, _, initial = value.partition("_")
            try:
                if kind != "lin":
                    raise ValueError(kind)
                kwargs[key] = _linear_schedule(float(initial))
            except ValueError as e:
                raise TrainingError(f"config {hp.source}: {key} {value!r} is not a number or lin_<x>") from e
    if isinstance(kwargs.get("train_freq"), list):
        kwargs["train_freq"] = tuple(kwargs["train_freq"])  # YAML has no tuples; SB3 wants (n, unit)
    rb = kwargs.get("replay_buffer_class")
    if isinstance(rb, str):
        if rb not in REPLAY_BUFFERS:
            raise TrainingError(f"config {hp.source}: unknown replay_buffer_class {rb!r}")
        kwargs["replay_buffer_class"] = REPLAY_BUFFERS[rb]
    space = env.observation_space
    is_goal_env = isinstance(space, gym.spaces.Dict) and "desired_goal" in space.spaces
    if algo in ("sac", "td3") and is_goal_env and "replay_buffer_class" not in kwargs:
        kwargs["replay_buffer_class"] = HerReplayBuffer  # goal env: HER automatically
        kwargs.setdefault("replay_buffer_kwargs", {"goal_selection_strategy": "future", "n_sampled_goal": 4})
    if hp.noise_type:
        n = env.action_space.shape[0]
        noise_cls = {"normal": NormalActionNoise, "ornstein-uhlenbeck": OrnsteinUhlenbeckActionNoise}.get(
            hp.noise_type
        )
        if noise_cls is None:
            raise TrainingError(f"config {hp.source}: unknown noise_type {hp.noise_type!r}")
        kwargs["action_noise"] = noise_cls(np.zeros(n), hp.noise_std * np.ones(n))
    return kwargs


def _callbacks(hp: Hyperparams, eval_env: gym.Env, args: TrainArgs) -> tuple[Any, list[BaseCallback]]:
    """The config's success evaluation (on ``eval_env``) and its other callbacks, as rl-zoo3 builds them."""
    eval_kwargs = {"seed": args.seed + 10_000, **hp.eval_kwargs, "verbose": args.verbose}
    evaluator = SuccessEvalCallback(
        eval_freq=hp.eval_freq,
        eval_episodes=hp.eval_episodes,
        target_success=hp.target_success,
        env=eval_env,
        **eval_kwargs,
    )
    try:
        others = [cls(**kwargs) for cls, kwargs in hp.callbacks]
    except (TypeError, ValueError) as e:
        raise TrainingError(f"config {hp.source}: callback: {e}") from e
    return evaluator, others


def train(args: TrainArgs) -> TrainResult:
    """Train, evaluate and save a policy (see the module docstring)."""
    env_id = resolve_env_id(args.env)
    out = Path(args.out)
    state_path = out / STATE_NAME
    state: dict[str, Any] = {}
    if args.resume:
        if not state_path.exists():
            raise TrainingError(f"nothing to resume in {out}: no {STATE_NAME}")
        state = json.loads(state_path.read_text(encoding="utf-8"))
        if state["env_id"] != env_id or state["algo"] != args.algo:
            raise TrainingError(
                f"{out} holds a {state['algo']} run on {state['env_id']}, not {args.algo} on {env_id}"
            )
        args.seed, total = state["seed"], int(state["total_timesteps"])
        hp = (
            load_run_hyperparams(args, env_id)
            if not state.get("config")
            else load_hyperparams(Path(state["config"]), env_id)
        )
    else:
        hp = load_run_hyperparams(args, env_id)
        total = int(args.timesteps or hp.n_timesteps)
    if total <= 0:
        raise TrainingError(f"timesteps must be > 0, got {total}")
    torch.set_num_threads(args.threads or 1)
    out.mkdir(parents=True, exist_ok=True)
    atomic_write_text(
        state_path,
        json.dumps(
            {
                "env_id": env_id,
                "algo": args.algo,
                "seed": args.seed,
                "total_timesteps": total,
                "config": str(args.config) if args.config else (state.get("config") if args.resume else None),
            },
            indent=2,
        ),
    )

    env = make_vec_env(env_id, n_envs=hp.n_envs, seed=args.seed, env_kwargs=hp.env_kwargs)
    eval_env = gym.make(env_id, **hp.env_kwargs)
    algo_cls = ALGOS[args.algo]
    ckpt_dir = out / "checkpoints"
    if args.resume:
        ckpt = newest_checkpoint(ckpt_dir)
        if ckpt is None:
            raise TrainingError(f"nothing to resume in {ckpt_dir}: no checkpoint")
        model = algo_cls.load(ckpt, env=env, device="cpu")
        replay = ckpt.with_name(ckpt.stem + "_replay.pkl")
        if isinstance(model, OffPolicyAlgorithm) and replay.exists():
            model.load_replay_buffer(replay)
    else:
        model = algo_cls(
            hp.policy,
            env,
            seed=args.seed,
            device="cpu",
            tensorboard_log=str(out / "tb"),
            verbose=0,
            **_algo_kwargs(hp, env, args.algo),
        )
    evaluator, others = _callbacks(hp, eval_env, args)
    callbacks = CallbackList([evaluator, *others, CheckpointEvery(ckpt_dir, args.checkpoint_freq)])
    start = time.perf_counter()
    try:
        model.learn(
            total_timesteps=max(total - model.num_timesteps, 0),
            callback=callbacks,
            reset_num_timesteps=not args.resume,
            progress_bar=args.progress,
            tb_log_name="run",
        )
    except KeyboardInterrupt:
        save_checkpoint(model, ckpt_dir)  # `bioscara train --resume` continues from here
        raise
    finally:
        env.close()
    final = evaluator.last if evaluator.reached_at is not None else evaluator.evaluate(hp.eval_episodes)
    model_path = out / "model.zip"
    model.save(model_path)
    metadata_path = write_metadata(
        out,
        build_metadata(
            eval_env,
            env_id,
            hp.env_kwargs,
            algo=args.algo,
            seed=args.seed,
            timesteps=model.num_timesteps,
            config=hp.as_dict(),
            final_eval=final.as_dict() if final else None,
        ),
    )
    eval_env.close()
    return TrainResult(
        model_path=model_path,
        metadata_path=metadata_path,
        timesteps=model.num_timesteps,
        wall_time_s=time.perf_counter() - start,
        final_eval=final,
        target_reached_at=evaluator.reached_at,
        target_reached_after_s=evaluator.reached_after_s,
    )
