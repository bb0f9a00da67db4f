"""Bioscara-PickPlace: pick a block off the table and place it at a target."""

from __future__ import annotations

import math
from types import MappingProxyType

import numpy as np

from bioscara_gym import kinematics
from bioscara_gym.envs.base import BioscaraEnv
from bioscara_gym.envs.rendering import SceneState

#: Block edge length in m (``geom block`` in ``assets/scene.xml``).
BLOCK_SIZE = 0.03
#: The gripper's width is measured between the finger pads' mid-planes; the clear
#: gap is this much narrower (``assets/README.md``, "Gripper").
PAD_THICKNESS = 0.02
#: TCP below the block centre, m, when grasped (fingertips near the block's bottom).
GRASP_DEPTH = 0.015


class KinematicBlock:
    """The block where there is no physics (``mock``, ``i2c``): carried when grasped.

    The block is held when the gripper is commanded narrower than the block
    with the TCP within 1.5 cm (horizontally) of the block's centre and below
    its top; it falls back to the table when the gripper opens. On the real
    arm this stands in for an external block sensor, which the testbed does
    not have.
    """

    def __init__(self) -> None:
        """Start with the block at the origin, not held."""
        self.pos = np.zeros(3)
        self.yaw = 0.0
        self.held = False
        self._offset = np.zeros(3)

    def place(self, pos: np.ndarray, yaw: float) -> None:
        """Put the block at ``pos`` with ``yaw`` (rad), not held."""
        self.pos = np.asarray(pos, dtype=float).copy()
        self.yaw = yaw
        self.held = False

    def update(self, tcp: np.ndarray, width: float) -> None:
        """Carry, grasp or drop the block after a control step."""
        closed = width - PAD_THICKNESS < BLOCK_SIZE
        if self.held and not closed:
            self.held = False
            self.pos[2] = BLOCK_SIZE / 2
        elif not self.held and closed:
            d = tcp - self.pos
            if math.hypot(d[0], d[1]) < 0.015 and -BLOCK_SIZE < d[2] < BLOCK_SIZE / 2:
                self.held = True
                self._offset = self.pos - tcp
        if self.held:
            self.pos = tcp + self._offset
            self.pos[2] = max(self.pos[2], BLOCK_SIZE / 2)


