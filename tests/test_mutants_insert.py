"""Tests that kill mutants of bioscara_gym/envs/insert.py (issue #24 item 11, docs/mutation.md).

Expected values are literals from ``BioscaraInsertEnv``'s docstring and the
module's constants (the hole 0.3-0.55 m from the j1 axis, turned by a yaw in
[0, pi/2); the TCP within 3 cm of it, the peg's tip 3-8 mm above the 35 mm
top; the wrist anywhere in its command range; the goal 15 mm down the hole;
no success in a step that stalled; the lift at ``lift_speed`` with
``lift_sensitivity``), the packaged configuration (j2's max velocity
0.03 m/s, j4's command range ±2.98069 rad, the gripper's 0.04 m) and plain
geometry.
"""

from __future__ import annotations

import math
from collections.abc import Iterator

import numpy as np
import pytest
from rigs import ScriptedRng

from bioscara_gym import kinematics
from bioscara_gym.envs.insert import BioscaraInsertEnv

#: The goal's height: the fixture's 35 mm top less the 15 mm insertion depth.
GOAL_Z = 0.020
#: A hole only the positive elbow reaches (the negative one's j1 would pass -3.01647 rad) and its
#: mirror, which only the negative elbow reaches.
ONLY_POSITIVE = (-0.4972, 0.2351)
ONLY_NEGATIVE = (-0.4972, -0.2351)


@pytest.fixture
def insert() -> Iterator[BioscaraInsertEnv]:
    """A mock Insert env, not reset (a mutant's redraw loop would hang there)."""
    env = BioscaraInsertEnv(backend="mock")
    yield env
    env.close()


def _tip(pose: np.ndarray) -> np.ndarray:
    """The peg's tip for a start pose: the TCP 30 mm lower."""
    return kinematics.forward(pose) - np.array([0.0, 0.0, 0.03])


# ------------------------------------------------------------------ the draws
#: coin (elbow), hole radius 0.4 m, hole j1 0, hole yaw pi/4, TCP 15 mm off, bearing 0 (+x),
#: gap 3 mm, j4 a quarter of the way up its range.
SCRIPT = [0.2, 0.4, 0.5, 0.5, 0.5, 0.5, 0.0, 0.25]


@pytest.mark.parametrize(("coin", "elbow"), [(0.2, 1.0), (0.7, -1.0)])
def test_the_hole_is_drawn_around_j1_with_the_starts_elbow(
    insert: BioscaraInsertEnv, coin: float, elbow: float
) -> None:
    u = insert
    u.np_random = ScriptedRng([coin, *SCRIPT[1:]])
    pose = u._random_pose()
    assert math.hypot(*u._hole_xy) == pytest.approx(0.4, abs=1e-9)
    assert kinematics.inverse(np.array([*u._hole_xy, 0.0]), elbow)[0] == pytest.approx(0.0, abs=1e-9)
    assert u.hole_yaw == pytest.approx(math.pi / 4)
    assert math.copysign(1.0, pose[2]) == elbow


def test_the_hole_yaw_spans_a_quarter_turn(insert: BioscaraInsertEnv) -> None:
    u = insert
    for f, yaw in ((0.0, 0.0), (0.999999, math.pi / 2)):
        u.np_random = ScriptedRng([0.4, 0.5, f])
        _, drawn = u._draw_fixture(1.0)
        assert drawn == pytest.approx(yaw, abs=1e-5)


@pytest.mark.parametrize(
    ("bearing", "offset"),
    [(0.5, (0.015, 0.0)), (0.25, (0.0, -0.015)), (0.75, (0.0, 0.015)), (0.0, (-0.015, 0.0))],
)
def test_the_tcp_starts_at_the_drawn_offset_and_bearing_from_the_hole(
    insert: BioscaraInsertEnv, bearing: float, offset: tuple[float, float]
) -> None:
    u = insert
    script = list(SCRIPT)
    script[5] = bearing  # bearing = -pi + f 2 pi
    u.np_random = ScriptedRng(script)
    pose = u._random_pose()
    np.testing.assert_allclose(_tip(pose)[:2], u._hole_xy + np.array(offset), atol=1e-9)


@pytest.mark.parametrize(("f", "distance"), [(0.0, 0.0), (1.0, 0.03)])
def test_the_tcp_starts_within_3_cm_of_the_hole(insert: BioscaraInsertEnv, f: float, distance: float) -> None:
    u = insert
    script = list(SCRIPT)
    script[4] = f
    u.np_random = ScriptedRng(script)
    pose = u._random_pose()
    assert math.hypot(*(_tip(pose)[:2] - u._hole_xy)) == pytest.approx(distance, abs=1e-9)


