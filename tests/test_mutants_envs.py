"""Tests that kill mutants of bioscara_gym/envs/ (issue #24 item 11, docs/mutation.md).

Expected values are literals from the env class docstrings (the spec), the
KinematicBlock docstring, the module constants' sources (assets/scene.xml:
3 cm block; assets/README.md: 2 cm pads) or plain geometry.
"""

from __future__ import annotations

import math

import gymnasium as gym
import numpy as np
import pytest

import bioscara_gym  # noqa: F401  (registers the ids)
from bioscara_gym.envs.pick_place import KinematicBlock

PICK = "Bioscara-PickPlace-v1"


# ------------------------------------------------------------ KinematicBlock


def _block_at(x: float = 0.3, y: float = 0.0) -> KinematicBlock:
    b = KinematicBlock()
    b.place(np.array([x, y, 0.015]), 0.2)
    return b


def test_kinematic_block_starts_at_the_origin_not_held() -> None:
    b = KinematicBlock()
    assert b.pos.tolist() == [0.0, 0.0, 0.0]
    assert b.yaw == 0.0
    assert b.held is False


def test_kinematic_block_place_copies_the_position_and_releases() -> None:
    b = KinematicBlock()
    p = np.array([0.3, 0.1, 0.015])
    b.held = True
    b.place(p, 0.5)
    p[0] = 9.0
    assert b.pos.tolist() == [0.3, 0.1, 0.015]
    assert b.yaw == 0.5
    assert b.held is False


@pytest.mark.parametrize(("width", "held"), [(0.04, True), (0.049, True), (0.051, False), (0.12, False)])
def test_kinematic_block_is_grasped_only_when_the_gap_is_narrower_than_the_block(
    width: float, held: bool
) -> None:
    # gap = width - 2 cm pads; block 3 cm: touched at 0.05 m (class docstring)
    b = _block_at()
    b.update(np.array([0.3, 0.0, 0.015]), width)
    assert b.held is held


@pytest.mark.parametrize(
    ("dx", "dy", "held"),
    [
        (0.0, 0.0, True),
        (0.014, 0.0, True),
        (0.0, -0.014, True),
        (0.016, 0.0, False),
        (0.0, 0.016, False),
        (0.011, 0.011, False),
        (0.01, 0.01, True),
    ],
)
def test_kinematic_block_is_grasped_only_within_1_5_cm_horizontally(dx: float, dy: float, held: bool) -> None:
    # 0.011*sqrt(2) = 0.0156 > 0.015; 0.01*sqrt(2) = 0.0141 < 0.015
    b = _block_at()
    b.update(np.array([0.3 + dx, 0.0 + dy, 0.015]), 0.04)
    assert b.held is held


@pytest.mark.parametrize(("dz", "held"), [(0.014, True), (0.016, False), (-0.029, True), (-0.031, False)])
def test_kinematic_block_is_grasped_only_below_its_top(dz: float, held: bool) -> None:
    # top is 1.5 cm above the centre; 3 cm below the centre is 1.5 cm under the table
    b = _block_at()
    b.update(np.array([0.3, 0.0, 0.015 + dz]), 0.04)
    assert b.held is held


def test_kinematic_block_is_carried_with_its_grasp_offset() -> None:
    b = _block_at()
    b.update(np.array([0.31, 0.005, 0.01]), 0.04)  # offset (-0.01, -0.005, +0.005)
    b.update(np.array([0.41, 0.105, 0.06]), 0.04)
    np.testing.assert_allclose(b.pos, [0.40, 0.10, 0.065], atol=1e-12)
    assert b.held is True


def test_kinematic_block_grasp_sets_the_offset_from_the_tcp() -> None:
    b = _block_at()
    b.update(np.array([0.305, 0.0, 0.0]), 0.04)
    np.testing.assert_allclose(b.pos, [0.3, 0.0, 0.015], atol=1e-12)


def test_kinematic_block_carried_never_goes_below_the_table() -> None:
    b = _block_at()
    b.update(np.array([0.3, 0.0, 0.015]), 0.04)
    b.update(np.array([0.35, 0.0, -0.02]), 0.04)
    np.testing.assert_allclose(b.pos, [0.35, 0.0, 0.015], atol=1e-12)


def test_kinematic_block_falls_to_the_table_when_the_gripper_opens() -> None:
    b = _block_at()
    b.update(np.array([0.3, 0.0, 0.015]), 0.04)
    b.update(np.array([0.35, 0.02, 0.06]), 0.04)
    b.update(np.array([0.36, 0.03, 0.08]), 0.10)
    assert b.held is False
    np.testing.assert_allclose(b.pos, [0.35, 0.02, 0.015], atol=1e-12)
    b.update(np.array([0.4, 0.0, 0.08]), 0.10)  # not held: stays
    np.testing.assert_allclose(b.pos, [0.35, 0.02, 0.015], atol=1e-12)


def test_kinematic_block_held_stays_held_while_closed_away_from_it() -> None:
    b = _block_at()
    b.update(np.array([0.3, 0.0, 0.015]), 0.04)
    b.update(np.array([0.5, 0.0, 0.015]), 0.045)
    assert b.held is True
    np.testing.assert_allclose(b.pos, [0.5, 0.0, 0.015], atol=1e-12)


