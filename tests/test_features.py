"""``GoalErrorExtractor``: the goal error as a policy feature, right under HER relabelling."""

from __future__ import annotations

import math

import gymnasium as gym
import numpy as np
import pytest
import torch as th
from gymnasium import spaces

from bioscara_gym.training.features import GoalErrorExtractor


def _goal_space(obs: int = 5, goal: int = 3) -> spaces.Dict:
    box = lambda n: spaces.Box(-np.inf, np.inf, shape=(n,), dtype=np.float64)  # noqa: E731
    return spaces.Dict({"observation": box(obs), "achieved_goal": box(goal), "desired_goal": box(goal)})


BATCH = {
    "observation": th.arange(10, dtype=th.float32).reshape(2, 5),
    "achieved_goal": th.tensor([[0.1, 0.2, 0.3], [0.0, 0.0, 0.0]]),
    "desired_goal": th.tensor([[0.12, 0.2, 0.29], [-0.04, 0.0, 0.0]]),
}
#: BATCH's goal error in units of 0.02 m.
ERROR = th.tensor([[1.0, 0.0, -0.5], [-2.0, 0.0, 0.0]])


def test_features_are_observation_and_scaled_error() -> None:
    extractor = GoalErrorExtractor(_goal_space(), scale=0.02)
    features = extractor(BATCH)
    assert extractor.features_dim == 5 + 3 == features.shape[1]
    th.testing.assert_close(features[:, :5], BATCH["observation"])
    th.testing.assert_close(features[:, 5:], ERROR)


def test_features_can_include_both_goals() -> None:
    extractor = GoalErrorExtractor(_goal_space(), scale=0.02, include_goals=True)
    features = extractor(BATCH)
    assert extractor.features_dim == 5 + 3 + 3 + 3 == features.shape[1]
    th.testing.assert_close(features[:, :5], BATCH["observation"])
    th.testing.assert_close(features[:, 5:8], BATCH["achieved_goal"])
    th.testing.assert_close(features[:, 8:11], BATCH["desired_goal"])
    th.testing.assert_close(features[:, 11:], ERROR)


def test_error_follows_a_relabelled_goal() -> None:
    """HER swaps ``desired_goal``; the error feature must change with it, not stay stale."""
    extractor = GoalErrorExtractor(_goal_space(), scale=0.01)
    obs = {"observation": th.zeros(1, 5), "achieved_goal": th.zeros(1, 3), "desired_goal": th.zeros(1, 3)}
    relabelled = {**obs, "desired_goal": th.tensor([[0.03, 0.0, 0.0]])}
    th.testing.assert_close(extractor(obs)[:, 5:], th.zeros(1, 3))
    th.testing.assert_close(extractor(relabelled)[:, 5:], th.tensor([[3.0, 0.0, 0.0]]))


def test_reach_space_gives_the_documented_feature_size() -> None:
    env = gym.make("Bioscara-Reach-v0", backend="mock")
    try:
        extractor = GoalErrorExtractor(env.observation_space)
    finally:
        env.close()
    assert extractor.features_dim == 12 + 3


@pytest.mark.parametrize(
    ("space", "message"),
    [
        (spaces.Box(-1, 1, shape=(3,)), "needs a Dict observation space"),
        (spaces.Dict({"observation": spaces.Box(-1, 1, shape=(3,))}), "lacks achieved_goal, desired_goal"),
        (spaces.Dict({**_goal_space().spaces, "desired_goal": spaces.Box(-1, 1, (2,))}), "differ"),
        (spaces.Dict({**_goal_space().spaces, "observation": spaces.Box(-1, 1, (2, 2))}), "flat entries"),
    ],
)
def test_unusable_space_is_refused_naming_the_problem(space: spaces.Space, message: str) -> None:
    with pytest.raises(ValueError, match=message):
        GoalErrorExtractor(space)


@pytest.mark.parametrize("scale", [0.0, -0.01])
def test_non_positive_scale_is_refused(scale: float) -> None:
    with pytest.raises(ValueError, match=f"scale {scale} must be > 0"):
        GoalErrorExtractor(_goal_space(), scale=scale)


def _stack_batch(lower: list[float], upper: list[float]) -> dict[str, th.Tensor]:
    """A Stack observation (indices from its docstring's table) with the target at (0.4, 0, 0.015)."""
    o = th.zeros(1, 32)
    o[0, 12:15] = th.tensor(lower)  # lower_pos
    o[0, 15:18] = th.tensor([0.1, 0.1, 0.1])  # lower_from_tcp
    o[0, 22:25] = th.tensor(upper)  # upper_pos
    o[0, 25:28] = th.tensor([0.01, 0.0, -0.02])  # upper_from_tcp
    o[0, 21], o[0, 31] = 0.3, -0.2  # lower_yaw, upper_yaw
    achieved = th.cat((o[:, 12:15], o[:, 22:25]), dim=1)
    return {
        "observation": o,
        "achieved_goal": achieved,
        "desired_goal": th.tensor([[0.4, 0, 0.015, 0.4, 0, 0.045]]),
    }


#: The upper block on the table, away from the target.
APART = [0.3, 0.1, 0.015]
#: Joint ranges whose middles are 0 rad for j1, j3, j4 (``joint_pos`` 0 there).
JOINT_RANGE = [[-3.0, 3.0], [0.0, 0.3], [-2.6, 2.6], [-3.0, 3.0]]
#: The lower block's yaw (0.3 rad) and the wrist's turn to it over pi/4, with j1 + j3 + j4 = 0:
#: 0.3 - pi/2 is -1.2708, a quarter turn on is 0.3 (the fingers lie along the tool's y axis).
LOWER_TURN = [0.3, 0.3 / (math.pi / 4)]
#: The upper block's (-0.2 rad), likewise.
UPPER_TURN = [-0.2, -0.2 / (math.pi / 4)]


