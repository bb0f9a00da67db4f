"""Tests that kill mutants mutmut found surviving in ``training/metadata.py`` (docs/mutation.md).

No training: Gymnasium spaces and a stand-in env built here, a stand-in
model whose ``save`` writes a small zip, metadata files written here.
Expected values are literals from the module's documented contract (what
``metadata.json`` holds, what each check refuses and how its one line reads).
"""

from __future__ import annotations

import json
import re
import zipfile
from pathlib import Path
from types import SimpleNamespace
from typing import IO, Any

import gymnasium as gym
import numpy as np
import pytest

from bioscara_gym.errors import MetadataError, TrainingError
from bioscara_gym.training.metadata import (
    PolicyShapes,
    build_metadata,
    check_embedded_metadata,
    check_metadata,
    check_policy_shapes,
    read_embedded_metadata,
    read_metadata,
    resolve_env_id,
    save_policy,
    space_description,
    validate_metadata,
    write_metadata,
)

BOX = gym.spaces.Box(low=np.array([-1.0, -2.0], np.float32), high=np.array([3.0, 0.5], np.float32))
DICT = gym.spaces.Dict(
    {"observation": gym.spaces.Box(-1.0, 1.0, (3,)), "goal": gym.spaces.Box(0.0, 1.0, (2,))}
)
ISO_8601 = r"\d{4}-\d{2}-\d{2}T\d{2}:\d{2}:\d{2}[+-]\d{4}"


def env_with(observation_space: gym.Space, action_space: gym.Space, **unwrapped: Any) -> Any:
    """Just enough of an env: spaces, and ``unwrapped`` with the given attributes."""
    return SimpleNamespace(
        observation_space=observation_space,
        action_space=action_space,
        unwrapped=SimpleNamespace(**unwrapped),
    )


def valid(**changes: Any) -> dict[str, Any]:
    metadata = {
        "env_id": "Bioscara-Reach-v0",
        "env_kwargs": {"control_mode": "cartesian", "control_freq": 20},
        "observation_space": {},
        "action_space": {},
    }
    metadata.update(changes)
    return metadata


class ZipModel:
    """Anything with stable-baselines3's ``save(file)``: writes a zip holding ``data``."""

    def save(self, file: IO[bytes]) -> None:
        with zipfile.ZipFile(file, "w") as archive:
            archive.writestr("data", "{}")


# --------------------------------------------------------------- describing
def test_a_box_is_described_by_type_shape_dtype_and_its_extreme_bounds() -> None:
    assert space_description(BOX) == {
        "type": "Box",
        "shape": [2],
        "dtype": "float32",
        "low": -2.0,
        "high": 3.0,
    }


def test_a_dict_space_is_described_key_by_key_and_other_spaces_by_repr() -> None:
    described = space_description(gym.spaces.Dict({"a": gym.spaces.Discrete(3), "b": BOX}))
    assert described == {"a": {"type": "Discrete", "repr": "Discrete(3)"}, "b": space_description(BOX)}


def test_build_metadata_states_the_behaviour_kwargs_and_keeps_the_given_ones() -> None:
    env = env_with(BOX, BOX, control_mode="joint_velocity", control_freq=10.0)
    given = {"control_mode": "cartesian", "reward_type": "log"}
    metadata = build_metadata(env, "Bioscara-Reach-v0", given, seed=3)
    assert metadata["env_kwargs"] == {"control_mode": "cartesian", "reward_type": "log", "control_freq": 10.0}
    assert metadata["env_id"] == "Bioscara-Reach-v0" and metadata["seed"] == 3
    assert metadata["action_space"]["type"] == "Box"
    assert re.fullmatch(ISO_8601, metadata["created"]), metadata["created"]
    assert isinstance(metadata["package_version"], str)


def test_build_metadata_states_a_behaviour_kwarg_the_env_lacks_as_none() -> None:
    metadata = build_metadata(env_with(BOX, BOX, control_mode="cartesian"), "Bioscara-Reach-v0", {})
    assert metadata["env_kwargs"] == {"control_mode": "cartesian", "control_freq": None}


def test_metadata_json_is_sorted_indented_with_a_final_newline_and_paths_as_text(tmp_path: Path) -> None:
    path = write_metadata(tmp_path, {"b": 1, "a": Path("run") / "model.zip"})
    assert path == tmp_path / "metadata.json"
    assert path.read_text(encoding="utf-8") == '{\n  "a": "run/model.zip",\n  "b": 1\n}\n'


