"""``bioscara train`` / ``bioscara eval`` and the ``training`` package behind them.

Every training run here is tiny (a few hundred env steps, 16x16 networks, two
evaluation episodes) from a config file written to a temporary directory, so
the module stays well under a minute on a shared CPU. Runs reused by several
tests are module-scoped fixtures; tests that edit a run work on a copy.
"""

from __future__ import annotations

import contextlib
import json
import shutil
import signal
import subprocess
import sys
import time
from collections.abc import Callable, Iterator
from dataclasses import dataclass
from pathlib import Path
from types import SimpleNamespace
from typing import Any

import gymnasium as gym
import numpy as np
import pytest
import torch as th
import yaml
from rigs import run_blocked
from stable_baselines3 import PPO, SAC, TD3, HerReplayBuffer
from stable_baselines3.common.buffers import DictReplayBuffer
from stable_baselines3.common.off_policy_algorithm import OffPolicyAlgorithm
from stable_baselines3.common.save_util import load_from_pkl, load_from_zip_file

from bioscara_gym.cli import EXIT_INTERRUPTED, main
from bioscara_gym.errors import HyperparamError, MetadataError, MissingExtraError, TrainingError
from bioscara_gym.fsutil import atomic_open
from bioscara_gym.training.algos import ALGOS
from bioscara_gym.training.checkpoints import STATE_NAME
from bioscara_gym.training.features import GoalErrorExtractor
from bioscara_gym.training.hyperparams import (
    EXTRA_KEYS,
    Hyperparams,
    default_config_path,
    load_hyperparams,
)
from bioscara_gym.training.literals import parse_literal_call
from bioscara_gym.training.metadata import (
    METADATA_NAME,
    build_metadata,
    check_metadata,
    read_metadata,
    resolve_env_id,
    write_metadata,
)
from bioscara_gym.training.sb3 import algo_kwargs
from bioscara_gym.training.zoo import SuccessEvalCallback

# Resuming SB3's HER buffer mid-episode truncates the episode cut by the Ctrl-C, as intended.
pytestmark = pytest.mark.filterwarnings("ignore:The last trajectory in the replay buffer:UserWarning")

REACH = "Bioscara-Reach-v0"
PICK = "Bioscara-PickPlace-v1"
TOTAL = 300  # env steps of every tiny off-policy run
INTERRUPT_AT = 170  # mid-episode (episodes are 50 steps), after learning_starts
REACH_KWARGS = {"control_mode": "cartesian", "reward_type": "dense"}

#: A tiny SAC/TD3 + HER entry: learns from step 100, evaluates at 200 and at the end.
TINY_OFF_POLICY: dict[str, Any] = {
    "n_timesteps": TOTAL,
    "policy": "MultiInputPolicy",
    "buffer_size": 1000,
    "batch_size": 32,
    "learning_starts": 100,
    "replay_buffer_class": "HerReplayBuffer",
    "replay_buffer_kwargs": "dict(goal_selection_strategy='future', n_sampled_goal=4)",
    # As the packaged config: the goal error as a feature (saved, loaded, exported with the model).
    "policy_kwargs": "dict(net_arch=[16, 16], features_extractor_class=GoalErrorExtractor)",
    "env_kwargs": "dict(control_mode='cartesian', reward_type='dense')",
    "eval_freq": 200,
    "eval_episodes": 2,
}
TINY: dict[str, dict[str, Any]] = {
    "sac": TINY_OFF_POLICY,
    "td3": {**TINY_OFF_POLICY, "noise_type": "normal", "noise_std": 0.2},
    "ppo": {
        "n_timesteps": 128,
        "policy": "MultiInputPolicy",
        "n_steps": 64,
        "batch_size": 32,
        "n_epochs": 1,
        "policy_kwargs": "dict(net_arch=[16, 16])",
        "env_kwargs": "dict(reward_type='dense')",
        "eval_freq": 200,
        "eval_episodes": 2,
    },
}


def write_config(path: Path, entries: dict[str, dict[str, Any]]) -> Path:
    """Write an rl-zoo3 style hyperparameter file ``{env_id: entry}`` and return its path."""
    path.write_text(yaml.safe_dump(entries, sort_keys=False), encoding="utf-8")
    return path


def train_argv(out: Path, config: Path, *extra: str) -> list[str]:
    """``bioscara train`` arguments of a tiny run into ``out``."""
    return ["train", "--out", str(out), "--config", str(config), "--no-progress", *extra]


def one_line_error(capsys: pytest.CaptureFixture[str], command: str) -> str:
    """The single line on stderr, checked to be ``bioscara COMMAND: error: ...``."""
    err = capsys.readouterr().err
    lines = err.strip().splitlines()
    assert len(lines) == 1, f"expected a one-line error, got {len(lines)} lines:\n{err}"
    assert lines[0].startswith(f"bioscara {command}: error: "), lines[0]
    return lines[0]


def edit_metadata(run: Path, tmp_path: Path, **changes: Any) -> Path:
    """A copy of ``run`` in ``tmp_path`` whose metadata has ``changes`` (dotted keys: ``a.b``)."""
    copy = Path(shutil.copytree(run, tmp_path / "edited"))
    path = copy / METADATA_NAME
    metadata = json.loads(path.read_text(encoding="utf-8"))
    for key, value in changes.items():
        *parents, leaf = key.split(".")
        node = metadata
        for p in parents:
            node = node[p]
        node[leaf] = value
    path.write_text(json.dumps(metadata), encoding="utf-8")
    return copy / "model.zip"


def saved_num_timesteps(model_zip: Path) -> int:
    """``num_timesteps`` recorded in a saved SB3 model, read without rebuilding the model."""
    data, _, _ = load_from_zip_file(model_zip, device="cpu")
    return int(data["num_timesteps"])


@pytest.fixture(scope="module")
def sac_run(tmp_path_factory: pytest.TempPathFactory) -> Path:
    """The output directory of a finished tiny SAC + HER run on Reach (300 steps)."""
    root = tmp_path_factory.mktemp("sac")
    config = write_config(root / "cfg.yaml", {REACH: TINY["sac"]})
    rc = main(train_argv(root / "run", config))
    assert rc == 0
    return root / "run"


@pytest.fixture
def reach_env() -> Iterator[gym.Env]:
    """Reach with the tiny runs' env kwargs, closed at teardown."""
    env = gym.make(REACH, **REACH_KWARGS)
    yield env
    env.close()


# ------------------------------------------------------- end-to-end train/eval


def test_train_writes_a_model_that_loads_with_the_trained_step_count(
    sac_run: Path, reach_env: gym.Env
) -> None:
    model = SAC.load(sac_run / "model.zip", env=reach_env, device="cpu")
    assert model.num_timesteps == TOTAL


def test_train_writes_metadata_describing_the_run(sac_run: Path, reach_env: gym.Env) -> None:
    metadata = read_metadata(sac_run / "model.zip")
    assert metadata["env_id"] == REACH
    assert metadata["algo"] == "sac"
    assert metadata["timesteps"] == TOTAL
    assert metadata["env_kwargs"]["control_mode"] == "cartesian"
    assert metadata["final_eval"]["episodes"] == TINY["sac"]["eval_episodes"]
    check_metadata(metadata, reach_env, REACH)  # matches the env it was trained on


def test_train_prints_where_the_model_and_metadata_went(
    tmp_path: Path, capsys: pytest.CaptureFixture[str]
) -> None:
    config = write_config(tmp_path / "cfg.yaml", {REACH: {**TINY["sac"], "n_timesteps": 100}})
    assert main(train_argv(tmp_path / "run", config)) == 0
    out = capsys.readouterr().out
    assert "final success rate" in out
    assert "model.zip" in out
    assert METADATA_NAME in out


