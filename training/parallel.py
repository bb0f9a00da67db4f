"""Envs in subprocesses: the vectorized training envs, and DAgger's rollouts across workers.

``n_envs`` above 1 (a config's key, or ``bioscara train --n-envs``) runs each
env in a process of its own through stable-baselines3's ``SubprocVecEnv``;
1 keeps one env in this process (``DummyVecEnv`` for SB3's methods). An env
step of the simulated arm is mostly MuJoCo and the firmware model in
Python, each worker a process of its own. Whether a second core adds steps
a second depends on the machine: on the two virtual CPUs this was measured
on, two workers stepped PickPlace no faster than one process (README,
``benchmarks/parallel_rollouts.py``).

:func:`label_rollouts` is DAgger's rollout loop over such workers, and
:func:`run_episodes_on` its evaluation's: episode ``k`` of a call is reset
with seed ``seed + k`` whichever worker runs it, so the expert's
demonstrations and the evaluations are the same episodes as with one env (an
episode of the simulated arm is a function of its seed and the policy alone).
"""

from __future__ import annotations

from collections.abc import Callable
from typing import Any

import gymnasium as gym
import numpy as np

from bioscara_gym.tasks import GOAL_KEYS, Policy
from bioscara_gym.training.evaluate import EpisodeLog, EpisodeResult, EvalStats, stopped_after
from bioscara_gym.training.extras import needs_train
from bioscara_gym.training.labelling import LabellingPolicy

with needs_train():
    from stable_baselines3.common.vec_env import DummyVecEnv, SubprocVecEnv, VecEnv

__all__ = ["env_maker", "label_rollouts", "make_vec_envs", "run_episodes_on"]


def make_vec_envs(env_id: str, n_envs: int, env_kwargs: dict[str, Any] | None = None) -> VecEnv:
    """``n_envs`` envs of ``env_id``: in subprocesses when more than one, else in this process.

    Raises:
        ValueError: ``n_envs`` below 1.
    """
    if n_envs < 1:
        raise ValueError(f"n_envs {n_envs}: must be >= 1")
    kwargs = dict(env_kwargs or {})
    fns = [_env_fn(env_id, kwargs) for _ in range(n_envs)]
    if n_envs == 1:
        return DummyVecEnv(fns)
    # fork would copy the parent's MuJoCo, torch and thread state; spawn starts clean.
    return SubprocVecEnv(fns, start_method="spawn")


def _env_fn(env_id: str, kwargs: dict[str, Any]) -> Callable[[], gym.Env]:
    make = env_maker(env_id)
    return lambda: make(**kwargs)


def env_maker(env_id: str) -> Callable[..., gym.Env]:
    """``gym.make(env_id, **kwargs)`` as a function a spawned worker can run (it registers the tasks)."""

    def make(**kwargs: Any) -> gym.Env:
        import bioscara_gym  # noqa: F401 - a spawned worker starts without the registrations

        return gym.make(env_id, **kwargs)

    return make


def label_rollouts(
    venv: VecEnv,
    act: Policy,
    expert: Policy,
    episodes: int,
    seed: int,
    beta: float,
    rng: np.random.Generator,
    on_episode: EpisodeLog | None = None,
    max_failures: int | None = None,
) -> tuple[list[dict[str, np.ndarray]], list[np.ndarray], list[EpisodeResult]]:
    """Run ``episodes`` seeded episodes on ``venv``'s workers with ``act``; label every state with ``expert``.

    As the one-env loop: each step takes the expert's action with probability
    ``beta`` (DAgger's mixture), and the expert labels every state the
    acting policy reaches. ``max_failures`` stops it as it stops
    :func:`run_episodes_on`; the states of the episodes still running then
    are kept, their results are not.

    Returns:
        The observations, their labels, and the results of the episodes the
        one-env loop counts, in seed order.

    Raises:
        ValueError: ``episodes`` below 1, as the one-env loop.
    """
    choose = LabellingPolicy(act, expert, beta, rng)
    results = _play_on(venv, choose, episodes, seed, max_failures, on_episode)
    return choose.rows, choose.labels, results


def _settled(results: dict[int, EpisodeResult], episodes: int, max_failures: int | None) -> int | None:
    """How many of ``episodes`` the one-env loop counts, once the finished ``results`` decide it."""
    prefix = []
    while len(prefix) in results:
        prefix.append(results[len(prefix)])
    cut = stopped_after(prefix, max_failures)
    if cut is not None:
        return cut
    return episodes if len(prefix) == episodes else None


def run_episodes_on(
    venv: VecEnv, policy: Policy, episodes: int, seed: int = 0, max_failures: int | None = None
) -> EvalStats:
    """``run_episodes`` (training/evaluate.py) on ``venv``'s workers: the same episodes and stats.

    Episode ``k`` is reset with seed ``seed + k``. With ``max_failures`` the
    stats are the one-env loop's, which stops after the episode that fails
    once more than that: no episode starts once the finished ones decide
    it, and the episodes past it that were running are not counted.

    Raises:
        ValueError: ``episodes`` below 1.
    """
    return EvalStats.over(_play_on(venv, policy, episodes, seed, max_failures))


def _play_on(
    venv: VecEnv,
    policy: Policy,
    episodes: int,
    seed: int,
    max_failures: int | None,
    on_episode: EpisodeLog | None = None,
) -> list[EpisodeResult]:
    """Episodes ``seed``, ``seed + 1``, ... on ``venv``'s workers, ``policy`` called in worker order.

    A worker without an episode left to run idles (its steps are not acted
    on). Returns the results of the episodes the one-env loop counts.

    Raises:
        ValueError: ``episodes`` below 1 (before a worker is asked).
    """
    if episodes < 1:
        raise ValueError(f"episodes must be >= 1, got {episodes}")
    n = venv.num_envs
    results: dict[int, EpisodeResult] = {}
    running: list[int | None] = [None] * n  # the episode each worker runs; None: it idles
    obs: list[dict[str, np.ndarray]] = [{} for _ in range(n)]
    totals, steps = [0.0] * n, [0] * n
    started = 0

    def start(i: int) -> None:
        """Worker ``i`` resets for the next seeded episode, or idles when none is left to run."""
        nonlocal started
        running[i] = None
        if started < episodes and _settled(results, episodes, max_failures) is None:
            obs[i] = venv.env_method("reset", seed=seed + started, indices=[i])[0][0]
            running[i], totals[i], steps[i] = started, 0.0, 0
            started += 1

    for i in range(n):
        start(i)
    idle = np.zeros(venv.action_space.shape, dtype=np.float32)
    while any(k is not None for k in running):
        actions = np.repeat(idle[None], n, axis=0)
        for i, k in enumerate(running):
            if k is not None:
                actions[i] = policy(obs[i])
        next_obs, rewards, dones, infos = venv.step(actions)
        for i, k in enumerate(running):
            if k is None:
                continue
            totals[i] += float(rewards[i])
            steps[i] += 1
            if dones[i]:
                results[k] = EpisodeResult.ended(infos[i], totals[i], steps[i])
                if on_episode is not None:
                    on_episode(results[k].success, steps[i])
                start(i)
            else:
                obs[i] = {key: np.asarray(next_obs[key][i]) for key in GOAL_KEYS}
    last = _settled(results, episodes, max_failures)
    assert last is not None  # every started episode has finished, and none is left to start
    return [results[k] for k in range(last)]
