"""Demonstrations: `bioscara collect` into Minari datasets; learning from them (`--demos`, `--algo bc`)."""

from __future__ import annotations

import json
import re
import shutil
from pathlib import Path

import gymnasium as gym
import numpy as np
import pytest
import yaml

import bioscara_gym  # noqa: F401
from bioscara_gym.cli import main

minari = pytest.importorskip("minari", reason="minari is in the [train] extra")

PICK = "Bioscara-PickPlace-v1"
REACH = "Bioscara-Reach-v0"


pytestmark = pytest.mark.usefixtures("datasets")  # Minari's datasets in the test's tmp_path


def collect(*args: str) -> int:
    return main(["collect", "--no-progress", *args])


def tiny_config(tmp_path: Path, env_id: str = PICK, **callback: object) -> Path:
    """The packaged SAC entry with a 2-episode evaluation and a small demonstration callback."""
    from bioscara_gym.training.hyperparams import default_config_path

    entry = yaml.safe_load(default_config_path("sac").read_text(encoding="utf-8"))[env_id]
    entry.update(learning_starts=210, batch_size=32, buffer_size=2000)
    entry["callback"] = [
        {"bioscara_gym.training.zoo.SuccessEvalCallback": {"eval_freq": 10_000, "eval_episodes": 2}},
        {"bioscara_gym.training.zoo.DemonstrationCallback": dict(episodes=2, pretrain_steps=20, **callback)},
    ]
    path = tmp_path / "tiny.yaml"
    path.write_text(yaml.safe_dump({env_id: entry}), encoding="utf-8")
    return path


@pytest.fixture(scope="module")
def pick_dataset(tmp_path_factory: pytest.TempPathFactory) -> Path:
    """Two expert PickPlace episodes, recorded once for the module."""
    root = tmp_path_factory.mktemp("shared_minari")
    with pytest.MonkeyPatch.context() as mp:
        mp.setenv("MINARI_DATASETS_PATH", str(root))
        assert collect("--expert", "--env", "Bioscara-PickPlace", "--episodes", "2", "--dataset", "pick") == 0
    return root


def test_collect_records_a_minari_dataset_that_recovers_its_env(
    pick_dataset: Path, monkeypatch: pytest.MonkeyPatch
) -> None:
    monkeypatch.setenv("MINARI_DATASETS_PATH", str(pick_dataset))
    dataset = minari.load_dataset("pick-v0")
    assert dataset.total_episodes == 2
    assert dataset.total_steps == 400  # 200-step episodes
    env = dataset.recover_environment()
    try:
        assert env.spec.id == PICK
        assert env.unwrapped.control_mode == "cartesian"  # the packaged config's, so --demos fits it
    finally:
        env.close()


def test_collect_prints_size_and_success_rate(capsys: pytest.CaptureFixture[str]) -> None:
    assert collect("--expert", "--env", "Bioscara-Reach", "--episodes", "2", "--dataset", "reach") == 0
    out = capsys.readouterr().out
    assert "reach-v0: 2 episodes, 100 steps" in out
    assert "MB" in out and "success 100.0%" in out


def test_load_demos_flattens_episodes_into_transitions(
    pick_dataset: Path, monkeypatch: pytest.MonkeyPatch
) -> None:
    from bioscara_gym.training.demos import load_demos

    monkeypatch.setenv("MINARI_DATASETS_PATH", str(pick_dataset))
    env = gym.make(PICK, control_mode="cartesian")
    try:
        demos = load_demos("pick", env)
    finally:
        env.close()
    assert len(demos) == 400
    assert demos.obs["observation"].shape == (400, 22)
    assert demos.actions.shape == (400, 5)
    np.testing.assert_array_equal(demos.obs["observation"][1:200], demos.next_obs["observation"][:199])
    assert list(demos.episode_starts) == [0, 200]


def test_demos_from_another_control_mode_are_refused(
    pick_dataset: Path, monkeypatch: pytest.MonkeyPatch
) -> None:
    from bioscara_gym.errors import TrainingError
    from bioscara_gym.training.demos import load_demos

    monkeypatch.setenv("MINARI_DATASETS_PATH", str(pick_dataset))
    env = gym.make(PICK, control_mode="velocity")
    try:
        with pytest.raises(TrainingError, match="control_mode='cartesian'"):
            load_demos("pick", env)
    finally:
        env.close()


