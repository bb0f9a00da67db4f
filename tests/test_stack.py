"""Bioscara-Stack-v0: registration, documented spaces, goal sampling, success rule, physics, expert.

Expected values are the docstring's (``BioscaraStackEnv``) and the scene's:
3 cm blocks, so a block resting on the table has its centre 15 mm high and
one resting on the other 45 mm.
"""

from __future__ import annotations

import math
import re
from collections.abc import Callable

import gymnasium as gym
import mujoco
import numpy as np
import pytest
from conftest import expert_success
from test_envs_docs import _slice, _table_rows

import bioscara_gym  # noqa: F401 - registers the tasks
from bioscara_gym import TASKS
from bioscara_gym.envs.stack import BioscaraStackEnv, KinematicStack
from bioscara_gym.experts import StackExpert, expert_for, observation_expert_for

STACK = "Bioscara-Stack-v0"
MakeEnv = Callable[..., gym.Env]


def _segment_distance(p: np.ndarray, a: np.ndarray, b: np.ndarray) -> float:
    t = np.clip((p - a) @ (b - a) / ((b - a) @ (b - a)), 0.0, 1.0)
    return float(np.linalg.norm(p - (a + t * (b - a))))


# ---------------------------------------------------------------- registration


def test_stack_is_registered_with_300_steps_and_dagger_by_default() -> None:
    assert gym.spec(STACK).max_episode_steps == 300
    assert gym.spec(STACK).entry_point == "bioscara_gym.envs.stack:BioscaraStackEnv"
    assert TASKS[STACK].default_method == "dagger"


def test_experts_are_the_stack_expert(make_env: MakeEnv) -> None:
    u = make_env(STACK, backend="mock").unwrapped
    assert isinstance(expert_for(u), StackExpert)
    assert isinstance(observation_expert_for(u), StackExpert)


# ------------------------------------------------------------- documentation


def test_documented_observation_layout_is_obs_slices(make_env: MakeEnv) -> None:
    doc = BioscaraStackEnv.__doc__
    documented = {name: _slice(idx) for idx, name, *_ in _table_rows(doc, "idx", "OBS_SLICES")}
    assert list(documented.items()) == list(BioscaraStackEnv.OBS_SLICES.items())
    sizes = dict(re.findall(r"\| (observation|achieved_goal|desired_goal)\s*\| \((\d+),\)", doc))
    assert sizes == {"observation": "32", "achieved_goal": "6", "desired_goal": "6"}
    env = make_env(STACK, backend="mock")
    assert {k: str(v.shape[0]) for k, v in env.observation_space.spaces.items()} == sizes


def test_obs_slices_hold_each_block(make_env: MakeEnv) -> None:
    env = make_env(STACK)
    u = env.unwrapped
    obs, _ = env.reset(seed=2)
    for _ in range(3):
        obs, *_ = env.step(env.action_space.sample())
    o, s = obs["observation"], u.OBS_SLICES
    for which, body in (("lower", "block"), ("upper", "block2")):
        np.testing.assert_array_equal(o[s[f"{which}_pos"]], u.sim.data.joint(body).qpos[:3])
        np.testing.assert_allclose(o[s[f"{which}_from_tcp"]], o[s[f"{which}_pos"]] - o[s["tcp"]])
    both = np.concatenate((o[s["lower_pos"]], o[s["upper_pos"]]))
    np.testing.assert_array_equal(obs["achieved_goal"], both)


# ------------------------------------------------------------- goal sampling


