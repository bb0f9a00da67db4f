"""The loop every Bioscara task shares, with named hooks for the tasks.

``reset`` brings the arm up (:meth:`BioscaraEnv.bring_up`), poses it
(:meth:`~BioscaraEnv._random_pose`) and samples a goal
(:meth:`~BioscaraEnv._sample_goal`); ``step`` sets the action
(:meth:`~BioscaraEnv._set_action`), runs one control cycle, observes
(:meth:`~BioscaraEnv._get_obs`) and scores (:meth:`~BioscaraEnv.compute_reward`,
:meth:`~BioscaraEnv._is_success`). A task file fills in the hooks and
documents its spaces.

The env drives the arm only through :class:`~bioscara_gym.hardware.arm.Arm`
and the joint/gripper API, so the same policy runs on ``sim``, ``mock``,
``emulated`` and ``i2c``. The action mapping is :mod:`~bioscara_gym.envs.actions`,
domain randomization :mod:`~bioscara_gym.envs.randomization` and pictures
:mod:`~bioscara_gym.envs.rendering`; only the last two reach into the MuJoCo
model, only where the backend has one, and MuJoCo is imported only by the
backends that simulate and by a renderer.
"""

from __future__ import annotations

import contextlib
import math
import numbers
from collections import deque
from collections.abc import Mapping, Sequence
from types import MappingProxyType
from typing import Any, ClassVar

import gymnasium as gym
import numpy as np
from gymnasium import spaces

from bioscara_gym import kinematics
from bioscara_gym.envs import rendering
from bioscara_gym.envs.actions import (
    CONTROL_MODES,
    LIMIT_MARGIN,
    ActionMap,
    check_cartesian_step,
    coordinated,
    to_range,
    to_unit,
)
from bioscara_gym.envs.randomization import DomainRandomization, PhysicsRandomizer
from bioscara_gym.hardware.arm import (
    MAX_CONTROL_FREQ,
    MIN_CONTROL_FREQ,
    Arm,
    CommandMode,
    Lifecycle,
    PhaseObserver,
    check_control_freq,
)
from bioscara_gym.hardware.backends import BACKENDS, Backend, make_backend
from bioscara_gym.hardware.config import ArmConfig, load_config
from bioscara_gym.hardware.errors import JointError, StalledError
from bioscara_gym.hardware.field_watch import FieldLostError
from bioscara_gym.hardware.registers import Flag
from bioscara_gym.hardware.safety import SafeStopReport

#: Joint command interface each control mode uses (prefer :attr:`BioscaraEnv.command_mode`).
JOINT_MODE = MappingProxyType(
    {
        "velocity": CommandMode.VELOCITY,
        "position": CommandMode.POSITION,
        "cartesian": CommandMode.POSITION,
    }
)
REWARD_TYPES = ("dense", "sparse", "log")
#: What ``info["bus"]`` counts per joint since the episode's reset (``CommStats``' counters).
BUS_COUNTERS = ("transactions", "retries", "errors", "bus_errors", "malformed", "implausible")

__all__ = [
    "CONTROL_MODES",
    "JOINT_MODE",
    "MAX_CONTROL_FREQ",
    "MIN_CONTROL_FREQ",
    "REWARD_TYPES",
    "BioscaraEnv",
    "DomainRandomization",
    "check_control_freq",
]


def check_positive(name: str, value: object, unit: str) -> float:
    """``value`` as a float if it is a finite number > 0, else a ValueError naming ``name``.

    A string from a config or a hand-edited metadata.json (``goal_radius:
    "abc"``) was a TypeError from the comparison, a traceback on the command line.
    """
    if isinstance(value, bool) or not isinstance(value, numbers.Real):
        raise ValueError(f"{name} {value!r} must be a number > 0 ({unit})")
    if not (math.isfinite(value) and value > 0):
        raise ValueError(f"{name} {value} must be > 0 ({unit})")
    return float(value)