def test_collect_refuses_an_existing_dataset_without_overwrite(
    datasets: Path, capsys: pytest.CaptureFixture[str]
) -> None:
    assert collect("--expert", "--env", "Bioscara-Reach", "--episodes", "1", "--dataset", "r") == 0
    capsys.readouterr()
    assert collect("--expert", "--env", "Bioscara-Reach", "--episodes", "2", "--dataset", "r") == 2
    err = capsys.readouterr().err
    assert err.count("\n") == 1 and "--overwrite" in err
    assert minari.load_dataset("r-v0").total_episodes == 1
    again = ["--expert", "--env", "Bioscara-Reach", "--episodes", "2", "--dataset", "r", "--overwrite"]
    assert collect(*again) == 0
    assert minari.load_dataset("r-v0").total_episodes == 2


@pytest.mark.parametrize(
    ("args", "message"),
    [
        (["--expert", "--env", "Bioscara-Nope", "--episodes", "1"], "unknown env"),
        (["--expert", "--episodes", "0"], "--episodes must be > 0"),
        (["--episodes", "1"], "exactly one of --expert or --model"),
        (["--expert", "--episodes", "1", "--seed", "-1"], "--seed must be >= 0, got -1"),  # was a traceback
    ],
)
def test_collect_bad_input_is_one_line_and_writes_nothing(
    args: list[str], message: str, datasets: Path, capsys: pytest.CaptureFixture[str]
) -> None:
    assert collect(*args, "--dataset", "bad") == 2
    err = capsys.readouterr().err
    assert err.count("\n") == 1 and message in err
    assert not (datasets / "bad-v0").exists()


def test_interrupted_collect_leaves_no_dataset(datasets: Path, monkeypatch: pytest.MonkeyPatch) -> None:
    from bioscara_gym.training import demos

    calls = {"n": 0}

    def factory(env: gym.Env) -> tuple[object, object]:
        def policy(obs: dict[str, np.ndarray]) -> np.ndarray:
            calls["n"] += 1
            if calls["n"] > 60:
                raise KeyboardInterrupt
            return np.zeros(env.action_space.shape, dtype=np.float32)

        return policy, lambda: None

    with pytest.raises(KeyboardInterrupt):
        demos.collect(REACH, 3, "cut", factory, progress=False)
    assert not (datasets / "cut-v0").exists()
    assert [p.name for p in datasets.iterdir()] == []  # no temporary directory either


def test_collect_on_the_emulated_backend(datasets: Path) -> None:
    assert collect("--expert", "--env", "Bioscara-Reach", "--episodes", "1", "--dataset", "emu",
                   "--backend", "emulated") == 0  # fmt: skip
    env = minari.load_dataset("emu-v0").recover_environment()
    try:
        assert env.spec.kwargs["backend"] == "emulated"
    finally:
        env.close()


def test_bc_trains_a_model_that_eval_and_collect_load(
    pick_dataset: Path, tmp_path: Path, monkeypatch: pytest.MonkeyPatch, capsys: pytest.CaptureFixture[str]
) -> None:
    monkeypatch.setenv("MINARI_DATASETS_PATH", str(pick_dataset))
    out = tmp_path / "bc"
    cfg = tiny_config(tmp_path)
    args = ["train", "--algo", "bc", "--env", "Bioscara-PickPlace", "--demos", "pick", "--timesteps", "50"]
    assert main([*args, "--config", str(cfg), "--out", str(out), "--no-progress"]) == 0
    metadata = json.loads((out / "metadata.json").read_text(encoding="utf-8"))
    assert metadata["algo"] == "bc" and metadata["bc_steps"] == 50
    assert metadata["demos"]["dataset"] == "pick"
    assert "final success rate" in capsys.readouterr().out
    assert main(["eval", "--model", str(out / "model.zip"), "--episodes", "1"]) == 0
    monkeypatch.setenv("MINARI_DATASETS_PATH", str(tmp_path / "mine"))
    assert collect("--model", str(out / "model.zip"), "--episodes", "1", "--dataset", "from-bc") == 0


