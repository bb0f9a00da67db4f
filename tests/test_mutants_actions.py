"""Tests that kill mutants of bioscara_gym/envs/actions.py (issue #24 item 11, docs/mutation.md).

Pure numpy, no env. Expected values are literals from the module's
docstrings and constants' comments (the margins 0.03 rad / 0.002 m, the
5 mm reach margin, j3 capped at 1.5 rad/s and 4 rad/s^2 in cartesian mode,
the 0.1 rad wrist step), the packaged configuration (j1 +-3.04647 rad,
1 rad/s, 2 rad/s^2; j3 +-2.62672 rad, 5 rad/s, 14 rad/s^2) and plain
geometry through :func:`bioscara_gym.kinematics.forward`.
"""

from __future__ import annotations

import dataclasses
import math
import re

import numpy as np
import pytest

from bioscara_gym import kinematics
from bioscara_gym.envs.actions import (
    ActionMap,
    check_cartesian_step,
    command_range,
    coordinated,
    planar_reach,
)
from bioscara_gym.hardware.config import load_config

JOINTS = ("j1", "j2", "j3", "j4")
DT = 0.04


def _map(mode: str, lead: bool = False) -> ActionMap:
    config = load_config()
    if mode == "cartesian":
        config = coordinated(config)
    return ActionMap.for_joints(mode, [config.joint(n) for n in JOINTS], DT, (0.01, 0.01, 0.01), lead=lead)


# ------------------------------------------------------------- module helpers


@pytest.mark.parametrize(
    ("step", "expected"),
    [(0.02, (0.02, 0.02, 0.02)), ((0.01, 0.02, 0.005), (0.01, 0.02, 0.005)), ([1, 2, 3], (1.0, 2.0, 3.0))],
)
def test_cartesian_step_is_three_floats(step: object, expected: tuple[float, float, float]) -> None:
    got = check_cartesian_step(step)
    assert got == expected
    assert all(type(v) is float for v in got)


@pytest.mark.parametrize("bad", [None, 0.0, (0.01, -0.01, 0.01), (0.01, math.nan, 0.01), "far"])
def test_a_bad_cartesian_step_is_refused_in_one_line(bad: object) -> None:
    message = f"cartesian_step {bad!r} must be one length or (x, y, z), each > 0 (m)"
    with pytest.raises(ValueError, match=f"^{re.escape(message)}$"):
        check_cartesian_step(bad)


def test_command_range_is_the_limits_less_the_margin_by_joint_type() -> None:
    config = load_config()
    lo, hi = command_range([config.joint(n) for n in JOINTS])
    np.testing.assert_allclose(lo, [-3.01647, 0.0004, -2.59672, -2.98069], atol=1e-12)
    np.testing.assert_allclose(hi, [3.01647, 0.336, 2.59672, 2.98069], atol=1e-12)
    lo, hi = command_range([config.joint(n) for n in JOINTS], {"revolute": 0.1, "prismatic": 0.0})
    np.testing.assert_allclose(lo, [-2.94647, -0.0016, -2.52672, -2.91069], atol=1e-12)


def test_coordinated_caps_only_j3_and_keeps_a_lower_limit() -> None:
    config = load_config()
    capped = coordinated(config)
    for name in ("j1", "j2", "j4"):
        assert capped.joint(name) == config.joint(name)
    j3 = capped.joint("j3")
    assert (j3.max_velocity, j3.max_acceleration) == (1.5, 4.0)
    slow = dataclasses.replace(
        config,
        joints=tuple(
            dataclasses.replace(j, max_velocity=1.0, max_acceleration=3.0) if j.name == "j3" else j
            for j in config.joints
        ),
    )
    j3 = coordinated(slow).joint("j3")
    assert (j3.max_velocity, j3.max_acceleration) == (1.0, 3.0)


def _rim(j3: float) -> float:
    """Distance of the TCP from the j1 axis with j3 at ``j3`` (plain forward kinematics)."""
    return float(np.hypot(*kinematics.forward(np.array([0.0, 0.0, j3, 0.0]))[:2]))


