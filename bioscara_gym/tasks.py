"""The tasks by env id: what registration, training, evaluation and deployment need of each.

One :class:`TaskSpec` per task, kept as Gymnasium keeps its registrations
(``gymnasium/envs/__init__.py``): names and entry-point strings, so importing
this module imports nothing else. ``import bioscara_gym`` registers every
entry of :data:`TASKS` with Gymnasium; training, evaluation and deployment
reach a task's env through ``gym.make`` and everything else they need of it
(its experts, its observation layout by name, its learner's features) through
its entry here, never by importing or testing the env class.

Adding a task (``Bioscara-Push-v0``): its env module under ``envs/``, its
scripted expert (and, for DAgger, an expert that acts on the observation
alone) in ``experts.py``, a features extractor reading its observation layout
in ``training/features.py`` if its learner needs one, and one entry below.
"""

from __future__ import annotations

import importlib
from collections.abc import Callable, Mapping
from dataclasses import dataclass, field
from typing import Any, Protocol

import numpy as np

#: The keys of every task's observation dict (a goal-conditioned env's, as HER needs).
GOAL_KEYS = ("observation", "achieved_goal", "desired_goal")

#: What acts in a task: observation dict in, action out.
Policy = Callable[[dict[str, np.ndarray]], np.ndarray]


class Expert(Protocol):
    """A scripted policy bound to one env: an action per observation, ``reset()`` per episode."""

    def __call__(self, obs: dict[str, np.ndarray]) -> np.ndarray:
        """The action for ``obs``."""
        ...

    def reset(self) -> None:
        """Forget the previous episode."""
        ...


def load_entry_point(entry_point: str) -> Any:
    """The object ``"package.module:Name"`` names (the module is imported).

    Raises:
        ValueError: Not of the form ``module:Name``.
        ImportError: The module cannot be imported (e.g. an extra is missing).
        AttributeError: The module has no such name.
    """
    module, sep, name = entry_point.partition(":")
    if not sep or not module or not name:
        raise ValueError(f"entry point {entry_point!r} is not of the form package.module:Name")
    return getattr(importlib.import_module(module), name)


@dataclass(frozen=True)
class TaskSpec:
    """One task: its env, episode length and what acts in it, by name.

    Attributes:
        id: The versioned env id (``Bioscara-Reach-v0``).
        entry_point: The env class, ``module:Class``; its ``OBS_SLICES`` name
            where each quantity lies in ``obs["observation"]``.
        max_episode_steps: Episode length in control steps (Gymnasium's time limit).
        expert: The scripted expert, ``module:Class``, built with the unwrapped
            env (``bioscara eval --expert``, ``deploy --expert``, demonstrations).
        observation_expert: An expert whose action is a function of the
            observation alone, so it can label any state (DAgger's labels,
            ``bioscara collect --expert``), or ``None``.
        extractor: The features extractor an imitation learner of this task
            reads its observation with (``module:Class``), or ``None``.
        default_method: The training method of ``bioscara train`` without
            ``--algo`` or ``--config`` (a name of ``training/methods.py``).
        kwargs: Keyword arguments the id fixes (an older version's behaviour,
            as Gymnasium registers ``Reacher-v4`` beside ``-v5``).
    """

    id: str
    entry_point: str
    max_episode_steps: int
    expert: str
    observation_expert: str | None = None
    extractor: str | None = None
    default_method: str = "sac"
    kwargs: Mapping[str, Any] = field(default_factory=dict)

    def env_class(self) -> type:
        """The env class (its module is imported)."""
        return load_entry_point(self.entry_point)

    def obs_slices(self) -> Mapping[str, slice]:
        """Where each named quantity lies in ``obs["observation"]`` (the env class's ``OBS_SLICES``)."""
        return self.env_class().OBS_SLICES

    def make_expert(self, env: Any) -> Expert:
        """The scripted expert bound to ``env`` (the unwrapped env)."""
        return load_entry_point(self.expert)(env)

    def make_observation_expert(self, env: Any) -> Expert:
        """The observation-only expert bound to ``env`` (the unwrapped env).

        Raises:
            LookupError: The task has none.
        """
        if self.observation_expert is None:
            raise LookupError(f"{self.id} has no expert that acts on the observation alone")
        return load_entry_point(self.observation_expert)(env)

    def extractor_class(self) -> type:
        """The imitation learner's features extractor.

        Raises:
            LookupError: The task names none.
        """
        if self.extractor is None:
            raise LookupError(f"{self.id} names no features extractor for an imitation learner")
        return load_entry_point(self.extractor)


