"""Tests that kill mutants mutmut found surviving in ``training/deploy_safety.py`` (docs/mutation.md).

A stand-in env and deadman guard built here, the mock arm for the enabled
check. Expected values are literals from the module's documented contract
(the stop reasons, :func:`stop_for`'s table of messages, the exit codes
README.md's fault matrix names: 2 refused, 3 safety stop, 128 + the signal).
"""

from __future__ import annotations

import signal
from typing import Any

import numpy as np
import pytest
from gymnasium import spaces

from bioscara_gym.hardware.arm import Arm
from bioscara_gym.hardware.errors import CommError, DeadmanError, JointError, NotEnabledError, StalledError
from bioscara_gym.hardware.registers import Reg
from bioscara_gym.training.deploy_safety import (
    EXIT_REFUSED,
    EXIT_SAFETY_STOP,
    CycleCheck,
    Outcome,
    SafetyLayer,
    SafetyStop,
    StopReason,
    outcome_for,
    stop_for,
)
from bioscara_gym.training.signals import Interrupted


class Env:
    """Just enough of an env: a 2-value action space in [-1, 1]; ``step`` records the action."""

    def __init__(self, info: dict[str, Any] | None = None, error: Exception | None = None) -> None:
        self.action_space = spaces.Box(np.array([-1.0, -0.5], np.float32), np.array([1.0, 0.5], np.float32))
        self.info = info or {}
        self.error = error
        self.sent: list[np.ndarray] = []

    def step(self, action: np.ndarray) -> Any:
        self.sent.append(action)
        if self.error is not None:
            raise self.error
        return ("obs", 1.5, False, True, self.info)


class Guard:
    """A deadman guard whose checks return the given silences, or raise the given error."""

    def __init__(self, *results: float | Exception) -> None:
        self.results = list(results)
        self.checks = 0

    def check(self) -> float:
        self.checks += 1
        result = self.results.pop(0)
        if isinstance(result, Exception):
            raise result
        return result


def layer(mock_arm: Arm, env: Env | None = None, guard: Guard | None = None) -> SafetyLayer:
    return SafetyLayer(env or Env(), mock_arm, guard or Guard(0.01, 0.02))  # type: ignore[arg-type]


# ------------------------------------------------------------- the reasons
def test_the_stop_reasons_are_named_as_the_run_log_writes_them() -> None:
    assert {r.name: r.value for r in StopReason} == {
        "COMPLETED": "completed",
        "NAN_ACTION": "nan_action",
        "STALL": "stall",
        "COMM_ERROR": "comm_error",
        "JOINT_ERROR": "joint_error",
        "DEADMAN": "deadman",
        "INTERRUPTED": "interrupted",
        "TERMINATED": "terminated",
        "HUNG_UP": "hung_up",
        "LOG_ERROR": "log_error",
        "ERROR": "error",
    }
    assert (EXIT_REFUSED, EXIT_SAFETY_STOP) == (2, 3)


def test_a_safety_stop_carries_its_reason_message_and_joint() -> None:
    stop = SafetyStop(StopReason.STALL, "j2 stalled", "j2")
    assert (stop.reason, str(stop), stop.joint) == (StopReason.STALL, "j2 stalled", "j2")
    assert SafetyStop(StopReason.ERROR, "x").joint is None


@pytest.mark.parametrize(
    ("error", "reason", "message", "joint"),
    [
        (
            DeadmanError("j3", 0.0625, 0.05),
            StopReason.DEADMAN,
            "deadman guard: j3 went 62.5 ms without a transaction (limit 50 ms); its firmware would stop it",
            "j3",
        ),
        (StalledError("stall flag", joint="j2"), StopReason.STALL, "j2 stalled: ", "j2"),
        (StalledError("stall flag"), StopReason.STALL, "a joint stalled: ", None),
        (CommError("no reply", joint="j1", register=Reg.PING), StopReason.COMM_ERROR, "communication error: ",
         "j1"),
        (NotEnabledError("not enabled", joint="j4"), StopReason.JOINT_ERROR, "joint error: ", "j4"),
    ],
    ids=["deadman", "stall", "stall-no-joint", "comm", "joint"],
)  # fmt: skip
def test_stop_for_follows_its_table(
    error: Exception, reason: StopReason, message: str, joint: str | None
) -> None:
    stop = stop_for(error)
    assert stop is not None
    assert (stop.reason, stop.joint) == (reason, joint)
    assert str(stop) == message + ("" if isinstance(error, DeadmanError) else str(error))


def test_stop_for_gives_a_safety_stop_back_and_nothing_for_other_errors() -> None:
    stop = SafetyStop(StopReason.NAN_ACTION, "NaN")
    assert stop_for(stop) is stop
    assert stop_for(RuntimeError("boom")) is None


# ----------------------------------------------------------------- outcome
def test_a_completed_run_is_exit_0_without_a_stop_report() -> None:
    outcome = Outcome()
    assert (outcome.reason, outcome.message, outcome.joint, outcome.exit_code, outcome.stop_report) == (
        StopReason.COMPLETED,
        "completed",
        None,
        0,
        None,
    )


@pytest.mark.parametrize(
    ("error", "expected"),
    [
        (Interrupted(signal.SIGINT), (StopReason.INTERRUPTED, "SIGINT received", None, 130)),
        (Interrupted(signal.SIGTERM), (StopReason.TERMINATED, "SIGTERM received", None, 143)),
        (Interrupted(signal.SIGHUP), (StopReason.HUNG_UP, "SIGHUP received", None, 129)),
        (KeyboardInterrupt(), (StopReason.INTERRUPTED, "SIGINT received", None, 130)),
        (StalledError("stall flag", joint="j2"), (StopReason.STALL, "j2 stalled: j2: stall flag", "j2", 3)),
        (RuntimeError("boom"), (StopReason.ERROR, "RuntimeError: boom", None, 1)),
    ],
    ids=["sigint", "sigterm", "sighup", "keyboard", "safety-stop", "other"],
)
def test_outcome_for_each_way_a_run_ends(error: BaseException, expected: tuple[Any, ...]) -> None:
    outcome = outcome_for(error)
    assert (outcome.reason, outcome.message, outcome.joint, outcome.exit_code) == expected
    assert outcome.stop_report is None


