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
from rigs import ScriptedRng

import bioscara_gym  # noqa: F401  (registers the ids)
from bioscara_gym import kinematics
from bioscara_gym.envs.pick_place import BioscaraPickPlaceEnv, KinematicBlock

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


@pytest.mark.parametrize(
    ("tcp", "held"),
    [
        # d = TCP - block is exact in binary here: (0, 0.015, 0), (0, 0, 0.015), (0, 0, -0.03)
        ((0.3, 0.015, 0.015), False),  # 1.5 cm away horizontally: not within
        ((0.3, 0.0, 0.03), False),  # level with the block's top: not below it
        ((0.3, 0.0, -0.015), False),  # 3 cm under the centre: too deep
    ],
)
def test_kinematic_block_grasp_boundaries_are_exclusive(tcp: tuple[float, float, float], held: bool) -> None:
    b = _block_at()
    b.update(np.array(tcp), 0.04)
    assert b.held is held


@pytest.mark.parametrize("pos", [[0, 1, 0], np.array([0.3, 0.1, 0.015], dtype=np.float32)])
def test_kinematic_block_place_keeps_a_float64_position(pos: object) -> None:
    # the block position is achieved_goal, a float64 Box, and is carried in m
    b = KinematicBlock()
    b.place(pos, 0.0)
    assert b.pos.dtype == np.float64
    np.testing.assert_array_equal(b.pos, np.asarray(pos, dtype=np.float64))


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


def test_pick_place_takes_the_base_envs_arguments_by_position_and_by_name() -> None:
    env = BioscaraPickPlaceEnv("mock", control_mode="position")
    try:
        assert env.sim is None
        assert env.control_mode == "position"
    finally:
        env.close()


def test_pick_place_mock_block_is_grasped_and_lifted_by_the_arm(pick: gym.Env) -> None:
    obs, _ = pick.reset(seed=0)
    u = pick.unwrapped
    tcp = obs["observation"][9:12].copy()
    u._block.place(tcp - [0.0, 0.0, 0.01], 0.1)  # TCP 1 cm above the centre, below the top
    close = np.array([0.0, 0.0, 0.0, 0.0, -1.0], dtype=np.float32)  # width 0.04 m: gap 2 cm
    obs, *_ = pick.step(close)
    np.testing.assert_allclose(obs["observation"][15:18], [0.0, 0.0, -0.01], atol=1e-9)
    lift = np.array([0.0, 1.0, 0.0, 0.0, -1.0], dtype=np.float32)
    for _ in range(5):
        obs, *_ = pick.step(lift)
    o = obs["observation"]
    assert o[11] > tcp[2] + 0.003  # the lift went up
    np.testing.assert_allclose(o[15:18], [0.0, 0.0, -0.01], atol=1e-9)  # and the block with it
    np.testing.assert_allclose(obs["achieved_goal"], o[9:12] + np.array([0.0, 0.0, -0.01]), atol=1e-9)


# ----------------------------------------------- draws: scripted and bounded


class _BoundedRng:
    """``np_random`` that fails the test after ``limit`` draws (a redraw loop that never ends)."""

    def __init__(self, seed: int, limit: int) -> None:
        self._rng = np.random.default_rng(seed)
        self._left = limit

    def _count(self) -> None:
        self._left -= 1
        if self._left < 0:
            raise AssertionError("too many draws: a redraw loop that does not end")

    def uniform(self, low: float = 0.0, high: float = 1.0) -> float:
        self._count()
        return self._rng.uniform(low, high)

    def random(self) -> float:
        self._count()
        return self._rng.random()


@pytest.fixture
def fresh_pick() -> BioscaraPickPlaceEnv:
    """A mock PickPlace env of its own; the tests replace its ``np_random``.

    Not reset: a mutant's redraw loop would hang there. Its arm reads 0 on
    every joint, so the TCP is the stretched arm's (0.614476, 0, 0.005).
    """
    env = BioscaraPickPlaceEnv(backend="mock")
    yield env
    env.close()


@pytest.mark.parametrize("where", ["low", "middle", "high"])
def test_table_points_lie_within_the_sector_the_command_range_and_the_annulus(
    fresh_pick: BioscaraPickPlaceEnv, where: str
) -> None:
    u = fresh_pick
    lo, hi = u.command_low[0], u.command_high[0]  # j1's end stops less the margin
    j1 = {"low": lo, "middle": 0.0, "high": hi}[where]
    u.np_random = _BoundedRng(seed=1, limit=2000)  # half the sector is past the stop: ~2 draws a point
    radii, offsets = [], []
    for elbow in (1.0, -1.0) * 100:
        point, q1 = u._sample_table_point(j1, elbow)
        assert point[2] == 0.015  # on the table: the 3 cm block's centre
        radius = math.hypot(point[0], point[1])
        assert 0.25 <= radius <= 0.55
        assert lo <= q1 <= hi
        assert abs(q1 - j1) <= 1.0
        sol = kinematics.inverse(point, elbow)
        assert sol[0] == pytest.approx(q1, abs=1e-9)  # j1 there, with that elbow
        radii.append(radius)
        offsets.append(q1 - j1)
    assert min(radii) < 0.27 and max(radii) > 0.53
    # the whole sector where it is commandable: [0, 1] at the low stop, [-1, 0] at the high one
    assert min(offsets) < (0.1 if where == "low" else -0.9)
    assert max(offsets) > (-0.1 if where == "high" else 0.9)


