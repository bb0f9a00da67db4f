"""Gymnasium tasks of the Bioscara arm, registered on ``import bioscara_gym``.

=========================  ===================================  =================
id                         class                                max_episode_steps
=========================  ===================================  =================
``Bioscara-Reach-v0``      :class:`BioscaraReachEnv`            50 (2 s)
``Bioscara-PickPlace-v0``  :class:`BioscaraPickPlaceEnv`        200 (8 s)
=========================  ===================================  =================

``gym.make("Bioscara-Reach")`` gives the latest version without Gymnasium's
"Using the latest versioned environment" warning: the unversioned name is our
documented alias, not an accident.
"""

from __future__ import annotations

import warnings

import gymnasium as gym

from bioscara_gym.envs.base import BioscaraEnv, DomainRandomization
from bioscara_gym.envs.pick_place import BioscaraPickPlaceEnv
from bioscara_gym.envs.reach import BioscaraReachEnv

TASKS = {
    "Bioscara-Reach-v0": ("bioscara_gym.envs.reach:BioscaraReachEnv", 50),
    "Bioscara-PickPlace-v0": ("bioscara_gym.envs.pick_place:BioscaraPickPlaceEnv", 200),
}


def register_envs() -> None:
    """Register the tasks with Gymnasium (idempotent)."""
    for env_id, (entry_point, steps) in TASKS.items():
        if env_id not in gym.registry:
            gym.register(id=env_id, entry_point=entry_point, max_episode_steps=steps)
    warnings.filterwarnings(
        "ignore", message=r".*Using the latest versioned environment `Bioscara-", category=UserWarning
    )


__all__ = [
    "TASKS",
    "BioscaraEnv",
    "BioscaraPickPlaceEnv",
    "BioscaraReachEnv",
    "DomainRandomization",
    "register_envs",
]
