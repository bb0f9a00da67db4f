"""Tests that kill mutants mutmut found surviving in ``envs/rendering.py`` (docs/mutation.md).

The renderer and the viewer are stand-ins that record what they are given
(no OpenGL), the mirror is the packaged scene itself. Expected values are
literals from rendering.py's docstrings (the render modes, the messages,
``MUJOCO_GL=egl`` headless), ``assets/scene.xml`` (the ``overview`` and
``fixture`` cameras, the ``block`` free joint, the ``target`` and
``fixture`` mocap bodies) and ``assets/bioscara.xml`` (the hidden ``peg``).
"""

from __future__ import annotations

import math
import os
import warnings
from typing import Any

import mujoco
import numpy as np
import pytest

from bioscara_gym.assets import scene_path
from bioscara_gym.envs import rendering
from bioscara_gym.envs.rendering import ArmView, SceneState, has_display, prepare, set_free_body

HEADLESS = {"DISPLAY": None, "WAYLAND_DISPLAY": None, "MUJOCO_GL": None}


def environ(monkeypatch: pytest.MonkeyPatch, **values: str | None) -> None:
    for name, value in {**HEADLESS, **values}.items():
        if value is None:
            monkeypatch.delenv(name, raising=False)
        else:
            monkeypatch.setenv(name, value)


# ------------------------------------------------------------------ displays and GL
@pytest.mark.parametrize(
    ("values", "expected"),
    [
        ({}, False),
        ({"DISPLAY": ":0"}, True),
        ({"WAYLAND_DISPLAY": "wayland-0"}, True),
        ({"DISPLAY": "", "WAYLAND_DISPLAY": ""}, False),
    ],
)
def test_a_display_is_display_or_wayland_display_set(
    monkeypatch: pytest.MonkeyPatch, values: dict[str, str], expected: bool
) -> None:
    environ(monkeypatch, **values)
    assert has_display() is expected


def test_an_unknown_render_mode_is_refused_naming_the_two() -> None:
    with pytest.raises(ValueError) as caught:
        prepare("ansi")
    assert str(caught.value) == "render_mode 'ansi' must be one of ['rgb_array', 'human']"


def test_human_without_a_display_is_refused_in_one_line(monkeypatch: pytest.MonkeyPatch) -> None:
    environ(monkeypatch)
    with pytest.raises(ValueError) as caught:
        prepare("human")
    assert str(caught.value) == (
        "render_mode='human' needs a display, and DISPLAY and WAYLAND_DISPLAY are unset; "
        "render_mode='rgb_array' works headless"
    )


@pytest.mark.parametrize(
    ("mode", "values", "expected"),
    [
        ("human", {"DISPLAY": ":0"}, None),  # a display: MuJoCo's default
        ("human", {"WAYLAND_DISPLAY": "wayland-0"}, "egl"),  # no DISPLAY: EGL
        ("rgb_array", {"WAYLAND_DISPLAY": "wayland-0"}, "egl"),
        ("rgb_array", {"MUJOCO_GL": "osmesa"}, "osmesa"),
    ],
)
def test_mujoco_gl_is_egl_without_display_unless_set(
    monkeypatch: pytest.MonkeyPatch, mode: str, values: dict[str, str], expected: str | None
) -> None:
    environ(monkeypatch, **values)
    with warnings.catch_warnings():
        warnings.simplefilter("error")  # with a display (Wayland's too) no warning
        prepare(mode)
    assert os.environ.get("MUJOCO_GL") == expected


def _make_env_with(mode: str) -> None:
    prepare(mode)  # as the env's constructor calls it; the warning points at the env's caller


def test_mujoco_imported_headless_before_the_gl_was_chosen_is_warned_about(
    monkeypatch: pytest.MonkeyPatch,
) -> None:
    environ(monkeypatch)
    assert "mujoco" in rendering.sys.modules  # this process imported it (above)
    with pytest.warns(UserWarning) as caught:
        _make_env_with("rgb_array")
    (warning,) = caught
    assert str(warning.message) == (
        "MuJoCo was imported before MUJOCO_GL was set and there is no display, so it cannot "
        "render; set MUJOCO_GL=egl before importing mujoco (or make the rendering env first)"
    )
    # stacklevel 3 points at the env's caller; mutmut's trampoline adds frames, so only "not prepare":
    assert warning.filename != rendering.__file__
    assert os.environ.get("MUJOCO_GL") == "egl"


# ------------------------------------------------------------------ the mirror
def test_a_free_body_is_put_at_its_position_turned_about_z() -> None:
    model = mujoco.MjModel.from_xml_path(str(scene_path()))
    data = mujoco.MjData(model)
    set_free_body(model, data, "block", np.array([0.25, -0.125, 0.5]), math.pi / 2)
    a = int(model.jnt_qposadr[model.joint("block").id])
    np.testing.assert_array_equal(data.qpos[a : a + 3], [0.25, -0.125, 0.5])
    np.testing.assert_allclose(data.qpos[a + 3 : a + 7], [math.sqrt(0.5), 0, 0, math.sqrt(0.5)], atol=1e-15)
    set_free_body(model, data, "block", np.zeros(3), math.pi)
    np.testing.assert_allclose(data.qpos[a + 3 : a + 7], [0, 0, 0, 1], atol=1e-15)


class FakeRenderer:
    """Stands in for ``mujoco.Renderer``: records its size, scenes and calls."""

    made: list[FakeRenderer] = []

    def __init__(self, model: Any, height: int, width: int) -> None:
        self.model, self.height, self.width = model, height, width
        self.scenes: list[tuple[Any, str]] = []
        self.closed = False
        FakeRenderer.made.append(self)

    def update_scene(self, data: Any, camera: str) -> None:
        self.scenes.append((data, camera))

    def render(self) -> np.ndarray:
        return np.zeros((self.height, self.width, 3), dtype=np.uint8)

    def close(self) -> None:
        self.closed = True


