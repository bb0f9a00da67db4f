"""Hostile hyperparameter files for ``bioscara train --config``: one line, exit 2, nothing written.

Each case was seen to misbehave: infinities and NaN trained (and were written
into ``metadata.json`` as bare ``NaN``, not JSON) or failed in torch with two
lines naming neither file nor key; a number YAML reads as a string (``9e-1``)
reached numpy; a string in a DAgger file failed a comparison with a
``TypeError``; ``net_arch=[1000000000]`` asked torch for 72 GB; a key given
twice silently took the last value; an alias bomb hung the tool while its
error message was written.
"""

from __future__ import annotations

import re
import threading
from collections.abc import Callable
from pathlib import Path
from typing import Any

import pytest
import yaml
from rigs import TINY_SAC_ENTRY, train_refusal

from bioscara_gym.errors import HyperparamError
from bioscara_gym.training.algos import sb3_class
from bioscara_gym.training.dagger_config import load_dagger_config
from bioscara_gym.training.hyperparams import check_algo_kwargs, load_hyperparams

REACH = "Bioscara-Reach-v0"
PICK = "Bioscara-PickPlace-v1"

#: A tiny PPO entry, valid as it stands.
PPO_ENTRY: dict[str, Any] = {
    "n_timesteps": 64,
    "policy": "MultiInputPolicy",
    "n_steps": 32,
    "batch_size": 32,
    "env_kwargs": {"reward_type": "dense"},
    "eval_freq": 32,
    "eval_episodes": 1,
}

Setup = Callable[[Path], list[str]]


def _run(algo: str, text: Callable[[dict[str, Any]], str], env: str = "Bioscara-Reach") -> Setup:
    def setup(root: Path) -> list[str]:
        config = root / "cfg.yaml"
        config.write_text(
            text({"sac": TINY_SAC_ENTRY, "td3": TINY_SAC_ENTRY, "ppo": PPO_ENTRY}.get(algo, {})),
            encoding="utf-8",
        )
        out = str(root / "run")
        return ["train", "--algo", algo, "--env", env, "--out", out, "--config", str(config), "--no-progress"]

    return setup


def run(algo: str = "sac", **changes: Any) -> Setup:
    """A new run of ``algo`` on its tiny entry with ``changes``."""
    return _run(algo, lambda entry: yaml.safe_dump({REACH: {**entry, **changes}}, sort_keys=False))


def run_lines(*lines: str, algo: str = "sac") -> Setup:
    """A new run of ``algo`` on its tiny entry followed by ``lines`` as written (YAML's own reading)."""

    def text(entry: dict[str, Any]) -> str:
        head = yaml.safe_dump({REACH: entry}, sort_keys=False)
        return head + "".join(f"  {line}\n" for line in lines)

    return _run(algo, text)


def dagger(*lines: str) -> Setup:
    """A new DAgger run on PickPlace whose entry is ``lines`` as written."""
    body = "".join(f"  {line}\n" for line in ("n_timesteps: 1000", *lines))
    return _run("dagger", lambda _: f"{PICK}:\n{body}", env="Bioscara-PickPlace")


SCHEDULE = r", or lin_<x> with such an x \(a schedule from x down to 0\)$"
WIDTHS = (
    r"; expected layer widths, whole numbers >= 1 and at most 4096, at most 16 layers "
    r"\(a list, or a mapping of pi, qf or vf to lists\)$"
)

