"""Hyperparameter files in rl-zoo3's format.

One YAML mapping per file, keyed by env id; each entry holds the algorithm's
keyword arguments plus rl-zoo3's extras (``n_timesteps``, ``policy``,
``n_envs``, ``env_kwargs``, ``noise_type``/``noise_std``,
``replay_buffer_class``) and ours (``eval_freq``, ``eval_episodes``,
``target_success``). Values that are strings of Python calls such as
``"dict(net_arch=[256, 256])"`` are parsed with :mod:`ast` for literals and
the few class names in :data:`NAMES` (``nn.ReLU``, ``GoalErrorExtractor``),
never evaluated.
"""

from __future__ import annotations

import ast
import importlib
from dataclasses import dataclass, field
from importlib import resources
from pathlib import Path
from typing import Any

import yaml

from bioscara_gym.errors import HyperparamError

#: Keys of an entry that are not the algorithm's constructor arguments.
EXTRA_KEYS = (
    "n_timesteps",
    "policy",
    "n_envs",
    "env_kwargs",
    "noise_type",
    "noise_std",
    "eval_freq",
    "eval_episodes",
    "target_success",
)


#: Names a value may use (rl-zoo3 writes ``activation_fn=nn.ReLU``), as ``module:attribute``.
NAMES = {
    "nn.ReLU": "torch.nn:ReLU",
    "nn.Tanh": "torch.nn:Tanh",
    "nn.ELU": "torch.nn:ELU",
    "nn.LeakyReLU": "torch.nn:LeakyReLU",
    "GoalErrorExtractor": "bioscara_gym.training.features:GoalErrorExtractor",
}


@dataclass(frozen=True)
class Hyperparams:
    """One env's entry of a hyperparameter file, parsed.

    Attributes:
        source: File the entry came from.
        n_timesteps: Training budget in env steps.
        policy: SB3 policy name.
        n_envs: Parallel envs (on-policy algorithms).
        env_kwargs: Keyword arguments for ``gym.make``.
        eval_freq: Env steps between success evaluations.
        eval_episodes: Episodes per evaluation.
        target_success: Success rate at which training stops early.
        noise_type: Action noise for TD3 (``normal`` or ``ornstein-uhlenbeck``).
        noise_std: Its standard deviation.
        algo_kwargs: Everything else, passed to the algorithm.
    """

    source: str
    n_timesteps: int
    policy: str = "MultiInputPolicy"
    n_envs: int = 1
    env_kwargs: dict[str, Any] = field(default_factory=dict)
    eval_freq: int = 2000
    eval_episodes: int = 100
    target_success: float = 0.95
    noise_type: str | None = None
    noise_std: float = 0.1
    algo_kwargs: dict[str, Any] = field(default_factory=dict)

    def as_dict(self) -> dict[str, Any]:
        """A plain, YAML/JSON-friendly view (for metadata and logs)."""
        out = {k: getattr(self, k) for k in ("source", "n_timesteps", "policy", "n_envs")}
        out.update(
            env_kwargs=dict(self.env_kwargs),
            eval_freq=self.eval_freq,
            eval_episodes=self.eval_episodes,
            target_success=self.target_success,
            noise_type=self.noise_type,
            noise_std=self.noise_std,
            algo_kwargs=_plain(self.algo_kwargs),
        )
        return out


def _plain(value: Any) -> Any:
    """``value`` with classes and other objects replaced by their names (for JSON)."""
    if isinstance(value, dict):
        return {k: _plain(v) for k, v in value.items()}
    if isinstance(value, list | tuple):
        return [_plain(v) for v in value]
    if isinstance(value, int | float | str | bool | None):
        return value
    if isinstance(value, type):
        return f"{value.__module__}.{value.__qualname__}"
    return str(value)