def test_eval_of_trained_model_writes_json_with_the_results(sac_run: Path, tmp_path: Path) -> None:
    report = tmp_path / "eval.json"
    rc = main(["eval", "--model", str(sac_run / "model.zip"), "--episodes", "3", "--json", str(report)])
    assert rc == 0
    results = json.loads(report.read_text(encoding="utf-8"))
    assert results["episodes"] == 3
    assert 0.0 <= results["success_rate"] <= 1.0
    assert np.isfinite(results["mean_final_distance"])


def test_eval_of_trained_model_prints_a_table(
    sac_run: Path, tmp_path: Path, capsys: pytest.CaptureFixture[str]
) -> None:
    rc = main(["eval", "--model", str(sac_run / "model.zip"), "--episodes", "3"])
    assert rc == 0
    out = capsys.readouterr().out
    for metric in ("episodes", "success rate", "mean final distance", "mean return", "stalls"):
        assert metric in out


@pytest.mark.parametrize("algo", ["td3", "ppo"])
def test_algo_trains_a_tiny_run_into_a_loadable_model(algo: str, tmp_path: Path) -> None:
    config = write_config(tmp_path / "cfg.yaml", {REACH: TINY[algo]})
    assert main(train_argv(tmp_path / "run", config, "--algo", algo)) == 0
    metadata = read_metadata(tmp_path / "run" / "model.zip")
    assert metadata["algo"] == algo
    env = gym.make(REACH, **metadata["env_kwargs"])
    try:
        model = ALGOS[algo].load(tmp_path / "run" / "model.zip", env=env, device="cpu")
    finally:
        env.close()
    assert isinstance(model, TD3 if algo == "td3" else PPO)
    assert model.num_timesteps >= TINY[algo]["n_timesteps"]


def test_ppo_with_two_envs_steps_them_in_subprocesses(
    tmp_path: Path, monkeypatch: pytest.MonkeyPatch
) -> None:
    # n_envs 2 x n_steps 64 = one rollout of 128 steps, collected by two worker processes.
    from stable_baselines3.common.vec_env import SubprocVecEnv

    made: list[object] = []
    real_init = SubprocVecEnv.__init__

    def spy(self: SubprocVecEnv, *args: Any, **kwargs: Any) -> None:
        real_init(self, *args, **kwargs)
        made.append(self)

    monkeypatch.setattr(SubprocVecEnv, "__init__", spy)
    config = write_config(tmp_path / "cfg.yaml", {REACH: TINY["ppo"]})
    assert main(train_argv(tmp_path / "run", config, "--algo", "ppo", "--n-envs", "2")) == 0
    assert len(made) == 1 and made[0].num_envs == 2  # type: ignore[attr-defined]
    assert read_metadata(tmp_path / "run" / "model.zip")["algo"] == "ppo"


# ------------------------------------------------------------ interrupt/resume


@dataclass
class InterruptedRun:
    """A tiny SAC run stopped by Ctrl-C at :data:`INTERRUPT_AT` steps."""

    out: Path
    config: Path
    exit_code: int
    stderr: str


@dataclass
class ResumedRun:
    """A copy of :class:`InterruptedRun` continued with ``--resume``."""

    out: Path
    config: Path
    exit_code: int
    loaded_replay_sizes: list[int]
    stderr: str


def scripted_evaluations(
    monkeypatch: pytest.MonkeyPatch, callback: SuccessEvalCallback, rates: list[float]
) -> list[int]:
    """``callback.evaluate`` returns ``rates`` in turn; the episode counts it was asked for."""
    asked: list[int] = []

    def evaluate(episodes: int, continuing: object = (), max_failures: int | None = None) -> SimpleNamespace:
        asked.append(episodes)
        return SimpleNamespace(success_rate=rates.pop(0))

    monkeypatch.setattr(callback, "evaluate", evaluate)
    return asked


def test_success_callback_records_the_target_and_stops_at_the_margin(monkeypatch: pytest.MonkeyPatch) -> None:
    cb = SuccessEvalCallback(eval_freq=1000, eval_episodes=100, target_success=0.95, stop_success=0.98)
    # quick 0.90 | quick 1.0, full 0.96 (target) | quick 0.95 (< stop: no full) | quick 1.0, full 0.99
    asked = scripted_evaluations(monkeypatch, cb, [0.90, 1.0, 0.96, 0.95, 1.0, 0.99])
    going = []
    for step in (1000, 2000, 3000, 4000):
        cb.num_timesteps = step
        going.append(cb._on_step())
    assert going == [True, True, True, False]
    assert asked == [20, 20, 100, 20, 20, 100]
    assert (cb.reached_at, cb.stopped_at) == (2000, 4000)


def test_success_callback_stops_at_the_target_by_default(monkeypatch: pytest.MonkeyPatch) -> None:
    cb = SuccessEvalCallback(eval_freq=1000, eval_episodes=100, target_success=0.95)
    scripted_evaluations(monkeypatch, cb, [1.0, 0.95])
    cb.num_timesteps = 1000
    assert cb._on_step() is False
    assert (cb.reached_at, cb.stopped_at) == (1000, 1000)


def test_success_callback_first_evaluation_then_the_multiples(monkeypatch: pytest.MonkeyPatch) -> None:
    cb = SuccessEvalCallback(eval_freq=1000, eval_episodes=100, target_success=0.95, first_eval=1)
    asked = scripted_evaluations(monkeypatch, cb, [0.5, 0.5, 0.5])
    for step in (1, 2, 999, 1000, 1001, 1999, 2000):  # as made (rl-zoo3 may skip the training start)
        cb.num_timesteps = step
        cb._on_step()
    assert asked == [20, 20, 20]  # at 1, 1000 and 2000
    cb.num_timesteps = 5000  # a resumed run: the next multiple, not the first evaluation
    cb._on_training_start()
    assert cb._next == 6000


def test_success_callback_resumed_at_its_first_evaluation_waits_for_the_next() -> None:
    cb = SuccessEvalCallback(eval_freq=1000)
    cb.num_timesteps = 1000  # evaluated there before the run stopped
    cb._on_training_start()
    assert cb._next == 2000
    cb.num_timesteps = 0
    cb._on_training_start()
    assert cb._next == 1000


def test_success_callback_defaults_its_first_evaluation_to_eval_freq(monkeypatch: pytest.MonkeyPatch) -> None:
    cb = SuccessEvalCallback(eval_freq=1000, eval_episodes=100, target_success=0.95)
    asked = scripted_evaluations(monkeypatch, cb, [0.5])
    cb.num_timesteps = 0
    cb._on_training_start()
    for step in (1, 999, 1000):
        cb.num_timesteps = step
        cb._on_step()
    assert asked == [20]


@pytest.mark.parametrize("first_eval", [0, -1])
def test_success_callback_refuses_a_first_evaluation_before_the_first_step(first_eval: int) -> None:
    with pytest.raises(ValueError, match=rf"first_eval \({first_eval}\) must be >= 1"):
        SuccessEvalCallback(first_eval=first_eval)


class SeededOutcomes(gym.Env):
    """Two-step episodes that fail for the seeds in ``failing``; records every reset's seed."""

    observation_space = gym.spaces.Box(-1.0, 1.0, (1,))
    action_space = gym.spaces.Box(-1.0, 1.0, (1,))

    def __init__(self, failing: set[int]) -> None:
        self.failing, self.seeds, self._t = failing, [], 0

    def reset(self, *, seed: int | None = None, options: dict | None = None) -> tuple[np.ndarray, dict]:
        self.seeds.append(seed)
        self._t = 0
        return np.zeros(1, np.float32), {}

    def step(self, action: np.ndarray) -> tuple[np.ndarray, float, bool, bool, dict]:
        self._t += 1
        info = {"is_success": self.seeds[-1] not in self.failing, "distance": 0.0}
        return np.zeros(1, np.float32), 0.0, False, self._t == 2, info


