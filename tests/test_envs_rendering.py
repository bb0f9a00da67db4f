"""Pictures of the arm, and MuJoCo only where needed: envs without MuJoCo, ``MUJOCO_GL``, displays.

Headless rendering needs ``MUJOCO_GL=egl`` before mujoco is imported; ``conftest.py``
sets it for the suite, and an env with a ``render_mode`` sets it itself.
"""

from __future__ import annotations

import os
import warnings
from collections.abc import Callable
from pathlib import Path

import gymnasium as gym
import imageio.v3 as iio
import numpy as np
import pytest
from rigs import run_blocked

from bioscara_gym.envs import BioscaraReachEnv, rendering

REACH = "Bioscara-Reach-v0"
PICK = "Bioscara-PickPlace-v1"
ROOT = Path(__file__).resolve().parents[1]

MakeEnv = Callable[..., gym.Env]


def _random_actions(env: gym.Env, n: int, seed: int = 0, scale: float = 1.0) -> list[np.ndarray]:
    rng = np.random.default_rng(seed)
    shape = env.action_space.shape
    return [(scale * rng.uniform(-1.0, 1.0, shape)).astype(np.float32) for _ in range(n)]


# ------------------------------------------------------------------- pictures


@pytest.mark.parametrize("backend", ["sim", "mock"])
def test_render_rgb_array_shows_the_arm(make_env: MakeEnv, backend: str) -> None:
    env = make_env(PICK, backend=backend, render_mode="rgb_array", width=160, height=120)
    env.reset(seed=0)
    first = env.render()
    assert first.shape == (120, 160, 3)
    assert first.dtype == np.uint8
    assert first.std() > 20.0
    env.reset(seed=1)  # another pose: the drawn arm (sim state or mirrored joints) moves
    second = env.render()
    assert np.abs(first.astype(int) - second.astype(int)).mean() > 1.0


def test_render_writes_a_viewable_png(make_env: MakeEnv, tmp_path: Path) -> None:
    env = make_env(PICK, render_mode="rgb_array")
    env.reset(seed=0)
    for action in _random_actions(env, 5, scale=0.5):
        env.step(action)
    image = env.render()
    assert image.shape == (480, 480, 3)
    iio.imwrite(tmp_path / "bioscara_env.png", image)
    np.testing.assert_array_equal(iio.imread(tmp_path / "bioscara_env.png"), image)


def test_render_without_render_mode_warns_and_returns_none(make_env: MakeEnv) -> None:
    env = make_env(REACH, backend="mock")
    env.reset(seed=0)
    with pytest.warns(UserWarning, match="render_mode"):
        assert env.unwrapped.render() is None


def test_mirror_and_simulation_draw_the_same_scene(make_env: MakeEnv) -> None:
    """On mock the measured joints and the kinematic block are drawn where sim would draw them."""
    images = []
    for backend in ("sim", "mock"):
        env = make_env(PICK, backend=backend, render_mode="rgb_array", width=160, height=120)
        env.reset(seed=2)
        images.append(env.render().astype(int))
    assert np.abs(images[0] - images[1]).mean() < 2.0


# ------------------------------------------------------------ displays and GL


def test_unknown_render_mode_is_refused() -> None:
    with pytest.raises(ValueError, match="render_mode 'ansi' must be one of"):
        BioscaraReachEnv(backend="mock", render_mode="ansi")


def test_human_without_a_display_is_refused_at_construction(monkeypatch: pytest.MonkeyPatch) -> None:
    monkeypatch.delenv("DISPLAY", raising=False)
    monkeypatch.delenv("WAYLAND_DISPLAY", raising=False)
    with pytest.raises(ValueError, match="needs a display") as caught:
        gym.make(REACH, backend="mock", render_mode="human")
    message = str(caught.value)
    assert "\n" not in message
    assert "rgb_array" in message and "headless" in message


@pytest.mark.parametrize(
    ("environ", "expected"),
    [
        ({}, "egl"),  # headless: EGL
        ({"DISPLAY": ":0"}, None),  # a display: MuJoCo's default
        ({"MUJOCO_GL": "osmesa"}, "osmesa"),  # the user's choice stands
        ({"MUJOCO_GL": "glfw", "DISPLAY": ":0"}, "glfw"),
    ],
)
def test_prepare_sets_mujoco_gl_only_if_unset_and_headless(
    monkeypatch: pytest.MonkeyPatch, environ: dict[str, str], expected: str | None
) -> None:
    for name in ("DISPLAY", "WAYLAND_DISPLAY", "MUJOCO_GL"):
        monkeypatch.delenv(name, raising=False)
    for name, value in environ.items():
        monkeypatch.setenv(name, value)
    with warnings.catch_warnings():
        warnings.simplefilter("ignore")  # this process has imported MuJoCo: too late, it warns
        rendering.prepare("rgb_array")
    assert os.environ.get("MUJOCO_GL") == expected


def _run(code: str, blocked: tuple[str, ...] = (), env: dict[str, str] | None = None) -> str:
    """Run ``code`` in a fresh interpreter in which importing any of ``blocked`` fails; its stdout."""
    result = run_blocked(code, blocked, env)
    assert result.returncode == 0, result.stderr
    return result.stdout.strip()


def test_envs_run_on_mock_without_mujoco() -> None:
    """``bioscara deploy --backend mock`` on a robot computer: no MuJoCo installed."""
    out = _run(
        """
        import gymnasium as gym
        import numpy as np
        import bioscara_gym
        from bioscara_gym import envs, experts
        from bioscara_gym.envs import actions, base, pick_place, randomization, reach, rendering

        for env_id in ("Bioscara-Reach-v0", "Bioscara-PickPlace-v1"):
            env = gym.make(env_id, backend="mock")
            expert = experts.expert_for(env.unwrapped)
            obs, _ = env.reset(seed=0)
            for _ in range(5):
                obs, *_ = env.step(expert(obs))
            env.unwrapped.bring_up()
            env.close()
        print("mujoco" in sys.modules)
        """,
        blocked=("mujoco",),
    )
    assert out == "False"


def test_an_env_sets_mujoco_gl_before_its_backend_imports_mujoco() -> None:
    out = _run(
        """
        import os
        import gymnasium as gym
        import bioscara_gym

        assert "MUJOCO_GL" not in os.environ and "mujoco" not in sys.modules
        env = gym.make("Bioscara-Reach-v0", backend="sim", render_mode="rgb_array", width=32, height=24)
        env.reset(seed=0)
        print(os.environ.get("MUJOCO_GL"), env.render().shape)
        """,
        env={"PATH": "/usr/bin:/bin"},  # no MUJOCO_GL, no DISPLAY
    )
    assert out == "egl (24, 32, 3)"


def test_an_env_without_render_mode_leaves_mujoco_gl_alone() -> None:
    out = _run(
        """
        import os
        import warnings
        import gymnasium as gym
        import bioscara_gym

        env = gym.make("Bioscara-Reach-v0", backend="sim")
        print(os.environ.get("MUJOCO_GL"))
        with warnings.catch_warnings(record=True) as caught:
            warnings.simplefilter("always")
            gym.make("Bioscara-Reach-v0", backend="sim", render_mode="rgb_array")
        print(*[str(w.message).split(";")[0] for w in caught])
        """,
        env={"PATH": "/usr/bin:/bin"},
    )
    assert out.splitlines() == [
        "None",
        "MuJoCo was imported before MUJOCO_GL was set and there is no display, so it cannot render",
    ]