def test_kinematic_block_is_not_grasped_by_a_gripper_closing_away_from_it() -> None:
    b = _block_at()
    b.update(np.array([0.4, 0.0, 0.015]), 0.04)
    assert b.held is False
    np.testing.assert_allclose(b.pos, [0.3, 0.0, 0.015], atol=1e-12)


# ------------------------------------------------------- goal sampling (mock)


@pytest.fixture(scope="module")
def pick() -> gym.Env:
    env = gym.make(PICK, backend="mock")
    yield env
    env.close()


def test_pick_place_goals_follow_the_docstring_distribution(pick: gym.Env) -> None:
    lifted = on_table = 0
    yaws = []
    for seed in range(60):
        obs, _ = pick.reset(seed=seed)
        block, target, o = obs["achieved_goal"], obs["desired_goal"], obs["observation"]
        tcp = o[9:12]
        assert block[2] == 0.015
        assert 0.25 <= math.hypot(block[0], block[1]) <= 0.55
        assert 0.25 <= math.hypot(target[0], target[1]) <= 0.55
        assert 0.015 <= target[2] <= 0.065
        # block drawn clear of the TCP (8 cm), target clear of the block (10 cm)
        assert math.hypot(*(block[:2] - tcp[:2])) > 0.08
        assert math.hypot(*(target[:2] - block[:2])) > 0.1
        if target[2] == 0.015:
            on_table += 1
        else:
            lifted += 1
        yaw = float(o[21])
        assert -math.pi / 4 <= yaw <= math.pi / 4
        yaws.append(yaw)
    # "on the table or up to 5 cm above it": both happen
    assert on_table >= 15 and lifted >= 15
    assert min(yaws) < -0.4 and max(yaws) > 0.4


def test_pick_place_start_pose_is_clear_of_the_block_top(pick: gym.Env) -> None:
    # TCP 1-3 cm above the 3 cm block's top: z in [0.04, 0.06]
    zs = []
    for seed in range(30):
        obs, _ = pick.reset(seed=seed)
        z = float(obs["observation"][11])
        assert 0.04 - 1e-3 <= z <= 0.06 + 1e-3
        zs.append(z)
    assert max(zs) - min(zs) > 0.01


def test_pick_place_observation_holds_the_block_after_reach_values(pick: gym.Env) -> None:
    obs, _ = pick.reset(seed=3)
    o = obs["observation"]
    assert o.shape == (22,)
    np.testing.assert_allclose(o[12:15], obs["achieved_goal"], atol=1e-6)
    np.testing.assert_allclose(o[15:18], obs["achieved_goal"] - o[9:12], atol=1e-6)
    assert o[18:21].tolist() == [0.0, 0.0, 0.0]
    u = pick.unwrapped
    assert u.OBS_SLICES["block_pos"] == slice(12, 15)
    assert u.OBS_SLICES["block_from_tcp"] == slice(15, 18)
    assert u.OBS_SLICES["block_vel"] == slice(18, 21)
    assert u.OBS_SLICES["block_yaw"] == slice(21, 22)
    assert u.cartesian_step == (0.02, 0.02, 0.01)
    assert u.SECTOR == 1.0


def test_pick_place_scene_shows_the_kinematic_block_on_mock(pick: gym.Env) -> None:
    obs, _ = pick.reset(seed=4)
    scene = pick.unwrapped._scene()
    pos, yaw = scene.bodies["block"]
    np.testing.assert_allclose(pos, obs["achieved_goal"], atol=1e-9)
    assert yaw == pytest.approx(float(obs["observation"][21]))


# ------------------------------------------------------------ the sim block


def test_pick_place_sim_puts_the_block_where_drawn_at_rest_with_its_yaw() -> None:
    env = gym.make(PICK)  # sim backend: the block is MuJoCo's
    try:
        obs, _ = env.reset(seed=5)
        o = obs["observation"]
        data = env.unwrapped.sim.data
        block = obs["achieved_goal"]
        assert block[2] == pytest.approx(0.015, abs=1e-9)
        np.testing.assert_allclose(data.body("block").xpos, block, atol=1e-9)
        assert o[18:21].tolist() == [0.0, 0.0, 0.0]
        # yaw about z from the body's rotation matrix (plain geometry)
        xmat = data.body("block").xmat
        yaw = math.atan2(xmat[3], xmat[0])
        assert abs(yaw) > 0.05
        assert float(o[21]) == pytest.approx(yaw, abs=1e-6)
        np.testing.assert_allclose(o[15:18], block - o[9:12], atol=1e-6)
        obs, *_ = env.step(np.zeros(env.action_space.shape, dtype=np.float32))
        joint = data.joint("block")  # the block's free joint: position, then quaternion
        np.testing.assert_allclose(obs["observation"][12:15], joint.qpos[:3], atol=1e-12)
        np.testing.assert_allclose(obs["observation"][18:21], joint.qvel[:3], atol=1e-6)
        assert np.any(joint.qvel[:3] != 0.0)  # it settles on the table: a velocity to show
    finally:
        env.close()
