"""What ``bioscara train`` leaves in ``--out``: a refused run leaves nothing, an earlier run is never lost.

The rules (README, "Using it"): bad input is one line before anything is
written; a new run never goes into a folder that holds another run (its
``train_state.json``, checkpoints or model), which ``--resume`` would
otherwise continue as if it were this one; ``--resume`` refuses a
checkpoint of another algorithm than the run's; every check of ``--out``,
of the config and of the demonstrations comes before an env is built or a
file is written. Each case is refused within a second or two.
"""

from __future__ import annotations

import json
import os
import re
from collections.abc import Iterator
from pathlib import Path
from typing import Any

import gymnasium as gym
import pytest
import yaml
from rigs import TINY_SAC_ENTRY

import bioscara_gym  # noqa: F401 - registers the tasks
from bioscara_gym.cli import main
from bioscara_gym.errors import EXIT_ERROR, HyperparamError

REACH = "Bioscara-Reach-v0"
PICK = "Bioscara-PickPlace-v1"
#: Reach's registered episode length (steps).
REACH_STEPS = 50

#: The tiny SAC + HER entry, valid as it stands, evaluating after its budget only.
ENTRY: dict[str, Any] = {**TINY_SAC_ENTRY, "eval_freq": 1000}

#: A SAC run's ``train_state.json`` on Reach (the config filled in per case).
STATE: dict[str, Any] = {
    "env_id": REACH,
    "algo": "sac",
    "seed": 1,
    "total_timesteps": 300,
    "config": None,
    "demos": None,
}


def config(root: Path, env_id: str = REACH, **changes: Any) -> Path:
    """``root/cfg.yaml``: :data:`ENTRY` for ``env_id`` with ``changes`` (``None`` removes a key)."""
    entry = {k: v for k, v in {**ENTRY, **changes}.items() if v is not None}
    path = root / "cfg.yaml"
    path.write_text(yaml.safe_dump({env_id: entry}, sort_keys=False), encoding="utf-8")
    return path


def snapshot(root: Path) -> dict[str, bytes]:
    """Every file under ``root`` and its contents (folders listed as such)."""
    return {
        str(p.relative_to(root)): p.read_bytes() if p.is_file() else b"<dir>"
        for p in sorted(root.rglob("*"))
        if not p.is_symlink()
    }


def refused(capsys: pytest.CaptureFixture[str], argv: list[str]) -> str:
    """Run ``bioscara ARGV``; check it is refused in one line with exit code 2, and return the line."""
    rc = main(argv)
    err = capsys.readouterr().err
    assert "Traceback" not in err, err
    lines = err.strip().splitlines()
    assert len(lines) == 1, f"expected one line, got {len(lines)}:\n{err}"
    assert lines[0].startswith("bioscara train: error: "), lines[0]
    assert rc == EXIT_ERROR
    return lines[0]


@pytest.fixture
def no_env(monkeypatch: pytest.MonkeyPatch) -> None:
    """Make ``gym.make`` fail the test: what is checked here must be refused before an env is made."""

    def made(*args: Any, **kwargs: Any) -> None:
        raise AssertionError(f"an env was made before the refusal: gym.make{args}")

    monkeypatch.setattr(gym, "make", made)


# ------------------------------------------------- a new run into an earlier run
def _state(run: Path, cfg: Path) -> None:
    run.mkdir(exist_ok=True)
    (run / "train_state.json").write_text(json.dumps({**STATE, "config": str(cfg)}), encoding="utf-8")


def _checkpoint(run: Path, cfg: Path) -> None:
    (run / "checkpoints").mkdir(parents=True)
    (run / "checkpoints" / "ckpt_200_steps.zip").write_bytes(b"an earlier run's")


def _model(run: Path, cfg: Path) -> None:
    run.mkdir(exist_ok=True)
    (run / "model.zip").write_bytes(b"an earlier run's")
    (run / "metadata.json").write_text("{}", encoding="utf-8")