@pytest.mark.parametrize(("f", "height"), [(0.0, 0.035 + 0.003), (1.0, 0.035 + 0.008)])
def test_the_peg_tip_starts_3_to_8_mm_above_the_fixture(
    insert: BioscaraInsertEnv, f: float, height: float
) -> None:
    u = insert
    script = list(SCRIPT)
    script[6] = f
    u.np_random = ScriptedRng(script)
    assert _tip(u._random_pose())[2] == pytest.approx(height, abs=1e-12)


@pytest.mark.parametrize(("f", "j4"), [(0.25, -1.490345), (0.0, -2.98069), (1.0, 2.98069)])
def test_the_wrist_starts_anywhere_in_its_command_range(
    insert: BioscaraInsertEnv, f: float, j4: float
) -> None:
    u = insert
    script = list(SCRIPT)
    script[7] = f
    u.np_random = ScriptedRng(script)
    assert u._random_pose()[3] == pytest.approx(j4, abs=1e-9)


@pytest.mark.parametrize(
    ("hole", "coin", "elbow"),
    [
        (ONLY_POSITIVE, 0.7, 1.0),  # the negative elbow drawn cannot reach it: the other one
        (ONLY_POSITIVE, 0.2, 1.0),
        (ONLY_NEGATIVE, 0.2, -1.0),
        ((0.45, -0.1), 0.7, -1.0),  # both reach it: the elbow drawn
        ((0.45, -0.1), 0.2, 1.0),
    ],
)
def test_a_bolted_fixture_is_reached_with_an_elbow_that_can(
    hole: tuple[float, float], coin: float, elbow: float
) -> None:
    env = BioscaraInsertEnv(backend="mock", fixture_pose=(*hole, 0.3))
    try:
        env.np_random = ScriptedRng([coin, 0.5, 0.5, 0.0, 0.25])
        pose = env._random_pose()
        assert env._hole_xy.tolist() == list(hole) and env.hole_yaw == 0.3
        assert math.copysign(1.0, pose[2]) == elbow
        np.testing.assert_allclose(_tip(pose)[:2], np.add(hole, [0.015, 0.0]), atol=1e-9)
        env._hole_xy[0] = 9.0  # the drawn hole is a copy: the bolted pose stays
        assert env.fixture_pose.tolist() == [*hole, 0.3]
    finally:
        env.close()


def test_the_goal_is_15_mm_down_the_hole(insert: BioscaraInsertEnv) -> None:
    u = insert
    u._hole_xy = np.array([0.4, -0.1])
    np.testing.assert_allclose(u._sample_goal(), [0.4, -0.1, GOAL_Z], atol=1e-15)


def test_the_sim_stands_the_fixture_at_the_hole_turned_by_its_yaw() -> None:
    env = BioscaraInsertEnv(backend="sim", fixture_pose=(0.45, -0.1, 0.3))
    try:
        env.reset(seed=0)
        m, d = env.sim.model, env.sim.data
        mocap = m.body("fixture").mocapid[0]
        np.testing.assert_allclose(d.mocap_pos[mocap], [0.45, -0.1, 0.0])
        # A turn of 0.3 rad about z: (cos 0.15, 0, 0, sin 0.15).
        np.testing.assert_allclose(d.mocap_quat[mocap], [0.9887710779, 0.0, 0.0, 0.1494381325], atol=1e-9)
        assert m.geom_rgba[m.geom("peg").id, 3] == 1.0  # the peg is shown
        obstacle = m.body("obstacle")  # another mocap: it stays where the scene parks it
        np.testing.assert_array_equal(d.mocap_pos[obstacle.mocapid[0]], m.body_pos[obstacle.id])
        np.testing.assert_array_equal(d.mocap_quat[obstacle.mocapid[0]], m.body_quat[obstacle.id])
        block = m.geom_bodyid == m.body("block").id  # PickPlace's block: taken off the table
        assert not m.geom_contype[block].any() and not m.geom_rgba[block, 3].any()
    finally:
        env.close()


