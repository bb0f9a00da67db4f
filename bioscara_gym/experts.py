"""Scripted experts: analytic SCARA inverse kinematics and a joint-space controller.

They act through the tasks' own action spaces, from observations only (plus
the arm's configuration), so they run on every backend like a policy would.
They prove the tasks solvable and are the baselines trained policies are
compared against (``bioscara eval --expert``). Each task names its experts in
:data:`bioscara_gym.tasks.TASKS`; :func:`expert_for` and
:func:`observation_expert_for` look them up there.

The scripted :class:`PickPlaceExpert` keeps a phase (approach, descend,
squeeze, carry), a squeeze counter and the elbow chosen per phase, so its
action is not a function of the observation alone and it cannot label a
state it did not reach itself. :class:`ObservationExpert` is the same
controller with that state read from the observation: the phase from where
the block is relative to the TCP and whether the gripper is commanded closed
(the observation holds the commanded width), the squeeze counter replaced by
closing in steps (the width itself counts them), and the elbow kept by a
switching cost instead of a memory (:meth:`JointSpaceController.solve`). Its
phase tests have tolerances, so a learner's inexact gripper output does not
flip the phase. DAgger labels the learner's states with it
(``training/dagger.py``), and ``bioscara collect --expert`` records it.
"""

from __future__ import annotations

import math
from collections.abc import Mapping

import numpy as np

from bioscara_gym import kinematics
from bioscara_gym.envs.actions import WRIST_STEP, to_range, to_unit
from bioscara_gym.envs.base import BioscaraEnv
from bioscara_gym.envs.insert import INSERT_DEPTH, PEG_TIP_BELOW_TCP
from bioscara_gym.envs.pick_place import BLOCK_SIZE, BioscaraPickPlaceEnv
from bioscara_gym.envs.push import PUSH_Z
from bioscara_gym.envs.stack import Z_TOL as STACK_Z_TOL
from bioscara_gym.tasks import Expert, task_of

#: Fraction of the braking-limited speed the controller asks for (the firmware
#: ramps every command with the joint's max acceleration).
BRAKE_MARGIN = 0.8
#: Proportional gain near the goal, 1/s.
GAIN = 8.0
#: :meth:`JointSpaceController.solve`'s cost of the other elbow by default: taken only if
#: the preferred one cannot reach.
ELBOW_REFUSED = 1e6


