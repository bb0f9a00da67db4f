"""Gymnasium tasks of the Bioscara arm, registered on ``import bioscara_gym``.

One file per task (:mod:`~bioscara_gym.envs.reach`,
:mod:`~bioscara_gym.envs.pick_place`) on the shared loop of
:mod:`~bioscara_gym.envs.base`.
"""

from bioscara_gym.envs.base import BioscaraEnv, DomainRandomization
from bioscara_gym.envs.pick_place import BioscaraPickPlaceEnv
from bioscara_gym.envs.reach import BioscaraReachEnv

__all__ = ["BioscaraEnv", "BioscaraPickPlaceEnv", "BioscaraReachEnv", "DomainRandomization"]