@pytest.mark.parametrize(
    ("held", "named"),
    [
        ([_state], r"train_state\.json"),
        ([_checkpoint], r"checkpoints"),
        ([_state, _checkpoint], r"train_state\.json, checkpoints"),
        ([_model], r"model\.zip"),
    ],
    ids=["state", "checkpoints", "state-and-checkpoints", "model"],
)
@pytest.mark.usefixtures("no_env")
def test_a_new_run_into_a_folder_holding_a_run_is_refused_and_leaves_it_as_it_was(
    tmp_path: Path, capsys: pytest.CaptureFixture[str], held: list[Any], named: str
) -> None:
    # Seen (a hostile test): train_state.json rewritten for the new run, the earlier run's
    # checkpoints kept, and --resume continued the seed-1 run as seed 2.
    cfg = config(tmp_path)
    run = tmp_path / "run"
    for make in held:
        make(run, cfg)
    (run / "notes.txt").write_text("mine", encoding="utf-8")
    before = snapshot(tmp_path)
    line = refused(
        capsys, ["train", "--algo", "td3", "--config", str(cfg), "--out", str(run), "--no-progress"]
    )
    assert re.search(rf"--out {re.escape(str(run))} already holds a run \({named}", line), line
    assert "--resume" in line and "another --out" in line
    assert snapshot(tmp_path) == before


def test_a_new_run_into_a_folder_of_other_files_trains(tmp_path: Path) -> None:
    run = tmp_path / "run"
    run.mkdir()
    (run / "notes.txt").write_text("mine", encoding="utf-8")
    (run / "tb").mkdir()  # TensorBoard logs alone are no run to lose
    assert main(["train", "--config", str(config(tmp_path)), "--out", str(run), "--timesteps", "1"]) == 0
    assert (run / "model.zip").is_file() and (run / "notes.txt").read_text(encoding="utf-8") == "mine"


def test_a_finished_run_is_not_overwritten_by_a_second_new_run(
    tmp_path: Path, capsys: pytest.CaptureFixture[str]
) -> None:
    # The hostile test's sequence with small budgets: a SAC run with checkpoints, then TD3 into it.
    cfg = config(tmp_path)
    run = tmp_path / "run"
    first = ["train", "--algo", "sac", "--config", str(cfg), "--out", str(run), "--no-progress"]
    assert main([*first, "--timesteps", "120", "--seed", "1"]) == 0
    capsys.readouterr()
    before = snapshot(tmp_path)
    second = ["train", "--algo", "td3", "--config", str(cfg), "--out", str(run), "--seed", "2"]
    line = refused(capsys, [*second, "--no-progress"])
    assert "already holds a run" in line
    assert snapshot(tmp_path) == before
    assert json.loads((run / "train_state.json").read_text(encoding="utf-8"))["seed"] == 1


# --------------------------------------------- --resume of another algorithm's checkpoint
def _sac_checkpoint(folder: Path, steps: int) -> Path:
    """A whole SAC + HER checkpoint (model and replay buffer) of Reach, named ``ckpt_<steps>_steps``."""
    from stable_baselines3 import SAC, HerReplayBuffer

    from bioscara_gym.training.checkpoints import save_checkpoint
    from bioscara_gym.training.zoo import SACGoalErrorPolicy

    env = gym.make(REACH, control_mode="cartesian", reward_type="dense")
    try:
        model = SAC(
            SACGoalErrorPolicy,
            env,
            buffer_size=1000,
            replay_buffer_class=HerReplayBuffer,
            policy_kwargs={"net_arch": [16, 16]},
            device="cpu",
        )
        return save_checkpoint(model, folder, steps, {"_replay.pkl": model.save_replay_buffer})
    finally:
        env.close()