class JointSpaceController:
    """Drives joints to targets through an env's action space.

    Args:
        env: The (unwrapped) Bioscara env whose action space is used.
    """

    def __init__(self, env: BioscaraEnv) -> None:
        """Read limits and the control mode from ``env``."""
        self.env = env
        cfgs = [env.config.joint(n) for n in env.joint_names]
        self.lo = np.array([c.min for c in cfgs])
        self.hi = np.array([c.max for c in cfgs])
        self.vmax = np.array([c.max_velocity for c in cfgs])
        # Targets must lie where the env lets commands go (clear of the end stops).
        self.cmd_lo, self.cmd_hi = env.command_low, env.command_high
        self.amax = np.array([c.max_acceleration for c in cfgs])
        self._joint_pos = env.OBS_SLICES["joint_pos"]

    def joints(self, observation: np.ndarray) -> np.ndarray:
        """Measured joint positions from the normalized ``observation`` vector."""
        return to_range(observation[self._joint_pos], self.lo, self.hi)

    def action(self, q: np.ndarray, q_target: np.ndarray) -> np.ndarray:
        """Joint part of the action that moves ``q`` toward ``q_target``."""
        if self.env.control_mode == "position":
            return np.clip(to_unit(q_target, self.cmd_lo, self.cmd_hi), -1.0, 1.0)
        e = q_target - q
        speed = np.minimum.reduce(
            [self.vmax, BRAKE_MARGIN * np.sqrt(2.0 * self.amax * np.abs(e)), GAIN * np.abs(e)]
        )
        return np.clip(np.sign(e) * speed / self.vmax, -1.0, 1.0)

    def cartesian_action(
        self, tcp: np.ndarray, xyz: np.ndarray, q4: float, q4_target: float, q: np.ndarray | None = None
    ) -> np.ndarray:
        """Cartesian-mode action moving the TCP to ``xyz`` and the wrist to ``q4_target``.

        With the measured joints ``q``, the step is shortened so that no joint
        asks for more speed than it can brake from before the target (as
        :meth:`action` does in velocity mode): the env keeps the speed a step
        asks (its targets lead by the braking distance), so the braking is the
        controller's.
        """
        a = np.clip(
            np.append((xyz - tcp) / np.asarray(self.env.cartesian_step), (q4_target - q4) / WRIST_STEP),
            -1.0,
            1.0,
        )
        if q is None or not self.env.cartesian_lead:
            return a
        goal = kinematics.inverse(xyz, 1.0 if q[2] >= 0 else -1.0)
        step = kinematics.inverse(
            tcp + a[:3] * np.asarray(self.env.cartesian_step), 1.0 if q[2] >= 0 else -1.0
        )
        if goal is None or step is None:
            return a
        e = np.append(np.asarray(goal) - q[:3], q4_target - q4)
        asked = np.abs(np.append(np.asarray(step) - q[:3], a[3] * WRIST_STEP)) / self.env.dt
        allowed = np.minimum(self.vmax, BRAKE_MARGIN * np.sqrt(2.0 * self.amax * np.abs(e)))
        with np.errstate(divide="ignore", invalid="ignore"):
            scale = np.where(asked > 1e-9, allowed / asked, np.inf)
        return a * min(1.0, float(np.min(scale)))

    def toward(self, q: np.ndarray, tcp: np.ndarray, xyz: np.ndarray, q4_target: float) -> np.ndarray:
        """Joint part of the action moving the TCP toward ``xyz`` and the wrist to ``q4_target``, in any mode.

        Cartesian mode: :meth:`cartesian_action`, braking for ``xyz``. Velocity
        and position modes: toward the IK solution of ``xyz`` with the arm's own
        elbow (the joints held where there is none).
        """
        if self.env.control_mode == "cartesian":
            return self.cartesian_action(tcp, xyz, q[3], q4_target, q)
        target = self.solve(xyz, q, 1.0 if q[2] >= 0 else -1.0)
        target = q.copy() if target is None else target
        target[3] = q4_target
        return self.action(q, target)

    def solve(
        self, xyz: np.ndarray, q: np.ndarray, elbow: float | None = None, switch_cost: float = ELBOW_REFUSED
    ) -> np.ndarray | None:
        """IK for the TCP at ``xyz`` within the commandable range: the solution reached soonest.

        Each elbow's solution costs its slowest joint's travel time (travel
        over max velocity), ties (e.g. both wait for the slow lift) broken by
        a tenth of the total; the elbow other than ``elbow`` costs
        ``switch_cost`` more.

        Args:
            xyz: TCP target in m.
            q: Current joint positions.
            elbow: Preferred sign of j3; ``None``: no preference.
            switch_cost: Extra cost, s, of the other elbow. The default
                (:data:`ELBOW_REFUSED`) takes it only where the preferred one
                cannot reach; :class:`ObservationExpert` charges a fraction of
                a second, so it changes elbow only for a much shorter path.

        Returns:
            j1..j4 targets (j4 kept at ``q[3]``), or ``None`` if unreachable.
        """
        best, best_cost = None, math.inf
        for sign in (1.0, -1.0):
            sol = kinematics.inverse(xyz, sign)
            if sol is None:
                continue
            cand = np.array([sol[0], sol[1], sol[2], q[3]])
            if np.any(cand[:3] < self.cmd_lo[:3]) or np.any(cand[:3] > self.cmd_hi[:3]):
                continue
            travel = np.abs(cand[:3] - q[:3]) / self.vmax[:3]
            cost = float(np.max(travel) + 0.1 * np.sum(travel))
            if elbow is not None and sign != elbow:
                cost += switch_cost
            if cost < best_cost:
                best, best_cost = cand, cost
        return best


class ReachExpert:
    """Moves the TCP to the desired goal: IK once per step, joint-space control."""

    def __init__(self, env: BioscaraEnv) -> None:
        """Bind to ``env`` (use ``env.unwrapped``)."""
        self.ctrl = JointSpaceController(env)
        self.reset()

    def reset(self) -> None:
        """Forget the elbow chosen for the last goal."""
        self._goal: np.ndarray | None = None
        self._elbow: float | None = None

    def __call__(self, obs: dict[str, np.ndarray]) -> np.ndarray:
        """Action for ``obs``."""
        q = self.ctrl.joints(obs["observation"])
        goal = obs["desired_goal"]
        if self.ctrl.env.control_mode == "cartesian":
            return self.ctrl.cartesian_action(obs["achieved_goal"], goal, q[3], q[3], q).astype(np.float32)
        if self._goal is None or not np.array_equal(goal, self._goal):
            first = self.ctrl.solve(goal, q)
            self._elbow = None if first is None else (1.0 if first[2] >= 0 else -1.0)
            self._goal = goal.copy()
        target = self.ctrl.solve(goal, q, self._elbow)
        if target is None:
            target = q
        return self.ctrl.action(q, target).astype(np.float32)


