"""From actions to joint commands: the pure mapping (:mod:`bioscara_gym.envs.actions`) and soft limits.

The mapping's tests build an :class:`ActionMap` from the packaged configuration
and pose it by hand: no arm, no backend. The soft-limit tests drive the
simulated arm into its end stops.
"""

from __future__ import annotations

import math
from collections.abc import Callable
from typing import Any

import gymnasium as gym
import numpy as np
import pytest

from bioscara_gym import kinematics
from bioscara_gym.envs import BioscaraReachEnv
from bioscara_gym.envs.actions import (
    CARTESIAN_J3_LIMITS,
    LIMIT_MARGIN,
    ActionMap,
    coordinated,
    ik_near,
    to_range,
    to_unit,
)
from bioscara_gym.hardware.config import load_config

REACH = "Bioscara-Reach-v0"
JOINTS = ("j1", "j2", "j3", "j4")
DT = 1.0 / 25.0

MakeEnv = Callable[..., gym.Env]


def _action_map(
    mode: str, cartesian_step: tuple[float, float, float] = (0.01, 0.01, 0.01), lead: bool = False
) -> ActionMap:
    """The map Reach builds for ``mode`` at 25 Hz on the packaged configuration (``lead``: PickPlace's)."""
    config = load_config()
    if mode == "cartesian":
        config = coordinated(config)
    return ActionMap.for_joints(mode, [config.joint(n) for n in JOINTS], DT, cartesian_step, lead=lead)


# ----------------------------------------------------------------- the map


def test_the_map_is_what_the_env_uses(make_env: MakeEnv) -> None:
    for mode in ("velocity", "position", "cartesian"):
        u = make_env(REACH, backend="mock", control_mode=mode).unwrapped
        m = _action_map(mode)
        np.testing.assert_array_equal(u.command_low, m.low)
        np.testing.assert_array_equal(u.command_high, m.high)
        q = np.array([0.3, 0.1, -0.7, 1.0])
        a = np.array([0.5, -0.25, 0.75, -1.0])
        np.testing.assert_array_equal(
            u._action_map.commands(a, q, kinematics.forward(q)), m.commands(a, q, kinematics.forward(q))
        )


def test_command_range_keeps_the_margin_inside_the_limits() -> None:
    m = _action_map("position")
    config = load_config()
    for i, name in enumerate(JOINTS):
        j = config.joint(name)
        margin = LIMIT_MARGIN[j.joint_type]
        assert m.low[i] == pytest.approx(j.min + margin)
        assert m.high[i] == pytest.approx(j.max - margin)


def test_cartesian_mode_caps_j3() -> None:
    m = _action_map("cartesian")
    assert (m.max_velocity[2], m.max_acceleration[2]) == CARTESIAN_J3_LIMITS
    np.testing.assert_array_equal(m.max_velocity[[0, 1, 3]], _action_map("velocity").max_velocity[[0, 1, 3]])


def test_unknown_mode_is_refused() -> None:
    with pytest.raises(ValueError, match="'torque'"):
        _action_map("torque")


def test_to_unit_inverts_to_range() -> None:
    lo, hi = np.array([-2.0, 0.0]), np.array([3.0, 0.5])
    a = np.array([-1.0, 0.3])
    np.testing.assert_allclose(to_unit(to_range(a, lo, hi), lo, hi), a)
    np.testing.assert_array_equal(to_range(np.array([-1.0, 1.0]), lo, hi), [lo[0], hi[1]])


def test_position_spans_the_command_range_and_neutral_holds() -> None:
    m = _action_map("position")
    np.testing.assert_array_equal(m.position(-np.ones(4)), m.low)
    np.testing.assert_allclose(m.position(np.ones(4)), m.high)
    q = np.array([0.3, 0.1, -0.7, 1.0])
    np.testing.assert_allclose(m.position(m.neutral(q)), q)


@pytest.mark.parametrize("mode", ["velocity", "cartesian"])
def test_neutral_is_zero_where_zero_holds(mode: str) -> None:
    np.testing.assert_array_equal(_action_map(mode).neutral(np.array([0.3, 0.1, -0.7, 1.0])), np.zeros(4))


def test_velocity_scales_by_max_velocity_away_from_the_stops() -> None:
    m = _action_map("velocity")
    q = (m.low + m.high) / 2.0
    a = np.array([0.5, -0.25, 0.75, -1.0])
    np.testing.assert_allclose(m.velocity(a, q), a * m.max_velocity)


def test_velocity_brakes_within_the_room_left() -> None:
    m = _action_map("velocity")
    at_stop = m.velocity(np.ones(4), m.high.copy())
    np.testing.assert_allclose(at_stop, 0.0, atol=1e-12)
    room = np.array([0.01, 0.001, 0.01, 0.01])
    v = m.stop_speed(room)
    # Held for one period, then braked at max acceleration: exactly the room.
    np.testing.assert_allclose(v * DT + v**2 / (2.0 * m.max_acceleration), room)
    np.testing.assert_allclose(m.velocity(np.ones(4), m.high - room), np.minimum(v, m.max_velocity))


