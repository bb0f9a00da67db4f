"""The stable-baselines3 algorithms by name, and a trained model loaded to act.

Training, evaluation, export and deployment of an SB3 model all use this
module; it imports none of them. Both tables are read off the registry of
training methods (:data:`~bioscara_gym.training.methods.METHODS`).
Importing it without the ``[train]`` extra raises
:class:`~bioscara_gym.errors.MissingExtraError`.
"""

from __future__ import annotations

import os
from pathlib import Path
from typing import Any

import numpy as np

from bioscara_gym.errors import MetadataError, PolicyFileError
from bioscara_gym.tasks import Policy
from bioscara_gym.training.extras import needs_train
from bioscara_gym.training.metadata import TRAINED_FOR_KEYS, check_embedded_metadata, read_metadata
from bioscara_gym.training.methods import METHODS

with needs_train():
    import stable_baselines3
    import torch
    from stable_baselines3.common.base_class import BaseAlgorithm


def sb3_class(name: str) -> type[BaseAlgorithm]:
    """The stable-baselines3 algorithm class called ``name`` (``SAC``)."""
    return getattr(stable_baselines3, name)


def policy_base(name: str) -> type:
    """The class every policy of SB3 algorithm ``name`` is (``SACPolicy``): its ``MlpPolicy``.

    Custom policies subclass one of its aliases (``SACGoalErrorPolicy`` its
    ``MultiInputPolicy``), and every alias subclasses ``MlpPolicy``'s class.
    """
    return sb3_class(name).policy_aliases["MlpPolicy"]


#: The algorithms trained from rl-zoo3 files, by ``--algo`` name.
ALGOS: dict[str, type[BaseAlgorithm]] = {n: sb3_class(s.model) for n, s in METHODS.items() if s.rl_zoo}
#: The class each ``algo`` of a model's metadata loads with: behaviour cloning
#: (``--algo bc``, and DAgger, which saves as ``bc``) saves a SAC model whose actor was only cloned.
MODEL_CLASSES: dict[str, type[BaseAlgorithm]] = {s.algo: sb3_class(s.model) for s in METHODS.values()}


def load_model(
    path: Path, require_embedded: bool = False, keys: tuple[str, ...] | None = TRAINED_FOR_KEYS
) -> tuple[BaseAlgorithm, dict[str, Any]]:
    """Load a trained ``model.zip`` to act, with its metadata (the algorithm is in the metadata).

    The ``metadata.json`` beside it must agree with the copy saved inside it
    in ``keys`` (every setting if ``None``;
    :func:`~bioscara_gym.training.metadata.check_embedded_metadata`; with
    ``require_embedded``, a model without a copy is refused too), and every
    weight of its policy must be finite.

    ``algo.load`` without an env fails for a model trained with
    ``HerReplayBuffer`` (the default for the goal tasks) and would allocate
    the whole replay buffer; acting needs neither, so the buffer is replaced
    by a one-entry plain one.

    Raises:
        MetadataError: No, unreadable or incomplete metadata, or an ``algo``
            it does not state or that is unknown, or that disagrees with the
            model's own copy.
        PolicyFileError: No model file, or one stable-baselines3 cannot load
            (truncated, not a model, saved by another algorithm), or a policy
            weight that is NaN or infinite.
    """
    path = Path(path)
    model_file = path / "model.zip" if path.is_dir() else path
    if not model_file.exists():  # seen: "no metadata.json next to nope.zip" for a typo
        dangling = f" (a symlink to {os.readlink(model_file)}, not there)" if model_file.is_symlink() else ""
        raise PolicyFileError(f"no model at {model_file}{dangling}")
    if not model_file.is_file():  # seen: a FIFO or /dev/zero was "no model at ..."
        raise PolicyFileError(f"{model_file} is not a regular file; give the model.zip")
    metadata = read_metadata(model_file)
    name = metadata.get("algo")
    if name not in MODEL_CLASSES:
        said = "does not say which algorithm trained the policy" if name is None else f"has algo {name!r}"
        raise MetadataError(
            f"metadata.json next to {model_file} {said}; expected one of {', '.join(MODEL_CLASSES)}"
        )
    act_only = {"replay_buffer_class": None, "replay_buffer_kwargs": {}, "buffer_size": 1}
    try:
        model = MODEL_CLASSES[name].load(model_file, env=None, device="cpu", custom_objects=act_only)
    except Exception as e:  # zipfile, pickle, torch and SB3's own asserts: all mean "not loadable"
        raise PolicyFileError(
            f"cannot load {model_file} as the {name.upper()} model metadata.json says it is (truncated, "
            f"not a stable-baselines3 zip, or another algorithm's?): {type(e).__name__}: {_first_line(e)}"
        ) from e
    check_embedded_metadata(metadata, model_file, required=require_embedded, keys=keys)
    check_weights(model, model_file)
    return model, metadata


def check_weights(model: BaseAlgorithm, model_file: Path) -> None:
    """Refuse a policy with a NaN or infinite weight, naming the first such parameter.

    Raises:
        PolicyFileError: One line naming the file and the parameter.
    """
    for name, parameter in model.policy.named_parameters():
        bad = int((~torch.isfinite(parameter)).sum())
        if bad:
            raise PolicyFileError(
                f"{model_file}: policy weight {name} holds {bad} non-finite value(s) (NaN or inf) of "
                f"{parameter.numel()}; the policy cannot act, retrain it"
            )


def _first_line(e: BaseException) -> str:
    """The first line of an exception's message (some libraries' messages span many)."""
    text = str(e).strip()
    return text.splitlines()[0] if text else "no message"


def sb3_policy(model: Any) -> Policy:
    """Deterministic actions of a stable-baselines3 model (``model.predict(obs, deterministic=True)``).

    A SAC model's (what DAgger, behaviour cloning and Reach's default train)
    are computed as ``predict`` computes them without its per-call set-up,
    which took about half of each call: switching every module to eval mode
    again, and building the Gaussian only to take its mode. The action is
    the squashed Gaussian's mode, ``tanh`` of the actor's mean, rescaled to
    the action space: the same numbers.
    """
    if not isinstance(model, stable_baselines3.SAC) or model.policy.actor.use_sde:

        def act(obs: dict[str, np.ndarray]) -> np.ndarray:
            action, _ = model.predict(obs, deterministic=True)
            return action

        return act
    policy = model.policy
    actor, shape = policy.actor, policy.action_space.shape

    def act_sac(obs: dict[str, np.ndarray]) -> np.ndarray:
        if policy.training or actor.training:  # training switched it back since the last call
            policy.set_training_mode(False)
        obs_tensor, vectorized = policy.obs_to_tensor(obs)
        with torch.no_grad():
            mean = actor.mu(actor.latent_pi(actor.extract_features(obs_tensor, actor.features_extractor)))
            actions = torch.tanh(mean).cpu().numpy().reshape((-1, *shape))
        actions = policy.unscale_action(actions)
        return actions if vectorized else actions.squeeze(axis=0)

    return act_sac
