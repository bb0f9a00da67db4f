"""Tests that kill mutants mutmut found surviving in ``training/train.py`` (docs/mutation.md).

No training: ``train()`` is given a stand-in method (a class that records
what it was built with), so a test sees which method runs, on which env,
after which checks. Expected values are literals from the module's
docstrings (what is refused, in which words) and ``bioscara_gym.tasks.TASKS``
(each task's default method).
"""

from __future__ import annotations

from pathlib import Path
from typing import Any

import pytest

from bioscara_gym.errors import TrainingError
from bioscara_gym.training import train as train_module
from bioscara_gym.training.checkpoints import write_run_state
from bioscara_gym.training.methods import METHODS
from bioscara_gym.training.train import TrainArgs, check_n_envs, check_timesteps, choose_method, train

REACH = "Bioscara-Reach-v0"
PICK = "Bioscara-PickPlace-v1"


# ------------------------------------------------------------------ the checks
@pytest.mark.parametrize("value", [None, 1, 300])
def test_a_budget_of_one_step_or_more_or_none_is_accepted(value: int | None) -> None:
    check_timesteps(value)


@pytest.mark.parametrize("value", [0, -5])
def test_a_budget_below_one_is_refused_in_one_line(value: int) -> None:
    with pytest.raises(TrainingError) as caught:
        check_timesteps(value)
    assert str(caught.value) == f"--timesteps {value}: must be >= 1 (omit it for the config's n_timesteps)"


@pytest.mark.parametrize("value", [None, 1, 4])
def test_one_env_or_more_or_none_is_accepted(value: int | None) -> None:
    check_n_envs(value)


@pytest.mark.parametrize("value", [0, -2])
def test_fewer_than_one_env_is_refused_in_one_line(value: int) -> None:
    with pytest.raises(TrainingError) as caught:
        check_n_envs(value)
    assert str(caught.value) == f"--n-envs {value}: must be >= 1 (omit it for the config's n_envs)"


def test_more_workers_than_eight_a_cpu_are_refused(monkeypatch: pytest.MonkeyPatch) -> None:
    # Seen (a hostile test): --n-envs 100000 started workers until "Too many open files".
    monkeypatch.setattr("os.sched_getaffinity", lambda pid: {0, 1}, raising=False)
    monkeypatch.setattr("os.cpu_count", lambda: 2)  # where there is no affinity
    check_n_envs(16)
    with pytest.raises(TrainingError) as caught:
        check_n_envs(17)
    assert (
        str(caught.value)
        == "--n-envs 17: at most 16 on this machine's 2 CPUs (8 a CPU; each is a process of its own)"
    )


# ------------------------------------------------------------------ the method
def test_algo_names_the_method_whatever_the_task_or_config(tmp_path: Path) -> None:
    assert choose_method(TrainArgs(algo="td3", out=tmp_path), PICK).name == "td3"
    assert choose_method(TrainArgs(algo="bc", config=Path("x.yaml"), out=tmp_path), REACH).name == "bc"


def test_an_unknown_algo_is_refused_naming_the_methods(tmp_path: Path) -> None:
    with pytest.raises(TrainingError) as caught:
        choose_method(TrainArgs(algo="a2c", out=tmp_path), REACH)
    assert str(caught.value) == "unknown algo 'a2c'; choose one of sac, td3, ppo, bc, dagger"


def test_without_algo_each_task_trains_with_its_default_method(tmp_path: Path) -> None:
    args = TrainArgs(out=tmp_path)
    assert choose_method(args, REACH).name == "sac"
    assert choose_method(args, PICK).name == "dagger"
    for env_id in ("Bioscara-Push-v0", "Bioscara-Stack-v0"):
        assert choose_method(args, env_id).name == "dagger"


def test_a_config_without_algo_trains_sac_even_where_the_task_defaults_to_dagger(tmp_path: Path) -> None:
    assert choose_method(TrainArgs(config=Path("sac.yaml"), out=tmp_path), PICK).name == "sac"


def test_an_env_that_is_not_a_task_trains_sac(tmp_path: Path) -> None:
    assert choose_method(TrainArgs(out=tmp_path), "CartPole-v1").name == "sac"


