"""Bioscara-Push-v0: registration, documented spaces, goal sampling, success rule, physics, expert.

Expected values are the docstring's (``BioscaraPushEnv``) and the scene's
(``assets/scene.xml``, ``assets/bioscara.xml``): a 3 cm block, the gripper
closed at 0.04 m, fingertips 5 mm above the table at j2 = 0.
"""

from __future__ import annotations

import math
import re
from collections.abc import Callable

import gymnasium as gym
import numpy as np
import pytest
from conftest import expert_success
from test_envs_docs import _documented_kwargs, _slice, _table_rows

import bioscara_gym  # noqa: F401 - registers the tasks
from bioscara_gym import TASKS, kinematics
from bioscara_gym.envs import BioscaraEnv
from bioscara_gym.envs.push import Z_TOL, BioscaraPushEnv, KinematicPushBlock
from bioscara_gym.envs.reach import BioscaraReachEnv
from bioscara_gym.experts import PushExpert, expert_for, observation_expert_for

PUSH = "Bioscara-Push-v0"
MakeEnv = Callable[..., gym.Env]


# ---------------------------------------------------------------- registration


def test_push_is_registered_with_200_steps_and_dagger_by_default() -> None:
    assert gym.spec(PUSH).max_episode_steps == 200
    assert gym.spec(PUSH).entry_point == "bioscara_gym.envs.push:BioscaraPushEnv"
    assert TASKS[PUSH].default_method == "dagger"


def test_experts_are_the_push_expert(make_env: MakeEnv) -> None:
    u = make_env(PUSH, backend="mock").unwrapped
    assert isinstance(expert_for(u), PushExpert)
    assert isinstance(observation_expert_for(u), PushExpert)


# ------------------------------------------------------------- documentation


def test_documented_observation_layout_is_obs_slices() -> None:
    doc = BioscaraPushEnv.__doc__
    documented = {name: _slice(idx) for idx, name, *_ in _table_rows(doc, "idx", "OBS_SLICES")}
    assert list(documented.items()) == list(BioscaraPushEnv.OBS_SLICES.items())
    size = int(re.search(r"\| observation\s*\| \((\d+),\)", doc).group(1))
    assert max(s.stop for s in documented.values()) == size == 24


def test_push_takes_reachs_kwargs_but_the_goal_ones() -> None:
    doc = " ".join(BioscaraPushEnv.__doc__.split())
    assert "Reach's kwargs but ``goal_radius`` and ``goal_horizon_s``" in doc
    documented = _documented_kwargs(BioscaraReachEnv.__doc__)
    for goal_kwarg in ("goal_radius", "goal_horizon_s"):
        documented.pop(goal_kwarg)
        with pytest.raises(TypeError, match=goal_kwarg):
            BioscaraPushEnv(backend="mock", **{goal_kwarg: 0.1})
    import inspect

    defaults = {
        n: p.default
        for n, p in inspect.signature(BioscaraEnv.__init__).parameters.items()
        if n not in ("self", "args", "kwargs")
    }
    assert documented == defaults


def test_action_is_the_four_joints_and_the_gripper_stays_closed(make_env: MakeEnv) -> None:
    env = make_env(PUSH)
    u = env.unwrapped
    assert env.action_space.shape == (4,)
    obs, _ = env.reset(seed=0)
    env.action_space.seed(0)
    for _ in range(10):
        assert obs["observation"][u.OBS_SLICES["gripper"]][0] == pytest.approx(-1.0)  # 0.04 m
        obs, *_ = env.step(env.action_space.sample())
    # The simulated fingers are closed: their slides add up to the 0.04 m width.
    d, m = u.sim.data, u.sim.model
    width = sum(d.qpos[m.jnt_qposadr[m.joint(f).id]] for f in ("finger_left", "finger_right"))
    assert width == pytest.approx(0.04, abs=1e-3)


def test_tool_dir_is_the_pushing_faces_direction(make_env: MakeEnv) -> None:
    env = make_env(PUSH)
    u = env.unwrapped
    obs, _ = env.reset(seed=3)
    q = u.sim.joint_positions()[:4]
    c, s = obs["observation"][u.OBS_SLICES["tool_dir"]]
    assert math.atan2(s, c) == pytest.approx(math.remainder(q[0] + q[2] + q[3], 2 * math.pi), abs=1e-3)
    # The pads lie across the tool's x axis: finger_left - finger_right is perpendicular to it.
    pads = u.sim.data.body("finger_left").xpos[:2] - u.sim.data.body("finger_right").xpos[:2]
    assert abs(pads @ np.array([c, s])) < 1e-3 * np.linalg.norm(pads)


