"""The metadata file written next to every trained policy, and its checks.

``deploy`` and ``eval`` refuse a policy whose metadata does not match the env
it would drive (another task, other observation or action spaces, another
control mode or rate), before anything touches the arm.

A copy of the metadata travels inside the model file too
(:data:`EMBEDDED_NAME` in ``model.zip``, which stable-baselines3 ignores;
the ONNX export keeps it in its metadata props): a ``metadata.json`` edited
by hand, or one swapped in from another run, disagrees with the model's own
copy and is refused (:func:`check_embedded_metadata`).
"""

from __future__ import annotations

import inspect
import io
import json
import math
import numbers
import time
import zipfile
from collections.abc import Mapping
from dataclasses import dataclass
from pathlib import Path
from typing import Any

import gymnasium as gym
import numpy as np
from gymnasium.envs import registration
from gymnasium.envs.registration import load_env_creator

import bioscara_gym
from bioscara_gym.errors import MetadataError, TrainingError
from bioscara_gym.fsutil import atomic_write_bytes, atomic_write_text, read_json

METADATA_NAME = "metadata.json"
#: The metadata's copy inside ``model.zip`` (stable-baselines3 reads only its own members).
EMBEDDED_NAME = "bioscara_metadata.json"
#: What a policy was trained for: the keys its two copies must agree on.
TRAINED_FOR_KEYS = ("env_id", "env_kwargs", "observation_space", "action_space", "algo")
#: Largest metadata file read, bytes (ours are a few kB).
MAX_METADATA_BYTES = 1024 * 1024
#: env kwargs that change what the policy's actions mean; they must match to deploy,
#: and metadata that does not state them is refused (a guessed control mode turns
#: a cartesian policy's actions into joint velocities).
BEHAVIOUR_KWARGS = ("control_mode", "control_freq")
#: The keys every metadata file must have, with their JSON types.
REQUIRED_KEYS: Mapping[str, type] = {
    "env_id": str,
    "env_kwargs": dict,
    "observation_space": dict,
    "action_space": dict,
}
#: How JSON names Python's types, for messages.
_JSON_NAMES: Mapping[type, str] = {
    dict: "an object",
    list: "a list",
    str: "a string",
    bool: "a boolean",
    type(None): "null",
}


def space_description(space: gym.Space) -> Any:
    """A JSON-friendly, comparable description of a Gymnasium space."""
    if isinstance(space, gym.spaces.Dict):
        return {k: space_description(s) for k, s in space.spaces.items()}
    if isinstance(space, gym.spaces.Box):
        return {
            "type": "Box",
            "shape": list(space.shape),
            "dtype": str(space.dtype),
            "low": float(space.low.min()),
            "high": float(space.high.max()),
        }
    return {"type": type(space).__name__, "repr": repr(space)}


def build_metadata(env: gym.Env, env_id: str, env_kwargs: dict[str, Any], **extra: Any) -> dict[str, Any]:
    """Describe the env a policy was trained on (plus ``extra`` facts)."""
    unwrapped = env.unwrapped
    kwargs = dict(env_kwargs)
    for key in BEHAVIOUR_KWARGS:
        kwargs.setdefault(key, getattr(unwrapped, key, None))
    return {
        "env_id": env_id,
        "env_kwargs": kwargs,
        "observation_space": space_description(env.observation_space),
        "action_space": space_description(env.action_space),
        "package_version": bioscara_gym.__version__,
        "created": time.strftime("%Y-%m-%dT%H:%M:%S%z"),
        **extra,
    }


def write_metadata(directory: Path, metadata: dict[str, Any]) -> Path:
    """Write ``metadata.json`` into ``directory`` atomically."""
    path = directory / METADATA_NAME
    atomic_write_text(path, _metadata_json(metadata))
    return path


def _metadata_json(metadata: dict[str, Any]) -> str:
    return json.dumps(metadata, indent=2, sort_keys=True, default=str) + "\n"


def save_policy(model: Any, directory: Path, metadata: dict[str, Any]) -> tuple[Path, Path]:
    """Write ``model.zip`` with a copy of ``metadata`` inside, then ``metadata.json``; each atomically.

    Args:
        model: Anything with stable-baselines3's ``save(file)``.
        directory: Where both go (created if missing).
        metadata: What :func:`build_metadata` returns.

    Returns:
        The model's path and the metadata's.
    """
    directory.mkdir(parents=True, exist_ok=True)
    buffer = io.BytesIO()
    model.save(buffer)
    with zipfile.ZipFile(buffer, "a") as archive:
        archive.writestr(EMBEDDED_NAME, _metadata_json(metadata))
    model_path = directory / "model.zip"
    atomic_write_bytes(model_path, buffer.getvalue())
    return model_path, write_metadata(directory, metadata)