class PickPlaceExpert:
    """Approach above the block, descend, squeeze, carry to the target."""

    #: Opening (m) while approaching and squeezing.
    OPEN = 0.075
    CLOSED = 0.04
    #: TCP height when grasping: fingertips 5 mm above the table (j2's soft limit
    #: keeps commands 2 mm above its lower end stop at -1.6 mm).
    GRASP_Z = kinematics.TCP_Z0 + 0.005
    #: Control steps to wait while the fingers close.
    SQUEEZE_STEPS = 8
    #: The carried block's lift above the table (m) until it is within ``LOWER_M``
    #: (horizontally) of a target on the table: dragged along the table, the block
    #: pressed on by the gripper took more than j1's force at 20 % current (the
    #: velocity-mode expert's j1 lost its field so in 1 of 20 episodes).
    CARRY_LIFT_M = 0.02
    LOWER_M = 0.01

    def __init__(
        self, env: BioscaraEnv, slices: Mapping[str, slice] | None = None, carry_lift_m: float | None = None
    ) -> None:
        """Bind to ``env`` (use ``env.unwrapped``), observations laid out as ``slices`` (default its own).

        ``carry_lift_m`` replaces :attr:`CARRY_LIFT_M` (0: carry at the target's height).
        """
        self.env = env
        self.carry_lift_m = self.CARRY_LIFT_M if carry_lift_m is None else float(carry_lift_m)
        self.ctrl = JointSpaceController(env)
        g = env.config.gripper
        self._w_lo, self._w_hi = g.min, g.max
        self._slices = env.OBS_SLICES if slices is None else slices
        self.reset()

    def reset(self) -> None:
        """Start a new episode in the approach phase."""
        self.phase = "approach"
        self._elbow: float | None = None
        self._elbow_phase = ""
        self._squeeze = 0
        self._grip_offset = np.zeros(3)

    def _width_action(self, width: float) -> float:
        return to_unit(width, self._w_lo, self._w_hi)

    def _carry_to(self, block: np.ndarray, goal: np.ndarray, offset: np.ndarray) -> np.ndarray:
        """TCP target carrying the block (``offset`` from the TCP) to ``goal``: lifted until over it."""
        xyz = goal - offset
        if math.hypot(*(block[:2] - goal[:2])) > self.LOWER_M:
            xyz[2] = max(xyz[2], self.GRASP_Z + self.carry_lift_m)
        xyz[2] = max(xyz[2], self.GRASP_Z)
        return xyz

    def _wrist_for(self, q: np.ndarray, yaw: float) -> float:
        """j4 that squares the fingers (along tool y) to the block's faces."""
        base = yaw - q[0] - q[2] - math.pi / 2
        candidates = [base + k * math.pi / 2 for k in range(-6, 7)]
        lo, hi = self.ctrl.cmd_lo[3], self.ctrl.cmd_hi[3]
        valid = [c for c in candidates if lo <= c <= hi]
        return min(valid, key=lambda c: abs(c - q[3]))

    def __call__(self, obs: dict[str, np.ndarray]) -> np.ndarray:
        """Action for ``obs``."""
        o = obs["observation"]
        q = self.ctrl.joints(o)
        s = self._slices
        tcp, block, yaw = o[s["tcp"]], o[s["block_pos"]], float(o[s["block_yaw"]][0])
        goal = obs["desired_goal"]
        width = self.OPEN
        if self.phase == "approach":
            xyz = np.array([block[0], block[1], max(tcp[2], BLOCK_SIZE + 0.01)])
            if np.linalg.norm(tcp[:2] - block[:2]) < 0.003:
                self.phase = "descend"
        if self.phase == "descend":
            xyz = np.array([block[0], block[1], self.GRASP_Z])
            if abs(tcp[2] - self.GRASP_Z) < 0.002:
                self.phase = "squeeze"
        if self.phase == "squeeze":
            xyz = np.array([block[0], block[1], self.GRASP_Z])
            width = self.CLOSED
            self._squeeze += 1
            if self._squeeze >= self.SQUEEZE_STEPS:
                self.phase = "carry"
                self._grip_offset = block - tcp
        if self.phase == "carry":
            width = self.CLOSED
            xyz = self._carry_to(block, goal, self._grip_offset)
        if self.env.control_mode == "cartesian":
            q4_target = self._wrist_for(q, yaw) if self.phase in ("approach", "descend") else q[3]
            a = self.ctrl.cartesian_action(tcp, xyz, q[3], q4_target, q)
            return np.append(a, self._width_action(width)).astype(np.float32)
        if self.phase != self._elbow_phase:  # pick the elbow once per phase, then keep it
            first = self.ctrl.solve(xyz, q)
            self._elbow = None if first is None else (1.0 if first[2] >= 0 else -1.0)
            self._elbow_phase = self.phase
        target = self.ctrl.solve(xyz, q, self._elbow)
        if target is None:
            target = q.copy()
        if self.phase in ("approach", "descend"):
            target[3] = self._wrist_for(target, yaw)
        else:
            target[3] = q[3]
        a = self.ctrl.action(q, target)
        return np.append(a, self._width_action(width)).astype(np.float32)