def test_planar_reach_is_the_annulus_j3_reaches_with_5_mm_to_spare() -> None:
    r_min, r_max = planar_reach(-2.59672, 2.59672)
    assert r_max == pytest.approx(0.329476 + 0.285 - 0.005, abs=1e-12)  # L1 + L2, less 5 mm
    assert r_min == pytest.approx(_rim(2.59672), abs=1e-12)  # folded as far as j3 goes
    # the tighter of the two limits folds it
    assert planar_reach(-2.0, 2.59672)[0] == pytest.approx(_rim(2.0), abs=1e-12)
    assert planar_reach(-2.59672, 2.0)[0] == pytest.approx(_rim(2.0), abs=1e-12)
    # j3 free to fold all the way: the inner hole is |L1 - L2| plus the 5 mm
    assert planar_reach(-4.0, 4.0)[0] == pytest.approx(0.329476 - 0.285 + 0.005, abs=1e-12)


# ------------------------------------------------------------------ ActionMap


def test_an_unknown_mode_is_refused_naming_the_modes() -> None:
    message = "control_mode 'torque' must be one of velocity, position, cartesian"
    with pytest.raises(ValueError, match=f"^{re.escape(message)}$"):
        _map("torque")


def test_a_map_keeps_its_limits_period_and_step() -> None:
    m = _map("cartesian")
    assert m.mode == "cartesian" and m.dt == DT and m.lead is False and m.elbow == 1.0
    np.testing.assert_array_equal(m.max_velocity, [1.0, 0.03, 1.5, 10.0])
    assert m.cartesian_step.tolist() == [0.01, 0.01, 0.01]
    assert m.cartesian_step.dtype == np.float64
    assert m.reach == planar_reach(m.low[2], m.high[2])
    config = load_config()
    default = ActionMap.for_joints("velocity", [config.joint(n) for n in JOINTS], DT, (0.01, 0.01, 0.01))
    assert default.lead is True  # the map's default, not the env's


def test_velocity_past_a_stop_only_moves_away_from_it() -> None:
    m = _map("velocity")
    beyond = m.high + np.array([0.01, 0.001, 0.01, 0.01])  # no room left: negative
    np.testing.assert_allclose(m.velocity(np.ones(4), beyond), 0.0, atol=1e-15)
    np.testing.assert_allclose(m.velocity(-0.5 * np.ones(4), beyond), -0.5 * m.max_velocity)


def test_velocity_counts_the_age_of_the_reading_only_when_it_is_positive() -> None:
    m = _map("velocity")
    q = m.high - 0.05
    qd = np.array([1.0, 0.03, 5.0, 10.0])
    np.testing.assert_array_equal(m.velocity(np.ones(4), q, qd, 0.0), m.velocity(np.ones(4), q))
    np.testing.assert_array_equal(m.velocity(np.ones(4), q, None, 0.1), m.velocity(np.ones(4), q))
    aged = m.velocity(np.ones(4), q, qd, 0.004)
    np.testing.assert_allclose(aged, m.velocity(np.ones(4), q + qd * 0.004))


def test_commands_dispatch_on_the_mode() -> None:
    q = np.array([0.3, 0.1, -0.7, 1.0])
    a = np.array([0.5, -0.25, 0.75, -1.0])
    tcp = kinematics.forward(q)
    for mode, expected in (
        ("velocity", _map("velocity").velocity(a, q)),
        ("position", _map("position").position(a)),
        ("cartesian", _map("cartesian").cartesian(a, q, tcp)),
    ):
        np.testing.assert_array_equal(_map(mode).commands(a, q, tcp), expected)


def test_position_neutral_is_clipped_into_the_unit_range() -> None:
    m = _map("position")
    np.testing.assert_array_equal(m.neutral(m.high + 1.0), [1.0, 1.0, 1.0, 1.0])
    np.testing.assert_array_equal(m.neutral(m.low - 1.0), [-1.0, -1.0, -1.0, -1.0])


def _pose(m: ActionMap, j1: float, j3: float, z: float = 0.1) -> tuple[np.ndarray, np.ndarray]:
    q = np.array([j1, z, j3, 0.0])
    m.elbow = 1.0 if j3 >= 0 else -1.0
    return q, kinematics.forward(q)


def test_cartesian_push_beyond_the_outer_rim_stops_on_it() -> None:
    m = _map("cartesian")
    q, tcp = _pose(m, j1=0.5, j3=0.3)  # near the stretched arm
    outward = tcp[:2] / np.linalg.norm(tcp[:2])
    for _ in range(10):
        cmd = m.cartesian(np.array([*outward, 0.0, 0.0]), q, tcp)
        q, tcp = cmd, kinematics.forward(cmd)
    assert np.hypot(*tcp[:2]) == pytest.approx(0.609476, abs=1e-9)  # L1 + L2 - 5 mm
    assert cmd[2] > 0  # still the same elbow