CASES = [
    # 1 and 7: infinities, NaN, zero and negative values of rates and coefficients.
    pytest.param(
        run_lines("learning_rate: .inf", algo="ppo"),
        r"cfg\.yaml: Bioscara-Reach-v0\.learning_rate is inf; expected a finite number > 0" + SCHEDULE,
        id="learning-rate-inf",
    ),
    pytest.param(
        run(learning_rate=0),
        r"cfg\.yaml: Bioscara-Reach-v0\.learning_rate is 0; expected a finite number > 0" + SCHEDULE,
        id="learning-rate-zero",
    ),
    pytest.param(
        run(learning_rate="lin_inf"),
        r"\.learning_rate is 'lin_inf'; expected a finite number > 0" + SCHEDULE,
        id="learning-rate-schedule-inf",
    ),
    pytest.param(
        run(learning_rate="lin_-0.001"),
        r"\.learning_rate is 'lin_-0\.001'; expected a finite number > 0" + SCHEDULE,
        id="learning-rate-schedule-negative",
    ),
    pytest.param(
        run_lines("clip_range: .nan", algo="ppo"),
        r"cfg\.yaml: Bioscara-Reach-v0\.clip_range is nan; expected a finite number > 0" + SCHEDULE,
        id="clip-range-nan",
    ),
    pytest.param(
        run_lines("max_grad_norm: .inf", algo="ppo"),
        r"\.max_grad_norm is inf; expected a finite number > 0$",
        id="max-grad-norm-inf",
    ),
    pytest.param(
        run(algo="ppo", max_grad_norm=0),
        r"\.max_grad_norm is 0; expected a finite number > 0$",
        id="max-grad-norm-zero",
    ),
    pytest.param(
        run(algo="ppo", ent_coef=-0.5),
        r"\.ent_coef is -0\.5; expected a finite number >= 0, or \(SAC\) auto or auto_<x> with x a finite "
        r"number > 0$",
        id="ent-coef-negative",
    ),
    pytest.param(
        run(algo="ppo", ent_coef="auto"),
        r"\.ent_coef is 'auto'; expected a finite number >= 0 \(PPO has no automatic entropy coefficient\)$",
        id="ent-coef-auto-for-ppo",
    ),
    pytest.param(
        run(ent_coef="auto_0"),
        r"\.ent_coef is 'auto_0'; expected a finite number >= 0, or \(SAC\) auto or auto_<x>",
        id="ent-coef-auto-zero",
    ),
    pytest.param(
        run(algo="ppo", gae_lambda=1.5),
        r"\.gae_lambda is 1\.5; expected a number in \[0, 1\]$",
        id="gae-lambda-above-one",
    ),
    pytest.param(
        run_lines("vf_coef: .inf", algo="ppo"),
        r"\.vf_coef is inf; expected a finite number >= 0$",
        id="vf-coef-inf",
    ),
    pytest.param(
        run_lines("target_kl: .nan", algo="ppo"),
        r"\.target_kl is nan; expected a finite number > 0, or null$",
        id="target-kl-nan",
    ),
    pytest.param(run_lines("tau: .nan"), r"\.tau is nan; expected a number in \(0, 1\]$", id="tau-nan"),
    pytest.param(
        run(train_freq=0),
        r"\.train_freq is 0; expected a whole number >= 1, or \[n, step\] or \[n, episode\]$",
        id="train-freq-zero",
    ),
    pytest.param(
        run(gradient_steps=0),
        r"\.gradient_steps is 0; expected a whole number >= 1, or -1 \(as many as env steps collected\)$",
        id="gradient-steps-zero",
    ),
    pytest.param(
        run_lines("noise_type: normal", "noise_std: .inf", algo="td3"),
        r"\.noise_std is inf; expected a finite number$",
        id="noise-std-inf",
    ),
    pytest.param(
        run_lines("noise_type: normal", "noise_std: -0.1", algo="td3"),
        r"\.noise_std is -0\.1; expected a finite number >= 0$",
        id="noise-std-negative",
    ),
    pytest.param(
        run_lines("use_sde: true", "sde_sample_freq: .nan"),
        r"cfg\.yaml: Bioscara-Reach-v0\.sde_sample_freq is nan; expected a finite number$",
        id="nan-in-another-key",
    ),
    # 2: numbers YAML reads as strings.
    pytest.param(
        run_lines("gamma: 9e-1", algo="ppo"),
        r"cfg\.yaml: Bioscara-Reach-v0\.gamma is '9e-1', a string; write 0\.9$",
        id="gamma-a-string",
    ),
    pytest.param(
        run_lines("learning_rate: 1e-5"),
        r"\.learning_rate is '1e-5', a string; write 1\.0e-05$",
        id="learning-rate-a-string",
    ),
    pytest.param(
        run(buffer_size="1e5"),
        r"\.buffer_size is '1e5', a string; write 100000$",
        id="buffer-size-a-string",
    ),
    pytest.param(run(n_envs="2"), r"\.n_envs is '2', a string; write 2$", id="n-envs-a-string"),
    pytest.param(
        run(eval_freq="2e2"), r"\.eval_freq is '2e2', a string; write 200$", id="eval-freq-a-string"
    ),
    pytest.param(
        run(target_success="0.9"),
        r"\.target_success is '0\.9', a string; write 0\.9$",
        id="target-success-a-string",
    ),
    pytest.param(
        run(learning_rate="nan"),
        r"\.learning_rate is 'nan', a string; expected a finite number$",
        id="learning-rate-the-string-nan",
    ),
    # 3: DAgger.
    pytest.param(
        dagger("learning_rate: 1e-3"),
        r"Bioscara-PickPlace-v1\.learning_rate is '1e-3', a string; write 0\.001$",
        id="dagger-learning-rate-a-string",
    ),
    pytest.param(
        dagger('target_success: "0.9"'),
        r"Bioscara-PickPlace-v1\.target_success is '0\.9', a string; write 0\.9$",
        id="dagger-target-success-a-string",
    ),
    pytest.param(
        dagger("beta: half"),
        r"cfg\.yaml: beta is 'half'; expected a number in \[0, 1\)$",
        id="dagger-beta-a-word",
    ),
    pytest.param(
        dagger("learning_rate: .inf"),
        r"Bioscara-PickPlace-v1\.learning_rate is inf; expected a finite number$",
        id="dagger-learning-rate-inf",
    ),
    pytest.param(
        dagger("learning_rate: true"),
        r"cfg\.yaml: learning_rate is True; expected a number > 0$",
        id="dagger-learning-rate-a-bool",
    ),
    pytest.param(
        dagger("net_arch: [100000000]"),
        r"cfg\.yaml: net_arch is \[100000000\]; expected layer widths >= 1 and at most 4096, "
        r"at most 16 layers$",
        id="dagger-net-arch-too-wide",
    ),
    # 5: layer widths and depth.
    pytest.param(
        run(policy_kwargs="dict(net_arch=[1000000000])"),
        r"Bioscara-Reach-v0\.policy_kwargs\.net_arch is \[1000000000\]" + WIDTHS,
        id="net-arch-too-wide",
    ),
    pytest.param(
        run(algo="ppo", policy_kwargs=f"dict(net_arch=dict(pi=[8], vf={[8] * 17}))"),
        r"\.policy_kwargs\.net_arch is \{'pi': \[8\], 'vf': \[8, 8, 8, 8, \.\.\.\]\}" + WIDTHS,
        id="net-arch-too-deep",
    ),
    # 6: a key given twice.
    pytest.param(
        run_lines("gamma: 0.9", "gamma: 0.5", algo="ppo"),
        r"cfg\.yaml is not valid YAML at line 11, column 3: found duplicate key 'gamma'$",
        id="duplicate-key",
    ),
    pytest.param(
        dagger("beta: 0.5", "beta: 0.1"),
        r"cfg\.yaml is not valid YAML at line 4, column 3: found duplicate key 'beta'$",
        id="dagger-duplicate-key",
    ),
]


