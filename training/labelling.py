"""DAgger's data: labelled states (:class:`Labelled`) and the episodes that produce them.

:func:`label_episodes` runs seeded episodes with one policy acting (the
expert, the learner, or DAgger's mixture of both) and labels every state
with the expert's action (:class:`LabellingPolicy`, which
:func:`~bioscara_gym.training.parallel.label_rollouts` runs on its workers
too); :class:`Rollouts` holds what it recorded, each
counted episode's result included, so a confirming evaluation's episodes can
join the aggregate (training/dagger.py).
"""

from __future__ import annotations

from dataclasses import dataclass

import gymnasium as gym
import numpy as np

from bioscara_gym.tasks import GOAL_KEYS, Policy
from bioscara_gym.training.demos import Demos
from bioscara_gym.training.evaluate import EpisodeLog, EpisodeResult, EvalStats, play_episodes

__all__ = ["Labelled", "LabellingPolicy", "Rollouts", "label_episodes", "labelled"]


@dataclass(frozen=True)
class Labelled:
    """States and the expert's actions in them (DAgger's aggregate dataset).

    Attributes:
        obs: ``observation``, ``achieved_goal``, ``desired_goal``, one row per state.
        actions: The expert's action in each state.
        iteration: The DAgger iteration each row was collected in (0: the expert's own episodes).
    """

    obs: dict[str, np.ndarray]
    actions: np.ndarray
    iteration: np.ndarray

    def __len__(self) -> int:
        """Number of labelled states."""
        return len(self.actions)

    def __add__(self, other: Labelled) -> Labelled:
        """Both datasets, ``self``'s rows first."""
        return Labelled(
            obs={k: np.concatenate((self.obs[k], other.obs[k])) for k in GOAL_KEYS},
            actions=np.concatenate((self.actions, other.actions)),
            iteration=np.concatenate((self.iteration, other.iteration)),
        )

    @classmethod
    def from_demos(cls, demos: Demos) -> Labelled:
        """A demonstration dataset's states and actions, as iteration 0."""
        return cls({k: demos.obs[k] for k in GOAL_KEYS}, demos.actions, np.zeros(len(demos), dtype=np.int32))


@dataclass(frozen=True)
class Rollouts:
    """What :func:`label_episodes` recorded: the labelled states and each counted episode's result."""

    data: Labelled
    results: tuple[EpisodeResult, ...]

    @property
    def episodes(self) -> int:
        """Episodes counted (all that ran, unless a failure allowance stopped them)."""
        return len(self.results)

    @property
    def successes(self) -> int:
        """Episodes that ended in success."""
        return sum(r.success for r in self.results)

    @property
    def success_rate(self) -> float:
        """Fraction of the episodes that ended in success."""
        return self.successes / self.episodes

    @property
    def stats(self) -> EvalStats:
        """The episodes' results as an evaluation's."""
        return EvalStats.over(self.results)


class LabellingPolicy:
    """The acting policy of a labelled rollout: it records each state and the expert's label for it.

    Each step takes the expert's action with probability ``beta`` (drawn
    from ``rng``; always when ``act`` is the expert): DAgger's mixture
    policy, which carries a weak learner into the later phases of the task.
    Otherwise ``act`` acts; the expert labels every state either way.
    """

    def __init__(self, act: Policy, expert: Policy, beta: float, rng: np.random.Generator) -> None:
        """Nothing recorded yet."""
        self.act, self.expert, self.beta, self.rng = act, expert, beta, rng
        self.rows: list[dict[str, np.ndarray]] = []
        self.labels: list[np.ndarray] = []

    def __call__(self, obs: dict[str, np.ndarray]) -> np.ndarray:
        """The action in ``obs``, its state and label recorded."""
        label = np.asarray(self.expert(obs), dtype=np.float32)
        mixed = self.act is self.expert or (self.beta > 0 and self.rng.random() < self.beta)
        self.rows.append(obs)
        self.labels.append(label)
        return label if mixed else self.act(obs)


def label_episodes(
    env: gym.Env,
    act: Policy,
    expert: Policy,
    episodes: int,
    seed: int,
    iteration: int,
    beta: float = 0.0,
    rng: np.random.Generator | None = None,
    on_episode: EpisodeLog | None = None,
    max_failures: int | None = None,
) -> Rollouts:
    """Run ``episodes`` seeded episodes acting with ``act``; label every state with ``expert``.

    With ``act`` the expert itself, these are demonstrations; with the
    learner, DAgger's new data (the states the learner reaches). With
    ``beta`` > 0 the expert acts in some steps (:class:`LabellingPolicy`).
    ``max_failures`` stops after the episode that fails once more than
    that, as an evaluation does
    (:func:`~bioscara_gym.training.evaluate.play_episodes`, which runs them).

    Raises:
        ValueError: ``episodes`` below 1.
    """
    choose = LabellingPolicy(act, expert, beta, rng if rng is not None else np.random.default_rng(seed))
    results = play_episodes(env, choose, episodes, seed, max_failures=max_failures, on_episode=on_episode)
    return Rollouts(labelled(choose.rows, choose.labels, iteration), tuple(results))


def labelled(obs_rows: list[dict[str, np.ndarray]], labels: list[np.ndarray], iteration: int) -> Labelled:
    """The states and their expert labels as arrays, tagged with ``iteration``."""
    return Labelled(
        obs={k: np.array([o[k] for o in obs_rows], dtype=np.float32) for k in GOAL_KEYS},
        actions=np.array(labels, dtype=np.float32),
        iteration=np.full(len(labels), iteration, dtype=np.int32),
    )