def test_targets_and_blocks_lie_where_the_docstring_says(make_env: MakeEnv) -> None:
    env = make_env(STACK, backend="mock")
    lower_there = 0
    for seed in range(100):
        obs, _ = env.reset(seed=seed)
        target, above = obs["desired_goal"][:3], obs["desired_goal"][3:]
        lower, upper = obs["achieved_goal"][:3], obs["achieved_goal"][3:]
        np.testing.assert_allclose(above, target + np.array([0.0, 0.0, 0.03]))
        assert target[2] == lower[2] == upper[2] == pytest.approx(0.015)
        assert 0.25 - 1e-9 <= math.hypot(*target[:2]) <= 0.55 + 1e-9, f"seed {seed}: target radius"
        assert 0.07 <= np.linalg.norm(upper[:2] - target[:2]) <= 0.15, f"seed {seed}: upper block"
        if np.array_equal(lower, target):
            lower_there += 1
            continue
        assert 0.07 <= np.linalg.norm(lower[:2] - target[:2]) <= 0.15, f"seed {seed}: lower block"
        assert np.linalg.norm(lower[:2] - upper[:2]) >= 0.07, f"seed {seed}: blocks too close"
        assert _segment_distance(upper[:2], lower[:2], target[:2]) >= 0.07, f"seed {seed}: in the way"
    assert 35 <= lower_there <= 65  # half the episodes start with the lower block there


# ----------------------------------------------------------- success, reward


TARGET = np.array([0.4, 0.1, 0.015, 0.4, 0.1, 0.045])


@pytest.mark.parametrize(
    ("offset", "success"),
    [
        ((0, 0, 0, 0, 0, 0), True),
        ((0.009, 0, 0, 0, 0.009, 0), True),
        ((0.011, 0, 0, 0.011, 0, 0), False),  # the stack 11 mm off the target
        ((0, 0, 0, 0.011, 0, 0), False),  # the upper block 11 mm off the lower one
        ((0, 0, 0, 0, 0, 0.0025), True),  # resting: a contact's depth either way
        ((0, 0, 0, 0, 0, 0.004), False),  # 4 mm above the lower block: not resting on it
        ((0, 0, 0, 0, 0, -0.03), False),  # beside it on the table
        ((0, 0, 0.03, 0, 0, 0.03), False),  # the lower block lifted too
    ],
)
def test_success_is_both_blocks_resting_in_their_places(
    make_env: MakeEnv, offset: tuple[float, ...], success: bool
) -> None:
    u = make_env(STACK, backend="mock", reward_type="sparse").unwrapped
    achieved = TARGET + np.array(offset)
    assert bool(u._is_success(achieved, TARGET)) is success
    assert u.compute_reward(achieved, TARGET, {}) == (0.0 if success else -1.0)


def test_rewards_are_per_block_and_vectorized(make_env: MakeEnv) -> None:
    achieved = np.stack([TARGET, TARGET + np.array([0.03, 0.04, 0, 0, 0, 0.012])])
    desired = np.stack([TARGET, TARGET])
    dense = make_env(STACK, backend="mock").unwrapped
    np.testing.assert_allclose(dense.compute_reward(achieved, desired, {}), [0.0, -(0.05 + 0.012)])
    log = make_env(STACK, backend="mock", reward_type="log").unwrapped
    expected = -(math.log1p(0.05 / 0.01) + math.log1p(0.012 / 0.01))
    np.testing.assert_allclose(log.compute_reward(achieved, desired, {}), [0.0, expected])
    sparse = make_env(STACK, backend="mock", reward_type="sparse").unwrapped
    np.testing.assert_array_equal(sparse.compute_reward(achieved, desired, {}), [0.0, -1.0])


# ------------------------------------------------------------------- physics


def _settle(env: gym.Env, steps: int = 25) -> dict[str, np.ndarray]:
    u = env.unwrapped
    hold = np.append(np.zeros(4), -0.5).astype(np.float32)  # cartesian: stay; the gripper open (0.06 m)
    for _ in range(steps):
        obs, _, terminated, _, info = env.step(hold)
        assert not terminated
    return obs | {"is_success": np.array(info["is_success"])}, u


