"""rl-zoo3 runs the shipped hyperparameter files (``training/configs/*.yaml``) unchanged.

``python -m rl_zoo3.train -conf training/configs/ALGO.yaml`` must load every
entry as rl-zoo3 reads it (its own ``yaml.safe_load``, ``eval`` of kwargs
strings, dotted-path policies and callbacks), build the model, train and
save; ``rl_zoo3.enjoy`` must load and run the result. rl-zoo3's entry points
are called in-process (each subprocess would spend seconds importing
rl-zoo3's dependencies). The default suite trains a few hundred steps per
entry with the buffers and batches shrunk through rl-zoo3's own
``--hyperparams`` overrides; the slow suite trains the entries as shipped and
runs two ``--optimize`` trials.
"""

from __future__ import annotations

import importlib
import sys
from pathlib import Path

import pytest
import yaml

from bioscara_gym.training.hyperparams import default_config_path

rl_zoo3_train = pytest.importorskip("rl_zoo3.train", reason="rl_zoo3 is a dev dependency")
rl_zoo3_enjoy = pytest.importorskip("rl_zoo3.enjoy")

REACH = "Bioscara-Reach-v0"
PICK = "Bioscara-PickPlace-v1"
ALGOS = ("sac", "td3", "ppo")
ENTRIES = [(algo, env_id) for algo in ALGOS for env_id in (REACH, PICK)]
STEPS = 300
EPISODE = {REACH: 50, PICK: 200}


def shrink(algo: str, env_id: str) -> list[str]:
    """Smaller buffers, batches and rollouts, so a few hundred steps train at all (rl-zoo3 syntax).

    HER samples only once an episode has ended: learning starts after the first one.
    """
    if algo == "ppo":
        return ["n_envs:2", "n_steps:64", "batch_size:32", "n_epochs:1"]
    return [f"learning_starts:{EPISODE[env_id] + 50}", "batch_size:32", "buffer_size:2000"]


SUCCESS_CALLBACK = "bioscara_gym.training.zoo.SuccessEvalCallback"

# rl-zoo3's own modules warn about things outside this project.
pytestmark = pytest.mark.filterwarnings("ignore::DeprecationWarning", "ignore::UserWarning")


def zoo(monkeypatch: pytest.MonkeyPatch, capsys: pytest.CaptureFixture[str], command: str, *args: str) -> str:
    """Run ``python -m rl_zoo3.COMMAND ARGS`` in this process; its stdout."""
    main = {"train": rl_zoo3_train.train, "enjoy": rl_zoo3_enjoy.enjoy}[command]
    with monkeypatch.context() as mp:
        mp.setattr(sys, "argv", [f"rl_zoo3.{command}", *args])
        capsys.readouterr()
        main()
        return capsys.readouterr().out


def train_args(algo: str, env_id: str, folder: Path, *extra: str) -> list[str]:
    """rl-zoo3 train arguments for a shipped entry."""
    return [
        "--algo", algo, "--env", env_id, "--gym-packages", "bioscara_gym",
        "-conf", str(default_config_path(algo)), "-f", str(folder),
        "--device", "cpu", "--num-threads", "1", "--seed", "0", "--eval-freq", "-1", *extra,
    ]  # fmt: skip


def enjoy_args(algo: str, env_id: str, folder: Path, steps: int) -> list[str]:
    """rl-zoo3 enjoy arguments for the newest run in ``folder``."""
    return [
        "--algo", algo, "--env", env_id, "--gym-packages", "bioscara_gym", "-f", str(folder),
        "--device", "cpu", "--num-threads", "1", "--no-render", "-n", str(steps),
    ]  # fmt: skip


def saved_model(folder: Path, algo: str, env_id: str) -> Path:
    """The model rl-zoo3 saved for the first run of ``algo`` on ``env_id``."""
    return folder / algo / f"{env_id}_1" / f"{env_id}.zip"


def check_train_then_enjoy(
    monkeypatch: pytest.MonkeyPatch,
    capsys: pytest.CaptureFixture[str],
    algo: str,
    env_id: str,
    folder: Path,
    *overrides: str,
) -> None:
    """Train ``STEPS`` steps of the shipped entry (with ``overrides``), then enjoy one episode."""
    hyperparams = ["--hyperparams", *overrides] if overrides else []
    out = zoo(monkeypatch, capsys, "train", *train_args(algo, env_id, folder, "-n", str(STEPS), *hyperparams))
    assert saved_model(folder, algo, env_id).is_file(), out[-2000:]
    # What rl-zoo3 saved is the entry as shipped (plus the overrides): env_kwargs a mapping.
    config = yaml.load(
        (folder / algo / f"{env_id}_1" / env_id / "config.yml").read_text(encoding="utf-8"),
        Loader=yaml.UnsafeLoader,
    )
    shipped = yaml.safe_load(default_config_path(algo).read_text(encoding="utf-8"))[env_id]
    assert dict(config)["env_kwargs"] == shipped["env_kwargs"]
    out = zoo(monkeypatch, capsys, "enjoy", *enjoy_args(algo, env_id, folder, EPISODE[env_id]))
    assert "Episode Length" in out, out[-2000:]