class ObservationExpert(PickPlaceExpert):
    """The PickPlace expert as a function of the observation (see the module docstring).

    Phases, decided afresh every step:

    | phase    | when                                                       | does                          |
    |----------|------------------------------------------------------------|-------------------------------|
    | carry    | gripper commanded fully closed, block between the fingers  | block to the target, lifted   |
    |          |                                                            | until over it (``_carry_to``) |
    | squeeze  | gripper closing, or open at grasp height over the block    | closes in ``SQUEEZE_LEVELS``  |
    | release  | gripper closed, block not between the fingers              | opens, as approach            |
    | descend  | open, within ``ALIGN_M`` of the block (``ALIGN_LOW_M`` low) | down to ``GRASP_Z``           |
    | approach | otherwise                                                  | above the block, wrist square |
    """

    #: Horizontal TCP-block distance (m) from which the gripper descends.
    ALIGN_M = 0.003
    #: The same while already below the approach height (no lift for a small drift).
    ALIGN_LOW_M = 0.008
    #: Block between the fingers: horizontal offset (m) and vertical range of block minus TCP.
    HOLD_XY_M = 0.008
    HOLD_Z_M = (-0.005, 0.012)
    #: Gripper action (unit) within which the width counts as open, and as closed: a
    #: learner's gripper output is never exact, and a phase must not flip on its last digit.
    WIDTH_TOL = 0.15
    CLOSED_TOL = 0.03
    #: Gripper actions of the squeeze, one a step (-1 is 0.04 m, fully closed): the width
    #: itself counts the steps, in steps a learner can tell apart (the scripted expert
    #: waits 8 steps, measured enough from 3).
    SQUEEZE_LEVELS = (-0.4, -0.7, -0.9)
    #: TCP height (m) within which the gripper counts as at grasp height.
    GRASP_TOL_M = 0.003
    #: Cost (s of the slowest joint's travel) of changing elbow.
    ELBOW_SWITCH_S = 0.3

    def __init__(
        self, env: BioscaraEnv, slices: Mapping[str, slice] | None = None, carry_lift_m: float | None = None
    ) -> None:
        """Bind to ``env`` (use ``env.unwrapped``); see :class:`PickPlaceExpert`."""
        super().__init__(env, slices, carry_lift_m)
        self._u_open = self._width_action(self.OPEN)
        self._u_closed = self._width_action(self.CLOSED)

    def _squeeze_step(self, width: float) -> float:
        """The next gripper action of the squeeze: the first of ``SQUEEZE_LEVELS`` below ``width`` by 0.1."""
        return next((level for level in self.SQUEEZE_LEVELS if level < width - 0.1), self._u_closed)

    def phase_of(self, obs: dict[str, np.ndarray]) -> str:
        """The phase ``obs`` is in (see the class docstring)."""
        o, s = obs["observation"], self._slices
        tcp, block = o[s["tcp"]], o[s["block_pos"]]
        width = float(o[s["gripper"]][0])
        d = block - tcp
        xy = math.hypot(d[0], d[1])
        held = xy < self.HOLD_XY_M and self.HOLD_Z_M[0] < d[2] < self.HOLD_Z_M[1]
        if width <= self._u_closed + self.CLOSED_TOL:
            return "carry" if held else "release"
        if width < self._u_open - self.WIDTH_TOL:  # closing
            return "squeeze" if held else "release"
        if abs(tcp[2] - self.GRASP_Z) < self.GRASP_TOL_M and xy < self.ALIGN_M:
            return "squeeze"
        low = tcp[2] < BLOCK_SIZE + 0.01 - 0.002
        if xy < self.ALIGN_M or (low and xy < self.ALIGN_LOW_M):
            return "descend"
        return "approach"

    def __call__(self, obs: dict[str, np.ndarray]) -> np.ndarray:
        """Action for ``obs``."""
        o = obs["observation"]
        q = self.ctrl.joints(o)
        s = self._slices
        tcp, block, yaw = o[s["tcp"]], o[s["block_pos"]], float(o[s["block_yaw"]][0])
        phase = self.phase = self.phase_of(obs)
        width_u = self._u_open
        if phase in ("approach", "release"):
            xyz = np.array([block[0], block[1], max(tcp[2], BLOCK_SIZE + 0.01)])
        elif phase == "descend":
            xyz = np.array([block[0], block[1], self.GRASP_Z])
        elif phase == "squeeze":
            xyz = np.array([block[0], block[1], self.GRASP_Z])
            width_u = self._squeeze_step(float(o[s["gripper"]][0]))
        else:  # carry
            width_u = self._u_closed
            xyz = self._carry_to(block, obs["desired_goal"], block - tcp)
        if self.env.control_mode == "cartesian":
            q4_target = self._wrist_for(q, yaw) if phase in ("approach", "descend") else q[3]
            a = self.ctrl.cartesian_action(tcp, xyz, q[3], q4_target, q)
            return np.append(a, width_u).astype(np.float32)
        elbow = 1.0 if q[2] >= 0 else -1.0  # the arm's own: kept unless the other is much shorter
        target = self.ctrl.solve(xyz, q, elbow, switch_cost=self.ELBOW_SWITCH_S)
        target = q.copy() if target is None else target
        if phase in ("approach", "descend", "release"):
            target[3] = self._wrist_for(target, yaw)
        else:
            target[3] = q[3]
        return np.append(self.ctrl.action(q, target), width_u).astype(np.float32)