def test_resume_from_another_algorithms_checkpoint_is_one_line_and_changes_nothing(
    tmp_path: Path, capsys: pytest.CaptureFixture[str]
) -> None:
    # Seen (a hostile test): a TD3 run's state over a SAC run's checkpoints; --resume ended in
    # "AttributeError: 'SACGoalErrorPolicy' object has no attribute 'actor_target'".
    cfg = config(tmp_path)
    run = tmp_path / "run"
    run.mkdir()
    state = {**STATE, "algo": "td3", "config": str(cfg)}
    (run / "train_state.json").write_text(json.dumps(state), encoding="utf-8")
    checkpoint = _sac_checkpoint(run / "checkpoints", 200)
    before = snapshot(tmp_path)
    line = refused(capsys, ["train", "--resume", "--out", str(run), "--no-progress"])
    assert re.search(rf"cannot resume from {re.escape(str(checkpoint))}: ", line), line
    assert "TD3" in line  # what the run is
    assert snapshot(tmp_path) == before
    assert not (run / "tb").exists()


# ------------------------------------------------- demonstrations checked up front
@pytest.fixture(scope="module")
def velocity_dataset(tmp_path_factory: pytest.TempPathFactory) -> Iterator[Path]:
    """Two expert Reach episodes recorded in velocity control (the tiny config trains cartesian)."""
    pytest.importorskip("minari", reason="minari is in the [train] extra")
    root = tmp_path_factory.mktemp("minari")
    with pytest.MonkeyPatch.context() as mp:
        mp.setenv("MINARI_DATASETS_PATH", str(root))
        argv = ["collect", "--no-progress", "--expert", "--env", "Bioscara-Reach", "--episodes", "2"]
        assert main([*argv, "--dataset", "vel", "--control-mode", "velocity"]) == 0
    yield root


@pytest.mark.parametrize("given", ["--demos", "config"])
def test_demos_of_another_control_mode_are_refused_before_the_run_writes_anything(
    velocity_dataset: Path,
    tmp_path: Path,
    capsys: pytest.CaptureFixture[str],
    monkeypatch: pytest.MonkeyPatch,
    given: str,
) -> None:
    # Seen (a hostile test): refused 8 s in, from inside learn(), after train_state.json and
    # tb/run_1 were written.
    monkeypatch.setenv("MINARI_DATASETS_PATH", str(velocity_dataset))
    run = tmp_path / "run"
    demos = {"bioscara_gym.training.zoo.DemonstrationCallback": {"dataset": "vel", "pretrain_steps": 5}}
    if given == "--demos":
        argv = ["train", "--config", str(config(tmp_path)), "--demos", "vel"]
    else:
        argv = ["train", "--config", str(config(tmp_path, callback=[demos]))]
    capsys.readouterr()
    line = refused(capsys, [*argv, "--out", str(run), "--no-progress", "--seed", "7"])
    assert line.endswith(
        "dataset vel-v0 was recorded with control_mode='velocity', the env has control_mode='cartesian'"
    ), line
    assert not run.exists()


# ------------------------------------------------------ what HER needs of the config
@pytest.mark.parametrize(
    ("env_id", "changes", "key", "value", "needed"),
    [
        (REACH, {"learning_starts": 10}, "learning_starts", "10", REACH_STEPS),
        (REACH, {"buffer_size": 10}, "buffer_size", "10", REACH_STEPS),
        (REACH, {"learning_starts": REACH_STEPS - 1}, "learning_starts", "49", REACH_STEPS),
        (PICK, {"learning_starts": None}, "learning_starts", r"100 \(SAC's default\)", 200),
    ],
    ids=["learning-starts", "buffer-size", "one-step-short", "sacs-default-on-pickplace"],
)
@pytest.mark.usefixtures("no_env")
def test_a_config_that_her_cannot_sample_from_is_refused_naming_file_and_entry(
    tmp_path: Path,
    capsys: pytest.CaptureFixture[str],
    env_id: str,
    changes: dict[str, Any],
    key: str,
    value: str,
    needed: int,
) -> None:
    # Seen (a hostile test): "RuntimeError: Unable to sample before the end of the first episode"
    # after training started, train_state.json and tb/ left behind.
    cfg = config(tmp_path, env_id, **changes)
    run = tmp_path / "run"
    argv = ["train", "--algo", "sac", "--env", env_id, "--config", str(cfg), "--out", str(run)]
    line = refused(capsys, [*argv, "--no-progress"])
    assert re.search(
        rf"config {re.escape(str(cfg))}: {env_id}\.{key} is {value}; .*HerReplayBuffer.* at least {needed} ",
        line,
    ), line
    assert not run.exists()