@pytest.mark.parametrize(("algo", "env_id"), ENTRIES)
def test_shipped_entry_is_a_valid_rl_zoo3_hyperparameter_file(algo: str, env_id: str) -> None:
    """Statically: what rl-zoo3 would choke on (a string env_kwargs, our own top-level keys)."""
    entry = yaml.safe_load(default_config_path(algo).read_text(encoding="utf-8"))[env_id]
    assert isinstance(entry.get("env_kwargs", {}), dict)
    assert not {"eval_freq", "eval_episodes", "target_success"} & set(entry)
    assert "GoalErrorExtractor" not in str(entry.get("policy_kwargs", ""))
    names = [next(iter(c)) for c in entry["callback"]]
    assert names[0] == SUCCESS_CALLBACK
    for name in names:  # dotted paths rl-zoo3 can import
        module, _, attribute = name.rpartition(".")
        assert callable(getattr(importlib.import_module(module), attribute))


# Every shipped entry, in the default suite, so a config rl-zoo3 cannot run fails CI.
@pytest.mark.parametrize(("algo", "env_id"), ENTRIES)
def test_rl_zoo3_trains_and_enjoys_every_shipped_entry(
    algo: str,
    env_id: str,
    tmp_path: Path,
    monkeypatch: pytest.MonkeyPatch,
    capsys: pytest.CaptureFixture[str],
) -> None:
    check_train_then_enjoy(monkeypatch, capsys, algo, env_id, tmp_path, *shrink(algo, env_id))


def test_rl_zoo3_runs_the_success_callback_and_the_goal_error_policy(
    tmp_path: Path, monkeypatch: pytest.MonkeyPatch, capsys: pytest.CaptureFixture[str]
) -> None:
    from stable_baselines3 import SAC

    from bioscara_gym.training.features import GoalErrorExtractor
    from bioscara_gym.training.zoo import SACGoalErrorPolicy

    # The shipped callback evaluates every 2000 steps; here every 100, and any rate meets the target.
    callback = f"[{{'{SUCCESS_CALLBACK}': dict(eval_freq=100, eval_episodes=2, target_success=0.0)}}]"
    args = train_args("sac", REACH, tmp_path, "-n", "1000", "--hyperparams", f"callback:{callback}")
    out = zoo(monkeypatch, capsys, "train", *args, *shrink("sac", REACH))
    assert "[eval] step     100" in out
    assert "target 0% reached" in out
    assert ">= 0%: stopping" in out
    assert "[eval] step     200" not in out  # stopped at the first evaluation
    model = SAC.load(saved_model(tmp_path, "sac", REACH), device="cpu", buffer_size=1,
                     custom_objects={"replay_buffer_class": None, "replay_buffer_kwargs": {}})  # fmt: skip
    assert model.num_timesteps == 100
    assert isinstance(model.policy, SACGoalErrorPolicy)
    extractor = model.actor.features_extractor
    assert isinstance(extractor, GoalErrorExtractor) and extractor.scale == 0.01


@pytest.mark.slow
@pytest.mark.parametrize(("algo", "env_id"), ENTRIES)
def test_rl_zoo3_trains_and_enjoys_every_shipped_entry_as_shipped(
    algo: str,
    env_id: str,
    tmp_path: Path,
    monkeypatch: pytest.MonkeyPatch,
    capsys: pytest.CaptureFixture[str],
) -> None:
    check_train_then_enjoy(monkeypatch, capsys, algo, env_id, tmp_path)


@pytest.mark.slow
def test_rl_zoo3_optimize_runs_two_trials_on_reach(
    tmp_path: Path, monkeypatch: pytest.MonkeyPatch, capsys: pytest.CaptureFixture[str]
) -> None:
    args = train_args(
        "sac", REACH, tmp_path, "-n", "400", "--optimize", "--n-trials", "2", "--n-evaluations", "1",
        "--eval-episodes", "2", "--sampler", "random", "--pruner", "none", "--no-optim-plots",
    )  # fmt: skip
    out = zoo(monkeypatch, capsys, "train", *args)
    assert "Number of finished trials:  2" in out, out[-3000:]
    assert list((tmp_path / "sac").glob(f"report_{REACH}_2-trials-400-random-none_*.csv"))


def test_reach_stops_with_a_margin_above_the_target_users_are_judged_on() -> None:
    """Issue #26 item 7: a run stopped at exactly 95 % left rl-zoo3's enjoy at 93-96 %.

    The shipped Reach entry stops only at 98 % on its own 100 episodes, and
    learns from the scripted expert's demonstrations (20 episodes, cloned
    before SAC's first step): with both, enjoy scored 100 % for seeds 0-2.
    """
    entry = yaml.safe_load(default_config_path("sac").read_text(encoding="utf-8"))[REACH]
    callbacks = {name: kwargs for c in entry["callback"] for name, kwargs in c.items()}
    assert callbacks[SUCCESS_CALLBACK]["target_success"] == 0.98
    assert callbacks[SUCCESS_CALLBACK]["eval_episodes"] == 100
    demos = callbacks["bioscara_gym.training.zoo.DemonstrationCallback"]
    assert demos["episodes"] == 20 and demos["pretrain_steps"] == 1000
