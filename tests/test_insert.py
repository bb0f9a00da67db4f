"""Bioscara-Insert: the peg, the fixture, the jam the firmware feels, the expert, the spec's numbers.

Expected values come from the task's definition (a 20 mm peg, a 21 mm hole,
the fixture's 35 mm top, the goal 15 mm down the hole, a 2 mm success
radius), from geometry (a square turned by theta is (cos + sin) theta wider)
and from the firmware's rule as configured (the lift's sensitivity), never
from the env's own formulas.
"""

from __future__ import annotations

import math
import re
from collections.abc import Callable
from pathlib import Path

import gymnasium as gym
import numpy as np
import pytest

import bioscara_gym  # noqa: F401 - registers the tasks
from bioscara_gym import TASKS, kinematics
from bioscara_gym.assets import scene_path
from bioscara_gym.envs import BioscaraEnv, BioscaraInsertEnv
from bioscara_gym.envs.insert import yaw_error
from bioscara_gym.experts import InsertExpert, expert_for, observation_expert_for
from bioscara_gym.hardware.registers import FLAG_STALL
from bioscara_gym.training.evaluate import run_episodes

INSERT = "Bioscara-Insert-v0"
#: Where the goal is: the fixture's top (35 mm) less the 15 mm insertion depth.
GOAL_Z = 0.020
#: The fixture's top, and the tip's height when it rests on it.
TOP_Z = 0.035
#: Descend, nothing else (cartesian action).
DOWN = np.array([0.0, 0.0, -1.0, 0.0], dtype=np.float32)

MakeEnv = Callable[..., gym.Env]


def _tip_z(env: gym.Env) -> float:
    """The peg tip's true height (MuJoCo's j2), m: the TCP 30 mm lower."""
    return float(env.unwrapped.sim.joint_positions()[1]) + kinematics.TCP_Z0 - 0.03


def _move_fixture(env: gym.Env, dx: float = 0.0, dyaw: float = 0.0) -> None:
    """Move the fixture after the reset, unseen by the policy: the hole off by ``dx`` (m), ``dyaw`` (rad)."""
    u = env.unwrapped
    m, d = u.sim.model, u.sim.data
    mocap = m.body("fixture").mocapid[0]
    d.mocap_pos[mocap, 0] += dx
    yaw = u.hole_yaw + dyaw
    d.mocap_quat[mocap] = (math.cos(yaw / 2), 0.0, 0.0, math.sin(yaw / 2))


def _run(env: gym.Env, policy: Callable[[dict[str, np.ndarray]], np.ndarray], obs: dict) -> tuple:
    """Play ``policy`` to the episode's end: the last (obs, reward, terminated, info) and the length."""
    steps = 0
    while True:
        obs, reward, terminated, truncated, info = env.step(policy(obs))
        steps += 1
        if terminated or truncated:
            return obs, reward, terminated, info, steps


# ---------------------------------------------------------------- registration
def test_insert_is_registered_with_its_experts_and_dagger_by_default(make_env: MakeEnv) -> None:
    env = make_env(INSERT)
    assert isinstance(env.unwrapped, BioscaraInsertEnv)
    assert env.spec.max_episode_steps == 150
    assert TASKS[INSERT].default_method == "dagger"
    assert isinstance(expert_for(env.unwrapped), InsertExpert)
    assert isinstance(observation_expert_for(env.unwrapped), InsertExpert)


# -------------------------------------------------------------- the arm's setup
def test_the_lift_runs_at_6_mm_s_with_sensitivity_4_in_the_firmware(make_env: MakeEnv) -> None:
    env = make_env(INSERT)
    env.reset(seed=0)
    j2 = env.unwrapped.config.joint("j2")
    assert (j2.max_velocity, j2.stall_threshold) == (0.006, 4)
    core = env.unwrapped.sim.cores["j2"]
    assert core.stallguard and core.stall_sensitivity == 4
    # SETMAXVELOCITY in motor deg/s: 6 mm/s at 4 mm a motor turn is 1.5 turns/s.
    assert core.max_velocity == pytest.approx(540.0)
    # The other joints keep the arm's own sensitivity (6).
    assert env.unwrapped.sim.cores["j1"].stall_sensitivity == 6


