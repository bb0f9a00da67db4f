"""Classes the hyperparameter files name by dotted path, for rl-zoo3 and ``bioscara train``.

rl-zoo3 (``python -m rl_zoo3.train``) resolves a ``policy`` containing a dot
and every ``callback`` entry by importing it, and builds a callback from its
YAML keyword arguments alone; ``bioscara train`` reads the same files
(:mod:`bioscara_gym.training.hyperparams`). So this module holds:

* :class:`SACGoalErrorPolicy`, :class:`TD3GoalErrorPolicy` and
  :class:`PPOGoalErrorPolicy`: each algorithm's ``MultiInputPolicy`` with
  :class:`~bioscara_gym.training.features.GoalErrorExtractor` as the default
  features extractor (rl-zoo3 evaluates ``policy_kwargs`` strings in its own
  namespace, where our extractor has no name);
* :class:`SuccessEvalCallback`: the periodic success evaluation that stops
  training at the target success rate. Given no env (as under rl-zoo3), it
  builds its evaluation env from the training env's spec, with the same
  ``env_kwargs``.

Example entry (``training/configs/sac.yaml``)::

    Bioscara-Reach-v0:
      policy: bioscara_gym.training.zoo.SACGoalErrorPolicy
      callback:
        - bioscara_gym.training.zoo.SuccessEvalCallback:
            eval_freq: 2000
            eval_episodes: 100
            target_success: 0.95
"""

from __future__ import annotations

import dataclasses
import math
import time
from collections.abc import Sequence
from typing import Any

import gymnasium as gym
import numpy as np

import bioscara_gym  # noqa: F401 - registers the tasks (rl-zoo3 may import us before --gym-packages)
from bioscara_gym.training.evaluate import EpisodeResult, EvalStats, play_episodes
from bioscara_gym.training.extras import needs_train
from bioscara_gym.training.features import GoalErrorExtractor

with needs_train():
    from stable_baselines3.common.callbacks import BaseCallback
    from stable_baselines3.common.policies import MultiInputActorCriticPolicy
    from stable_baselines3.sac.policies import MultiInputPolicy as SACMultiInputPolicy
    from stable_baselines3.td3.policies import MultiInputPolicy as TD3MultiInputPolicy

    from bioscara_gym.training.algos import sb3_policy

#: Seed of the first evaluation episode, relative to the model's seed (as ``bioscara train``).
EVAL_SEED_OFFSET = 10_000


class SACGoalErrorPolicy(SACMultiInputPolicy):
    """SAC's ``MultiInputPolicy`` acting on :class:`GoalErrorExtractor` features by default."""

    def __init__(
        self, *args: Any, features_extractor_class: type = GoalErrorExtractor, **kwargs: Any
    ) -> None:
        """As SAC's ``MultiInputPolicy``; only the default extractor differs."""
        super().__init__(*args, features_extractor_class=features_extractor_class, **kwargs)


class TD3GoalErrorPolicy(TD3MultiInputPolicy):
    """TD3's ``MultiInputPolicy`` acting on :class:`GoalErrorExtractor` features by default."""

    def __init__(
        self, *args: Any, features_extractor_class: type = GoalErrorExtractor, **kwargs: Any
    ) -> None:
        """As TD3's ``MultiInputPolicy``; only the default extractor differs."""
        super().__init__(*args, features_extractor_class=features_extractor_class, **kwargs)


class PPOGoalErrorPolicy(MultiInputActorCriticPolicy):
    """PPO's ``MultiInputPolicy`` acting on :class:`GoalErrorExtractor` features by default."""

    def __init__(
        self, *args: Any, features_extractor_class: type = GoalErrorExtractor, **kwargs: Any
    ) -> None:
        """As PPO's ``MultiInputPolicy``; only the default extractor differs."""
        super().__init__(*args, features_extractor_class=features_extractor_class, **kwargs)


def env_like(vec_env: Any) -> gym.Env:
    """A fresh env made from the spec of ``vec_env``'s first env (same id, same ``env_kwargs``).

    The wrappers the vec env adds (SB3's ``Monitor``) are left out.
    """
    spec = vec_env.get_attr("spec", indices=[0])[0]
    if spec is None:
        raise ValueError("SuccessEvalCallback: the training env has no spec; pass env=")
    return gym.make(dataclasses.replace(spec, additional_wrappers=()))


