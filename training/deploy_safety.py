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

Why a run stopped is a :class:`StopReason`; a :class:`SafetyStop` carries it,
and :func:`stop_for` is the one place a driver's exception becomes one. The
arm-facing half (the deadman guard, :func:`~bioscara_gym.hardware.safety.safe_stop`
and the final-state report) is :mod:`bioscara_gym.hardware.safety`, reached
through the :class:`~bioscara_gym.hardware.arm.Arm`; SIGINT, SIGTERM and
SIGHUP (``interrupted``, ``terminated``, ``hung_up``) are
:mod:`bioscara_gym.training.signals`.
"""

from __future__ import annotations

import signal
from dataclasses import dataclass
from enum import Enum
from typing import Any

import numpy as np

from bioscara_gym.errors import EXIT_ERROR, EXIT_FAULT
from bioscara_gym.hardware.arm import Arm, Lifecycle
from bioscara_gym.hardware.errors import CommError, DeadmanError, JointError, StalledError
from bioscara_gym.hardware.registers import Flag
from bioscara_gym.hardware.safety import DeadmanGuard, SafeStopReport
from bioscara_gym.training.signals import Interrupted

StepResult = tuple[Any, float, bool, bool, dict[str, Any]]


class StopReason(Enum):
    """Why a deployment ended."""

    COMPLETED = "completed"
    NAN_ACTION = "nan_action"
    STALL = "stall"
    COMM_ERROR = "comm_error"
    JOINT_ERROR = "joint_error"
    DEADMAN = "deadman"
    INTERRUPTED = "interrupted"
    TERMINATED = "terminated"
    HUNG_UP = "hung_up"
    LOG_ERROR = "log_error"
    ERROR = "error"


#: The stop reason of each stop signal: Ctrl-C, a kill or a supervisor, the terminal closed.
SIGNAL_REASONS = {
    signal.SIGINT: StopReason.INTERRUPTED,
    signal.SIGTERM: StopReason.TERMINATED,
    signal.SIGHUP: StopReason.HUNG_UP,
}


class SafetyStop(Exception):
    """The safety layer stopped the run; the message names the cause.

    Attributes:
        reason: What tripped.
        joint: The joint concerned, if one is.
    """

    def __init__(self, reason: StopReason, message: str, joint: str | None = None) -> None:
        """Record the reason, the message and the joint."""
        super().__init__(message)
        self.reason = reason
        self.joint = joint


def stop_for(error: BaseException) -> SafetyStop | None:
    """The :class:`SafetyStop` a driver or deadman error means; ``None`` for any other exception.

    ====================  ===============  ===================================
    exception             reason           message
    ====================  ===============  ===================================
    ``SafetyStop``        its own          its own
    ``DeadmanError``      ``deadman``      the guard's (joint, silence, limit)
    ``StalledError``      ``stall``        ``j2 stalled: ...``
    ``CommError``         ``comm_error``   ``communication error: ...``
    other ``JointError``  ``joint_error``  ``joint error: ...``
    ====================  ===============  ===================================
    """
    if isinstance(error, SafetyStop):
        return error
    if isinstance(error, DeadmanError):
        return SafetyStop(StopReason.DEADMAN, str(error), error.joint)
    if isinstance(error, StalledError):
        return SafetyStop(StopReason.STALL, f"{error.joint or 'a joint'} stalled: {error}", error.joint)
    if isinstance(error, CommError):
        return SafetyStop(StopReason.COMM_ERROR, f"communication error: {error}", error.joint)
    if isinstance(error, JointError):
        return SafetyStop(StopReason.JOINT_ERROR, f"joint error: {error}", error.joint)
    return None


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


#: Exit codes: refused before touching the arm, stopped by the safety layer (the CLI's).
EXIT_REFUSED = EXIT_ERROR
EXIT_SAFETY_STOP = EXIT_FAULT


@dataclass
class Outcome:
    """How a run ended: what the summary and the exit code say.

    Attributes:
        reason: Why it ended.
        message: One line for the operator.
        joint: The joint concerned, if one is.
        exit_code: The CLI's exit code.
        stop_report: What the safe stop did (``None`` if the run completed).
    """

    reason: StopReason = StopReason.COMPLETED
    message: str = "completed"
    joint: str | None = None
    exit_code: int = 0
    stop_report: SafeStopReport | None = None


def outcome_for(e: BaseException) -> Outcome:
    """How a run ends that ``e`` stopped: the signal's, :func:`stop_for`'s, else an error (exit code 1)."""
    if isinstance(e, Interrupted):
        reason = SIGNAL_REASONS[e.signum]
        return Outcome(reason, f"{e} received", None, e.exit_code)
    if isinstance(e, KeyboardInterrupt):
        return Outcome(StopReason.INTERRUPTED, "SIGINT received", None, 130)
    stop = stop_for(e)
    if stop is not None:
        return Outcome(stop.reason, str(stop), stop.joint, EXIT_SAFETY_STOP)
    return Outcome(StopReason.ERROR, f"{type(e).__name__}: {e}", None, 1)


class SafetyLayer:
    """Checks every action before it reaches the arm and every cycle after.

    Args:
        env: The Gymnasium env (wrapped as made).
        arm: The arm it drives.
        guard: The deadman guard over the arm's joints (:meth:`Arm.watch_deadman`).
    """

    def __init__(self, env: Any, arm: Arm, guard: DeadmanGuard) -> None:
        """Bind to ``env`` and its arm."""
        self.env = env
        self.arm = arm
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
        try:
            self.guard.check()  # the policy's own time counts on the wall clock
            result = self.env.step(safe)
            silence = self.guard.check()
        except (DeadmanError, JointError) as e:  # the SafetyStop it means
            raise stop_for(e) from e
        self._check_stall(result[4])
        self._check_enabled()
        return result, CycleCheck(safe, clamped, silence)

    @staticmethod
    def _check_stall(info: dict[str, Any]) -> None:
        """Stop if the env reports a stall (it has already deactivated the arm)."""
        if info.get("stalled"):
            joint = info.get("stalled_joint")
            who = joint or "a joint (the env did not say which)"
            how = (
                "lost its field (the arm's field watch: the rotor stayed behind the drive)"
                if info.get("field_lost")
                else "stalled (stall detection tripped)"
            )
            raise SafetyStop(StopReason.STALL, f"{who} {how}; every joint stopped", joint)

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
