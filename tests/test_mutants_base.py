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

import dataclasses
import math
import re
import warnings
from collections.abc import Iterator
from pathlib import Path

import gymnasium as gym
import numpy as np
import pytest

import bioscara_gym  # registers the ids
from bioscara_gym import kinematics
from bioscara_gym.envs.pick_place import BioscaraPickPlaceEnv
from bioscara_gym.envs.reach import BioscaraReachEnv
from bioscara_gym.hardware.backends import make_backend
from bioscara_gym.hardware.clock import ManualClock
from bioscara_gym.hardware.config import load_config
from bioscara_gym.hardware.errors import StalledError
from bioscara_gym.hardware.registers import Flag

REACH = "Bioscara-Reach-v0"
PICK = "Bioscara-PickPlace-v1"
JOINTS = ("j1", "j2", "j3", "j4")
DEFAULT_CONFIG = Path(bioscara_gym.__file__).parent / "hardware" / "default_config.yaml"


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


@pytest.mark.parametrize("env_id", [REACH, PICK, "Bioscara-Push-v0", "Bioscara-Stack-v0"])
def test_the_goal_is_drawn_from_the_arm_not_from_the_noisy_reading(envs: list[gym.Env], env_id: str) -> None:
    # Seen (a hostile test): noise of 0.5 rad left PickPlace's reset looking forever for a j1
    # in range (seed 63), and Reach's refused its range (ValueError: high - low < 0).
    off = _make(envs, env_id)
    on = _make(envs, env_id, randomization={"sensor_noise": 0.5})
    for seed in range(10):
        goal = off.reset(seed=seed)[0]["desired_goal"]
        np.testing.assert_array_equal(on.reset(seed=seed)[0]["desired_goal"], goal)


def test_a_held_block_follows_the_arm_not_the_noisy_reading(envs: list[gym.Env]) -> None:
    env = _make(envs, PICK, randomization={"sensor_noise": 0.01})
    env.reset(seed=0)
    block = env.unwrapped._block
    block.held, block._offset = True, np.zeros(3)
    close = np.array([0.0, 0.0, 0.0, 0.0, -1.0], dtype=np.float32)  # the gripper shut: it keeps the block
    obs = env.step(close)[0]
    tcp = kinematics.forward(_true_joints(env))
    np.testing.assert_allclose(obs["achieved_goal"], tcp, rtol=0, atol=1e-12)
    assert np.linalg.norm(obs["observation"][9:12] - tcp) > 1e-4  # the observed TCP is noisy


# ------------------------------------------------- the loop around the hooks


class _Phases:
    """A ``PhaseObserver`` that keeps what it is told."""

    def __init__(self) -> None:
        self.told: list[tuple[str, str]] = []

    def starting(self, phase: str, detail: str) -> None:
        self.told.append(("starting", phase))

    def done(self, phase: str, detail: str) -> None:
        self.told.append(("done", phase))


def test_bring_up_and_shut_down_tell_the_observer_each_step(envs: list[gym.Env]) -> None:
    u = _make(envs).unwrapped
    phases = _Phases()
    u.bring_up(phases)
    assert phases.told == [
        ("starting", "configure"),
        ("done", "configure"),
        ("starting", "activate"),
        ("done", "activate"),
        ("starting", "home"),
        ("done", "home"),
    ]
    u.reset(seed=0)
    phases = _Phases()
    assert u.shut_down(phases) == pytest.approx(0.08)  # the gripper's first width
    assert phases.told == [("done", "deactivate"), ("done", "cleanup")]


def test_reset_brings_the_arm_up_only_when_it_is_not_ready(
    envs: list[gym.Env], monkeypatch: pytest.MonkeyPatch
) -> None:
    env = _make(envs)
    u = env.unwrapped
    calls = []
    bring_up = u.bring_up
    monkeypatch.setattr(u, "bring_up", lambda: calls.append(u.arm.state) or bring_up())
    env.reset(seed=0)
    env.reset(seed=1)  # active and homed: nothing to bring up
    assert len(calls) == 1
    u.arm.deactivate()
    env.reset(seed=2)
    assert len(calls) == 2