def test_resume_without_algo_continues_with_the_runs_own_method(tmp_path: Path) -> None:
    state = {"env_id": REACH, "algo": "bc", "seed": 0, "total_timesteps": 10, "config": None, "demos": None}
    write_run_state(tmp_path, state)
    assert choose_method(TrainArgs(out=tmp_path, resume=True), PICK).name == "bc"
    assert choose_method(TrainArgs(out=tmp_path, resume=True, algo="td3"), PICK).name == "td3"
    assert choose_method(TrainArgs(out=tmp_path / "elsewhere"), PICK).name == "dagger"  # no resume: not read


def test_resume_with_nothing_to_resume_is_refused(tmp_path: Path) -> None:
    with pytest.raises(TrainingError) as caught:
        choose_method(TrainArgs(out=tmp_path, resume=True), REACH)
    assert str(caught.value) == f"nothing to resume in {tmp_path}: no train_state.json"


# ------------------------------------------------------------------ train()
class Recorded:
    """A stand-in training method: records how it was built; ``run`` answers ``"result"``."""

    built: list[tuple[TrainArgs, str, Any]] = []

    def __init__(self, args: TrainArgs, env_id: str, spec: Any) -> None:
        Recorded.built.append((args, env_id, spec))

    def run(self) -> str:
        return "result"


@pytest.fixture
def recorded(monkeypatch: pytest.MonkeyPatch) -> list[tuple[TrainArgs, str, Any]]:
    """Every method's class replaced by :class:`Recorded`; the list of what was built."""
    Recorded.built = []
    for name, spec in METHODS.items():
        monkeypatch.setitem(
            METHODS, name, type(spec)(**{**spec.__dict__, "entry_point": f"{__name__}:Recorded"})
        )
    return Recorded.built


def test_train_runs_the_chosen_method_on_the_versioned_env(
    tmp_path: Path, recorded: list[tuple[TrainArgs, str, Any]]
) -> None:
    args = TrainArgs(env="Bioscara-Reach", out=tmp_path, seed=0, timesteps=1, n_envs=1)
    assert train(args) == "result"
    ((given, env_id, spec),) = recorded
    assert given is args and env_id == REACH and spec.name == "sac"
    train(TrainArgs(env="Bioscara-PickPlace", out=tmp_path))
    assert recorded[-1][1] == PICK and recorded[-1][2].name == "dagger"


@pytest.mark.parametrize(
    ("changes", "message"),
    [
        ({"seed": -1}, "--seed must be >= 0, got -1"),
        ({"timesteps": 0}, "--timesteps 0: must be >= 1 (omit it for the config's n_timesteps)"),
        ({"n_envs": 0}, "--n-envs 0: must be >= 1 (omit it for the config's n_envs)"),
        ({"algo": "a2c"}, "unknown algo 'a2c'; choose one of sac, td3, ppo, bc, dagger"),
    ],
    ids=["seed", "timesteps", "n_envs", "algo"],
)
def test_train_refuses_bad_input_before_building_anything(
    tmp_path: Path, recorded: list[tuple[TrainArgs, str, Any]], changes: dict[str, Any], message: str
) -> None:
    with pytest.raises(TrainingError) as caught:
        train(TrainArgs(env="Bioscara-Reach", out=tmp_path / "run", **changes))
    assert str(caught.value) == message
    assert recorded == [] and not (tmp_path / "run").exists()


def test_train_refuses_an_unknown_env_first(
    tmp_path: Path, recorded: list[tuple[TrainArgs, str, Any]]
) -> None:
    with pytest.raises(TrainingError, match="Bioscara-Nope"):
        train(TrainArgs(env="Bioscara-Nope", out=tmp_path, seed=-1))
    assert recorded == []


def test_train_module_exports_what_the_cli_and_the_tests_import() -> None:
    assert set(train_module.__all__) == {
        "TrainArgs",
        "TrainResult",
        "TrainingInterrupted",
        "check_n_envs",
        "check_timesteps",
        "choose_method",
        "train",
    }
