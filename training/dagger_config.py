"""DAgger's configuration: one env's entry of ``training/configs/dagger.yaml``, checked on load.

Not an rl-zoo3 file (rl-zoo3 has no imitation learning); read with the same
:func:`~bioscara_gym.training.hyperparams.read_entry` and
:func:`~bioscara_gym.training.hyperparams.refuse_unknown_keys` as rl-zoo3's
files, so a bad entry gets the same one-line errors.
"""

from __future__ import annotations

import dataclasses
import math
from dataclasses import dataclass, field
from pathlib import Path
from typing import Any

from bioscara_gym.errors import HyperparamError
from bioscara_gym.training.hyperparam_values import (
    MAX_LAYER_WIDTH,
    MAX_LAYERS,
    net_arch_problem,
    refuse_non_finite,
    refuse_number_string,
    shown,
)
from bioscara_gym.training.hyperparams import read_entry, refuse_unknown_keys
from bioscara_gym.training.literals import ACTION_LOSSES


@dataclass(frozen=True)
class DaggerConfig:
    """One env's entry of ``training/configs/dagger.yaml``, checked on load.

    Not an rl-zoo3 file (rl-zoo3 has no imitation learning), read by
    :func:`load_dagger_config` with the same :func:`read_entry` and
    :func:`refuse_unknown_keys` as rl-zoo3's files.

    Attributes:
        source: File the entry came from.
        n_timesteps: Budget in env steps, the expert's episodes included.
        env_kwargs: Keyword arguments for ``gym.make``.
        net_arch: Hidden layers of the actor.
        features: Keyword arguments of the task's features extractor
            (PickPlace: :class:`~bioscara_gym.training.features.PickPlaceExtractor`).
        demo_episodes: Expert episodes cloned first (iteration 0).
        episodes_per_iteration: Learner episodes labelled per iteration.
        bc_steps_first: Gradient steps of the first cloning.
        bc_steps: Gradient steps after each aggregation (warm-started).
        batch_size: Labelled states per gradient step.
        learning_rate: Adam's learning rate.
        loss: The fit's action loss, ``mse`` (squared error) or ``l1``
            (absolute error: where the expert's labels change abruptly, as
            between two phases of a task, the fit keeps one of them rather
            than their mean, which can be a standstill). The default is the
            squared error, as before the key existed, so an older config or
            a resumed run fits as it did; every packaged entry asks ``l1``.
        beta: The expert acts a share ``beta ** i`` of iteration ``i``'s steps.
        eval_episodes: Episodes of the confirming success evaluation (fresh
            ones each time; their states join the aggregate when it falls
            short) and of the final one when the budget runs out.
        target_success: Success rate at which training stops.
        n_envs: Envs the rollouts run in, each in a subprocess when more
            than 1 (SB3's ``SubprocVecEnv``); 1: one env, in this process.
        fit_threads: torch's CPU threads while the actor is fitted (the
            rollouts' env waits meanwhile, so a second core is free); the
            rollouts keep ``--threads``. The fit's numbers depend on it.
    """

    source: str
    n_timesteps: int = 72_000
    env_kwargs: dict[str, Any] = field(default_factory=dict)
    net_arch: tuple[int, ...] = (256, 256)
    features: dict[str, float] = field(default_factory=dict)
    demo_episodes: int = 60
    episodes_per_iteration: int = 20
    bc_steps_first: int = 3000
    bc_steps: int = 2000
    batch_size: int = 256
    learning_rate: float = 1e-3
    loss: str = "mse"
    beta: float = 0.5
    eval_episodes: int = 100
    target_success: float = 0.9
    n_envs: int = 1
    fit_threads: int = 2

    def __post_init__(self) -> None:
        """Refuse counts below 1, rates outside their range, and values of the wrong type.

        Types are checked before ranges (seen: ``'>' not supported between
        'str' and 'int'`` for ``learning_rate: 1e-3``, which YAML reads as text).

        Raises:
            HyperparamError: The first bad value, named with the file.
        """
        where = f"config {self.source}"
        counts = (
            "n_timesteps",
            "demo_episodes",
            "episodes_per_iteration",
            "bc_steps_first",
            "batch_size",
            "n_envs",
            "fit_threads",
        )
        for name in (*counts, "eval_episodes"):
            value = getattr(self, name)
            if isinstance(value, bool) or not isinstance(value, int) or value < 1:
                raise HyperparamError(f"{where}: {name} is {shown(value)}; expected a whole number >= 1")
        if isinstance(self.bc_steps, bool) or not isinstance(self.bc_steps, int) or self.bc_steps < 0:
            bc_steps = shown(self.bc_steps)
            raise HyperparamError(f"{where}: bc_steps is {bc_steps}; expected a whole number >= 0")
        for name in ("target_success", "beta", "learning_rate"):
            value = getattr(self, name)
            refuse_number_string(value, f"{where}: {name}")
            if isinstance(value, bool) or not isinstance(value, int | float) or not math.isfinite(value):
                expected = {"target_success": "in (0, 1]", "beta": "in [0, 1)", "learning_rate": "> 0"}[name]
                raise HyperparamError(f"{where}: {name} is {shown(value)}; expected a number {expected}")
        if not 0.0 < self.target_success <= 1.0:
            raise HyperparamError(f"{where}: target_success is {shown(self.target_success)}; expected (0, 1]")
        if not 0.0 <= self.beta < 1.0:
            raise HyperparamError(f"{where}: beta is {shown(self.beta)}; expected [0, 1)")
        if not isinstance(self.loss, str) or self.loss not in ACTION_LOSSES:
            expected = ", ".join(ACTION_LOSSES)
            raise HyperparamError(f"{where}: loss is {shown(self.loss)}; expected one of {expected}")
        if not self.learning_rate > 0:
            raise HyperparamError(f"{where}: learning_rate is {shown(self.learning_rate)}; expected > 0")
        if not self.net_arch or net_arch_problem(list(self.net_arch)):
            raise HyperparamError(
                f"{where}: net_arch is {shown(list(self.net_arch))}; expected layer widths >= 1 and at most "
                f"{MAX_LAYER_WIDTH}, at most {MAX_LAYERS} layers"
            )

    def as_dict(self) -> dict[str, Any]:
        """A JSON-friendly view (for the metadata)."""
        out = dataclasses.asdict(self)
        out["net_arch"] = list(self.net_arch)
        return out