# ------------------------------------------------------------- goal sampling


def test_start_pose_and_goals_lie_where_the_docstring_says(make_env: MakeEnv) -> None:
    env = make_env(PUSH, backend="mock")
    u = env.unwrapped
    for seed in range(100):
        obs, _ = env.reset(seed=seed)
        tcp = obs["observation"][u.OBS_SLICES["tcp"]]
        block, target = obs["achieved_goal"], obs["desired_goal"]
        assert tcp[2] == pytest.approx(0.01, abs=1e-9), f"seed {seed}: fingertips 1 cm above the table"
        assert block[2] == pytest.approx(0.015) and target[2] == pytest.approx(0.015)
        assert 0.25 - 1e-9 <= math.hypot(*block[:2]) <= 0.55 + 1e-9, f"seed {seed}: block radius"
        assert 0.08 <= math.hypot(*(block[:2] - tcp[:2])) <= 0.25, f"seed {seed}: block from the TCP"
        assert 0.05 <= math.hypot(*(target[:2] - block[:2])) <= 0.2, f"seed {seed}: target from the block"
        elbow = 1.0 if u._q[2] >= 0 else -1.0
        j1_block = kinematics.inverse(block, elbow)[0]
        assert abs(j1_block - u._q[0]) <= 1.0 + 1e-6, f"seed {seed}: block out of j1's sector"


# ----------------------------------------------------------- success, reward


@pytest.mark.parametrize(
    ("offset", "success"),
    [
        ((0.0, 0.0, 0.0), True),
        ((0.009, 0.0, 0.0), True),
        ((0.006, 0.006, 0.0), True),  # 8.5 mm
        ((0.011, 0.0, 0.0), False),
        ((0.0, 0.0, 0.0025), True),  # resting, a little sunk or raised
        ((0.0, 0.0, 0.004), False),  # lifted: not resting on the table
        ((0.0, 0.0, 0.02), False),
        ((0.0, 0.0, 0.0062), False),  # tipped onto an edge: centre at 21.2 mm
    ],
)
def test_success_is_near_the_target_and_resting_on_the_table(
    make_env: MakeEnv, offset: tuple[float, float, float], success: bool
) -> None:
    u = make_env(PUSH, backend="mock", reward_type="sparse").unwrapped
    target = np.array([0.4, 0.1, 0.015])
    block = target + np.array(offset)
    assert bool(u._is_success(block, target)) is success
    assert u.compute_reward(block, target, {}) == (0.0 if success else -1.0)


def test_compute_reward_is_vectorized(make_env: MakeEnv) -> None:
    target = np.array([[0.4, 0.1, 0.015]] * 3)
    block = target + np.array([[0.0, 0.0, 0.0], [0.02, 0.0, 0.0], [0.0, 0.0, 0.02]])
    sparse = make_env(PUSH, backend="mock", reward_type="sparse").unwrapped
    np.testing.assert_array_equal(sparse.compute_reward(block, target, {}), [0.0, -1.0, -1.0])
    dense = make_env(PUSH, backend="mock").unwrapped
    np.testing.assert_allclose(dense.compute_reward(block, target, {}), [0.0, -0.02, -0.02])


# ------------------------------------------------------------------- physics


def _push_through_the_block(env: gym.Env, speed: float) -> tuple[np.ndarray, np.ndarray, list[float]]:
    """Drive the TCP at ``speed`` (share of the cartesian step) through the block to 10 cm past it.

    Returns the block's travel, the direction driven, and its height after every step.
    """
    u = env.unwrapped
    obs, _ = env.reset(seed=0)
    s = u.OBS_SLICES
    start = obs["achieved_goal"].copy()
    tcp = obs["observation"][s["tcp"]]
    u_dir = (start[:2] - tcp[:2]) / np.linalg.norm(start[:2] - tcp[:2])
    past = start[:2] + 0.1 * u_dir
    heights = []
    for _ in range(40):
        tcp = obs["observation"][s["tcp"]]
        way = speed * (past - tcp[:2]) / max(np.linalg.norm(past - tcp[:2]), 0.02)
        obs, _, terminated, _, _ = env.step(np.array([*way, 0.0, 0.0], dtype=np.float32))
        assert not terminated
        heights.append(float(obs["achieved_goal"][2]))
    return obs["achieved_goal"][:2] - start[:2], u_dir, heights