def test_success_callback_confirms_going_on_from_the_quick_episodes(monkeypatch: pytest.MonkeyPatch) -> None:
    from stable_baselines3.common.logger import Logger

    import bioscara_gym.training.zoo as zoo

    env = SeededOutcomes(failing={103, 109})
    monkeypatch.setattr(zoo, "sb3_policy", lambda model: lambda obs: np.zeros(1, np.float32))
    cb = SuccessEvalCallback(
        eval_freq=10, eval_episodes=12, quick_episodes=5, target_success=0.75, env=env, seed=100, verbose=0
    )
    cb.model = SimpleNamespace(logger=Logger(folder=None, output_formats=[]))
    cb.num_timesteps = 10
    assert cb._on_step() is False  # quick 4/5, then 10/12: the target, and the stop
    assert env.seeds == list(range(100, 112))  # each seed once: the quick episodes are the first five
    assert (cb.last.episodes, cb.last.success_rate) == (12, 10 / 12)
    assert [r.success for r in cb.results] == [True] * 3 + [False] + [True] * 5 + [False] + [True] * 2


def test_success_callback_stops_a_confirmation_at_the_failure_that_decides_it(
    monkeypatch: pytest.MonkeyPatch, capsys: pytest.CaptureFixture[str]
) -> None:
    from stable_baselines3.common.logger import Logger

    import bioscara_gym.training.zoo as zoo

    env = SeededOutcomes(failing={103, 106, 107, 108, 110})
    monkeypatch.setattr(zoo, "sb3_policy", lambda model: lambda obs: np.zeros(1, np.float32))
    cb = SuccessEvalCallback(
        eval_freq=10, eval_episodes=12, quick_episodes=5, target_success=0.75, env=env, seed=100, verbose=1
    )
    cb.model = SimpleNamespace(logger=Logger(folder=None, output_formats=[]))
    cb.num_timesteps = 10
    assert cb._on_step() is True  # quick 4/5; 9 of 12 needed, at most 3 failures: the 4th is seed 108
    assert env.seeds == list(range(100, 109))
    assert (cb.last.episodes, cb.last.success_rate) == (9, 5 / 9)
    assert cb.reached_at is None
    assert "over 9 of 12 (stopped: 4 failures) episodes" in capsys.readouterr().out


def test_success_callback_plays_no_more_when_the_given_episodes_decide(
    monkeypatch: pytest.MonkeyPatch,
) -> None:
    from stable_baselines3.common.logger import Logger

    import bioscara_gym.training.zoo as zoo
    from bioscara_gym.training.evaluate import EpisodeResult

    env = SeededOutcomes(failing=set())
    monkeypatch.setattr(zoo, "sb3_policy", lambda model: lambda obs: np.zeros(1, np.float32))
    cb = SuccessEvalCallback(eval_episodes=12, env=env, seed=100, verbose=0)
    cb.model = SimpleNamespace(logger=Logger(folder=None, output_formats=[]))
    failed = EpisodeResult(success=False, stalled=False, distance=0.0, total=0.0, steps=2)
    stats = cb.evaluate(12, continuing=[failed] * 4, max_failures=3)
    assert env.seeds == []
    assert (stats.episodes, stats.success_rate) == (4, 0.0)
    stats = cb.evaluate(12, continuing=[failed] * 3, max_failures=3)  # at the edge: the rest may all pass
    assert env.seeds == list(range(103, 112))
    assert (stats.episodes, stats.success_rate) == (12, 0.75)


@pytest.fixture(scope="module")
def interrupted_run(tmp_path_factory: pytest.TempPathFactory) -> InterruptedRun:
    """Ctrl-C simulated by the evaluation callback raising ``KeyboardInterrupt`` mid-episode."""
    root = tmp_path_factory.mktemp("interrupted")
    config = write_config(root / "cfg.yaml", {REACH: TINY["sac"]})
    original = SuccessEvalCallback._on_step

    def interrupt(self: SuccessEvalCallback) -> bool:
        if self.num_timesteps >= INTERRUPT_AT:
            raise KeyboardInterrupt
        return original(self)

    with pytest.MonkeyPatch.context() as mp:
        mp.setattr(SuccessEvalCallback, "_on_step", interrupt)
        stderr: list[str] = []
        mp.setattr("sys.stderr", _Recorder(stderr))
        rc = main(train_argv(root / "run", config))
    return InterruptedRun(out=root / "run", config=config, exit_code=rc, stderr="".join(stderr))


class _Recorder:
    """A text stream appending everything written to a list."""

    def __init__(self, sink: list[str]) -> None:
        self.sink = sink

    def write(self, text: str) -> int:
        self.sink.append(text)
        return len(text)

    def flush(self) -> None:
        pass

    def isatty(self) -> bool:
        return False


@pytest.fixture(scope="module")
def resumed_run(interrupted_run: InterruptedRun, tmp_path_factory: pytest.TempPathFactory) -> ResumedRun:
    """``bioscara train --resume`` on a copy of the interrupted run, recording the loaded replay buffer."""
    out = Path(shutil.copytree(interrupted_run.out, tmp_path_factory.mktemp("resumed") / "run"))
    sizes: list[int] = []
    original = OffPolicyAlgorithm.load_replay_buffer

    def spy(self: OffPolicyAlgorithm, path: Any, truncate_last_traj: bool = True) -> None:
        original(self, path, truncate_last_traj)
        sizes.append(self.replay_buffer.size())

    stderr: list[str] = []
    with pytest.MonkeyPatch.context() as mp:
        mp.setattr(OffPolicyAlgorithm, "load_replay_buffer", spy)
        mp.setattr("sys.stderr", _Recorder(stderr))
        rc = main(["train", "--resume", "--out", str(out), "--no-progress"])
    return ResumedRun(out, interrupted_run.config, rc, sizes, "".join(stderr))


def test_interrupted_train_exits_130_with_one_line(interrupted_run: InterruptedRun) -> None:
    assert interrupted_run.exit_code == EXIT_INTERRUPTED == 130
    checkpoint = interrupted_run.out / "checkpoints" / f"ckpt_{INTERRUPT_AT}_steps.zip"
    assert interrupted_run.stderr.strip() == (
        f"bioscara train: interrupted by SIGINT; checkpoint {checkpoint} "
        f"(continue with `bioscara train --resume --out {interrupted_run.out}`)"
    )


def test_interrupted_train_leaves_a_checkpoint_and_its_replay_buffer(interrupted_run: InterruptedRun) -> None:
    checkpoints = interrupted_run.out / "checkpoints"
    assert (checkpoints / f"ckpt_{INTERRUPT_AT}_steps.zip").is_file()
    assert (checkpoints / f"ckpt_{INTERRUPT_AT}_steps_replay.pkl").is_file()
    assert saved_num_timesteps(checkpoints / f"ckpt_{INTERRUPT_AT}_steps.zip") == INTERRUPT_AT


def test_interrupted_train_writes_no_final_model(interrupted_run: InterruptedRun) -> None:
    assert not (interrupted_run.out / "model.zip").exists()


def test_resume_says_in_one_line_that_the_cut_episode_ends_where_it_was_cut(resumed_run: ResumedRun) -> None:
    # Seen: stable-baselines3's raw 4-line HER warning, suggesting an option that would be wrong here;
    # then our line said the episode was dropped, where SB3's truncate_last_trajectory keeps it, ended.
    assert resumed_run.stderr.strip() == (
        "bioscara train: warning: the episode the checkpoint cut short stays in the replay buffer, "
        "ended where it was cut (training starts a new one)"
    )


def test_resume_trains_up_to_the_original_total(resumed_run: ResumedRun) -> None:
    assert resumed_run.exit_code == 0
    assert saved_num_timesteps(resumed_run.out / "model.zip") == TOTAL


