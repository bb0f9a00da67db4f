"""The tasks' docstrings say what the code does: arguments, spaces, observation layout, limits.

Gymnasium's own docstrings drifted from their code (documented defaults that
were not the defaults); these tests read the tables and compare.
"""

from __future__ import annotations

import ast
import inspect
import re
from collections.abc import Callable

import gymnasium as gym
import numpy as np
import pytest

from bioscara_gym import kinematics
from bioscara_gym.envs import BioscaraEnv, BioscaraPickPlaceEnv, BioscaraReachEnv
from bioscara_gym.envs.actions import CARTESIAN_J3_LIMITS, WRIST_STEP

REACH = "Bioscara-Reach-v0"
PICK = "Bioscara-PickPlace-v1"
TASK_IDS = (REACH, PICK)
TASK_CLASSES = (BioscaraReachEnv, BioscaraPickPlaceEnv)

MakeEnv = Callable[..., gym.Env]


def _cells(line: str) -> list[str]:
    return [c.strip() for c in line.strip().strip("|").split("|")]


def _table_rows(doc: str, *columns: str) -> list[list[str]]:
    """The body rows (cells stripped) of the Markdown table in ``doc`` whose first columns are ``columns``."""
    lines = doc.splitlines()
    start = next(
        i
        for i, line in enumerate(lines)
        if line.strip().startswith("|") and _cells(line)[: len(columns)] == list(columns)
    )
    rows = []
    for line in lines[start + 2 :]:
        if not line.strip().startswith("|"):
            break
        rows.append(_cells(line))
    return rows


def _documented_kwargs(doc: str) -> dict[str, object]:
    """The ``| kwarg | default | meaning |`` rows of a docstring's Arguments table."""
    section = doc.split("## Arguments", 1)[1].split("##", 1)[0]
    rows = {}
    for line in section.splitlines():
        cells = [c.strip() for c in line.strip().strip("|").split("|")]
        if len(cells) < 3 or not cells[0] or set(cells[0]) <= {"-"} or cells[0] == "kwarg":
            continue
        names = [n.strip() for n in cells[0].split(",")]
        values = [v.strip() for v in cells[1].split(",")] if len(names) > 1 else [cells[1]]
        for name, value in zip(names, values, strict=True):
            rows[name] = ast.literal_eval(value)
    return rows


def _defaults(*functions: Callable[..., object]) -> dict[str, object]:
    params = {}
    for f in functions:
        params.update(inspect.signature(f).parameters)
    return {n: p.default for n, p in params.items() if n not in ("self", "args", "kwargs")}


def _slice(idx: str) -> slice:
    """``"9-11"`` -> ``slice(9, 12)``, ``"8"`` -> ``slice(8, 9)``."""
    first, _, last = idx.partition("-")
    return slice(int(first), int(last or first) + 1)


# ------------------------------------------------------------------ arguments


def test_documented_kwarg_defaults_match_the_code() -> None:
    documented = _documented_kwargs(BioscaraReachEnv.__doc__)
    assert documented == _defaults(BioscaraEnv.__init__, BioscaraReachEnv.__init__)


def test_pick_place_takes_reachs_kwargs_but_the_goal_ones() -> None:
    """PickPlace's docstring: "Reach's kwargs but ``goal_radius`` and ``goal_horizon_s``"."""
    assert "Reach's kwargs but ``goal_radius`` and ``goal_horizon_s``" in " ".join(
        BioscaraPickPlaceEnv.__doc__.split()
    )
    documented = _documented_kwargs(BioscaraReachEnv.__doc__)
    for goal_kwarg in ("goal_radius", "goal_horizon_s"):
        documented.pop(goal_kwarg)
        with pytest.raises(TypeError, match=goal_kwarg):
            BioscaraPickPlaceEnv(backend="mock", **{goal_kwarg: 0.1})
    assert documented == _defaults(BioscaraEnv.__init__)


# -------------------------------------------------------------- observations


@pytest.mark.parametrize("env_id", TASK_IDS)
def test_documented_observation_size_matches_the_space(make_env: MakeEnv, env_id: str) -> None:
    env = make_env(env_id, backend="mock")
    size = int(re.search(r"\| observation\s*\| \((\d+),\)", type(env.unwrapped).__doc__).group(1))
    assert env.observation_space["observation"].shape == (size,)


@pytest.mark.parametrize("cls", TASK_CLASSES)
def test_documented_observation_layout_is_obs_slices(cls: type[BioscaraEnv]) -> None:
    rows = _table_rows(cls.__doc__, "idx", "OBS_SLICES")
    documented = {name: _slice(idx) for idx, name, *_ in rows}
    assert list(documented.items()) == list(cls.OBS_SLICES.items())
    size = int(re.search(r"\| observation\s*\| \((\d+),\)", cls.__doc__).group(1))
    stops = [0, *(s.stop for s in documented.values())]
    assert [s.start for s in documented.values()] == stops[:-1], "the slices must tile the vector"
    assert stops[-1] == size


