"""Bioscara-Reach: bring the tool centre point to a goal in space."""

from __future__ import annotations

from typing import Any

import numpy as np

from bioscara_gym import kinematics
from bioscara_gym.envs.base import BioscaraEnv, check_positive

#: Registered episode length (2 s at 25 Hz).
DEFAULT_EPISODE_STEPS = 50
#: Goals are reachable within this fraction of the default episode.
GOAL_HORIZON_FRACTION = 0.6
#: Damping (N s/m, N m s/rad) that pins Reach's unused block: it sinks 0.5 nm/s.
BLOCK_PIN_DAMPING = 1e9


def reachable_travel(v_max: np.ndarray, a_max: np.ndarray, t: float) -> np.ndarray:
    """Distance a trapezoidal profile covers from rest in ``t`` seconds and stops.

    Accelerate, cruise, brake within ``t``: ``a t^2 / 4`` when the peak speed is
    below ``v_max``, else ``v_max (t - v_max / a_max)``.
    """
    t_peak = 2.0 * v_max / a_max
    triangular = a_max * t * t / 4.0
    trapezoid = v_max * (t - v_max / a_max)
    return np.where(t <= t_peak, triangular, trapezoid)


def take_block_off_the_table(model: Any) -> None:
    """Pin the scene's block (a PickPlace prop) where it is, intangible and invisible (an ``MjModel``).

    Resting on the table it makes 4 friction contacts (24 constraint rows)
    in every physics step: taking it out took Reach from 1397 to 1603
    env steps/s. Without contacts it would fall forever; a huge damping on
    its free joint (integrated implicitly, so stable) holds it instead.
    """
    m = model
    body = m.body("block").id
    dofs = m.jnt_dofadr[m.joint("block").id] + np.arange(6)
    m.dof_damping[dofs] = BLOCK_PIN_DAMPING
    geoms = m.geom_bodyid == body
    m.geom_contype[geoms] = 0
    m.geom_conaffinity[geoms] = 0
    m.geom_rgba[geoms, 3] = 0.0