def test_step_after_the_arm_stopped_asks_for_a_reset_saying_why(envs: list[gym.Env]) -> None:
    env = _make(envs)
    env.reset(seed=0)
    env.unwrapped.arm.deactivate()
    with pytest.raises(
        gym.error.ResetNeeded, match=r"^the arm is inactive \(the episode ended on a stall\); call reset\(\)$"
    ):
        env.step(np.zeros(4, dtype=np.float32))


def test_a_stall_ends_with_the_arm_read_again_all_joints_disabled(
    envs: list[gym.Env], monkeypatch: pytest.MonkeyPatch
) -> None:
    env = _make(envs)
    env.reset(seed=0)
    u = env.unwrapped

    def stall(dt: float) -> None:
        raise StalledError("stall detection tripped", joint="j2")

    monkeypatch.setattr(u.arm, "cycle", stall)
    _, _, terminated, _, info = env.step(np.zeros(4, dtype=np.float32))
    assert terminated
    assert all(info["flags"][n] & Flag.NOT_ENABLED for n in JOINTS)  # what the joints say after the stop


def test_a_float32_action_gives_the_commands_of_the_same_numbers_in_float64(envs: list[gym.Env]) -> None:
    env = _make(envs, control_mode="position")
    u = env.unwrapped
    action = np.array([0.1, 0.2, -0.3, 0.7], dtype=np.float32)
    sent = []
    for a in (action, action.astype(np.float64)):
        env.reset(seed=0)
        env.step(a)
        sent.append([u.arm.commands[n] for n in JOINTS])
    assert sent[0] == sent[1]


def test_actions_beyond_full_scale_are_clipped_to_it(envs: list[gym.Env]) -> None:
    # position mode: -1 and 1 are the ends of the command range (limits less 0.03 rad,
    # 0.002 m: j1 +-3.01647, j2 0.0004-0.336 m, j3 +-2.59672, j4 +-2.98069); the gripper 0.04-0.12 m
    env = _make(envs, PICK, control_mode="position")
    u = env.unwrapped
    env.reset(seed=0)
    env.step(np.array([-1.5, 1.5, -5.0, 5.0, 3.0], dtype=np.float32))
    assert [u.arm.commands[n] for n in JOINTS] == pytest.approx(
        [-3.01647, 0.336, -2.59672, 2.98069], abs=1e-12
    )
    assert u.arm.gripper_command == pytest.approx(0.12)
    env.step(np.array([1.5, -1.5, 5.0, -5.0, -3.0], dtype=np.float32))
    assert [u.arm.commands[n] for n in JOINTS] == pytest.approx(
        [3.01647, 0.0004, 2.59672, -2.98069], abs=1e-12
    )
    assert u.arm.gripper_command == pytest.approx(0.04)


def test_cartesian_steps_move_from_the_measured_tcp(envs: list[gym.Env]) -> None:
    env = _make(envs, control_mode="cartesian")  # Reach: 1 cm at action 1, the IK target itself
    u = env.unwrapped
    obs, _ = env.reset(seed=0)
    tcp = obs["observation"][9:12]
    env.step(np.array([1.0, 0.0, -1.0, 0.0], dtype=np.float32))
    target = kinematics.forward(np.array([u.arm.commands[n] for n in JOINTS]))
    np.testing.assert_allclose(target, tcp + np.array([0.01, 0.0, -0.01]), atol=1e-9)


def test_reset_stops_velocity_commands(envs: list[gym.Env]) -> None:
    env = _make(envs, control_mode="velocity")
    u = env.unwrapped
    env.reset(seed=0)
    env.step(np.full(4, 0.5, dtype=np.float32))
    env.reset(seed=1)
    assert [u.arm.commands[n] for n in JOINTS] == [0.0, 0.0, 0.0, 0.0]


@pytest.mark.parametrize("mode", ["velocity", "position"])
def test_reset_holds_the_arm_until_the_first_step_on_sim(mode: str) -> None:
    # sim: the start pose is set, not driven to, so the hold is what the joints are left with
    env = gym.make(REACH, control_mode=mode)
    try:
        u = env.unwrapped
        env.reset(seed=0)
        env.step(np.array([0.1, 0.2, 0.3, 0.4], dtype=np.float32))
        last = [u.arm.commands[n] for n in JOINTS]
        env.reset(seed=1)
        held = [u.arm.commands[n] for n in JOINTS]
        # velocity: stopped; position: the last targets kept
        assert held == ([0.0, 0.0, 0.0, 0.0] if mode == "velocity" else last)
    finally:
        env.close()


