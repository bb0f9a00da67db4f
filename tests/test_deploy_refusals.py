"""``bioscara deploy`` refuses bad input in one line, before a byte reaches the arm.

A table of the ways a user gets deploy wrong (hand-edited or mismatched
policy files, arguments out of range), run through the real command line
in-process, the way test_config walks bad YAML. Each row must end with
exactly one line on stderr that names the problem, exit code 2, no
traceback, no run log, and no transaction on the emulated bus.
"""

from __future__ import annotations

import json
import shutil
import zipfile
from collections.abc import Callable
from pathlib import Path
from typing import Any

import gymnasium as gym
import pytest
from rigs import nan_actor_weights

from bioscara_gym.cli import main
from bioscara_gym.training.metadata import EMBEDDED_NAME, build_metadata, write_metadata

REACH = "Bioscara-Reach-v0"
PICK_PLACE = "Bioscara-PickPlace-v1"


# ------------------------------------------------------------ file editors
def edit_metadata(
    change: Callable[[dict[str, Any]], Any], inside: bool = False
) -> Callable[[Path], list[str]]:
    """A row's setup: copy the policy, replace its metadata by ``change(metadata)``.

    ``inside``: the copy inside ``model.zip`` too, as a model trained so would have it.
    """

    def setup(run: Path) -> list[str]:
        metadata = json.loads((run / "metadata.json").read_text())
        new = change(metadata)
        (run / "metadata.json").write_text(json.dumps(metadata if new is None else new))
        if inside:
            embed(run, metadata if new is None else new)
        return ["--model", str(run / "model.zip")]

    return setup


def without(*path: str) -> Callable[[dict[str, Any]], None]:
    def change(metadata: dict[str, Any]) -> None:
        node = metadata
        for key in path[:-1]:
            node = node[key]
        del node[path[-1]]

    return change


def setting(value: Any, *path: str) -> Callable[[dict[str, Any]], None]:
    def change(metadata: dict[str, Any]) -> None:
        node = metadata
        for key in path[:-1]:
            node = node[key]
        node[path[-1]] = value

    return change


def with_training_config(mode: str) -> Callable[[dict[str, Any]], None]:
    """Metadata as ``bioscara train`` writes it (with its config), then ``env_kwargs.control_mode`` edited."""

    def change(metadata: dict[str, Any]) -> None:
        metadata["config"] = {"env_kwargs": dict(metadata["env_kwargs"])}
        metadata["env_kwargs"]["control_mode"] = mode

    return change


