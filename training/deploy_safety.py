"""The policy-facing half of the safety layer: every action checked before the arm sees it.

``bioscara deploy`` sends every action through :class:`SafetyLayer`:

========================  ==================================================================
check                     what happens
========================  ==================================================================
NaN or inf in an action   :class:`SafetyStop` (``nan_action``) *before* the env sees it
action out of range       clamped to the action space; the arm clamps each joint command to
                          its configured limits (position range, +-max velocity)
a joint stalls            ``stall``, naming the joint (the env has already deactivated)
bus error after retries   ``comm_error`` (:class:`CommError`, naming joint and register)
a joint reports disabled  ``joint_error`` (firmware deadman, power loss) while the arm is active
silence > 50 ms           ``deadman``: a joint went longer than the firmware's deadman
                          (docs/firmware.md) without a transaction, on the backend's clock
========================  ==================================================================

The arm-facing half (the deadman guard, :func:`~bioscara_gym.hardware.safety.safe_stop`
and the final-state report) is :mod:`bioscara_gym.hardware.safety`; SIGINT and
SIGTERM are :mod:`bioscara_gym.training.signals`.
"""

from __future__ import annotations

from dataclasses import dataclass
from typing import Any

import numpy as np

from bioscara_gym.hardware.arm import Arm, Lifecycle
from bioscara_gym.hardware.errors import CommError, JointError, SafetyStop, StalledError, StopReason
from bioscara_gym.hardware.registers import Flag
from bioscara_gym.hardware.safety import DeadmanGuard

StepResult = tuple[Any, float, bool, bool, dict[str, Any]]


@dataclass(frozen=True)
class CycleCheck:
    """What the safety layer saw in one cycle.

    Attributes:
        action: The action sent to the env (clamped).
        clamped: Whether the policy's action was outside the action space.
        silence_s: Longest silence of any joint in the cycle, s.
    """

    action: np.ndarray
    clamped: bool
    silence_s: float


class SafetyLayer:
    """Checks every action before it reaches the arm and every cycle after.

    Args:
        env: The Gymnasium env (wrapped as made); its ``unwrapped`` is a
            Bioscara env with an ``arm``.
        guard: The deadman guard over the env's backend.
    """

    def __init__(self, env: Any, guard: DeadmanGuard) -> None:
        """Bind to ``env`` and its arm."""
        self.env = env
        self.arm: Arm = env.unwrapped.arm
        self.guard = guard
        self.low = np.asarray(env.action_space.low, dtype=np.float64)
        self.high = np.asarray(env.action_space.high, dtype=np.float64)
        self.shape = tuple(env.action_space.shape)
        self.clamped = 0

    def filter_action(self, action: Any) -> tuple[np.ndarray, bool]:
        """The action to send: finite and inside the action space.

        Raises:
            SafetyStop: ``nan_action`` if any element is NaN or infinite.
            ValueError: The action has the wrong shape (a policy for another env).
        """
        a = np.asarray(action, dtype=np.float64)
        if a.shape != self.shape:
            raise ValueError(f"policy returned an action of shape {a.shape}; the env expects {self.shape}")
        if not np.all(np.isfinite(a)):
            shown = np.array2string(a, precision=3, separator=", ")
            raise SafetyStop(StopReason.NAN_ACTION, f"policy returned a non-finite action {shown} (NaN/inf)")
        clipped = np.clip(a, self.low, self.high)
        clamped = bool(np.any(clipped != a))
        self.clamped += clamped
        return clipped, clamped

    def step(self, action: Any) -> tuple[StepResult, CycleCheck]:
        """Check ``action``, step the env, check the outcome.

        Returns:
            The env's ``(obs, reward, terminated, truncated, info)`` and the checks.

        Raises:
            SafetyStop: See the module docstring for the reasons.
        """
        safe, clamped = self.filter_action(action)
        self.guard.check()  # the policy's own time counts on the wall clock
        result = self._step_env(safe)
        silence = self.guard.check()
        self._check_stall(result[4])
        self._check_enabled()
        return result, CycleCheck(safe, clamped, silence)

    def _step_env(self, action: np.ndarray) -> StepResult:
        """Step the env; a driver error becomes the :class:`SafetyStop` it means."""
        try:
            return self.env.step(action)
        except StalledError as e:
            raise SafetyStop(StopReason.STALL, f"{e.joint or 'a joint'} stalled: {e}", e.joint) from e
        except CommError as e:
            raise SafetyStop(StopReason.COMM_ERROR, f"communication error: {e}", e.joint) from e
        except JointError as e:
            raise SafetyStop(StopReason.JOINT_ERROR, f"joint error: {e}", e.joint) from e

    @staticmethod
    def _check_stall(info: dict[str, Any]) -> None:
        """Stop if the env reports a stall (it has already deactivated the arm)."""
        if info.get("stalled"):
            joint = info.get("stalled_joint")
            who = joint or "a joint (the env did not say which)"
            raise SafetyStop(
                StopReason.STALL, f"{who} stalled (stall detection tripped); every joint stopped", joint
            )

    def _check_enabled(self) -> None:
        """Stop if a joint reports not enabled while the arm is active."""
        if self.arm.state is not Lifecycle.ACTIVE:
            return
        for name, state in self.arm.joint_states.items():
            if state.flags & Flag.NOT_ENABLED:
                raise SafetyStop(
                    StopReason.JOINT_ERROR,
                    f"{name} reports not enabled while the arm is active (firmware deadman, power loss)",
                    name,
                )
