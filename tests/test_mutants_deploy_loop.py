"""Tests that kill mutants mutmut found surviving in ``training/deploy_loop.py`` (docs/mutation.md).

In-process deployments of a constant policy (or Reach's scripted expert) on
the ``mock`` backend, whose clock the test advances inside a cycle to make
it late, and the loop's parts on their own (:class:`EpisodeClock` on a
clock the test sets, an episode's end, an overrun's warning, a policy that
raises). Expected values are literals from deploy.py's run-log table (the
``cycle`` and ``episode`` records and their fields), deploy_loop.py's
docstrings (episodes reset with the run's seed plus the episode's number,
the first 5 overruns warned about), the packaged Reach task (25 Hz, 50 steps
an episode, 1 s of mock homing) and the policy's own action.
"""

from __future__ import annotations

import io
import itertools
import os
import signal
import time
from collections.abc import Callable
from pathlib import Path
from types import SimpleNamespace
from typing import Any

import gymnasium as gym
import numpy as np
import pytest
from rich.console import Console
from rigs import ConstantPolicy, DeployRun, run_deployment

from bioscara_gym.hardware.emulated_bus import FaultPlan
from bioscara_gym.training import deploy_loop
from bioscara_gym.training.deploy_log import CycleTiming
from bioscara_gym.training.deploy_loop import ControlLoop, EpisodeClock, _act
from bioscara_gym.training.deploy_safety import CycleCheck, SafetyStop, StopReason
from bioscara_gym.training.signals import Interrupted

REACH = "Bioscara-Reach-v0"
JOINTS = ("j1", "j2", "j3", "j4")
#: The cycle record's fields (deploy.py's run-log table), "bus" only when the cycle had any.
CYCLE_FIELDS = {
    "type",
    "cycle",
    "episode",
    "step",
    "t",
    "period_s",
    "wall_period_s",
    "work_s",
    "silence_s",
    "overrun",
    "action",
    "clamped",
    "commands",
    "q",
    "qd",
    "flags",
    "reward",
}


@pytest.fixture
def deploy(tmp_path: Path, gripper_state_file: Path) -> Callable[..., DeployRun]:
    """``deploy(policy, on_cycle=None, **DeployArgs fields)`` on ``mock``, Reach named."""

    def run(policy: Any, on_cycle: Callable[[int, gym.Env], None] | None = None, **fields: Any) -> DeployRun:
        fields.setdefault("backend", "mock")
        fields.setdefault("log", tmp_path / "run.jsonl")
        fields.setdefault("state_file", gripper_state_file)
        fields.setdefault("env", REACH)
        fields.setdefault("expert", policy is None)
        most = 50 * fields.get("episodes", 1)  # Reach's episodes last 50 steps at most

        def hook(cycle: int, env: gym.Env) -> None:
            if cycle >= most:  # an episode that does not end fails here, not at a timeout
                raise AssertionError(
                    f"cycle {cycle}: more than {most} in {fields.get('episodes', 1)} episode(s)"
                )
            if on_cycle is not None:
                on_cycle(cycle, env)

        return run_deployment(fields, policy, None, hook, catch=(Interrupted,))

    return run


def cycles_of(run: DeployRun) -> list[dict[str, Any]]:
    return [r for r in run.records if r["type"] == "cycle"]


def late(cycles: range, by_s: float) -> Callable[[int, gym.Env], None]:
    """An ``on_cycle`` hook: the mock's clock runs ``by_s`` on before each of ``cycles`` starts."""

    def hook(cycle: int, env: gym.Env) -> None:
        if cycle in cycles:
            env.unwrapped.arm.clock.sleep(by_s)

    return hook