# ------------------------------------------------------------ the arguments
def test_a_new_insert_env_takes_positional_arguments_and_starts_with_no_hole() -> None:
    env = BioscaraInsertEnv("mock", "velocity", 20.0, "sparse")
    try:
        assert (env.control_mode, env.control_freq, env.reward_type) == ("velocity", 20.0, "sparse")
        assert env.distance_threshold == 0.002 and env.fixture_pose is None
        assert env.lift_speed == 0.006 and env.config.joint("j2").stall_threshold == 4
        assert env.hole_yaw == 0.0 and env._hole_xy.tolist() == [0.0, 0.0]
    finally:
        env.close()


def test_the_lift_speed_may_be_j2s_max_velocity_with_its_own_sensitivity() -> None:
    env = BioscaraInsertEnv(backend="mock", lift_speed=0.03, lift_sensitivity=7)
    try:
        j2 = env.config.joint("j2")
        assert (j2.max_velocity, j2.stall_threshold) == (0.03, 7)
        assert [j.name for j in env.config.joints] == ["j1", "j2", "j3", "j4"]
        assert env.config.joint("j1").max_velocity == 1.0  # the other joints untouched
    finally:
        env.close()


@pytest.mark.parametrize(
    ("kwargs", "message"),
    [
        ({"lift_speed": True}, "lift_speed True must be a speed > 0 (m/s)"),
        ({"lift_speed": -0.001}, "lift_speed -0.001 must be a speed > 0 (m/s)"),
        ({"lift_speed": 0.05}, "lift_speed 0.05 m/s is above j2's max velocity 0.03 m/s"),
        ({"fixture_pose": (0.4, 0.0)}, "fixture_pose (0.4, 0.0) must be (x m, y m, yaw rad)"),
        ({"fixture_pose": (0.4, "a", 0.0)}, "fixture_pose (0.4, 'a', 0.0) must be (x m, y m, yaw rad)"),
        ({"fixture_pose": (0.4, 0.0, math.inf)}, "fixture_pose (0.4, 0.0, inf) must be finite"),
        ({"fixture_pose": (math.nan, 0.0, 0.0)}, "fixture_pose (nan, 0.0, 0.0) must be finite"),
        (
            {"fixture_pose": (2.0, 0.5, 0.0)},
            "fixture_pose (2.0, 0.5, 0.0): the arm cannot reach the hole at (2, 0.5) m",
        ),
    ],
)
def test_bad_arguments_are_refused_with_their_whole_message(kwargs: dict, message: str) -> None:
    with pytest.raises(ValueError) as caught:
        BioscaraInsertEnv(backend="mock", **kwargs)
    assert str(caught.value) == message
    if "(x m, y m, yaw rad)" in message:  # raised ``from None``: one line, not the parse error's traceback
        assert caught.value.__cause__ is None and caught.value.__suppress_context__


@pytest.mark.parametrize("hole", [ONLY_POSITIVE, ONLY_NEGATIVE])
def test_a_hole_one_elbow_reaches_may_be_bolted(hole: tuple[float, float]) -> None:
    env = BioscaraInsertEnv(backend="mock", fixture_pose=(*hole, 0.0))
    try:
        assert env.fixture_pose.tolist() == [*hole, 0.0]
    finally:
        env.close()


def test_ik_keeps_j1_and_j3_within_the_command_range(insert: BioscaraInsertEnv) -> None:
    u = insert
    q = u._ik(np.array([0.4, 0.0]), 1.0)
    assert kinematics.forward(np.array([q[0], 0.0, q[1]]))[:2] == pytest.approx([0.4, 0.0], abs=1e-12)
    assert q[1] > 0
    assert u._ik(np.array(ONLY_POSITIVE), -1.0) is None
    assert u._ik(np.array([0.7, 0.0]), 1.0) is None  # beyond the 0.614 m reach
    # Within planar reach, but j3 at ±2.7 rad, past its command range ±2.59672 (j4's is ±2.98069).
    for j3 in (2.7, -2.7):
        assert u._ik(kinematics.forward(np.array([0.0, 0.0, j3]))[:2], math.copysign(1.0, j3)) is None


# ----------------------------------------------------------- the observation
@pytest.mark.parametrize(
    ("q4", "error", "turn"),
    [
        (0.0, 0.3, 0.3),
        (0.0, -0.3, -0.3),
        (2.9, 0.3, 0.3 - math.pi / 2),  # j4 would pass 2.98069: the quarter turn back
        (-2.9, -0.3, -0.3 + math.pi / 2),
        (2.95, 0.75, 0.75 - math.pi / 2),  # a quarter turn back, not a half turn
        (-2.95, -0.75, -0.75 + math.pi / 2),
    ],
)
def test_the_wrist_turn_is_the_smallest_j4_can_make(
    insert: BioscaraInsertEnv, q4: float, error: float, turn: float
) -> None:
    u = insert
    u._q = np.array([0.2, 0.05, 0.4, q4])
    u.hole_yaw = 0.2 + 0.4 + q4 + error
    assert u.peg_yaw() == pytest.approx(0.2 + 0.4 + q4)
    assert u.wrist_turn() == pytest.approx(turn)


