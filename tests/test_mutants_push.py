"""Tests that kill mutants of bioscara_gym/envs/push.py (issue #24 item 11, docs/mutation.md).

Expected values are literals from ``KinematicPushBlock``'s docstring (the
closed gripper's footprint: 12 mm along the tool's x axis, 0.04 / 2 + 0.01 =
30 mm along its y axis; the block a disc of radius 15 mm, pushed out the
shortest way while the fingertips are below its top), ``BioscaraPushEnv``'s
(the block 8-25 cm from the start TCP, j1 within 1 rad with the start pose's
elbow; the target 5-20 cm from the block; the gripper held closed at
0.04 m) and plain geometry.
"""

from __future__ import annotations

import math
from collections.abc import Iterator

import gymnasium as gym
import numpy as np
import pytest
from rigs import ScriptedRng

import bioscara_gym  # noqa: F401  (registers the ids)
from bioscara_gym import kinematics
from bioscara_gym.envs.push import BioscaraPushEnv, KinematicPushBlock


def _block(x: float, y: float) -> KinematicPushBlock:
    b = KinematicPushBlock(0.04)
    b.place(np.array([x, y, 0.015]), 0.0)
    return b


@pytest.mark.parametrize("pos", [[0, 1, 0], np.array([0.3, 0.1, 0.015], dtype=np.float32)])
def test_place_keeps_a_float64_position(pos: object) -> None:
    b = KinematicPushBlock(0.04)
    b.place(pos, 0.2)
    assert b.pos.dtype == np.float64
    np.testing.assert_array_equal(b.pos, np.asarray(pos, dtype=np.float64))


def test_fingertips_level_with_the_top_push_nothing() -> None:
    b = _block(0.02, 0.0)  # overlapping the footprint
    b.update(np.array([0.0, 0.0, 0.03]), 0.0)  # at the block's top, not below it
    assert b.pos.tolist() == [0.02, 0.0, 0.015]


def test_a_block_exactly_touching_the_footprint_is_not_pushed() -> None:
    b = _block(0.0, 0.045)  # 30 mm half-width + 15 mm radius: the gap is exactly r
    b.update(np.array([0.0, 0.0, 0.01]), 0.0)
    assert b.pos.tolist() == [0.0, 0.045, 0.015]


def test_a_block_at_a_corner_is_pushed_out_along_the_shortest_way() -> None:
    b = _block(0.02, 0.035)  # off the footprint's corner (0.012, 0.03) by (0.008, 0.005)
    b.update(np.array([0.0, 0.0, 0.01]), 0.0)
    gap = b.pos[:2] - [0.012, 0.03]
    assert math.hypot(*gap) == pytest.approx(0.015, abs=1e-12)  # one radius from the corner
    assert gap[1] / gap[0] == pytest.approx(0.005 / 0.008)  # along the same direction


@pytest.mark.parametrize(
    ("inside", "out"),
    [
        # centre inside the footprint: out through the nearest side, one radius beyond it
        ((0.002, 0.025), (0.002, 0.045)),  # 5 mm from the +y side, 10 mm from +x
        ((0.002, -0.025), (0.002, -0.045)),  # the -y side
        ((-0.008, 0.01), (-0.027, 0.01)),  # 4 mm from the -x side
        ((0.0, 0.0), (0.027, 0.0)),  # the centre: the +x side (12 mm away, y 30 mm)
    ],
)
def test_a_block_with_its_centre_inside_leaves_through_the_nearest_side(
    inside: tuple[float, float], out: tuple[float, float]
) -> None:
    b = _block(*inside)
    b.update(np.array([0.0, 0.0, 0.01]), 0.0)
    np.testing.assert_allclose(b.pos, [*out, 0.015], atol=1e-12)


# ------------------------------------------------------------- goal sampling


@pytest.fixture
def push() -> Iterator[BioscaraPushEnv]:
    """A mock Push env, not reset (a mutant's redraw loop would hang there)."""
    env = BioscaraPushEnv(backend="mock")
    yield env
    env.close()


