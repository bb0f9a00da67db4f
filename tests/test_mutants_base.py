"""Tests that kill mutants of bioscara_gym/envs/base.py (issue #24 item 11, docs/mutation.md).

Episodes with latency and sensor-noise randomization on, on the mock backend
(fast, no MuJoCo). Expected values are literals from the sources: the
``DomainRandomization`` docstring (latency drawn 0..N control steps, noise a
Gaussian std on the measured joint positions), ``BioscaraEnv`` (the delay
line holds the arm until the first command comes through; a seed always
gives the same episode; noise and latency have streams of their own, so
turning them on does not change the tasks), the packaged configuration (j1:
1 rad/s, limits +-3.04647 rad; gripper 0.04-0.12 m, first width 0.08 m).
"""

from __future__ import annotations

from collections.abc import Iterator

import gymnasium as gym
import numpy as np
import pytest

import bioscara_gym  # noqa: F401  (registers the ids)
from bioscara_gym import kinematics

REACH = "Bioscara-Reach-v0"
PICK = "Bioscara-PickPlace-v1"
JOINTS = ("j1", "j2", "j3", "j4")


@pytest.fixture
def envs() -> Iterator[list[gym.Env]]:
    """Envs a test makes (``envs.append(gym.make(...))``), closed after it."""
    made: list[gym.Env] = []
    yield made
    for env in made:
        env.close()


def _make(envs: list[gym.Env], env_id: str = REACH, **kwargs: object) -> gym.Env:
    env = gym.make(env_id, backend="mock", **kwargs)
    envs.append(env)
    return env


def _true_joints(env: gym.Env) -> np.ndarray:
    """j1..j4 as the arm's drivers report them (no sensor noise)."""
    states = env.unwrapped.arm.joint_states
    return np.array([states[n].position for n in JOINTS])


def _seen_joints(env: gym.Env, obs: dict[str, np.ndarray]) -> np.ndarray:
    """j1..j4 as the policy sees them: ``joint_pos`` scaled back over the joint ranges."""
    lo, hi = np.array(env.unwrapped.joint_range).T
    return lo + (obs["observation"][:4] + 1.0) * 0.5 * (hi - lo)


# ------------------------------------------------------------------- latency


def _j1_commands(env: gym.Env, seed: int, speeds: list[float]) -> list[float]:
    """Reset with ``seed``, ask j1 for each of ``speeds`` (action = rad/s at 1 rad/s max); j1's commands."""
    env.reset(seed=seed)
    sent = []
    for v in speeds:
        env.step(np.array([v, 0.0, 0.0, 0.0], dtype=np.float32))
        sent.append(env.unwrapped.arm.commands["j1"])
    return sent


SPEEDS = [0.01, 0.02, 0.03, 0.04, 0.05, 0.06]


def _delay(sent: list[float]) -> int:
    """Steps the commands lag ``SPEEDS``: held (0) that long, then each action that late."""
    delay = next(i for i, c in enumerate(sent) if c != 0.0)
    assert sent[:delay] == [0.0] * delay
    assert sent[delay:] == pytest.approx(SPEEDS[: len(SPEEDS) - delay], rel=1e-6)  # float32 actions
    return delay


def test_latency_is_drawn_from_0_to_latency_steps_each_episode(envs: list[gym.Env]) -> None:
    env = _make(envs, control_mode="velocity", randomization={"latency_steps": 3})
    delays = [_delay(_j1_commands(env, seed, SPEEDS)) for seed in range(30)]
    assert set(delays) == {0, 1, 2, 3}


def test_no_latency_without_latency_randomization(envs: list[gym.Env]) -> None:
    env = _make(envs, control_mode="velocity", randomization={"sensor_noise": 0.001})
    for seed in range(5):
        assert _delay(_j1_commands(env, seed, SPEEDS)) == 0


def test_the_delay_line_starts_empty_each_episode(envs: list[gym.Env]) -> None:
    # a seed gives the same episode whatever ran before: nothing of the last one is sent
    used = _make(envs, control_mode="velocity", randomization={"latency_steps": 3})
    fresh = _make(envs, control_mode="velocity", randomization={"latency_steps": 3})
    for seed in range(4):
        _j1_commands(used, seed + 10, [0.5] * 3)  # an episode that leaves actions in the line
        assert _j1_commands(used, seed, SPEEDS) == _j1_commands(fresh, seed, SPEEDS)