# ------------------------------------------------------------------ the cycle records
def test_each_cycle_is_one_record_numbered_across_episodes(deploy: Callable[..., DeployRun]) -> None:
    run = deploy(ConstantPolicy([2.0, 0.0, 0.0, -0.5]), episodes=2)
    assert run.error is None, run.output
    cycles = cycles_of(run)
    assert [r["cycle"] for r in cycles] == list(range(100))
    assert [r["episode"] for r in cycles] == [0] * 50 + [1] * 50
    assert [r["step"] for r in cycles] == list(range(50)) * 2
    assert all(set(r) == CYCLE_FIELDS for r in cycles), set(cycles[0]) ^ CYCLE_FIELDS
    first = cycles[0]
    assert first["t"] == pytest.approx(1.04)  # mock homing: 1 s, then one control period
    assert first["action"] == [2.0, 0.0, 0.0, -0.5] and first["clamped"] is True  # the policy's own action
    assert set(first["commands"]) == set(first["q"]) == set(first["qd"]) == set(JOINTS)
    assert first["commands"]["j1"] == 1.0 and first["commands"]["j2"] == 0.0  # clamped to 1, and 0
    assert first["flags"] == {"j1": 0, "j2": 0, "j3": 0, "j4": 0}  # homed and enabled: no flag set
    assert [r["overrun"] for r in cycles] == [False] * 100
    assert all(0 < r["work_s"] < 5.0 and r["silence_s"] == pytest.approx(0.04) for r in cycles)


def test_a_cycles_periods_follow_the_previous_cycle_of_its_episode(deploy: Callable[..., DeployRun]) -> None:
    run = deploy(ConstantPolicy([0.0, 0.0, 0.0, 0.0]), episodes=2)
    cycles = cycles_of(run)
    for r in (cycles[0], cycles[50]):  # after a reset
        assert r["period_s"] is None and r["wall_period_s"] is None
    for prev, r in itertools.pairwise(cycles):
        if r["step"] == 0:
            continue
        assert r["period_s"] == pytest.approx(0.04)  # 25 Hz on the mock's clock
        assert r["period_s"] == pytest.approx(r["t"] - prev["t"], abs=1e-12)
        assert 0 < r["wall_period_s"] < 5.0


def test_each_cycle_logs_the_reward_the_env_gave(deploy: Callable[..., DeployRun]) -> None:
    rewards: list[float] = []

    def wrap(cycle: int, env: gym.Env) -> None:
        if cycle == 0:  # SafetyLayer steps the env deploy made: record its rewards from inside it
            inner = env.unwrapped
            original = inner.step

            def step(action: Any) -> Any:
                result = original(action)
                rewards.append(float(result[1]))
                return result

            inner.step = step

    run = deploy(ConstantPolicy([0.5, 0.5, 0.0, 0.0]), on_cycle=wrap)
    cycles = cycles_of(run)
    assert len(rewards) == 50 and len(set(rewards)) > 1
    assert [r["reward"] for r in cycles] == rewards
    (episode,) = [r for r in run.records if r["type"] == "episode"]
    assert episode["return"] == pytest.approx(sum(rewards))


def test_an_integer_action_is_logged_as_floats(deploy: Callable[..., DeployRun]) -> None:
    def ints(obs: dict[str, np.ndarray]) -> list[int]:
        return [1, 0, 0, -1]

    run = deploy(ints)
    assert run.error is None, run.output
    action = cycles_of(run)[0]["action"]
    assert action == [1.0, 0.0, 0.0, -1.0] and all(type(a) is float for a in action)


def test_the_cycle_a_safety_stop_cuts_short_is_logged_as_stopped(deploy: Callable[..., DeployRun]) -> None:
    run = deploy(ConstantPolicy([0.5, 0.0, 0.0, 0.0], bad_from=52), episodes=2)
    assert run.error is not None and run.error.code == 3
    cycles = cycles_of(run)
    last = cycles[-1]
    assert last["t"] == pytest.approx(cycles[-2]["t"] + 0.04)
    del last["t"]
    assert last == {
        "type": "cycle",
        "cycle": 52,
        "episode": 1,
        "step": 2,
        "action": ["nan", 0.0, 0.0, 0.0],
        "flags": {"j1": 0, "j2": 0, "j3": 0, "j4": 0},
        "stopped": True,
    }
    assert run.summary["cycles"] == 52 and run.summary["episodes"] == 1  # the stopped cycle is not counted