def load_dagger_config(path: str | Path, env_id: str) -> DaggerConfig:
    """``env_id``'s entry of DAgger file ``path``.

    Raises:
        HyperparamError: Unreadable, not YAML, no entry, an unknown key (with
            the closest known one), or a bad value.
    """
    entry = read_entry(path, env_id, kind="DAgger ")
    names = [f.name for f in dataclasses.fields(DaggerConfig) if f.name != "source"]
    refuse_unknown_keys(
        entry, names, f"config {path}: {env_id}", "a DAgger setting", f"known keys: {', '.join(names)}"
    )
    for key in ("env_kwargs", "features"):
        if not isinstance(entry.get(key, {}), dict):
            raise HyperparamError(f"config {path}: {env_id}.{key} must be a mapping")
    for key, value in entry.items():
        refuse_number_string(value, f"config {path}: {env_id}.{key}")
    for key, value in entry.get("features", {}).items():
        refuse_number_string(value, f"config {path}: {env_id}.features.{key}")
    refuse_non_finite(entry, f"config {path}: {env_id}")
    if "net_arch" in entry:
        if not isinstance(entry["net_arch"], list):
            raise HyperparamError(f"config {path}: {env_id}.net_arch must be a list of layer widths")
        entry["net_arch"] = tuple(entry["net_arch"])
    value = entry.get("n_timesteps")  # YAML writes 3e5 as a float
    if isinstance(value, float) and value.is_integer():
        entry["n_timesteps"] = int(value)
    return DaggerConfig(source=str(path), **entry)