def parse_literal_call(text: str, where: str) -> Any:
    """Parse ``"dict(a=1, b=[2, 3])"`` or a literal; names only from :data:`NAMES`.

    Raises:
        HyperparamError: Anything but literals, nested ``dict(...)`` calls and
            the names of :data:`NAMES`.
    """
    try:
        node = ast.parse(text, mode="eval").body
    except SyntaxError as e:
        raise HyperparamError(f"{where}: {text!r} is not a Python literal or dict(...)") from e

    def convert(n: ast.AST) -> Any:
        if (
            isinstance(n, ast.Call)
            and isinstance(n.func, ast.Name)
            and n.func.id == "dict"
            and not n.args
            and all(kw.arg is not None for kw in n.keywords)  # no **mapping
        ):
            return {kw.arg: convert(kw.value) for kw in n.keywords}
        if isinstance(n, ast.List):
            return [convert(e) for e in n.elts]
        if isinstance(n, ast.Tuple):
            return tuple(convert(e) for e in n.elts)
        if isinstance(n, ast.Dict):
            return {convert(k): convert(v) for k, v in zip(n.keys, n.values, strict=True)}
        if isinstance(n, ast.Name | ast.Attribute) and ast.unparse(n) in NAMES:
            module, attribute = NAMES[ast.unparse(n)].split(":")
            return getattr(importlib.import_module(module), attribute)
        try:
            return ast.literal_eval(n)
        except ValueError as e:
            raise HyperparamError(
                f"{where}: {ast.unparse(n)!r} is not allowed; use literals, dict(...) "
                f"and the names {', '.join(NAMES)}"
            ) from e

    return convert(node)


def default_config_path(algo: str) -> Path:
    """The packaged hyperparameter file of ``algo`` (``training/configs/ALGO.yaml``)."""
    return Path(str(resources.files("bioscara_gym.training") / "configs" / f"{algo}.yaml"))


def load_hyperparams(path: str | Path, env_id: str) -> Hyperparams:
    """Read ``env_id``'s entry from a hyperparameter file.

    Raises:
        HyperparamError: Unreadable file, not YAML, no entry for ``env_id``,
            or a malformed value; the message names the file and key.
    """
    path = Path(path)
    try:
        data = yaml.safe_load(path.read_text(encoding="utf-8"))
    except OSError as e:
        raise HyperparamError(f"cannot read config {path}: {e.strerror or e}") from e
    except yaml.YAMLError as e:
        mark = getattr(e, "problem_mark", None)
        where = f" at line {mark.line + 1}, column {mark.column + 1}" if mark else ""
        problem = getattr(e, "problem", None) or type(e).__name__
        raise HyperparamError(f"config {path} is not valid YAML{where}: {problem}") from e
    if not isinstance(data, dict):
        raise HyperparamError(f"config {path}: expected a mapping of env ids, got {type(data).__name__}")
    if env_id not in data:
        known = ", ".join(sorted(map(str, data))) or "none"
        raise HyperparamError(f"config {path} has no entry for {env_id}; entries: {known}")
    entry = data[env_id]
    if not isinstance(entry, dict):
        raise HyperparamError(f"config {path}: entry {env_id} must be a mapping")
    values: dict[str, Any] = {}
    for key, value in entry.items():
        where = f"config {path}: {env_id}.{key}"
        values[key] = parse_literal_call(value, where) if isinstance(value, str) and "(" in value else value
    if "n_timesteps" not in values:
        raise HyperparamError(f"config {path}: {env_id}.n_timesteps is missing")
    extras = {k: values.pop(k) for k in EXTRA_KEYS if k in values}
    env_kwargs = extras.pop("env_kwargs", {}) or {}
    if not isinstance(env_kwargs, dict):
        raise HyperparamError(f"config {path}: {env_id}.env_kwargs must be dict(...)")
    try:
        return Hyperparams(
            source=str(path),
            n_timesteps=int(float(extras.pop("n_timesteps"))),
            env_kwargs=env_kwargs,
            algo_kwargs=values,
            **{k: v for k, v in extras.items()},
        )
    except (TypeError, ValueError) as e:
        raise HyperparamError(f"config {path}: {env_id}: {e}") from e