def test_the_arm_is_driven_to_the_start_pose_at_the_control_period(
    envs: list[gym.Env], monkeypatch: pytest.MonkeyPatch
) -> None:
    env = _make(envs, control_freq=50.0)
    u = env.unwrapped
    periods = []
    move_to = u.arm.move_to
    monkeypatch.setattr(
        u.arm, "move_to", lambda pose, **kw: periods.append(kw.get("period_s")) or move_to(pose, **kw)
    )
    env.reset(seed=0)
    assert periods == [0.02]


def test_every_episode_draws_its_own_sensor_noise(envs: list[gym.Env]) -> None:
    env = _make(envs, randomization={"sensor_noise": 0.01})
    seen = set()
    for seed in range(130):  # more episodes than a few noise streams could give
        obs, _ = env.reset(seed=seed)
        seen.add(tuple(np.round(_seen_joints(env, obs) - _true_joints(env), 12)))
    assert len(seen) == 130


def test_success_is_strictly_within_the_threshold(envs: list[gym.Env]) -> None:
    u = _make(envs).unwrapped  # distance_threshold 0.01 m
    assert not u._is_success(np.array([0.01, 0.0, 0.0]), np.zeros(3))  # |d| is exactly 0.01
    assert u._is_success(np.array([0.0099, 0.0, 0.0]), np.zeros(3))


def test_the_scene_shows_the_goal_and_the_measured_joints(envs: list[gym.Env]) -> None:
    env = _make(envs)
    obs, _ = env.reset(seed=2)
    scene = env.unwrapped._scene()
    np.testing.assert_array_equal(scene.goal, obs["desired_goal"])
    assert list(scene.joints) == list(JOINTS)
    np.testing.assert_allclose(list(scene.joints.values()), _seen_joints(env, obs), atol=1e-9)


def test_render_without_a_render_mode_warns_and_returns_nothing(envs: list[gym.Env]) -> None:
    env = _make(envs)
    env.reset(seed=0)
    with warnings.catch_warnings(record=True) as caught:
        warnings.simplefilter("always")
        assert env.unwrapped.render() is None
    # gymnasium's logger colours it: "WARN: " and the message between terminal colour codes
    message = "WARN: render() called without a render_mode; pass render_mode='rgb_array'"
    assert [str(w.message) for w in caught] == [f"\x1b[33m{message}\x1b[0m"]


def test_steps_draw_nothing_without_a_render_mode(envs: list[gym.Env]) -> None:
    env = _make(envs)
    env.reset(seed=0)
    with warnings.catch_warnings():
        warnings.simplefilter("error")
        env.step(np.zeros(4, dtype=np.float32))


class _View:
    """Stands in for the renderer: keeps what it is asked to draw."""

    def __init__(self) -> None:
        self.drawn: list[tuple[object, object]] = []

    def render(self, sim: object, scene: object) -> str:
        self.drawn.append((sim, scene))
        return "picture"

    def close(self) -> None:
        pass


def test_human_mode_draws_the_simulation_and_the_scene_each_step() -> None:
    env = gym.make(REACH)  # sim
    try:
        u = env.unwrapped
        env.reset(seed=0)
        u.render_mode, u._view = "human", _View()
        env.step(np.zeros(4, dtype=np.float32))
        env.step(np.zeros(4, dtype=np.float32))
        assert len(u._view.drawn) == 2
        sim, scene = u._view.drawn[-1]
        assert sim is u.sim
        np.testing.assert_array_equal(scene.goal, u.goal)
        assert u.render() == "picture"
    finally:
        env.close()


def test_a_still_cartesian_action_holds_the_arm_in_its_own_elbow(envs: list[gym.Env]) -> None:
    env = _make(envs, control_mode="cartesian")
    u = env.unwrapped
    signs = set()
    for seed in range(12):
        env.reset(seed=seed)
        start = _true_joints(env)
        env.step(np.zeros(4, dtype=np.float32))
        held = np.array([u.arm.commands[n] for n in JOINTS])
        np.testing.assert_allclose(held, start, atol=1e-6)  # not the other elbow's mirror pose
        signs.add(
            (float(np.sign(start[2])), bool(start[2] < 1.0), bool(np.sign(start[3]) == np.sign(start[2])))
        )
    # both elbows, j3 within 1 rad of the stretched arm too, j4 of either sign
    assert {s[0] for s in signs} == {-1.0, 1.0}
    assert (1.0, True) in {s[:2] for s in signs}
    assert {s[2] for s in signs} == {True, False}


