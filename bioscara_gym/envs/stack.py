"""Bioscara-Stack: put one block on the other at a target on the table, the lower one first."""

from __future__ import annotations

import math
from types import MappingProxyType
from typing import Any

import numpy as np
from gymnasium import spaces

from bioscara_gym.envs.base import BioscaraEnv
from bioscara_gym.envs.blocks import SimBlock
from bioscara_gym.envs.pick_place import BLOCK_SIZE, BioscaraPickPlaceEnv, KinematicBlock
from bioscara_gym.envs.rendering import SceneState

#: A block counts as resting where it should within this height, m (of 15 mm on the
#: table, of 45 mm on the other block).
Z_TOL = 0.003
#: Distance of each block's start from the target, m.
START_RANGE = (0.07, 0.15)
#: Least distance between the blocks' starts, and from the upper block to the lower
#: one's way to the target (dragged along the table), m.
CLEARANCE = 0.07
#: Share of the episodes whose lower block starts at the target.
LOWER_THERE = 0.5


def _segment_distance(p: np.ndarray, a: np.ndarray, b: np.ndarray) -> float:
    """Distance from the point ``p`` to the segment ``a``-``b`` (all (2,), m)."""
    ab = b - a
    t = float(np.clip((p - a) @ ab / max(float(ab @ ab), 1e-12), 0.0, 1.0))
    return float(np.linalg.norm(p - (a + t * ab)))


class KinematicStack:
    """Both blocks where there is no physics (``mock``, ``i2c``): grasped, carried, stacked.

    Each block is PickPlace's :class:`KinematicBlock` (held when the gripper
    closes on it, dropped when it opens), the upper one tried first, and only
    one held at a time. A dropped block lands on the other one if it overlaps
    it, else on the table.
    """

    def __init__(self) -> None:
        """Two blocks at the origin, not held."""
        self.lower, self.upper = KinematicBlock(), KinematicBlock()

    def update(self, tcp: np.ndarray, width: float) -> None:
        """Carry, grasp, drop and stack after a control step."""
        for block, other in ((self.upper, self.lower), (self.lower, self.upper)):
            if other.held:
                continue
            was_held = block.held
            block.update(tcp, width)
            overlaps = np.all(np.abs(block.pos[:2] - other.pos[:2]) < BLOCK_SIZE)
            if was_held and not block.held and overlaps:
                block.pos[2] = other.pos[2] + BLOCK_SIZE


