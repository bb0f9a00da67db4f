"""Bioscara-Insert: put the square peg held in the gripper into a hole with 1 mm of clearance."""

from __future__ import annotations

import dataclasses
import math
from types import MappingProxyType
from typing import Any

import numpy as np

from bioscara_gym import kinematics
from bioscara_gym.envs.base import BioscaraEnv
from bioscara_gym.envs.reach import take_block_off_the_table
from bioscara_gym.envs.rendering import SceneState
from bioscara_gym.hardware.config import ArmConfig

#: Peg: 20 mm square (``geom peg`` in ``assets/bioscara.xml``), its tip this far below the TCP, m.
PEG_SIZE = 0.02
PEG_TIP_BELOW_TCP = 0.03
#: Fixture (``body fixture`` in ``assets/scene.xml``): hole width (1 mm more than the peg), the
#: fixture's top above the table and the hole's depth, m.
HOLE_SIZE = 0.021
FIXTURE_TOP = 0.035
HOLE_DEPTH = 0.02
#: The goal: the peg's tip this far down the hole (5 mm above its floor), m.
INSERT_DEPTH = 0.015
#: The lift's speed and stall sensitivity in this task (see the class docstring, "Contact").
LIFT_SPEED = 0.006
LIFT_SENSITIVITY = 4
#: Start: the TCP within this horizontal distance of the hole, m, and the peg's tip this high
#: above the fixture's top, m.
START_OFFSET_M = 0.03
START_GAP_M = (0.003, 0.008)
#: Holes are drawn this far from the j1 axis, m (inside the reach, as PickPlace's blocks).
HOLE_RADIUS_M = (0.3, 0.55)
#: Alignment repeats every quarter turn: the peg and the hole are square.
QUARTER_TURN = math.pi / 2


def yaw_error(hole_yaw: float | np.ndarray, peg_yaw: float | np.ndarray) -> float | np.ndarray:
    """The wrist turn, rad, that squares the peg to the hole: in [-pi/4, pi/4)."""
    return (np.asarray(hole_yaw) - peg_yaw + QUARTER_TURN / 2) % QUARTER_TURN - QUARTER_TURN / 2