# ------------------------------------------------------------------ saving
def test_save_policy_puts_a_copy_of_the_metadata_inside_the_model(tmp_path: Path) -> None:
    out = tmp_path / "runs" / "reach"  # created, parents too
    model_path, metadata_path = save_policy(ZipModel(), out, valid())
    assert (model_path, metadata_path) == (out / "model.zip", out / "metadata.json")
    with zipfile.ZipFile(model_path) as archive:
        assert sorted(archive.namelist()) == ["bioscara_metadata.json", "data"]
        inside = archive.read("bioscara_metadata.json").decode("utf-8")
    assert inside == metadata_path.read_text(encoding="utf-8")
    assert read_embedded_metadata(model_path) == valid()


def test_a_model_without_a_copy_inside_has_none(tmp_path: Path) -> None:
    path = tmp_path / "model.zip"
    with zipfile.ZipFile(path, "w") as archive:
        archive.writestr("data", "{}")
    assert read_embedded_metadata(path) is None
    assert check_embedded_metadata(valid(), path) is None


@pytest.mark.parametrize(
    ("inside", "message"),
    [
        ("[1, 2]", "its copy of the training metadata is not a JSON object"),
        ("{not json", "its copy of the training metadata cannot be read ("),
    ],
    ids=["list", "not-json"],
)
def test_a_broken_copy_inside_is_refused_naming_the_model(tmp_path: Path, inside: str, message: str) -> None:
    path = tmp_path / "model.zip"
    with zipfile.ZipFile(path, "w") as archive:
        archive.writestr("bioscara_metadata.json", inside)
    with pytest.raises(MetadataError) as caught:
        read_embedded_metadata(path)
    assert str(caught.value).startswith(f"{path}: {message}")


# ------------------------------------------------------- the copy inside
def test_a_missing_copy_is_refused_when_required(tmp_path: Path) -> None:
    path = tmp_path / "model.zip"
    with zipfile.ZipFile(path, "w") as archive:
        archive.writestr("data", "{}")
    with pytest.raises(MetadataError) as caught:
        check_embedded_metadata(valid(), path, required=True)
    assert str(caught.value) == (
        f"{path} carries no copy of its training metadata (saved by an older bioscara-gym), "
        "so metadata.json beside it cannot be checked; retrain it to deploy it"
    )


@pytest.mark.parametrize(
    ("beside", "where", "shown"),
    [
        ({"action_space": {"shape": [2], "high": 2.0}}, "action_space.high", "2.0"),
        ({"action_space": {"shape": [2]}}, "action_space.high", "None"),
        ({"action_space": {"shape": [2], "high": 1.0, "extra": 0}}, "action_space.extra", "0"),
        ({"action_space": [2]}, "action_space", "[2]"),
        ({"algo": "td3"}, "algo", "'td3'"),
    ],
    ids=["value", "key-missing-beside", "key-only-beside", "not-an-object-beside", "top-level"],
)
def test_the_first_setting_that_differs_from_the_copy_inside_is_named(
    tmp_path: Path, beside: dict[str, Any], where: str, shown: str
) -> None:
    inside = valid(action_space={"shape": [2], "high": 1.0}, algo="sac")
    model_path, _ = save_policy(ZipModel(), tmp_path, inside)
    sidecar = {**inside, **beside}
    with pytest.raises(MetadataError) as caught:
        check_embedded_metadata(sidecar, model_path)
    message = str(caught.value)
    assert message.startswith(f"{tmp_path / 'metadata.json'} says {where} is {shown}, but ")
    assert message.endswith("(its own copy of the metadata); was metadata.json edited or swapped? Refused")
    assert check_embedded_metadata(inside, model_path) == inside


def test_the_difference_message_names_both_files_and_both_values(tmp_path: Path) -> None:
    inside = valid(action_space={"shape": [2], "high": 1.0}, algo="sac")
    model_path, _ = save_policy(ZipModel(), tmp_path, inside)
    with pytest.raises(MetadataError) as caught:
        check_embedded_metadata({**inside, "action_space": {"shape": [2], "high": 2.0}}, model_path)
    assert str(caught.value) == (
        f"{tmp_path / 'metadata.json'} says action_space.high is 2.0, but {model_path} was trained with 1.0 "
        "(its own copy of the metadata); was metadata.json edited or swapped? Refused"
    )


def test_a_difference_inside_an_object_only_inside_is_named_by_its_key(tmp_path: Path) -> None:
    inside = valid(action_space={"shape": [2], "high": 1.0}, algo="sac")
    model_path, _ = save_policy(ZipModel(), tmp_path, inside)
    sidecar = {**inside, "action_space": "Box"}
    with pytest.raises(MetadataError, match=r"says action_space is 'Box', but .* trained with \{'high': 1.0"):
        check_embedded_metadata(sidecar, model_path)


