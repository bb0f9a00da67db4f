"""Tests that kill mutants of bioscara_gym/envs/reach.py (issue #24 item 11, docs/mutation.md).

Expected values are literals from ``BioscaraReachEnv``'s docstring (the
arguments table: ``goal_radius`` 0.15 m; the goal drawn in joint space,
kept within ``goal_radius`` of the start TCP, the draw shrunk toward the
start pose after 100 rejections), ``reachable_travel``'s (``a t^2 / 4``
below the peak speed, else ``v_max (t - v_max / a_max)``), worked by hand
for the packaged j1 (1 rad/s, 2 rad/s^2) and j3 (5 rad/s, 14 rad/s^2), and
``take_block_off_the_table``'s (a 1e9 damping, no contacts, invisible).
"""

from __future__ import annotations

import re

import mujoco
import numpy as np
import pytest

from bioscara_gym.assets import scene_path
from bioscara_gym.envs.reach import BioscaraReachEnv, reachable_travel, take_block_off_the_table


@pytest.mark.parametrize(
    ("t", "j1", "j3"),
    [
        # j1 peaks at 1 rad/s after 0.5 s (t_peak 1 s); j3 at 5 rad/s after 5/14 s (t_peak 5/7 s)
        (0.5, 2 * 0.25 / 4, 14 * 0.25 / 4),  # both triangular: 0.125, 0.875 rad
        (1.0, 0.5, 5 * (1.0 - 5 / 14)),  # j1 at its peak time: a t^2/4 = v (t - v/a) = 0.5
        (2.0, 1.5, 5 * (2.0 - 5 / 14)),  # both trapezoidal: 1 x (2 - 0.5)
    ],
)
def test_reachable_travel_is_a_triangle_then_a_trapezoid(t: float, j1: float, j3: float) -> None:
    travel = reachable_travel(np.array([1.0, 5.0]), np.array([2.0, 14.0]), t)
    np.testing.assert_allclose(travel, [j1, j3], rtol=1e-12)


def test_reach_pins_its_unused_block_intangible_and_invisible() -> None:
    model = mujoco.MjModel.from_xml_path(str(scene_path()))
    take_block_off_the_table(model)
    dofs = model.jnt_dofadr[model.joint("block").id] + np.arange(6)
    assert model.dof_damping[dofs].tolist() == [1e9] * 6
    geoms = model.geom_bodyid == model.body("block").id
    assert geoms.any()
    assert not model.geom_contype[geoms].any() and not model.geom_conaffinity[geoms].any()
    assert model.geom_rgba[geoms, 3].tolist() == [0.0] * int(geoms.sum())


def test_goals_are_within_15_cm_by_default_and_positional_arguments_reach_the_base() -> None:
    u = BioscaraReachEnv("mock", control_mode="position")
    try:
        assert u.goal_radius == 0.15
        assert u.sim is None and u.control_mode == "position"
        assert u.goal_horizon_s == pytest.approx(1.2)  # 60 % of 50 steps at 25 Hz
    finally:
        u.close()


@pytest.mark.parametrize(
    ("kwargs", "message"),
    [
        ({"goal_horizon_s": 0.0}, "goal_horizon_s 0.0 must be > 0 (seconds)"),
        ({"goal_horizon_s": -1.0}, "goal_horizon_s -1.0 must be > 0 (seconds)"),
        ({"goal_radius": 0.0}, "goal_radius 0.0 must be > 0 (m)"),
        ({"goal_radius": "abc"}, "goal_radius 'abc' must be a number > 0 (m)"),  # was a TypeError
        ({"goal_horizon_s": float("nan")}, "goal_horizon_s nan must be > 0 (seconds)"),
    ],
)
def test_a_goal_horizon_or_radius_of_zero_is_refused(kwargs: dict, message: str) -> None:
    with pytest.raises(ValueError, match=f"^{re.escape(message)}$"):
        BioscaraReachEnv(backend="mock", **kwargs)


class _ScriptedJoints:
    """Stands in for ``np_random``: ``uniform(lo, hi)`` returns the next joint vector of a script."""

    def __init__(self, draws: list[np.ndarray]) -> None:
        self._draws = list(draws)

    def uniform(self, low: object, high: object) -> np.ndarray:
        if not self._draws:
            raise AssertionError("more draws than scripted")
        return self._draws.pop(0)


@pytest.mark.parametrize(("rejected", "lift"), [(100, 0.02), (200, 0.01), (99, 0.04)])
def test_after_each_100_rejections_the_draw_is_shrunk_halfway_to_the_start(
    rejected: int, lift: float
) -> None:
    # A new env measures every joint at 0 (the TCP of the stretched arm). A draw 1 m up
    # is out of the 15 cm at any scale used here; a draw 4 cm up is kept, shrunk by
    # half after 100 rejections, by a quarter after 200.
    u = BioscaraReachEnv(backend="mock")
    try:
        far, near = np.array([0.0, 1.0, 0.0, 0.0]), np.array([0.0, 0.04, 0.0, 0.0])
        u.np_random = _ScriptedJoints([far] * rejected + [near])
        goal = u._sample_goal()
        np.testing.assert_allclose(u.goal_joints, [0.0, lift, 0.0, 0.0], atol=1e-12)
        np.testing.assert_allclose(goal, [0.614476, 0.0, 0.005 + lift], atol=1e-12)  # L1 + L2 along x
    finally:
        u.close()