class SuccessEvalCallback(BaseCallback):
    """Evaluate the success rate every ``eval_freq`` env steps; stop at ``stop_success``.

    A cheap evaluation (``quick_episodes``) runs often; when it reaches the
    rate in question, a full one (``eval_episodes``) confirms it, so every
    rate that passes is measured on the full set. The full one goes on from
    the quick one's episodes (the model has not changed and the seeds are
    the same, so they are not played twice), and stops at the failure that
    puts the rate out of reach (the decision is the same). The first confirmed
    ``target_success`` is recorded (``reached_at``, ``reached_after_s``: the
    figure benchmarks quote); training stops at the first confirmed
    ``stop_success`` (default: the target). A stop above the target leaves a
    margin: a model stopped exactly at 95 % on 100 episodes scores 93-96 % on
    another 100. Episodes are deterministic and seeded (``seed``, ``seed + 1``,
    ...; default the model's seed + 10000).

    Args:
        eval_freq: Env steps (summed over parallel envs) between evaluations;
            they come at its multiples.
        first_eval: Env steps before the first evaluation (default
            ``eval_freq``); 1 evaluates after the first step, for a model
            that starts trained (an actor cloned from demonstrations).
        eval_episodes: Episodes of the confirming evaluation.
        target_success: Success rate recorded as reached.
        stop_success: Success rate at which training stops (>= the target).
        quick_episodes: Episodes of the frequent evaluation.
        env: Evaluation env; default one like the training env, made at the start.
        seed: Seed of the first evaluation episode.
        verbose: Print each evaluation.
    """

    def __init__(
        self,
        eval_freq: int = 2000,
        eval_episodes: int = 100,
        target_success: float = 0.95,
        stop_success: float | None = None,
        quick_episodes: int = 20,
        first_eval: int | None = None,
        env: gym.Env | None = None,
        seed: int | None = None,
        verbose: int = 1,
    ) -> None:
        """Set up the schedule; the env may come later (see ``env``)."""
        super().__init__(verbose)
        first_eval = eval_freq if first_eval is None else first_eval
        if min(eval_freq, eval_episodes, first_eval) < 1:
            raise ValueError(
                f"eval_freq ({eval_freq}), eval_episodes ({eval_episodes}) and first_eval ({first_eval}) "
                "must be >= 1"
            )
        self.eval_env = env
        self._owns_env = env is None
        self.eval_freq = int(eval_freq)
        self.episodes = int(eval_episodes)
        self.quick_episodes = min(int(quick_episodes), self.episodes)
        self.first_eval = int(first_eval)
        self.target = float(target_success)
        self.stop = self.target if stop_success is None else float(stop_success)
        if not self.target <= self.stop <= 1:
            raise ValueError(f"stop_success ({self.stop}) must be in [target_success ({self.target}), 1]")
        self.seed = seed
        self.last: EvalStats | None = None
        self.results: list[EpisodeResult] = []
        self.reached_at: int | None = None
        self.reached_after_s: float | None = None
        self.stopped_at: int | None = None
        self._start = time.perf_counter()
        self._next = self.first_eval

    def _init_callback(self) -> None:
        if self.eval_env is None:
            self.eval_env = env_like(self.training_env)
        if self.seed is None:
            self.seed = (getattr(self.model, "seed", None) or 0) + EVAL_SEED_OFFSET

    def _on_training_start(self) -> None:
        self._start = time.perf_counter()
        steps = self.num_timesteps  # a resumed run goes on at the next multiple
        self._next = self.first_eval if steps < self.first_eval else self._after(steps)

    def _after(self, steps: int) -> int:
        """The first multiple of ``eval_freq`` above ``steps``."""
        return (steps // self.eval_freq + 1) * self.eval_freq

    def _on_training_end(self) -> None:
        if self._owns_env and self.eval_env is not None:
            self.eval_env.close()
            self.eval_env = None

    def evaluate(
        self, episodes: int, continuing: Sequence[EpisodeResult] = (), max_failures: int | None = None
    ) -> EvalStats:
        """The stats of ``episodes`` deterministic episodes, logged; ``self.results`` their results.

        ``continuing``: the results of the first of them, played already by
        this model; the rest are played (seeds from ``seed + len(continuing)``).
        ``max_failures``: stop after the episode that fails once more than
        this (the stats are then of the episodes played).
        """
        if self.eval_env is None:
            self._init_callback()
        assert self.eval_env is not None and self.seed is not None
        self.results = list(continuing[:episodes])
        played = len(self.results)
        allowed = None if max_failures is None else max_failures - sum(not r.success for r in self.results)
        if played < episodes and (allowed is None or allowed >= 0):
            policy = sb3_policy(self.model)
            self.results += play_episodes(
                self.eval_env, policy, episodes - played, seed=self.seed + played, max_failures=allowed
            )
        stats = EvalStats.over(self.results)
        self.logger.record("eval/success_rate", stats.success_rate)
        self.logger.record("eval/mean_final_distance", stats.mean_final_distance)
        self.logger.record("eval/mean_return", stats.mean_return)
        self.logger.record("eval/stalls", stats.stalls)
        self.logger.dump(self.num_timesteps)
        self.last = stats
        if self.verbose:
            elapsed = time.perf_counter() - self._start
            failures = sum(not r.success for r in self.results)
            cut = f" of {episodes} (stopped: {failures} failures)" if stats.episodes < episodes else ""
            print(
                f"[eval] step {self.num_timesteps:>7}  {elapsed:6.0f} s  success {stats.success_rate:6.1%} "
                f"over {stats.episodes}{cut} episodes  "
                f"final distance {stats.mean_final_distance * 1000:6.1f} mm",
                flush=True,
            )
        return stats

    def _on_step(self) -> bool:
        if self.num_timesteps < self._next:
            return True
        self._next = self._after(self.num_timesteps)
        wanted = self.target if self.reached_at is None else self.stop
        stats = self.evaluate(self.quick_episodes)
        if stats.success_rate < wanted:
            return True
        if self.quick_episodes < self.episodes:
            # stopped at the failure that puts ``wanted`` out of reach: the decision is the same
            allowed = self.episodes - math.ceil(self.episodes * wanted - 1e-9)
            stats = self.evaluate(self.episodes, continuing=self.results, max_failures=allowed)
        if self.reached_at is None and stats.success_rate >= self.target:
            self.reached_at = self.num_timesteps
            self.reached_after_s = time.perf_counter() - self._start
            if self.verbose:
                print(f"[eval] target {self.target:.0%} reached", flush=True)
        if stats.success_rate >= self.stop:
            self.stopped_at = self.num_timesteps
            if self.verbose:
                print(f"[eval] {stats.success_rate:.0%} >= {self.stop:.0%}: stopping", flush=True)
            return False
        return True


class DemonstrationCallback(BaseCallback):
    """Learn from demonstrations: BC, then SAC with demos (:mod:`bioscara_gym.training.imitation`).

    At the start of training it loads the Minari dataset ``dataset`` or, with
    none, records ``episodes`` successful episodes of the env's scripted
    expert in memory (seeds from ``seed``); fits the actor to them
    (``pretrain_steps`` behaviour-cloning steps; skipped when resuming) and
    makes the SAC model sample ``demo_batch_size`` of them in every batch,
    with a Q-filtered behaviour-cloning loss of weight ``bc_weight``.

    Args:
        dataset: Minari dataset name; ``None``: collect with the expert.
        episodes: Expert episodes to collect when there is no dataset.
        pretrain_steps: Behaviour-cloning steps before the first env step.
        demo_batch_size: Demonstrations per batch.
        bc_weight: Weight of the behaviour-cloning loss.
        q_filter: Clone only where the critic prefers the demonstrated action.
        init_std: SAC's exploration noise after pre-training.
        seed: Seed of the first collected episode.
        verbose: Print what was loaded or collected.
    """

    def __init__(
        self,
        dataset: str | None = None,
        episodes: int = 100,
        pretrain_steps: int = 3000,
        demo_batch_size: int = 128,
        bc_weight: float = 1.0,
        q_filter: bool = True,
        init_std: float = 0.1,
        seed: int = 1_000_000,
        verbose: int = 1,
    ) -> None:
        """Store the settings; everything happens at the start of training."""
        super().__init__(verbose)
        self.dataset = dataset
        self.episodes = int(episodes)
        self.pretrain_steps = int(pretrain_steps)
        self.demo_batch_size = int(demo_batch_size)
        self.bc_weight = float(bc_weight)
        self.q_filter = bool(q_filter)
        self.init_std = float(init_std)
        self.seed = int(seed)
        self.demos: Any = None
        self.collect_s = 0.0
        self.pretrain_s = 0.0

    def _on_training_start(self) -> None:
        from bioscara_gym.tasks import task_of
        from bioscara_gym.training.demos import check_demos, load_demos, rollout_demos
        from bioscara_gym.training.imitation import attach_demos, bc_pretrain

        env = env_like(self.training_env)
        try:
            start = time.perf_counter()
            if self.dataset:
                self.demos = load_demos(self.dataset, successful_only=True)
                check_demos(self.demos, env)
            else:
                expert = task_of(env).make_expert(env.unwrapped)
                self.demos = rollout_demos(env, expert, expert.reset, self.episodes, seed=self.seed)
            self.collect_s = time.perf_counter() - start
            d = self.demos
            rewards = np.asarray(
                env.unwrapped.compute_reward(d.next_obs["achieved_goal"], d.next_obs["desired_goal"], None)
            )
        finally:
            env.close()
        if self.verbose:
            source = d.dataset_id if self.dataset else "the expert"
            print(
                f"[demos] {len(d.successes)} successful episodes, {len(d)} steps from {source} "
                f"({self.collect_s:.0f} s)",
                flush=True,
            )
        if self.model.num_timesteps == 0 and self.pretrain_steps > 0:
            start = time.perf_counter()
            loss = bc_pretrain(self.model, d, self.pretrain_steps, init_std=self.init_std, seed=self.seed)
            self.pretrain_s = time.perf_counter() - start
            if self.verbose:
                print(
                    f"[demos] BC pre-training: {self.pretrain_steps} steps, loss {loss:.4f} "
                    f"({self.pretrain_s:.0f} s)",
                    flush=True,
                )
        attach_demos(self.model, d, rewards, self.demo_batch_size, self.bc_weight, self.q_filter)

    def _on_step(self) -> bool:
        return True
