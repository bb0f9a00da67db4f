"""``GoalErrorExtractor``: the goal error as a policy feature, right under HER relabelling."""

from __future__ import annotations

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
