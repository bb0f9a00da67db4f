"""bioscara-gym: the Bioscara SCARA arm as a reinforcement-learning testbed.

``import bioscara_gym`` registers the Gymnasium tasks (``Bioscara-Reach-v0``,
``Bioscara-PickPlace-v0``); the driver layer is :mod:`bioscara_gym.hardware`.
"""

import os
from importlib.metadata import PackageNotFoundError, version

# Headless (no display): render with EGL unless the user chose a backend.
# MuJoCo reads this when it is first imported, which the next import does.
if "MUJOCO_GL" not in os.environ and not os.environ.get("DISPLAY"):
    os.environ["MUJOCO_GL"] = "egl"

from bioscara_gym.envs import register_envs

try:
    __version__ = version("bioscara-gym")
except PackageNotFoundError:  # pragma: no cover - running from a source tree
    __version__ = "0.0.0+unknown"

register_envs()

__all__ = ["__version__", "register_envs"]
