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
from bioscara_gym.training.evaluate import EvalStats, run_episodes
from bioscara_gym.training.extras import needs_train
from bioscara_gym.training.hyperparams import Hyperparams, default_config_path, load_hyperparams
from bioscara_gym.training.metadata import build_metadata, resolve_env_id, write_metadata

with needs_train():
    import torch
    from stable_baselines3 import SAC, HerReplayBuffer
    from stable_baselines3.common.base_class import BaseAlgorithm
    from stable_baselines3.common.callbacks import BaseCallback, CallbackList
    from stable_baselines3.common.env_util import make_vec_env
    from stable_baselines3.common.noise import NormalActionNoise, OrnsteinUhlenbeckActionNoise
    from stable_baselines3.common.off_policy_algorithm import OffPolicyAlgorithm

    from bioscara_gym.training.algos import ALGOS
    from bioscara_gym.training.bc import bc_pretrain
    from bioscara_gym.training.zoo import EVAL_SEED_OFFSET, DemonstrationCallback, SuccessEvalCallback

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
        demos: Minari dataset of demonstrations to learn from (SAC: Nair et al.
            2018, see :mod:`bioscara_gym.training.bc`; ``bc``: cloned alone).
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
    demos: str | None = None


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
    """The hyperparameters of this run (config file or packaged defaults; ``bc`` reads SAC's)."""
    if args.algo not in ALGOS and args.algo != "bc":
        raise TrainingError(f"unknown algo {args.algo!r}; choose one of {', '.join(ALGOS)}, bc")
    algo = "sac" if args.algo == "bc" else args.algo
    path = Path(args.config) if args.config else default_config_path(algo)
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
    specs = list(hp.callbacks)
    if args.demos:  # --demos: this dataset, in the config's demonstration callback or a default one
        specs = [
            (c, {**k, "dataset": args.demos}) if c is DemonstrationCallback else (c, k) for c, k in specs
        ]
        if not any(c is DemonstrationCallback for c, _ in specs):
            specs.append((DemonstrationCallback, {"dataset": args.demos}))
    if any(c is DemonstrationCallback for c, _ in specs) and args.algo != "sac":
        raise TrainingError(f"demonstrations are learned with --algo sac (or bc), not {args.algo}")
    try:
        others = [cls(**kwargs) for cls, kwargs in specs]
    except (TypeError, ValueError) as e:
        raise TrainingError(f"config {hp.source}: callback: {e}") from e
    return evaluator, others


def _demo_facts(callbacks: list[BaseCallback]) -> dict[str, Any]:
    """What the run learned from besides its own experience (for the metadata)."""
    for cb in callbacks:
        if isinstance(cb, DemonstrationCallback) and cb.demos is not None:
            return {
                "demos": {
                    "dataset": cb.dataset,
                    "episodes": len(cb.demos.successes),
                    "steps": len(cb.demos),
                    "collect_s": round(cb.collect_s, 1),
                    "pretrain_steps": cb.pretrain_steps,
                }
            }
    return {}


def train(args: TrainArgs) -> TrainResult:
    """Train, evaluate and save a policy (see the module docstring)."""
    env_id = resolve_env_id(args.env)
    if args.algo == "bc":

        return train_bc(args, env_id, load_run_hyperparams(args, env_id))
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
        args.demos = args.demos or state.get("demos")
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
    if args.demos and args.algo != "sac":
        raise TrainingError(f"demonstrations are learned with --algo sac (or bc), not {args.algo}")
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
                "demos": args.demos if not args.resume else state.get("demos"),
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
            **_demo_facts(others),
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


#: Behaviour-cloning steps of ``bioscara train --algo bc`` without ``--timesteps``.
BC_STEPS = 10_000


def train_bc(args: TrainArgs, env_id: str, hp: Hyperparams) -> TrainResult:
    """``bioscara train --algo bc``: clone the demonstrations into a SAC actor, evaluate, save.

    The policy, its kwargs and the env's kwargs are those of the SAC config's
    entry; ``--timesteps`` counts gradient steps (default :data:`BC_STEPS`).
    Without ``--demos`` the scripted expert's episodes are collected first.
    """
    from bioscara_gym.experts import expert_for
    from bioscara_gym.training.demos import check_demos, load_demos, rollout_demos

    if args.resume:
        raise TrainingError("--algo bc trains in one go; there is nothing to resume")
    steps = int(args.timesteps or BC_STEPS)
    if steps <= 0:
        raise TrainingError(f"timesteps must be > 0, got {steps}")
    torch.set_num_threads(args.threads or 1)
    settings = next((k for c, k in hp.callbacks if c is DemonstrationCallback), {})
    start = time.perf_counter()
    env = gym.make(env_id, **hp.env_kwargs)
    try:
        if args.demos:
            demos = load_demos(args.demos, successful_only=True)
            check_demos(demos, env)
        else:
            expert = expert_for(env.unwrapped)
            episodes, seed = int(settings.get("episodes", 100)), int(settings.get("seed", 1_000_000))
            demos = rollout_demos(env, expert, expert.reset, episodes, seed=seed)
        kwargs = _algo_kwargs(hp, env, "sac")
        kwargs.update(replay_buffer_class=None, replay_buffer_kwargs=None, buffer_size=1, action_noise=None)
        model = SAC(hp.policy, env, seed=args.seed, device="cpu", verbose=0, **kwargs)
        loss = bc_pretrain(
            model, demos, steps, init_std=float(settings.get("init_std", 0.1)), seed=args.seed
        )
        eval_env = gym.make(env_id, **hp.env_kwargs)
        try:

            def act(obs: dict[str, np.ndarray]) -> np.ndarray:
                return model.predict(obs, deterministic=True)[0]

            final = run_episodes(eval_env, act, hp.eval_episodes, seed=args.seed + EVAL_SEED_OFFSET)
        finally:
            eval_env.close()
        out = Path(args.out)
        out.mkdir(parents=True, exist_ok=True)
        model_path = out / "model.zip"
        model.save(model_path)
        metadata_path = write_metadata(
            out,
            build_metadata(
                env,
                env_id,
                hp.env_kwargs,
                algo="bc",
                seed=args.seed,
                timesteps=0,
                bc_steps=steps,
                bc_loss=loss,
                demos={"dataset": args.demos, "episodes": len(demos.successes), "steps": len(demos)},
                config=hp.as_dict(),
                final_eval=final.as_dict(),
            ),
        )
    finally:
        env.close()
    if args.verbose:
        print(f"[bc] {steps} steps on {len(demos)} demonstration steps, loss {loss:.4f}", flush=True)
    return TrainResult(
        model_path=model_path,
        metadata_path=metadata_path,
        timesteps=0,
        wall_time_s=time.perf_counter() - start,
        final_eval=final,
        target_reached_at=None,
        target_reached_after_s=None,
    )