def test_resume_loads_the_checkpoint_replay_buffer(resumed_run: ResumedRun) -> None:
    saved = load_from_pkl(resumed_run.out / "checkpoints" / f"ckpt_{INTERRUPT_AT}_steps_replay.pkl")
    assert isinstance(saved, HerReplayBuffer)
    assert saved.size() > 0
    assert resumed_run.loaded_replay_sizes == [saved.size()]


def test_resume_writes_metadata_with_the_total_timesteps(resumed_run: ResumedRun) -> None:
    assert read_metadata(resumed_run.out / "model.zip")["timesteps"] == TOTAL


def test_resume_keeps_the_run_config_for_a_later_resume(resumed_run: ResumedRun) -> None:
    # A second Ctrl-C then --resume must still use the run's config (its env_kwargs), not the packaged one.
    state = json.loads((resumed_run.out / STATE_NAME).read_text(encoding="utf-8"))
    assert state["config"] == str(resumed_run.config)


def test_sigterm_saves_a_checkpoint_and_exits_143_with_one_line(tmp_path: Path) -> None:
    """A real ``bioscara train`` process, sent SIGTERM once training has started (about 10 s)."""
    config = write_config(tmp_path / "cfg.yaml", {REACH: {**TINY["sac"], "n_timesteps": 100_000}})
    out = tmp_path / "run"
    argv = [sys.executable, "-m", "bioscara_gym.cli", *train_argv(out, config)]
    proc = subprocess.Popen(argv, stdout=subprocess.PIPE, stderr=subprocess.PIPE, text=True)
    try:
        deadline = time.monotonic() + 60
        while not (out / "tb").exists() and proc.poll() is None and time.monotonic() < deadline:
            time.sleep(0.1)  # SB3 makes the TensorBoard directory as learning starts
        assert (out / "tb").exists(), "training did not start"
        proc.send_signal(signal.SIGTERM)
        _, stderr = proc.communicate(timeout=60)
    finally:
        if proc.poll() is None:
            proc.kill()
            proc.wait()
    assert proc.returncode == 143
    assert "Traceback" not in stderr
    lines = [line for line in stderr.splitlines() if line.startswith("bioscara")]
    assert len(lines) == 1, stderr
    assert lines[0].startswith("bioscara train: interrupted by SIGTERM; checkpoint ")
    [checkpoint] = (out / "checkpoints").glob("ckpt_*_steps.zip")
    assert str(checkpoint) in lines[0]
    assert checkpoint.with_name(checkpoint.stem + "_replay.pkl").is_file()
    env = gym.make(REACH, **REACH_KWARGS)
    try:
        assert SAC.load(checkpoint, env=env, device="cpu").num_timesteps < 100_000
    finally:
        env.close()
    assert not (out / "model.zip").exists()


def test_a_signal_while_the_envs_close_after_the_save_keeps_the_run_done(
    tmp_path: Path, monkeypatch: pytest.MonkeyPatch, capsys: pytest.CaptureFixture[str]
) -> None:
    # Seen (a review): SIGINT while SubprocVecEnv's workers were joined, model.zip already saved:
    # "interrupted by SIGINT before training started; nothing saved", exit 130.
    import os

    from stable_baselines3.common.vec_env import DummyVecEnv

    close = DummyVecEnv.close

    def close_under_a_signal(self: DummyVecEnv) -> None:
        os.kill(os.getpid(), signal.SIGINT)
        close(self)

    monkeypatch.setattr(DummyVecEnv, "close", close_under_a_signal)
    config = write_config(tmp_path / "cfg.yaml", {REACH: TINY["sac"]})
    assert main(train_argv(tmp_path / "run", config)) == 0
    assert (tmp_path / "run" / "model.zip").is_file() and (tmp_path / "run" / METADATA_NAME).is_file()
    assert "interrupted" not in capsys.readouterr().err