@pytest.mark.parametrize("env_id", sorted(set(TASKS) - {INSERT}))
def test_the_other_tasks_do_not_see_the_peg_or_the_fixture(make_env: MakeEnv, env_id: str) -> None:
    other = make_env(env_id).unwrapped
    other.reset(seed=0)
    m = other.sim.model
    assert m.geom_rgba[m.geom("peg").id, 3] == 0.0
    assert m.body_mass[m.body("tool").id] == pytest.approx(0.15)  # the peg weighs nothing there
    assert other.sim.data.mocap_pos[m.body("fixture").mocapid[0], 2] < -2.0


def test_insert_shows_the_peg(make_env: MakeEnv) -> None:
    insert = make_env(INSERT).unwrapped
    assert insert.sim.model.geom_rgba[insert.sim.model.geom("peg").id, 3] == 1.0


def test_cartesian_targets_lead_by_the_braking_distance_as_pickplaces(make_env: MakeEnv) -> None:
    # BioscaraEnv's default is off (Reach); the expert and the learner here brake themselves.
    assert make_env(INSERT, backend="mock").unwrapped.cartesian_lead is True


def test_the_peg_touches_only_the_fixture() -> None:
    import mujoco

    m = mujoco.MjModel.from_xml_path(str(scene_path()))
    peg = m.geom("peg").id
    touching = sorted(
        m.geom(g).name
        for g in range(m.ngeom)
        if g != peg
        and (m.geom_contype[g] & m.geom_conaffinity[peg] or m.geom_contype[peg] & m.geom_conaffinity[g])
    )
    walls = ["fixture_x+", "fixture_x-", "fixture_y+", "fixture_y-"]
    assert touching == ["fixture_floor", "fixture_table", *walls]


# ----------------------------------------------------------------- spaces, goal
def test_yaw_error_is_the_nearest_quarter_turn() -> None:
    assert yaw_error(0.0, 0.02) == pytest.approx(-0.02)
    assert yaw_error(0.0, math.pi / 2 + 0.02) == pytest.approx(-0.02)
    assert yaw_error(1.0, 0.0) == pytest.approx(1.0 - math.pi / 2)  # -0.5708: a quarter turn less
    assert yaw_error(0.0, 0.8) == pytest.approx(math.pi / 2 - 0.8)  # 0.7708
    assert yaw_error(0.0, -3 * math.pi) == pytest.approx(0.0, abs=1e-12)


@pytest.mark.parametrize("backend", ["sim", "mock"])
def test_observation_holds_what_its_names_say(make_env: MakeEnv, backend: str) -> None:
    env = make_env(INSERT, backend=backend)
    u = env.unwrapped
    obs, _ = env.reset(seed=1)
    env.action_space.seed(1)
    for step in range(3):
        if step:
            obs, *_ = env.step(env.action_space.sample())
        o, s = obs["observation"], u.OBS_SLICES
        assert o.shape == (20,)
        q = np.array([u.arm.joint_states[n].position for n in u.joint_names])
        tcp = kinematics.forward(q)
        np.testing.assert_allclose(o[s["peg_tip"]], tcp - [0.0, 0.0, 0.03], atol=1e-12)
        np.testing.assert_array_equal(obs["achieved_goal"], o[s["peg_tip"]])
        np.testing.assert_allclose(o[s["goal_from_tip"]], obs["desired_goal"] - o[s["peg_tip"]], atol=1e-12)
        assert o[s["above_top"]][0] == pytest.approx(tcp[2] - 0.03 - TOP_Z)
        turn = o[s["wrist_turn"]][0]
        misfit = u.hole_yaw - (q[0] + q[2] + q[3]) - turn  # whole quarter turns: the peg is square
        assert math.remainder(misfit, math.pi / 2) == pytest.approx(0.0, abs=1e-9)
        assert u.command_low[3] <= q[3] + turn <= u.command_high[3]