def read_embedded_metadata(model_file: Path) -> dict[str, Any] | None:
    """The metadata saved inside ``model_file``, or ``None`` if it has none (saved by an older version).

    Raises:
        MetadataError: The copy is there but is not a JSON object.
    """
    try:
        with zipfile.ZipFile(model_file) as archive:
            if EMBEDDED_NAME not in archive.namelist():
                return None
            with archive.open(EMBEDDED_NAME) as member:  # read at most the limit: the size stated may lie
                data = member.read(MAX_METADATA_BYTES + 1)
        too_large = len(data) > MAX_METADATA_BYTES
        embedded = None if too_large else json.loads(data.decode("utf-8"))
    except (OSError, zipfile.BadZipFile, UnicodeDecodeError, ValueError) as e:
        raise MetadataError(f"{model_file}: its copy of the training metadata cannot be read ({e})") from e
    if too_large:
        raise MetadataError(
            f"{model_file}: its copy of the training metadata is over {MAX_METADATA_BYTES} bytes "
            "(ours are a few kB); not read"
        )
    if not isinstance(embedded, dict):
        raise MetadataError(f"{model_file}: its copy of the training metadata is not a JSON object")
    return embedded


def _difference(key: str, inside: Any, beside: Any) -> tuple[str, Any, Any]:
    """The first place where two metadata values differ: dotted key and both values."""
    if isinstance(inside, dict) and isinstance(beside, dict):
        for sub in sorted(set(inside) | set(beside)):
            if inside.get(sub) != beside.get(sub):
                return _difference(f"{key}.{sub}", inside.get(sub), beside.get(sub))
    return key, inside, beside


def check_embedded_metadata(
    sidecar: dict[str, Any],
    model_file: Path,
    required: bool = False,
    keys: tuple[str, ...] | None = TRAINED_FOR_KEYS,
) -> dict[str, Any] | None:
    """Refuse a ``metadata.json`` that disagrees with the copy saved inside the model.

    Args:
        sidecar: The ``metadata.json`` beside ``model_file``, read.
        model_file: The ``model.zip``.
        required: Refuse a model with no copy inside too (``deploy``: what the
            policy was trained for must be proven, not read from an editable file).
        keys: The settings compared; ``None``: every one (``export`` copies
            the whole metadata into the ONNX file, the success rate included).

    Returns:
        The embedded copy (``None`` if there is none and it is not required).

    Raises:
        MetadataError: One line naming the first setting that differs, or the missing copy.
    """
    embedded = read_embedded_metadata(model_file)
    if embedded is None:
        if required:
            raise MetadataError(
                f"{model_file} carries no copy of its training metadata (saved by an older bioscara-gym), "
                f"so {METADATA_NAME} beside it cannot be checked; retrain it to deploy it"
            )
        return None
    for key in sorted(set(embedded) | set(sidecar)) if keys is None else keys:
        if embedded.get(key) != sidecar.get(key):
            where, inside, beside = _difference(key, embedded.get(key), sidecar.get(key))
            raise MetadataError(
                f"{model_file.parent / METADATA_NAME} says {where} is {beside!r}, but {model_file} was "
                f"trained with {inside!r} (its own copy of the metadata); was {METADATA_NAME} edited or "
                "swapped? Refused"
            )
    return embedded


def validate_metadata(metadata: Any, source: str) -> dict[str, Any]:
    """Refuse metadata that lacks a setting or has one of the wrong type; nothing is defaulted.

    Args:
        metadata: The parsed JSON.
        source: Where it came from, for the message (a path).

    Returns:
        ``metadata``, checked.

    Raises:
        MetadataError: One line naming ``source`` and the key.
    """
    if not isinstance(metadata, dict):
        raise MetadataError(f"{source}: expected a JSON object, got {_json_type(metadata)}")
    for key, kind in REQUIRED_KEYS.items():
        if key not in metadata:
            raise MetadataError(f"{source}: '{key}' is missing; re-export or retrain the policy")
        if not isinstance(metadata[key], kind):
            raise MetadataError(
                f"{source}: '{key}' must be {_JSON_NAMES[kind]}, got {_json_type(metadata[key])}"
            )
    kwargs = metadata["env_kwargs"]
    for key in BEHAVIOUR_KWARGS:
        if key not in kwargs:
            raise MetadataError(
                f"{source}: env_kwargs.{key} is missing: the setting the policy was trained with "
                "must be stated, it is never guessed"
            )
    if not isinstance(kwargs["control_mode"], str):
        raise MetadataError(
            f"{source}: env_kwargs.control_mode must be a string, got {_json_type(kwargs['control_mode'])}"
        )
    freq = kwargs["control_freq"]
    if isinstance(freq, bool) or not isinstance(freq, numbers.Real) or not math.isfinite(freq) or freq <= 0:
        raise MetadataError(f"{source}: env_kwargs.control_freq must be a rate in Hz > 0, got {freq!r}")
    # Training writes the hyperparameters it used too: a hand edit of one copy shows.
    config = metadata.get("config")
    trained = config.get("env_kwargs") if isinstance(config, dict) else None
    for key in BEHAVIOUR_KWARGS:
        if isinstance(trained, dict) and key in trained and trained[key] != kwargs[key]:
            raise MetadataError(
                f"{source}: env_kwargs.{key} is {kwargs[key]!r} but config.env_kwargs.{key}, what "
                f"training used, is {trained[key]!r}; was the file edited by hand?"
            )
    return metadata