# ------------------------------------------------------------------ episodes
def test_each_episode_resets_with_the_runs_seed_plus_its_number(deploy: Callable[..., DeployRun]) -> None:
    goals: list[np.ndarray] = []

    def policy(obs: dict[str, np.ndarray]) -> np.ndarray:
        if not goals or not np.array_equal(goals[-1], obs["desired_goal"]):
            goals.append(obs["desired_goal"].copy())
        return np.zeros(4, dtype=np.float32)

    run = deploy(policy, episodes=2, seed=3)
    assert run.error is None, run.output
    env = gym.make(REACH, backend="mock")
    try:
        expected = [env.reset(seed=seed)[0]["desired_goal"] for seed in (3, 4)]
    finally:
        env.close()
    assert len(goals) == 2
    np.testing.assert_array_equal(goals[0], expected[0])
    np.testing.assert_array_equal(goals[1], expected[1])


def test_an_episode_ends_when_the_env_terminates_it_before_its_time_limit(
    deploy: Callable[..., DeployRun],
) -> None:
    def terminate_at_step_10(cycle: int, env: gym.Env) -> None:
        if cycle == 0:  # the env deploy made terminates its first episode after 10 steps
            inner = env.unwrapped
            original, steps = inner.step, [0]

            def step(action: Any) -> Any:
                obs, reward, terminated, truncated, info = original(action)
                steps[0] += 1
                return obs, reward, terminated or steps[0] == 10, truncated, info

            inner.step = step

    run = deploy(ConstantPolicy([0.0, 0.0, 0.0, 0.0]), on_cycle=terminate_at_step_10, episodes=2)
    assert run.error is None, run.output
    assert [r["steps"] for r in run.records if r["type"] == "episode"] == [10, 50]
    assert run.summary["cycles"] == 60


def test_a_resets_bus_errors_are_a_record_naming_its_episode(deploy: Callable[..., DeployRun]) -> None:
    # deploy.py's run-log table: bus records per phase, "reset with its episode"; the cycles' own
    # in their cycle records. NACKs (seeded) on the emulated bus from the last cycle of episode 0
    # through the reset of episode 1.
    def nack_around_the_reset(cycle: int, env: gym.Env) -> None:
        if cycle == 49:
            env.unwrapped.backend.bus.faults = FaultPlan(nack=0.15, seed=3)
        if cycle == 50:
            env.unwrapped.backend.bus.faults = FaultPlan()

    run = deploy(
        ConstantPolicy([0.0, 0.0, 0.0, 0.0]), on_cycle=nack_around_the_reset, episodes=2, backend="emulated"
    )
    assert run.error is None, run.output
    assert [r for r in run.records if r["type"] == "bus"] == [
        {"type": "bus", "phase": "reset", "episode": 1, "joints": {"j2": {"retries": 2, "bus_errors": 2}}}
    ]
    assert [(r["cycle"], r["bus"]) for r in cycles_of(run) if "bus" in r] == [
        (49, {"j3": {"retries": 3, "bus_errors": 3}, "j4": {"retries": 1, "bus_errors": 1}})
    ]


def test_a_policy_with_reset_is_reset_before_each_episode(deploy: Callable[..., DeployRun]) -> None:
    class Stateful:
        def __init__(self) -> None:
            self.calls: list[str] = []

        def reset(self) -> None:
            self.calls.append("reset")

        def __call__(self, obs: dict[str, np.ndarray]) -> np.ndarray:
            self.calls.append("act")
            return np.zeros(4, dtype=np.float32)

    policy = Stateful()
    run = deploy(policy, episodes=2)
    assert run.error is None, run.output
    assert policy.calls == (["reset"] + ["act"] * 50) * 2