def test_train_with_demos_learns_from_the_dataset_and_saves_a_plain_sac(
    pick_dataset: Path, tmp_path: Path, monkeypatch: pytest.MonkeyPatch, capsys: pytest.CaptureFixture[str]
) -> None:
    from stable_baselines3 import SAC

    monkeypatch.setenv("MINARI_DATASETS_PATH", str(pick_dataset))
    out = tmp_path / "run"
    args = ["train", "--env", "Bioscara-PickPlace", "--demos", "pick", "--timesteps", "260"]
    assert main([*args, "--config", str(tiny_config(tmp_path)), "--out", str(out), "--no-progress"]) == 0
    # Only the successful episodes are learned from (the cartesian expert fails some).
    assert re.search(r"\[demos\] \d successful episodes, \d+ steps from pick-v0", capsys.readouterr().out)
    metadata = json.loads((out / "metadata.json").read_text(encoding="utf-8"))
    assert metadata["demos"]["dataset"] == "pick"
    assert metadata["demos"]["steps"] == 200 * metadata["demos"]["episodes"]
    act_only = {"replay_buffer_class": None, "replay_buffer_kwargs": {}, "buffer_size": 1}
    model = SAC.load(out / "model.zip", custom_objects=act_only)
    assert model.num_timesteps == 260
    assert not hasattr(model, "demo_buffer") or model.demo_buffer is None


@pytest.mark.parametrize("damage", ["missing", "truncated", "metadata-emptied", "another-task"])
def test_train_with_a_bad_dataset_is_one_line_and_writes_nothing(
    pick_dataset: Path, tmp_path: Path, damage: str, capsys: pytest.CaptureFixture[str]
) -> None:
    # Seen (a hostile test): train_state.json and the TensorBoard folder left in --out, and
    # h5py's 'Unable to synchronously open file (truncated file: ...)' naming no dataset.
    root = tmp_path / "minari"
    shutil.copytree(pick_dataset, root)
    env_id = "Bioscara-PickPlace"
    if damage == "truncated":
        data = next(root.glob("pick-v0/data/*.hdf5"))
        data.write_bytes(data.read_bytes()[:2000])
        expected = r"dataset pick-v0 in .*minari cannot be read: .*truncated"
    elif damage == "metadata-emptied":  # a second hostile pass: Minari's own AssertionError
        (root / "pick-v0" / "data" / "metadata.json").write_text("{}")
        expected = r"dataset pick-v0 in .*minari cannot be read: Minari's AssertionError$"
    elif damage == "another-task":  # a second hostile pass: refused after the run's files were made
        env_id = "Bioscara-Reach"
        expected = r"dataset pick-v0 was recorded on Bioscara-PickPlace-v1, not Bioscara-Reach-v0$"
    else:
        shutil.rmtree(root / "pick-v0")
        expected = r"no dataset pick-v0 in .*minari; record one with"
    out = tmp_path / "run"
    args = ["train", "--env", env_id, "--algo", "sac", "--demos", "pick", "--timesteps", "260"]
    config = tiny_config(tmp_path, env_id=f"{env_id}-v1" if env_id.endswith("PickPlace") else f"{env_id}-v0")
    assert main([*args, "--config", str(config), "--out", str(out), "--no-progress"]) == 2
    err = capsys.readouterr().err.strip()
    assert "\n" not in err and re.match(rf"bioscara train: error: {expected}", err), err
    assert not out.exists()


def test_q_filtered_bc_update_logs_its_losses() -> None:
    from stable_baselines3 import SAC
    from stable_baselines3.common.logger import configure

    from bioscara_gym.experts import expert_for
    from bioscara_gym.training.demos import rollout_demos
    from bioscara_gym.training.hyperparams import default_config_path
    from bioscara_gym.training.imitation import DemoSAC, attach_demos
    from bioscara_gym.training.sb3 import algo_kwargs, load_run_hyperparams

    hp = load_run_hyperparams("SAC", default_config_path("sac"), REACH)
    env = gym.make(REACH, **hp.env_kwargs)
    try:
        expert = expert_for(env.unwrapped)
        demos = rollout_demos(env, expert, expert.reset, 1)
        kwargs = {**algo_kwargs(hp, env, "sac"), "learning_starts": 1000, "buffer_size": 200}
        model = SAC(hp.policy, env, seed=0, device="cpu", **kwargs)
        model.set_logger(configure(None, []))
        model.learn(60)  # one episode in the buffer, no update yet
        attach_demos(model, demos, np.zeros(len(demos)), demo_batch_size=8)
        assert isinstance(model, DemoSAC)
        model.train(gradient_steps=2, batch_size=16)
    finally:
        env.close()
    logged = model.logger.name_to_value
    assert logged["train/bc_loss"] >= 0 and 0 <= logged["train/q_filter_kept"] <= 1