def test_cartesian_moves_each_axis_by_its_own_step() -> None:
    m = ActionMap.for_joints(
        "cartesian",
        [coordinated(load_config()).joint(n) for n in JOINTS],
        DT,
        (0.01, 0.02, 0.005),
        lead=False,
    )
    q, tcp = _pose(m, j1=0.5, j3=1.0)
    cmd = m.cartesian(np.array([1.0, -1.0, 1.0, 0.0]), q, tcp)
    np.testing.assert_allclose(kinematics.forward(cmd), tcp + np.array([0.01, -0.02, 0.005]), atol=1e-9)


def test_cartesian_holds_when_the_target_is_out_of_reach_on_the_axis() -> None:
    m = _map("cartesian")
    q = np.array([0.5, 0.1, 2.5, 0.0])
    tcp = np.array([0.0, 0.0, 0.105])  # a TCP measured on the j1 axis (r = 0): nothing to scale
    cmd = m.cartesian(np.zeros(4), q, tcp)
    np.testing.assert_allclose(cmd, q, atol=1e-12)


def test_a_step_without_its_age_is_taken_where_the_joint_was_measured() -> None:
    m = _map("velocity")
    q = m.high - 0.05
    qd = np.array([1.0, 0.03, 5.0, 10.0])
    at_q = m.velocity(np.ones(4), q)
    np.testing.assert_array_equal(m.velocity(np.ones(4), q, qd), at_q)
    tcp = kinematics.forward(q)
    np.testing.assert_array_equal(m.commands(np.ones(4), q, tcp, qd), at_q)
    aged = m.velocity(np.ones(4), q + qd * 0.004)
    assert np.all(aged <= at_q) and aged[0] < at_q[0]  # 4 ms closer to the stop: j1 braked harder
    np.testing.assert_allclose(m.commands(np.ones(4), q, tcp, qd, 0.004), aged)


def test_velocity_brakes_before_the_low_stop_too() -> None:
    m = _map("velocity")
    np.testing.assert_allclose(m.velocity(-np.ones(4), m.low.copy()), 0.0, atol=1e-12)
    np.testing.assert_allclose(m.velocity(np.ones(4), m.low.copy()), m.max_velocity)


def test_the_reach_is_j3s_even_with_a_narrower_wrist() -> None:
    low = np.array([-3.0, 0.0, -2.59672, -1.0])
    high = np.array([3.0, 0.3, 2.59672, 1.0])
    m = ActionMap("cartesian", low, high, np.ones(4), np.ones(4), DT, [1, 1, 1])
    assert m.reach[0] == pytest.approx(_rim(2.59672), abs=1e-12)
    assert m.cartesian_step.dtype == np.float64


def test_for_joints_keeps_the_margin_it_is_given() -> None:
    config = load_config()
    m = ActionMap.for_joints(
        "position",
        [config.joint(n) for n in JOINTS],
        DT,
        (0.01, 0.01, 0.01),
        {"revolute": 0.1, "prismatic": 0.0},
    )
    np.testing.assert_allclose(m.low, [-2.94647, -0.0016, -2.52672, -2.91069], atol=1e-12)


def test_cartesian_push_beyond_the_rim_keeps_the_tcp_height() -> None:
    m = _map("cartesian")
    q, tcp = _pose(m, j1=0.5, j3=0.05, z=0.1)  # 5 mm inside the outer rim or less
    outward = tcp[:2] / np.linalg.norm(tcp[:2])
    cmd = m.cartesian(np.array([*outward, 0.0, 0.0]), q, tcp)
    target = kinematics.forward(cmd)
    assert np.hypot(*target[:2]) == pytest.approx(0.609476, abs=1e-9)
    assert target[2] == pytest.approx(tcp[2], abs=1e-12)


def test_a_big_step_past_pi_stops_j1_at_its_limit_not_a_turn_back() -> None:
    # 10 cm a step at 0.3 m from the axis asks j1 about 0.3 rad: from 3.0 rad past pi,
    # where inverse() gives the same direction as -2.98 rad
    m = ActionMap.for_joints(
        "cartesian", [coordinated(load_config()).joint(n) for n in JOINTS], DT, (0.1, 0.1, 0.01), lead=False
    )
    q, tcp = _pose(m, j1=3.0, j3=1.5)
    tangent = np.array([-tcp[1], tcp[0]]) / np.hypot(tcp[0], tcp[1])  # counter-clockwise
    cmd = m.cartesian(np.array([*tangent, 0.0, 0.0]), q, tcp)
    assert cmd[0] == pytest.approx(m.high[0])
    assert m.elbow == 1.0 and cmd[2] > 0