@pytest.mark.parametrize("env_id", TASK_IDS)
def test_obs_slices_hold_what_they_name(make_env: MakeEnv, env_id: str) -> None:
    env = make_env(env_id, backend="mock")
    u = env.unwrapped
    g = u.config.gripper
    lo = np.array([u.config.joint(n).min for n in u.joint_names])
    hi = np.array([u.config.joint(n).max for n in u.joint_names])
    obs, _ = env.reset(seed=0)
    env.action_space.seed(0)
    for step in range(3):
        if step:
            obs, *_ = env.step(env.action_space.sample())
        o, s = obs["observation"], u.OBS_SLICES
        measured = np.array([u.arm.joint_states[n].position for n in u.joint_names])
        np.testing.assert_allclose(lo + (o[s["joint_pos"]] + 1.0) / 2.0 * (hi - lo), measured, atol=1e-12)
        np.testing.assert_allclose(o[s["tcp"]], kinematics.forward(measured))
        width = u.arm.gripper.get_position()
        np.testing.assert_allclose(o[s["gripper"]], [2.0 * (width - g.min) / (g.max - g.min) - 1.0])
        if "block_pos" in s:
            np.testing.assert_array_equal(o[s["block_pos"]], obs["achieved_goal"])
            np.testing.assert_allclose(o[s["block_from_tcp"]], o[s["block_pos"]] - o[s["tcp"]])
            assert o[s["block_yaw"]][0] == pytest.approx(u.block_yaw)
        else:
            np.testing.assert_array_equal(o[s["tcp"]], obs["achieved_goal"])


@pytest.mark.parametrize("cls", TASK_CLASSES)
def test_documented_gripper_range_is_the_configs(cls: type[BioscaraEnv]) -> None:
    env = cls(backend="mock")
    try:
        ranges = re.findall(r"\[([\d.]+), ([\d.]+)\] m", cls.__doc__.split("## Observation space")[1])
        assert ranges, "no gripper range in the observation table"
        for low, high in ranges:
            assert (float(low), float(high)) == (env.config.gripper.min, env.config.gripper.max)
    finally:
        env.close()


# -------------------------------------------------------------------- actions


def test_documented_action_table_is_the_command_range_and_speeds() -> None:
    env = BioscaraReachEnv(backend="mock")
    try:
        rows = _table_rows(BioscaraReachEnv.__doc__, "idx", "joint")
        assert [r[1] for r in rows] == list(env.joint_names)
        for i, (idx, name, velocity, position) in enumerate(rows):
            assert int(idx) == i
            cfg = env.config.joint(name)
            unit = "m" if cfg.joint_type == "prismatic" else "rad"
            assert velocity == f"\N{MULTIPLICATION SIGN} {cfg.max_velocity} {unit}/s"
            low, high = re.fullmatch(rf"\[(\S+), (\S+)\] {unit}", position).groups()
            assert float(low) == pytest.approx(env.command_low[i], abs=5e-6)
            assert float(high) == pytest.approx(env.command_high[i], abs=5e-6)
    finally:
        env.close()


def test_numbers_the_docstrings_quote_are_the_codes() -> None:
    reach = " ".join(BioscaraReachEnv.__doc__.split())
    pick = " ".join(BioscaraPickPlaceEnv.__doc__.split())
    assert BioscaraReachEnv.cartesian_step == (0.01, 0.01, 0.01)
    assert "x and y by up to 1 cm and z by up to 1 cm per control step" in reach
    assert BioscaraPickPlaceEnv.cartesian_step == (0.02, 0.02, 0.01)
    assert "x and y move by up to 2 cm per step" in pick
    assert WRIST_STEP == 0.1 and "turns the wrist by up to 0.1 rad" in reach
    assert CARTESIAN_J3_LIMITS == (1.5, 4.0) and "capped at 1.5 rad/s and 4 rad/s^2" in reach
    assert BioscaraEnv.stall_penalty == -10.0 and "A stall adds -10" in reach


# ----------------------------------------------------------------- public API


def test_documented_public_attributes_exist(make_env: MakeEnv) -> None:
    u = make_env(REACH, backend="mock").unwrapped
    names = [r[0] for r in _table_rows(BioscaraEnv.__doc__, "name", "type") if r[0]]
    assert {"arm", "backend", "command_mode", "command_low", "command_high", "OBS_SLICES"} <= set(names)
    for name in names:
        assert hasattr(u, name), name