def test_the_wrist_turns_the_short_way_unless_j4_would_pass_its_range(make_env: MakeEnv) -> None:
    env = make_env(INSERT)
    u = env.unwrapped
    s = u.OBS_SLICES["wrist_turn"]
    short = long = 0
    for seed in range(60):
        obs, _ = env.reset(seed=seed)
        q4, turn = u.arm.joint_states["j4"].position, obs["observation"][s][0]
        err = yaw_error(u.hole_yaw, u.peg_yaw())
        if u.command_low[3] <= q4 + err <= u.command_high[3]:
            assert turn == pytest.approx(err)  # at most an eighth of a turn
            assert abs(turn) <= math.pi / 4
            short += 1
        else:  # the quarter turn back
            assert turn == pytest.approx(err - math.copysign(math.pi / 2, err))
            assert math.pi / 4 <= abs(turn) <= 3 * math.pi / 4
            long += 1
    assert short >= 40 and long >= 1


def test_goal_and_start_are_drawn_as_documented(make_env: MakeEnv) -> None:
    env = make_env(INSERT)
    u = env.unwrapped
    fixture = u.sim.model.body("fixture").mocapid[0]
    for seed in range(20):
        obs, _ = env.reset(seed=seed)
        goal, tip = obs["desired_goal"], obs["achieved_goal"]
        assert goal[2] == pytest.approx(GOAL_Z)
        assert 0.3 - 1e-9 <= math.hypot(goal[0], goal[1]) <= 0.55 + 1e-9
        assert math.hypot(*(tip[:2] - goal[:2])) <= 0.03 + 1e-6
        assert TOP_Z + 0.003 - 1e-6 <= tip[2] <= TOP_Z + 0.008 + 1e-6
        np.testing.assert_allclose(u.sim.data.mocap_pos[fixture], [goal[0], goal[1], 0.0])
        assert 0.0 <= u.hole_yaw < math.pi / 2
        assert u.arm.gripper_command == pytest.approx(0.04)  # closed on the peg


def test_a_seed_gives_the_same_episode(make_env: MakeEnv) -> None:
    a, b = make_env(INSERT), make_env(INSERT)
    oa, _ = a.reset(seed=5)
    ob, _ = b.reset(seed=5)
    np.testing.assert_array_equal(oa["observation"], ob["observation"])
    np.testing.assert_array_equal(oa["desired_goal"], ob["desired_goal"])
    oc, _ = a.reset(seed=6)
    assert not np.allclose(oc["desired_goal"], oa["desired_goal"])


def test_a_bolted_fixture_stays_where_it_is(make_env: MakeEnv) -> None:
    env = make_env(INSERT, fixture_pose=(0.45, -0.1, 0.3))
    for seed in range(3):
        obs, _ = env.reset(seed=seed)
        np.testing.assert_allclose(obs["desired_goal"], [0.45, -0.1, GOAL_Z])
        assert env.unwrapped.hole_yaw == 0.3


# ------------------------------------------------------------- reward, success
def test_reward_is_minus_the_tip_goal_distance_and_success_is_2_mm(make_env: MakeEnv) -> None:
    u = make_env(INSERT).unwrapped
    goal = np.array([0.4, 0.1, GOAL_Z])
    tips = np.array([[0.4, 0.1, 0.0215], [0.4, 0.1, 0.0225], [0.4, 0.1, TOP_Z]])
    np.testing.assert_allclose(u.compute_reward(tips, goal, {}), [-0.0015, -0.0025, -0.015])
    assert list(u._is_success(tips, goal)) == [True, False, False]
    sparse = make_env(INSERT, reward_type="sparse").unwrapped
    np.testing.assert_array_equal(sparse.compute_reward(tips, goal, {}), [0.0, -1.0, -1.0])


