"""Tests that kill mutants of bioscara_gym/envs/stack.py (issue #24 item 11, docs/mutation.md).

Expected values are literals from ``BioscaraStackEnv``'s docstring and the
module's constants (the target and both starts drawn within 1 rad of j1 with
the start pose's elbow, each start 7-15 cm from the target, 7 cm between the
starts and from the upper block to the lower one's way; the lower block at
the target in half the episodes; yaws within ±π/4; log reward summed over
the blocks), ``KinematicStack``'s (a block lands on the other only if they
overlap: closer than 3 cm in x and y) and plain geometry.
"""

from __future__ import annotations

import math
from collections.abc import Iterator

import numpy as np
import pytest
from rigs import ScriptedRng

from bioscara_gym import kinematics
from bioscara_gym.envs.stack import BioscaraStackEnv, KinematicStack, _segment_distance


@pytest.mark.parametrize(
    ("p", "distance"),
    [
        ((0.5, 1.0), 1.0),  # above the segment
        ((2.0, 1.0), math.sqrt(2.0)),  # past b: to b
        ((-1.0, 1.0), math.sqrt(2.0)),  # before a: to a
    ],
)
def test_segment_distance_is_to_the_nearest_point_of_the_segment(
    p: tuple[float, float], distance: float
) -> None:
    assert _segment_distance(np.array(p), np.zeros(2), np.array([1.0, 0.0])) == pytest.approx(distance)


def test_a_block_dropped_exactly_3_cm_beside_the_other_lands_on_the_table() -> None:
    k = KinematicStack()
    k.lower.place(np.array([0.0, 0.0, 0.015]), 0.0)
    k.upper.place(np.array([0.03, 0.0, 0.015]), 0.0)
    k.update(np.array([0.03, 0.0, 0.015]), 0.04)  # grasp the upper block
    k.update(np.array([0.03, 0.0, 0.06]), 0.04)  # lift it
    k.update(np.array([0.03, 0.0, 0.06]), 0.10)  # open: 3 cm apart is not overlapping
    assert k.upper.pos.tolist() == [0.03, 0.0, 0.015]


@pytest.fixture
def stack() -> Iterator[BioscaraStackEnv]:
    """A mock Stack env, not reset (a mutant's redraw loop would hang there)."""
    env = BioscaraStackEnv(backend="mock")
    yield env
    env.close()


def _pose(u: BioscaraStackEnv, q: list[float]) -> None:
    """The arm at ``q`` as it reports it (what the draws start from), read without noise."""
    u._q = u._q_arm = np.array(q)
    u._tcp = u._tcp_arm = kinematics.forward(u._q)


#: target: radius 0.4 m at the arm's j1; the upper block: radius 0.31 m at the same j1
#: (10 cm from the target); the coin (< 0.5: the lower block at the target); the yaws
SCRIPT = [0.5, 0.5, 0.2, 0.5, 0.2, 0.0, 0.999999]


@pytest.mark.parametrize(
    ("q", "elbow"),
    [
        ([1.0, 0.005, 0.5, -0.3], 1.0),  # the wrist's sign is not the elbow's
        ([1.0, 0.005, -0.5, 0.3], -1.0),
        ([0.0, 0.005, 0.0, 0.0], 1.0),  # the stretched arm: the positive elbow
    ],
)
def test_the_target_and_starts_are_drawn_around_j1_with_the_arms_elbow(
    stack: BioscaraStackEnv, q: list[float], elbow: float
) -> None:
    u = stack
    _pose(u, q)
    u.np_random = ScriptedRng(SCRIPT)
    goal = u._sample_goal()
    lower, upper = u._kinematic.lower.pos, u._kinematic.upper.pos
    np.testing.assert_array_equal(lower, goal[:3])  # the coin: the lower block at the target
    np.testing.assert_allclose(goal[3:], goal[:3] + np.array([0.0, 0.0, 0.03]))
    for point, radius in ((goal[:3], 0.4), (upper, 0.31)):
        assert kinematics.inverse(point, elbow)[0] == pytest.approx(q[0], abs=1e-9)
        assert math.hypot(*point[:2]) == pytest.approx(radius, abs=1e-9)