class BioscaraPickPlaceEnv(BioscaraEnv):
    """Pick a 3 cm block off the table and place it at a target position.

    ## Description
    Same arm, backends and conventions as ``Bioscara-Reach`` (see
    :class:`~bioscara_gym.envs.reach.BioscaraReachEnv`), plus the gripper. The
    block lies on the table 0.25-0.55 m from the j1 axis, with a random yaw,
    where j1 is within 1 rad of the start pose's (with the start pose's
    elbow); the target is within 1 rad of j1 from the block, on the table or
    up to 5 cm above it (the lift moves at 0.03 m/s). The gap
    between the finger pads is the commanded width minus 2 cm, so the block
    is touched at a width of 0.05 m and squeezed at 0.04 m.

    ## Action space
    ``Box(-1, 1, (5,), float32)``: the four joint commands of Reach, then the
    gripper opening mapped onto [0.04, 0.12] m. In ``cartesian`` mode x and y
    move by up to 2 cm per step (Reach: 1 cm), to carry the block in time.

    ## Observation space
    | key           | shape | content                                        |
    |---------------|-------|------------------------------------------------|
    | observation   | (22,) | Reach's 12 values, then the block's, see below |
    | achieved_goal | (3,)  | block position in m                            |
    | desired_goal  | (3,)  | target position in m                           |

    ``observation``, by index and by name in ``OBS_SLICES``:

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

    On ``sim`` and ``emulated`` the block is simulated by MuJoCo; on ``mock``
    and ``i2c`` a kinematic stand-in (:class:`KinematicBlock`) is carried when
    grasped, since the testbed has no block sensor.

    ## Rewards, episode end, arguments
    As Reach: dense (minus block-target distance), sparse or log, a stall
    ends the episode with -10, ``max_episode_steps`` 200 (8 s at 25 Hz), and
    Reach's kwargs but ``goal_radius`` and ``goal_horizon_s``
    (``distance_threshold`` default 0.01 m).

    ## Version history
    * v1: cartesian mode keeps the speed a step asks: each joint's target
      leads by its braking distance (``cartesian_lead``; v0 braked on every
      step's target, so j1 turned at about 0.3-0.5 rad/s of its 1 rad/s). The block and
      target sectors are drawn in j1, as above: v0 drew them in bearing (1 rad
      around the TCP's), and a block a few degrees away across the back of the
      base then needed j1 to turn 5 rad the long way round. That change was
      made under the id ``-v0``; v0's distribution is no longer made, and
      ``gym.make("Bioscara-PickPlace-v0")`` names the versions there are.
    * v0: initial release.
    """

    uses_gripper = True
    #: 2 cm steps in x and y: carrying the block across the table at Reach's 1 cm
    #: costs the scripted cartesian controller 10 points of success (74 % vs 84 %).
    #: The scripted experts brake themselves and DAgger learns it from them.
    cartesian_lead = True
    cartesian_step = (0.02, 0.02, 0.01)
    #: Reach's observation, then the block's (see the observation table).
    OBS_SLICES = MappingProxyType(
        {
            **BioscaraEnv.OBS_SLICES,
            "block_pos": slice(12, 15),
            "block_from_tcp": slice(15, 18),
            "block_vel": slice(18, 21),
            "block_yaw": slice(21, 22),
        }
    )

    def __init__(self, *args: object, **kwargs: object) -> None:
        """See the class docstring for the arguments."""
        super().__init__(*args, **kwargs)  # type: ignore[arg-type]
        self._block = KinematicBlock()
        self.block_yaw = 0.0
        if self.sim is not None:
            m = self.sim.model
            jid = m.joint("block").id
            self._block_qadr = int(m.jnt_qposadr[jid])
            self._block_dadr = int(m.jnt_dofadr[jid])

    def _random_pose(self) -> np.ndarray:
        """TCP above the table, clear of the block's top, anywhere in reach."""
        q = super()._random_pose()
        z = self.np_random.uniform(BLOCK_SIZE + 0.01, BLOCK_SIZE + 0.03)
        q[1] = z - kinematics.TCP_Z0
        return q

    def _sample_table_point(self, j1: float, elbow: float) -> tuple[np.ndarray, float]:
        """A point on the table within reach and j1 within ``SECTOR`` rad of ``j1``, with ``elbow``.

        The sector is drawn in j1, not in bearing: j1 turns 6.1 rad, not a
        full turn, so a point a few degrees away across the back of the base
        can be 5 rad of j1 away. Drawn in j1 with the arm's own elbow, every
        leg of the task is within what j1 (1 rad/s) swings in a second or two,
        in every control mode.

        Returns:
            The point (m) and j1 (rad) there with ``elbow``.
        """
        lo, hi = self.command_low[0], self.command_high[0]
        j1 = min(max(j1, lo), hi)  # a reading just past the range still has a sector inside it
        while True:
            r = self.np_random.uniform(0.25, 0.55)
            q1 = j1 + self.np_random.uniform(-self.SECTOR, self.SECTOR)
            if lo <= q1 <= hi:
                c3 = (r * r - kinematics.L1**2 - kinematics.L2**2) / (2 * kinematics.L1 * kinematics.L2)
                q3 = math.copysign(math.acos(c3), elbow)
                xy = kinematics.forward(np.array([q1, 0.0, q3]))[:2]
                return np.array([xy[0], xy[1], BLOCK_SIZE / 2]), q1

    #: Half-width in rad of j1's sectors blocks and targets are drawn from.
    SECTOR = 1.0

    def _sample_goal(self) -> np.ndarray:
        """Place the block on the table, then draw the target: on the table or up to 5 cm above."""
        tcp = self._tcp_arm
        q1, elbow = float(self._q_arm[0]), 1.0 if self._q_arm[2] >= 0 else -1.0
        while True:
            block, block_j1 = self._sample_table_point(q1, elbow)
            if np.linalg.norm(block[:2] - tcp[:2]) > 0.08:
                break
        while True:
            target, _ = self._sample_table_point(block_j1, elbow)
            if np.linalg.norm(target[:2] - block[:2]) > 0.1:
                break
        if self.np_random.random() < 0.5:
            target[2] += self.np_random.uniform(0.0, 0.05)
        self.block_yaw = float(self.np_random.uniform(-math.pi / 4, math.pi / 4))
        if self.sim is not None:
            d, a = self.sim.data, self._block_qadr
            d.qpos[a : a + 3] = block
            d.qpos[a + 3 : a + 7] = [math.cos(self.block_yaw / 2), 0, 0, math.sin(self.block_yaw / 2)]
            d.qvel[self._block_dadr : self._block_dadr + 6] = 0.0
            import mujoco  # the sim backend has imported it

            mujoco.mj_forward(self.sim.model, d)
        else:
            self._block.place(block, self.block_yaw)
        return target

    def _block_state(self) -> tuple[np.ndarray, np.ndarray, float]:
        """Block position (m), linear velocity (m/s) and yaw (rad)."""
        if self.sim is None:
            self._block.update(self._tcp_arm.copy(), self.arm.gripper_command)
            return self._block.pos.copy(), np.zeros(3), self._block.yaw
        d, a = self.sim.data, self._block_qadr
        w, x, y, z = d.qpos[a + 3 : a + 7]
        yaw = math.atan2(2 * (w * z + x * y), 1 - 2 * (y * y + z * z))
        return d.qpos[a : a + 3].copy(), d.qvel[self._block_dadr : self._block_dadr + 3].copy(), yaw

    def _get_obs(self) -> dict[str, np.ndarray]:
        tcp = self.tcp_position()
        block, block_vel, yaw = self._block_state()
        observation = np.concatenate((self._joint_obs(), block, block - tcp, block_vel, (yaw,)))
        return {"observation": observation, "achieved_goal": block, "desired_goal": self.goal.copy()}

    def _scene(self) -> SceneState:
        """Reach's scene, plus the kinematic block where there is no simulation."""
        scene = super()._scene()
        if self.sim is None:
            scene.bodies = {"block": (self._block.pos, self._block.yaw)}
        return scene
