"""Feature extractors for goal-conditioned policies.

A policy for a goal task has to act on the goal error ``desired - achieved``.
Fed the two goals side by side in metres, a network must first learn weights
large enough to resolve a centimetre out of a workspace of a metre; that alone
took most of a 5-minute training budget on Bioscara-Reach.
:class:`GoalErrorExtractor` hands it the error directly, in units of ``scale``.
It is computed inside the network from whatever goals the batch holds, so it
stays right when HER relabels ``desired_goal`` (a goal-relative entry in the
env's ``observation`` would not).

By default the absolute goals are left out: the error and the observation
(which holds the arm's joints, so where the goals are) determine the action,
and every extra input is one more source of small, spurious action changes
near the goal, where Reach's 1 cm success radius is decided. Measured with
SAC+HER on Reach (100 episodes): 90 % success at 15k steps without them,
78-84 % with them.
"""

from __future__ import annotations

from gymnasium import spaces

from bioscara_gym.training.extras import needs_train

with needs_train():
    import torch as th
    from stable_baselines3.common.torch_layers import BaseFeaturesExtractor

GOAL_KEYS = ("observation", "achieved_goal", "desired_goal")


class GoalErrorExtractor(BaseFeaturesExtractor):
    """``observation`` and ``(desired - achieved) / scale`` (and both goals, if asked).

    Args:
        observation_space: A goal env's ``Dict`` space with flat ``Box`` entries
            ``observation``, ``achieved_goal`` and ``desired_goal``.
        scale: Length (in goal units, m for Bioscara) that maps to 1.0.
        include_goals: Also pass ``achieved_goal`` and ``desired_goal`` through.

    Raises:
        ValueError: The space lacks a key, an entry is not flat, the goals'
            shapes differ, or ``scale`` is not positive.
    """

    def __init__(
        self, observation_space: spaces.Dict, scale: float = 0.01, include_goals: bool = False
    ) -> None:
        """Check the space and size the features."""
        if not isinstance(observation_space, spaces.Dict):
            raise ValueError(f"GoalErrorExtractor needs a Dict observation space, got {observation_space}")
        missing = [k for k in GOAL_KEYS if k not in observation_space.spaces]
        if missing:
            raise ValueError(f"GoalErrorExtractor: observation space lacks {', '.join(missing)}")
        shapes = {k: observation_space[k].shape for k in GOAL_KEYS}
        if any(shape is None or len(shape) != 1 for shape in shapes.values()):
            raise ValueError(f"GoalErrorExtractor needs flat entries, got shapes {shapes}")
        if shapes["achieved_goal"] != shapes["desired_goal"]:
            raise ValueError(
                f"GoalErrorExtractor: achieved_goal {shapes['achieved_goal']} and "
                f"desired_goal {shapes['desired_goal']} differ in shape"
            )
        if not scale > 0:
            raise ValueError(f"GoalErrorExtractor: scale {scale} must be > 0")
        n_obs, n_goal = shapes["observation"][0], shapes["desired_goal"][0]
        super().__init__(observation_space, features_dim=n_obs + (3 if include_goals else 1) * n_goal)
        self.scale = float(scale)
        self.include_goals = bool(include_goals)

    def forward(self, observations: dict[str, th.Tensor]) -> th.Tensor:
        """Features of a batch of dict observations."""
        achieved, desired = observations["achieved_goal"], observations["desired_goal"]
        error = (desired - achieved) / self.scale
        if self.include_goals:
            return th.cat((observations["observation"], achieved, desired, error), dim=1)
        return th.cat((observations["observation"], error), dim=1)