@pytest.mark.parametrize(
    ("lower", "upper", "active"),
    [
        # 4 mm from the target, on the table: in place (the expert's 5 mm and the task's 3 mm),
        # so the upper block is worked on: from the TCP (0.01, 0, -0.02), and it goes a block
        # height (3 cm) over the lower one: (0.404, 0, 0.045) - (0.3, 0.1, 0.015).
        ([0.404, 0.0, 0.015], APART, [1, 0, 0.1, 0, -0.2, 1.04, -1, 0.3, 2, 0, -3, 3, -3, 3, *UPPER_TURN]),
        # 6 mm away, or 4 mm too high: the lower block is still the one to bring to the target.
        ([0.406, 0.0, 0.015], APART, [0, 0, 1, 1, 1, -0.06, 0, 0, 3, 3, 3, -1.2, 0, 0, *LOWER_TURN]),
        ([0.4, 0.0, 0.019], APART, [0, 0, 1, 1, 1, 0, 0, -0.04, 3, 3, 3, 0, 0, -0.8, *LOWER_TURN]),
        # The upper block 2.2 mm and 1 mm from its place on the lower one: done; 4 mm high: not.
        (
            [0.4, 0.0, 0.015],
            [0.402, 0.001, 0.046],
            [1, 1, 0.1, 0, -0.2, -0.02, -0.01, -0.01, 2, 0, -3, -0.4, -0.2, -0.2, *UPPER_TURN],
        ),
        (
            [0.4, 0.0, 0.015],
            [0.402, 0.001, 0.049],
            [1, 0, 0.1, 0, -0.2, -0.02, -0.01, -0.04, 2, 0, -3, -0.4, -0.2, -0.8, *UPPER_TURN],
        ),
    ],
)
def test_stack_features_end_with_the_block_being_worked_on(
    lower: list[float], upper: list[float], active: list[float]
) -> None:
    extractor = _stack_extractor()
    features = extractor(_stack_batch(lower, upper))
    assert features.shape == (1, extractor.features_dim)
    th.testing.assert_close(features[0, -16:], th.tensor(active), atol=1e-5, rtol=0)


def _stack_extractor() -> th.nn.Module:
    from bioscara_gym.training.features import StackExtractor

    env = gym.make("Bioscara-Stack-v0", backend="mock")
    try:
        return StackExtractor(env.observation_space, fine_m=0.005, joint_range=JOINT_RANGE)
    finally:
        env.close()


@pytest.mark.parametrize(
    ("j4", "turn"),
    [
        # j4 at 1.5 rad (0.5 of its range): 0.3 - 1.5 - pi/2 = -2.7708, two quarter turns on
        # 0.3708 rad; at -2.4 rad (-0.8): 0.3 + 2.4 - pi/2 = 1.1292, a quarter turn back -0.4416.
        (0.5, 0.3708 / (math.pi / 4)),
        (-0.8, -0.4416 / (math.pi / 4)),
    ],
)
def test_stack_wrist_turn_is_the_least_of_the_four_that_square_the_fingers(j4: float, turn: float) -> None:
    batch = _stack_batch([0.406, 0.0, 0.015], APART)
    batch["observation"][0, 3] = j4
    th.testing.assert_close(_stack_extractor()(batch)[0, -1], th.tensor(turn), atol=2e-4, rtol=0)


def test_stack_extractor_refuses_joint_ranges_it_cannot_unscale() -> None:
    from bioscara_gym.training.features import StackExtractor

    space = gym.make("Bioscara-Stack-v0", backend="mock").observation_space
    with pytest.raises(ValueError, match=r"joint_range .* must be 4 \[min, max\] pairs"):
        StackExtractor(space, joint_range=[[0.0, 1.0]] * 3)
    with pytest.raises(ValueError, match="must be 4"):
        StackExtractor(space, joint_range=[[1.0, 0.0]] * 4)
    with pytest.raises(ValueError, match="StackExtractor: joint_range is needed"):
        StackExtractor(space)


def _pick_extractor(**kwargs: object) -> th.nn.Module:
    from bioscara_gym.training.features import PickPlaceExtractor

    env = gym.make("Bioscara-PickPlace-v1", backend="mock")
    try:
        return PickPlaceExtractor(env.observation_space, **kwargs)
    finally:
        env.close()


def test_pickplace_features_without_joint_ranges_are_those_older_models_were_trained_on() -> None:
    # 22 observation values (the docstring's table), the goal error coarse (3) and fine (3),
    # block-from-TCP fine (3): a model saved before the wrist's turn loads with its shapes.
    assert _pick_extractor().features_dim == 22 + 3 + 3 + 3


@pytest.mark.parametrize(("j4", "turn"), [(0.0, 0.3 / (math.pi / 4)), (0.5, 0.3708 / (math.pi / 4))])
def test_pickplace_features_end_with_the_wrist_turn_given_joint_ranges(j4: float, turn: float) -> None:
    # As Stack's: block yaw 0.3 rad, j1 + j3 + j4 = 0 (or j4 1.5 rad: 0.3708 rad, see above).
    extractor = _pick_extractor(joint_range=JOINT_RANGE)
    o = th.zeros(1, 22)
    o[0, 21], o[0, 3] = 0.3, j4  # block_yaw, j4's joint_pos
    goal = th.zeros(1, 3)
    features = extractor({"observation": o, "achieved_goal": goal, "desired_goal": goal})
    assert features.shape == (1, 22 + 9 + 1) == (1, extractor.features_dim)
    th.testing.assert_close(features[0, -1], th.tensor(turn), atol=2e-4, rtol=0)