def test_an_episode_ends_in_a_record_and_a_line(deploy: Callable[..., DeployRun]) -> None:
    run = deploy(None, episodes=2)  # Reach's scripted expert: both succeed
    assert run.error is None, run.output
    episodes = [r for r in run.records if r["type"] == "episode"]
    assert [(r["type"], r["episode"], r["success"], r["steps"], r["stalled"]) for r in episodes] == [
        ("episode", 0, True, 50, False),
        ("episode", 1, True, 50, False),
    ]
    for r in episodes:
        assert set(r) == {"type", "episode", "success", "distance", "steps", "return", "stalled"}
        assert 0 <= r["distance"] < 0.01  # Reach's success: within distance_threshold, 0.01 m
    lines = [line for line in run.lines if " episode " in line]
    assert len(lines) == 2
    assert lines[0].startswith("           episode 1/2: success, distance ") and lines[0].endswith(
        " mm, 50 steps"
    )
    assert lines[1].startswith("           episode 2/2: success, distance ")
    d = episodes[0]["distance"] * 1000
    assert lines[0] == f"           episode 1/2: success, distance {d:.1f} mm, 50 steps"
    assert run.summary["episodes"] == 2 and run.summary["successes"] == 2 and run.summary["cycles"] == 100


def make_loop(out: io.StringIO | None = None, **args: Any) -> tuple[ControlLoop, list[dict[str, Any]]]:
    """A loop whose log is a list and whose console writes to ``out``; no arm."""
    written: list[dict[str, Any]] = []
    fields = {"episodes": 4, "realtime": False, "backend": "mock", "dt": 0.04, **args}
    loop = ControlLoop(
        target=SimpleNamespace(dt=fields["dt"]),
        args=SimpleNamespace(**fields),
        log=SimpleNamespace(write=written.append),
        bus=SimpleNamespace(cycle=dict),
        timing=CycleTiming(nominal_s=fields["dt"]),
        signals=None,
        console=Console(file=out or io.StringIO(), width=200),
        tell=None,
    )
    return loop, written


def test_an_episodes_success_distance_and_stall_come_from_its_last_info() -> None:
    out = io.StringIO()
    loop, written = make_loop(out)
    loop._end_episode(2, {"is_success": 1.0, "distance": 0.25, "stalled": 1}, 37, -1.5)
    loop._end_episode(3, {}, 50, 0.0)
    assert written == [
        {
            "type": "episode",
            "episode": 2,
            "success": True,
            "distance": 0.25,
            "steps": 37,
            "return": -1.5,
            "stalled": True,
        },
        {
            "type": "episode",
            "episode": 3,
            "success": False,
            "distance": None,
            "steps": 50,
            "return": 0.0,
            "stalled": False,
        },
    ]
    assert out.getvalue().splitlines() == [
        "           episode 3/4: success, distance 250.0 mm, 37 steps",
        "           episode 4/4: miss, distance nan mm, 50 steps",
    ]
    assert loop.counts == {"episodes": 2, "successes": 1, "cycles": 0}


# ------------------------------------------------------------------ the run phase
def test_the_run_phase_names_the_episodes_rate_and_log(
    deploy: Callable[..., DeployRun], tmp_path: Path
) -> None:
    run = deploy(ConstantPolicy([0.0, 0.0, 0.0, 0.0]), episodes=2, rate=20.0)
    assert run.error is None, run.output
    detail = f"2 episode(s) at 20 Hz, log {tmp_path / 'run.jsonl'}"
    assert f"run        {detail}" in run.lines
    assert {"type": "phase", "phase": "run", "detail": detail} in [
        {k: r[k] for k in ("type", "phase", "detail")} for r in run.records if r["type"] == "phase"
    ]


def test_the_hook_sees_each_cycles_number_and_the_env(deploy: Callable[..., DeployRun]) -> None:
    seen: list[tuple[int, Any]] = []
    run = deploy(ConstantPolicy([0.0, 0.0, 0.0, 0.0]), on_cycle=lambda cycle, env: seen.append((cycle, env)))
    assert [c for c, _ in seen] == list(range(50))
    assert all(env is run.deployment.env for _, env in seen)