@pytest.mark.parametrize(("setup", "message"), CASES)
def test_hostile_config_is_one_line_exit_2_and_nothing_written(
    tmp_path: Path, capsys: pytest.CaptureFixture[str], setup: Setup, message: str
) -> None:
    line = train_refusal(tmp_path, capsys, setup(tmp_path), message)
    assert line.startswith("bioscara train: error: config "), line
    assert not (tmp_path / "run").exists()


def test_the_suggested_spelling_of_a_string_number_is_a_number_to_yaml(tmp_path: Path) -> None:
    for written, suggested in (("9e-1", 0.9), ("1e-5", 1e-05), ("3e-4", 0.0003), ("1e20", 1e20)):
        config = tmp_path / "cfg.yaml"
        config.write_text(yaml.safe_dump({REACH: {**PPO_ENTRY, "learning_rate": written}}), encoding="utf-8")
        with pytest.raises(HyperparamError) as error:
            load_hyperparams(config, REACH)
        fix = str(error.value).rpartition("; write ")[2]
        assert yaml.safe_load(fix) == suggested, str(error.value)


def _bomb(entry: str) -> str:
    """``entry`` after anchors 11 levels deep of 9 aliases each (9**11 leaves of ``*a11``)."""
    lines = ["a0: &a0 [x]"]
    lines += [f"a{i}: &a{i} [" + ", ".join([f"*a{i - 1}"] * 9) + "]" for i in range(1, 12)]
    return "\n".join(lines) + "\n" + entry


BOMBS = [
    pytest.param("sac", "n_envs: *a11", r"\.n_envs is \[\[\[\.\.\.\], ", id="n-envs"),
    pytest.param("sac", "gamma: *a11", r"\.gamma is \[\[\[\.\.\.\], ", id="gamma"),
    pytest.param("sac", "policy_kwargs: {net_arch: *a11}", r"\.net_arch is \[\[\[", id="net-arch"),
    pytest.param("sac", "callback: *a11", r"\.callback: expected a dotted path", id="callback"),
    pytest.param("dagger", "loss: *a11", r": loss is \[\[\[\.\.\.\], ", id="dagger-loss"),
]


@pytest.mark.parametrize(("algo", "line", "message"), BOMBS)
def test_an_alias_bomb_is_refused_at_once_with_a_short_message(
    tmp_path: Path, algo: str, line: str, message: str
) -> None:
    env_id = PICK if algo == "dagger" else REACH
    entry = (
        {"n_timesteps": 1000}
        if algo == "dagger"
        else {k: v for k, v in TINY_SAC_ENTRY.items() if k != "policy_kwargs"}
    )
    text = _bomb(yaml.safe_dump({env_id: entry}, sort_keys=False) + f"  {line}\n")
    config = tmp_path / "cfg.yaml"
    config.write_text(text, encoding="utf-8")
    assert len(text) < 10_000
    result: list[BaseException] = []

    def check() -> None:
        try:
            if algo == "dagger":
                load_dagger_config(config, env_id)
            else:
                check_algo_kwargs(load_hyperparams(config, env_id), sb3_class("SAC"), env_id)
        except BaseException as e:  # handed to the test's thread
            result.append(e)

    worker = threading.Thread(target=check, daemon=True)
    worker.start()
    worker.join(timeout=1)
    assert not worker.is_alive(), "the check did not return within 1 s"
    assert len(result) == 1 and isinstance(result[0], HyperparamError), result
    assert len(str(result[0])) < 600, str(result[0])
    assert re.search(message, str(result[0])), str(result[0])