def truncate_model(run: Path) -> list[str]:
    zip_path = run / "model.zip"
    data = zip_path.read_bytes()
    zip_path.write_bytes(data[: len(data) // 2])
    return ["--model", str(zip_path)]


def pick_place_metadata(run: Path) -> list[str]:
    """The Reach model.zip next to the metadata of a PickPlace policy (which is self-consistent)."""
    env = gym.make(PICK_PLACE, control_mode="cartesian", backend="mock")
    write_metadata(run, build_metadata(env, PICK_PLACE, {"control_mode": "cartesian"}, algo="sac"))
    env.close()
    return ["--model", str(run / "model.zip")]


def pick_place_metadata_inside_and_beside(run: Path) -> list[str]:
    """The Reach weights, with PickPlace metadata both beside and inside the zip: only the shapes tell."""
    pick_place_metadata(run)
    embed(run, json.loads((run / "metadata.json").read_text()))
    return ["--model", str(run / "model.zip")]


def embed(run: Path, metadata: dict[str, Any] | None) -> None:
    """Replace the copy of the metadata inside ``run/model.zip`` (``None``: remove it)."""
    path = run / "model.zip"
    with zipfile.ZipFile(path) as old:
        members = {n: old.read(n) for n in old.namelist() if n != EMBEDDED_NAME}
    with zipfile.ZipFile(path, "w") as new:
        for name, data in members.items():
            new.writestr(name, data)
        if metadata is not None:
            new.writestr(EMBEDDED_NAME, json.dumps(metadata))


def mode_and_rate_edited_in_both_places(run: Path) -> list[str]:
    """Seen: control_mode (and control_freq) changed in env_kwargs and config.env_kwargs by hand."""
    metadata = json.loads((run / "metadata.json").read_text())
    metadata["config"] = {"env_kwargs": dict(metadata["env_kwargs"])}
    for kwargs in (metadata["env_kwargs"], metadata["config"]["env_kwargs"]):
        kwargs.update(control_mode="velocity", control_freq=25.0)
    (run / "metadata.json").write_text(json.dumps(metadata))
    return ["--model", str(run / "model.zip")]


def saved_without_its_copy(run: Path) -> list[str]:
    """A model.zip saved before the metadata travelled inside it."""
    embed(run, None)
    return ["--model", str(run / "model.zip")]


def model(run: Path) -> list[str]:
    return ["--model", str(run / "model.zip")]


def expert(run: Path) -> list[str]:
    return ["--expert", "--env", REACH]


def onnx_props(change: Callable[[dict[str, str]], None]) -> Callable[[Path], list[str]]:
    """A row's setup: the exported ONNX file with its metadata_props changed."""

    def setup(run: Path) -> list[str]:
        import onnx

        proto = onnx.load(str(run / "policy.onnx"))
        props = {p.key: p.value for p in proto.metadata_props}
        change(props)
        del proto.metadata_props[:]
        for key, value in props.items():
            proto.metadata_props.add(key=key, value=value)
        onnx.save(proto, str(run / "edited.onnx"))
        return ["--onnx", str(run / "edited.onnx")]

    return setup


def obs_keys_of_pick_place(props: dict[str, str]) -> None:
    """Claim the PickPlace observation layout in a graph that takes Reach's."""
    keys = [[k, 22 if k == "observation" else n] for k, n in json.loads(props["obs_keys"])]
    props["obs_keys"] = json.dumps(keys)


def unsealed(run: Path) -> list[str]:
    """The exported ONNX file without the graph's seal of its metadata, as exported before it had one."""
    import onnx

    proto = onnx.load(str(run / "policy.onnx"))
    proto.graph.doc_string = ""
    onnx.save(proto, str(run / "unsealed.onnx"))
    return ["--onnx", str(run / "unsealed.onnx")]


def control_freq_50(props: dict[str, str]) -> None:
    """Claim a 50 Hz training rate in the metadata of a policy trained at 25 Hz."""
    metadata = json.loads(props["bioscara_metadata"])
    assert metadata["env_kwargs"]["control_freq"] == 25
    metadata["env_kwargs"]["control_freq"] = 50
    props["bioscara_metadata"] = json.dumps(metadata, sort_keys=True)


def metadata_of_pick_place(props: dict[str, str]) -> None:
    """Embed PickPlace metadata in the Reach graph (its obs_keys stay Reach's)."""
    env = gym.make(PICK_PLACE, control_mode="cartesian", backend="mock")
    props["bioscara_metadata"] = json.dumps(
        build_metadata(env, PICK_PLACE, {"control_mode": "cartesian"}, algo="sac")
    )
    env.close()


# ------------------------------------------------------------------- table
ROWS: list[tuple[str, Callable[[Path], list[str]], list[str], str]] = [
    # (id, setup -> policy arguments, extra arguments, expected part of the one line)
    ("truncated-model-zip", truncate_model, [], "truncated, not a stable-baselines3 zip, or another"),
    ("metadata-other-algo", edit_metadata(setting("td3", "algo")), [], "as the TD3 model metadata.json says"),
    ("metadata-a-list", edit_metadata(lambda m: [m]), [], "expected a JSON object, got a list"),
    ("metadata-not-json", edit_metadata(lambda m: "{"), [], "expected a JSON object, got a string"),
    ("metadata-unknown-algo", edit_metadata(setting("a2c", "algo")), [], "has algo 'a2c'; expected one of"),
    ("metadata-no-algo", edit_metadata(without("algo")), [], "does not say which algorithm"),
    (
        "metadata-unknown-kwarg",
        edit_metadata(setting(3, "env_kwargs", "arm_speed"), inside=True),
        [],
        "env_kwargs has 'arm_speed', which Bioscara-Reach-v0 does not take",
    ),
    (
        "metadata-control-freq-text",
        edit_metadata(setting("fast", "env_kwargs", "control_freq")),
        [],
        "env_kwargs.control_freq must be a rate in Hz > 0, got 'fast'",
    ),
    (
        "metadata-control-mode-a-number",
        edit_metadata(setting(2, "env_kwargs", "control_mode")),
        [],
        "env_kwargs.control_mode must be a string, got the number 2",
    ),
    (
        "metadata-bad-control-mode",
        edit_metadata(setting("torque", "env_kwargs", "control_mode"), inside=True),
        [],
        "control_mode 'torque' must be one of",
    ),
    ("metadata-no-env-kwargs", edit_metadata(without("env_kwargs")), [], "'env_kwargs' is missing"),
    (
        "metadata-mode-edited-against-its-config",
        edit_metadata(with_training_config("velocity")),
        [],
        "env_kwargs.control_mode is 'velocity' but config.env_kwargs.control_mode, what training used, "
        "is 'cartesian'",
    ),
    (
        "metadata-no-control-mode",
        edit_metadata(without("env_kwargs", "control_mode")),
        [],
        "env_kwargs.control_mode is missing",
    ),
    ("metadata-no-env-id", edit_metadata(without("env_id")), [], "'env_id' is missing"),
    ("metadata-unknown-env", edit_metadata(setting("Bioscara-Juggle-v0", "env_id")), [], "Bioscara-Juggle"),
    (
        "reach-model-pick-place-metadata",
        pick_place_metadata,
        [],
        "metadata.json says env_id is 'Bioscara-PickPlace-v1', but",
    ),
    (
        "reach-model-pick-place-metadata-inside-too",
        pick_place_metadata_inside_and_beside,
        [],
        "takes 12 values of observation 'observation', the env gives 22",
    ),
    (
        "metadata-mode-and-rate-edited-in-both-places",
        mode_and_rate_edited_in_both_places,
        [],
        "metadata.json says env_kwargs.control_mode is 'velocity', but",
    ),
    ("model-without-its-own-copy", saved_without_its_copy, [], "carries no copy of its training metadata"),
    (
        "model-nan-actor-weights",
        nan_actor_weights,
        [],
        "policy weight actor.mu.weight holds 128 non-finite value(s) (NaN or inf)",
    ),
    (
        "onnx-graph-disagrees-with-its-obs-keys",
        onnx_props(obs_keys_of_pick_place),
        [],
        "the graph's input 'obs' takes 18 values, but its obs_keys add up to 28",
    ),
    (  # a hostile test's: an edited control_freq ran a 25 Hz policy at 50 Hz
        "onnx-metadata-edited-after-export",
        onnx_props(control_freq_50),
        [],
        "its bioscara_metadata was changed after export (the graph's seal of it differs); export it again "
        "from its model.zip",
    ),
    (
        "onnx-without-a-seal",
        unsealed,
        [],
        "has no seal of its metadata (exported by an older bioscara-gym); export it again from its model.zip",
    ),
    (
        "onnx-metadata-swapped-for-another-tasks",
        onnx_props(metadata_of_pick_place),
        [],
        "its bioscara_metadata was changed after export (the graph's seal of it differs)",
    ),
    ("rate-inf", model, ["--rate", "inf"], "--rate inf Hz must be within 20-100 Hz"),
    ("rate-1e9", model, ["--rate", "1e9"], "--rate 1e+09 Hz must be within 20-100 Hz"),
    ("rate-nan", expert, ["--rate", "nan"], "--rate nan Hz must be within 20-100 Hz"),
    ("rate-other-than-trained", model, ["--rate", "30"], "control_freq=25.0, the env has control_freq=30.0"),
    ("seed-negative", model, ["--seed", "-1"], "--seed must be >= 0, got -1"),
    ("episodes-zero", expert, ["--episodes", "0"], "--episodes must be >= 1, got 0"),
    ("fault-unknown", expert, ["--faults", "lag_ms=2"], "unknown fault 'lag_ms'; expected nack"),
    ("fault-not-a-number", expert, ["--faults", "nack=lots"], "fault 'nack': 'lots' is not a number"),
    ("expert-without-env", lambda run: ["--expert"], [], "--expert needs --env ID"),
    ("fault-negative-jitter", expert, ["--faults", "jitter_ms=-1"], "fault 'jitter_ms': -1 must be >= 0"),
    ("fault-drift-huge", expert, ["--faults", "drift_ppm=1e7"], "drift_ppm=1e+07 must be within ±10000"),
    (
        "state-file-is-the-log",
        lambda run: [*expert(run), "--state-file", str(run.parent / "deploy.jsonl")],
        [],
        "--log and --state-file name the same file",
    ),
    (
        "record-is-the-log",
        lambda run: [*expert(run), "--record", str(run.parent / "deploy.jsonl")],
        [],
        "--log and --record name the same file",
    ),
    ("state-file-a-device", expert, ["--state-file", "/dev/full"], "--state-file /dev/full is not a regular"),
    ("state-file-a-directory", lambda run: [*expert(run), "--state-file", str(run)], [], "is not a regular"),
    (
        "log-under-a-file",
        lambda run: [*expert(run), "--log", str(run / "model.zip" / "x.jsonl")],
        [],
        "model.zip is not a directory",
    ),
    ("other-task", model, ["--env", PICK_PLACE], "policy was trained on Bioscara-Reach-v0"),
    # Seen (a hostile test): an output naming an input overwrote it (exit 0).
    (
        "log-is-the-model",
        lambda run: [*model(run), "--log", str(run / "model.zip")],
        [],
        "model.zip is the --model file; writing it would destroy it",
    ),
    (
        "state-file-is-the-metadata",
        lambda run: [*model(run), "--state-file", str(run / "metadata.json")],
        [],
        "metadata.json is the policy's metadata.json file; writing it would destroy it",
    ),
]


@pytest.mark.parametrize(("setup", "extra", "expected"), [r[1:] for r in ROWS], ids=[r[0] for r in ROWS])
def test_bad_input_is_one_line_and_nothing_reaches_the_arm(
    setup: Callable[[Path], list[str]],
    extra: list[str],
    expected: str,
    sac_dir: Path,
    onnx_path: Path,
    tmp_path: Path,
    bus_traffic: list[tuple[int, bytes]],
    capsys: pytest.CaptureFixture[str],
) -> None:
    run = tmp_path / "policy"
    shutil.copytree(sac_dir, run)
    log = tmp_path / "deploy.jsonl"
    argv = ["deploy", "--backend", "emulated", "--log", str(log)]  # a row's own options come last and win
    argv += ["--state-file", str(tmp_path / "gripper.json"), *setup(run), *extra]

    code = main(argv)

    err = capsys.readouterr().err
    assert code == 2, err
    assert err.count("\n") == 1 and err.startswith("bioscara deploy: error: "), err
    assert expected in err
    assert "Traceback" not in err
    assert bus_traffic == []
    assert not log.exists()


def test_a_run_log_that_cannot_be_opened_is_refused_before_the_arm_is_touched(
    tmp_path: Path, bus_traffic: list[tuple[int, bytes]], capsys: pytest.CaptureFixture[str]
) -> None:
    locked = tmp_path / "locked"
    locked.mkdir()
    log = locked / "run.jsonl"

    def refuse(*args: Any, **kwargs: Any) -> None:
        raise PermissionError(13, "Permission denied", str(log))

    with pytest.MonkeyPatch.context() as mp:
        mp.setattr("bioscara_gym.training.deploy.RunLog", refuse)
        code = main(["deploy", "--expert", "--env", REACH, "--log", str(log)])
    err = capsys.readouterr().err
    assert code == 2
    assert err.count("\n") == 1 and f"cannot open the run log {log}: Permission denied" in err
    assert bus_traffic == []


@pytest.mark.parametrize(
    ("setup", "expected"),
    [
        (pick_place_metadata_inside_and_beside, "takes 12 values of observation 'observation'"),
        (pick_place_metadata, "metadata.json says env_id is 'Bioscara-PickPlace-v1', but"),
        (mode_and_rate_edited_in_both_places, "says env_kwargs.control_mode is 'velocity', but"),
        (nan_actor_weights, "policy weight actor.mu.weight holds 128 non-finite value(s)"),
        (truncate_model, "truncated, not a stable-baselines3 zip, or another"),
        (edit_metadata(without("env_kwargs", "control_freq")), "env_kwargs.control_freq is missing"),
    ],
    ids=[
        "reach-model-pick-place-metadata-inside-too",
        "reach-model-pick-place-metadata",
        "mode-edited-in-both-places",
        "nan-actor-weights",
        "truncated-model-zip",
        "metadata-no-control-freq",
    ],
)
def test_eval_refuses_the_same_policy_files_in_one_line(
    setup: Callable[[Path], list[str]],
    expected: str,
    sac_dir: Path,
    tmp_path: Path,
    capsys: pytest.CaptureFixture[str],
) -> None:
    run = tmp_path / "policy"
    shutil.copytree(sac_dir, run)
    code = main(["eval", *setup(run), "--episodes", "1", "--backend", "mock"])
    err = capsys.readouterr().err
    assert code == 2, err
    assert err.count("\n") == 1 and err.startswith("bioscara eval: error: ") and expected in err, err


@pytest.mark.parametrize(
    ("argv", "expected"),
    [
        (["--seed", "-1"], "--seed must be >= 0, got -1"),
        (["--video-episodes", "0", "--video", "v.mp4"], "--video-episodes must be >= 1, got 0"),
        (["--episodes", "0"], "episodes must be >= 1, got 0"),
        # Seen (a hostile test): --model was ignored; a directory failed after every episode ran.
        (["--model", "model.zip"], "--expert and --model both name a policy; give one"),
        (["--json", "."], "--json .: is a folder; give a file name"),
        (["--json", f"{__file__}/x.json"], f"{__file__} is a file, not a folder"),
    ],
    ids=[
        "seed-negative",
        "video-episodes-zero",
        "episodes-zero",
        "model-and-expert",
        "json-a-directory",
        "json-under-a-file",
    ],
)
def test_eval_refuses_bad_arguments_in_one_line(
    argv: list[str], expected: str, capsys: pytest.CaptureFixture[str]
) -> None:
    code = main(["eval", "--expert", "--env", "Bioscara-Reach", "--backend", "mock", *argv])
    err = capsys.readouterr().err
    assert code == 2, err
    assert err.count("\n") == 1 and expected in err, err
