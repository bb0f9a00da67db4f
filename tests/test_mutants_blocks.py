"""Tests that kill mutants of bioscara_gym/envs/blocks.py (issue #24 item 11, docs/mutation.md).

``SimBlock`` on the sim backend's MuJoCo scene (``assets/scene.xml``: ``block``
on the table, ``block2`` parked weightless and intangible). Expected values
are literals from its docstrings (placed at rest, yaw about z, ``bring_in``
gives ``block2`` the weight and contacts of ``block``) or MuJoCo's own view of
the scene (``data.joint``, ``data.body``), not the class's arithmetic.
"""

from __future__ import annotations

import math
from collections.abc import Iterator
from typing import Any

import mujoco
import numpy as np
import pytest

from bioscara_gym.envs.blocks import SimBlock
from bioscara_gym.hardware.backends import make_backend
from bioscara_gym.hardware.config import load_config


@pytest.fixture
def sim() -> Iterator[Any]:
    backend = make_backend("sim", load_config())
    yield backend.sim
    backend.close()


@pytest.mark.parametrize("name", ["block", "block2"])
def test_a_block_is_placed_at_rest_where_asked_with_its_yaw(sim: Any, name: str) -> None:
    other = "block2" if name == "block" else "block"
    sim.data.joint(name).qvel[:] = 1.0
    sim.data.joint(other).qvel[:] = 2.0
    SimBlock(sim, name).place(np.array([0.4, -0.1, 0.2]), 0.3)
    mujoco.mj_forward(sim.model, sim.data)
    joint = sim.data.joint(name)
    assert joint.qpos[:3].tolist() == pytest.approx([0.4, -0.1, 0.2])
    assert joint.qvel.tolist() == [0.0] * 6
    assert sim.data.joint(other).qvel.tolist() == [2.0] * 6  # the other block untouched
    xmat = sim.data.body(name).xmat
    assert math.atan2(xmat[3], xmat[0]) == pytest.approx(0.3)


@pytest.mark.parametrize("name", ["block", "block2"])
def test_a_blocks_state_is_its_position_linear_velocity_and_yaw_about_z(sim: Any, name: str) -> None:
    joint = sim.data.joint(name)
    joint.qpos[:3] = [0.3, 0.2, 0.1]
    q = np.array([0.9, 0.2, 0.3, 0.25])  # tilted: the yaw of a z-y-x rotation
    joint.qpos[3:7] = q / np.linalg.norm(q)
    joint.qvel[:] = [0.1, -0.2, 0.3, 4.0, 5.0, 6.0]
    mujoco.mj_forward(sim.model, sim.data)
    pos, vel, yaw = SimBlock(sim, name).state()
    assert pos.tolist() == pytest.approx([0.3, 0.2, 0.1])
    assert vel.tolist() == pytest.approx([0.1, -0.2, 0.3])
    xmat = sim.data.body(name).xmat
    assert yaw == pytest.approx(math.atan2(xmat[3], xmat[0]), abs=1e-12)
    pos[0] = 9.0
    vel[0] = 9.0
    assert joint.qpos[0] == 0.3 and joint.qvel[0] == 0.1  # copies


def test_bring_in_gives_block2_the_weight_and_contacts_of_block(sim: Any) -> None:
    m = sim.model
    g1, g2 = m.geom("block").id, m.geom("block2").id
    b1, b2 = m.body("block").id, m.body("block2").id
    assert m.body_gravcomp[b2] == 1.0 and m.geom_contype[g2] == 0  # parked
    SimBlock(sim, "block2").bring_in()
    assert (m.geom_contype[g2], m.geom_conaffinity[g2]) == (m.geom_contype[g1], m.geom_conaffinity[g1])
    assert (m.body_contype[b2], m.body_conaffinity[b2]) == (m.body_contype[b1], m.body_conaffinity[b1])
    assert m.geom_contype[g2] != 0 and m.body_conaffinity[b2] != 0
    assert m.body_gravcomp[b2] == 0.0


def test_bring_in_copies_the_block_named_like(sim: Any) -> None:
    m = sim.model
    m.geom_contype[m.geom("block").id] = 4
    m.geom_conaffinity[m.geom("block").id] = 6
    SimBlock(sim, "block2").bring_in(like="block")
    assert (m.geom_contype[m.geom("block2").id], m.geom_conaffinity[m.geom("block2").id]) == (4, 6)
    blk = SimBlock(sim, "block")
    blk.bring_in(like="block2")  # the other way round: block2's values now
    assert m.geom_contype[m.geom("block").id] == 4
    assert (blk.sim, blk.name) == (sim, "block")