class BioscaraReachEnv(BioscaraEnv):
    """Move the Bioscara's tool centre point (TCP) to a goal position.

    ## Description
    The policy commands the four joints of the Bioscara SCARA arm through the
    joint driver API (``set_velocity`` or ``set_position`` on each joint), on a
    simulated arm (``backend="sim"``) or on the real one (``backend="i2c"``)
    without a change. Goals lie within ``goal_radius`` (15 cm) of the start
    TCP position, where the arm can reach them within the episode under its
    joint speed and acceleration limits (the lift j2 moves at only 0.03 m/s).

    ## Action space
    ``Box(-1, 1, (4,), float32)``; one entry per joint, scaled to the joint:

    | idx | joint | velocity mode (default)      | position mode                   |
    |-----|-------|------------------------------|---------------------------------|
    | 0   | j1    | × 1.0 rad/s                  | [-3.01647, 3.01647] rad         |
    | 1   | j2    | × 0.03 m/s                   | [0.0004, 0.336] m               |
    | 2   | j3    | × 5.0 rad/s                  | [-2.59672, 2.59672] rad         |
    | 3   | j4    | × 10.0 rad/s                 | [-2.98069, 2.98069] rad         |

    Position targets span each joint's limits minus 0.03 rad (2 mm for j2),
    as in the table (the env's ``command_low`` and ``command_high``);
    velocity commands are braked so a joint stops before its end stop (soft
    limits), so only obstacles and overloads stall a joint.

    In ``cartesian`` mode the action moves the TCP instead: entries 0-2 are a
    displacement of x and y by up to 1 cm and z by up to 1 cm per control step
    from the measured TCP, entry 3 turns the wrist by up to 0.1 rad. Analytic
    IK turns the target into joint position targets (sent with
    ``set_position``), keeping the elbow the arm has; the firmware moves each
    joint there and brakes on it, so an action of 0 holds the arm where it
    is (``cartesian_lead=True`` instead keeps the speed a step asks, as
    PickPlace does: a learner must then brake itself; SAC+HER on Reach did
    not learn to, 20-46 % after 30k steps where it reaches 96 % without the
    lead; so does a longer step, 40-70 % at 5 and 18 cm); targets are held inside
    the annulus the arm reaches within its j3 limits, so pushing into a rim
    slides along it. In this mode the elbow j3 is capped at 1.5 rad/s and
    4 rad/s^2 (about j1's TCP speed), so the joints of a step arrive together
    and the TCP moves along the commanded line.

    ## Observation space
    ``Dict`` with:

    | key             | shape | content                                                          |
    |-----------------|-------|------------------------------------------------------------------|
    | observation     | (12,) | the arm's state, laid out as in the next table                   |
    | achieved_goal   | (3,)  | TCP position in m, from the measured joints (forward kinematics) |
    | desired_goal    | (3,)  | goal position in m                                               |

    ``observation``, by index and by name in ``OBS_SLICES``:

    | idx  | OBS_SLICES | content                                                          | unit |
    |------|------------|------------------------------------------------------------------|------|
    | 0-3  | joint_pos  | j1..j4 positions scaled to [-1, 1] by the joint limits           | 1    |
    | 4-7  | joint_vel  | j1..j4 velocities divided by the joint's max velocity            | 1    |
    | 8    | gripper    | gripper width scaled to [-1, 1] over [0.04, 0.12] m              | 1    |
    | 9-11 | tcp        | TCP position x, y, z, from the measured joints                   | m    |

    ## Rewards
    ``dense`` (default): minus the distance between TCP and goal in m.
    ``sparse``: 0 within ``distance_threshold``, else -1. ``log``:
    ``-log(1 + distance / distance_threshold)``, steepest near the goal (what
    the packaged training config uses). A stall adds -10 and ends the
    episode. ``compute_reward`` is vectorized (for HER).

    ## Episode end
    ``terminated`` when a joint stalls (``info["stalled"]``, ``info["stalled_joint"]``);
    ``truncated`` after ``max_episode_steps`` (50, i.e. 2 s at 25 Hz).
    ``info["is_success"]`` is True within ``distance_threshold`` of the goal.

    ## Starting state
    The first reset configures, activates and homes the arm through the home
    command interface (in simulation too: each joint drives into its end
    stop). Later resets keep the homed arm and start from a pose drawn
    uniformly within the joint limits.

    ## Arguments
    | kwarg              | default    | meaning                                                       |
    |--------------------|------------|---------------------------------------------------------------|
    | backend            | "sim"      | "sim", "mock", "emulated" (real driver, emulated bus), "i2c"  |
    | control_mode       | "velocity" | "velocity", "position" or "cartesian" (TCP displacement)      |
    | control_freq       | 25.0       | control rate in Hz; >= 20 (the joints' 50 ms deadman)         |
    | reward_type        | "dense"    | "dense", "sparse" or "log" (see Rewards)                      |
    | distance_threshold | 0.01       | success radius in m                                           |
    | randomization      | None       | DomainRandomization / dict / True: masses, friction, damping, |
    |                    |            | sensor noise, command latency (seeded by ``reset(seed=)``)    |
    | render_mode        | None       | "rgb_array" or "human"                                        |
    | config             | None       | ArmConfig or YAML path (default: the packaged SPEC values)    |
    | backend_options    | None       | dict passed to the backend (e.g. ``faults`` for "emulated")   |
    | width, height      | 480, 480   | rendered image size in pixels                                 |
    | cartesian_lead     | None       | cartesian mode: targets lead by the braking distance; None:   |
    |                    |            | the class's ``cartesian_lead`` (Reach: False, PickPlace: True)|
    | cartesian_step     | None       | cartesian mode: TCP displacement at action 1 (m, one length   |
    |                    |            | or x, y, z); None: the class's ``cartesian_step``             |
    | goal_radius        | 0.15       | goals lie within this distance (m) of the start TCP           |
    | goal_horizon_s     | None       | goals are reachable within this many seconds; None: 60 % of   |
    |                    |            | 50 control periods (1.2 s at 25 Hz). Lower it with a shorter  |
    |                    |            | max_episode_steps                                             |

    ``max_episode_steps`` is ``gym.make``'s argument (default 50). The env
    cannot see it (Gymnasium applies it as a wrapper), hence ``goal_horizon_s``.

    ## Version history
    * v0: initial release.
    """

    def __init__(
        self,
        *args: Any,
        goal_horizon_s: float | None = None,
        goal_radius: float = 0.15,
        **kwargs: Any,
    ) -> None:
        """See the class docstring for the arguments."""
        super().__init__(*args, **kwargs)
        if goal_horizon_s is None:
            goal_horizon_s = GOAL_HORIZON_FRACTION * DEFAULT_EPISODE_STEPS * self.dt
        self.goal_horizon_s = check_positive("goal_horizon_s", goal_horizon_s, "seconds")
        self.goal_radius = check_positive("goal_radius", goal_radius, "m")
        if self.sim is not None:
            take_block_off_the_table(self.sim.model)

    def _sample_goal(self) -> np.ndarray:
        """A goal within ``goal_radius`` of the TCP, reachable within ``goal_horizon_s``.

        Goals are drawn in joint space (so they are reachable under every
        joint's speed and acceleration limits) and kept if their TCP position
        lies within ``goal_radius`` of the start; after 100 rejections the
        draw is shrunk toward the start pose, which always succeeds.
        """
        travel = reachable_travel(self._vmax, self._amax, self.goal_horizon_s)
        q0 = self._q_arm
        lo = np.maximum(self.command_low, q0 - travel)
        hi = np.minimum(self.command_high, q0 + travel)
        tcp = self._tcp_arm
        scale = 1.0
        while True:
            for _ in range(100):
                q = q0 + scale * (self.np_random.uniform(lo, hi) - q0)
                if np.linalg.norm(kinematics.forward(q) - tcp) <= self.goal_radius:
                    self.goal_joints = q
                    return kinematics.forward(q)
            scale *= 0.5

    def _get_obs(self) -> dict[str, np.ndarray]:
        tcp = self.tcp_position()
        return {
            "observation": self._joint_obs(),
            "achieved_goal": tcp,
            "desired_goal": self.goal.copy(),
        }