def _json_type(value: Any) -> str:
    """How JSON would name the type of ``value``, with the value when it is short."""
    if isinstance(value, numbers.Real) and not isinstance(value, bool):
        return f"the number {value!r}"
    name = _JSON_NAMES.get(type(value), type(value).__name__)
    return f"{name} {value!r}" if isinstance(value, str) and len(value) <= 20 else name


def policy_files(model_path: Path) -> dict[str, Path]:
    """The files a policy is read from: ``--model`` (``model.zip``, or its folder) and ``metadata``.

    Keyed by what names them, for :func:`~bioscara_gym.fsutil.output_clash`.
    """
    model_path = Path(model_path)
    directory = model_path if model_path.is_dir() else model_path.parent
    model_file = directory / "model.zip" if model_path.is_dir() else model_path
    return {"--model": model_file, "policy's metadata.json": directory / METADATA_NAME}


def read_metadata(model_path: Path) -> dict[str, Any]:
    """Read and validate the metadata next to ``model_path`` (a ``model.zip`` or its directory).

    Raises:
        MetadataError: Missing, unreadable or incomplete file (:func:`validate_metadata`).
    """
    model_path = Path(model_path)
    directory = model_path if model_path.is_dir() else model_path.parent
    path = directory / METADATA_NAME
    try:
        metadata = read_json(path, max_bytes=MAX_METADATA_BYTES)
    except FileNotFoundError as e:
        raise MetadataError(
            f"no {METADATA_NAME} next to {model_path}: cannot tell what the policy was trained for"
        ) from e
    except (OSError, ValueError) as e:
        raise MetadataError(f"cannot read {path}: {e}") from e
    return validate_metadata(metadata, str(path))


def check_metadata(metadata: dict[str, Any], env: gym.Env, env_id: str) -> None:
    """Refuse a policy trained for something else than ``env``.

    Raises:
        MetadataError: Different task, spaces, control mode or control rate;
            the message names what differs.
    """
    trained = metadata.get("env_id")
    if trained != env_id:
        raise MetadataError(f"policy was trained on {trained}, not {env_id}")
    unwrapped = env.unwrapped
    for key in BEHAVIOUR_KWARGS:
        want = metadata.get("env_kwargs", {}).get(key)
        have = getattr(unwrapped, key, None)
        if want is not None and have is not None and want != have:
            raise MetadataError(f"policy was trained with {key}={want!r}, the env has {key}={have!r}")
    for name, space in (("observation_space", env.observation_space), ("action_space", env.action_space)):
        if metadata.get(name) != space_description(space):
            raise MetadataError(
                f"{name} differs: policy {metadata.get(name)} vs env {space_description(space)}"
            )


@dataclass(frozen=True)
class PolicyShapes:
    """What a policy itself takes and gives, read from the policy, not its metadata.

    Attributes:
        observation: Observation key to its number of values, in the policy's order.
        action: Number of action values.
        source: What the shapes were read from, for messages.
    """

    observation: dict[str, int]
    action: int
    source: str

    @classmethod
    def of_spaces(cls, observation_space: gym.Space, action_space: gym.Space, source: str) -> PolicyShapes:
        """The shapes of a policy that carries Gymnasium spaces (a stable-baselines3 model)."""
        if isinstance(observation_space, gym.spaces.Dict):
            obs = {k: _size(s) for k, s in observation_space.spaces.items()}
        else:
            obs = {"": _size(observation_space)}
        return cls(obs, _size(action_space), source)


def _size(space: gym.Space) -> int:
    return int(np.prod(space.shape)) if space.shape is not None else -1