class FakeViewer:
    """Stands in for ``mujoco.viewer.launch_passive``'s handle."""

    def __init__(self, model: Any, data: Any) -> None:
        self.model, self.data = model, data
        self.syncs = 0
        self.closed = False

    def sync(self) -> None:
        self.syncs += 1

    def close(self) -> None:
        self.closed = True


@pytest.fixture
def fake_renderer(monkeypatch: pytest.MonkeyPatch) -> list[FakeRenderer]:
    FakeRenderer.made = []
    monkeypatch.setattr(mujoco, "Renderer", FakeRenderer)
    return FakeRenderer.made


def scene(**changes: Any) -> SceneState:
    return SceneState(**{"goal": np.array([0.3, -0.2, 0.1]), "joints": {}, **changes})


def test_the_mirror_is_the_packaged_scene_posed_as_measured(fake_renderer: list[FakeRenderer]) -> None:
    view = ArmView("rgb_array", width=64, height=48)
    state = scene(
        joints={"j1": 0.5, "j2": 0.125, "j3": -1.0, "j4": 2.0},
        bodies={"block": (np.array([0.4, 0.1, 0.2]), 0.0)},
        mocaps={"fixture": (np.array([0.35, 0.05, 0.0]), math.pi)},
        shown=("peg",),
    )
    image = view.render(None, state)
    assert image.shape == (48, 64, 3)  # (height, width, 3)
    model, data = view._mirror
    for name, q in {"j1": 0.5, "j2": 0.125, "j3": -1.0, "j4": 2.0}.items():
        assert data.qpos[model.jnt_qposadr[model.joint(name).id]] == q, name
    a = int(model.jnt_qposadr[model.joint("block").id])
    np.testing.assert_array_equal(data.qpos[a : a + 7], [0.4, 0.1, 0.2, 1, 0, 0, 0])
    fixture = model.body("fixture").mocapid[0]
    np.testing.assert_array_equal(data.mocap_pos[fixture], [0.35, 0.05, 0.0])
    np.testing.assert_allclose(data.mocap_quat[fixture], [0, 0, 0, 1], atol=1e-15)
    obstacle = model.body("obstacle").mocapid[0]  # not in the scene state: where scene.xml parks it
    np.testing.assert_array_equal(data.mocap_pos[obstacle], [0, 0, -2])
    np.testing.assert_array_equal(data.mocap_quat[obstacle], [1, 0, 0, 0])
    np.testing.assert_array_equal(data.mocap_pos[model.body("target").mocapid[0]], [0.3, -0.2, 0.1])
    assert model.geom_rgba[model.geom("peg").id, 3] == 1.0
    assert model.geom_rgba[model.geom("fixture_table").id, 3] == 0.0  # not shown: stays hidden
    np.testing.assert_allclose(data.xpos[model.body("block").id], [0.4, 0.1, 0.2])  # mj_forward ran
    (renderer,) = fake_renderer
    assert (renderer.model, renderer.height, renderer.width) == (model, 48, 64)
    assert renderer.scenes == [(data, "overview")]  # the scene's camera (assets/scene.xml)


def test_the_mirror_and_the_renderer_are_made_once(fake_renderer: list[FakeRenderer]) -> None:
    view = ArmView("rgb_array", width=32, height=24)
    view.render(None, scene())
    mirror = view._mirror
    view.render(None, scene(camera="fixture", joints={"j1": -0.25}))
    assert view._mirror is mirror and len(fake_renderer) == 1
    model, data = mirror
    assert fake_renderer[0].scenes == [(data, "overview"), (data, "fixture")]
    assert data.qpos[model.jnt_qposadr[model.joint("j1").id]] == -0.25
    view.close()
    assert fake_renderer[0].closed and view._renderer is None
    view.close()  # twice: nothing left to close


def test_a_simulation_is_drawn_itself_not_the_mirror(fake_renderer: list[FakeRenderer]) -> None:
    model = mujoco.MjModel.from_xml_path(str(scene_path()))
    data = mujoco.MjData(model)
    sim = type("Sim", (), {"model": model, "data": data})()
    view = ArmView("rgb_array", width=32, height=24)
    view.render(sim, scene(joints={"j1": 1.0}))
    assert view._mirror is None
    assert fake_renderer[0].model is model and fake_renderer[0].scenes == [(data, "overview")]
    assert data.qpos[model.jnt_qposadr[model.joint("j1").id]] == 0.0  # the sim's own state
    np.testing.assert_array_equal(data.mocap_pos[model.body("target").mocapid[0]], [0.3, -0.2, 0.1])


def test_human_mode_updates_one_window_and_returns_no_image(monkeypatch: pytest.MonkeyPatch) -> None:
    from mujoco import viewer

    opened: list[FakeViewer] = []

    def launch_passive(model: Any, data: Any) -> FakeViewer:
        opened.append(FakeViewer(model, data))
        return opened[-1]

    monkeypatch.setattr(viewer, "launch_passive", launch_passive)
    monkeypatch.setattr(mujoco, "Renderer", None)  # human mode makes no renderer
    view = ArmView("human", width=32, height=24)
    assert view.render(None, scene()) is None
    assert view.render(None, scene()) is None
    (window,) = opened
    assert window.syncs == 2 and (window.model, window.data) == view._mirror
    view.close()
    assert window.closed and view._viewer is None