class BioscaraEnv(gym.Env[dict[str, np.ndarray], np.ndarray]):
    """Base class of the goal-conditioned Bioscara tasks (see the task docstrings).

    Public attributes, read-only:

    | name           | type               | content                                                  |
    |----------------|--------------------|----------------------------------------------------------|
    | arm            | ``Arm``            | the arm the env drives: lifecycle, homing, commands      |
    | backend        | ``Backend``        | its joints, gripper, clock, bus statistics               |
    | sim            | ``ArmSim`` or None | the backend's MuJoCo arm (sim, emulated); None otherwise |
    | config         | ``ArmConfig``      | joint limits (j3 capped in cartesian mode)               |
    | command_mode   | ``CommandMode``    | joint command interface of the control mode              |
    | command_low    | (4,) float array   | lowest command of j1..j4: limit + ``limit_margin``       |
    | command_high   | (4,) float array   | highest command of j1..j4: limit - ``limit_margin``      |
    | OBS_SLICES     | str -> slice       | where each quantity lies in ``obs["observation"]``       |
    | goal           | (3,) float array   | the episode's goal, m                                    |
    | dt             | float              | control period, s (``1 / control_freq``)                 |

    and the constructor's ``control_mode``, ``control_freq``, ``reward_type``,
    ``distance_threshold``, ``randomization`` (a :class:`DomainRandomization`)
    and ``render_mode``.

    Public operations besides the Gymnasium API: :meth:`bring_up` (what the
    first ``reset`` does to make the arm ready), :meth:`shut_down` (the
    orderly end), :meth:`safe_stop` (the end after a failure) and
    :meth:`tcp_position`. The env is the one owner of the arm's lifecycle:
    it brings the arm up (here or on ``reset``) and shuts it down (here, in
    :meth:`safe_stop`, or on ``close``); ``bioscara deploy`` calls these and
    reads the rest from :attr:`arm`'s public API (clock, bus statistics,
    deadman guard, final state).
    """

    metadata = {"render_modes": list(rendering.RENDER_MODES), "render_fps": 25}
    #: Joints the policy commands, in action order.
    joint_names = ("j1", "j2", "j3", "j4")
    #: Whether the action has a last element for the gripper width.
    uses_gripper = False
    #: Reward when a stall ends the episode.
    stall_penalty = -10.0
    #: Commands stay this far inside the end stops: rad for revolute joints, m for the lift.
    limit_margin = LIMIT_MARGIN
    #: Cartesian mode: TCP displacement (x, y, z) per control step at action 1, m.
    #: 1 cm in x and y: half the 2 cm first tried, so an action error costs half
    #: the distance (SAC+HER on Reach: 78 % vs 52 % success at 15k steps).
    cartesian_step = (0.01, 0.01, 0.01)
    #: Cartesian mode: each joint's target leads the IK target by its braking
    #: distance (:meth:`~bioscara_gym.envs.actions.ActionMap.lead_target`), so
    #: the arm keeps the speed a step asks and a controller brakes itself.
    #: Off by default: SAC+HER learns Reach without it (below) and not with it.
    cartesian_lead = False
    #: Where each quantity lies in ``obs["observation"]`` (see the task's observation table).
    OBS_SLICES: ClassVar[MappingProxyType[str, slice]] = MappingProxyType(
        {
            "joint_pos": slice(0, 4),
            "joint_vel": slice(4, 8),
            "gripper": slice(8, 9),
            "tcp": slice(9, 12),
        }
    )

    def __init__(
        self,
        backend: str | Backend = "sim",
        control_mode: str = "velocity",
        control_freq: float = 25.0,
        reward_type: str = "dense",
        distance_threshold: float = 0.01,
        randomization: DomainRandomization | dict | bool | None = None,
        render_mode: str | None = None,
        config: ArmConfig | str | None = None,
        backend_options: dict[str, Any] | None = None,
        width: int = 480,
        height: int = 480,
        cartesian_lead: bool | None = None,
        cartesian_step: float | Sequence[float] | None = None,
    ) -> None:
        """Create the env; the backend is built now, the arm is brought up on reset."""
        if isinstance(backend, str) and backend not in BACKENDS:  # the registry's for the Bioscara's joints
            raise ValueError(f"backend {backend!r} is unknown; expected one of {', '.join(BACKENDS)}")
        if control_mode not in CONTROL_MODES:
            raise ValueError(f"control_mode {control_mode!r} must be one of {', '.join(CONTROL_MODES)}")
        check_control_freq(control_freq)
        if reward_type not in REWARD_TYPES:
            choices = ", ".join(map(repr, REWARD_TYPES))
            raise ValueError(f"reward_type {reward_type!r} must be one of {choices}")
        check_positive("distance_threshold", distance_threshold, "m")
        if cartesian_lead is not None and not isinstance(cartesian_lead, bool):
            raise ValueError(f"cartesian_lead {cartesian_lead!r} must be true, false or None (the class's)")
        sizes = (("width", width, rendering.MAX_WIDTH), ("height", height, rendering.MAX_HEIGHT))
        for name, pixels, most in sizes:
            whole = isinstance(pixels, numbers.Integral) and not isinstance(pixels, bool)
            if not whole or not 1 <= pixels <= most:
                raise ValueError(
                    f"{name} {pixels!r} must be a whole number of pixels from 1 to {most} "
                    "(the scene's offscreen framebuffer)"
                )
        if backend_options is not None and not isinstance(backend_options, Mapping):
            raise ValueError(f"backend_options {backend_options!r} must be a dict of the backend's options")
        if render_mode is not None:
            rendering.prepare(render_mode)  # before the backend imports MuJoCo
        self.control_mode = control_mode
        self._field_lost = False  # the last step's stall was the field watch's
        if cartesian_lead is not None:  # else the class's
            self.cartesian_lead = bool(cartesian_lead)
        if cartesian_step is not None:  # else the class's
            self.cartesian_step = check_cartesian_step(cartesian_step)
        self.control_freq = float(control_freq)
        self.dt = 1.0 / self.control_freq
        self.reward_type = reward_type
        self.distance_threshold = float(distance_threshold)
        self.randomization = DomainRandomization.coerce(randomization)
        self.render_mode = render_mode
        self.metadata = {**self.metadata, "render_fps": round(self.control_freq)}
        if isinstance(backend, Backend):
            self.backend = backend
        else:
            cfg = config if isinstance(config, ArmConfig) else load_config(config)
            self.backend = make_backend(backend, cfg, **(backend_options or {}))
        self.config = self._arm_config(self.backend.config)
        if control_mode == "cartesian":
            self.config = coordinated(self.config)
        self.arm = Arm(self.backend, self.config)
        joint_cfgs = [self.config.joint(n) for n in self.joint_names]
        self._lo = np.array([j.min for j in joint_cfgs])
        self._hi = np.array([j.max for j in joint_cfgs])
        self._action_map = ActionMap.for_joints(
            control_mode, joint_cfgs, self.dt, self.cartesian_step, self.limit_margin, self.cartesian_lead
        )
        self.command_low, self.command_high = self._action_map.low, self._action_map.high
        self.command_low.flags.writeable = self.command_high.flags.writeable = False
        self._vmax = self._action_map.max_velocity
        self._amax = self._action_map.max_acceleration
        g = self.config.gripper
        self._width_lo, self._width_hi = g.min, g.max
        n_act = len(self.joint_names) + int(self.uses_gripper)
        self.action_space = spaces.Box(-1.0, 1.0, shape=(n_act,), dtype=np.float32)
        self.observation_space = self._make_observation_space()
        self.goal = np.zeros(3)
        # The joints and TCP as the arm reports them: what the task draws its goals from and the world
        # (a kinematic block, the peg) follows. The observation's _q and _tcp add the sensor noise.
        self._q_arm = np.zeros(len(self.joint_names))
        self._tcp_arm = kinematics.forward(self._q_arm)
        self._q = self._q_arm
        self._qd = np.zeros(len(self.joint_names))
        self._tcp = self._tcp_arm
        self._width = self.config.gripper.backup_init_pos
        self._latency: deque[np.ndarray] = deque()
        self._latency_steps = 0
        self._physics = PhysicsRandomizer(self.randomization)
        self._snapshot: Any = None
        self._bus_at_reset: dict[str, dict[str, int]] = {}
        self._was_reset = False
        self._closed = False
        self._noise_rng = np.random.default_rng(0)
        self._view = None if render_mode is None else rendering.ArmView(render_mode, width, height)

    # ------------------------------------------------------------ public
    @property
    def sim(self) -> Any:
        """The backend's MuJoCo arm (``None`` on mock and hardware)."""
        return self.backend.sim

    @property
    def joint_range(self) -> list[list[float]]:
        """``[min, max]`` of each joint (rad, m for j2): what ``joint_pos`` scales to [-1, 1]."""
        return [[float(lo), float(hi)] for lo, hi in zip(self._lo, self._hi, strict=True)]

    @property
    def command_mode(self) -> CommandMode:
        """The joint command interface the control mode uses (position for cartesian)."""
        return JOINT_MODE[self.control_mode]

    def bring_up(self, observer: PhaseObserver | None = None) -> None:
        """Make the arm ready to take the policy's commands; each step only if needed.

        Configure, activate, home the joints not yet homed (through the home
        command interface, in simulation too) and claim :attr:`command_mode`
        on every joint the policy commands. ``reset`` calls it when the arm
        is not active or a joint is not homed.

        Args:
            observer: Told when each step (configure, activate, home) starts and ends.

        Raises:
            JointError: A step failed (see :meth:`~bioscara_gym.hardware.arm.Arm.bring_up`).
        """
        self.arm.bring_up(self.command_mode, self.joint_names, observer)

    def shut_down(self, observer: PhaseObserver | None = None) -> float | None:
        """End the session in order: joints disabled (gripper width saved), disconnected, bus closed.

        The env cannot step afterwards. See :meth:`~bioscara_gym.hardware.arm.Arm.shut_down`.

        Args:
            observer: Told each step (deactivate, cleanup).

        Returns:
            The gripper's width after deactivating, m (``None`` if the arm was not active).

        Raises:
            JointError: A joint's disable was not acknowledged; call :meth:`safe_stop`.
        """
        return self.arm.shut_down(observer)

    def safe_stop(self) -> SafeStopReport:
        """End the session after a failure: every joint stopped and disabled whatever its flags say.

        See :func:`~bioscara_gym.hardware.safety.safe_stop`. The env cannot step afterwards.
        """
        return self.arm.safe_stop()

    def tcp_position(self) -> np.ndarray:
        """TCP position (m) from the measured joints, as on the real arm."""
        return self._tcp.copy()

    def _arm_config(self, config: ArmConfig) -> ArmConfig:
        """Hook: the configuration the task runs the arm with (default: the backend's as it is).

        Whatever it changes reaches the joints as the arm's own settings do
        (limits and stall sensitivity are sent when the arm is enabled).
        """
        return config

    # ------------------------------------------------------------ spaces
    def _make_observation_space(self) -> spaces.Dict:
        inf = np.inf
        size = max(s.stop for s in self.OBS_SLICES.values())
        return spaces.Dict(
            {
                "observation": spaces.Box(-inf, inf, shape=(size,), dtype=np.float64),
                "achieved_goal": spaces.Box(-inf, inf, shape=(3,), dtype=np.float64),
                "desired_goal": spaces.Box(-inf, inf, shape=(3,), dtype=np.float64),
            }
        )

    # ------------------------------------------------------------ episodes
    def reset(
        self, *, seed: int | None = None, options: dict[str, Any] | None = None
    ) -> tuple[dict[str, np.ndarray], dict[str, Any]]:
        """Start an episode: bring the arm up (homing the first time), pose it, sample a goal.

        In simulation every episode starts from the same snapshot of physics
        and firmware taken right after homing (the arm at rest, nothing left
        over from the previous episode), then the episode's physics is drawn
        and the joints are placed at its start pose; so a seed always gives
        the same episode. The arm homes under the nominal physics (seen: it
        homed under the first episode's draw, which the snapshot then carried
        into every episode, so a seed's episode depended on the first seed).

        Raises:
            ValueError: ``options`` given: none are taken.
            gymnasium.error.ClosedEnvironmentError: The env was closed.
        """
        self._check_open()
        if options:  # seen: {"goal": [...]} taken silently, and a random goal drawn
            why = "an episode's start and goal come from the seed"
            raise ValueError(f"reset options {options!r} are not taken: {why}")
        super().reset(seed=seed)
        if self.sim is not None:
            self._physics.nominal(self.sim.model)
        if self.arm.state is not Lifecycle.ACTIVE or not all(
            self.arm.joints[n].is_homed() for n in self.joint_names
        ):
            self.bring_up()
        if self.sim is not None:
            if self._snapshot is None:
                self._snapshot = self.sim.snapshot()
            self.sim.restore(self._snapshot)
        self._randomize()
        if self.sim is not None:
            # The drives' PID-error jitter: a stream of its own, so it does not change the tasks.
            self.sim.seed_drives(int(self._noise_rng.integers(2**63)))
        self._hold()
        self._move_to(self._random_pose())
        self.arm.read()
        self._measure()
        self._action_map.elbow = 1.0 if self._q[2] >= 0 else -1.0
        self.goal = self._sample_goal()
        self._bus_at_reset = self._bus_totals()
        self._was_reset = True
        obs = self._get_obs()
        return obs, self._get_info(obs)

    def step(self, action: np.ndarray) -> tuple[dict[str, np.ndarray], float, bool, bool, dict[str, Any]]:
        """Command the arm for one control period and observe the result.

        Raises:
            ValueError: The action has the wrong shape, is not real numbers or
                holds NaN or infinity.
            gymnasium.error.ResetNeeded: Not reset yet, or the arm is not active
                (the last episode ended on a stall).
            gymnasium.error.ClosedEnvironmentError: The env was closed.
        """
        self._check_open()
        given = np.asarray(action)
        if given.dtype.kind not in "iuf":  # seen: a complex action lost its imaginary part with a warning
            raise ValueError(f"action of dtype {given.dtype} must be real numbers")
        action = given.astype(np.float64, copy=False)
        if action.shape != self.action_space.shape:
            raise ValueError(f"action shape {action.shape} != expected {self.action_space.shape}")
        if not np.all(np.isfinite(action)):
            raise ValueError(f"action {action} holds NaN or infinity")
        if not self._was_reset:
            raise gym.error.ResetNeeded("call reset() before step()")
        if self.arm.state is not Lifecycle.ACTIVE:
            raise gym.error.ResetNeeded(
                f"the arm is {self.arm.state.value} (the episode ended on a stall); call reset()"
            )
        stalled, stalled_joint = self._cycle(action)
        self._measure()
        obs = self._get_obs()
        info = self._get_info(obs, stalled, stalled_joint)
        reward = float(self.compute_reward(obs["achieved_goal"], obs["desired_goal"], info))
        if stalled:
            reward += self.stall_penalty
        if self.render_mode == "human":
            self.render()
        return obs, reward, stalled, False, info

    # ------------------------------------------------------ reset, in order
    def _randomize(self) -> None:
        """Draw the episode's latency and physics; seed the sensor noise."""
        # Streams of their own, seeded by one draw whatever the settings, so turning
        # noise or latency on does not change the tasks. (Drawing the latency from
        # np_random did: integers(0, 1) takes no bits from it, integers(0, 4) does.)
        seed = int(self.np_random.integers(2**63))
        self._noise_rng = np.random.default_rng(seed)
        latency_rng = np.random.default_rng((seed, 1))
        self._latency_steps = int(latency_rng.integers(0, self.randomization.latency_steps + 1))
        self._latency.clear()
        if self.sim is not None:
            self._physics.randomize(self.sim.model, self.np_random)

    def _hold(self) -> None:
        """Command the joints to stay and the gripper to its start width."""
        for name in self.joint_names:
            hold = 0.0 if self.command_mode is CommandMode.VELOCITY else self.arm.commands[name]
            self.arm.set_command(name, hold)
        width0 = self.config.gripper.backup_init_pos
        self.arm.set_gripper(width0)
        self.arm.gripper.set_position(width0)

    def _random_pose(self) -> np.ndarray:
        """Hook: the episode's start pose for j1..j4 (default: uniform in the command range)."""
        return self.np_random.uniform(self.command_low, self.command_high)

    def _move_to(self, pose: np.ndarray) -> None:
        """Put the arm at ``pose``: teleported in simulation, driven on hardware."""
        if self.sim is not None:
            self.sim.set_joint_state(dict(zip(self.joint_names, pose, strict=True)))
            for name in self.joint_names:  # no real joint jumps: the drivers must not take it for noise
                self.arm.joints[name].forget_position()
            self.arm.forget_motion()  # nor for a rotor left behind its field
            return
        self.arm.move_to(dict(zip(self.joint_names, map(float, pose), strict=True)), period_s=self.dt)

    def _sample_goal(self) -> np.ndarray:
        """Hook: the episode's goal (m), the arm measured at its start pose; places the task's objects."""
        raise NotImplementedError

    # ------------------------------------------------------- step, in order
    def _cycle(self, action: np.ndarray) -> tuple[bool, str | None]:
        """Set ``action`` and run one control cycle: whether a joint stalled, and which if known.

        The stalled joint is the :class:`StalledError`'s ``joint``, else the
        first whose state flags STALL. A stall stops every joint (the arm is
        deactivated), as on the arm; so does a rotor the arm's field watch
        saw fall behind its field (:class:`FieldLostError`, ``info["field_lost"]``).
        """
        stalled, joint = False, None
        self._field_lost = False
        try:
            self._set_action(action)
            self.arm.cycle(self.dt)
        except StalledError as e:
            stalled, joint = True, e.joint
            self._field_lost = isinstance(e, FieldLostError)
        if joint is None:
            for name in self.joint_names:
                if self.arm.joint_states[name].flags & Flag.STALL:
                    stalled, joint = True, name
                    break
        if stalled and self.arm.state is Lifecycle.ACTIVE:
            self.arm.deactivate()
        if self.arm.state is not Lifecycle.ACTIVE:
            with contextlib.suppress(JointError):
                self.arm.read()
        return stalled, joint

    def _set_action(self, action: np.ndarray) -> None:
        """Hook: clip ``action``, delay it (latency randomization), set the joint and gripper commands."""
        a = np.clip(action, -1.0, 1.0)
        if self._latency_steps:
            self._latency.append(a)
            # Until the first command has come through the delay line, hold the arm.
            ready = len(self._latency) > self._latency_steps
            a = self._latency.popleft() if ready else self._neutral_action()
        cmds = self._action_map.commands(a, self._q, self._tcp, self._qd, self.arm.cycle_bus_s)
        for name, value in zip(self.joint_names, cmds, strict=True):
            self.arm.set_command(name, float(value))
        if self.uses_gripper:
            self.arm.set_gripper(float(to_range(float(a[-1]), self._width_lo, self._width_hi)))

    def _neutral_action(self) -> np.ndarray:
        """The action that holds the arm where it is."""
        a = np.zeros(self.action_space.shape, dtype=np.float32)
        a[: len(self.joint_names)] = self._action_map.neutral(self._q)
        return a

    def _measure(self) -> None:
        """Read the joints, the gripper and the TCP; the observation's copy with sensor noise, if randomized.

        The noise is the sensor's: what the policy observes and the cartesian
        controller acts on. The goals are drawn from, and the world follows,
        the joints as the arm reports them (seen: noise of 0.5 rad on the
        reading left PickPlace's draw of the block looking forever for a j1
        in range, and Reach's refused its range ``high < low``).
        """
        states = self.arm.joint_states
        for i, name in enumerate(self.joint_names):
            st = states[name]
            self._q_arm[i] = st.position
            self._qd[i] = st.velocity
        # A stall refused by a write has run the arm's on-error transition, which
        # disconnects the gripper: its width stays the last one read.
        if self.arm.gripper.is_initialized:
            self._width = self.arm.gripper.get_position()
        self._tcp_arm = kinematics.forward(self._q_arm)  # once per step; observations reuse it
        noise = self.randomization.sensor_noise
        if noise:
            self._q = self._q_arm + self._noise_rng.normal(0.0, noise, size=self._q_arm.shape)
            self._tcp = kinematics.forward(self._q)
        else:
            self._q, self._tcp = self._q_arm, self._tcp_arm

    def _joint_obs(self) -> np.ndarray:
        """The arm's part of the observation: ``OBS_SLICES`` joint_pos, joint_vel, gripper, tcp."""
        q_n = to_unit(self._q, self._lo, self._hi)
        qd_n = self._qd / self._vmax
        w_n = to_unit(self._width, self._width_lo, self._width_hi)
        return np.concatenate((q_n, qd_n, (w_n,), self.tcp_position()))

    def _get_obs(self) -> dict[str, np.ndarray]:
        """Hook: the observation dict (``observation`` laid out as ``OBS_SLICES``)."""
        raise NotImplementedError

    # ---------------------------------------------------------- goal logic
    def _is_success(self, achieved: np.ndarray, desired: np.ndarray) -> np.ndarray:
        """Hook: whether ``achieved`` lies within ``distance_threshold`` of ``desired``."""
        return np.linalg.norm(achieved - desired, axis=-1) < self.distance_threshold

    def compute_reward(
        self, achieved_goal: np.ndarray, desired_goal: np.ndarray, info: Any
    ) -> np.ndarray | float:
        """Reward for (batches of) goals, vectorized for HER.

        Dense: minus the distance in m. Sparse: 0 within ``distance_threshold``,
        else -1. Log: ``-log(1 + distance / distance_threshold)``, dense and
        steepest at the goal: a millimetre there is worth as much as a
        centimetre 10 cm away, so a critic resolves the last centimetre that
        success is judged on. The stall penalty is added by :meth:`step`, not here.
        """
        achieved, desired = self._goal_pair(achieved_goal, desired_goal)
        d = np.linalg.norm(achieved - desired, axis=-1)
        if self.reward_type == "sparse":  # a NaN distance is no success: -1, as _is_success says
            return (d < self.distance_threshold).astype(np.float64) - 1.0
        if self.reward_type == "log":
            return -np.log1p(d / self.distance_threshold)
        return -d

    def _goal_pair(self, achieved: Any, desired: Any) -> tuple[np.ndarray, np.ndarray]:
        """``achieved`` and ``desired`` as arrays (their own dtype: HER's float32 batches stay so), checked.

        Raises:
            ValueError: Either's last dimension is not the goal's width.
        """
        width = self.observation_space["desired_goal"].shape[-1]
        pair = np.asarray(achieved), np.asarray(desired)
        for name, goal in zip(("achieved_goal", "desired_goal"), pair, strict=True):
            if goal.ndim == 0 or goal.shape[-1] != width:
                raise ValueError(f"{name} of shape {goal.shape}: this task's goals are {width} values each")
        return pair

    def _get_info(
        self, obs: dict[str, np.ndarray], stalled: bool = False, stalled_joint: str | None = None
    ) -> dict[str, Any]:
        """``is_success``, ``distance`` (m), ``stalled``, ``stalled_joint`` (if known), ``flags``, ``bus``.

        And ``field_lost``: the stall was the arm's field watch's, not the firmware's flag.
        ``bus`` (backends with a bus): per joint, :data:`BUS_COUNTERS` since the
        episode's reset and their ``error_rate``, so that a seed gives the same
        info (Gymnasium's ``check_env`` compares it); the totals since the
        backend was made are in ``backend.comm_stats()``.
        """
        achieved, desired = obs["achieved_goal"], obs["desired_goal"]
        info: dict[str, Any] = {
            "is_success": bool(self._is_success(achieved, desired)),
            "distance": float(np.linalg.norm(achieved - desired)),
            "stalled": stalled,
            "field_lost": stalled and self._field_lost,
            "flags": {n: int(self.arm.joint_states[n].flags) for n in self.joint_names},
        }
        if stalled_joint is not None:
            info["stalled_joint"] = stalled_joint
        totals = self._bus_totals()
        if totals:
            info["bus"] = {n: _since(counts, self._bus_at_reset.get(n)) for n, counts in totals.items()}
        return info

    def _bus_totals(self) -> dict[str, dict[str, int]]:
        """Each joint's :data:`BUS_COUNTERS` since the backend was made (none without a bus)."""
        stats = self.backend.comm_stats()
        return {n: {c: getattr(s, f"total_{c}") for c in BUS_COUNTERS} for n, s in stats.items()}

    # ------------------------------------------------------------ render
    def _scene(self) -> rendering.SceneState:
        """Hook: what a picture shows besides the simulation (goal marker, mirrored joints)."""
        return rendering.SceneState(
            goal=self.goal, joints=dict(zip(self.joint_names, self._q.tolist(), strict=True))
        )

    def render(self) -> np.ndarray | None:
        """An RGB image (``rgb_array``) or a window (``human``) of the arm."""
        self._check_open()
        if self._view is None:
            gym.logger.warn("render() called without a render_mode; pass render_mode='rgb_array'")
            return None
        return self._view.render(self.sim, self._scene())

    def close(self) -> None:
        """Shut the arm down (joints disabled) and release the renderer; the env is then done."""
        self._closed = True
        if self._view is not None:
            self._view.close()
        if self.arm.state is not Lifecycle.FINALIZED:
            self.arm.shutdown()

    def _check_open(self) -> None:
        """Refuse a closed env (seen: reset() after close() raised "cannot claim velocity ... finalized").

        Raises:
            gymnasium.error.ClosedEnvironmentError: :meth:`close` was called.
        """
        if self._closed:
            raise gym.error.ClosedEnvironmentError(f"{type(self).__name__} is closed; make a new env")


def _since(counts: dict[str, int], start: dict[str, int] | None) -> dict[str, float]:
    """``counts`` less those at ``start`` (none: from zero), with the errors per transaction."""
    since: dict[str, float] = {c: counts[c] - (start or {}).get(c, 0) for c in BUS_COUNTERS}
    since["error_rate"] = since["errors"] / since["transactions"] if since["transactions"] else 0.0
    return since