@pytest.mark.parametrize("j1", [-1.0, 1.0])
def test_near_the_stretched_arm_the_elbow_stays_while_j1_is_in_range(j1: float) -> None:
    m = _map("cartesian", lead=False)
    q, tcp = _pose(m, j1=j1, j3=0.2)
    cmd = m.cartesian(np.array([0.3, 0.3, 0.0, 0.0]), q, tcp)
    assert m.elbow == 1.0 and cmd[2] > 0


def test_the_elbow_switch_depends_on_j3_not_on_the_wrist() -> None:
    m = _map("cartesian", lead=False)
    q, tcp = _pose(m, j1=m.high[0] - 0.005, j3=-0.28)
    q[3] = 2.0  # the wrist far from j3
    tangent = np.array([-tcp[1], tcp[0]])
    cmd = m.cartesian(np.array([*(tangent / np.linalg.norm(tangent)), 0.0, 0.0]), q, tcp)
    assert cmd[2] > 0 and m.elbow == 1.0


def test_the_elbow_switch_at_the_low_limit() -> None:
    m = _map("cartesian", lead=False)
    q, tcp = _pose(m, j1=m.low[0] + 0.005, j3=0.28)
    tangent = np.array([tcp[1], -tcp[0]])  # clockwise: j1 would pass its low limit
    cmd = m.cartesian(np.array([*(tangent / np.linalg.norm(tangent)), 0.0, 0.0]), q, tcp)
    assert cmd[2] < 0 and m.elbow == -1.0
    assert m.low[0] <= cmd[0] <= m.high[0]


def test_no_elbow_switch_when_the_other_elbow_is_past_the_limit_too() -> None:
    # the positive elbow at the high limit: the negative elbow's j1 is larger still
    m = _map("cartesian", lead=False)
    q, tcp = _pose(m, j1=m.high[0] - 0.005, j3=0.28)
    tangent = np.array([-tcp[1], tcp[0]])
    cmd = m.cartesian(np.array([*(tangent / np.linalg.norm(tangent)), 0.0, 0.0]), q, tcp)
    assert cmd[2] > 0 and m.elbow == 1.0
    assert cmd[0] == pytest.approx(m.high[0])


@pytest.mark.parametrize("j3", [-1.5, 1.5])
def test_cartesian_stops_j1_at_its_low_limit(j3: float) -> None:
    m = _map("cartesian")
    q, tcp = _pose(m, j1=m.low[0] + 0.005, j3=j3)
    tangent = np.array([tcp[1], -tcp[0]])
    cmd = m.cartesian(np.array([*(tangent / np.linalg.norm(tangent)), 0.0, 0.0]), q, tcp)
    assert cmd[0] == pytest.approx(m.low[0])


def test_with_the_lead_each_target_goes_a_braking_distance_ahead_of_the_ik_target() -> None:
    led, plain = _map("cartesian", lead=True), _map("cartesian", lead=False)
    for m in (led, plain):
        q, tcp = _pose(m, j1=0.5, j3=1.0)
    action = np.array([0.6, -0.8, 0.5, 0.3])
    target = plain.cartesian(action, q, tcp)
    cmd = led.cartesian(action, q, tcp)
    np.testing.assert_allclose(cmd, np.clip(led.lead_target(q, target), led.low, led.high), atol=1e-12)
    assert abs(cmd[0] - q[0]) > abs(target[0] - q[0])  # j1 well under its max: ahead of the IK target


def test_a_big_step_back_leads_by_the_max_velocity_braking_distance() -> None:
    # j1 at -0.1 rad a step asks -2.5 rad/s: the max, -1 rad/s, held 1 x 0.04 + 1 / 4 = 0.29 rad behind
    m = _map("cartesian")
    q = np.array([0.5, 0.1, 1.0, 0.0])
    assert m.lead_target(q, q + np.array([-0.1, 0.0, 0.0, 0.0]))[0] - q[0] == pytest.approx(-0.29)