class PushExpert:
    """Pushes the block to the target with the closed gripper, from the observation alone.

    In the frame of the push (``u`` from the block to the target, ``v`` to its
    left; ``s``, ``t`` the TCP's coordinates from the block's centre, and
    ``phi`` its bearing from straight behind the block), decided afresh every
    step, so it labels any state (DAgger) and is its own observation expert:

    | phase | when                                               | TCP target                               |
    |-------|----------------------------------------------------|------------------------------------------|
    | push  | behind (``s <= -PUSH_S``), ``abs(t) < BACK_OFF_M`` | on along ``u`` as far as the block has   |
    |       |                                                    | to go (``abs(t) <= ALIGN_M``), or back   |
    |       |                                                    | to the orbit's point behind the block    |
    |       |                                                    | (``BACK_OFF_M``), blended between; and   |
    |       |                                                    | back onto the line                       |
    | orbit | otherwise                                          | round the block on a circle of           |
    |       |                                                    | ``ORBIT_M`` toward straight behind it,   |
    |       |                                                    | ``ORBIT_RAD`` ahead                      |
    | hold  | the block within ``DONE_M`` of the target           | ``STANDOFF_M`` from the block, on the    |
    |       |                                                    | side the TCP is                          |

    The orbit is one continuous field: its target turns into the point
    straight behind the block as ``phi`` goes to 0, where the push begins.
    It goes round the side the TCP is on, or the other where that side
    leaves the arm's reach. The wrist keeps the pushing face (the tool's x
    axis) along ``u`` (in ``hold``, toward the block); the fingertips stay
    at :data:`~bioscara_gym.envs.push.PUSH_Z`. Each step asks for
    ``STEP_GAIN`` of the way to the target, cut to ``WAYPOINT_M``
    (``PUSH_STEP_M`` pushing) along its line, so every control mode follows
    the planned lines; in cartesian mode the step then brakes for it as the
    other experts' do (:meth:`JointSpaceController.cartesian_action`).
    """

    #: Behind the block from here (m) the TCP pushes when on the line.
    PUSH_S = 0.02
    #: Off the line by at most this much (m), the TCP pushes (and steers back onto it):
    #: the pusher is 6 cm wide, the block 3 cm.
    ALIGN_M = 0.01
    #: Off the line by this much (m), it backs off to the orbit's point behind the block
    #: (between the two, a blend of both).
    BACK_OFF_M = 0.03
    #: Radius (m) of the orbit round the block: the pusher's corner (3.2 cm from the TCP),
    #: half the block's diagonal (2.1 cm) and 1.2 cm to spare.
    ORBIT_M = 0.065
    #: How far ahead on the orbit the target lies, rad.
    ORBIT_RAD = 0.5
    #: The block counts as there within this distance of the target (m): stop pushing.
    DONE_M = 0.005
    #: Then the TCP steps back to this far from the block's centre (m), clear of it.
    STANDOFF_M = 0.06
    #: Longest TCP step (m) a control step asks for: the cartesian step, and the waypoint
    #: that keeps velocity and position control on the planned lines.
    WAYPOINT_M = 0.02
    #: The same while pushing: the block is met at up to 0.25 m/s.
    PUSH_STEP_M = 0.01
    #: Fraction of the way to the target asked for in one step: the arm lags its
    #: commands by about a step, and asking for all of it overshoots the line.
    STEP_GAIN = 0.5

    def __init__(self, env: BioscaraEnv) -> None:
        """Bind to ``env`` (use ``env.unwrapped``)."""
        self.env = env
        self.ctrl = JointSpaceController(env)
        self._slices = env.OBS_SLICES

    def reset(self) -> None:
        """Nothing to forget: the action is a function of the observation."""

    def phase_of(self, obs: dict[str, np.ndarray]) -> str:
        """The phase ``obs`` is in (see the class docstring)."""
        return self._plan(obs)[0]

    def _plan(self, obs: dict[str, np.ndarray]) -> tuple[str, np.ndarray, np.ndarray]:
        """Phase, TCP target (x, y) and the direction the pushing face should face."""
        o, s = obs["observation"], self._slices
        q = self.ctrl.joints(o)
        tcp, block = o[s["tcp"]][:2], o[s["block_pos"]][:2]
        e = obs["desired_goal"][:2] - block
        dist = math.hypot(e[0], e[1])
        rel = tcp - block
        if dist < self.DONE_M:  # there: step back from the block, so nothing nudges it on
            away = rel / max(math.hypot(rel[0], rel[1]), 1e-9)
            return "hold", block + self.STANDOFF_M * away, -away
        u = e / dist
        v = np.array([-u[1], u[0]])
        along, across = float(rel @ u), float(rel @ v)
        if along <= -self.PUSH_S and abs(across) < self.BACK_OFF_M:
            # On along the line as far as the block still has to go (whatever the pusher's
            # turn, it carries the block as far as it moves), and back onto the line; off
            # the line, back to the orbit's point behind the block instead, blended
            # (no edge for a learner to stall at).
            ahead = min(dist, self.PUSH_STEP_M / self.STEP_GAIN)
            off = min(max((abs(across) - self.ALIGN_M) / (self.BACK_OFF_M - self.ALIGN_M), 0.0), 1.0)
            forward = (1.0 - off) * ahead + off * (-self.ORBIT_M - along)
            return "push", tcp + forward * u - across * v, u
        phi = math.atan2(across, -along)  # 0: straight behind the block
        side = math.copysign(1.0, phi) if phi else 1.0
        for _ in range(2):
            near_way = math.copysign(1.0, phi) == side
            bearing = phi - side * (min(abs(phi), self.ORBIT_RAD) if near_way else self.ORBIT_RAD)
            xy = block + self.ORBIT_M * (-math.cos(bearing) * u + math.sin(bearing) * v)
            if self.ctrl.solve(np.array([xy[0], xy[1], PUSH_Z]), q) is not None:
                break
            side = -side  # round the other side: this one leaves the arm's reach
        return "orbit", xy, u

    def __call__(self, obs: dict[str, np.ndarray]) -> np.ndarray:
        """Action for ``obs``."""
        o = obs["observation"]
        q = self.ctrl.joints(o)
        tcp = o[self._slices["tcp"]]
        phase, xy, u = self._plan(obs)
        step = self.STEP_GAIN * (xy - tcp[:2])  # cut along its line, not per axis: the direction is the plan
        limit = self.PUSH_STEP_M if phase == "push" else self.WAYPOINT_M
        length = float(np.linalg.norm(step))
        if length > limit:
            step *= limit / length
        xyz = np.array([tcp[0] + step[0], tcp[1] + step[1], PUSH_Z])
        q4_target = q[3] if phase == "hold" else self._wrist_for(q, math.atan2(u[1], u[0]))
        return self.ctrl.toward(q, tcp, xyz, q4_target).astype(np.float32)

    def _wrist_for(self, q: np.ndarray, face: float) -> float:
        """j4 that turns the pushing face (the tool's x axis, either way) to ``face`` (rad), nearest q4."""
        base = face - q[0] - q[2]
        candidates = [base + k * math.pi for k in range(-3, 4)]
        lo, hi = self.ctrl.cmd_lo[3], self.ctrl.cmd_hi[3]
        valid = [c for c in candidates if lo <= c <= hi]
        return min(valid, key=lambda c: abs(c - q[3]))