# ------------------------------------------------------------ the actions
def test_an_action_inside_the_space_passes_unclamped(mock_arm: Arm) -> None:
    safety = layer(mock_arm)
    action, clamped = safety.filter_action([0.5, -0.25])
    assert action.tolist() == [0.5, -0.25] and clamped is False
    assert action.dtype == np.float64
    assert safety.clamped == 0


def test_each_clamped_action_is_counted_against_its_own_bound(mock_arm: Arm) -> None:
    safety = layer(mock_arm)
    assert safety.filter_action([2.0, -0.75])[0].tolist() == [1.0, -0.5]
    assert safety.filter_action([-2.0, 0.75])[0].tolist() == [-1.0, 0.5]
    assert safety.filter_action([0.0, 0.0])[1] is False
    assert safety.clamped == 2
    assert (safety.low.tolist(), safety.high.tolist(), safety.shape) == ([-1.0, -0.5], [1.0, 0.5], (2,))


def test_an_action_of_the_wrong_shape_names_both_shapes(mock_arm: Arm) -> None:
    with pytest.raises(ValueError) as caught:
        layer(mock_arm).filter_action([0.0, 0.0, 0.0])
    assert str(caught.value) == "policy returned an action of shape (3,); the env expects (2,)"


def test_a_non_finite_action_is_shown_in_the_stop_message(mock_arm: Arm) -> None:
    with pytest.raises(SafetyStop) as caught:
        layer(mock_arm).filter_action([np.nan, 0.12345])
    assert caught.value.reason is StopReason.NAN_ACTION
    assert str(caught.value) == "policy returned a non-finite action [  nan, 0.123] (NaN/inf)"


# ---------------------------------------------------------------- stepping
def test_step_sends_the_clamped_action_and_reports_the_cycle(mock_arm: Arm) -> None:
    env, guard = Env(), Guard(0.01, 0.02)
    result, check = layer(mock_arm, env, guard).step([3.0, 0.0])
    assert result == ("obs", 1.5, False, True, {})
    assert env.sent[0].tolist() == [1.0, 0.0]
    assert isinstance(check, CycleCheck)
    assert (check.action.tolist(), check.clamped, check.silence_s) == ([1.0, 0.0], True, 0.02)
    assert guard.checks == 2  # before the env steps (the policy's time) and after


def test_a_deadman_trip_before_the_step_stops_before_the_env_sees_the_action(mock_arm: Arm) -> None:
    env = Env()
    trip = DeadmanError("j1", 0.0625, 0.05)
    with pytest.raises(SafetyStop) as caught:
        layer(mock_arm, env, Guard(trip)).step([0.0, 0.0])
    assert caught.value.reason is StopReason.DEADMAN and caught.value.joint == "j1"
    assert caught.value.__cause__ is trip
    assert env.sent == []


def test_a_deadman_trip_after_the_step_stops_too(mock_arm: Arm) -> None:
    with pytest.raises(SafetyStop) as caught:
        layer(mock_arm, Env(), Guard(0.01, DeadmanError("j2", 0.0625, 0.05))).step([0.0, 0.0])
    assert caught.value.reason is StopReason.DEADMAN and caught.value.joint == "j2"


def test_a_driver_error_of_the_step_is_its_safety_stop_caused_by_it(mock_arm: Arm) -> None:
    error = JointError("driver fault", joint="j3")
    with pytest.raises(SafetyStop) as caught:
        layer(mock_arm, Env(error=error)).step([0.0, 0.0])
    assert caught.value.reason is StopReason.JOINT_ERROR and caught.value.joint == "j3"
    assert caught.value.__cause__ is error


def test_any_other_error_of_the_step_is_not_a_safety_stop(mock_arm: Arm) -> None:
    with pytest.raises(RuntimeError, match="physics"):
        layer(mock_arm, Env(error=RuntimeError("physics"))).step([0.0, 0.0])


def test_a_stall_the_env_reports_names_the_joint(mock_arm: Arm) -> None:
    env = Env(info={"stalled": True, "stalled_joint": "j4"})
    with pytest.raises(SafetyStop) as caught:
        layer(mock_arm, env).step([0.0, 0.0])
    assert caught.value.reason is StopReason.STALL and caught.value.joint == "j4"
    assert str(caught.value) == "j4 stalled (stall detection tripped); every joint stopped"


def test_a_field_the_arms_watch_saw_lost_is_named_as_such_not_as_the_firmwares_stall(mock_arm: Arm) -> None:
    env = Env(info={"stalled": True, "stalled_joint": "j1", "field_lost": True})
    with pytest.raises(SafetyStop) as caught:
        layer(mock_arm, env).step([0.0, 0.0])
    assert caught.value.reason is StopReason.STALL and caught.value.joint == "j1"
    assert str(caught.value) == (
        "j1 lost its field (the arm's field watch: the rotor stayed behind the drive); every joint stopped"
    )


def test_a_step_of_an_unconfigured_arm_skips_the_enabled_check(mock_arm: Arm) -> None:
    # Unconfigured: its joints' last flags say nothing; the check is for an active arm only.
    result, _ = layer(mock_arm).step([0.0, 0.0])
    assert result[1] == 1.5
