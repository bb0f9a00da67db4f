"""Compile-and-step tests of the Bioscara MuJoCo model (bioscara_gym/assets/scene.xml).

Like mujoco_menagerie's model tests: the scene must compile and survive a second of
random controls without a single MuJoCo warning. The other tests pin down what the
rest of the project relies on: names, kinematics, the drive model's end-stop
behaviour and the gripper. Rendering is not tested here.
"""

from __future__ import annotations

from collections.abc import Iterator
from pathlib import Path

import mujoco
import numpy as np
import pytest

SCENE_XML = Path(__file__).resolve().parents[1] / "bioscara_gym" / "assets" / "scene.xml"

ARM_JOINTS = ("j1", "j2", "j3", "j4")
FINGER_JOINTS = ("finger_left", "finger_right")
REACH_M = 0.329476 + 0.285
"""Planar reach at full stretch (docs/model.md "Kinematics"), m."""


@pytest.fixture
def warnings_raised() -> Iterator[list[str]]:
    """Collects every message MuJoCo passes to mju_warning while the test runs."""
    messages: list[str] = []
    previous = mujoco.get_mju_user_warning()
    mujoco.set_mju_user_warning(messages.append)
    try:
        yield messages
    finally:
        mujoco.set_mju_user_warning(previous)


@pytest.fixture
def model(warnings_raised: list[str]) -> mujoco.MjModel:
    """The compiled scene; compiling must not warn."""
    compiled = mujoco.MjModel.from_xml_path(str(SCENE_XML))
    assert warnings_raised == [], f"compiling {SCENE_XML.name} warned: {warnings_raised}"
    return compiled


@pytest.fixture
def data(model: mujoco.MjModel) -> mujoco.MjData:
    """Data reset to the "home" keyframe."""
    new = mujoco.MjData(model)
    mujoco.mj_resetDataKeyframe(model, new, model.key("home").id)
    mujoco.mj_forward(model, new)
    return new


def _fired_warnings(data: mujoco.MjData) -> dict[str, int]:
    return {
        mujoco.mjtWarning(i).name: int(data.warning[i].number)
        for i in range(len(data.warning))
        if data.warning[i].number
    }


def _set_arm(model: mujoco.MjModel, data: mujoco.MjData, q: dict[str, float]) -> None:
    """Puts joints at q and their drives' set points (activations) on them."""
    for name, value in q.items():
        data.qpos[model.joint(name).qposadr[0]] = value
        act = model.actuator(name)
        if act.dyntype[0] == mujoco.mjtDyn.mjDYN_INTEGRATOR:
            data.act[model.actuator_actadr[act.id]] = value
    mujoco.mj_forward(model, data)


def test_scene_compiles_without_warnings(model: mujoco.MjModel) -> None:
    assert model.nu == 5
    assert model.opt.integrator == mujoco.mjtIntegrator.mjINT_IMPLICITFAST
    assert model.opt.gravity[2] < 0


@pytest.mark.parametrize(
    ("obj", "name"),
    [(mujoco.mjtObj.mjOBJ_JOINT, n) for n in ARM_JOINTS + FINGER_JOINTS]
    + [(mujoco.mjtObj.mjOBJ_ACTUATOR, n) for n in (*ARM_JOINTS, "gripper")]
    + [(mujoco.mjtObj.mjOBJ_SITE, n) for n in ("tcp", "target")]
    + [(mujoco.mjtObj.mjOBJ_BODY, n) for n in ("block", "obstacle", "target")]
    + [(mujoco.mjtObj.mjOBJ_GEOM, n) for n in ("block", "obstacle")]
    + [(mujoco.mjtObj.mjOBJ_CAMERA, "overview"), (mujoco.mjtObj.mjOBJ_KEY, "home")],
)
def test_named_element_exists(model: mujoco.MjModel, obj: mujoco.mjtObj, name: str) -> None:
    assert mujoco.mj_name2id(model, obj, name) >= 0, f"no {obj.name} named {name!r}"


def test_joint_limits_match_spec(model: mujoco.MjModel) -> None:
    spec = {
        "j1": (-3.04647, 3.04647),
        "j2": (-0.0016, 0.338),
        "j3": (-2.62672, 2.62672),
        "j4": (-3.01069, 3.01069),
    }
    for name, limits in spec.items():
        joint = model.joint(name)
        assert joint.limited[0], name
        np.testing.assert_allclose(joint.range, limits, err_msg=name)


def test_drive_set_point_range_is_wider_than_joint_range(model: mujoco.MjModel) -> None:
    for name in ARM_JOINTS:
        lo, hi = model.joint(name).range
        act_lo, act_hi = model.actuator(name).actrange
        assert act_lo < lo, name
        assert act_hi > hi, name


def test_tcp_at_full_reach_when_all_joints_zero(model: mujoco.MjModel, data: mujoco.MjData) -> None:
    _set_arm(model, data, dict.fromkeys(ARM_JOINTS, 0.0))
    j1_axis_xy = data.xanchor[model.joint("j1").id][:2]
    tcp = data.site("tcp").xpos
    np.testing.assert_allclose(tcp[:2] - j1_axis_xy, [REACH_M, 0.0], atol=1e-6)
    # Fingertips ~5 mm above the table top (z = 0) at j2 = 0, tool z pointing down.
    assert 0.003 < tcp[2] < 0.008
    tool_z = data.site("tcp").xmat.reshape(3, 3)[:, 2]
    np.testing.assert_allclose(tool_z, [0.0, 0.0, -1.0], atol=1e-9)


