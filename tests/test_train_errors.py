"""``bioscara train`` on bad input: one line on stderr, exit code 2, nothing trained or written.

A table of bad inputs, as tests/test_config.py has for the arm's YAML: each
case writes its files into a fresh directory, runs the CLI in-process and
checks the one line (naming the file, key and expectation), the exit code,
that no traceback was printed and that nothing was trained or written: a
new run leaves no output directory, a ``--resume`` leaves the run as it was.
Every case is refused before an env step is taken, so the table runs in a
few seconds.
"""

from __future__ import annotations

import json
import os
import threading
import time
import zipfile
from collections.abc import Callable
from pathlib import Path
from typing import Any

import pytest
import yaml
from rigs import TINY_SAC_ENTRY, train_refusal

from bioscara_gym.cli import main
from bioscara_gym.errors import EXIT_ERROR

REACH = "Bioscara-Reach-v0"

#: A tiny SAC + HER entry, valid as it stands.
ENTRY: dict[str, Any] = TINY_SAC_ENTRY

#: A valid ``train_state.json`` of a SAC run on Reach (the config is filled in per case).
STATE: dict[str, Any] = {
    "env_id": REACH,
    "algo": "sac",
    "seed": 0,
    "total_timesteps": 300,
    "config": None,
    "demos": None,
}

#: Builds a case's inputs in a directory and returns the ``bioscara`` arguments.
Setup = Callable[[Path], list[str]]


def _config(root: Path, **changes: Any) -> Path:
    """``root/cfg.yaml``: :data:`ENTRY` with ``changes`` (``None`` removes a key)."""
    entry = {k: v for k, v in {**ENTRY, **changes}.items() if v is not None}
    path = root / "cfg.yaml"
    path.write_text(yaml.safe_dump({REACH: entry}, sort_keys=False), encoding="utf-8")
    return path


def new_run(*extra: str, **changes: Any) -> Setup:
    """A new run on a config with ``changes``, with extra arguments."""

    def setup(root: Path) -> list[str]:
        config = _config(root, **changes)
        return ["train", "--out", str(root / "run"), "--config", str(config), "--no-progress", *extra]

    return setup


def out_a_file(root: Path) -> list[str]:
    """``--out`` naming a file (seen: "[Errno 17] File exists")."""
    (root / "run").write_text("notes")
    return ["train", "--out", str(root / "run"), "--config", str(_config(root)), "--no-progress"]


#: Fills a run's ``checkpoints`` folder.
Checkpoints = Callable[[Path], None]


def resume(
    state_text: Callable[[Path], str] | None, *extra: str, checkpoint: bool | Checkpoints = False
) -> Setup:
    """``--resume`` of a run whose ``train_state.json`` is ``state_text(config)`` (``None``: no file).

    ``checkpoint``: make the (empty) checkpoints folder, or with a function fill it.
    """

    def setup(root: Path) -> list[str]:
        config = _config(root)
        run = root / "run"
        run.mkdir()
        if state_text is not None:
            (run / "train_state.json").write_text(state_text(config), encoding="utf-8")
        if checkpoint:
            (run / "checkpoints").mkdir()
        if callable(checkpoint):
            checkpoint(run / "checkpoints")
        return ["train", "--resume", "--out", str(run), "--no-progress", *extra]

    return setup


def model_zip(steps: int, n_envs: int | None = None) -> Checkpoints:
    """A checkpoint ``ckpt_<steps>_steps.zip``: a whole zip of a model's members, and nothing beside it.

    ``n_envs``: the envs its model says it stepped (SB3's ``data``); none said if ``None``.
    """

    def fill(folder: Path) -> None:
        with zipfile.ZipFile(folder / f"ckpt_{steps}_steps.zip", "w") as archive:
            archive.writestr("data", "{}" if n_envs is None else json.dumps({"n_envs": n_envs}))
            archive.writestr("policy.pth", b"")

    return fill