class StackExpert:
    """Stacks the blocks with PickPlace's observation expert, a block at a time, from the observation.

    Decided afresh every step, so it labels any state (DAgger) and is its own
    observation expert:

    | phase | when                                                 | does                                  |
    |-------|------------------------------------------------------|---------------------------------------|
    | lower | the lower block more than ``PLACED_M`` from the target | ``ObservationExpert``: it to there  |
    | clear | it is there, gripper not open, the upper not held    | opens in place                        |
    | rise  | it is there, open, the fingertips below ``CLEAR_Z``   | straight up                           |
    |       | within ``NEAR_M`` of it, about to go to the upper    |                                       |
    | upper | otherwise, the upper block not on the lower one      | ``ObservationExpert``: it onto the    |
    |       |                                                      | lower, at ``CARRY_Z`` until over it,  |
    |       |                                                      | ``GUARD_M`` away until that high      |
    | done  | the upper block on the lower one                     | opens in place                        |

    ``ObservationExpert`` sees a PickPlace observation made of the chosen
    block's entries, and as its target the place the block is going to.
    """

    #: A block counts as in place within this horizontal distance (m) and ``Z_TOL`` in height.
    PLACED_M = 0.005
    #: ... and within this height of it (m): the task's own height tolerance.
    PLACED_Z = STACK_Z_TOL
    #: Fingertips 1 cm above the lower block's top before they leave it (PickPlace's approach height), m.
    CLEAR_Z = BLOCK_SIZE + 0.01
    #: The carried upper block's centre (m) until it is over the lower one: its bottom 5 mm over that top.
    CARRY_Z = 1.5 * BLOCK_SIZE + 0.005
    #: A carried block comes no nearer the lower one (m, horizontally) until it is at ``CARRY_Z``:
    #: 3 cm apart they touch, and the arm lags its commands.
    GUARD_M = 0.07
    #: The fingertips rise before leaving the lower block from within this distance of it (m).
    NEAR_M = BLOCK_SIZE + 0.02

    def __init__(self, env: BioscaraEnv) -> None:
        """Bind to ``env`` (use ``env.unwrapped``)."""
        self.env = env
        # It reads :meth:`_view`'s observations; the lower block slides to its target (carried
        # 1 cm clear, the learner did worse: README, the task table).
        self.pick = ObservationExpert(env, slices=BioscaraPickPlaceEnv.OBS_SLICES, carry_lift_m=0.0)
        self.ctrl = self.pick.ctrl
        self._slices = env.OBS_SLICES
        g = env.config.gripper
        self._u_open = to_unit(ObservationExpert.OPEN, g.min, g.max)
        self.phase = "lower"

    def reset(self) -> None:
        """Nothing to forget: the action is a function of the observation."""

    def _view(self, obs: dict[str, np.ndarray], which: str, target: np.ndarray) -> dict[str, np.ndarray]:
        """PickPlace's observation of the ``which`` block (``lower``, ``upper``), going to ``target``."""
        o, s = obs["observation"], self._slices
        pos = o[s[f"{which}_pos"]]
        own = (o[s[f"{which}_from_tcp"]], o[s[f"{which}_vel"]], o[s[f"{which}_yaw"]])
        parts = [o[: s["lower_pos"].start], pos, *own]
        return {"observation": np.concatenate(parts), "achieved_goal": pos, "desired_goal": target}

    @classmethod
    def _placed(cls, pos: np.ndarray, place: np.ndarray, tol: float) -> bool:
        """Whether ``pos`` is within ``tol`` of ``place`` horizontally and ``PLACED_Z`` in height."""
        return bool(math.hypot(*(pos[:2] - place[:2])) < tol and abs(pos[2] - place[2]) < cls.PLACED_Z)

    def phase_of(self, obs: dict[str, np.ndarray]) -> str:
        """The phase ``obs`` is in (see the class docstring)."""
        return self._plan(obs)[0]

    def _plan(self, obs: dict[str, np.ndarray]) -> tuple[str, dict[str, np.ndarray] | None]:
        """Phase, and the PickPlace view the observation expert acts on (``None``: this expert acts)."""
        o, s = obs["observation"], self._slices
        tcp, lower, upper = o[s["tcp"]], o[s["lower_pos"]], o[s["upper_pos"]]
        target = obs["desired_goal"][:3]
        if not self._placed(lower, target, self.PLACED_M):
            return "lower", self._view(obs, "lower", target)
        on_lower = lower + np.array([0.0, 0.0, BLOCK_SIZE])
        if self._placed(upper, on_lower, self.PLACED_M):
            return "done", None
        upper_view = self._view(obs, "upper", on_lower)
        width = float(o[s["gripper"]][0])
        if self.pick.phase_of(upper_view) == "release" and width < self._u_open - self.pick.WIDTH_TOL:
            return "clear", None
        near = math.hypot(*(tcp[:2] - lower[:2])) < self.NEAR_M
        is_open = width >= self._u_open - self.pick.WIDTH_TOL
        low = tcp[2] < self.CLEAR_Z - 0.003
        if is_open and near and low and self.pick.phase_of(upper_view) == "approach":
            return "rise", None
        apart = upper[:2] - lower[:2]
        far = math.hypot(*apart) > self.PLACED_M
        if far and self.pick.phase_of(upper_view) == "carry":
            way = on_lower.copy()
            way[2] = self.CARRY_Z
            if upper[2] < self.CARRY_Z - 0.002:  # not high enough yet: come no nearer than GUARD_M
                way[:2] = lower[:2] + apart * max(1.0, self.GUARD_M / math.hypot(*apart))
            upper_view["desired_goal"] = way
        return "upper", upper_view

    def __call__(self, obs: dict[str, np.ndarray]) -> np.ndarray:
        """Action for ``obs``."""
        phase, view = self._plan(obs)
        self.phase = phase
        if view is not None:
            return self.pick(view)
        o = obs["observation"]
        tcp = o[self._slices["tcp"]]
        q = self.ctrl.joints(o)
        xyz = tcp.copy()
        if phase == "rise":
            xyz[2] = self.CLEAR_Z
        return np.append(self.ctrl.toward(q, tcp, xyz, q[3]), self._u_open).astype(np.float32)