# ------------------------------------------------------------ cartesian mode


def _pose(m: ActionMap, j1: float, j3: float, z: float = 0.1) -> tuple[np.ndarray, np.ndarray]:
    """The arm measured at (j1, z, j3, 0) and its TCP; ``m`` keeps the elbow j3 has."""
    q = np.array([j1, z, j3, 0.0])
    m.elbow = 1.0 if j3 >= 0 else -1.0
    return q, kinematics.forward(q)


def _toward(direction: np.ndarray) -> np.ndarray:
    """Cartesian action of full length along ``direction`` (x, y), wrist and z still."""
    action = np.zeros(4)
    action[:2] = direction / np.linalg.norm(direction)
    return action


def test_cartesian_push_into_the_inner_rim_slides_along_it() -> None:
    m = _action_map("cartesian")
    q, tcp = _pose(m, j1=0.5, j3=m.high[2])  # elbow folded as far as j3 allows: on the inner rim
    inward = -tcp[:2]
    tangent = np.array([-inward[1], inward[0]])
    cmd = m.cartesian(_toward(inward + tangent), q, tcp)
    assert cmd[2] <= m.high[2]
    assert abs(cmd[0] - q[0]) > 0.01, "the arm froze instead of sliding along the rim"
    r_min = m.reach[0]
    assert np.hypot(*kinematics.forward(cmd)[:2]) >= r_min - 1e-9


def test_cartesian_rim_keeps_j3_targets_inside_its_limits() -> None:
    m = _action_map("cartesian")
    q, tcp = _pose(m, j1=0.5, j3=m.high[2])
    cmd = m.cartesian(_toward(-tcp[:2]), q, tcp)  # straight at the base
    np.testing.assert_allclose(cmd[2], m.high[2], atol=1e-6)
    np.testing.assert_allclose(cmd[0], q[0], atol=1e-6)


@pytest.mark.parametrize("j3", [-1.5, -2.4])
def test_cartesian_stops_j1_at_its_limit_rather_than_swing_to_the_other_elbow(j3: float) -> None:
    m = _action_map("cartesian")
    q, tcp = _pose(m, j1=m.high[0] - 0.005, j3=j3)
    tangent = np.array([-tcp[1], tcp[0]])  # counter-clockwise: j1 would pass its limit
    cmd = m.cartesian(_toward(tangent), q, tcp)
    assert cmd[0] == pytest.approx(m.high[0])
    assert cmd[2] < 0 and m.elbow == -1.0
    assert np.all(np.abs(cmd[:3] - q[:3]) < 0.2)


def test_cartesian_switches_elbow_near_the_stretched_arm() -> None:
    m = _action_map("cartesian", lead=False)  # the IK target itself (Reach)
    q, tcp = _pose(m, j1=m.high[0] - 0.005, j3=-0.28)
    tangent = np.array([-tcp[1], tcp[0]])
    cmd = m.cartesian(_toward(tangent), q, tcp)
    assert cmd[2] > 0 and m.elbow == 1.0
    assert cmd[0] <= m.high[0]
    target = tcp[:2] + m.cartesian_step[0] * tangent / np.linalg.norm(tangent)
    np.testing.assert_allclose(kinematics.forward(cmd)[:2], target, atol=1e-9)


def test_cartesian_ik_keeps_j1_within_half_a_turn_of_the_arm() -> None:
    m = _action_map("cartesian")
    q, tcp = _pose(m, j1=2.98, j3=1.0)
    past_pi = kinematics.forward(np.array([3.2, 0.1, 1.0]))  # inverse() reports j1 as 3.2 - 2 pi
    j1, _, j3 = ik_near(past_pi, 1.0, q[0])
    assert j1 == pytest.approx(3.2) and j3 == pytest.approx(1.0)
    cmd = m.cartesian(np.zeros(4), q, tcp)
    assert cmd[0] == pytest.approx(2.98)


def test_cartesian_wrist_turns_by_wrist_step() -> None:
    m = _action_map("cartesian", lead=False)
    q, tcp = _pose(m, j1=0.5, j3=1.0)
    cmd = m.cartesian(np.array([0.0, 0.0, 0.0, -0.5]), q, tcp)
    assert cmd[3] == pytest.approx(q[3] - 0.05)
    np.testing.assert_allclose(cmd[:3], q[:3], atol=1e-9)