def check_policy_shapes(shapes: PolicyShapes, env: gym.Env) -> None:
    """Refuse a policy whose own inputs or outputs do not fit ``env``.

    The metadata says what the policy was trained for; this checks the policy
    itself, so a model file next to another policy's metadata is refused
    before the arm is touched.

    Raises:
        MetadataError: The first difference: a missing or extra observation
            key, a size, or the action size; named with ``shapes.source``.
    """
    expected = PolicyShapes.of_spaces(env.observation_space, env.action_space, "env")
    for key, size in expected.observation.items():
        if key not in shapes.observation:
            raise MetadataError(f"{shapes.source} takes no observation '{key}', which the env gives")
        if shapes.observation[key] != size:
            raise MetadataError(
                f"{shapes.source} takes {shapes.observation[key]} values of observation '{key}', "
                f"the env gives {size}"
            )
    extra = [k for k in shapes.observation if k not in expected.observation]
    if extra:
        raise MetadataError(f"{shapes.source} takes observation '{extra[0]}', which the env does not give")
    if shapes.action != expected.action:
        raise MetadataError(
            f"{shapes.source} gives {shapes.action} action values, the env takes {expected.action}"
        )


def resolve_env_id(env: str) -> str:
    """The registered, versioned id for ``env`` (``Bioscara-Reach`` -> ``Bioscara-Reach-v0``).

    Raises:
        TrainingError: Unknown env id, with the registered Bioscara ids.
    """
    from gymnasium.envs.registration import find_highest_version, get_env_id, parse_env_id

    if env in gym.registry:
        return env
    try:
        ns, name, version = parse_env_id(env)
    except gym.error.Error:
        ns, name, version = None, env, None
    latest = find_highest_version(ns, name) if version is None else None
    if latest is not None:
        return get_env_id(ns, name, latest)
    known = ", ".join(sorted(k for k in gym.registry if k.startswith("Bioscara")))
    raise TrainingError(f"unknown env {env!r}; registered: {known}")


#: Keywords ``gym.make`` takes itself (``max_episode_steps``, ...), not the env's constructor. Read
#: off registration's ``make``, not ``gym.make``: a ``gym.make`` replaced when this module is first
#: imported (a test's stand-in taking ``**kwargs``) left it empty for the whole process.
GYM_MAKE_KEYWORDS = frozenset(
    p for p in inspect.signature(registration.make).parameters if p not in ("id", "kwargs")
)


def env_kwargs_problem(env_id: str, kwargs: Mapping[str, Any]) -> str | None:
    """What is wrong with ``kwargs`` for ``gym.make(env_id, **kwargs)``, or ``None``.

    A keyword the env's constructor does not take, named with those it
    does: ``has 'bogus', which Bioscara-Reach-v0 does not take; it takes ...``.
    Checked before an env is made from a file's kwargs (a config's, a
    policy's metadata), so the file is named instead of a traceback.

    Raises:
        gymnasium.error.Error: ``env_id`` is not registered.
    """
    spec = gym.spec(env_id)
    creator = load_env_creator(spec.entry_point) if isinstance(spec.entry_point, str) else spec.entry_point
    known = keyword_parameters(creator)
    unknown = [k for k in kwargs if k not in known and k not in GYM_MAKE_KEYWORDS]
    render_modes = getattr(creator, "metadata", {}).get("render_modes", [])
    render_mode = kwargs.get("render_mode")
    if render_mode is not None and (not isinstance(render_mode, str) or render_mode not in render_modes):
        renders = f"renders {', '.join(render_modes)} or null" if render_modes else "renders nothing (null)"
        return f"has render_mode {render_mode!r}; {env_id} {renders}"
    if not unknown:
        return None
    settings = ", ".join(n for n in known if n not in ("backend", "backend_options", "config"))
    return f"has {unknown[0]!r}, which {env_id} does not take; it takes {settings}"


def keyword_parameters(creator: Any) -> list[str]:
    """The keyword parameters an env class takes, following ``**kwargs`` up its bases."""
    classes = creator.__mro__ if isinstance(creator, type) else (creator,)
    names: list[str] = []
    for cls in classes:
        target = cls.__init__ if isinstance(creator, type) else cls
        if isinstance(creator, type) and "__init__" not in vars(cls):
            continue
        params = inspect.signature(target).parameters.values()
        names += [p.name for p in params if p.kind in (p.POSITIONAL_OR_KEYWORD, p.KEYWORD_ONLY)]
        if not any(p.kind is p.VAR_KEYWORD for p in params):
            break
    return [n for n in dict.fromkeys(names) if n != "self"]