def test_the_expert_inserts_without_a_stall(make_env: MakeEnv) -> None:
    env = make_env(INSERT)
    expert = InsertExpert(env.unwrapped)
    obs, _ = env.reset(seed=0)
    obs, _, terminated, info, _ = _run(env, expert, obs)
    assert info["is_success"] and not terminated and not info["stalled"]
    assert _tip_z(env) == pytest.approx(GOAL_Z, abs=0.001)  # down the hole, not on the fixture


def test_expert_succeeds_in_at_least_95_percent_of_40_episodes() -> None:
    env = gym.make(INSERT)
    try:
        stats = run_episodes(env, InsertExpert(env.unwrapped), 40, seed=0)
    finally:
        env.close()
    assert stats.success_rate >= 0.95
    assert stats.stalls == 0


@pytest.mark.parametrize("mode", ["velocity", "position"])
def test_expert_succeeds_in_the_other_control_modes(mode: str) -> None:
    env = gym.make(INSERT, control_mode=mode)
    try:
        assert run_episodes(env, InsertExpert(env.unwrapped), 6, seed=0).success_rate >= 5 / 6
    finally:
        env.close()


def test_expert_acts_on_the_observation_alone(make_env: MakeEnv) -> None:
    env = make_env(INSERT)
    expert = InsertExpert(env.unwrapped)
    obs, _ = env.reset(seed=2)
    for _ in range(20):
        obs, *_ = env.step(expert(obs))
    first = expert(obs)
    fresh = InsertExpert(env.unwrapped)
    np.testing.assert_array_equal(fresh(obs), first)


# ------------------------------------------- the jam, as the firmware sees it
def test_landing_on_the_fixture_trips_the_firmwares_stall_and_fails(make_env: MakeEnv) -> None:
    env = make_env(INSERT)
    obs, _ = env.reset(seed=0)
    _move_fixture(env, dx=0.005)
    obs, reward, terminated, info, steps = _run(env, lambda o: DOWN, obs)
    assert terminated and info["stalled"] and info["stalled_joint"] == "j2"
    assert not info["is_success"]
    assert reward <= -10.0
    assert _tip_z(env) == pytest.approx(TOP_Z, abs=0.0005)  # on the fixture's top
    assert env.unwrapped.sim.cores["j2"].flags & FLAG_STALL  # the firmware's own flag
    # 3-8 mm to fall at 6 mm/s, then at most 0.3 s of pressing.
    assert steps * 0.04 <= 0.008 / 0.006 + 0.1 + 0.3


def test_at_the_arms_own_sensitivity_the_firmware_does_not_notice_the_jam(make_env: MakeEnv) -> None:
    """j2's configured 12 (threshold 120) sees no jam at 6 mm/s: the env does not make one up."""
    env = make_env(INSERT, lift_sensitivity=12)
    obs, _ = env.reset(seed=0)
    _move_fixture(env, dx=0.005)
    obs, _, terminated, info, steps = _run(env, lambda o: DOWN, obs)
    assert not terminated and not info["stalled"] and steps == 150
    assert _tip_z(env) == pytest.approx(TOP_Z, abs=0.0005)  # pressed on the fixture all along


@pytest.mark.parametrize(
    ("dx", "dyaw", "jams"),
    [
        (0.0008, 0.0, True),  # 0.8 mm off: beyond the 0.5 mm a side
        (0.0003, 0.0, False),  # 0.3 mm off: within it
        (0.0, 0.07, True),  # 4.0 degrees: 20 (cos + sin - 1) = 1.39 mm wider than the peg
        (0.0, 0.03, False),  # 1.7 degrees: 0.59 mm wider, under the 1 mm clearance
    ],
)
def test_a_misaligned_peg_jams_and_an_aligned_one_slides_in(
    make_env: MakeEnv, dx: float, dyaw: float, jams: bool
) -> None:
    env = make_env(INSERT)
    expert = InsertExpert(env.unwrapped)
    obs, _ = env.reset(seed=3)
    _move_fixture(env, dx=dx, dyaw=dyaw)  # the expert aligns with where the hole was
    obs, _, terminated, info, _ = _run(env, expert, obs)
    if jams:
        assert terminated and info["stalled_joint"] == "j2" and not info["is_success"]
        assert _tip_z(env) == pytest.approx(TOP_Z, abs=0.0005)
    else:
        assert not terminated and not info["stalled"]
        assert _tip_z(env) == pytest.approx(GOAL_Z, abs=0.001)