def test_learning_starts_of_one_episode_on_every_env_is_what_her_needs() -> None:
    from stable_baselines3 import SAC, TD3

    from bioscara_gym.training.hyperparams import Hyperparams, check_her_episodes

    def hp(**algo_kwargs: Any) -> Hyperparams:
        return Hyperparams(source="cfg.yaml", n_timesteps=300, algo_kwargs=algo_kwargs)

    check_her_episodes(hp(learning_starts=REACH_STEPS), SAC, REACH, REACH_STEPS, n_envs=1)
    check_her_episodes(hp(learning_starts=2 * REACH_STEPS), TD3, REACH, REACH_STEPS, n_envs=2)
    with pytest.raises(HyperparamError, match=r"learning_starts is 99; .* at least 100 .*2 envs"):
        check_her_episodes(hp(learning_starts=99), TD3, REACH, REACH_STEPS, n_envs=2)
    # No HER: a replay buffer of the config's own, or an env without goals.
    check_her_episodes(hp(learning_starts=1, replay_buffer_class=None), SAC, REACH, REACH_STEPS, n_envs=1)
    check_her_episodes(hp(learning_starts=1), SAC, "Pendulum-v1", 200, n_envs=1)


# ----------------------------------------------------------- env_kwargs and --out
def test_a_bad_reward_type_names_the_config_and_its_entry(
    tmp_path: Path, capsys: pytest.CaptureFixture[str]
) -> None:
    cfg = config(tmp_path, env_kwargs={"control_mode": "cartesian", "reward_type": "bogus"})
    run = tmp_path / "run"
    line = refused(capsys, ["train", "--config", str(cfg), "--out", str(run), "--no-progress"])
    assert re.search(
        rf"error: config {re.escape(str(cfg))}: {REACH}\.env_kwargs: reward_type 'bogus' must be one of ",
        line,
    ), line
    assert not run.exists()


@pytest.mark.skipif(not Path("/proc").is_dir(), reason="no /proc: a folder that refuses files")
@pytest.mark.usefixtures("no_env")
def test_an_out_that_cannot_be_made_is_refused_first_naming_out(
    tmp_path: Path, capsys: pytest.CaptureFixture[str]
) -> None:
    line = refused(
        capsys, ["train", "--config", str(config(tmp_path)), "--out", "/proc/foo", "--no-progress"]
    )
    assert line.startswith("bioscara train: error: --out /proc/foo: cannot write in /proc"), line
    assert not Path("/proc/foo").exists()


@pytest.mark.parametrize("where", ["out", "parent"])
@pytest.mark.usefixtures("no_env")
def test_an_out_through_a_dangling_symlink_is_refused_first_naming_out(
    tmp_path: Path, capsys: pytest.CaptureFixture[str], where: str
) -> None:
    # Seen (a hostile test): "error: File exists: dangl" after the envs and the model were built.
    link = tmp_path / "dangl"
    link.symlink_to(tmp_path / "gone")
    out = link if where == "out" else link / "run"
    cfg = config(tmp_path)
    before = snapshot(tmp_path)
    line = refused(capsys, ["train", "--config", str(cfg), "--out", str(out), "--no-progress"])
    assert line.startswith(f"bioscara train: error: --out {out}: {link} is a symlink to "), line
    assert "does not exist" in line
    assert snapshot(tmp_path) == before
    assert not (tmp_path / "gone").exists() and os.path.islink(link)


# ------------------------------------------------ --resume of an interrupted run
def _train_until_interrupted(monkeypatch: pytest.MonkeyPatch, argv: list[str], at: int) -> None:
    """Run ``bioscara ARGV`` with Ctrl-C at env step ``at`` (from the evaluation callback, once)."""
    from bioscara_gym.training.zoo import SuccessEvalCallback

    original = SuccessEvalCallback._on_step

    def interrupt(self: SuccessEvalCallback) -> bool:
        if self.num_timesteps == at:
            raise KeyboardInterrupt
        return original(self)

    with monkeypatch.context() as mp:
        mp.setattr(SuccessEvalCallback, "_on_step", interrupt)
        assert main(argv) == 130


