"""The scene's blocks as a task sees them: placed and read through their free joints.

``assets/scene.xml`` holds two 3 cm cubes, ``block`` (blue, on the table) and
``block2`` (yellow, parked under the floor, weightless and intangible until a
task takes it: :meth:`SimBlock.bring_in`). Only the backends that simulate
have them; a task on ``mock`` or ``i2c`` keeps a kinematic stand-in instead
(PickPlace's :class:`~bioscara_gym.envs.pick_place.KinematicBlock`, Push's
:class:`~bioscara_gym.envs.push.KinematicPushBlock`).
"""

from __future__ import annotations

import math
from typing import Any

import numpy as np

from bioscara_gym.envs.rendering import set_free_body


class SimBlock:
    """A block of the MuJoCo scene, by the name of its free joint (and of its body and geom).

    Args:
        sim: The backend's :class:`~bioscara_gym.hardware.sim.ArmSim`.
        name: ``"block"`` or ``"block2"``.
    """

    def __init__(self, sim: Any, name: str) -> None:
        """Find the block's joint addresses in ``sim``'s model."""
        self.sim, self.name = sim, name
        m = sim.model
        jid = m.joint(name).id
        self._qadr = int(m.jnt_qposadr[jid])
        self._dadr = int(m.jnt_dofadr[jid])

    def bring_in(self, like: str = "block") -> None:
        """Give the block weight and the contacts of the block ``like`` (a parked block has neither)."""
        m = self.sim.model
        geom, model_geom = m.geom(self.name).id, m.geom(like).id
        body, model_body = m.body(self.name).id, m.body(like).id
        m.geom_contype[geom] = m.geom_contype[model_geom]
        m.geom_conaffinity[geom] = m.geom_conaffinity[model_geom]
        # MuJoCo's broad phase filters by each body's masks (its geoms' together) first.
        m.body_contype[body] = m.body_contype[model_body]
        m.body_conaffinity[body] = m.body_conaffinity[model_body]
        m.body_gravcomp[body] = 0.0

    def place(self, pos: np.ndarray, yaw: float) -> None:
        """Put the block at ``pos`` (m), turned by ``yaw`` (rad) about z, at rest (``mj_forward`` after)."""
        set_free_body(self.sim.model, self.sim.data, self.name, pos, yaw)
        self.sim.data.qvel[self._dadr : self._dadr + 6] = 0.0

    def state(self) -> tuple[np.ndarray, np.ndarray, float]:
        """Position (m), linear velocity (m/s) and yaw (rad) of the block."""
        d, a = self.sim.data, self._qadr
        w, x, y, z = d.qpos[a + 3 : a + 7]
        yaw = math.atan2(2 * (w * z + x * y), 1 - 2 * (y * y + z * z))
        return d.qpos[a : a + 3].copy(), d.qvel[self._dadr : self._dadr + 3].copy(), yaw