def _drop_upper_block(env: gym.Env, offset_xy: tuple[float, float]) -> None:
    """Put the upper block 1 cm above its place on the lower one, ``offset_xy`` aside, at rest."""
    u = env.unwrapped
    lower = u.sim.data.body("block").xpos.copy()
    m, d = u.sim.model, u.sim.data
    a = m.jnt_qposadr[m.joint("block2").id]
    d.qpos[a : a + 3] = lower + np.array([offset_xy[0], offset_xy[1], 0.04])
    d.qpos[a + 3 : a + 7] = [1, 0, 0, 0]
    d.qvel[m.jnt_dofadr[m.joint("block2").id] : m.jnt_dofadr[m.joint("block2").id] + 6] = 0.0
    mujoco.mj_forward(m, d)


def _episode_with_lower_there(env: gym.Env) -> dict[str, np.ndarray]:
    for seed in range(20):
        obs, _ = env.reset(seed=seed)
        if np.array_equal(obs["achieved_goal"][:3], obs["desired_goal"][:3]):
            return obs
    raise AssertionError("no episode of seeds 0-19 starts with the lower block at the target")


def test_an_upper_block_dropped_on_the_lower_one_rests_on_it(make_env: MakeEnv) -> None:
    env = make_env(STACK, control_mode="cartesian")
    _episode_with_lower_there(env)
    _drop_upper_block(env, (0.004, -0.003))
    obs, _ = _settle(env)
    lower, upper = obs["achieved_goal"][:3], obs["achieved_goal"][3:]
    assert upper[2] == pytest.approx(0.045, abs=0.001), "resting on the lower block"
    np.testing.assert_allclose(upper[:2] - lower[:2], [0.004, -0.003], atol=0.001)
    assert obs["is_success"]


def test_an_upper_block_dropped_off_centre_falls_to_the_table(make_env: MakeEnv) -> None:
    env = make_env(STACK, control_mode="cartesian")
    _episode_with_lower_there(env)
    _drop_upper_block(env, (0.022, 0.0))  # its centre of mass beyond the lower block's edge
    obs, _ = _settle(env, steps=40)
    assert obs["achieved_goal"][5] < 0.035, "it cannot rest there: it tips off"
    assert not obs["is_success"]


@pytest.mark.parametrize("env_id", sorted(set(TASKS) - {STACK}))
def test_the_other_tasks_keep_block2_parked(make_env: MakeEnv, env_id: str) -> None:
    env = make_env(env_id)
    env.reset(seed=0)
    for _ in range(5):
        env.step(env.action_space.sample())
    sim = env.unwrapped.sim
    assert sim.data.body("block2").xpos[2] == pytest.approx(-2.0, abs=1e-9)
    assert sim.model.geom("block2").contype == sim.model.geom("block2").conaffinity == 0


def test_kinematic_blocks_stack_when_dropped_on_each_other() -> None:
    stack = KinematicStack()
    stack.lower.place(np.array([0.4, 0.0, 0.015]), 0.0)
    stack.upper.place(np.array([0.3, 0.0, 0.015]), 0.0)
    grasp = np.array([0.3, 0.0, 0.01])
    stack.update(grasp, width=0.04)  # closed on the upper block
    assert stack.upper.held and not stack.lower.held
    stack.update(np.array([0.405, 0.0, 0.045]), width=0.04)  # carried over the lower one
    stack.update(np.array([0.405, 0.0, 0.045]), width=0.08)  # and let go
    assert not stack.upper.held
    np.testing.assert_allclose(stack.upper.pos, [0.405, 0.0, 0.045])
    np.testing.assert_allclose(stack.lower.pos, [0.4, 0.0, 0.015])


# -------------------------------------------------------------------- expert


def test_expert_succeeds_in_95_percent_of_20_cartesian_episodes() -> None:
    success, stalls = expert_success(STACK, 20, control_mode="cartesian")
    assert success >= 0.95 and stalls == 0


@pytest.mark.slow
def test_expert_succeeds_in_95_percent_of_200_cartesian_episodes() -> None:
    success, stalls = expert_success(STACK, 200, control_mode="cartesian")
    assert success >= 0.95 and stalls == 0


def test_expert_stacks_the_kinematic_blocks_on_mock() -> None:
    assert expert_success(STACK, 6, control_mode="cartesian", backend="mock")[0] >= 0.8