def _saved_n_envs(model: Path) -> int:
    """The envs a saved model says it stepped."""
    import zipfile

    with zipfile.ZipFile(model) as archive:
        return json.loads(archive.read("data"))["n_envs"]


def test_resume_from_a_checkpoint_cut_before_the_first_episode_ended_learns_on(
    tmp_path: Path, monkeypatch: pytest.MonkeyPatch, capsys: pytest.CaptureFixture[str]
) -> None:
    # Suspected (a review): the unfinished episode dropped, learning at step 61 before a new
    # episode ends, HER's "Unable to sample before the end of the first episode". It is kept,
    # cut short (stable-baselines3's truncate_last_trajectory), so HER samples it.
    from stable_baselines3.common.save_util import load_from_pkl

    cfg, run = config(tmp_path, n_timesteps=150, learning_starts=60), tmp_path / "run"
    argv = ["train", "--config", str(cfg), "--out", str(run), "--no-progress"]
    _train_until_interrupted(monkeypatch, argv, at=30)
    buffer = load_from_pkl(run / "checkpoints" / "ckpt_30_steps_replay.pkl")
    assert buffer.pos > 0 and not (buffer.ep_length > 0).any()  # no whole episode in it
    capsys.readouterr()
    assert main(["train", "--resume", "--out", str(run), "--no-progress"]) == 0
    assert "Traceback" not in capsys.readouterr().err
    assert (run / "model.zip").is_file()


def test_resume_steps_the_envs_of_the_run_not_the_configs_n_envs(
    tmp_path: Path, monkeypatch: pytest.MonkeyPatch, capsys: pytest.CaptureFixture[str]
) -> None:
    # Seen: a run trained with --n-envs 1 on a config of n_envs 4, Ctrl-C, then the printed
    # `--resume --out RUN` was refused by HER's check for 4 envs ("at least 200"); past it, 4
    # envs met a replay buffer of 1 ("cannot reshape array"). A run on 2 resumed on 1 the same.
    cfg, run = config(tmp_path, n_timesteps=150, n_envs=4), tmp_path / "run"
    argv = ["train", "--config", str(cfg), "--out", str(run), "--no-progress", "--n-envs", "1"]
    _train_until_interrupted(monkeypatch, argv, at=30)
    capsys.readouterr()
    rc = main(["train", "--resume", "--out", str(run), "--no-progress"])
    assert rc == 0, capsys.readouterr().err
    assert _saved_n_envs(run / "model.zip") == 1


def _forbid_envs(monkeypatch: pytest.MonkeyPatch) -> None:
    """As :func:`no_env`, from now on."""

    def made(*args: Any, **kwargs: Any) -> None:
        raise AssertionError(f"an env was made before the refusal: gym.make{args}")

    monkeypatch.setattr(gym, "make", made)


def test_resume_of_an_off_policy_run_on_other_n_envs_is_refused_in_one_line(
    tmp_path: Path, capsys: pytest.CaptureFixture[str], monkeypatch: pytest.MonkeyPatch
) -> None:
    # Seen: HER's check passed for --n-envs 2 (learning_starts 100), then two envs met the
    # checkpoint's replay buffer of one: "ValueError: cannot reshape array of size 4 into shape (2,4)".
    cfg, run = config(tmp_path), tmp_path / "run"
    run.mkdir()
    (run / "train_state.json").write_text(json.dumps({**STATE, "config": str(cfg)}), encoding="utf-8")
    _sac_checkpoint(run / "checkpoints", 200)
    _forbid_envs(monkeypatch)
    before = snapshot(tmp_path)
    line = refused(capsys, ["train", "--resume", "--out", str(run), "--n-envs", "2", "--no-progress"])
    assert re.search(rf"--resume continues {re.escape(str(run))}'s 1 env\b.*--n-envs 2 would change", line)
    assert snapshot(tmp_path) == before


