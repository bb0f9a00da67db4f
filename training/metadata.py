"""The metadata file written next to every trained policy, and its checks.

``deploy`` and ``eval`` refuse a policy whose metadata does not match the env
it would drive (another task, other observation or action spaces, another
control mode or rate), before anything touches the arm.
"""

from __future__ import annotations

import json
import time
from pathlib import Path
from typing import Any

import gymnasium as gym

import bioscara_gym
from bioscara_gym.errors import MetadataError, TrainingError
from bioscara_gym.fsutil import atomic_write_text

METADATA_NAME = "metadata.json"
#: env kwargs that change what the policy's actions mean; they must match to deploy.
BEHAVIOUR_KWARGS = ("control_mode", "control_freq")


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
    atomic_write_text(path, json.dumps(metadata, indent=2, sort_keys=True, default=str) + "\n")
    return path


def read_metadata(model_path: Path) -> dict[str, Any]:
    """Read the metadata next to ``model_path`` (a ``model.zip`` or its directory).

    Raises:
        MetadataError: Missing or unreadable file.
    """
    model_path = Path(model_path)
    directory = model_path if model_path.is_dir() else model_path.parent
    path = directory / METADATA_NAME
    try:
        return json.loads(path.read_text(encoding="utf-8"))
    except FileNotFoundError as e:
        raise MetadataError(
            f"no {METADATA_NAME} next to {model_path}: cannot tell what the policy was trained for"
        ) from e
    except (OSError, json.JSONDecodeError) as e:
        raise MetadataError(f"cannot read {path}: {e}") from e


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
