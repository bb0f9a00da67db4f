"""Bioscara-Push: push a block across the table to a target with the closed gripper."""

from __future__ import annotations

import math
from types import MappingProxyType

import numpy as np

from bioscara_gym import kinematics
from bioscara_gym.envs.base import BioscaraEnv
from bioscara_gym.envs.blocks import SimBlock
from bioscara_gym.envs.pick_place import BLOCK_SIZE, PAD_THICKNESS, BioscaraPickPlaceEnv

#: TCP (fingertip) height while pushing, m: the pads touch the block's side from 10 mm
#: up to its top at 30 mm.
PUSH_Z = 0.01
#: Sliding friction of the block on the table in Push (chosen; the scene's 1.0 suits
#: grasping). A cube pushed above ``BLOCK_SIZE / 2 / mu`` tips over its front edge: at
#: mu = 1 that is 15 mm, inside the pads' contact, and the cube rocked against the
#: pusher until a joint's stall detector tripped (2 of 40 scripted episodes); at 0.5
#: it is the cube's top. 0.5 is within what dry plastic on wood is usually given.
PUSH_FRICTION = 0.5
#: Half the finger pads' length along the tool's x axis, m (``assets/bioscara.xml``, class ``finger``).
PAD_HALF_LENGTH = 0.012
#: A block counts as resting on the table within this height of ``BLOCK_SIZE / 2``, m.
Z_TOL = 0.003
#: Distance from the block to its target, m.
PUSH_RANGE = (0.05, 0.2)
#: Horizontal distance from the start TCP to the block, m: clear of the closed gripper,
#: and near enough to be reached within the episode.
START_RANGE = (0.08, 0.25)


def tool_yaw(q: np.ndarray) -> float:
    """Direction (rad) of the tool's x axis, the closed gripper's pushing face normal: j1 + j3 + j4."""
    return float(q[0] + q[2] + q[3])


class KinematicPushBlock:
    """The block where there is no physics (``mock``, ``i2c``): pushed out of the closed gripper.

    The closed gripper's footprint is a rectangle at the TCP, ``PAD_HALF_LENGTH``
    along the tool's x axis and ``closed_width / 2 + PAD_THICKNESS / 2`` along
    its y axis; the block is a disc of radius ``BLOCK_SIZE / 2``. After each
    step, if the fingertips are below the block's top and the two overlap, the
    block moves out along the shortest way. It never rotates. On the real arm
    this stands in for an external block sensor, which the testbed does not have.

    Args:
        closed_width: The gripper's closed width (between the pads' mid-planes), m.
    """

    def __init__(self, closed_width: float) -> None:
        """Start with the block at the origin."""
        self.pos = np.zeros(3)
        self.yaw = 0.0
        self.half = np.array([PAD_HALF_LENGTH, closed_width / 2 + PAD_THICKNESS / 2])

    def place(self, pos: np.ndarray, yaw: float) -> None:
        """Put the block at ``pos`` (m) with ``yaw`` (rad)."""
        self.pos = np.asarray(pos, dtype=float).copy()
        self.yaw = yaw

    def update(self, tcp: np.ndarray, yaw: float) -> None:
        """Push the block out of the gripper's footprint (TCP at ``tcp``, tool x axis at ``yaw``)."""
        if tcp[2] >= BLOCK_SIZE:
            return
        c, s = math.cos(yaw), math.sin(yaw)
        rel = self.pos[:2] - tcp[:2]
        local = np.array([c * rel[0] + s * rel[1], -s * rel[0] + c * rel[1]])
        closest = np.clip(local, -self.half, self.half)
        gap = local - closest
        dist = math.hypot(gap[0], gap[1])
        r = BLOCK_SIZE / 2
        if dist >= r:
            return
        if dist > 1e-12:
            local = closest + gap / dist * r
        else:  # the centre inside the footprint: out through the nearest side
            axis = int(np.argmin(self.half - np.abs(local)))
            local[axis] = math.copysign(self.half[axis] + r, local[axis] or 1.0)
        self.pos[:2] = tcp[:2] + np.array([c * local[0] - s * local[1], s * local[0] + c * local[1]])