class BioscaraInsertEnv(BioscaraEnv):
    """Insert a 20 mm square peg, held in the gripper, into a square hole 1 mm wider.

    ## Description
    Same arm, backends and conventions as ``Bioscara-Reach`` (see
    :class:`~bioscara_gym.envs.reach.BioscaraReachEnv`). The gripper holds a
    20 mm square peg (closed at 0.04 m, the peg's width between the pads)
    whose tip is 30 mm below the TCP. A fixture stands on the table: a block
    35 mm tall with a square hole 21 mm wide (0.5 mm of clearance a side)
    and 20 mm deep. The peg goes in only square to the hole: with the peg
    centred, j4 may be off by at most about 2.9 degrees (a 20 mm square
    turned by theta is 20 (cos theta + sin theta) mm wide), less the
    peg's offset. The policy must align x, y and the wrist above the hole,
    then lower the peg 15 mm down the hole.

    ## Contact, felt as the real arm feels it
    There is no force sensor: a peg that lands on the fixture holds the lift
    j2 against its drive, the drive's rotor slips poles, and the firmware's
    stall detector sees them in the PID error (``docs/firmware.md``, "Stall
    detection"), stops the motor and sets STALL; the env ends the episode
    as a failure (``terminated``, ``info["stalled"]``, -10). Nothing in the
    env decides a jam: the firmware's rule does, run by the emulated
    firmware on ``sim`` and ``emulated`` and by the joint itself on the arm.

    The firmware only sees a jam at some lift speeds, so the task runs the
    lift at ``lift_speed`` (6 mm/s; 9.4 rad/s at the motor) with the stall
    sensitivity ``lift_sensitivity`` (4: threshold 40 microsteps), both sent
    to the joint as the arm's configuration (SETMAXVELOCITY,
    ENABLESTALLGUARD). Held at 6 mm/s the rotor's field runs on by 77
    microsteps a millisecond, under the spike filter's 100, so the low-pass
    error climbs past 40 within 0.14-0.18 s of contact (16 of 16 contact
    phases, ``benchmarks/insert_jam.py``). At the arm's own settings the
    firmware would not notice: its j2 sensitivity 12 (threshold 120) catches
    no jam at 6 or 10 mm/s and 9 of 16 at 15 mm/s, and at the lift's
    30 mm/s the blocked error, 384 a pass, is always dropped by the spike
    filter. Until the STALL the lift presses with its drive's full force,
    314 N at its 40 % current (329 N on the fixture with the 15 N it
    carries); a lift commanded slower than about 5 mm/s (velocity mode)
    may press unnoticed, as on the arm. In ``cartesian`` mode (the
    default here) every command more than 0.1 mm downward runs the lift at
    ``lift_speed``, so a jam is always felt.

    ## Action space
    ``Box(-1, 1, (4,), float32)``, as Reach's. In ``cartesian`` mode
    (default) x and y move by up to 5 mm per step (Reach: 1 cm), z by up
    to 1 cm (the lift covers 0.24 mm of it per step at 6 mm/s), the wrist
    by up to 0.1 rad. In ``velocity`` mode j2's entry scales ``lift_speed``.

    ## Observation space
    | key           | shape | content                                          |
    |---------------|-------|--------------------------------------------------|
    | observation   | (20,) | Reach's 12 values, then the peg's, see below     |
    | achieved_goal | (3,)  | peg tip position in m, from the measured joints  |
    | desired_goal  | (3,)  | the goal: on the hole's axis, 15 mm down, in m   |

    ``observation``, by index and by name in ``OBS_SLICES``:

    | idx   | OBS_SLICES    | content                                                 | unit |
    |-------|---------------|---------------------------------------------------------|------|
    | 0-3   | joint_pos     | j1..j4 positions scaled to [-1, 1] by the joint limits  | 1    |
    | 4-7   | joint_vel     | j1..j4 velocities divided by the joint's max velocity   | 1    |
    | 8     | gripper       | gripper width scaled to [-1, 1] over [0.04, 0.12] m     | 1    |
    | 9-11  | tcp           | TCP position x, y, z, from the measured joints          | m    |
    | 12-14 | peg_tip       | peg tip x, y, z: the TCP 30 mm lower                    | m    |
    | 15-17 | goal_from_tip | the goal minus the peg tip                              | m    |
    | 18    | wrist_turn    | the j4 turn that squares the peg to the hole, see below | rad  |
    | 19    | above_top     | peg tip height above the fixture's top (< 0: in hole)   | m    |

    The wrist turn is the hole's yaw minus the peg's (j1 + j3 + j4),
    wrapped to [-pi/4, pi/4) (the peg is square), unless that would take j4
    beyond its command range: then the quarter turn the other way (up to
    3 pi/4). The peg is rigid in the gripper, so its tip and yaw follow from the
    joints on every backend, the real arm included; the hole's pose is the
    fixture's (drawn per episode, or ``fixture_pose`` where it is bolted).
    On ``mock`` there is no fixture and nothing to jam on.

    ## Rewards
    As Reach, on the peg tip's distance to the goal: ``dense`` (default),
    ``sparse`` or ``log``; a stall adds -10 and ends the episode.

    ## Success and episode end
    ``info["is_success"]``: the peg's tip within ``distance_threshold``
    (2 mm) of the goal and no stall in the step, i.e. the peg 13-17 mm down
    the hole (the fixture admits it nowhere else). ``terminated`` on a
    stall (of any joint); ``truncated`` after ``max_episode_steps`` (150,
    6 s at 25 Hz).

    ## Starting state
    The gripper closed on the peg (0.04 m); the TCP within 3 cm (horizontally)
    of the hole, the peg's tip 3-8 mm above the fixture's top, the wrist
    anywhere in its range. A random fixture stands 0.3-0.55 m from the j1
    axis, where j1 is within its range with the start's elbow, turned by
    any yaw.

    ## Arguments
    | kwarg              | default     | meaning                                                    |
    |--------------------|-------------|------------------------------------------------------------|
    | backend            | "sim"       | "sim", "mock", "emulated", "i2c" (as Reach)                |
    | control_mode       | "cartesian" | "cartesian" (TCP displacement), "velocity" or "position"   |
    | control_freq       | 25.0        | control rate in Hz; >= 20 (the joints' 50 ms deadman)      |
    | reward_type        | "dense"     | "dense", "sparse" or "log"                                 |
    | distance_threshold | 0.002       | success radius around the goal, m                          |
    | randomization      | None        | as Reach                                                   |
    | render_mode        | None        | "rgb_array" or "human"                                     |
    | config             | None        | ArmConfig or YAML path (default: the packaged one)         |
    | backend_options    | None        | dict passed to the backend                                 |
    | width, height      | 480, 480    | rendered image size in pixels                              |
    | cartesian_lead     | None        | cartesian targets lead by the braking distance; None: the  |
    |                    |             | class's (True, as PickPlace: the expert brakes itself)     |
    | cartesian_step     | None        | TCP displacement at action 1 (m, one length or x, y, z);   |
    |                    |             | None: the class's (5 mm in x and y, 1 cm in z)             |
    | lift_speed         | 0.006       | j2's max velocity in this task, m/s (see Contact)          |
    | lift_sensitivity   | 4           | j2's stall sensitivity in this task (threshold 10x it)     |
    | fixture_pose       | None        | (x m, y m, yaw rad) of the hole; None: drawn every episode |

    ## Version history
    * v0: initial release.
    """

    #: x and y at 5 mm a step: the peg must be placed within 0.5 mm.
    cartesian_step = (0.005, 0.005, 0.01)
    #: Targets lead by the braking distance, as PickPlace's: the expert (and so DAgger's
    #: learner) brakes itself, and the lift keeps its speed down the hole.
    cartesian_lead = True
    #: Reach's observation, then the peg's (see the observation table).
    OBS_SLICES = MappingProxyType(
        {
            **BioscaraEnv.OBS_SLICES,
            "peg_tip": slice(12, 15),
            "goal_from_tip": slice(15, 18),
            "wrist_turn": slice(18, 19),
            "above_top": slice(19, 20),
        }
    )

    def __init__(
        self,
        backend: Any = "sim",
        control_mode: str = "cartesian",
        *args: Any,
        distance_threshold: float = 0.002,
        lift_speed: float = LIFT_SPEED,
        lift_sensitivity: int = LIFT_SENSITIVITY,
        fixture_pose: tuple[float, float, float] | None = None,
        **kwargs: Any,
    ) -> None:
        """See the class docstring for the arguments."""
        if isinstance(lift_speed, bool) or not isinstance(lift_speed, int | float) or not lift_speed > 0:
            raise ValueError(f"lift_speed {lift_speed!r} must be a speed > 0 (m/s)")
        self.lift_speed = float(lift_speed)
        self.lift_sensitivity = lift_sensitivity
        super().__init__(backend, control_mode, *args, distance_threshold=distance_threshold, **kwargs)
        self.fixture_pose = None if fixture_pose is None else self._check_fixture_pose(fixture_pose)
        self.hole_yaw = 0.0
        self._hole_xy = np.zeros(2)
        if self.sim is not None:
            m = self.sim.model
            take_block_off_the_table(m)
            m.geom_rgba[m.geom("peg").id, 3] = 1.0
            self._fixture_mocap = int(m.body("fixture").mocapid[0])

    def _arm_config(self, config: ArmConfig) -> ArmConfig:
        """The arm with the lift at ``lift_speed`` and ``lift_sensitivity`` (see "Contact")."""
        lift = config.joint("j2")
        if self.lift_speed > lift.max_velocity:
            raise ValueError(
                f"lift_speed {self.lift_speed:g} m/s is above j2's max velocity {lift.max_velocity:g} m/s"
            )
        lift = dataclasses.replace(lift, max_velocity=self.lift_speed, stall_threshold=self.lift_sensitivity)
        return dataclasses.replace(config, joints=tuple(lift if j.name == "j2" else j for j in config.joints))

    def _check_fixture_pose(self, pose: Any) -> np.ndarray:
        """``fixture_pose`` as an array, or one line saying what is wrong with it."""
        try:
            x, y, yaw = (float(v) for v in pose)
        except (TypeError, ValueError):
            raise ValueError(f"fixture_pose {pose!r} must be (x m, y m, yaw rad)") from None
        if not all(math.isfinite(v) for v in (x, y, yaw)):
            raise ValueError(f"fixture_pose {pose!r} must be finite")
        if all(self._ik(np.array([x, y]), elbow) is None for elbow in (1.0, -1.0)):
            raise ValueError(f"fixture_pose {pose!r}: the arm cannot reach the hole at ({x:g}, {y:g}) m")
        return np.array([x, y, yaw])

    def _ik(self, xy: np.ndarray, elbow: float) -> np.ndarray | None:
        """j1, j3 that put the TCP over ``xy`` with ``elbow``, within the command range; or None."""
        sol = kinematics.inverse(np.array([xy[0], xy[1], 0.0]), elbow)
        if sol is None:
            return None
        q = np.array([sol[0], sol[2]])
        lo, hi = self.command_low[[0, 2]], self.command_high[[0, 2]]
        return q if np.all(q >= lo) and np.all(q <= hi) else None

    # ------------------------------------------------------------- episodes
    def _hold(self) -> None:
        """Reach's hold, with the gripper closed on the peg."""
        super()._hold()
        self.arm.set_gripper(self.config.gripper.min)
        self.arm.gripper.set_position(self.config.gripper.min)

    def _draw_fixture(self, elbow: float) -> tuple[np.ndarray, float]:
        """The hole's position (m) and yaw (rad): ``fixture_pose``, or drawn reachable with ``elbow``."""
        if self.fixture_pose is not None:
            return self.fixture_pose[:2].copy(), float(self.fixture_pose[2])
        lo, hi = self.command_low[0], self.command_high[0]
        while True:
            r = self.np_random.uniform(*HOLE_RADIUS_M)
            c3 = (r * r - kinematics.L1**2 - kinematics.L2**2) / (2 * kinematics.L1 * kinematics.L2)
            q3 = math.copysign(math.acos(c3), elbow)
            xy = kinematics.forward(np.array([self.np_random.uniform(lo, hi), 0.0, q3]))[:2]
            if self._ik(xy, elbow) is not None:
                return xy, float(self.np_random.uniform(0.0, QUARTER_TURN))

    def _random_pose(self) -> np.ndarray:
        """The TCP within ``START_OFFSET_M`` of the hole, the peg's tip 3-8 mm above the fixture."""
        elbow = 1.0 if self.np_random.random() < 0.5 else -1.0
        self._hole_xy, self.hole_yaw = self._draw_fixture(elbow)
        if self.fixture_pose is not None and self._ik(self._hole_xy, elbow) is None:
            elbow = -elbow
        while True:
            r = self.np_random.uniform(0.0, START_OFFSET_M)
            bearing = self.np_random.uniform(-math.pi, math.pi)
            q13 = self._ik(self._hole_xy + r * np.array([math.cos(bearing), math.sin(bearing)]), elbow)
            if q13 is not None:
                break
        gap = self.np_random.uniform(*START_GAP_M)
        j2 = FIXTURE_TOP + gap + PEG_TIP_BELOW_TCP - kinematics.TCP_Z0
        j4 = self.np_random.uniform(self.command_low[3], self.command_high[3])
        return np.array([q13[0], j2, q13[1], j4])

    def _sample_goal(self) -> np.ndarray:
        """Stand the fixture at the hole drawn with the start pose; the goal is 15 mm down its hole."""
        if self.sim is not None:
            d, half = self.sim.data, self.hole_yaw / 2
            d.mocap_pos[self._fixture_mocap] = (*self._hole_xy, 0.0)
            d.mocap_quat[self._fixture_mocap] = (math.cos(half), 0.0, 0.0, math.sin(half))
        return np.array([*self._hole_xy, FIXTURE_TOP - INSERT_DEPTH])

    # ---------------------------------------------------------- observation
    def peg_tip(self) -> np.ndarray:
        """The peg's tip (m), from the measured joints."""
        return self.tcp_position() - np.array([0.0, 0.0, PEG_TIP_BELOW_TCP])

    def peg_yaw(self) -> float:
        """The peg's yaw about z (rad): the tool's, j1 + j3 + j4, from the measured joints."""
        return float(self._q[0] + self._q[2] + self._q[3])

    def wrist_turn(self) -> float:
        """The j4 turn (rad) that squares the peg to the hole: of the quarter turns j4 can make, the smallest.

        That is the yaw error in [-pi/4, pi/4) (:func:`yaw_error`), unless
        it would take j4 past its command range; then a quarter turn less
        the other way.
        """
        q4, lo, hi = float(self._q[3]), self.command_low[3], self.command_high[3]
        err = float(yaw_error(self.hole_yaw, self.peg_yaw()))

        def turns_from(q: float) -> list[float]:
            return [err + k * QUARTER_TURN for k in range(-4, 5) if lo <= q + err + k * QUARTER_TURN <= hi]

        # A reading far past the range (sensor noise of 10 rad) has no turn inside it: turn from its edge.
        return min(turns_from(q4) or turns_from(min(max(q4, lo), hi)), key=abs)

    def _get_obs(self) -> dict[str, np.ndarray]:
        tip = self.peg_tip()
        above = tip[2] - (self.goal[2] + INSERT_DEPTH)
        observation = np.concatenate((self._joint_obs(), tip, self.goal - tip, (self.wrist_turn(), above)))
        return {"observation": observation, "achieved_goal": tip, "desired_goal": self.goal.copy()}

    def _scene(self) -> SceneState:
        """Reach's scene from the fixture's camera; a mirror also shows the peg and stands the fixture."""
        scene = super()._scene()
        scene.camera = "fixture"
        scene.mocaps = {"fixture": (np.array([*self._hole_xy, 0.0]), self.hole_yaw)}
        scene.shown = ("peg",)
        return scene

    def _get_info(
        self, obs: dict[str, np.ndarray], stalled: bool = False, stalled_joint: str | None = None
    ) -> dict[str, Any]:
        """Reach's info; a step that stalled is no success, wherever the peg is."""
        info = super()._get_info(obs, stalled, stalled_joint)
        info["is_success"] = info["is_success"] and not stalled
        return info