def test_the_yaws_span_a_quarter_turn_each_way_one_per_block(stack: BioscaraStackEnv) -> None:
    u = stack
    _pose(u, [1.0, 0.005, 0.5, 0.0])
    u.np_random = ScriptedRng(SCRIPT)
    u._sample_goal()
    assert u.block_yaws == pytest.approx((-0.7853981633974483, 0.7853981633974483), abs=1e-5)
    assert u.block_yaw == u.block_yaws[0]
    assert (u._kinematic.lower.yaw, u._kinematic.upper.yaw) == u.block_yaws


def test_a_lower_start_too_near_the_upper_block_is_drawn_again(stack: BioscaraStackEnv) -> None:
    u = stack
    _pose(u, [1.0, 0.005, 0.5, 0.0])
    # the coin at 0.5: the lower block away from the target. Its first draw (radius 0.31 m,
    # 0.1 rad on) is 3 cm from the upper block; the second (radius 0.49 m) is clear
    u.np_random = ScriptedRng([0.5, 0.5, 0.2, 0.5, 0.5, 0.2, 0.55, 0.8, 0.5, 0.0, 0.0])
    goal = u._sample_goal()
    lower, upper = u._kinematic.lower.pos, u._kinematic.upper.pos
    assert math.hypot(*lower[:2]) == pytest.approx(0.49, abs=1e-9)
    assert np.linalg.norm(lower[:2] - upper[:2]) >= 0.07
    assert 0.07 <= np.linalg.norm(lower[:2] - goal[:2]) <= 0.15


def test_the_log_reward_of_one_goal_is_summed_over_the_blocks() -> None:
    u = BioscaraStackEnv(backend="mock", reward_type="log")
    try:
        achieved = np.array([0.01, 0.0, 0.015, 0.0, 0.0, 0.045])  # the lower block 1 cm off
        desired = np.array([0.0, 0.0, 0.015, 0.0, 0.0, 0.045])
        assert u.compute_reward(achieved, desired, {}) == pytest.approx(-math.log(2.0))
        batch = u.compute_reward(np.stack([achieved, desired]), np.stack([desired, desired]), {})
        np.testing.assert_allclose(batch, [-math.log(2.0), 0.0])
    finally:
        u.close()


def test_the_mock_scene_shows_both_kinematic_blocks_and_the_upper_target(stack: BioscaraStackEnv) -> None:
    obs, _ = stack.reset(seed=0)
    scene = stack._scene()
    np.testing.assert_array_equal(scene.goal, obs["desired_goal"][3:])
    assert list(scene.joints) == ["j1", "j2", "j3", "j4"]
    assert scene.joints["j1"] == pytest.approx(float(stack._q[0]))
    (lower, lower_yaw), (upper, upper_yaw) = scene.bodies["block"], scene.bodies["block2"]
    np.testing.assert_array_equal(lower, obs["achieved_goal"][:3])
    np.testing.assert_array_equal(upper, obs["achieved_goal"][3:])
    assert (lower_yaw, upper_yaw) == stack.block_yaws


def test_a_new_stack_env_takes_positional_arguments_and_has_6_zero_goal_values() -> None:
    u = BioscaraStackEnv("mock", control_mode="position")
    try:
        assert u.sim is None and u.control_mode == "position"
        assert u.goal.tolist() == [0.0] * 6
        assert u.block_yaws == (0.0, 0.0)
        for key in ("achieved_goal", "desired_goal"):
            space = u.observation_space[key]
            assert space.shape == (6,) and space.dtype == np.float64
            assert np.all(space.low == -np.inf) and np.all(space.high == np.inf)
    finally:
        u.close()


@pytest.mark.parametrize(
    ("upper", "success"),
    [
        ((0.0, 0.0, 0.045), True),
        ((0.0, 0.0099, 0.045), True),
        ((0.0, 0.02, 0.045), False),  # 2 cm off sideways
        ((0.01, 0.0, 0.045), False),  # exactly 1 cm: not within
        ((0.0, 0.0, 0.003), False),  # exactly 3 mm off in height (a desired height of 0): not within
    ],
)
def test_success_is_both_blocks_within_1_cm_and_3_mm(
    stack: BioscaraStackEnv, upper: tuple[float, float, float], success: bool
) -> None:
    lower = (0.0, 0.0, 0.015)
    desired_upper = (0.0, 0.0, 0.0) if upper[2] == 0.003 else (0.0, 0.0, 0.045)
    achieved = np.array([*lower, *upper])
    desired = np.array([*lower, *desired_upper])
    assert bool(stack._is_success(achieved, desired)) is success
