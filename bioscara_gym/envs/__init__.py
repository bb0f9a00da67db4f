"""Gymnasium tasks of the Bioscara arm, registered on ``import bioscara_gym``.

One file per task (:mod:`~bioscara_gym.envs.reach`,
:mod:`~bioscara_gym.envs.pick_place`, :mod:`~bioscara_gym.envs.push`,
:mod:`~bioscara_gym.envs.stack`, :mod:`~bioscara_gym.envs.insert`; the scene's
blocks in :mod:`~bioscara_gym.envs.blocks`) on the shared loop of
:mod:`~bioscara_gym.envs.base`, which maps actions with
:mod:`~bioscara_gym.envs.actions`, randomizes with
:mod:`~bioscara_gym.envs.randomization` and draws with
:mod:`~bioscara_gym.envs.rendering`. None of them imports MuJoCo at import
time: an env on ``mock`` or ``i2c`` runs without it.
"""

from bioscara_gym.envs.base import BioscaraEnv
from bioscara_gym.envs.insert import BioscaraInsertEnv
from bioscara_gym.envs.pick_place import BioscaraPickPlaceEnv
from bioscara_gym.envs.push import BioscaraPushEnv
from bioscara_gym.envs.randomization import DomainRandomization
from bioscara_gym.envs.reach import BioscaraReachEnv
from bioscara_gym.envs.stack import BioscaraStackEnv

__all__ = [
    "BioscaraEnv",
    "BioscaraInsertEnv",
    "BioscaraPickPlaceEnv",
    "BioscaraPushEnv",
    "BioscaraReachEnv",
    "BioscaraStackEnv",
    "DomainRandomization",
]