def test_a_jam_stalls_through_the_real_driver_on_the_emulated_bus(make_env: MakeEnv) -> None:
    env = make_env(INSERT, backend="emulated", max_episode_steps=60)
    obs, _ = env.reset(seed=0)
    _move_fixture(env, dx=0.005)
    obs, reward, terminated, info, _ = _run(env, lambda o: DOWN, obs)
    assert terminated and info["stalled_joint"] == "j2" and reward <= -10.0


def test_the_episode_after_a_stall_starts_afresh(make_env: MakeEnv) -> None:
    env = make_env(INSERT)
    obs, _ = env.reset(seed=0)
    _move_fixture(env, dx=0.005)
    _run(env, lambda o: DOWN, obs)
    obs, _ = env.reset(seed=0)
    obs, _, terminated, info, _ = _run(env, InsertExpert(env.unwrapped), obs)
    assert info["is_success"] and not terminated


# ---------------------------------------------------------------- bad input
@pytest.mark.parametrize(
    ("kwargs", "message"),
    [
        ({"lift_speed": 0.0}, "lift_speed 0.0 must be a speed > 0"),
        ({"lift_speed": "fast"}, "lift_speed 'fast' must be a speed > 0"),
        ({"lift_speed": 0.05}, "lift_speed 0.05 m/s is above j2's max velocity 0.03 m/s"),
        ({"lift_sensitivity": 300}, "stall_threshold"),
        ({"fixture_pose": (2.0, 0.0, 0.0)}, "cannot reach the hole"),
        ({"fixture_pose": (0.4, 0.0)}, "must be \\(x m, y m, yaw rad\\)"),
        ({"fixture_pose": (0.4, math.nan, 0.0)}, "must be finite"),
    ],
)
def test_bad_arguments_are_refused_in_one_line(kwargs: dict, message: str) -> None:
    with pytest.raises(ValueError, match=message) as caught:
        BioscaraInsertEnv(backend="mock", **kwargs)
    assert "\n" not in str(caught.value)


# ------------------------------------------------------------------ the spec
def test_documented_kwarg_defaults_match_the_code() -> None:
    from test_envs_docs import _defaults, _documented_kwargs

    documented = _documented_kwargs(BioscaraInsertEnv.__doc__)
    assert documented == _defaults(BioscaraEnv.__init__, BioscaraInsertEnv.__init__)


def test_documented_observation_layout_is_obs_slices() -> None:
    from test_envs_docs import _slice, _table_rows

    doc = BioscaraInsertEnv.__doc__
    rows = _table_rows(doc, "idx", "OBS_SLICES")
    assert {name: _slice(idx) for idx, name, *_ in rows} == dict(BioscaraInsertEnv.OBS_SLICES)
    assert "| observation   | (20,)" in doc


def test_numbers_the_docstring_quotes_are_the_codes() -> None:
    doc = " ".join(BioscaraInsertEnv.__doc__.split())
    assert BioscaraInsertEnv.cartesian_step == (0.005, 0.005, 0.01)
    assert "x and y move by up to 5 mm per step" in doc
    assert "``lift_speed`` (6 mm/s" in doc and "(4: threshold 40 microsteps)" in doc
    assert "``truncated`` after ``max_episode_steps`` (150, 6 s at 25 Hz)" in doc


# ------------------------------------------------------------------ learning
#: A run small enough for the default suite: mock backend, a 16x16 network, one-episode iterations.
TINY_DAGGER = {
    "n_timesteps": 600,
    "env_kwargs": {"backend": "mock"},
    "net_arch": [16, 16],
    "demo_episodes": 2,
    "episodes_per_iteration": 1,
    "bc_steps_first": 20,
    "bc_steps": 10,
    "batch_size": 32,
    "eval_episodes": 1,
}