def test_home_keyframe_holds_still(model: mujoco.MjModel, data: mujoco.MjData) -> None:
    q0 = data.qpos.copy()
    while data.time < 1.0:
        mujoco.mj_step(model, data)
    np.testing.assert_allclose(data.qpos[:6], q0[:6], atol=1e-5)
    np.testing.assert_allclose(data.qpos[4] + data.qpos[5], 0.08, atol=1e-4)


def test_one_second_of_random_controls_raises_no_warning(
    model: mujoco.MjModel, data: mujoco.MjData, warnings_raised: list[str]
) -> None:
    rng = np.random.default_rng(0)
    lo, hi = model.actuator_ctrlrange.T
    hold_steps = round(0.05 / model.opt.timestep)  # a new command every 50 ms
    for step in range(round(1.0 / model.opt.timestep)):
        if step % hold_steps == 0:
            data.ctrl[:] = rng.uniform(lo, hi)
        mujoco.mj_step(model, data)
        assert np.all(np.isfinite(data.qpos)), f"NaN at t={data.time:.3f}"
    assert _fired_warnings(data) == {}
    assert warnings_raised == []
    assert np.all(np.isfinite(data.qvel))
    assert np.all(np.isfinite(data.act))
    # End stops are stiff: allow 0.02 rad / 1 mm of transient overshoot.
    for name in ARM_JOINTS + FINGER_JOINTS:
        joint = model.joint(name)
        tol = 0.02 if joint.type[0] == mujoco.mjtJoint.mjJNT_HINGE else 1e-3
        q = data.qpos[joint.qposadr[0]]
        assert joint.range[0] - tol <= q <= joint.range[1] + tol, f"{name}: q={q}"


def test_j1_pushed_into_its_limit_stops_there_while_its_set_point_runs_away(
    model: mujoco.MjModel, data: mujoco.MjData, warnings_raised: list[str]
) -> None:
    limit = model.joint("j1").range[1]
    qadr = model.joint("j1").qposadr[0]
    act_id = model.actuator("j1").id
    actadr = model.actuator_actadr[act_id]
    _set_arm(model, data, {"j1": 1.0})
    steps_per_second = round(1.0 / model.opt.timestep)
    lag = {}
    max_penetration = -np.inf
    for step in range(1, 8 * steps_per_second + 1):
        data.ctrl[act_id] = 0.5
        mujoco.mj_step(model, data)
        q = data.qpos[qadr]
        max_penetration = max(max_penetration, q - limit)
        if step % steps_per_second == 0:
            lag[step // steps_per_second] = data.act[actadr] - q
    assert np.rad2deg(max_penetration) < 0.2
    assert q > limit - 1e-3, "j1 did not reach its end stop"
    # Reaches the stop after ~4.1 s; from then on the set point keeps moving at 0.5 rad/s.
    assert lag[6] < lag[7] < lag[8]
    assert lag[8] == pytest.approx(0.5 * 8.0 - (limit - 1.0), abs=0.01)
    assert abs(data.actuator_force[act_id]) == pytest.approx(17.5)
    assert _fired_warnings(data) == {}
    assert warnings_raised == []


def test_gripper_ctrl_is_opening_width(model: mujoco.MjModel, data: mujoco.MjData) -> None:
    for width in (0.04, 0.12, 0.08):
        data.ctrl[model.actuator("gripper").id] = width
        for _ in range(round(0.3 / model.opt.timestep)):
            mujoco.mj_step(model, data)
        left = data.qpos[model.joint("finger_left").qposadr[0]]
        right = data.qpos[model.joint("finger_right").qposadr[0]]
        assert left + right == pytest.approx(width, abs=1e-3)
        assert left == pytest.approx(right, abs=1e-4)


def _planar_ik(x: float, y: float, z_tcp: float) -> np.ndarray:
    """Elbow-up joint set points putting the tcp at (x, y, z_tcp), tool yaw 0."""
    l1, l2 = 0.329476, 0.285
    q3 = np.arccos(np.clip((x * x + y * y - l1 * l1 - l2 * l2) / (2 * l1 * l2), -1.0, 1.0))
    q1 = np.arctan2(y, x) - np.arctan2(l2 * np.sin(q3), l1 + l2 * np.cos(q3))
    return np.array([q1, z_tcp - 0.005, q3, -q1 - q3])


def test_gripper_lifts_the_block(model: mujoco.MjModel, data: mujoco.MjData) -> None:
    block = data.body("block").xpos.copy()
    max_vel = np.array([1.0, 0.03, 5.0, 10.0])

    def move(z_tcp: float, width: float, seconds: float) -> None:
        goal = _planar_ik(block[0], block[1], z_tcp)
        for _ in range(round(seconds / model.opt.timestep)):
            data.ctrl[:4] = np.clip(5.0 * (goal - data.act[:4]), -max_vel, max_vel)
            data.ctrl[4] = width
            mujoco.mj_step(model, data)

    move(0.06, 0.10, 3.0)  # above the block, open
    move(0.008, 0.10, 2.5)  # down around it
    move(0.008, 0.04, 0.5)  # close: 10 N squeeze
    held_at = data.body("block").xpos - data.site("tcp").xpos
    assert abs(held_at[2]) < 0.015, "the fingers did not reach around the block"
    move(0.10, 0.04, 3.5)  # lift
    assert data.body("block").xpos[2] > 0.09
    slip = data.body("block").xpos - data.site("tcp").xpos - held_at
    np.testing.assert_allclose(slip, 0.0, atol=1e-3)