# --------------------------------------------------------------- validating
@pytest.mark.parametrize(
    ("metadata", "message"),
    [
        ([1], "expected a JSON object, got a list"),
        ("x", "expected a JSON object, got a string 'x'"),
        (None, "expected a JSON object, got null"),
        (
            {k: v for k, v in valid().items() if k != "env_id"},
            "'env_id' is missing; re-export or retrain the policy",
        ),
        (valid(env_id=3), "'env_id' must be a string, got the number 3"),
        (valid(env_kwargs=[]), "'env_kwargs' must be an object, got a list"),
        (valid(observation_space=True), "'observation_space' must be an object, got a boolean"),
        (valid(action_space="x" * 21), "'action_space' must be an object, got a string"),
        (valid(action_space="x" * 20), f"'action_space' must be an object, got a string {'x' * 20!r}"),
        (valid(action_space=1.5), "'action_space' must be an object, got the number 1.5"),
        (
            valid(env_kwargs={"control_freq": 20}),
            "env_kwargs.control_mode is missing: the setting the policy was trained with must be stated, "
            "it is never guessed",
        ),
        (valid(env_kwargs={"control_mode": 1, "control_freq": 20}),
         "env_kwargs.control_mode must be a string, got the number 1"),
        (valid(env_kwargs={"control_mode": "cartesian", "control_freq": True}),
         "env_kwargs.control_freq must be a rate in Hz > 0, got True"),
        (valid(env_kwargs={"control_mode": "cartesian", "control_freq": 0}),
         "env_kwargs.control_freq must be a rate in Hz > 0, got 0"),
        (valid(env_kwargs={"control_mode": "cartesian", "control_freq": float("inf")}),
         "env_kwargs.control_freq must be a rate in Hz > 0, got inf"),
        (valid(env_kwargs={"control_mode": "cartesian", "control_freq": "20"}),
         "env_kwargs.control_freq must be a rate in Hz > 0, got '20'"),
        (
            valid(config={"env_kwargs": {"control_freq": 10}}),
            "env_kwargs.control_freq is 20 but config.env_kwargs.control_freq, what training used, is 10; "
            "was the file edited by hand?",
        ),
    ],
)  # fmt: skip
def test_metadata_lacking_a_setting_or_of_the_wrong_type_is_one_line(metadata: Any, message: str) -> None:
    with pytest.raises(MetadataError) as caught:
        validate_metadata(metadata, "run/metadata.json")
    assert str(caught.value) == f"run/metadata.json: {message}"


def test_a_json_type_it_has_no_name_for_is_named_by_python() -> None:
    with pytest.raises(MetadataError) as caught:
        validate_metadata(valid(env_kwargs=(1, 2)), "m")
    assert str(caught.value) == "m: 'env_kwargs' must be an object, got tuple"


def test_metadata_that_agrees_with_its_training_config_passes() -> None:
    metadata = valid(config={"env_kwargs": {"control_mode": "cartesian", "control_freq": 20}})
    assert validate_metadata(metadata, "m") is metadata
    assert validate_metadata(valid(config={"env_kwargs": {"reward_type": "log"}}), "m")
    assert validate_metadata(valid(config="sac.yaml"), "m")


def test_a_control_rate_below_1_hz_is_still_a_rate() -> None:
    metadata = valid(env_kwargs={"control_mode": "cartesian", "control_freq": 0.5})
    assert validate_metadata(metadata, "m") is metadata


def test_a_bad_metadata_file_is_named_by_its_path(tmp_path: Path) -> None:
    (tmp_path / "metadata.json").write_text(json.dumps(valid(env_id=3)), encoding="utf-8")
    with pytest.raises(MetadataError) as caught:
        read_metadata(tmp_path / "model.zip")
    assert str(caught.value) == f"{tmp_path / 'metadata.json'}: 'env_id' must be a string, got the number 3"


def test_metadata_is_read_from_the_models_directory(tmp_path: Path) -> None:
    (tmp_path / "metadata.json").write_text(json.dumps(valid()), encoding="utf-8")
    assert read_metadata(tmp_path / "model.zip") == valid()
    assert read_metadata(tmp_path) == valid()


def test_a_metadata_file_over_1_mib_is_refused(tmp_path: Path) -> None:
    path = tmp_path / "metadata.json"
    path.write_text(json.dumps({**valid(), "pad": "x" * (1024 * 1024)}), encoding="utf-8")
    with pytest.raises(MetadataError, match=r"cannot read .*larger than 1048576 bytes"):
        read_metadata(tmp_path)


def test_a_missing_metadata_file_is_one_line_naming_the_model(tmp_path: Path) -> None:
    with pytest.raises(MetadataError) as caught:
        read_metadata(tmp_path / "model.zip")
    assert str(caught.value) == (
        f"no metadata.json next to {tmp_path / 'model.zip'}: cannot tell what the policy was trained for"
    )