def test_insert_trains_with_dagger_by_default_on_its_extractor(tmp_path: Path) -> None:
    import yaml

    from bioscara_gym.training.algos import load_model
    from bioscara_gym.training.dagger_config import load_dagger_config
    from bioscara_gym.training.features import InsertExtractor
    from bioscara_gym.training.hyperparams import default_config_path
    from bioscara_gym.training.train import TrainArgs, choose_method, train

    packaged = load_dagger_config(default_config_path("dagger"), INSERT)
    assert packaged.env_kwargs == {"control_mode": "cartesian"} and packaged.target_success == 0.93
    assert choose_method(TrainArgs(env="Bioscara-Insert", out=tmp_path), INSERT).name == "dagger"
    config = tmp_path / "dagger.yaml"
    config.write_text(yaml.safe_dump({INSERT: TINY_DAGGER}), encoding="utf-8")
    run = TrainArgs(env="Bioscara-Insert", algo="dagger", config=config, out=tmp_path / "r", progress=False)
    result = train(run)
    model, metadata = load_model(result.model_path)
    assert metadata["method"] == "dagger" and metadata["env_id"] == INSERT
    assert isinstance(model.actor.features_extractor, InsertExtractor)


def test_extractor_sees_the_alignment_in_millimetres_and_hundredths_of_a_radian(make_env: MakeEnv) -> None:
    import torch as th

    from bioscara_gym.training.features import InsertExtractor

    env = make_env(INSERT, backend="mock")
    ext = InsertExtractor(env.observation_space)
    obs, _ = env.reset(seed=0)
    obs["observation"][env.unwrapped.OBS_SLICES["goal_from_tip"]] = [0.0004, -0.02, -0.015]
    obs["observation"][env.unwrapped.OBS_SLICES["wrist_turn"]] = [0.005]
    obs["observation"][env.unwrapped.OBS_SLICES["above_top"]] = [0.0015]
    features = ext({k: th.as_tensor(v[None], dtype=th.float32) for k, v in obs.items()})
    assert features.shape == (1, 20 + 3 + 4)
    # x 0.4 mm, y 20 mm clipped at 3, 1.5 mm above the top, 0.005 rad: in 1 mm and 0.01 rad.
    np.testing.assert_allclose(features[0, -4:].numpy(), [0.4, -3.0, 1.5, 0.5], rtol=1e-5)
    with pytest.raises(ValueError, match=re.escape(f"{INSERT}'s is (20,)")):
        InsertExtractor(make_env("Bioscara-Reach-v0", backend="mock").observation_space)
    with pytest.raises(ValueError, match="must be > 0"):
        InsertExtractor(env.observation_space, fine_m=0.0)


def test_the_sac_her_baseline_config_loads() -> None:
    import yaml

    from bioscara_gym.training.hyperparams import default_config_path

    entry = yaml.safe_load(default_config_path("sac").read_text(encoding="utf-8"))[INSERT]
    assert entry["replay_buffer_class"] == "HerReplayBuffer"
    assert entry["env_kwargs"] == {"control_mode": "cartesian", "reward_type": "log"}


# ------------------------------------------------------------------- pictures
@pytest.mark.parametrize("backend", ["sim", "mock"])
def test_pictures_are_taken_from_the_fixtures_camera(make_env: MakeEnv, backend: str) -> None:
    """The fixture's green fills a tenth of the lower middle (from the overview it is a few pixels)."""
    env = make_env(INSERT, backend=backend, render_mode="rgb_array", width=160, height=120)
    env.reset(seed=4)
    image = env.render().astype(int)
    r, g, b = image[..., 0], image[..., 1], image[..., 2]
    green = (g > r + 40) & (g > b + 40)
    assert green[60:, 40:120].mean() > 0.1