def test_the_drives_jitter_is_seeded_from_the_whole_63_bit_range(monkeypatch: pytest.MonkeyPatch) -> None:
    env = gym.make(REACH)  # sim: the drives' PID-error jitter has a stream of its own
    try:
        u = env.unwrapped
        seeds: list[int] = []
        seed_drives = u.sim.seed_drives
        monkeypatch.setattr(u.sim, "seed_drives", lambda s: seeds.append(s) or seed_drives(s))
        for seed in range(20):
            env.reset(seed=seed)
        assert len(set(seeds)) == 20
        assert all(0 <= s < 2**63 for s in seeds) and max(seeds) > 2**62
    finally:
        env.close()


def test_joint_velocities_are_observed_over_each_joints_max_velocity(envs: list[gym.Env]) -> None:
    # max velocities (packaged configuration): j1 1 rad/s, j2 0.03 m/s, j3 5 rad/s, j4 10 rad/s
    env = _make(envs, control_mode="velocity")
    u = env.unwrapped
    env.reset(seed=0)
    action = np.array([0.5, -0.5, 0.25, -0.25], dtype=np.float32)
    obs, *_ = env.step(action)
    states = u.arm.joint_states
    assert [states[n].velocity for n in JOINTS] == pytest.approx([0.5, -0.015, 1.25, -2.5])
    np.testing.assert_allclose(obs["observation"][4:8], action, atol=1e-9)


def test_pick_place_takes_the_base_defaults_25_hz_and_1_cm() -> None:
    # PickPlace passes its arguments on: "max_episode_steps 200 (8 s at 25 Hz)",
    # "distance_threshold default 0.01 m" (its docstring)
    u = BioscaraPickPlaceEnv(backend="mock")
    try:
        assert u.control_freq == 25.0 and u.dt == 0.04
        assert u.distance_threshold == 0.01
        assert u.metadata["render_fps"] == 25
    finally:
        u.close()


# --------------------------------------------------------------- the arguments
#: How a refused image size ends.
FRAME = "(the scene's offscreen framebuffer)"


@pytest.mark.parametrize(
    ("kwargs", "message"),
    [
        ({"backend": "usb"}, "backend 'usb' is unknown; expected one of sim, mock, emulated, i2c, sitl"),
        ({"control_mode": "torque"}, "control_mode 'torque' must be one of velocity, position, cartesian"),
        ({"reward_type": "shaped"}, "reward_type 'shaped' must be one of 'dense', 'sparse', 'log'"),
        ({"distance_threshold": 0.0}, "distance_threshold 0.0 must be > 0 (m)"),
        ({"distance_threshold": -0.01}, "distance_threshold -0.01 must be > 0 (m)"),
        # Seen (a second hostile pass, through a config or a metadata.json): TypeErrors, or taken.
        ({"distance_threshold": "x"}, "distance_threshold 'x' must be a number > 0 (m)"),
        ({"distance_threshold": float("inf")}, "distance_threshold inf must be > 0 (m)"),
        ({"cartesian_lead": "x"}, "cartesian_lead 'x' must be true, false or None (the class's)"),
        ({"width": "x"}, f"width 'x' must be a whole number of pixels from 1 to 640 {FRAME}"),
        ({"height": 0}, f"height 0 must be a whole number of pixels from 1 to 480 {FRAME}"),
        # Seen (a hostile test of the env API): taken, then MuJoCo's "Image width 641 > framebuffer
        # width 640" at the first render().
        ({"width": 641}, f"width 641 must be a whole number of pixels from 1 to 640 {FRAME}"),
        ({"height": 481}, f"height 481 must be a whole number of pixels from 1 to 480 {FRAME}"),
        ({"width": True}, f"width True must be a whole number of pixels from 1 to 640 {FRAME}"),
        ({"backend_options": "x"}, "backend_options 'x' must be a dict of the backend's options"),
        (
            {"backend_options": {"bogus": 1}},
            "the mock backend takes no option bogus; its options: clock, homing_time_s, state_file",
        ),
        ({"config": 123}, "config 123 must be the path of a YAML file (or None: the packaged one)"),
    ],
)
def test_a_bad_argument_is_refused_in_one_line_naming_the_choices(kwargs: dict, message: str) -> None:
    with pytest.raises(ValueError, match=f"^{re.escape(message)}$"):
        BioscaraReachEnv(**{"backend": "mock", **kwargs})