# ----------------------------------------------------------------- checking
def test_check_metadata_names_the_setting_that_differs() -> None:
    env = env_with(BOX, BOX, control_mode="cartesian", control_freq=10.0)
    metadata = valid(observation_space=space_description(BOX), action_space=space_description(BOX))
    with pytest.raises(MetadataError) as caught:
        check_metadata(metadata, env, "Bioscara-Reach-v0")
    assert str(caught.value) == "policy was trained with control_freq=20, the env has control_freq=10.0"


def test_check_metadata_skips_a_setting_the_env_does_not_have() -> None:
    env = env_with(BOX, BOX, control_mode="cartesian")  # no control_freq
    metadata = valid(observation_space=space_description(BOX), action_space=space_description(BOX))
    check_metadata(metadata, env, "Bioscara-Reach-v0")


def test_check_metadata_of_metadata_without_env_kwargs_checks_the_spaces_only() -> None:
    env = env_with(BOX, BOX, control_mode="cartesian", control_freq=10.0)
    metadata = valid(observation_space=space_description(BOX), action_space=space_description(BOX))
    del metadata["env_kwargs"]
    check_metadata(metadata, env, "Bioscara-Reach-v0")


def test_check_metadata_names_both_spaces_when_they_differ() -> None:
    env = env_with(BOX, DICT, control_mode="cartesian", control_freq=20)
    metadata = valid(observation_space=space_description(BOX), action_space=space_description(BOX))
    with pytest.raises(MetadataError) as caught:
        check_metadata(metadata, env, "Bioscara-Reach-v0")
    assert str(caught.value) == (
        f"action_space differs: policy {space_description(BOX)} vs env {space_description(DICT)}"
    )


# ------------------------------------------------------------ policy shapes
def test_the_shapes_of_a_dict_space_are_per_key_and_of_a_box_under_no_key() -> None:
    shapes = PolicyShapes.of_spaces(DICT, BOX, "model.zip")
    assert shapes == PolicyShapes({"observation": 3, "goal": 2}, 2, "model.zip")
    assert PolicyShapes.of_spaces(BOX, gym.spaces.Box(-1, 1, (2, 3)), "m").observation == {"": 2}
    assert PolicyShapes.of_spaces(BOX, gym.spaces.Box(-1, 1, (2, 3)), "m").action == 6
    assert PolicyShapes.of_spaces(BOX, gym.spaces.Sequence(BOX), "m").action == -1  # no fixed shape


@pytest.mark.parametrize(
    ("observation", "action", "message"),
    [
        ({"observation": 3}, 2, "policy.onnx takes no observation 'goal', which the env gives"),
        ({"observation": 3, "goal": 4}, 2,
         "policy.onnx takes 4 values of observation 'goal', the env gives 2"),
        ({"observation": 3, "goal": 2, "x": 1, "y": 1}, 2,
         "policy.onnx takes observation 'x', which the env does not give"),
        ({"observation": 3, "goal": 2}, 4, "policy.onnx gives 4 action values, the env takes 2"),
    ],
    ids=["missing", "size", "extra", "action"],
)  # fmt: skip
def test_a_policy_whose_inputs_or_outputs_do_not_fit_is_refused_naming_it(
    observation: dict[str, int], action: int, message: str
) -> None:
    with pytest.raises(MetadataError) as caught:
        check_policy_shapes(PolicyShapes(observation, action, "policy.onnx"), env_with(DICT, BOX))
    assert str(caught.value) == message


def test_a_policy_that_fits_passes() -> None:
    check_policy_shapes(PolicyShapes({"observation": 3, "goal": 2}, 2, "policy.onnx"), env_with(DICT, BOX))
    check_policy_shapes(PolicyShapes({"": 2}, 2, "policy.onnx"), env_with(BOX, BOX))


# -------------------------------------------------------------- env ids
TASK_IDS = "Bioscara-Insert-v0, Bioscara-PickPlace-v1, Bioscara-Push-v0, Bioscara-Reach-v0, Bioscara-Stack-v0"


def test_an_id_that_is_no_env_id_is_refused_naming_the_registered_ones() -> None:
    with pytest.raises(TrainingError) as caught:
        resolve_env_id("not an id!")
    assert str(caught.value).startswith("unknown env 'not an id!'; registered: ")
    assert TASK_IDS in str(caught.value)


def test_a_namespaced_id_without_a_version_resolves_to_its_latest_version() -> None:
    gym.register(id="ProbeNs/Probe-v0", entry_point="gymnasium.envs.classic_control:CartPoleEnv")
    gym.register(id="ProbeNs/Probe-v1", entry_point="gymnasium.envs.classic_control:CartPoleEnv")
    try:
        assert resolve_env_id("ProbeNs/Probe") == "ProbeNs/Probe-v1"
    finally:
        del gym.registry["ProbeNs/Probe-v0"], gym.registry["ProbeNs/Probe-v1"]