@pytest.mark.parametrize("recorded", ["packaged", "another-file"])
def test_resume_with_another_config_than_the_runs_is_refused_and_keeps_its_state(
    tmp_path: Path, capsys: pytest.CaptureFixture[str], monkeypatch: pytest.MonkeyPatch, recorded: str
) -> None:
    # Seen: a run on the packaged config resumed with --config FILE trained on FILE's entry and
    # rewrote train_state.json to it; a run on a file of its own ignored --config without a word.
    (tmp_path / "other").mkdir()
    cfg, other = config(tmp_path), config(tmp_path / "other")
    run = tmp_path / "run"
    run.mkdir()
    state = {**STATE, "config": None if recorded == "packaged" else str(other)}
    (run / "train_state.json").write_text(json.dumps(state), encoding="utf-8")
    _sac_checkpoint(run / "checkpoints", 200)
    _forbid_envs(monkeypatch)
    before = snapshot(tmp_path)
    argv = ["train", "--resume", "--out", str(run), "--config", str(cfg), "--no-progress"]
    line = refused(capsys, argv)
    assert re.search(
        rf"--resume continues {re.escape(str(run))}'s config .*; --config {re.escape(str(cfg))} "
        r"would change it",
        line,
    ), line
    assert snapshot(tmp_path) == before


@pytest.mark.parametrize("recorded", ["packaged", "file"])
def test_resume_with_the_runs_own_config_keeps_its_recorded_state(tmp_path: Path, recorded: str) -> None:
    from bioscara_gym.training.methods import method_spec
    from bioscara_gym.training.run import TrainArgs

    spec = method_spec("sac")
    cfg, run = config(tmp_path), tmp_path / "run"
    run.mkdir()
    state = {**STATE, "config": None if recorded == "packaged" else str(cfg)}
    (run / "train_state.json").write_text(json.dumps(state), encoding="utf-8")
    _sac_checkpoint(run / "checkpoints", 200)
    given = spec.default_config() if recorded == "packaged" else cfg
    args = TrainArgs(env=REACH, config=given, out=run, resume=True, progress=False)
    plan = spec.method_class()(args, REACH, spec).plan()
    assert plan.state == state


@pytest.mark.parametrize(
    ("recorded", "given"), [("pp", "other"), (None, "pp")], ids=["another", "none-before"]
)
def test_resume_with_other_demonstrations_than_the_runs_is_refused_and_keeps_its_state(
    tmp_path: Path,
    capsys: pytest.CaptureFixture[str],
    monkeypatch: pytest.MonkeyPatch,
    recorded: str | None,
    given: str,
) -> None:
    # Before: --resume --demos X trained on X while train_state.json still named the run's own.
    run = tmp_path / "run"
    run.mkdir()
    (run / "train_state.json").write_text(json.dumps({**STATE, "demos": recorded}), encoding="utf-8")
    _sac_checkpoint(run / "checkpoints", 200)
    _forbid_envs(monkeypatch)
    before = snapshot(tmp_path)
    line = refused(capsys, ["train", "--resume", "--out", str(run), "--demos", given, "--no-progress"])
    shown = f"demonstrations {recorded}" if recorded else "run without demonstrations"
    assert line.endswith(
        f"--resume continues {run}'s {shown}; --demos {given} would change them "
        "(drop it, or train a new run with --out elsewhere)"
    ), line
    assert snapshot(tmp_path) == before


def test_resume_with_the_runs_own_demonstrations_by_their_full_id_keeps_its_state(tmp_path: Path) -> None:
    from bioscara_gym.training.methods import method_spec
    from bioscara_gym.training.run import TrainArgs

    spec = method_spec("sac")
    run = tmp_path / "run"
    run.mkdir()
    state = {**STATE, "demos": "pp"}
    (run / "train_state.json").write_text(json.dumps(state), encoding="utf-8")
    _sac_checkpoint(run / "checkpoints", 200)
    args = TrainArgs(env=REACH, demos="pp-v0", out=run, resume=True, progress=False)
    method = spec.method_class()(args, REACH, spec)
    assert method.resumed().demos == "pp"
    assert args.demos == "pp"
