"""SAC, TD3 and PPO through stable-baselines3: the runner of the rl-zoo3 methods (``--algo sac|td3|ppo``).

One :class:`SB3Method` fills in the steps of
:class:`~bioscara_gym.training.base.TrainingMethod` for every algorithm of
:data:`~bioscara_gym.training.algos.ALGOS`: the hyperparameters are the
method's rl-zoo3 file (``training/configs/ALGO.yaml``) read as rl-zoo3 reads
it (:mod:`~bioscara_gym.training.hyperparams`), the envs a vectorized
training env and an evaluation env, the callbacks the config's (the success
evaluation that stops training at the target, demonstrations) plus a
checkpoint every ``checkpoint_freq`` env steps, saved with the replay buffer.
Off-policy algorithms on the goal tasks use HER.
"""

from __future__ import annotations

import contextlib
import inspect
import json
import warnings
import zipfile
from pathlib import Path
from typing import Any, BinaryIO

import gymnasium as gym
import numpy as np

from bioscara_gym.errors import CheckpointWarning, HyperparamError, TrainingError
from bioscara_gym.training.base import Resumed, RunPlan, TrainingMethod
from bioscara_gym.training.checkpoints import (
    checkpoint_dir,
    companion_path,
    load_newest,
    reason,
    save_checkpoint,
)
from bioscara_gym.training.evaluate import EvalStats
from bioscara_gym.training.extras import needs_train
from bioscara_gym.training.hyperparam_values import schedule_start, shown
from bioscara_gym.training.hyperparams import Hyperparams, check_algo_kwargs, load_hyperparams
from bioscara_gym.training.signals import SignalGuard

with needs_train():
    from stable_baselines3 import HerReplayBuffer
    from stable_baselines3.common.base_class import BaseAlgorithm
    from stable_baselines3.common.callbacks import BaseCallback, CallbackList
    from stable_baselines3.common.env_util import make_vec_env
    from stable_baselines3.common.noise import NormalActionNoise, OrnsteinUhlenbeckActionNoise
    from stable_baselines3.common.off_policy_algorithm import OffPolicyAlgorithm
    from stable_baselines3.common.vec_env import SubprocVecEnv

    from bioscara_gym.training.algos import sb3_class
    from bioscara_gym.training.parallel import env_maker
    from bioscara_gym.training.zoo import DemonstrationCallback, SuccessEvalCallback

REPLAY_BUFFERS = {"HerReplayBuffer": HerReplayBuffer}
#: Keys whose value may be one of rl-zoo3's schedule strings ``lin_<initial value>``.
SCHEDULE_KEYS = ("learning_rate", "clip_range", "clip_range_vf")
#: The replay buffer saved with a checkpoint, beside it.
REPLAY_SUFFIX = "_replay.pkl"


def load_run_hyperparams(spec_model: str, path: Path, env_id: str) -> Hyperparams:
    """``env_id``'s entry of rl-zoo3 file ``path``, its keys checked against the SB3 class ``spec_model``.

    Raises:
        TrainingError: Unreadable, malformed, or a key the algorithm does not take.
    """
    try:
        hp = load_hyperparams(path, env_id)
        check_algo_kwargs(hp, sb3_class(spec_model), env_id)
    except HyperparamError as e:
        raise TrainingError(str(e)) from e
    return hp


def _linear_schedule(initial: float) -> Any:
    """rl-zoo3's ``lin_<initial>``: from ``initial`` at the start down to 0 at the end."""

    def schedule(progress_remaining: float) -> float:
        return progress_remaining * initial

    return schedule