def test_the_largest_image_fits_the_scenes_framebuffer_and_a_numpy_integer_is_a_size() -> None:
    from bioscara_gym.envs.rendering import MAX_HEIGHT, MAX_WIDTH

    u = BioscaraReachEnv(backend="sim", width=np.int64(640), height=np.int64(480))
    try:
        offscreen = u.sim.model.vis.global_
        assert (MAX_WIDTH, MAX_HEIGHT) == (offscreen.offwidth, offscreen.offheight) == (640, 480)
    finally:
        u.close()


def test_the_renderer_is_made_for_the_render_mode_at_480_by_480_by_default(
    monkeypatch: pytest.MonkeyPatch,
) -> None:
    monkeypatch.setenv("MUJOCO_GL", "egl")  # left alone by the env, restored after the test
    u = BioscaraReachEnv(backend="mock", render_mode="rgb_array")
    try:
        assert u.render_mode == "rgb_array"
        assert u._view.render_mode == "rgb_array"
        assert u._view.size == (480, 480)
    finally:
        u.close()
    u = BioscaraReachEnv(backend="mock", render_mode="rgb_array", width=640, height=360)
    try:
        assert u._view.size == (360, 640)
    finally:
        u.close()


def test_an_unknown_render_mode_is_refused() -> None:
    with pytest.raises(ValueError, match=r"^render_mode 'ascii' must be one of "):
        BioscaraReachEnv(backend="mock", render_mode="ascii")


def test_the_render_rate_is_the_control_rate() -> None:
    u = BioscaraReachEnv(backend="mock", control_freq=50.0)
    try:
        assert u.metadata["render_fps"] == 50
        assert u.dt == 0.02
    finally:
        u.close()


def test_the_cartesian_step_argument_replaces_the_tasks() -> None:
    u = BioscaraReachEnv(backend="mock", control_mode="cartesian", cartesian_step=0.02)
    try:
        assert u.cartesian_step == (0.02, 0.02, 0.02)
    finally:
        u.close()


def test_a_backend_instance_is_used_as_it_is() -> None:
    backend = make_backend("mock", load_config())
    u = BioscaraReachEnv(backend=backend)
    try:
        assert u.backend is backend
        assert u.sim is None
    finally:
        u.close()


def test_the_configuration_is_taken_as_given_or_loaded_from_a_path(tmp_path: Path) -> None:
    base = load_config()
    slow = dataclasses.replace(
        base,
        joints=tuple(dataclasses.replace(j, max_velocity=0.5) if j.name == "j1" else j for j in base.joints),
    )
    u = BioscaraReachEnv(backend="mock", config=slow)
    try:
        assert u.config.joint("j1").max_velocity == 0.5
    finally:
        u.close()
    path = tmp_path / "arm.yaml"
    path.write_text(DEFAULT_CONFIG.read_text().replace("max_velocity: 1.0 ", "max_velocity: 0.75 ", 1))
    u = BioscaraReachEnv(backend="mock", config=str(path))
    try:
        assert u.config.joint("j1").max_velocity == 0.75
    finally:
        u.close()


def test_the_backend_options_reach_the_backend() -> None:
    clock = ManualClock()
    u = BioscaraReachEnv(backend="mock", backend_options={"clock": clock})
    try:
        assert u.backend.clock is clock
    finally:
        u.close()


def test_cartesian_mode_runs_the_arm_with_j3_capped() -> None:
    # CARTESIAN_J3_LIMITS: 1.5 rad/s, 4 rad/s^2 (the packaged j3: 5 rad/s); the arm gets the capped limits too
    for mode, limits in (("cartesian", (1.5, 4.0)), ("position", (5.0, 14.0))):
        u = BioscaraReachEnv(backend="mock", control_mode=mode)
        try:
            for config in (u.config, u.arm.config):
                j3 = config.joint("j3")
                assert (j3.max_velocity, j3.max_acceleration) == limits
        finally:
            u.close()