class InsertExpert:
    """Align the peg over the hole (x, y and the wrist), then lower it down the hole.

    Its action is a function of the observation alone, so it is both the
    task's scripted expert and the one DAgger labels a learner's states
    with. Decided afresh every step, by name from ``OBS_SLICES``:

    | phase  | when                                                  | does                      |
    |--------|-------------------------------------------------------|---------------------------|
    | insert | the tip below the fixture's top, or within            | x, y and wrist held; the  |
    |        | ``ALIGN_M`` and ``ALIGN_RAD`` of the hole             | tip down to the goal      |
    | align  | otherwise                                             | x, y, wrist to the hole;  |
    |        |                                                       | the tip ``HOVER_M`` above |
    |        |                                                       | the fixture's top         |

    The tolerances leave the 1 mm clearance a margin: a peg 0.25 mm off
    and 0.015 rad (0.86 degrees) turned is 0.8 mm wider than itself
    (2 x 0.25 mm + 20 mm x 0.015).
    """

    #: Horizontal tip-goal distance (m) and yaw error (rad) within which the peg goes down.
    ALIGN_M = 0.00025
    ALIGN_RAD = 0.015
    #: The tip's height above the fixture's top while aligning, m.
    HOVER_M = 0.002
    #: Cartesian mode: the share of the x, y error a step asks for. The joints arrive at
    #: speed (the env's targets lead by the braking distance), so asking for all of it
    #: rings about the hole by 1 mm for a third of a second.
    XY_GAIN = 0.5

    def __init__(self, env: BioscaraEnv) -> None:
        """Bind to ``env`` (use ``env.unwrapped``)."""
        self.env = env
        self.ctrl = JointSpaceController(env)
        self._slices = env.OBS_SLICES
        self.phase = "align"

    def reset(self) -> None:
        """Nothing to forget: the action is a function of the observation."""
        self.phase = "align"

    def phase_of(self, obs: dict[str, np.ndarray]) -> str:
        """The phase ``obs`` is in (see the class docstring)."""
        o, s = obs["observation"], self._slices
        to_goal, yaw = o[s["goal_from_tip"]], o[s["wrist_turn"]][0]
        aligned = math.hypot(to_goal[0], to_goal[1]) < self.ALIGN_M and abs(yaw) < self.ALIGN_RAD
        return "insert" if aligned or o[s["above_top"]][0] < 0.0 else "align"

    def __call__(self, obs: dict[str, np.ndarray]) -> np.ndarray:
        """Action for ``obs``."""
        o, s = obs["observation"], self._slices
        q = self.ctrl.joints(o)
        goal = obs["desired_goal"]
        phase = self.phase = self.phase_of(obs)
        tip_z = goal[2] if phase == "insert" else goal[2] + INSERT_DEPTH + self.HOVER_M
        xyz = np.array([goal[0], goal[1], tip_z + PEG_TIP_BELOW_TCP])
        q4_target = q[3] + float(o[s["wrist_turn"]][0])
        tcp = o[s["tcp"]]
        if self.env.control_mode == "cartesian":
            # One step of the slow lift at a time: a step asking more would make the
            # controller's braking (cartesian_action) slow x, y and the wrist with it.
            lift_step = self.ctrl.vmax[1] * self.env.dt
            xyz[2] = tcp[2] + np.clip(xyz[2] - tcp[2], -lift_step, lift_step)
            xyz[:2] = tcp[:2] + self.XY_GAIN * (xyz[:2] - tcp[:2])
        return self.ctrl.toward(q, tcp, xyz, q4_target).astype(np.float32)


def expert_for(env: BioscaraEnv) -> Expert:
    """The scripted expert of ``env``'s task (:data:`bioscara_gym.tasks.TASKS`), bound to ``env``.

    Raises:
        KeyError: ``env`` was not made from a registered task.
    """
    return task_of(env).make_expert(env)


def observation_expert_for(env: BioscaraEnv) -> Expert:
    """The expert of ``env``'s task whose action is a function of the observation alone.

    Raises:
        KeyError: ``env`` was not made from a registered task.
        LookupError: The task has no such expert.
    """
    return task_of(env).make_observation_expert(env)