#: Every task, by versioned env id. A changed task gets a new version (its
#: docstring's version history says what changed); an older version stays
#: registered while its behaviour can still be made (PickPlace-v0's goal
#: distribution cannot: Gymnasium then names the versions there are).
TASKS: dict[str, TaskSpec] = {
    "Bioscara-Reach-v0": TaskSpec(
        id="Bioscara-Reach-v0",
        entry_point="bioscara_gym.envs.reach:BioscaraReachEnv",
        max_episode_steps=50,
        expert="bioscara_gym.experts:ReachExpert",
    ),
    "Bioscara-PickPlace-v1": TaskSpec(
        id="Bioscara-PickPlace-v1",
        entry_point="bioscara_gym.envs.pick_place:BioscaraPickPlaceEnv",
        max_episode_steps=200,
        expert="bioscara_gym.experts:PickPlaceExpert",
        observation_expert="bioscara_gym.experts:ObservationExpert",
        extractor="bioscara_gym.training.features:PickPlaceExtractor",
        default_method="dagger",
    ),
    "Bioscara-Push-v0": TaskSpec(
        id="Bioscara-Push-v0",
        entry_point="bioscara_gym.envs.push:BioscaraPushEnv",
        max_episode_steps=200,
        expert="bioscara_gym.experts:PushExpert",
        observation_expert="bioscara_gym.experts:PushExpert",
        extractor="bioscara_gym.training.features:PushExtractor",
        default_method="dagger",
    ),
    "Bioscara-Stack-v0": TaskSpec(
        id="Bioscara-Stack-v0",
        entry_point="bioscara_gym.envs.stack:BioscaraStackEnv",
        max_episode_steps=300,
        expert="bioscara_gym.experts:StackExpert",
        observation_expert="bioscara_gym.experts:StackExpert",
        extractor="bioscara_gym.training.features:StackExtractor",
        default_method="dagger",
    ),
    "Bioscara-Insert-v0": TaskSpec(
        id="Bioscara-Insert-v0",
        entry_point="bioscara_gym.envs.insert:BioscaraInsertEnv",
        max_episode_steps=150,
        expert="bioscara_gym.experts:InsertExpert",
        observation_expert="bioscara_gym.experts:InsertExpert",
        extractor="bioscara_gym.training.features:InsertExtractor",
        default_method="dagger",
    ),
}


def task(env_id: str) -> TaskSpec:
    """The task registered as ``env_id`` (versioned, or the latest version of an unversioned id).

    Raises:
        KeyError: No such task; the message lists the registered ones.
    """
    if env_id in TASKS:
        return TASKS[env_id]
    versions = sorted(t for t in TASKS if t.rpartition("-v")[0] == env_id)
    if versions:
        return TASKS[versions[-1]]
    raise KeyError(f"no task {env_id!r}; registered: {', '.join(TASKS)}")


def task_of(env: Any) -> TaskSpec:
    """The task of a made env (wrapped or not), from its spec's id.

    Raises:
        KeyError: The env was not made from a registered task (``gym.make``).
    """
    spec = getattr(getattr(env, "unwrapped", env), "spec", None)
    if spec is None:
        raise KeyError(f"{type(env).__name__} was not made with gym.make, so its task is unknown")
    return task(spec.id)