def test_the_observation_measures_the_peg_from_the_goal_and_the_top(insert: BioscaraInsertEnv) -> None:
    u = insert
    u.reset(seed=0)
    u._q = np.array([0.0, 0.07, 0.0, 0.0])
    u._tcp = kinematics.forward(u._q)  # TCP at z 0.075: the tip at 0.045, 10 mm above the top
    u.goal = np.array([0.3, 0.2, GOAL_Z])
    u.hole_yaw = 0.1
    obs = u._get_obs()
    tip = u._tcp - [0.0, 0.0, 0.03]
    s = u.OBS_SLICES
    np.testing.assert_allclose(obs["observation"][s["peg_tip"]], tip)
    np.testing.assert_allclose(obs["observation"][s["goal_from_tip"]], [0.3 - tip[0], 0.2 - tip[1], -0.025])
    assert obs["observation"][s["wrist_turn"]][0] == pytest.approx(0.1)
    assert obs["observation"][s["above_top"]][0] == pytest.approx(0.01)
    obs["desired_goal"][0] = 9.0  # a copy
    assert u.goal[0] == 0.3


def test_a_step_that_stalls_is_no_success_even_at_the_goal(insert: BioscaraInsertEnv) -> None:
    u = insert
    u.reset(seed=0)
    at_goal = {"achieved_goal": np.array([0.4, 0.0, GOAL_Z]), "desired_goal": np.array([0.4, 0.0, GOAL_Z])}
    assert u._get_info(at_goal)["is_success"] is True
    info = u._get_info(at_goal, True, "j2")
    assert info["is_success"] is False and info["stalled"] is True and info["stalled_joint"] == "j2"


def test_the_gripper_is_closed_on_the_peg_at_the_start(insert: BioscaraInsertEnv) -> None:
    u = insert
    u.reset(seed=0)
    assert u.arm.gripper_command == 0.04
    assert u.arm.gripper.get_position() == pytest.approx(0.04)


def test_the_scene_is_seen_from_the_fixture_with_the_peg_and_the_hole(insert: BioscaraInsertEnv) -> None:
    u = insert
    u.reset(seed=0)
    u._hole_xy, u.hole_yaw = np.array([0.4, -0.1]), 0.3
    scene = u._scene()
    assert scene.camera == "fixture" and scene.shown == ("peg",)
    ((pos, yaw),) = scene.mocaps.values()
    assert list(scene.mocaps) == ["fixture"] and yaw == 0.3
    assert pos.tolist() == [0.4, -0.1, 0.0]
    np.testing.assert_array_equal(scene.goal, u.goal)


@pytest.mark.parametrize("past", [10.0, -10.0])
def test_a_wrist_reading_far_past_its_range_still_gets_a_turn_inside_it(
    insert: BioscaraInsertEnv, past: float
) -> None:
    # Seen (a hostile test): with sensor noise of 10, "min() arg is an empty sequence".
    insert.hole_yaw = 0.3
    insert._q = np.array([0.0, 0.1, 0.0, past])
    turn = insert.wrist_turn()
    edge = 2.98069 if past > 0 else -2.98069  # j4's command range, the packaged configuration
    assert -2.98069 <= edge + turn <= 2.98069
    assert math.remainder(0.3 - past - turn, math.pi / 2) == pytest.approx(0.0, abs=1e-9)


def test_a_wrist_reading_just_past_its_range_turns_the_long_way_as_before(insert: BioscaraInsertEnv) -> None:
    # A reviewer's: clamping every reading changed this observation with no noise (j4 reads up
    # to 16 mrad past its range in simulation): -0.005 rad, which leaves j4 past the range.
    insert.hole_yaw = 2.98069 + 0.010 - 0.005  # the peg 5 mrad past square, j4 10 mrad past its top
    insert._q = np.array([0.0, 0.1, 0.0, 2.98069 + 0.010])
    assert insert.wrist_turn() == pytest.approx(-0.005 - math.pi / 2, abs=1e-9)