def fifo(name: str) -> Checkpoints:
    """A FIFO ``name`` in the checkpoints folder, with a model zip of 100 steps as its checkpoint.

    A reader that opens it (seen: ``--resume`` hung there) is released by a
    writer that opens and closes it at once, so the case fails instead of hanging.
    """

    def release(path: Path) -> None:
        deadline = time.monotonic() + 30
        while time.monotonic() < deadline:
            try:
                os.close(os.open(path, os.O_WRONLY | os.O_NONBLOCK))  # ENXIO until a reader opens it
            except OSError:
                time.sleep(0.05)
                continue
            return

    def fill(folder: Path) -> None:
        model_zip(100)(folder)
        os.mkfifo(folder / name)
        threading.Thread(target=release, args=(folder / name,), daemon=True).start()

    return fill


def state_json(**changes: Any) -> Callable[[Path], str]:
    """A ``train_state.json`` text: :data:`STATE` for the case's config, with ``changes``."""

    def text(config: Path) -> str:
        return json.dumps({**STATE, "config": str(config), **changes})

    return text


def without(key: str) -> Callable[[Path], str]:
    """A ``train_state.json`` text lacking ``key``."""

    def text(config: Path) -> str:
        state = {**STATE, "config": str(config)}
        del state[key]
        return json.dumps(state)

    return text