@pytest.mark.parametrize(("cls", "size"), [(BioscaraReachEnv, 4), (BioscaraPickPlaceEnv, 5)])
def test_a_new_env_has_its_spaces_and_a_zero_goal(cls: type, size: int) -> None:
    u = cls(backend="mock")
    try:
        space = u.action_space
        assert space.shape == (size,) and space.dtype == np.float32
        assert space.low.tolist() == [-1.0] * size and space.high.tolist() == [1.0] * size
        assert u.goal.tolist() == [0.0, 0.0, 0.0]  # (3,) m until the first reset draws one
    finally:
        u.close()


# ------------------------------------------------ a hostile test of the env API
def test_step_before_reset_says_so_and_a_closed_env_is_named_closed(envs: list[gym.Env]) -> None:
    # Seen: "the arm is unconfigured (the episode ended on a stall)" before any reset, and
    # "cannot claim velocity on j1 while finalized" from reset() after close().
    u = _make(envs).unwrapped
    with pytest.raises(gym.error.ResetNeeded, match=r"^call reset\(\) before step\(\)$"):
        u.step(np.zeros(4))
    u.reset(seed=0)
    u.close()
    closed = r"^BioscaraReachEnv is closed; make a new env$"
    for call in (lambda: u.reset(seed=0), lambda: u.step(np.zeros(4)), u.render):
        with pytest.raises(gym.error.ClosedEnvironmentError, match=closed):
            call()
    u.close()  # twice is fine


@pytest.mark.parametrize("action", [np.zeros(4) + 1j, np.zeros(4, dtype=bool), ["0", "0", "0", "0"]])
def test_an_action_that_is_not_real_numbers_is_refused(envs: list[gym.Env], action: object) -> None:
    # Seen: a complex action lost its imaginary part with only numpy's ComplexWarning.
    env = _make(envs)
    env.reset(seed=0)
    dtype = np.asarray(action).dtype
    with pytest.raises(ValueError, match=f"^action of dtype {dtype} must be real numbers$"):
        env.step(action)
    env.step(np.zeros(4, dtype=np.int64))  # whole numbers are numbers


@pytest.mark.parametrize(
    ("env_id", "width", "reward_type"),
    [
        (REACH, 3, "dense"),
        (PICK, 3, "sparse"),
        ("Bioscara-Push-v0", 3, "sparse"),
        ("Bioscara-Stack-v0", 6, "sparse"),
        ("Bioscara-Stack-v0", 6, "dense"),
    ],
)
def test_compute_reward_refuses_goals_of_another_width(
    envs: list[gym.Env], env_id: str, width: int, reward_type: str
) -> None:
    u = _make(envs, env_id, reward_type=reward_type).unwrapped
    good = np.zeros((5, width))
    assert u.compute_reward(good, good, None).shape == (5,)
    message = f"^achieved_goal of shape \\(5, {width + 1}\\): this task's goals are {width} values each$"
    with pytest.raises(ValueError, match=message):
        u.compute_reward(np.zeros((5, width + 1)), np.zeros((5, width + 1)), None)
    scalar = f"^desired_goal of shape \\(\\): this task's goals are {width} values each$"
    with pytest.raises(ValueError, match=scalar):
        u.compute_reward(good, 0.0, None)


@pytest.mark.parametrize("options", [{"goal": [0.3, 0.0, 0.1]}, "x"])
def test_reset_options_are_refused_since_none_are_taken(envs: list[gym.Env], options: object) -> None:
    # Seen: options={"goal": ...} was taken silently, and the episode got a random goal.
    env = _make(envs)
    message = f"reset options {options!r} are not taken: an episode's start and goal come from the seed"
    with pytest.raises(ValueError, match=f"^{re.escape(message)}$"):
        env.reset(seed=0, options=options)
    env.reset(seed=0, options={})  # what SB3's vector envs pass
    env.reset(seed=0, options=None)


def test_a_sparse_reward_of_a_nan_distance_is_no_success(envs: list[gym.Env]) -> None:
    # Seen: -(nan >= threshold) is -0.0, success, where _is_success said False.
    u = _make(envs, reward_type="sparse").unwrapped
    rewards = u.compute_reward(np.array([[np.nan, 0, 0], [0, 0, 0], [0.02, 0, 0]]), np.zeros((3, 3)), None)
    np.testing.assert_array_equal(rewards, [-1.0, 0.0, -1.0])
    assert math.copysign(1.0, rewards[1]) == 1.0  # 0.0, not -0.0