@pytest.mark.parametrize("env_id", [REACH, PICK])
def test_turning_latency_on_does_not_change_the_tasks(envs: list[gym.Env], env_id: str) -> None:
    off = _make(envs, env_id)
    on = _make(envs, env_id, randomization={"latency_steps": 3})
    for seed in range(5):
        obs_off, _ = off.reset(seed=seed)
        obs_on, _ = on.reset(seed=seed)
        np.testing.assert_array_equal(_true_joints(on), _true_joints(off))
        np.testing.assert_array_equal(obs_on["desired_goal"], obs_off["desired_goal"])
        np.testing.assert_array_equal(obs_on["achieved_goal"], obs_off["achieved_goal"])


def test_position_mode_latency_holds_the_arm_and_the_gripper_until_the_first_command(
    envs: list[gym.Env],
) -> None:
    env = _make(envs, PICK, control_mode="position", randomization={"latency_steps": 2})
    u = env.unwrapped
    action = np.array([0.5, 0.5, 0.5, 0.5, 1.0], dtype=np.float32)
    held = through = 0
    for seed in range(12):
        env.reset(seed=seed)
        start = _true_joints(env)
        env.step(action)
        first = np.array([u.arm.commands[n] for n in JOINTS])
        if first[0] == pytest.approx(start[0], abs=1e-6):  # held where it is (a float32 action)
            np.testing.assert_allclose(first, start, atol=1e-6)
            assert u.arm.gripper_command == pytest.approx(0.08)  # the first width
            held += 1
        else:  # no delay drawn: j1 at 3/4 of its command range, the gripper wide open
            assert first[0] == pytest.approx(0.5 * (3.04647 - 0.03), abs=1e-6)
            assert u.arm.gripper_command == pytest.approx(0.12)
            through += 1
    assert held and through


# --------------------------------------------------------------- sensor noise


def test_sensor_noise_is_a_gaussian_of_the_given_std_on_each_joint_position(envs: list[gym.Env]) -> None:
    env = _make(envs, randomization={"sensor_noise": 0.01})
    obs, _ = env.reset(seed=7)
    hold = np.zeros(4, dtype=np.float32)
    errors = []
    for _ in range(300):
        errors.append(_seen_joints(env, obs) - _true_joints(env))
        obs, *_ = env.step(hold)
    e = np.array(errors)
    assert np.all(np.abs(e.mean(axis=0)) < 0.002)  # 300 draws: the mean's std is 0.0006
    assert np.all((e.std(axis=0) > 0.009) & (e.std(axis=0) < 0.011))
    assert np.all(np.abs(np.corrcoef(e.T) - np.eye(4)) < 0.2)  # each joint draws its own


def test_sensor_noise_reaches_the_tcp_but_not_the_velocities(envs: list[gym.Env]) -> None:
    noisy = _make(envs, randomization={"sensor_noise": 0.01})
    clean = _make(envs)
    obs_n, _ = noisy.reset(seed=3)
    obs_c, _ = clean.reset(seed=3)
    action = np.array([0.3, 0.0, -0.3, 0.2], dtype=np.float32)
    for _ in range(3):
        obs_n, *_ = noisy.step(action)
        obs_c, *_ = clean.step(action)
        o = obs_n["observation"]
        np.testing.assert_allclose(o[9:12], kinematics.forward(_seen_joints(noisy, obs_n)), atol=1e-9)
        np.testing.assert_array_equal(o[4:8], obs_c["observation"][4:8])
        np.testing.assert_array_equal(_true_joints(noisy), _true_joints(clean))
        assert np.all(np.abs(_seen_joints(noisy, obs_n) - _true_joints(noisy)) > 0.0)


def test_a_seed_gives_the_same_sensor_noise(envs: list[gym.Env]) -> None:
    a = _make(envs, randomization={"sensor_noise": 0.01})
    b = _make(envs, randomization={"sensor_noise": 0.01})
    hold = np.zeros(4, dtype=np.float32)
    obs_a, _ = a.reset(seed=11)
    a.reset(seed=12)
    obs_a2, _ = a.reset(seed=11)
    obs_b, _ = b.reset(seed=11)
    np.testing.assert_array_equal(obs_a["observation"], obs_b["observation"])
    np.testing.assert_array_equal(obs_a2["observation"], obs_b["observation"])
    for _ in range(3):
        np.testing.assert_array_equal(a.step(hold)[0]["observation"], b.step(hold)[0]["observation"])
    c_obs, _ = b.reset(seed=12)
    assert not np.array_equal(c_obs["observation"][:4], obs_b["observation"][:4])


def test_turning_sensor_noise_on_does_not_change_the_start_pose(envs: list[gym.Env]) -> None:
    off = _make(envs, PICK)
    on = _make(envs, PICK, randomization={"sensor_noise": 0.001})
    for seed in range(5):
        off.reset(seed=seed)
        on.reset(seed=seed)
        np.testing.assert_array_equal(_true_joints(on), _true_joints(off))
