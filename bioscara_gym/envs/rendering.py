"""Pictures of the arm: an ``rgb_array`` renderer and a ``human`` viewer, MuJoCo imported lazily.

The env imports this module on every backend, MuJoCo only when a picture is
first drawn: an env on ``mock`` or ``i2c`` without ``render_mode`` runs where
MuJoCo is not installed (a robot computer deploying an ONNX policy).

What is drawn is the simulation itself on ``sim`` and ``emulated``, and
elsewhere a mirror: the packaged scene with its joints and free bodies put
where the arm measured them (:class:`SceneState`).
"""

from __future__ import annotations

import math
import os
import sys
import warnings
from collections.abc import Mapping
from dataclasses import dataclass, field
from typing import Any

import numpy as np

from bioscara_gym.assets import scene_path

RENDER_MODES = ("rgb_array", "human")
#: Largest image, pixels: the offscreen framebuffer of ``assets/scene.xml`` (MuJoCo's default, no
#: ``<global offwidth offheight>``); seen: ``width=641`` was taken and failed at the first render().
MAX_WIDTH, MAX_HEIGHT = 640, 480
#: Camera of ``assets/scene.xml`` that ``rgb_array`` images are taken with (unless a task names another).
CAMERA = "overview"


def has_display() -> bool:
    """Whether a window can be opened (``DISPLAY`` or ``WAYLAND_DISPLAY`` is set)."""
    return bool(os.environ.get("DISPLAY") or os.environ.get("WAYLAND_DISPLAY"))


def prepare(render_mode: str) -> None:
    """Check that ``render_mode`` can work here and choose MuJoCo's OpenGL back end.

    Call before anything imports MuJoCo (MuJoCo reads ``MUJOCO_GL`` when it is
    imported): without a ``DISPLAY`` and with ``MUJOCO_GL`` unset it sets
    ``MUJOCO_GL=egl``, so ``rgb_array`` renders headless. A ``MUJOCO_GL``
    already set is left alone. If MuJoCo was imported already, headless and
    without ``MUJOCO_GL``, it is too late: a warning says so.

    Raises:
        ValueError: ``render_mode`` is unknown, or ``"human"`` without a display.
    """
    if render_mode not in RENDER_MODES:
        raise ValueError(f"render_mode {render_mode!r} must be one of {list(RENDER_MODES)}")
    if render_mode == "human" and not has_display():
        raise ValueError(
            "render_mode='human' needs a display, and DISPLAY and WAYLAND_DISPLAY are unset; "
            "render_mode='rgb_array' works headless"
        )
    if "MUJOCO_GL" not in os.environ and not os.environ.get("DISPLAY"):
        if "mujoco" in sys.modules and not has_display():
            warnings.warn(
                "MuJoCo was imported before MUJOCO_GL was set and there is no display, so it cannot "
                "render; set MUJOCO_GL=egl before importing mujoco (or make the rendering env first)",
                stacklevel=3,
            )
        os.environ["MUJOCO_GL"] = "egl"


@dataclass
class SceneState:
    """What the env shows besides the simulation's own state.

    Attributes:
        goal: Position (m) of the goal marker (mocap body ``target``).
        joints: Measured joint positions by name; drawn only by a mirror.
        bodies: Free bodies' position (m) and yaw (rad) by joint name; drawn
            only by a mirror (e.g. PickPlace's kinematic block).
        camera: The scene's camera ``rgb_array`` images are taken with.
        mocaps: Mocap bodies' position (m) and yaw (rad) by body name; posed
            only in a mirror (the simulation poses its own).
        shown: Geoms the scene hides (alpha 0) that this task shows, by name;
            shown only in a mirror (e.g. Insert's peg).
    """

    goal: np.ndarray
    joints: Mapping[str, float]
    bodies: Mapping[str, tuple[np.ndarray, float]] = field(default_factory=dict)
    camera: str = CAMERA
    mocaps: Mapping[str, tuple[np.ndarray, float]] = field(default_factory=dict)
    shown: tuple[str, ...] = ()


def set_free_body(model: Any, data: Any, joint: str, pos: np.ndarray, yaw: float) -> None:
    """Put the free joint ``joint`` of ``model`` at ``pos`` (m), turned by ``yaw`` (rad) about z."""
    a = int(model.jnt_qposadr[model.joint(joint).id])
    data.qpos[a : a + 3] = pos
    data.qpos[a + 3 : a + 7] = [math.cos(yaw / 2), 0, 0, math.sin(yaw / 2)]


class ArmView:
    """Draws the arm as an RGB image or in a window.

    Args:
        render_mode: ``"rgb_array"`` or ``"human"``.
        width: Image width in pixels (``rgb_array``).
        height: Image height in pixels (``rgb_array``).
    """

    def __init__(self, render_mode: str, width: int, height: int) -> None:
        """Remember the mode and size; MuJoCo is imported on the first :meth:`render`."""
        self.render_mode = render_mode
        self.size = (int(height), int(width))
        self._renderer: Any = None
        self._viewer: Any = None
        self._mirror: tuple[Any, Any] | None = None

    def _model(self, sim: Any, scene: SceneState) -> tuple[Any, Any]:
        """The model to draw: the simulation's own, or the mirror posed as measured."""
        if sim is not None:
            return sim.model, sim.data
        import mujoco

        if self._mirror is None:
            model = mujoco.MjModel.from_xml_path(str(scene_path()))
            self._mirror = (model, mujoco.MjData(model))
        model, data = self._mirror
        for name, q in scene.joints.items():
            data.qpos[model.jnt_qposadr[model.joint(name).id]] = q
        for joint, (pos, yaw) in scene.bodies.items():
            set_free_body(model, data, joint, pos, yaw)
        for body, (pos, yaw) in scene.mocaps.items():
            mocap = model.body(body).mocapid[0]
            data.mocap_pos[mocap] = pos
            data.mocap_quat[mocap] = [math.cos(yaw / 2), 0, 0, math.sin(yaw / 2)]
        for geom in scene.shown:
            model.geom_rgba[model.geom(geom).id, 3] = 1.0
        return model, data

    def render(self, sim: Any, scene: SceneState) -> np.ndarray | None:
        """Draw ``sim`` (an :class:`~bioscara_gym.hardware.sim.ArmSim`) or, if ``None``, the mirror.

        Returns:
            The image, ``(height, width, 3)`` uint8, in ``rgb_array`` mode;
            ``None`` in ``human`` mode (the window is updated).
        """
        import mujoco

        model, data = self._model(sim, scene)
        data.mocap_pos[model.body("target").mocapid[0]] = scene.goal
        mujoco.mj_forward(model, data)
        if self.render_mode == "human":
            if self._viewer is None:
                from mujoco import viewer

                self._viewer = viewer.launch_passive(model, data)
            self._viewer.sync()
            return None
        if self._renderer is None:
            self._renderer = mujoco.Renderer(model, *self.size)
        self._renderer.update_scene(data, camera=scene.camera)
        return self._renderer.render()

    def close(self) -> None:
        """Release the renderer and close the window."""
        if self._renderer is not None:
            self._renderer.close()
            self._renderer = None
        if self._viewer is not None:
            self._viewer.close()
            self._viewer = None