def test_the_block_is_drawn_around_the_arms_j1_with_its_elbow(push: BioscaraPushEnv) -> None:
    u = push
    u._q_arm = np.array([1.0, 0.005, 0.5, 0.0])  # the positive elbow at j1 = 1 rad
    u._tcp_arm = kinematics.forward(u._q_arm)
    # block: radius 0.5 m, j1 offset -0.2 rad (12 cm from the TCP; the other elbow's point is 53 cm away);
    # target: radius 0.4 m, no offset (14 cm from the block); yaw 0
    u.np_random = ScriptedRng([5 / 6, 0.4, 0.5, 0.5, 0.5])
    target = u._sample_goal()
    block = u._block.pos
    assert kinematics.inverse(block, 1.0)[0] == pytest.approx(0.8, abs=1e-9)
    assert kinematics.inverse(target, 1.0)[0] == pytest.approx(0.8, abs=1e-9)
    assert math.hypot(*block[:2]) == pytest.approx(0.5, abs=1e-9)


def test_a_stretched_arm_draws_with_the_positive_elbow(push: BioscaraPushEnv) -> None:
    u = push  # a new env: every joint at 0, j3 = 0 exactly
    # block: radius 0.52 m, j1 offset -0.4 rad (12 cm from the TCP; the other elbow's 51 cm)
    u.np_random = ScriptedRng([0.9, 0.3, 0.5, 0.5, 0.5])
    u._sample_goal()
    assert kinematics.inverse(u._block.pos, 1.0)[0] == pytest.approx(-0.4, abs=1e-9)


def test_on_sim_the_fingers_start_closed_and_at_rest() -> None:
    env = gym.make("Bioscara-Push-v0")
    try:
        env.reset(seed=0)
        data = env.unwrapped.sim.data
        for finger in ("finger_left", "finger_right"):
            assert data.joint(finger).qpos[0] == pytest.approx(0.02)  # half the closed 0.04 m
            assert data.joint(finger).qvel[0] == 0.0
    finally:
        env.close()


@pytest.mark.parametrize(("fraction", "yaw"), [(0.0, -0.7853981633974483), (0.999999, 0.7853981633974483)])
def test_the_block_yaw_spans_a_quarter_turn_each_way(
    push: BioscaraPushEnv, fraction: float, yaw: float
) -> None:
    u = push
    u._q_arm = np.array([1.0, 0.005, 0.5, 0.0])
    u._tcp_arm = kinematics.forward(u._q_arm)
    u.np_random = ScriptedRng([5 / 6, 0.4, 0.5, 0.5, fraction])
    u._sample_goal()
    assert u.block_yaw == pytest.approx(yaw, abs=1e-5)
    assert u._block.yaw == u.block_yaw


def test_push_takes_the_base_envs_arguments_by_position() -> None:
    u = BioscaraPushEnv("mock", control_mode="position")
    try:
        assert u.sim is None and u.control_mode == "position"
    finally:
        u.close()


def test_the_mock_observation_has_24_values_and_a_block_at_rest(push: BioscaraPushEnv) -> None:
    obs, _ = push.reset(seed=0)
    assert obs["observation"].shape == (24,)
    assert obs["observation"][18:21].tolist() == [0.0, 0.0, 0.0]


@pytest.mark.parametrize(
    ("achieved", "success"),
    [
        ((0.0, 0.0, 0.015), True),
        ((0.0, 0.0099, 0.015), True),
        ((0.0, 0.02, 0.015), False),  # 2 cm off sideways
        ((0.01, 0.0, 0.015), False),  # exactly 1 cm: not within
        ((0.0, 0.0, 0.0175), True),  # 2.5 mm high: resting
        ((0.0, 0.0, 0.0185), False),  # 3.5 mm high: lifted or tipped
    ],
)
def test_success_is_within_1_cm_horizontally_and_3_mm_of_resting(
    push: BioscaraPushEnv, achieved: tuple[float, float, float], success: bool
) -> None:
    assert bool(push._is_success(np.array(achieved), np.array([0.0, 0.0, 0.015]))) is success


def test_a_height_exactly_3_mm_off_is_not_resting(push: BioscaraPushEnv) -> None:
    assert not push._is_success(np.array([0.0, 0.0, 0.003]), np.zeros(3))  # |dz| is exactly Z_TOL


def test_the_kinematic_block_starts_at_the_origin() -> None:
    b = KinematicPushBlock(0.04)
    assert b.pos.tolist() == [0.0, 0.0, 0.0] and b.yaw == 0.0
    assert b.half.tolist() == pytest.approx([0.012, 0.03])  # the closed gripper's half footprint


def test_on_sim_the_block_slides_on_the_table_with_friction_0_5() -> None:
    u = BioscaraPushEnv()  # sim: "MuJoCo slides the block on the table under friction (0.5)"
    try:
        m = u.sim.model
        for geom in ("block", "table"):
            assert m.geom_friction[m.geom(geom).id, 0] == 0.5
    finally:
        u.close()