CASES = [
    # train_state.json of --resume.
    pytest.param(resume(None), r"nothing to resume in .*run: no train_state\.json", id="resume-no-state"),
    pytest.param(
        resume(without("algo")), r"run/train_state\.json: key 'algo' is missing", id="state-missing-key"
    ),
    pytest.param(
        resume(without("total_timesteps")),
        r"run/train_state\.json: key 'total_timesteps' is missing",
        id="state-missing-total",
    ),
    pytest.param(
        resume(lambda _: "{nope"),
        r"run/train_state\.json: not readable JSON \(Expecting",
        id="state-not-json",
    ),
    pytest.param(
        resume(lambda _: "[1, 2]"),
        r"run/train_state\.json: expected a JSON object, got list",
        id="state-a-list",
    ),
    pytest.param(
        resume(state_json(), "--timesteps", "999", checkpoint=True),
        r"--resume continues .*run's budget of \d+ steps; --timesteps 999 would change it",
        id="resume-with-another-budget",
    ),
    pytest.param(
        resume(state_json(seed="0")),
        r"run/train_state\.json: seed is '0'; expected int",
        id="state-seed-not-int",
    ),
    pytest.param(
        resume(state_json(total_timesteps=0)),
        r"run/train_state\.json: total_timesteps is 0; expected >= 1",
        id="state-total-zero",
    ),
    pytest.param(
        resume(state_json(), checkpoint=True),
        r"nothing to resume in .*run/checkpoints: no checkpoint",
        id="resume-no-checkpoint",
    ),
    # Seen (a hostile test): --seed ignored, the run's seed 0 used without a word.
    pytest.param(
        resume(state_json(seed=3), "--seed", "5", checkpoint=model_zip(200)),
        r"--resume continues .*run's seed 3; --seed 5 would change it \(drop it, or train a new run",
        id="resume-with-another-seed",
    ),
    pytest.param(  # --seed 0 was --seed's default: it was taken as not given
        resume(state_json(seed=3), "--seed", "0", checkpoint=model_zip(200)),
        r"--resume continues .*run's seed 3; --seed 0 would change it \(drop it, or train a new run",
        id="resume-with-seed-0-given",
    ),
    # Seen: a budget below the steps taken finished the run (exit 0, a new model.zip).
    pytest.param(
        resume(state_json(total_timesteps=100), checkpoint=model_zip(2491)),
        r"cannot resume from .*run/train_state\.json: total_timesteps is 100, below the 2491 steps its "
        r"checkpoint ckpt_2491_steps\.zip has taken$",
        id="state-total-below-the-steps-taken",
    ),
    # A run on 8 envs ends up to 8 steps past its budget (SAC, train_freq 1): one more is refused,
    # though --resume is not told --n-envs (a reviewer's: a PPO run on 8 was refused on 1).
    pytest.param(
        resume(state_json(total_timesteps=100), checkpoint=model_zip(109, n_envs=8)),
        r"total_timesteps is 100, below the 109 steps its checkpoint ckpt_109_steps\.zip has taken$",
        id="state-total-one-step-past-eight-envs",
    ),
    pytest.param(
        resume(state_json(total_timesteps=100), checkpoint=model_zip(108, n_envs=8)),
        r"ckpt_108_steps\.zip cannot be loaded",
        id="state-total-eight-envs-past-is-resumed",
    ),
    pytest.param(  # DAgger's run may end a phase past its budget: 120 episodes of 200 steps
        resume(
            state_json(env_id="Bioscara-PickPlace-v1", algo="dagger", config=None, total_timesteps=1000),
            "--env",
            "Bioscara-PickPlace",
            checkpoint=model_zip(25_001),
        ),
        r"cannot resume from .*run/train_state\.json: total_timesteps is 1000, below the 25001 steps its "
        r"checkpoint ckpt_25001_steps\.zip has taken$",
        id="dagger-state-total-below-the-steps-taken",
    ),
    pytest.param(  # one phase past: the budget passes, and the checkpoint's missing aggregate is named
        resume(
            state_json(env_id="Bioscara-PickPlace-v1", algo="dagger", config=None, total_timesteps=1000),
            "--env",
            "Bioscara-PickPlace",
            checkpoint=model_zip(25_000),
        ),
        r"ckpt_25000_steps\.zip cannot be loaded \(FileNotFoundError: .*ckpt_25000_steps_dagger\.npz'\)$",
        id="dagger-state-total-one-phase-below-the-steps-taken",
    ),
    # Seen: accepted, though --seed refuses it.
    pytest.param(
        resume(state_json(seed=10**30), checkpoint=model_zip(200)),
        r"run/train_state\.json: seed is 1000000000000000000000000000000; expected 0 to 4294967295$",
        id="state-seed-beyond-32-bits",
    ),
    pytest.param(
        resume(state_json(seed=-1), checkpoint=model_zip(200)),
        r"run/train_state\.json: seed is -1; expected 0 to 4294967295$",
        id="state-seed-negative",
    ),
    # Seen: HER's 28-line "Unable to sample before the end of the first episode" traceback.
    pytest.param(
        resume(state_json(), checkpoint=model_zip(200)),
        r"cannot resume: checkpoint .*run/checkpoints/ckpt_200_steps\.zip cannot be loaded "
        r"\(FileNotFoundError: its replay buffer ckpt_200_steps_replay\.pkl is missing\)$",
        id="resume-without-the-replay-buffer",
    ),
    # Seen: --resume hung, reading a FIFO.
    pytest.param(
        resume(state_json(), checkpoint=fifo("ckpt_250_steps.zip")),
        r"cannot resume from .*run/checkpoints/ckpt_250_steps\.zip: not a regular file$",
        id="checkpoint-a-fifo",
    ),
    pytest.param(
        resume(state_json(), checkpoint=fifo("ckpt_100_steps_replay.pkl")),
        r"cannot resume from .*run/checkpoints/ckpt_100_steps_replay\.pkl: not a regular file$",
        id="replay-buffer-a-fifo",
    ),
    # Hyperparameter keys.
    pytest.param(
        new_run(batch_sise=32),
        r"cfg\.yaml: Bioscara-Reach-v0\.batch_sise is not a hyperparameter of SAC; "
        r"did you mean 'batch_size'\?",
        id="hyperparameter-typo",
    ),
    pytest.param(
        new_run(zzz=1),
        r"cfg\.yaml: Bioscara-Reach-v0\.zzz is not a hyperparameter of SAC; see the SAC documentation$",
        id="hyperparameter-unknown",
    ),
    pytest.param(
        new_run(policy_kwargs="dict(net_arch=[16, 16], no_such_option=1)"),
        r"cfg\.yaml: Bioscara-Reach-v0: TypeError: .*no_such_option",
        id="policy-kwarg-unknown",
    ),
    # The evaluation schedule and the budget.
    pytest.param(
        new_run(eval_freq=0),
        r"cfg\.yaml: Bioscara-Reach-v0\.eval_freq is 0; expected a whole number >= 1",
        id="eval-freq-zero",
    ),
    pytest.param(
        new_run(eval_freq=-200),
        r"cfg\.yaml: Bioscara-Reach-v0\.eval_freq is -200; expected a whole number >= 1",
        id="eval-freq-negative",
    ),
    pytest.param(
        new_run(eval_episodes=0),
        r"cfg\.yaml: Bioscara-Reach-v0\.eval_episodes is 0; expected a whole number >= 1",
        id="eval-episodes-zero",
    ),
    pytest.param(
        new_run(
            eval_freq=None,
            eval_episodes=None,
            callback=[{"bioscara_gym.training.zoo.SuccessEvalCallback": {"eval_episodes": 0}}],
        ),
        r"Bioscara-Reach-v0\.callback\.SuccessEvalCallback\.eval_episodes is 0; expected a whole number",
        id="eval-episodes-zero-in-callback",
    ),
    pytest.param(
        new_run(
            eval_freq=None,
            eval_episodes=None,
            callback=[{"bioscara_gym.training.zoo.SuccessEvalCallback": {"first_eval": 0}}],
        ),
        r"Bioscara-Reach-v0\.callback\.SuccessEvalCallback\.first_eval is 0; expected a whole number >= 1 "
        r"\(env steps before the first success evaluation\)",
        id="first-eval-zero",
    ),
    pytest.param(
        new_run(target_success=1.5),
        r"Bioscara-Reach-v0\.target_success is 1\.5; expected a success rate in \[0, 1\]",
        id="target-success-above-one",
    ),
    pytest.param(
        new_run(
            eval_freq=None,
            eval_episodes=None,
            callback=[{"bioscara_gym.training.zoo.SuccessEvalCallback": {"stop_success": 0.9}}],
        ),
        r"Bioscara-Reach-v0\.callback\.SuccessEvalCallback\.stop_success is 0\.9; expected at least "
        r"target_success \(0\.95\)",
        id="stop-below-target",
    ),
    pytest.param(
        new_run(n_timesteps=0),
        r"cfg\.yaml: Bioscara-Reach-v0\.n_timesteps is 0; expected a whole number >= 1",
        id="n-timesteps-zero",
    ),
    pytest.param(new_run("--timesteps", "0"), r"--timesteps 0: must be >= 1", id="timesteps-zero"),
    pytest.param(new_run("--timesteps", "-5"), r"--timesteps -5: must be >= 1", id="timesteps-negative"),
    pytest.param(
        new_run("--timesteps", "0", "--algo", "bc"), r"--timesteps 0: must be >= 1", id="bc-timesteps-zero"
    ),
    # Seen: a 30-line traceback from gymnasium's seeding.
    pytest.param(new_run("--seed", "-1"), r"--seed must be >= 0, got -1$", id="seed-negative"),
    # Seen (a hostile test): "config .../sac.yaml: Bioscara-Reach-v0: ValueError: Seed must be ..."
    pytest.param(
        new_run("--seed", "4294967296"),
        r"--seed must be <= 4294967295 \(2\*\*32 - 1\), got 4294967296$",
        id="seed-beyond-32-bits",
    ),
    pytest.param(
        new_run("--seed", "4294967296", "--algo", "bc"),
        r"--seed must be <= 4294967295 \(2\*\*32 - 1\), got 4294967296$",
        id="bc-seed-beyond-32-bits",
    ),
    pytest.param(
        new_run("--seed", "4294967296", "--algo", "dagger", "--env", "Bioscara-PickPlace"),
        r"--seed must be <= 4294967295 \(2\*\*32 - 1\), got 4294967296$",
        id="dagger-seed-beyond-32-bits",
    ),
    # Seen (a hostile test): accepted, and training started.
    pytest.param(new_run("--threads", "0"), r"--threads must be >= 1, got 0$", id="threads-zero"),
    pytest.param(out_a_file, r"--out .*run is a file; give a folder for the run$", id="out-a-file"),
    pytest.param(
        new_run("--seed", "-1", "--algo", "dagger", "--env", "Bioscara-PickPlace"),
        r"--seed must be >= 0, got -1$",
        id="dagger-seed-negative",
    ),
    # SB3 takes these and trains on nothing (seen: batch_size 0 trained and saved a model).
    pytest.param(
        new_run(batch_size=0),
        r"cfg\.yaml: Bioscara-Reach-v0\.batch_size is 0; expected a whole number >= 1 \(samples per gradient",
        id="batch-size-zero",
    ),
    pytest.param(
        new_run(buffer_size=-1),
        r"Bioscara-Reach-v0\.buffer_size is -1; expected a whole number >= 1",
        id="buffer-size-negative",
    ),
    pytest.param(
        new_run(learning_starts=-5),
        r"Bioscara-Reach-v0\.learning_starts is -5; expected a whole number >= 0",
        id="learning-starts-negative",
    ),
    # Seen (a hostile test, 2026-11-29): tracebacks of 32 and 47 lines, and os.system called.
    pytest.param(
        new_run(env_kwargs={"control_mode": "cartesian", "bogus_env_kw": 1}),
        r"cfg\.yaml: Bioscara-Reach-v0\.env_kwargs has 'bogus_env_kw', which Bioscara-Reach-v0 "
        r"does not take; it takes .*control_mode",
        id="env-kwarg-unknown",
    ),
    pytest.param(
        new_run(policy_kwargs="dict(net_arch=[-64, 64])"),
        r"Bioscara-Reach-v0\.policy_kwargs\.net_arch is \[-64, 64\]; expected layer widths, "
        r"whole numbers >= 1",
        id="net-arch-negative",
    ),
    pytest.param(
        new_run(policy_kwargs="dict(net_arch=dict(pi=[64], qf=[0]))"),
        r"\.net_arch is \{'pi': \[64\], 'qf': \[0\]\}; expected layer widths",
        id="net-arch-zero-in-a-mapping",
    ),
    pytest.param(  # a reviewer's: a traceback from the check itself
        new_run(policy_kwargs="dict(net_arch=dict(pi=64, qf=[16]))"),
        r"\.net_arch is \{'pi': 64, 'qf': \[16\]\}; expected layer widths",
        id="net-arch-a-width-not-a-list",
    ),
    pytest.param(  # a second hostile pass: SB3 asserts a list, a traceback
        new_run(policy_kwargs="dict(net_arch=(64, 64))"),
        r"\.net_arch is \(64, 64\); expected layer widths",
        id="net-arch-a-tuple",
    ),
    pytest.param(
        new_run(policy=".foo.Bar"),
        r"\.policy: '\.foo\.Bar' is not a dotted path package\.module\.Name$",
        id="policy-a-relative-path",
    ),
    pytest.param(
        new_run(n_envs=1000),
        r"cfg\.yaml: Bioscara-Reach-v0\.n_envs 1000: at most \d+ on this machine's \d+ CPUs",
        id="config-n-envs-beyond-the-workers",
    ),
    pytest.param(  # a hostile test of the config files: it ran the command, then an AttributeError
        new_run(callback=[{"os.system": {"command": "true"}}]),
        r"cfg\.yaml: Bioscara-Reach-v0\.callback: os\.system is not a stable-baselines3 callback class "
        r"\(BaseCallback\)$",
        id="callback-not-a-callback-class",
    ),
    pytest.param(  # the last hostile test's: numpy's 'Unable to allocate 21.8 TiB' traceback
        new_run(buffer_size=10**12),
        r"cfg\.yaml: Bioscara-Reach-v0: the model does not fit in memory \(MemoryError: Unable to "
        r"allocate .* for an array with shape \(1000000000000, 1, .*\); lower buffer_size$",
        id="buffer-size-beyond-memory",
    ),
    pytest.param(
        new_run(policy="os.system"),
        r"cfg\.yaml: Bioscara-Reach-v0\.policy: os\.system is not a stable-baselines3 policy class$",
        id="policy-not-a-policy-class",
    ),
    pytest.param(
        lambda root: ["train", "--out", str(root / "run"), "--config", "/dev/zero", "--no-progress"],
        r"cannot read config /dev/zero: not a regular file$",
        id="config-a-device",
    ),
    # Seen (a hostile test, 2026-11-29): a TypeError and an AttributeError traceback from gym.make.
    pytest.param(
        new_run(env_kwargs={"control_mode": "cartesian", "randomization": 3}),
        r"randomization must be true, false, null or a mapping of mass, friction, damping, "
        r"sensor_noise, latency_steps; got 3$",
        id="randomization-a-number",
    ),
    pytest.param(
        new_run(env_kwargs={"control_mode": "cartesian", "randomization": {"mas": 0.1}}),
        r"randomization has 'mas'; it takes mass, friction",
        id="randomization-a-misspelt-field",
    ),
    pytest.param(
        new_run(env_kwargs={"control_mode": "cartesian", "render_mode": 5}),
        r"cfg\.yaml: Bioscara-Reach-v0\.env_kwargs has render_mode 5; Bioscara-Reach-v0 renders "
        r"rgb_array, human or null$",
        id="render-mode-a-number",
    ),
    pytest.param(
        new_run(env_kwargs={"control_mode": "cartesian", "render_mode": "ansi"}),
        r"env_kwargs has render_mode 'ansi'; Bioscara-Reach-v0 renders rgb_array, human or null$",
        id="render-mode-unknown",
    ),
    pytest.param(new_run(gamma=1.5), r"\.gamma is 1\.5; expected a number in \(0, 1\]", id="gamma"),
    pytest.param(new_run(tau=0), r"\.tau is 0; expected a number in \(0, 1\]", id="tau-zero"),
]