def test_a_signal_inside_a_cycle_is_taken_at_the_next_cycle_boundary(
    deploy: Callable[..., DeployRun],
) -> None:
    def terminate_at_3(cycle: int, env: gym.Env) -> None:
        if cycle == 3:
            os.kill(os.getpid(), signal.SIGTERM)

    run = deploy(ConstantPolicy([0.0, 0.0, 0.0, 0.0]), on_cycle=terminate_at_3)
    assert isinstance(run.error, Interrupted) and run.error.signum == signal.SIGTERM
    cycles = cycles_of(run)
    assert [r["cycle"] for r in cycles] == [0, 1, 2, 3] and "stopped" not in cycles[-1]  # cycle 3 completed
    assert run.summary["stop_reason"] == "terminated" and run.summary["cycles"] == 4


# ------------------------------------------------------------------ overruns
def test_the_first_five_overruns_are_warned_about_and_all_counted(deploy: Callable[..., DeployRun]) -> None:
    # 45 ms late from cycle 3 on (under the deadman's 50 ms): cycle 3's period is 85 ms, then 45 ms each.
    run = deploy(ConstantPolicy([0.0, 0.0, 0.0, 0.0]), on_cycle=late(range(3, 10), 0.045))
    assert run.error is None, run.output
    assert [line for line in run.lines if line.startswith("warning: overrun")] == [
        "warning: overrun at cycle 3: period 85.0 ms > 40 ms",
        "warning: overrun at cycle 4: period 45.0 ms > 40 ms",
        "warning: overrun at cycle 5: period 45.0 ms > 40 ms",
        "warning: overrun at cycle 6: period 45.0 ms > 40 ms",
        "warning: overrun at cycle 7: period 45.0 ms > 40 ms (further overruns are only counted)",
    ]
    assert [r["cycle"] for r in cycles_of(run) if r["overrun"]] == [3, 4, 5, 6, 7, 8, 9]
    assert run.summary["overruns"] == 7


def test_a_late_wall_clock_is_no_overrun_where_it_does_not_pace_the_loop(
    deploy: Callable[..., DeployRun],
) -> None:
    def slow_host(cycle: int, env: gym.Env) -> None:
        if cycle == 3:
            time.sleep(0.06)  # the host, not the mock's clock

    run = deploy(ConstantPolicy([0.0, 0.0, 0.0, 0.0]), on_cycle=slow_host)
    assert run.error is None, run.output
    assert cycles_of(run)[3]["wall_period_s"] > 0.06
    assert run.summary["overruns"] == 0 and "warning: overrun" not in run.output


def test_on_the_arm_the_wall_clock_paces_the_loop_and_its_period_is_warned_about() -> None:
    out = io.StringIO()
    loop, _ = make_loop(out, backend="i2c")
    check = CycleCheck(np.zeros(4), False, 0.0125)
    timing = loop._account_cycle(0.04, 0.0625, 0.001, check)
    assert timing == {
        "period_s": 0.04,
        "wall_period_s": 0.0625,
        "work_s": 0.001,
        "silence_s": 0.0125,
        "overrun": True,
    }
    assert out.getvalue() == "warning: overrun at cycle 0: period 62.5 ms > 40 ms\n"
    loop, _ = make_loop(out := io.StringIO(), backend="emulated", realtime=True)
    assert loop._account_cycle(0.03, 0.0625, 0.001, check)["overrun"] is True
    assert out.getvalue() == "warning: overrun at cycle 0: period 62.5 ms > 40 ms\n"
    loop, _ = make_loop(out := io.StringIO(), backend="emulated")
    assert loop._account_cycle(0.0625, 0.03, 0.001, check)["overrun"] is True
    assert out.getvalue() == "warning: overrun at cycle 0: period 62.5 ms > 40 ms\n"
    assert loop.timing.silences == [0.0125] and loop.timing.work == [0.001]
    loop, _ = make_loop(out := io.StringIO(), dt=0.6)  # 1.67 Hz: the nominal period in whole ms
    assert loop._account_cycle(0.7, 0.7, 0.001, check)["overrun"] is True
    assert out.getvalue() == "warning: overrun at cycle 0: period 700.0 ms > 600 ms\n"