class BioscaraPushEnv(BioscaraPickPlaceEnv):
    """Push a 3 cm block across the table to a target with the closed gripper.

    ## Description
    Same arm, backends and conventions as ``Bioscara-Reach`` (see
    :class:`~bioscara_gym.envs.reach.BioscaraReachEnv`) and the block of
    ``Bioscara-PickPlace``. The gripper is held closed (width 0.04 m, a 2 cm
    gap between the pads: too narrow for the block), so the fingers are a
    6 x 2.4 cm pusher; the policy does not command it. The task is planar: the
    arm starts with its fingertips 1 cm above the table, the block lies
    0.25-0.55 m from the j1 axis where j1 is within 1 rad of the start pose's
    (with the start pose's elbow), and the target lies on the table 5-20 cm
    from the block, within 1 rad of j1 from it. On ``sim`` and ``emulated``
    MuJoCo slides the block on the table under friction (0.5) when the
    fingers push it.

    ## Action space
    ``Box(-1, 1, (4,), float32)``: the four joint commands of Reach. In
    ``cartesian`` mode x and y move by up to 2 cm per step (Reach: 1 cm).

    ## Observation space
    | key           | shape | content                                        |
    |---------------|-------|------------------------------------------------|
    | observation   | (24,) | Reach's 12 values, then the block's, see below |
    | achieved_goal | (3,)  | block position in m                            |
    | desired_goal  | (3,)  | target position in m, on the table             |

    ``observation``, by index and by name in ``OBS_SLICES`` (PickPlace's layout, then the tool):

    | idx   | OBS_SLICES     | content                                                 | unit |
    |-------|----------------|---------------------------------------------------------|------|
    | 0-3   | joint_pos      | j1..j4 positions scaled to [-1, 1] by the joint limits  | 1    |
    | 4-7   | joint_vel      | j1..j4 velocities divided by the joint's max velocity   | 1    |
    | 8     | gripper        | gripper width scaled to [-1, 1] over [0.04, 0.12] m     | 1    |
    | 9-11  | tcp            | TCP position x, y, z, from the measured joints          | m    |
    | 12-14 | block_pos      | block position x, y, z                                  | m    |
    | 15-17 | block_from_tcp | block position minus TCP position                       | m    |
    | 18-20 | block_vel      | block linear velocity (0 on ``mock`` and ``i2c``)       | m/s  |
    | 21    | block_yaw      | block yaw about z                                       | rad  |
    | 22-23 | tool_dir       | cos, sin of the tool's x axis (j1 + j3 + j4): the pushing face's normal | 1 |

    The gripper entry is -1 throughout (held closed). On ``mock`` and ``i2c``
    a kinematic stand-in (:class:`KinematicPushBlock`) is pushed out of the
    closed gripper's footprint, since the testbed has no block sensor.

    ## Rewards
    As Reach on the block-target distance (3-D, m): ``dense`` minus the
    distance, ``log`` ``-log(1 + distance / distance_threshold)``; ``sparse``
    0 on success, else -1. A stall adds -10 and ends the episode.

    ## Success
    The block's centre within ``distance_threshold`` (0.01 m) of the target
    horizontally, resting on the table: its centre within 3 mm of 15 mm high.
    The block is never lifted: the closed pads cannot hold it and the
    fingertips stay above the table; a block wedged between the pads and
    lifted, or tipped onto an edge, is not a success.

    ## Episode end, arguments
    As Reach: a stall ends the episode, ``max_episode_steps`` 200 (8 s at
    25 Hz); Reach's kwargs but ``goal_radius`` and ``goal_horizon_s``
    (``distance_threshold`` default 0.01 m).

    ## Version history
    * v0: initial release, with ``Bioscara-PickPlace-v1``'s cartesian actions
      (each joint's target leads by its braking distance, ``cartesian_lead``).
    """

    uses_gripper = False
    #: PickPlace's observation, then the pushing face's direction (see the observation table).
    OBS_SLICES = MappingProxyType({**BioscaraPickPlaceEnv.OBS_SLICES, "tool_dir": slice(22, 24)})

    def __init__(self, *args: object, **kwargs: object) -> None:
        """See the class docstring for the arguments."""
        super().__init__(*args, **kwargs)
        self._block = KinematicPushBlock(self.config.gripper.min)  # type: ignore[assignment]
        self._sim_block = None
        if self.sim is not None:
            self._sim_block = SimBlock(self.sim, "block")
            m = self.sim.model
            for geom in ("block", "table"):  # MuJoCo takes the larger of a pair's frictions
                m.geom_friction[m.geom(geom).id, 0] = PUSH_FRICTION

    def _hold(self) -> None:
        """Hold the joints and close the gripper (it stays closed)."""
        super()._hold()
        closed = self.config.gripper.min
        self.arm.set_gripper(closed)
        self.arm.gripper.set_position(closed)

    def _random_pose(self) -> np.ndarray:
        """Anywhere in reach, the fingertips at ``PUSH_Z`` above the table."""
        q = BioscaraEnv._random_pose(self)
        q[1] = PUSH_Z - kinematics.TCP_Z0
        return q

    def _sample_goal(self) -> np.ndarray:
        """Place the block on the table, then draw the target on the table ``PUSH_RANGE`` from it."""
        tcp = self._tcp_arm
        q1, elbow = float(self._q_arm[0]), 1.0 if self._q_arm[2] >= 0 else -1.0
        while True:
            block, block_j1 = self._sample_table_point(q1, elbow)
            if START_RANGE[0] <= np.linalg.norm(block[:2] - tcp[:2]) <= START_RANGE[1]:
                break
        while True:
            target, _ = self._sample_table_point(block_j1, elbow)
            if PUSH_RANGE[0] <= np.linalg.norm(target[:2] - block[:2]) <= PUSH_RANGE[1]:
                break
        self.block_yaw = float(self.np_random.uniform(-math.pi / 4, math.pi / 4))
        if self._sim_block is not None:
            self._sim_block.place(block, self.block_yaw)
            self._close_fingers()
            import mujoco  # the sim backend has imported it

            mujoco.mj_forward(self.sim.model, self.sim.data)
        else:
            self._block.place(block, self.block_yaw)
        return target

    def _close_fingers(self) -> None:
        """Put the simulated fingers at the closed width at rest (the servo's command since ``_hold``)."""
        m, d = self.sim.model, self.sim.data
        for finger in ("finger_left", "finger_right"):
            jid = m.joint(finger).id
            d.qpos[m.jnt_qposadr[jid]] = self.config.gripper.min / 2
            d.qvel[m.jnt_dofadr[jid]] = 0.0

    def _block_state(self) -> tuple[np.ndarray, np.ndarray, float]:
        """Block position (m), linear velocity (m/s) and yaw (rad)."""
        if self._sim_block is not None:
            return self._sim_block.state()
        self._block.update(self._tcp_arm.copy(), tool_yaw(self._q_arm))
        return self._block.pos.copy(), np.zeros(3), self._block.yaw

    def _get_obs(self) -> dict[str, np.ndarray]:
        obs = super()._get_obs()
        yaw = tool_yaw(self._q)
        obs["observation"] = np.concatenate((obs["observation"], (math.cos(yaw), math.sin(yaw))))
        return obs

    def _is_success(self, achieved: np.ndarray, desired: np.ndarray) -> np.ndarray:
        """Within ``distance_threshold`` horizontally, resting on the table (height within ``Z_TOL``)."""
        d = np.asarray(achieved) - np.asarray(desired)
        horizontal = np.hypot(d[..., 0], d[..., 1])
        return (horizontal < self.distance_threshold) & (np.abs(d[..., 2]) < Z_TOL)

    def compute_reward(
        self, achieved_goal: np.ndarray, desired_goal: np.ndarray, info: object
    ) -> np.ndarray | float:
        """Reach's dense and log rewards; sparse: 0 on success (:meth:`_is_success`), else -1."""
        if self.reward_type == "sparse":
            return self._is_success(*self._goal_pair(achieved_goal, desired_goal)).astype(np.float64) - 1.0
        return super().compute_reward(achieved_goal, desired_goal, info)


__all__ = ["PUSH_Z", "BioscaraPushEnv", "KinematicPushBlock", "tool_yaw"]