def _truncate(path: Path) -> None:
    """Cut ``path`` to its first half, as a crash or a full disk would."""
    data = path.read_bytes()
    path.write_bytes(data[: len(data) // 2])


def test_resume_skips_a_truncated_newest_checkpoint_with_a_one_line_warning(
    interrupted_run: InterruptedRun, tmp_path: Path, capsys: pytest.CaptureFixture[str]
) -> None:
    out = Path(shutil.copytree(interrupted_run.out, tmp_path / "run"))
    good = out / "checkpoints" / f"ckpt_{INTERRUPT_AT}_steps.zip"
    newest = out / "checkpoints" / "ckpt_250_steps.zip"
    shutil.copy(good, newest)
    _truncate(newest)
    rc = main(["train", "--resume", "--out", str(out), "--no-progress"])
    err = capsys.readouterr().err
    assert rc == 0
    assert err.strip().splitlines() == [
        "bioscara train: warning: the episode the checkpoint cut short stays in the replay buffer, "
        "ended where it was cut (training starts a new one)",
        f"bioscara train: warning: checkpoint {newest} cannot be loaded (BadZipFile: no data, policy.pth "
        f"in it (truncated?)); resuming from {good.name} instead",
    ]
    assert saved_num_timesteps(out / "model.zip") == TOTAL


def test_resume_with_no_loadable_checkpoint_is_a_one_line_error(
    interrupted_run: InterruptedRun, tmp_path: Path, capsys: pytest.CaptureFixture[str]
) -> None:
    out = Path(shutil.copytree(interrupted_run.out, tmp_path / "run"))
    checkpoint = out / "checkpoints" / f"ckpt_{INTERRUPT_AT}_steps.zip"
    _truncate(checkpoint)
    rc = main(["train", "--resume", "--out", str(out), "--no-progress"])
    assert rc == 2
    assert one_line_error(capsys, "train") == (
        f"bioscara train: error: cannot resume: checkpoint {checkpoint} cannot be loaded "
        "(BadZipFile: no data, policy.pth in it (truncated?))"
    )
    assert not (out / "model.zip").exists()


def test_a_checkpoint_save_cut_short_leaves_the_previous_file(tmp_path: Path) -> None:
    path = tmp_path / "ckpt_100_steps.zip"
    path.write_bytes(b"complete")
    with pytest.raises(KeyboardInterrupt), atomic_open(path) as f:
        f.write(b"half")
        raise KeyboardInterrupt
    assert path.read_bytes() == b"complete"
    assert list(tmp_path.iterdir()) == [path]  # no temporary file left behind


def test_resume_with_nothing_to_resume_is_refused(tmp_path: Path, capsys: pytest.CaptureFixture[str]) -> None:
    rc = main(["train", "--resume", "--out", str(tmp_path / "empty"), "--no-progress"])
    assert rc != 0
    assert "nothing to resume" in one_line_error(capsys, "train")


# --------------------------------------------------------------- expert eval


def test_eval_expert_on_reach_succeeds_every_episode(tmp_path: Path) -> None:
    report = tmp_path / "expert.json"
    rc = main(["eval", "--expert", "--env", "Bioscara-Reach", "--episodes", "5", "--json", str(report)])
    assert rc == 0
    results = json.loads(report.read_text(encoding="utf-8"))
    assert results["episodes"] == 5
    assert results["success_rate"] == 1.0
    assert results["source"] == "expert"


def test_eval_expert_on_pick_place_reports_its_success_rate(tmp_path: Path) -> None:
    report = tmp_path / "expert.json"
    rc = main(["eval", "--expert", "--env", "Bioscara-PickPlace", "--episodes", "2", "--json", str(report)])
    assert rc == 0
    results = json.loads(report.read_text(encoding="utf-8"))
    assert results["episodes"] == 2
    assert results["success_rate"] == 1.0


# ----------------------------------------------------------------- bad input


def test_train_unknown_env_is_a_one_line_error(tmp_path: Path, capsys: pytest.CaptureFixture[str]) -> None:
    rc = main(["train", "--env", "Bioscara-Nope", "--out", str(tmp_path / "run"), "--no-progress"])
    assert rc != 0
    line = one_line_error(capsys, "train")
    assert "Bioscara-Nope" in line
    assert REACH in line  # names what is registered


def test_train_error_prints_user_input_verbatim(tmp_path: Path, capsys: pytest.CaptureFixture[str]) -> None:
    # "[/x]" is a closing tag to Rich's markup parser: it must be printed, not parsed.
    rc = main(["train", "--env", "[/x]", "--out", str(tmp_path / "run"), "--no-progress"])
    assert rc != 0
    assert "'[/x]'" in one_line_error(capsys, "train")


def test_train_unknown_algo_is_a_one_line_error(tmp_path: Path, capsys: pytest.CaptureFixture[str]) -> None:
    rc = main(["train", "--algo", "a2c", "--out", str(tmp_path / "run"), "--no-progress"])
    assert rc != 0
    line = one_line_error(capsys, "train")
    assert "a2c" in line
    assert "sac" in line


def test_train_missing_config_is_a_one_line_error(tmp_path: Path, capsys: pytest.CaptureFixture[str]) -> None:
    rc = main(train_argv(tmp_path / "run", tmp_path / "missing.yaml"))
    assert rc != 0
    assert "missing.yaml" in one_line_error(capsys, "train")


def test_train_config_that_is_not_yaml_is_a_one_line_error(
    tmp_path: Path, capsys: pytest.CaptureFixture[str]
) -> None:
    config = tmp_path / "cfg.yaml"
    config.write_text(f"{REACH}: [1, 2\n", encoding="utf-8")
    rc = main(train_argv(tmp_path / "run", config))
    assert rc != 0
    assert "not valid YAML" in one_line_error(capsys, "train")


def test_train_config_without_an_entry_for_the_env_is_a_one_line_error(
    tmp_path: Path, capsys: pytest.CaptureFixture[str]
) -> None:
    config = write_config(tmp_path / "cfg.yaml", {PICK: TINY["sac"]})
    rc = main(train_argv(tmp_path / "run", config))
    assert rc != 0
    line = one_line_error(capsys, "train")
    assert f"no entry for {REACH}" in line


def test_train_config_with_a_code_string_is_a_one_line_error(
    tmp_path: Path, capsys: pytest.CaptureFixture[str]
) -> None:
    entry = {**TINY["sac"], "policy_kwargs": "__import__('os')"}
    config = write_config(tmp_path / "cfg.yaml", {REACH: entry})
    rc = main(train_argv(tmp_path / "run", config))
    assert rc != 0
    line = one_line_error(capsys, "train")
    assert "policy_kwargs" in line
    assert not (tmp_path / "run" / "model.zip").exists()


def test_train_bad_input_leaves_no_output_directory(tmp_path: Path) -> None:
    main(["train", "--algo", "a2c", "--out", str(tmp_path / "run"), "--no-progress"])
    assert not (tmp_path / "run").exists()


def test_eval_without_model_or_expert_is_a_one_line_error(capsys: pytest.CaptureFixture[str]) -> None:
    assert main(["eval", "--episodes", "1"]) != 0
    assert "--model" in one_line_error(capsys, "eval")


def test_eval_refuses_a_video_name_it_cannot_write_before_the_episodes(
    tmp_path: Path, capsys: pytest.CaptureFixture[str]
) -> None:
    # Seen (a hostile test): the episodes ran, then imageio named a temporary file; the folder stayed.
    video = tmp_path / "new" / "v.txt"
    assert (
        main(["eval", "--expert", "--env", "Bioscara-Reach", "--episodes", "1", "--video", str(video)]) == 2
    )
    assert one_line_error(capsys, "eval").endswith(
        f"--video {video}: a video file name ends in .mp4, .mkv, .mov, .avi, .webm, .gif"
    )
    assert not (tmp_path / "new").exists()


def test_eval_makes_the_folders_of_its_json(tmp_path: Path) -> None:
    # The output check must not refuse what eval makes itself (a reviewer caught that it did).
    report = tmp_path / "new" / "deeper" / "e.json"
    assert (
        main(["eval", "--expert", "--env", "Bioscara-Reach", "--episodes", "1", "--json", str(report)]) == 0
    )
    assert json.loads(report.read_text())["episodes"] == 1


@pytest.mark.skipif(not Path("/proc").is_dir(), reason="no /proc: a folder that refuses files")
def test_eval_refuses_a_json_it_cannot_write_before_the_episodes(capsys: pytest.CaptureFixture[str]) -> None:
    # Seen (a hostile test): the episodes ran, then a temporary file in /proc was named.
    args = ["eval", "--expert", "--env", "Bioscara-Reach", "--episodes", "1", "--json", "/proc/x.json"]
    assert main(args) == 2
    assert "--json /proc/x.json: cannot write in /proc: " in one_line_error(capsys, "eval")


def test_eval_expert_on_unknown_env_is_a_one_line_error(capsys: pytest.CaptureFixture[str]) -> None:
    assert main(["eval", "--expert", "--env", "Bioscara-Nope", "--episodes", "1"]) != 0
    assert "Bioscara-Nope" in one_line_error(capsys, "eval")


def test_eval_model_without_metadata_is_a_one_line_error(
    sac_run: Path, tmp_path: Path, capsys: pytest.CaptureFixture[str]
) -> None:
    shutil.copy(sac_run / "model.zip", tmp_path / "model.zip")
    assert main(["eval", "--model", str(tmp_path / "model.zip"), "--episodes", "1"]) != 0
    assert METADATA_NAME in one_line_error(capsys, "eval")


def test_eval_model_whose_metadata_names_another_task_is_a_one_line_error(
    sac_run: Path, tmp_path: Path, capsys: pytest.CaptureFixture[str]
) -> None:
    model = edit_metadata(sac_run, tmp_path, env_id=PICK)
    assert main(["eval", "--model", str(model), "--episodes", "1"]) != 0
    assert "differs" in one_line_error(capsys, "eval")


def test_eval_model_whose_metadata_names_an_unregistered_env_is_a_one_line_error(
    sac_run: Path, tmp_path: Path, capsys: pytest.CaptureFixture[str]
) -> None:
    model = edit_metadata(sac_run, tmp_path, env_id="Bioscara-Nope-v0")
    assert main(["eval", "--model", str(model), "--episodes", "1"]) != 0
    assert "Bioscara-Nope" in one_line_error(capsys, "eval")


def test_eval_model_whose_metadata_action_space_differs_is_a_one_line_error(
    sac_run: Path, tmp_path: Path, capsys: pytest.CaptureFixture[str]
) -> None:
    model = edit_metadata(sac_run, tmp_path, **{"action_space.shape": [5]})
    assert main(["eval", "--model", str(model), "--episodes", "1"]) != 0
    assert "action_space differs" in one_line_error(capsys, "eval")


def test_eval_model_whose_metadata_has_a_setting_the_env_does_not_take_is_a_one_line_error(
    sac_run: Path, tmp_path: Path, capsys: pytest.CaptureFixture[str]
) -> None:
    # Seen (a hostile test): a 29-line traceback ending in gym.make's TypeError.
    model = edit_metadata(sac_run, tmp_path, **{"env_kwargs.bogus_kw": 1})
    assert main(["eval", "--model", str(model), "--episodes", "1"]) == 2
    line = one_line_error(capsys, "eval")
    assert "env_kwargs (metadata.json) has 'bogus_kw', which Bioscara-Reach-v0 does not take" in line


def test_the_eval_env_ignores_the_render_mode_training_recorded() -> None:
    # Seen (a hostile test): render_mode 5 in metadata.json, a traceback from gymnasium.
    # How the training env rendered is none of the policy's business: eval renders for --video only.
    from bioscara_gym.training.evaluate import make_eval_env

    metadata = {"env_id": "Bioscara-Reach-v0", "env_kwargs": {"render_mode": 5}}
    with contextlib.closing(make_eval_env(metadata)) as env:
        assert env.unwrapped.render_mode is None
    with contextlib.closing(make_eval_env(metadata, render=True)) as env:
        assert env.unwrapped.render_mode == "rgb_array"


def test_eval_model_whose_metadata_control_mode_is_invalid_is_a_one_line_error(
    sac_run: Path, tmp_path: Path, capsys: pytest.CaptureFixture[str]
) -> None:
    # eval builds the env from the metadata, so a *valid* other control mode cannot be told apart
    # from the truth there; check_metadata's refusal of a mismatch is tested below.
    model = edit_metadata(sac_run, tmp_path, **{"env_kwargs.control_mode": "joint"})
    assert main(["eval", "--model", str(model), "--episodes", "1"]) != 0
    assert "control_mode" in one_line_error(capsys, "eval")


# --------------------------------------------------------------- hyperparams


def test_parse_literal_call_parses_nested_dict_calls_and_lists() -> None:
    parsed = parse_literal_call("dict(net_arch=dict(pi=[128, 128], vf=[64]), log_std_init=-2.5)", "here")
    assert parsed == {"net_arch": {"pi": [128, 128], "vf": [64]}, "log_std_init": -2.5}


def test_parse_literal_call_parses_plain_literals() -> None:
    assert parse_literal_call("[(1, 'a'), {'k': None}, True]", "here") == [(1, "a"), {"k": None}, True]


@pytest.mark.parametrize(
    "text",
    [
        "__import__('os')",
        "os",
        "dict(a=os)",
        "os.system('true')",
        "dict([('a', 1)])",
        "dict(**{'a': 1})",
        "list([1])",
        "[1, 2] + [3]",
        "lambda: 0",
    ],
)
def test_parse_literal_call_refuses_names_and_calls(text: str) -> None:
    with pytest.raises(HyperparamError, match=r"^where: "):
        parse_literal_call(text, "where")


def test_parse_literal_call_resolves_the_allowed_class_names() -> None:
    parsed = parse_literal_call(
        "dict(activation_fn=nn.Tanh, features_extractor_class=GoalErrorExtractor, net_arch=[8])", "here"
    )
    expected = {"activation_fn": th.nn.Tanh, "features_extractor_class": GoalErrorExtractor, "net_arch": [8]}
    assert parsed == expected


def test_parse_literal_call_names_the_allowed_names_when_refusing() -> None:
    with pytest.raises(HyperparamError, match=r"'nn\.Sigmoid' is not allowed.*nn\.ReLU.*GoalErrorExtractor"):
        parse_literal_call("dict(activation_fn=nn.Sigmoid)", "where")


def test_hyperparams_as_dict_names_classes_so_metadata_is_json(tmp_path: Path) -> None:
    config = write_config(tmp_path / "cfg.yaml", {REACH: TINY["sac"]})
    plain = load_hyperparams(config, REACH).as_dict()
    assert plain["algo_kwargs"]["policy_kwargs"]["features_extractor_class"] == (
        "bioscara_gym.training.features.GoalErrorExtractor"
    )
    json.dumps(plain)


def test_parse_literal_call_refuses_invalid_syntax() -> None:
    with pytest.raises(HyperparamError, match="not a Python literal"):
        parse_literal_call("dict(a=1", "where")


def test_load_hyperparams_splits_extras_from_algorithm_arguments(tmp_path: Path) -> None:
    config = write_config(tmp_path / "cfg.yaml", {REACH: {**TINY["td3"], "n_timesteps": "3e4"}})
    hp = load_hyperparams(config, REACH)
    assert hp.source == str(config)
    assert hp.n_timesteps == 30_000
    assert (hp.eval_freq, hp.eval_episodes, hp.noise_type, hp.noise_std) == (200, 2, "normal", 0.2)
    assert hp.env_kwargs == REACH_KWARGS
    policy_kwargs = {"net_arch": [16, 16], "features_extractor_class": GoalErrorExtractor}
    assert hp.algo_kwargs["policy_kwargs"] == policy_kwargs
    her = {"goal_selection_strategy": "future", "n_sampled_goal": 4}
    assert hp.algo_kwargs["replay_buffer_kwargs"] == her
    assert not set(EXTRA_KEYS) & set(hp.algo_kwargs)


def test_config_replay_buffer_class_her_maps_to_the_sb3_class(tmp_path: Path, reach_env: gym.Env) -> None:
    config = write_config(tmp_path / "cfg.yaml", {REACH: TINY["sac"]})
    hp = load_hyperparams(config, REACH)
    assert hp.algo_kwargs["replay_buffer_class"] == "HerReplayBuffer"
    assert algo_kwargs(hp, reach_env, "sac")["replay_buffer_class"] is HerReplayBuffer


def test_config_unknown_replay_buffer_class_is_refused(reach_env: gym.Env) -> None:
    hp = Hyperparams(source="cfg.yaml", n_timesteps=1, algo_kwargs={"replay_buffer_class": "Nope"})
    with pytest.raises(TrainingError, match="replay_buffer_class 'Nope'"):
        algo_kwargs(hp, reach_env, "sac")


def test_config_noise_type_becomes_action_noise(reach_env: gym.Env) -> None:
    hp = Hyperparams(source="cfg.yaml", n_timesteps=1, noise_type="normal", noise_std=0.3)
    noise = algo_kwargs(hp, reach_env, "td3")["action_noise"]
    assert noise._sigma.tolist() == pytest.approx([0.3] * reach_env.action_space.shape[0])


def test_load_hyperparams_requires_n_timesteps(tmp_path: Path) -> None:
    entry = {k: v for k, v in TINY["sac"].items() if k != "n_timesteps"}
    config = write_config(tmp_path / "cfg.yaml", {REACH: entry})
    with pytest.raises(HyperparamError, match="n_timesteps is missing"):
        load_hyperparams(config, REACH)


@pytest.mark.parametrize("algo", sorted(ALGOS))
@pytest.mark.parametrize("env_id", [REACH, PICK])
def test_packaged_config_loads_for_every_algo_and_task(algo: str, env_id: str) -> None:
    hp = load_hyperparams(default_config_path(algo), env_id)
    assert hp.n_timesteps > 0
    assert hp.eval_episodes > 0


def test_packaged_reach_config_builds_sac_on_the_goal_error() -> None:
    hp = load_hyperparams(default_config_path("sac"), REACH)
    env = gym.make(REACH, backend="mock", **hp.env_kwargs)
    try:
        model = SAC(hp.policy, env, device="cpu", **algo_kwargs(hp, env, "sac"))
    finally:
        env.close()
    extractor = model.actor.features_extractor
    assert isinstance(extractor, GoalErrorExtractor) and extractor.scale == 0.01
    assert isinstance(model.critic.features_extractor, GoalErrorExtractor)
    assert isinstance(model.replay_buffer, HerReplayBuffer)
    assert hp.env_kwargs == {"control_mode": "cartesian", "reward_type": "log"}


@pytest.mark.parametrize("algo", ["sac", "td3"])
def test_off_policy_on_goal_env_gets_her_when_config_omits_it(algo: str, reach_env: gym.Env) -> None:
    hp = Hyperparams(source="cfg.yaml", n_timesteps=1, algo_kwargs={"learning_starts": 10})
    model = ALGOS[algo]("MultiInputPolicy", reach_env, device="cpu", **algo_kwargs(hp, reach_env, algo))
    assert isinstance(model.replay_buffer, HerReplayBuffer)


def test_off_policy_keeps_the_replay_buffer_the_config_names(reach_env: gym.Env) -> None:
    hp = Hyperparams(source="cfg.yaml", n_timesteps=1, algo_kwargs={"replay_buffer_class": DictReplayBuffer})
    model = SAC("MultiInputPolicy", reach_env, device="cpu", **algo_kwargs(hp, reach_env, "sac"))
    assert type(model.replay_buffer) is DictReplayBuffer


def test_on_policy_gets_no_replay_buffer(reach_env: gym.Env) -> None:
    hp = Hyperparams(source="cfg.yaml", n_timesteps=1)
    assert "replay_buffer_class" not in algo_kwargs(hp, reach_env, "ppo")


#: TINY["sac"] as rl-zoo3 writes it: env_kwargs a mapping, the evaluation a dotted-path callback.
ZOO_SUCCESS = "bioscara_gym.training.zoo.SuccessEvalCallback"
TINY_ZOO: dict[str, Any] = {
    **{k: v for k, v in TINY_OFF_POLICY.items() if k not in ("eval_freq", "eval_episodes", "policy_kwargs")},
    "policy": "bioscara_gym.training.zoo.SACGoalErrorPolicy",
    "policy_kwargs": "dict(net_arch=[16, 16])",
    "env_kwargs": dict(REACH_KWARGS),
    "callback": [{ZOO_SUCCESS: {"eval_freq": 200, "eval_episodes": 2, "target_success": 0.0}}],
}


def test_load_hyperparams_reads_the_rl_zoo3_form(tmp_path: Path) -> None:
    from bioscara_gym.training.zoo import SACGoalErrorPolicy

    hp = load_hyperparams(write_config(tmp_path / "cfg.yaml", {REACH: TINY_ZOO}), REACH)
    assert hp.policy is SACGoalErrorPolicy
    assert hp.env_kwargs == REACH_KWARGS
    assert (hp.eval_freq, hp.eval_episodes, hp.target_success) == (200, 2, 0.0)
    assert hp.callbacks == () and hp.eval_kwargs == {}
    assert not set(EXTRA_KEYS) & set(hp.algo_kwargs)
    plain = hp.as_dict()
    assert plain["policy"] == "bioscara_gym.training.zoo.SACGoalErrorPolicy"
    json.dumps(plain)


@pytest.mark.parametrize("algo", sorted(ALGOS))
@pytest.mark.parametrize("env_id", [REACH, PICK])
def test_packaged_config_takes_its_evaluation_from_the_success_callback(algo: str, env_id: str) -> None:
    entry = yaml.safe_load(default_config_path(algo).read_text(encoding="utf-8"))[env_id]
    callback = next(c for c in entry["callback"] if ZOO_SUCCESS in c)
    hp = load_hyperparams(default_config_path(algo), env_id)
    assert (hp.eval_freq, hp.eval_episodes, hp.target_success) == tuple(
        callback[ZOO_SUCCESS][k] for k in ("eval_freq", "eval_episodes", "target_success")
    )
    assert hp.env_kwargs == entry["env_kwargs"]


def test_load_hyperparams_keeps_other_success_kwargs_and_other_callbacks(tmp_path: Path) -> None:
    from stable_baselines3.common.callbacks import StopTrainingOnMaxEpisodes

    entry = {
        **TINY_ZOO,
        "callback": [
            {ZOO_SUCCESS: {"eval_freq": 100, "quick_episodes": 5}},
            {"stable_baselines3.common.callbacks.StopTrainingOnMaxEpisodes": {"max_episodes": 3}},
        ],
    }
    hp = load_hyperparams(write_config(tmp_path / "cfg.yaml", {REACH: entry}), REACH)
    assert (hp.eval_freq, hp.eval_kwargs) == (100, {"quick_episodes": 5})
    assert hp.callbacks == ((StopTrainingOnMaxEpisodes, {"max_episodes": 3}),)
    json.dumps(hp.as_dict())


@pytest.mark.parametrize(
    ("change", "message"),
    [
        ({"policy": "bioscara_gym.training.zoo.Nope"}, r"\.policy: bioscara_gym\.training\.zoo has no Nope"),
        ({"callback": ["no_such_module.Callback"]}, r"\.callback: cannot import no_such_module"),
        ({"callback": [{ZOO_SUCCESS: {"eval_freqq": 1}}]}, r"\.callback: .*Callback: .*eval_freqq"),
        ({"callback": [{ZOO_SUCCESS: {}, "other.Callback": {}}]}, r"\.callback: expected a dotted path"),
        ({"callback": [ZOO_SUCCESS, ZOO_SUCCESS]}, "more than one"),
        ({"eval_freq": 100}, "eval_freq given both at the top and in the callback"),
        ({"env_kwargs": [1]}, "env_kwargs must be a mapping"),
        ({"normalize": True}, r"\.normalize: bioscara train does not support normalize.*rl_zoo3"),
        ({"frame_stack": 2}, "does not support frame_stack"),
        ({"env_wrapper": "gymnasium.wrappers.FlattenObservation"}, "does not support env_wrapper"),
    ],
)
def test_load_hyperparams_refuses_malformed_rl_zoo3_entries(
    tmp_path: Path, change: dict[str, Any], message: str
) -> None:
    config = write_config(tmp_path / "cfg.yaml", {REACH: {**TINY_ZOO, **change}})
    with pytest.raises(HyperparamError, match=message):
        load_hyperparams(config, REACH)


def test_config_lin_schedule_and_train_freq_list_become_what_sb3_takes(reach_env: gym.Env) -> None:
    given = {"learning_rate": "lin_0.002", "train_freq": [1, "episode"]}
    hp = Hyperparams(source="cfg.yaml", n_timesteps=1, algo_kwargs=given)
    kwargs = algo_kwargs(hp, reach_env, "sac")
    assert kwargs["learning_rate"](1.0) == pytest.approx(0.002)
    assert kwargs["learning_rate"](0.25) == pytest.approx(0.0005)
    assert kwargs["train_freq"] == (1, "episode")


def test_config_unknown_schedule_is_refused(reach_env: gym.Env) -> None:
    hp = Hyperparams(source="cfg.yaml", n_timesteps=1, algo_kwargs={"learning_rate": "exp_0.1"})
    with pytest.raises(TrainingError, match=r"learning_rate 'exp_0\.1'"):
        algo_kwargs(hp, reach_env, "sac")


def test_train_reads_the_rl_zoo3_form_and_stops_at_the_callbacks_target(tmp_path: Path) -> None:
    config = write_config(tmp_path / "cfg.yaml", {REACH: TINY_ZOO})
    assert main(train_argv(tmp_path / "run", config)) == 0
    metadata = read_metadata(tmp_path / "run" / "model.zip")
    assert metadata["timesteps"] == 200  # target 0 % met at the first evaluation
    assert metadata["config"]["policy"] == "bioscara_gym.training.zoo.SACGoalErrorPolicy"
    model = SAC.load(tmp_path / "run" / "model.zip", device="cpu", buffer_size=1,
                     custom_objects={"replay_buffer_class": None, "replay_buffer_kwargs": {}})  # fmt: skip
    assert isinstance(model.actor.features_extractor, GoalErrorExtractor)


# ------------------------------------------------------------------- env ids


@pytest.mark.parametrize("given", ["Bioscara-Reach", REACH])
def test_resolve_env_id_returns_the_versioned_id(given: str) -> None:
    assert resolve_env_id(given) == REACH


@pytest.mark.parametrize("given", ["Bioscara-Nope", "Bioscara-Reach-v9"])
def test_resolve_env_id_refuses_unknown_ids_naming_the_registered_ones(given: str) -> None:
    with pytest.raises(TrainingError, match=f"unknown env '{given}'.*{REACH}"):
        resolve_env_id(given)


# ------------------------------------------------------------------ metadata


def test_metadata_round_trips_through_its_file(tmp_path: Path, reach_env: gym.Env) -> None:
    metadata = build_metadata(reach_env, REACH, REACH_KWARGS, algo="sac", seed=3, timesteps=TOTAL)
    path = write_metadata(tmp_path, metadata)
    assert path == tmp_path / METADATA_NAME
    assert read_metadata(tmp_path / "model.zip") == metadata
    assert read_metadata(tmp_path) == metadata


def test_metadata_records_the_behaviour_kwargs_even_when_defaulted(reach_env: gym.Env) -> None:
    metadata = build_metadata(reach_env, REACH, {})
    assert metadata["env_kwargs"]["control_mode"] == reach_env.unwrapped.control_mode
    assert metadata["env_kwargs"]["control_freq"] == reach_env.unwrapped.control_freq


def test_check_metadata_accepts_the_env_it_was_built_from(tmp_path: Path, reach_env: gym.Env) -> None:
    write_metadata(tmp_path, build_metadata(reach_env, REACH, REACH_KWARGS))
    check_metadata(read_metadata(tmp_path), reach_env, REACH)


def test_check_metadata_refuses_another_env_id(reach_env: gym.Env) -> None:
    metadata = build_metadata(reach_env, PICK, REACH_KWARGS)
    with pytest.raises(MetadataError, match=f"trained on {PICK}, not {REACH}"):
        check_metadata(metadata, reach_env, REACH)


def test_check_metadata_refuses_another_control_mode(reach_env: gym.Env) -> None:
    metadata = build_metadata(reach_env, REACH, {**REACH_KWARGS, "control_mode": "velocity"})
    with pytest.raises(MetadataError, match="control_mode='velocity'"):
        check_metadata(metadata, reach_env, REACH)


def test_check_metadata_refuses_another_action_space(reach_env: gym.Env) -> None:
    metadata = build_metadata(reach_env, REACH, REACH_KWARGS)
    metadata["action_space"]["shape"] = [5]
    with pytest.raises(MetadataError, match="action_space differs"):
        check_metadata(metadata, reach_env, REACH)


def test_check_metadata_refuses_another_observation_space(
    reach_env: gym.Env, make_env: Callable[..., gym.Env]
) -> None:
    metadata = build_metadata(make_env(PICK), REACH, REACH_KWARGS)
    with pytest.raises(MetadataError, match="observation_space differs"):
        check_metadata(metadata, reach_env, REACH)


def test_read_metadata_refuses_a_missing_file(tmp_path: Path) -> None:
    with pytest.raises(MetadataError, match=f"no {METADATA_NAME} next to"):
        read_metadata(tmp_path / "model.zip")


def test_read_metadata_refuses_a_file_that_is_not_json(tmp_path: Path) -> None:
    (tmp_path / METADATA_NAME).write_text("{not json", encoding="utf-8")
    with pytest.raises(MetadataError, match="cannot read"):
        read_metadata(tmp_path / "model.zip")


# ------------------------------------------------------------ missing extras
def _cli_without(blocked: tuple[str, ...], argv: list[str], cwd: Path) -> subprocess.CompletedProcess[str]:
    """``bioscara ARGV`` in a fresh interpreter in which importing ``blocked`` fails."""
    return run_blocked(f"from bioscara_gym.cli import main\nsys.exit(main({argv!r}))\n", blocked, cwd=cwd)


@pytest.mark.parametrize(
    ("extra", "line"),
    [
        (["--check", "-1"], "--check must be >= 0 (0: no check against torch), got -1"),
        (["--onnx", "{tmp}"], "--onnx {tmp}: is a folder; give a file name"),
        (["--onnx", "{tmp}/notes/p.onnx"], "--onnx {tmp}/notes/p.onnx: {tmp}/notes is a file, not a folder"),
    ],
    ids=["check-negative", "onnx-a-folder", "onnx-under-a-file"],
)
def test_export_refuses_bad_arguments_before_exporting(
    sac_run: Path, tmp_path: Path, extra: list[str], line: str, capsys: pytest.CaptureFixture[str]
) -> None:
    # Seen (a hostile test): --check -1 exported and reported a check "over -1 observations";
    # a folder or a path under a file named a temporary file or metadata.json.
    (tmp_path / "notes").write_text("x")
    argv = ["export", "--model", str(sac_run / "model.zip"), "--onnx", str(tmp_path / "p.onnx")]
    argv += [a.format(tmp=tmp_path) for a in extra]
    assert main(argv) == 2
    assert one_line_error(capsys, "export") == f"bioscara export: error: {line.format(tmp=tmp_path)}"
    assert not (tmp_path / "p.onnx").exists()


TRAIN_HINT = "bioscara train needs the [train] extra: pip install 'bioscara-gym[train]'"


@pytest.mark.parametrize(
    ("blocked", "argv", "hint"),
    [
        (("torch",), ["train", "--timesteps", "10", "--out", "run"], TRAIN_HINT),
        (("stable_baselines3",), ["train", "--timesteps", "10", "--out", "run"], TRAIN_HINT),
        (
            ("torch",),
            ["eval", "--model", "run/model.zip", "--episodes", "1"],
            TRAIN_HINT.replace("bioscara train", "eval --model"),
        ),
        (
            ("torch",),
            ["export", "--model", "run/model.zip", "--onnx", "p.onnx"],
            TRAIN_HINT.replace("bioscara train", "bioscara export"),
        ),
        (  # seen: it named `bioscara train`
            ("torch",),
            ["deploy", "--model", "run/model.zip", "--backend", "mock"],
            TRAIN_HINT.replace("bioscara train", "deploy --model"),
        ),
        (
            ("onnxruntime",),
            ["deploy", "--onnx", "p.onnx", "--backend", "mock"],
            "deploy --onnx needs the [onnx] extra: pip install 'bioscara-gym[onnx]'",
        ),
    ],
    ids=[
        "train-no-torch",
        "train-no-sb3",
        "eval-no-torch",
        "export-no-torch",
        "deploy-model-no-torch",
        "deploy-onnx-no-ort",
    ],
)
def test_a_missing_extra_is_one_line_naming_it(
    tmp_path: Path, blocked: tuple[str, ...], argv: list[str], hint: str
) -> None:
    (tmp_path / "run").mkdir()
    metadata = {  # enough for the metadata check deploy runs before it imports torch
        "env_id": REACH,
        "env_kwargs": {"control_mode": "cartesian", "control_freq": 25.0},
        "observation_space": {},
        "action_space": {},
        "algo": "sac",
    }
    (tmp_path / "run" / "metadata.json").write_text(json.dumps(metadata))
    result = _cli_without(blocked, argv, tmp_path)
    assert result.returncode == 2, result.stderr
    assert result.stderr.strip() == f"bioscara {argv[0]}: error: {hint}"


def test_a_broken_dependency_is_not_reported_as_a_missing_extra() -> None:
    from bioscara_gym.training.extras import needs_train

    with pytest.raises(ModuleNotFoundError) as caught, needs_train():
        raise ModuleNotFoundError("No module named 'sympy'", name="sympy")
    assert not isinstance(caught.value, MissingExtraError)


def test_packaged_pickplace_config_learns_from_demonstrations() -> None:
    from bioscara_gym.training.zoo import DemonstrationCallback

    hp = load_hyperparams(default_config_path("sac"), PICK)
    assert any(cls is DemonstrationCallback for cls, _ in hp.callbacks)
    assert hp.env_kwargs["control_mode"] == "cartesian"


def test_train_demos_with_another_algo_is_a_one_line_error(
    tmp_path: Path, capsys: pytest.CaptureFixture[str]
) -> None:
    out = tmp_path / "run"
    rc = main(["train", "--env", "Bioscara-PickPlace", "--algo", "td3", "--demos", "x", "--out", str(out)])
    assert rc != 0
    assert "--algo sac" in one_line_error(capsys, "train")
    assert not out.exists()