def algo_kwargs(hp: Hyperparams, env: Any, algo: str) -> dict[str, Any]:
    """The algorithm's keyword arguments from ``hp``: schedules, replay buffer (HER on goal tasks), noise.

    Raises:
        TrainingError: An unknown schedule, replay buffer or noise type.
    """
    kwargs = dict(hp.algo_kwargs)
    for key in SCHEDULE_KEYS:
        value = kwargs.get(key)
        if isinstance(value, str):  # check_algo_counts checked x when the file was read
            initial = schedule_start(value)
            if initial is None:
                raise TrainingError(f"config {hp.source}: {key} {shown(value)} is not a number or lin_<x>")
            kwargs[key] = _linear_schedule(initial)
    if isinstance(kwargs.get("train_freq"), list):
        kwargs["train_freq"] = tuple(kwargs["train_freq"])  # YAML has no tuples; SB3 wants (n, unit)
    rb = kwargs.get("replay_buffer_class")
    if isinstance(rb, str):
        if rb not in REPLAY_BUFFERS:
            raise TrainingError(f"config {hp.source}: unknown replay_buffer_class {shown(rb)}")
        kwargs["replay_buffer_class"] = REPLAY_BUFFERS[rb]
    space = env.observation_space
    is_goal_env = isinstance(space, gym.spaces.Dict) and "desired_goal" in space.spaces
    if algo in ("sac", "td3") and is_goal_env and "replay_buffer_class" not in kwargs:
        kwargs["replay_buffer_class"] = HerReplayBuffer  # goal env: HER automatically
        kwargs.setdefault("replay_buffer_kwargs", {"goal_selection_strategy": "future", "n_sampled_goal": 4})
    if hp.noise_type:
        n = env.action_space.shape[0]
        noises = {"normal": NormalActionNoise, "ornstein-uhlenbeck": OrnsteinUhlenbeckActionNoise}
        noise_cls = noises.get(hp.noise_type) if isinstance(hp.noise_type, str) else None
        if noise_cls is None:
            raise TrainingError(f"config {hp.source}: unknown noise_type {shown(hp.noise_type)}")
        kwargs["action_noise"] = noise_cls(np.zeros(n), hp.noise_std * np.ones(n))
    return kwargs


# ------------------------------------------------------------------ checkpoints
def save_sb3_checkpoint(model: BaseAlgorithm, directory: Path) -> Path:
    """Save ``model`` (and an off-policy model's replay buffer) as ``ckpt_<steps>_steps.zip``."""
    companions = {}
    if isinstance(model, OffPolicyAlgorithm):

        def write_buffer(f: BinaryIO) -> None:
            model.save_replay_buffer(f)

        companions[REPLAY_SUFFIX] = write_buffer
    return save_checkpoint(model, directory, model.num_timesteps, companions)


def load_sb3_checkpoint(algo_cls: type[BaseAlgorithm], path: Path, env: Any) -> BaseAlgorithm:
    """A checkpoint of ``algo_cls`` with (off-policy) its replay buffer.

    Raises:
        FileNotFoundError: See :func:`check_replay_buffer`.
    """
    check_replay_buffer(algo_cls, path)
    model = algo_cls.load(path, env=env, device="cpu")
    if isinstance(model, OffPolicyAlgorithm):
        _load_replay_buffer(model, companion_path(path, REPLAY_SUFFIX))
    return model


def check_replay_buffer(algo_cls: type[BaseAlgorithm], path: Path) -> None:
    """Refuse an off-policy checkpoint without its replay buffer.

    Raises:
        FileNotFoundError: It would train on an empty one (seen: HER's
            "Unable to sample" traceback).
    """
    replay = companion_path(path, REPLAY_SUFFIX)
    if issubclass(algo_cls, OffPolicyAlgorithm) and not replay.exists():
        raise FileNotFoundError(f"its replay buffer {replay.name} is missing")


def _load_replay_buffer(model: OffPolicyAlgorithm, path: Path) -> None:
    """Load a checkpoint's replay buffer; stable-baselines3's warnings become one line each.

    HER's buffer keeps the episode the checkpoint cut short, marked as
    ended where it was cut (a time-out, so its last value is bootstrapped),
    and samples it: training restarts the env, so that episode never ends
    otherwise. stable-baselines3 says so in a four-line warning that
    suggests ``truncate_last_trajectory=False``, which would be wrong here.
    """
    with warnings.catch_warnings(record=True) as caught:
        warnings.simplefilter("always")
        model.load_replay_buffer(path)
    for warning in caught:
        text = str(warning.message)
        if "last trajectory in the replay buffer will be truncated" in text:
            text = (
                "the episode the checkpoint cut short stays in the replay buffer, ended where it "
                "was cut (training starts a new one)"
            )
        warnings.warn(" ".join(text.split()), CheckpointWarning, stacklevel=3)


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
            save_sb3_checkpoint(self.model, self.directory)
        return True


def collection_steps(
    hp: Hyperparams, algo_cls: type[BaseAlgorithm], n_envs: int, episode_steps: int | None
) -> int | None:
    """Env steps one collection takes: how far past its budget a run may end (``None``: unbounded).

    PPO collects whole rollouts (``n_steps`` an env), an off-policy
    algorithm ``train_freq`` steps or episodes (of at most ``episode_steps``),
    before it looks at the budget.
    """
    defaults = {k: p.default for k, p in inspect.signature(algo_cls).parameters.items()}
    kwargs = {**defaults, **hp.algo_kwargs}
    try:
        if not issubclass(algo_cls, OffPolicyAlgorithm):
            return int(kwargs["n_steps"]) * n_envs
        freq = kwargs["train_freq"]
        n, unit = (freq, "step") if isinstance(freq, int) else tuple(freq)
        per_env = int(n) * (int(episode_steps) if unit == "episode" else 1)  # type: ignore[arg-type]
    except (TypeError, ValueError):  # malformed, or episodes without a limit: no bound
        return None
    return per_env * n_envs


