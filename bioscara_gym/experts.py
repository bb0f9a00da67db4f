"""Scripted experts: analytic SCARA inverse kinematics and a joint-space controller.

They act through the tasks' own action spaces, from observations only (plus
the arm's configuration), so they run on every backend like a policy would.
They prove the tasks solvable and are the baselines trained policies are
compared against (``bioscara eval --expert``).
"""

from __future__ import annotations

import math

import numpy as np

from bioscara_gym import kinematics
from bioscara_gym.envs.actions import WRIST_STEP, to_range, to_unit
from bioscara_gym.envs.base import BioscaraEnv
from bioscara_gym.envs.pick_place import BLOCK_SIZE

#: Fraction of the braking-limited speed the controller asks for (the firmware
#: ramps every command with the joint's max acceleration).
BRAKE_MARGIN = 0.8
#: Proportional gain near the goal, 1/s.
GAIN = 8.0


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

    def cartesian_action(self, tcp: np.ndarray, xyz: np.ndarray, q4: float, q4_target: float) -> np.ndarray:
        """Cartesian-mode action moving the TCP to ``xyz`` and the wrist to ``q4_target``."""
        a = np.append((xyz - tcp) / np.asarray(self.env.cartesian_step), (q4_target - q4) / WRIST_STEP)
        return np.clip(a, -1.0, 1.0)

    def solve(self, xyz: np.ndarray, q: np.ndarray, elbow: float | None = None) -> np.ndarray | None:
        """IK for the TCP at ``xyz`` within the commandable range.

        Args:
            xyz: TCP target in m.
            q: Current joint positions.
            elbow: Preferred sign of j3; ``None`` picks the solution reached
                soonest (slowest joint's travel over its max velocity, ties
                broken by the total travel).

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
            # Slowest joint's time, ties (e.g. both wait for the slow lift) broken by total motion.
            cost = float(np.max(travel) + 0.1 * np.sum(travel))
            if elbow is not None and sign != elbow:
                cost += 1e6  # only if the preferred elbow cannot reach
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
            return self.ctrl.cartesian_action(obs["achieved_goal"], goal, q[3], q[3]).astype(np.float32)
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

    def __init__(self, env: BioscaraEnv) -> None:
        """Bind to ``env`` (use ``env.unwrapped``)."""
        self.env = env
        self.ctrl = JointSpaceController(env)
        g = env.config.gripper
        self._w_lo, self._w_hi = g.min, g.max
        self._slices = env.OBS_SLICES
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
            xyz = goal - self._grip_offset
            xyz[2] = max(xyz[2], self.GRASP_Z)
        if self.env.control_mode == "cartesian":
            q4_target = self._wrist_for(q, yaw) if self.phase in ("approach", "descend") else q[3]
            a = self.ctrl.cartesian_action(tcp, xyz, q[3], q4_target)
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


def expert_for(env: BioscaraEnv) -> ReachExpert | PickPlaceExpert:
    """The scripted expert of ``env``'s task."""
    from bioscara_gym.envs.pick_place import BioscaraPickPlaceEnv

    return PickPlaceExpert(env) if isinstance(env, BioscaraPickPlaceEnv) else ReachExpert(env)