class BioscaraStackEnv(BioscaraPickPlaceEnv):
    """Stack two 3 cm blocks at a target on the table: the blue one below, the yellow one on it.

    ## Description
    Same arm, backends, gripper and conventions as ``Bioscara-PickPlace``
    (see :class:`~bioscara_gym.envs.pick_place.BioscaraPickPlaceEnv`), with
    two blocks: the lower (blue, ``block``) and the upper (yellow,
    ``block2``). The target lies on the table 0.25-0.55 m from the j1 axis
    where j1 is within 1 rad of the start pose's (with the start pose's
    elbow); the upper block 7-15 cm from it. In half the episodes the lower
    block starts at the target; in the others 7-15 cm from it, at least 7 cm
    from the upper block, and the upper block at least 7 cm from the lower
    one's way to the target: the lower one has to be brought there first.
    Both are real MuJoCo bodies on ``sim`` and ``emulated``.

    ## Action space
    PickPlace's: ``Box(-1, 1, (5,), float32)``, the four joint commands and the
    gripper opening mapped onto [0.04, 0.12] m; in ``cartesian`` mode x and y
    move by up to 2 cm per step.

    ## Observation space
    | key           | shape | content                                                 |
    |---------------|-------|---------------------------------------------------------|
    | observation   | (32,) | Reach's 12 values, then each block's, see below         |
    | achieved_goal | (6,)  | lower block position, upper block position, in m        |
    | desired_goal  | (6,)  | the target, and the point a block height above it, in m |

    ``observation``, by index and by name in ``OBS_SLICES``:

    | idx   | OBS_SLICES     | content                                                 | unit |
    |-------|----------------|---------------------------------------------------------|------|
    | 0-3   | joint_pos      | j1..j4 positions scaled to [-1, 1] by the joint limits  | 1    |
    | 4-7   | joint_vel      | j1..j4 velocities divided by the joint's max velocity   | 1    |
    | 8     | gripper        | gripper width scaled to [-1, 1] over [0.04, 0.12] m     | 1    |
    | 9-11  | tcp            | TCP position x, y, z, from the measured joints          | m    |
    | 12-14 | lower_pos      | lower block position x, y, z                            | m    |
    | 15-17 | lower_from_tcp | lower block position minus TCP position                 | m    |
    | 18-20 | lower_vel      | lower block linear velocity (0 on ``mock`` and ``i2c``) | m/s  |
    | 21    | lower_yaw      | lower block yaw about z                                 | rad  |
    | 22-24 | upper_pos      | upper block position x, y, z                            | m    |
    | 25-27 | upper_from_tcp | upper block position minus TCP position                 | m    |
    | 28-30 | upper_vel      | upper block linear velocity (0 on ``mock`` and ``i2c``) | m/s  |
    | 31    | upper_yaw      | upper block yaw about z                                 | rad  |

    On ``mock`` and ``i2c`` a kinematic stand-in (:class:`KinematicStack`)
    carries a grasped block and drops it on the table or on the other block,
    since the testbed has no block sensor.

    ## Rewards
    On each block's distance to its place in ``desired_goal`` (3-D, m):
    ``dense`` minus their sum, ``log`` the sum of
    ``-log(1 + distance / distance_threshold)``, ``sparse`` 0 on success, else
    -1. A stall adds -10 and ends the episode.

    ## Success
    Each block within ``distance_threshold`` (0.01 m) of its place
    horizontally and within 3 mm of its height: the lower one resting on
    the table at the target (centre 15 mm high), the upper one resting on
    it (centre 45 mm high, so on the lower block: it cannot be there
    otherwise unless held).

    ## Episode end, arguments
    As PickPlace: a stall ends the episode, ``max_episode_steps`` 300 (12 s
    at 25 Hz); Reach's kwargs but ``goal_radius`` and ``goal_horizon_s``
    (``distance_threshold`` default 0.01 m).

    ## Version history
    * v0: initial release, with ``Bioscara-PickPlace-v1``'s cartesian actions
      (each joint's target leads by its braking distance, ``cartesian_lead``).
    """

    #: Reach's observation, then the lower block's and the upper block's (see the observation table).
    OBS_SLICES = MappingProxyType(
        {
            **BioscaraEnv.OBS_SLICES,
            "lower_pos": slice(12, 15),
            "lower_from_tcp": slice(15, 18),
            "lower_vel": slice(18, 21),
            "lower_yaw": slice(21, 22),
            "upper_pos": slice(22, 25),
            "upper_from_tcp": slice(25, 28),
            "upper_vel": slice(28, 31),
            "upper_yaw": slice(31, 32),
        }
    )

    def __init__(self, *args: Any, **kwargs: Any) -> None:
        """See the class docstring for the arguments."""
        super().__init__(*args, **kwargs)
        self.goal = np.zeros(6)
        self._kinematic = KinematicStack()
        self._sim_blocks: tuple[SimBlock, SimBlock] | None = None
        self.block_yaws = (0.0, 0.0)
        if self.sim is not None:
            lower, upper = SimBlock(self.sim, "block"), SimBlock(self.sim, "block2")
            upper.bring_in(like="block")
            self._sim_blocks = (lower, upper)

    def _make_observation_space(self) -> spaces.Dict:
        space = super()._make_observation_space()
        goal = spaces.Box(-np.inf, np.inf, shape=(6,), dtype=np.float64)
        return spaces.Dict({"observation": space["observation"], "achieved_goal": goal, "desired_goal": goal})

    def _sample_goal(self) -> np.ndarray:
        """Draw the target, place the upper block, then the lower one (at the target in half the episodes)."""
        q1, elbow = float(self._q_arm[0]), 1.0 if self._q_arm[2] >= 0 else -1.0
        target, target_j1 = self._sample_table_point(q1, elbow)
        upper = self._near(target, target_j1, elbow)
        lower = target.copy()
        if self.np_random.random() >= LOWER_THERE:
            while True:
                lower = self._near(target, target_j1, elbow)
                if (
                    np.linalg.norm(lower[:2] - upper[:2]) >= CLEARANCE
                    and _segment_distance(upper[:2], lower[:2], target[:2]) >= CLEARANCE
                ):
                    break
        yaws = self.np_random.uniform(-math.pi / 4, math.pi / 4, size=2)
        self.block_yaws = (float(yaws[0]), float(yaws[1]))
        self.block_yaw = self.block_yaws[0]
        if self._sim_blocks is not None:
            for block, pos, yaw in zip(self._sim_blocks, (lower, upper), self.block_yaws, strict=True):
                block.place(pos, yaw)
            import mujoco  # the sim backend has imported it

            mujoco.mj_forward(self.sim.model, self.sim.data)
        else:
            self._kinematic.lower.place(lower, self.block_yaws[0])
            self._kinematic.upper.place(upper, self.block_yaws[1])
        return np.concatenate((target, target + np.array([0.0, 0.0, BLOCK_SIZE])))

    def _near(self, target: np.ndarray, target_j1: float, elbow: float) -> np.ndarray:
        """A point on the table ``START_RANGE`` from ``target``, within the sector of ``target_j1``."""
        while True:
            point, _ = self._sample_table_point(target_j1, elbow)
            if START_RANGE[0] <= np.linalg.norm(point[:2] - target[:2]) <= START_RANGE[1]:
                return point

    def _blocks(self) -> list[tuple[np.ndarray, np.ndarray, float]]:
        """Position (m), linear velocity (m/s) and yaw (rad) of the lower block, then the upper one."""
        if self._sim_blocks is not None:
            return [block.state() for block in self._sim_blocks]
        self._kinematic.update(self._tcp_arm.copy(), self.arm.gripper_command)
        return [(b.pos.copy(), np.zeros(3), b.yaw) for b in (self._kinematic.lower, self._kinematic.upper)]

    def _get_obs(self) -> dict[str, np.ndarray]:
        tcp = self.tcp_position()
        parts = [self._joint_obs()]
        for pos, vel, yaw in self._blocks():
            parts += [pos, pos - tcp, vel, (yaw,)]
        observation = np.concatenate(parts)
        s = self.OBS_SLICES
        achieved = np.concatenate((observation[s["lower_pos"]], observation[s["upper_pos"]]))
        return {"observation": observation, "achieved_goal": achieved, "desired_goal": self.goal.copy()}

    def _block_errors(self, achieved: np.ndarray, desired: np.ndarray) -> tuple[np.ndarray, np.ndarray]:
        """Horizontal (m) and vertical (m, absolute) error of each block, shape ``(..., 2)`` each."""
        d = (np.asarray(achieved) - np.asarray(desired)).reshape(*np.shape(achieved)[:-1], 2, 3)
        return np.hypot(d[..., 0], d[..., 1]), np.abs(d[..., 2])

    def _is_success(self, achieved: np.ndarray, desired: np.ndarray) -> np.ndarray:
        """Both blocks within ``distance_threshold`` of their places horizontally and ``Z_TOL`` in height."""
        horizontal, vertical = self._block_errors(achieved, desired)
        return np.all((horizontal < self.distance_threshold) & (vertical < Z_TOL), axis=-1)

    def compute_reward(
        self, achieved_goal: np.ndarray, desired_goal: np.ndarray, info: object
    ) -> np.ndarray | float:
        """Dense: minus the distances (m) summed; log: Reach's log term summed; sparse: success - 1."""
        a, desired = self._goal_pair(achieved_goal, desired_goal)
        if self.reward_type == "sparse":
            return self._is_success(a, desired).astype(np.float64) - 1.0
        d = np.linalg.norm((a - desired).reshape(*a.shape[:-1], 2, 3), axis=-1)
        if self.reward_type == "log":
            return -np.sum(np.log1p(d / self.distance_threshold), axis=-1)
        return -np.sum(d, axis=-1)

    def _scene(self) -> SceneState:
        """The target marker at the upper block's place; the kinematic blocks where nothing is simulated."""
        scene = SceneState(
            goal=self.goal[3:], joints=dict(zip(self.joint_names, self._q.tolist(), strict=True))
        )
        if self.sim is None:
            k = self._kinematic
            scene.bodies = {"block": (k.lower.pos, k.lower.yaw), "block2": (k.upper.pos, k.upper.yaw)}
        return scene