def test_the_closed_gripper_slides_the_block_without_lifting_it(make_env: MakeEnv) -> None:
    env = make_env(PUSH, control_mode="cartesian")
    m = env.unwrapped.sim.model
    assert m.geom_friction[m.geom("block").id, 0] == m.geom_friction[m.geom("table").id, 0] == 0.5
    # At the pace the expert pushes at most: PUSH_STEP_M a step (0.25 m/s).
    speed = PushExpert.PUSH_STEP_M / env.unwrapped.cartesian_step[0]
    moved, u_dir, heights = _push_through_the_block(env, speed)
    assert np.linalg.norm(moved) > 0.03, "the block should have been pushed"
    assert moved @ u_dir > 0.7 * np.linalg.norm(moved), "pushed along the TCP's way"
    assert max(heights) < 0.015 + 0.001, "the block never leaves the table"


def test_a_push_at_full_speed_rocks_the_block_by_less_than_the_success_tolerance(make_env: MakeEnv) -> None:
    # The cartesian actions keep the speed a step asks (targets lead by the braking
    # distance, as PickPlace-v1's), so the TCP meets the block at up to 0.5 m/s: the impact
    # lifts it about 1.3 mm and tips it about 1.4 degrees, within the success rule's Z_TOL.
    env = make_env(PUSH, control_mode="cartesian")
    moved, _, heights = _push_through_the_block(env, 1.0)
    assert np.linalg.norm(moved) > 0.03
    assert max(heights) < 0.015 + Z_TOL


def test_random_actions_never_lift_the_block(make_env: MakeEnv) -> None:
    env = make_env(PUSH, control_mode="cartesian")
    rng = np.random.default_rng(0)
    highest = 0.0
    for seed in range(6):
        obs, _ = env.reset(seed=seed)
        for _ in range(60):
            action = rng.uniform(-1, 1, 4).astype(np.float32)
            action[2] = -abs(action[2])  # press down as much as up: the closed pads cannot hold it
            obs, _, terminated, _, _ = env.step(action)
            highest = max(highest, float(obs["achieved_goal"][2]))
            if terminated:
                break
    assert highest < 0.015 + 0.001


def test_kinematic_block_is_pushed_out_of_the_closed_gripper() -> None:
    block = KinematicPushBlock(closed_width=0.04)  # footprint half-extents 0.012 (x) and 0.03 (y)
    block.place(np.array([0.4, 0.0, 0.015]), 0.3)
    block.update(np.array([0.38, 0.0, 0.01]), yaw=0.0)  # 5 mm of overlap along x
    np.testing.assert_allclose(block.pos, [0.38 + 0.012 + 0.015, 0.0, 0.015])
    assert block.yaw == 0.3
    block.place(np.array([0.4, 0.0, 0.015]), 0.0)
    block.update(np.array([0.36, 0.0, 0.01]), yaw=math.pi / 2)  # turned: 3 cm half-extent along x
    np.testing.assert_allclose(block.pos, [0.36 + 0.03 + 0.015, 0.0, 0.015], atol=1e-12)
    block.update(np.array([0.40, 0.0, 0.035]), yaw=0.0)  # fingertips above the block's top
    np.testing.assert_allclose(block.pos, [0.405, 0.0, 0.015], atol=1e-12)
    block.update(np.array([0.40, -0.005, 0.01]), yaw=0.0)  # centre inside: out by the nearer, narrow side
    np.testing.assert_allclose(block.pos, [0.40 + 0.012 + 0.015, 0.0, 0.015], atol=1e-12)


# -------------------------------------------------------------------- expert


def test_expert_succeeds_in_95_percent_of_40_cartesian_episodes() -> None:
    success, stalls = expert_success(PUSH, 40, control_mode="cartesian")
    assert success >= 0.95 and stalls == 0


@pytest.mark.slow
def test_expert_succeeds_in_95_percent_of_200_cartesian_episodes() -> None:
    success, stalls = expert_success(PUSH, 200, control_mode="cartesian")
    assert success >= 0.95 and stalls == 0


def test_expert_pushes_in_velocity_control_too() -> None:
    assert expert_success(PUSH, 10, control_mode="velocity")[0] >= 0.8


def test_expert_pushes_the_kinematic_block_on_mock() -> None:
    assert expert_success(PUSH, 10, control_mode="cartesian", backend="mock")[0] >= 0.8


def test_expert_is_a_function_of_the_observation(make_env: MakeEnv) -> None:
    env = make_env(PUSH, control_mode="cartesian")
    expert = PushExpert(env.unwrapped)
    obs, _ = env.reset(seed=1)
    for _ in range(30):
        obs, *_ = env.step(expert(obs))
    fresh = PushExpert(env.unwrapped)
    np.testing.assert_array_equal(fresh(obs), expert(obs))