def saved_n_envs(checkpoint: Path) -> int:
    """The envs a checkpoint's model stepped (its ``data``'s ``n_envs``); 1 if it does not say."""
    try:
        with zipfile.ZipFile(checkpoint) as archive:
            n_envs = json.loads(archive.read("data")).get("n_envs")
    except (OSError, KeyError, ValueError, zipfile.BadZipFile, AttributeError):
        return 1  # a damaged checkpoint is named when it is loaded
    return n_envs if isinstance(n_envs, int) and not isinstance(n_envs, bool) and n_envs >= 1 else 1


# ---------------------------------------------------------------------- method
class SB3Method(TrainingMethod):
    """A stable-baselines3 algorithm trained from its rl-zoo3 file (see the module docstring)."""

    def plan(self) -> RunPlan:
        """The config's entry (``--config``, the run's on ``--resume``, else the packaged one) and budget.

        On ``--resume`` also the run's envs (:meth:`_resumed_n_envs`).
        """
        args = self.args
        if args.resume:
            resumed = self.resumed()
            hp = self._hyperparams(resumed.config)
            # The run's own envs, which --resume may not repeat (seen: a PPO run on 8 refused on 1).
            n_envs = max(args.n_envs or hp.n_envs, saved_n_envs(resumed.newest))
            steps = self.episode_steps(hp.env_kwargs)
            self.check_budget(resumed, collection_steps(hp, sb3_class(self.spec.model), n_envs, steps))
            total, config, demos = resumed.total, resumed.config, resumed.demos
            n_envs = self._resumed_n_envs(resumed)
        else:
            config = str(args.config) if args.config else None
            hp = self._hyperparams(config)
            total, demos, n_envs = args.timesteps or hp.n_timesteps, args.demos, None
        if args.demos and self.spec.name != "sac":
            raise TrainingError(f"demonstrations are learned with --algo sac (or bc), not {self.spec.name}")
        return RunPlan(hp, hp.env_kwargs, int(total), self.run_state(total, config, demos), n_envs)

    def _resumed_n_envs(self, resumed: Resumed) -> int:
        """The envs a resumed run steps: its checkpoint's, or (PPO) ``--n-envs``.

        The checkpoint is the newest whole one with its replay buffer (as
        :meth:`build_model` will load), found before any env is made. An
        off-policy run keeps its envs: its replay buffer holds a column of
        each (seen: a run on 2 resumed on the config's 1 ended in "cannot
        reshape array of size 4 into shape (2,4)"); PPO's rollouts start anew.

        Raises:
            TrainingError: No such checkpoint, or another ``--n-envs`` than an
                off-policy run's.
        """
        algo_cls = sb3_class(self.spec.model)
        with warnings.catch_warnings():
            warnings.simplefilter("ignore", CheckpointWarning)  # build_model's load names a skipped one
            _, path = load_newest(checkpoint_dir(self.out), lambda p: check_replay_buffer(algo_cls, p))
        saved, given = saved_n_envs(path), self.args.n_envs
        if given is not None and given != saved and issubclass(algo_cls, OffPolicyAlgorithm):
            envs = "1 env" if saved == 1 else f"{saved} envs"
            raise TrainingError(
                f"--resume continues {self.out}'s {envs}, whose episodes its replay buffer holds; "
                f"--n-envs {given} would change them (drop it, or train a new run with --out elsewhere)"
            )
        return given or saved

    def _hyperparams(self, config: str | None) -> Hyperparams:
        """The entry of ``config`` (``None``: the packaged file), checked against the algorithm."""
        path = Path(config) if config else self.spec.default_config()
        return load_run_hyperparams(self.spec.model, path, self.env_id)

    def make_envs(self, plan: RunPlan, stack: contextlib.ExitStack) -> gym.Env:
        """The evaluation env, then the vectorized training envs (``n_envs``, seeded; subprocesses if > 1)."""
        hp = plan.config
        self.eval_env = stack.enter_context(contextlib.closing(gym.make(self.env_id, **hp.env_kwargs)))
        self.algo_kwargs = algo_kwargs(hp, self.eval_env, self.spec.name)  # the training envs' spaces
        n_envs = plan.n_envs or self.args.n_envs or hp.n_envs
        self.env = make_vec_env(
            env_maker(self.env_id),
            n_envs=n_envs,
            seed=self.args.seed,
            env_kwargs=hp.env_kwargs,
            # each env in a process of its own (training/parallel.py)
            vec_env_cls=SubprocVecEnv if n_envs > 1 else None,
            vec_env_kwargs={"start_method": "spawn"} if n_envs > 1 else None,
        )
        stack.callback(self.env.close)
        return self.eval_env

    def callbacks(self, plan: RunPlan) -> list[Any]:
        """The config's success evaluation (on the evaluation env), its other callbacks, checkpoints."""
        hp, args = plan.config, self.args
        eval_kwargs = {"seed": args.seed + 10_000, **hp.eval_kwargs, "verbose": args.verbose}
        self.evaluator = SuccessEvalCallback(
            eval_freq=hp.eval_freq,
            eval_episodes=hp.eval_episodes,
            target_success=hp.target_success,
            env=self.eval_env,
            **eval_kwargs,
        )
        specs = list(hp.callbacks)
        if args.demos:  # --demos: this dataset, in the config's demonstration callback or a default one
            specs = [
                (c, {**k, "dataset": args.demos}) if c is DemonstrationCallback else (c, k) for c, k in specs
            ]
            if not any(c is DemonstrationCallback for c, _ in specs):
                specs.append((DemonstrationCallback, {"dataset": args.demos}))
        if any(c is DemonstrationCallback for c, _ in specs) and self.spec.name != "sac":
            raise TrainingError(f"demonstrations are learned with --algo sac (or bc), not {self.spec.name}")
        try:
            self.others = [cls(**kwargs) for cls, kwargs in specs]
        except (TypeError, ValueError) as e:
            raise TrainingError(f"config {hp.source}: callback: {e}") from e
        every = CheckpointEvery(checkpoint_dir(self.out), args.checkpoint_freq)
        return [self.evaluator, *self.others, every]

    def build_model(self, plan: RunPlan) -> BaseAlgorithm:
        """A new model, or (``--resume``) the newest checkpoint that loads, with its replay buffer."""
        algo_cls = sb3_class(self.spec.model)
        if self.args.resume:
            model, _ = load_newest(
                checkpoint_dir(self.out), lambda path: load_sb3_checkpoint(algo_cls, path, self.env)
            )
            return model
        hp = plan.config
        try:
            return algo_cls(
                hp.policy,
                self.env,
                seed=self.args.seed,
                device="cpu",
                tensorboard_log=str(self.out / "tb"),
                verbose=0,
                **self.algo_kwargs,
            )
        except (TypeError, ValueError) as e:  # e.g. a key inside policy_kwargs the policy does not take
            raise TrainingError(f"config {hp.source}: {self.env_id}: {reason(e)}") from e
        except MemoryError as e:  # seen: buffer_size 10**12, numpy's "Unable to allocate 21.8 TiB" traceback
            raise TrainingError(
                f"config {hp.source}: {self.env_id}: the model does not fit in memory ({reason(e)}); "
                "lower buffer_size"
            ) from e

    def learn(self, plan: RunPlan, callbacks: list[Any], guard: SignalGuard) -> None:
        """``model.learn`` for what is left of the budget; the success evaluation may stop it early."""
        self.model.learn(
            total_timesteps=max(plan.total - self.model.num_timesteps, 0),
            callback=CallbackList(callbacks),
            reset_num_timesteps=not self.args.resume,
            progress_bar=self.args.progress,
            tb_log_name="run",
        )
        self.reached_at = self.evaluator.reached_at
        self.reached_after_s = self.evaluator.reached_after_s

    def evaluate(self, plan: RunPlan) -> EvalStats:
        """The full evaluation that stopped training, else ``eval_episodes`` episodes now."""
        if self.evaluator.stopped_at is not None and self.evaluator.last is not None:
            return self.evaluator.last
        return self.evaluator.evaluate(plan.config.eval_episodes)

    def checkpoint(self) -> Path | None:
        """Save the model and its replay buffer."""
        return save_sb3_checkpoint(self.model, checkpoint_dir(self.out))

    @property
    def timesteps(self) -> int:
        """The model's env steps."""
        return int(self.model.num_timesteps) if self.model is not None else 0

    def metadata(self, plan: RunPlan) -> dict[str, Any]:
        """What the run learned from besides its own experience (demonstrations)."""
        for cb in self.others:
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