@pytest.mark.parametrize("past", [-5.0, 5.0])
def test_a_j1_reading_past_the_command_range_draws_from_the_sector_at_the_stop(
    fresh_pick: BioscaraPickPlaceEnv, past: float
) -> None:
    # Seen (a hostile test): a reading more than the sector's 1 rad past a stop (sensor noise
    # of 0.5 rad) left the draw looking forever for a j1 in range.
    u = fresh_pick
    lo, hi = u.command_low[0], u.command_high[0]
    stop = hi if past > 0 else lo
    u.np_random = _BoundedRng(seed=1, limit=2000)
    offsets = [u._sample_table_point(stop + past, 1.0)[1] - stop for _ in range(100)]
    assert all(lo <= stop + o <= hi and abs(o) <= 1.0 for o in offsets)
    assert max(map(abs, offsets)) > 0.9  # the whole sector inside the range


@pytest.mark.parametrize(("fraction", "radius"), [(0.0, 0.25), (0.5, 0.4), (0.999999, 0.55)])
def test_a_table_point_is_at_the_drawn_radius(
    fresh_pick: BioscaraPickPlaceEnv, fraction: float, radius: float
) -> None:
    fresh_pick.np_random = ScriptedRng([fraction, 0.5])  # radius, then j1 offset 0
    point, q1 = fresh_pick._sample_table_point(0.5, 1.0)
    assert math.hypot(point[0], point[1]) == pytest.approx(radius, abs=1e-6)
    assert q1 == 0.5


@pytest.mark.parametrize("end", ["low", "high"])
def test_a_table_point_may_lie_exactly_at_j1s_command_limit(
    fresh_pick: BioscaraPickPlaceEnv, end: str
) -> None:
    u = fresh_pick
    j1 = float(u.command_low[0] if end == "low" else u.command_high[0])
    u.np_random = rng = ScriptedRng([0.5, 0.5])  # radius 0.4, j1 offset exactly 0
    _, q1 = u._sample_table_point(j1, 1.0)
    assert q1 == j1
    assert rng.left == 0


def _script_goal(u: BioscaraPickPlaceEnv, lift: float, yaw: float) -> None:
    # block: radius 0.4 at j1 offset 0; target: radius 0.55 at j1 offset 0 (15 cm further out);
    # then the lift's coin (< 0.5: lifted) and height, then the yaw
    fractions = [0.5, 0.5, 0.999999, 0.5, lift]
    if lift < 0.5:
        fractions.append(1.0)  # the top of the lift: 5 cm
    u.np_random = ScriptedRng([*fractions, yaw])


def test_a_stretched_arm_draws_with_the_positive_elbow(fresh_pick: BioscaraPickPlaceEnv) -> None:
    # j3 = 0 exactly counts as the positive elbow, as in the action map's IK
    u = fresh_pick
    np.testing.assert_array_equal(u._q, [0.0, 0.0, 0.0, 0.0])  # a new env's
    np.testing.assert_allclose(u.tcp_position(), [0.614476, 0.0, 0.005], atol=1e-12)  # L1 + L2 along x
    _script_goal(u, lift=0.9, yaw=0.5)
    target = u._sample_goal()
    block = u._block.pos
    # j1 = 0 with j3 > 0: the forearm bends towards +y
    assert block[1] > 0.0 and target[1] > 0.0
    assert kinematics.inverse(block, 1.0)[0] == pytest.approx(0.0, abs=1e-9)
    assert target[2] == 0.015  # the coin at 0.9: on the table
    assert u.block_yaw == 0.0


@pytest.mark.parametrize(("fraction", "yaw"), [(0.0, -0.7853981633974483), (0.999999, 0.7853981633974483)])
def test_the_block_yaw_spans_a_quarter_turn_each_way(
    fresh_pick: BioscaraPickPlaceEnv, fraction: float, yaw: float
) -> None:
    u = fresh_pick
    _script_goal(u, lift=0.1, yaw=fraction)
    target = u._sample_goal()
    assert u.block_yaw == pytest.approx(yaw, abs=1e-5)
    assert u._block.yaw == u.block_yaw
    assert target[2] == pytest.approx(0.065)  # lifted by the full 5 cm


def test_goal_draws_end(fresh_pick: BioscaraPickPlaceEnv) -> None:
    # the block 8 cm clear of the TCP and the target 10 cm clear of the block are
    # drawn again only rarely: 100 goals in well under 10 draws each
    u = fresh_pick
    u.np_random = _BoundedRng(seed=2, limit=1000)
    for _ in range(100):
        u._sample_goal()


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


def test_pick_place_sim_block_yaw_is_about_z_when_the_block_is_tilted() -> None:
    env = BioscaraPickPlaceEnv()  # sim
    try:
        import mujoco

        data = env.sim.data
        q = np.array([0.9, 0.2, 0.3, 0.25])
        data.joint("block").qpos[3:7] = q / np.linalg.norm(q)
        mujoco.mj_forward(env.sim.model, data)
        xmat = data.body("block").xmat  # yaw of a z-y-x rotation from the matrix: plain geometry
        _, _, yaw = env._block_state()
        assert yaw == pytest.approx(math.atan2(xmat[3], xmat[0]), abs=1e-9)
    finally:
        env.close()