@pytest.mark.parametrize(
    ("step", "ahead"),
    [
        # j1 (1 rad/s, 2 rad/s^2) at 25 Hz: 0.02 rad in a step asks 0.5 rad/s, held with
        # the target 0.5 x 0.04 + 0.5^2 / (2 x 2) = 0.0825 rad ahead.
        (0.02, 0.0825),
        # 0.1 rad asks 2.5 rad/s: the max, 1 rad/s, held 1 x 0.04 + 1 / 4 = 0.29 rad ahead.
        (0.1, 0.29),
        (-0.02, -0.0825),
        (0.0, 0.0),  # nothing asked: the target is where the joint is
    ],
)
def test_cartesian_lead_puts_the_target_a_braking_distance_ahead(step: float, ahead: float) -> None:
    m = _action_map("cartesian")
    q = np.array([0.5, 0.1, 1.0, 0.0])
    target = q + np.array([step, 0.0, 0.0, 0.0])
    assert m.lead_target(q, target)[0] - q[0] == pytest.approx(ahead)


def test_a_long_cartesian_move_turns_j1_at_its_max_velocity_with_the_lead(make_env: MakeEnv) -> None:
    # Reach at 2 cm a step across the front (0.5 m/s asked): with the lead j1 reaches its
    # 1 rad/s; without it the firmware brakes on every step's target and j1 stays near 0.5.
    peaks = {}
    for lead in (False, True):
        step = (0.02, 0.02, 0.01)
        env = make_env(REACH, control_mode="cartesian", cartesian_lead=lead, cartesian_step=step)
        env.reset(seed=0)
        u = env.unwrapped
        tangent = np.array([-u.tcp_position()[1], u.tcp_position()[0]])
        action = np.zeros(4, dtype=np.float32)
        action[:2] = tangent / np.linalg.norm(tangent)
        speeds = []
        for _ in range(25):
            obs, *_ = env.step(action)
            speeds.append(abs(obs["observation"][4]))  # j1's velocity over its max
        peaks[lead] = max(speeds)
    assert peaks[True] > 0.95
    assert peaks[False] < 0.7


def test_reach_holds_the_ik_target_and_pickplace_leads_by_default() -> None:
    assert gym.make(REACH, backend="mock").unwrapped.cartesian_lead is False
    assert gym.make("Bioscara-PickPlace-v1", backend="mock").unwrapped.cartesian_lead is True
    assert gym.make(REACH, backend="mock", cartesian_lead=True).unwrapped._action_map.lead is True


# ----------------------------------------------------------------- soft limits


def _true_joints(env: gym.Env) -> np.ndarray:
    """j1..j4 from the MuJoCo state (not from the firmware or the observation)."""
    return env.unwrapped.sim.joint_positions()[:4]


def _soft_limit_cases() -> list[Any]:
    cases = []
    for name in JOINTS:
        for direction in (1.0, -1.0):
            sign = "+" if direction > 0 else "-"
            cases.append(pytest.param(name, direction, id=f"{name}{sign}"))
    return cases


@pytest.mark.parametrize(("joint", "direction"), _soft_limit_cases())
def test_full_speed_toward_end_stop_brakes_before_it(make_env: MakeEnv, joint: str, direction: float) -> None:
    probe = BioscaraReachEnv(backend="mock")
    cfg = probe.config.joint(joint)
    probe.close()
    steps = math.ceil((cfg.max - cfg.min) / cfg.max_velocity * 25.0) + 25  # time to cross the range
    env = make_env(REACH, max_episode_steps=steps)
    env.reset(seed=JOINTS.index(joint))
    idx = JOINTS.index(joint)
    push = np.zeros(4, dtype=np.float32)
    push[idx] = direction
    for i in range(steps):
        _, _, terminated, truncated, info = env.step(push)
        q = _true_joints(env)[idx]
        assert not terminated, f"step {i}: {info.get('stalled_joint')} stalled"
        assert cfg.min < q < cfg.max, f"step {i}: {joint} at {q} reached its end stop"
    assert truncated
    stop = cfg.max if direction > 0 else cfg.min
    assert abs(stop - q) < 0.05 * (cfg.max - cfg.min), f"{joint} stopped at {q}, far from {stop}"


def test_cartesian_step_keyword_sets_the_displacement_at_action_one(make_env: MakeEnv) -> None:
    env = make_env(REACH, control_mode="cartesian", cartesian_lead=False, cartesian_step=(0.05, 0.04, 0.01))
    env.reset(seed=0)
    u = env.unwrapped
    assert u.cartesian_step == (0.05, 0.04, 0.01)
    assert list(u._action_map.cartesian_step) == [0.05, 0.04, 0.01]
    assert make_env(REACH, cartesian_step=0.03).unwrapped.cartesian_step == (0.03, 0.03, 0.03)


@pytest.mark.parametrize("bad", [0, -0.01, (0.01, 0.01), (0.01, 0.01, math.inf), "far", [0.01, 0.0, 0.01]])
def test_a_cartesian_step_that_is_not_three_positive_lengths_is_one_line(bad: Any) -> None:
    with pytest.raises(
        ValueError, match=r"^cartesian_step .* must be one length or \(x, y, z\), each > 0 \(m\)$"
    ):
        gym.make(REACH, backend="mock", cartesian_step=bad)