@pytest.mark.parametrize(("setup", "message"), CASES)
def test_bad_train_input_is_one_line_exit_2_and_nothing_written(
    tmp_path: Path, capsys: pytest.CaptureFixture[str], setup: Setup, message: str
) -> None:
    train_refusal(tmp_path, capsys, setup(tmp_path), message)


def test_a_dagger_resume_allows_a_phase_of_the_configs_own_episode_length(
    tmp_path: Path, capsys: pytest.CaptureFixture[str]
) -> None:
    # Seen (a review): a config of 800-step episodes, interrupted after iteration 0 at 800 steps of
    # a 1-step budget: the printed --resume command was refused ("below the 800 steps"); the
    # overshoot came from the registered 200 steps. 120 episodes of 800 steps are 96,000.
    packaged = Path(__file__).parent.parent / "training" / "configs" / "dagger.yaml"
    entry = yaml.safe_load(packaged.read_text(encoding="utf-8"))["Bioscara-PickPlace-v1"]
    entry["env_kwargs"] = {**entry["env_kwargs"], "max_episode_steps": 800}
    config = tmp_path / "dagger.yaml"
    config.write_text(yaml.safe_dump({"Bioscara-PickPlace-v1": entry}), encoding="utf-8")
    run = tmp_path / "run"
    (run / "checkpoints").mkdir(parents=True)
    state = {**STATE, "env_id": "Bioscara-PickPlace-v1", "algo": "dagger", "config": str(config)}
    (run / "train_state.json").write_text(json.dumps({**state, "total_timesteps": 1}), encoding="utf-8")
    for steps, expected in (
        (96_002, "below the 96002 steps"),  # the budget's 1 step and a phase past it: 96,001
        (96_001, "ckpt_96001_steps.zip cannot be loaded"),
    ):
        for old in (run / "checkpoints").iterdir():
            old.unlink()
        model_zip(steps)(run / "checkpoints")
        argv = ["train", "--resume", "--out", str(run), "--env", "Bioscara-PickPlace", "--no-progress"]
        assert main(argv) == EXIT_ERROR
        assert expected in capsys.readouterr().err
