"""The stable-baselines3 algorithms by name, and a trained model loaded to act.

Training, evaluation, export and deployment of an SB3 model all use this
module; it imports none of them. Importing it without the ``[train]`` extra
raises :class:`~bioscara_gym.errors.MissingExtraError`.
"""

from __future__ import annotations

from collections.abc import Callable
from pathlib import Path
from typing import Any

import numpy as np

from bioscara_gym.training.extras import needs_train
from bioscara_gym.training.metadata import read_metadata

with needs_train():
    import torch  # noqa: F401 - stable-baselines3 needs it; missing, it names the extra
    from stable_baselines3 import PPO, SAC, TD3
    from stable_baselines3.common.base_class import BaseAlgorithm

ALGOS: dict[str, type[BaseAlgorithm]] = {"sac": SAC, "td3": TD3, "ppo": PPO}
#: The class each ``algo`` of a model's metadata loads with: behaviour cloning
#: (``bioscara train --algo bc``) saves a SAC model whose actor was only cloned.
MODEL_CLASSES: dict[str, type[BaseAlgorithm]] = {**ALGOS, "bc": SAC}

Policy = Callable[[dict[str, np.ndarray]], np.ndarray]


def load_model(path: Path) -> tuple[BaseAlgorithm, dict[str, Any]]:
    """Load a trained ``model.zip`` to act, with its metadata (the algorithm is in the metadata).

    ``algo.load`` without an env fails for a model trained with
    ``HerReplayBuffer`` (the default for the goal tasks) and would allocate
    the whole replay buffer; acting needs neither, so the buffer is replaced
    by a one-entry plain one.

    Raises:
        MetadataError: No or unreadable metadata.
        FileNotFoundError: No model file.
    """
    path = Path(path)
    model_file = path / "model.zip" if path.is_dir() else path
    metadata = read_metadata(model_file)
    if not model_file.exists():
        raise FileNotFoundError(f"no model at {model_file}")
    algo = MODEL_CLASSES[metadata.get("algo", "sac")]
    act_only = {"replay_buffer_class": None, "replay_buffer_kwargs": {}, "buffer_size": 1}
    model = algo.load(model_file, env=None, device="cpu", custom_objects=act_only)
    return model, metadata


def sb3_policy(model: Any) -> Policy:
    """Deterministic actions of a stable-baselines3 model."""

    def act(obs: dict[str, np.ndarray]) -> np.ndarray:
        action, _ = model.predict(obs, deterministic=True)
        return action

    return act