# ------------------------------------------------------------------ realtime
def test_realtime_paces_the_loop_on_the_wall_clock_and_otherwise_it_runs_free(
    deploy: Callable[..., DeployRun], tmp_path: Path
) -> None:
    run = deploy(ConstantPolicy([0.0, 0.0, 0.0, 0.0]), realtime=True)
    assert run.error is None, run.output
    assert 0.035 < run.summary["wall_period_mean_s"] < 0.06  # 25 Hz
    run = deploy(ConstantPolicy([0.0, 0.0, 0.0, 0.0]), log=tmp_path / "free.jsonl")
    assert run.summary["wall_period_mean_s"] < 0.02


class FakeTime:
    """``perf_counter`` and ``sleep`` of a clock the test sets; sleeps are recorded, not taken."""

    def __init__(self, now: float) -> None:
        self.now = now
        self.sleeps: list[float] = []

    def perf_counter(self) -> float:
        return self.now

    def sleep(self, s: float) -> None:
        self.sleeps.append(s)


def test_an_episode_clock_gives_no_period_for_its_first_cycle(monkeypatch: pytest.MonkeyPatch) -> None:
    fake = FakeTime(100.0)
    monkeypatch.setattr(deploy_loop, "time", fake)
    clock = EpisodeClock()
    assert clock.tick(2.0) == (100.0, None, None)
    fake.now = 100.25
    assert clock.tick(2.5) == (100.25, 0.5, 0.25)
    fake.now = 101.0
    assert clock.tick(2.75) == (101.0, 0.25, 0.75)
    assert (clock.prev_wall, clock.prev_clock) == (101.0, 2.75)


def test_pacing_sleeps_until_the_next_deadline_and_never_catches_up_more_than_a_period(
    monkeypatch: pytest.MonkeyPatch,
) -> None:
    fake = FakeTime(10.125)
    monkeypatch.setattr(deploy_loop, "time", fake)
    clock = EpisodeClock(deadline=10.0)
    clock.pace(0.5)
    assert clock.deadline == 10.5 and fake.sleeps == [0.375]
    fake.now = 11.0  # exactly at the next deadline: no sleep
    clock.pace(0.5)
    assert clock.deadline == 11.0 and fake.sleeps == [0.375]
    fake.now = 13.0  # 2 s late: the deadline moves to a period ago, no burst of cycles
    clock.pace(0.5)
    assert clock.deadline == 12.5 and fake.sleeps == [0.375]
    clock.pace(0.5)
    assert clock.deadline == 13.0 and fake.sleeps == [0.375]
    fake.now = 12.75
    clock.pace(0.5)
    assert clock.deadline == 13.5 and fake.sleeps == [0.375, 0.75]


def test_a_new_episode_clock_is_due_now() -> None:
    before = time.perf_counter()
    clock = EpisodeClock()
    assert before <= clock.deadline <= time.perf_counter()
    assert clock.prev_wall is None and clock.prev_clock is None


# ------------------------------------------------------------------ a failing policy
def test_a_policy_that_raises_is_a_nan_action_stop_in_one_line() -> None:
    error = ValueError("mean is NaN\n  at layer 3")

    def failing(obs: dict[str, np.ndarray]) -> np.ndarray:
        raise error

    with pytest.raises(SafetyStop) as caught:
        _act(failing, {})
    assert caught.value.reason is StopReason.NAN_ACTION and caught.value.joint is None
    assert str(caught.value) == "the policy failed to act (ValueError: mean is NaN)"
    assert caught.value.__cause__ is error
    seen: list[Any] = []
    assert _act(lambda obs: seen.append(obs) or 7, {"observation": 1}) == 7
    assert seen == [{"observation": 1}]
