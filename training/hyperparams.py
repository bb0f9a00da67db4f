"""Hyperparameter files in rl-zoo3's format, read by ``bioscara train`` and rl-zoo3 alike.

One YAML mapping per file, keyed by env id; each entry holds the algorithm's
keyword arguments plus rl-zoo3's extras: ``n_timesteps``, ``policy`` (an SB3
name or a dotted path such as ``bioscara_gym.training.zoo.SACGoalErrorPolicy``),
``n_envs``, ``env_kwargs`` (a YAML mapping), ``noise_type``/``noise_std``,
``replay_buffer_class`` and ``callback`` (dotted paths, each optionally
mapped to its keyword arguments). The periodic success evaluation is the
callback :class:`bioscara_gym.training.zoo.SuccessEvalCallback`; its
``eval_freq``, ``eval_episodes`` and ``target_success`` become the fields of
:class:`Hyperparams`. So ``python -m rl_zoo3.train -conf FILE`` runs the same
entries unchanged.

Values that are strings of Python calls such as ``"dict(net_arch=[256, 256])"``
are parsed with :mod:`ast` for literals and the few class names in
:data:`~bioscara_gym.training.literals.NAMES` (``nn.ReLU``, ``GoalErrorExtractor``), never evaluated; dotted
paths are imported, as rl-zoo3 does. Files of the older, bioscara-only form
(``env_kwargs`` as a ``dict(...)`` string, ``eval_freq``/``eval_episodes``/
``target_success`` at the top of an entry) are still read; rl-zoo3 refuses them.
rl-zoo3 keys that change what the policy sees (``normalize``, ``frame_stack``,
``env_wrapper``, ``vec_env_wrapper``) are refused: a policy trained behind
them could not be evaluated, exported or deployed on the plain env. Counts
(``n_timesteps``, ``n_envs``, ``eval_freq``, ``eval_episodes``,
``quick_episodes``, ``first_eval``) must be whole numbers >= 1, ``target_success`` in
[0, 1] and ``stop_success`` (where training stops) in
[``target_success``, 1]; :func:`check_algo_kwargs` refuses keys the
algorithm does not take, and :func:`check_her_episodes` a ``learning_starts``
or ``buffer_size`` below the whole episodes HER samples. A number written
so that YAML reads a string (``9e-1``, ``"0.9"``) is refused with how to write
it (``n_timesteps`` alone is still converted, as it always was); infinities and
NaN are refused anywhere in an entry; rates, coefficients and schedules
(``lin_<x>``) must be in their range (:data:`ALGO_REALS`); ``net_arch`` has at
most :data:`MAX_LAYERS` layers of at most :data:`MAX_LAYER_WIDTH` units. A key
given twice in a mapping is refused (the arm config's strict loader). Values
are shown in messages with :func:`shown`, bounded (an alias bomb is not
expanded).
"""

from __future__ import annotations

import inspect
import math
from collections.abc import Iterable, Sequence
from dataclasses import dataclass, field
from importlib import resources
from pathlib import Path
from typing import Any

import yaml

from bioscara_gym.errors import HyperparamError
from bioscara_gym.fsutil import read_bytes
from bioscara_gym.hardware.config import MAX_CONFIG_BYTES, StrictSafeLoader
from bioscara_gym.hardware.errors import closest_name
from bioscara_gym.tasks import TASKS
from bioscara_gym.training.extras import needs_train
from bioscara_gym.training.hyperparam_values import (
    ALGO_COUNTS,
    ALGO_REALS,
    IN_CALLBACK,
    as_number,
    check_net_arch,
    check_numbers,
    check_real,
    check_train_freq,
    refuse_non_finite,
    shown,
)
from bioscara_gym.training.literals import import_dotted, parse_literal_call

#: Keys of an entry that are not the algorithm's constructor arguments.
EXTRA_KEYS = (
    "n_timesteps",
    "policy",
    "n_envs",
    "env_kwargs",
    "noise_type",
    "noise_std",
    "callback",
    "monitor_kwargs",
    # The older, bioscara-only spelling of SuccessEvalCallback's arguments.
    "eval_freq",
    "eval_episodes",
    "target_success",
)

#: rl-zoo3 keys ``bioscara train`` refuses: they change what the policy sees, so the
#: policy would not run on the plain env that eval, export and deploy give it.
ZOO_ONLY_KEYS = ("normalize", "frame_stack", "env_wrapper", "vec_env_wrapper")


#: The callback whose arguments are the evaluation schedule.
SUCCESS_CALLBACK = "bioscara_gym.training.zoo.SuccessEvalCallback"

#: Its arguments that have fields of their own in :class:`Hyperparams`.
EVAL_FIELDS = ("eval_freq", "eval_episodes", "target_success")


@dataclass(frozen=True)
class Hyperparams:
    """One env's entry of a hyperparameter file, parsed.

    Attributes:
        source: File the entry came from.
        n_timesteps: Training budget in env steps.
        policy: SB3 policy name, or the class a dotted path names.
        n_envs: Parallel envs (on-policy algorithms).
        env_kwargs: Keyword arguments for ``gym.make``.
        eval_freq: Env steps between success evaluations.
        eval_episodes: Episodes per evaluation.
        target_success: Success rate recorded as reached; training stops there
            unless the callback's ``stop_success`` (in ``eval_kwargs``) is higher.
        noise_type: Action noise for TD3 (``normal`` or ``ornstein-uhlenbeck``).
        noise_std: Its standard deviation.
        algo_kwargs: Everything else, passed to the algorithm.
        eval_kwargs: Further keyword arguments of the success callback
            (``quick_episodes``, ``first_eval``, ``seed``, ``verbose``).
        callbacks: The other callbacks of the entry: (class, keyword arguments).
    """

    source: str
    n_timesteps: int
    policy: str | type = "MultiInputPolicy"
    n_envs: int = 1
    env_kwargs: dict[str, Any] = field(default_factory=dict)
    eval_freq: int = 2000
    eval_episodes: int = 100
    target_success: float = 0.95
    noise_type: str | None = None
    noise_std: float = 0.1
    algo_kwargs: dict[str, Any] = field(default_factory=dict)
    eval_kwargs: dict[str, Any] = field(default_factory=dict)
    callbacks: tuple[tuple[type, dict[str, Any]], ...] = ()

    def as_dict(self) -> dict[str, Any]:
        """A plain, YAML/JSON-friendly view (for metadata and logs)."""
        out = {k: _plain(getattr(self, k)) for k in ("source", "n_timesteps", "policy", "n_envs")}
        out.update(
            env_kwargs=dict(self.env_kwargs),
            eval_freq=self.eval_freq,
            eval_episodes=self.eval_episodes,
            target_success=self.target_success,
            noise_type=self.noise_type,
            noise_std=self.noise_std,
            algo_kwargs=_plain(self.algo_kwargs),
        )
        if self.eval_kwargs:
            out["eval_kwargs"] = _plain(self.eval_kwargs)
        if self.callbacks:
            out["callbacks"] = [{_plain(cls): _plain(kwargs)} for cls, kwargs in self.callbacks]
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


def default_config_path(algo: str) -> Path:
    """The packaged hyperparameter file of ``algo`` (``training/configs/ALGO.yaml``)."""
    return Path(str(resources.files("bioscara_gym.training") / "configs" / f"{algo}.yaml"))


def read_entry(path: str | Path, env_id: str, kind: str = "") -> dict[str, Any]:
    """``env_id``'s entry of the YAML file ``path``: what every hyperparameter file's reading shares.

    Args:
        path: The file (rl-zoo3's format, or ``dagger.yaml``).
        env_id: The entry's key.
        kind: Named in the message when there is no entry (``"DAgger "``).

    Raises:
        HyperparamError: Unreadable file, not YAML, not a mapping of env ids,
            a key given twice in a mapping (with its line), no entry for
            ``env_id`` (the entries are listed), or an entry that is not a
            mapping; the message names the file.
    """
    path = Path(path)
    try:
        text = read_bytes(path, MAX_CONFIG_BYTES).decode("utf-8")
        data = yaml.load(text, Loader=StrictSafeLoader)  # safe, and a key given twice is refused
    except UnicodeDecodeError as e:
        raise HyperparamError(f"config {path} is not a UTF-8 text file: {e}") from e
    except OSError as e:
        raise HyperparamError(f"cannot read config {path}: {e.strerror or e}") from e
    except yaml.YAMLError as e:
        mark = getattr(e, "problem_mark", None)
        where = f" at line {mark.line + 1}, column {mark.column + 1}" if mark else ""
        problem = getattr(e, "problem", None) or type(e).__name__
        raise HyperparamError(f"config {path} is not valid YAML{where}: {problem}") from e
    except RecursionError as e:
        raise HyperparamError(f"config {path} is nested too deeply to be a hyperparameter file") from e
    if not isinstance(data, dict):
        raise HyperparamError(f"config {path}: expected a mapping of env ids, got {type(data).__name__}")
    if env_id not in data:
        known = ", ".join(sorted(map(str, data))) or "none"
        raise HyperparamError(f"config {path} has no {kind}entry for {env_id}; entries: {known}")
    entry = data[env_id]
    if not isinstance(entry, dict):
        raise HyperparamError(f"config {path}: entry {env_id} must be a mapping")
    return dict(entry)


def refuse_unknown_keys(
    keys: Iterable[Any], known: Sequence[str], where: str, what: str, otherwise: str, near: Sequence[str] = ()
) -> None:
    """Refuse the first key not in ``known``, with the closest known one (or ``near`` one) if any.

    The message is ``{where}.{key} is not {what}; did you mean '...'?``, or
    ends in ``otherwise`` when no name is close.

    Raises:
        HyperparamError: One line.
    """
    for key in keys:
        if key not in known:
            close = closest_name(key, [*known, *near])
            hint = f"did you mean {close!r}?" if close else otherwise
            raise HyperparamError(f"{where}.{key} is not {what}; {hint}")


def load_hyperparams(path: str | Path, env_id: str) -> Hyperparams:
    """Read ``env_id``'s entry from a hyperparameter file (rl-zoo3's format).

    Raises:
        HyperparamError: Unreadable file, not YAML, no entry for ``env_id``,
            or a malformed value; the message names the file and key.
    """
    path = Path(path)
    entry = read_entry(path, env_id)
    values: dict[str, Any] = {}
    for key, value in entry.items():
        where = f"config {path}: {env_id}.{key}"
        if key in ZOO_ONLY_KEYS:
            raise HyperparamError(
                f"{where}: bioscara train does not support {key} (the policy would not run on the plain "
                "env that eval, export and deploy use); train with `python -m rl_zoo3.train` instead"
            )
        values[key] = parse_literal_call(value, where) if isinstance(value, str) and "(" in value else value
    if "n_timesteps" not in values:
        raise HyperparamError(f"config {path}: {env_id}.n_timesteps is missing")
    extras = {k: values.pop(k) for k in EXTRA_KEYS if k in values}
    extras.pop("monitor_kwargs", None)  # rl-zoo3's Monitor logging; SB3 logs success itself
    env_kwargs = extras.pop("env_kwargs", {}) or {}
    if not isinstance(env_kwargs, dict):
        raise HyperparamError(f"config {path}: {env_id}.env_kwargs must be a mapping")
    where = f"config {path}: {env_id}"
    if isinstance(extras.get("policy"), str) and "." in extras["policy"]:
        extras["policy"] = _policy_class(extras["policy"], f"{where}.policy")
    eval_kwargs, callbacks = _split_callbacks(extras.pop("callback", None), f"{where}.callback")
    legacy = {k: extras.pop(k) for k in EVAL_FIELDS if k in extras}
    if legacy and set(legacy) & set(eval_kwargs):
        raise HyperparamError(f"{where}: {', '.join(legacy)} given both at the top and in the callback")
    eval_kwargs.update(legacy)
    check_numbers(values, extras, env_kwargs, eval_kwargs, legacy, callbacks, where)
    _check_schedule(extras, eval_kwargs, legacy, where)
    try:
        return Hyperparams(
            source=str(path),
            n_timesteps=int(float(extras.pop("n_timesteps"))),
            env_kwargs=env_kwargs,
            algo_kwargs=values,
            callbacks=callbacks,
            **{k: eval_kwargs.pop(k) for k in EVAL_FIELDS if k in eval_kwargs},
            eval_kwargs=eval_kwargs,
            **extras,
        )
    except (TypeError, ValueError) as e:
        raise HyperparamError(f"config {path}: {env_id}: {e}") from e


#: Keys that count something and must be at least 1, with what they count (for the message).
POSITIVE_COUNTS = {
    "n_timesteps": "env steps of the training budget",
    "n_envs": "parallel envs",
    "eval_freq": "env steps between success evaluations",
    "eval_episodes": "episodes per success evaluation",
    "quick_episodes": "episodes per quick success evaluation",
    "first_eval": "env steps before the first success evaluation",
}


def _policy_class(name: str, where: str) -> type:
    """The policy class a dotted path names, checked to be one before anything calls it.

    Raises:
        HyperparamError: Not importable, or not a stable-baselines3 policy
            class (``os.system`` was imported and called with the policy's
            arguments).
    """
    cls = import_dotted(name, where)
    with needs_train("a policy class"):
        from stable_baselines3.common.policies import BasePolicy
    if not (isinstance(cls, type) and issubclass(cls, BasePolicy)):
        raise HyperparamError(f"{where}: {name} is not a stable-baselines3 policy class")
    return cls


def _check_schedule(
    extras: dict[str, Any], eval_kwargs: dict[str, Any], legacy: dict[str, Any], where: str
) -> None:
    """Refuse counts below 1 and a target success rate outside [0, 1], naming the key.

    ``where`` is ``config PATH: ENV_ID``; a key of the success callback is
    named as written in the file (at the top of the entry, or in the callback).
    """
    for key, what in POSITIVE_COUNTS.items():
        source = extras if key in ("n_timesteps", "n_envs") else eval_kwargs
        if key not in source:
            continue
        name = key if source is extras or key in legacy else IN_CALLBACK + key
        number = as_number(source[key])
        if number is None or not math.isfinite(number) or number != int(number) or number < 1:
            raise HyperparamError(
                f"{where}.{name} is {shown(source[key])}; expected a whole number >= 1 ({what})"
            )
    for key in ("target_success", "stop_success"):
        rate = eval_kwargs.get(key)
        is_rate = isinstance(rate, int | float) and not isinstance(rate, bool) and 0 <= rate <= 1
        if rate is not None and not is_rate:
            name = key if key in legacy else IN_CALLBACK + key
            raise HyperparamError(f"{where}.{name} is {shown(rate)}; expected a success rate in [0, 1]")
    target, stop = eval_kwargs.get("target_success", 0.95), eval_kwargs.get("stop_success")
    if stop is not None and stop < target:
        raise HyperparamError(
            f"{where}.{IN_CALLBACK}stop_success is {shown(stop)}; expected at least target_success "
            f"({shown(target)}): "
            "training stops at stop_success after reaching the target"
        )


def check_algo_counts(hp: Hyperparams, env_id: str) -> None:
    """Refuse a count below 1, a negative ``learning_starts``, a value of :data:`ALGO_REALS` out of range.

    Then a ``net_arch`` too wide or too deep, a bad ``train_freq`` or
    ``gradient_steps``, a negative or infinite ``noise_std``, and an
    infinity or NaN anywhere in the algorithm's arguments.

    Raises:
        HyperparamError: One line naming the key, the file and what was expected.
    """
    where = f"config {hp.source}: {env_id}"
    for key, what in ALGO_COUNTS.items():
        if key in hp.algo_kwargs:
            number = as_number(hp.algo_kwargs[key])
            if number is None or not math.isfinite(number) or number != int(number) or number < 1:
                raise HyperparamError(
                    f"{where}.{key} is {shown(hp.algo_kwargs[key])}; expected a whole number >= 1 ({what})"
                )
    if "learning_starts" in hp.algo_kwargs:
        number = as_number(hp.algo_kwargs["learning_starts"])
        if number is None or not math.isfinite(number) or number != int(number) or number < 0:
            raise HyperparamError(
                f"{where}.learning_starts is {shown(hp.algo_kwargs['learning_starts'])}; expected a whole "
                "number >= 0 (env steps before learning starts)"
            )
    for key in ALGO_REALS:
        if key in hp.algo_kwargs:
            check_real(hp.algo_kwargs[key], key, where)
    check_train_freq(hp.algo_kwargs, where)
    if not (as_number(hp.noise_std) is not None and math.isfinite(hp.noise_std) and hp.noise_std >= 0):
        raise HyperparamError(f"{where}.noise_std is {shown(hp.noise_std)}; expected a finite number >= 0")
    refuse_non_finite(hp.algo_kwargs, where)
    policy_kwargs = hp.algo_kwargs.get("policy_kwargs")
    if isinstance(policy_kwargs, dict) and "net_arch" in policy_kwargs:
        check_net_arch(policy_kwargs["net_arch"], f"{where}.policy_kwargs.net_arch")


def check_algo_kwargs(hp: Hyperparams, algo_cls: type, env_id: str) -> None:
    """Refuse keys of ``hp.algo_kwargs`` that ``algo_cls`` does not take, naming key and file.

    First the values :func:`check_algo_counts` checks.

    Raises:
        HyperparamError: An unknown key, with the closest known one if any.
    """
    check_algo_counts(hp, env_id)
    parameters = inspect.signature(algo_cls).parameters
    ent_coef = hp.algo_kwargs.get("ent_coef")
    if isinstance(ent_coef, str) and "target_entropy" not in parameters:  # "auto" is SAC's
        raise HyperparamError(
            f"config {hp.source}: {env_id}.ent_coef is {shown(ent_coef)}; expected a finite number >= 0 "
            f"({algo_cls.__name__} has no automatic entropy coefficient)"
        )
    if any(p.kind is inspect.Parameter.VAR_KEYWORD for p in parameters.values()):
        return
    known = [name for name in parameters if name not in ("policy", "env")]
    refuse_unknown_keys(
        hp.algo_kwargs,
        known,
        f"config {hp.source}: {env_id}",
        f"a hyperparameter of {algo_cls.__name__}",
        f"see the {algo_cls.__name__} documentation",
        near=EXTRA_KEYS,
    )


def check_her_episodes(
    hp: Hyperparams, algo_cls: type, env_id: str, episode_steps: int | None, n_envs: int
) -> None:
    """Refuse a ``learning_starts`` or ``buffer_size`` below an episode on each env, when HER samples.

    ``HerReplayBuffer`` samples only finished episodes, and each env's share
    of it (``buffer_size`` / ``n_envs``) must hold one: else the first
    gradient step, after ``learning_starts`` env steps (counted over all
    envs), raised "Unable to sample before the end of the first episode",
    a traceback after ``train_state.json`` and ``tb/`` were written. HER
    samples when the entry names it, or for an off-policy algorithm on a
    goal task (:data:`~bioscara_gym.tasks.TASKS`) whose entry names no
    replay buffer (the runner adds HER then). ``episode_steps`` ``None``:
    episodes without a limit, nothing to check.

    Raises:
        HyperparamError: One line naming the file, the key (or the
            algorithm's default it takes) and the least HER needs.
    """
    with needs_train("HER's replay buffer"):
        from stable_baselines3.common.off_policy_algorithm import OffPolicyAlgorithm
    kwargs = hp.algo_kwargs
    buffer = kwargs.get("replay_buffer_class")
    named = buffer if isinstance(buffer, str) else getattr(buffer, "__name__", None)
    off_policy = issubclass(algo_cls, OffPolicyAlgorithm)
    added = "replay_buffer_class" not in kwargs and env_id in TASKS and off_policy
    if episode_steps is None or not (named == "HerReplayBuffer" or added):
        return
    needed = int(episode_steps) * n_envs
    defaults = {k: p.default for k, p in inspect.signature(algo_cls).parameters.items()}
    for key in ("learning_starts", "buffer_size"):
        value = as_number(kwargs[key]) if key in kwargs else as_number(defaults.get(key))
        if value is None or value >= needed:  # not a number: check_algo_counts names it
            continue
        given = shown(kwargs[key]) if key in kwargs else f"{defaults[key]} ({algo_cls.__name__}'s default)"
        envs = "the 1 env" if n_envs == 1 else f"each of the {n_envs} envs"
        raise HyperparamError(
            f"config {hp.source}: {env_id}.{key} is {given}; HerReplayBuffer samples only whole episodes, "
            f"so it must be at least {needed} (an episode of {episode_steps} steps on {envs})"
        )


def _split_callbacks(spec: Any, where: str) -> tuple[dict[str, Any], tuple[tuple[type, dict[str, Any]], ...]]:
    """rl-zoo3's ``callback`` value: the success callback's kwargs, and the other callbacks.

    rl-zoo3 accepts a dotted path, a ``{path: kwargs}`` mapping, or a list of them.
    """
    from bioscara_gym.training.zoo import SuccessEvalCallback

    if spec is None:
        return {}, ()
    items = spec if isinstance(spec, list) else [spec]
    eval_kwargs: dict[str, Any] | None = None
    others: list[tuple[type, dict[str, Any]]] = []
    for item in items:
        if isinstance(item, str):
            name, kwargs = item, {}
        elif isinstance(item, dict) and len(item) == 1:
            name, kwargs = next(iter(item.items()))
            kwargs = {} if kwargs is None else kwargs
        else:
            raise HyperparamError(f"{where}: expected a dotted path or {{path: kwargs}}, got {shown(item)}")
        if not isinstance(name, str) or not isinstance(kwargs, dict):
            raise HyperparamError(f"{where}: expected a dotted path mapped to its kwargs, got {shown(item)}")
        cls = import_dotted(name, where)
        with needs_train("a callback class"):
            from stable_baselines3.common.callbacks import BaseCallback
        if not (isinstance(cls, type) and issubclass(cls, BaseCallback)):  # seen: os.system ran a command
            raise HyperparamError(f"{where}: {name} is not a stable-baselines3 callback class (BaseCallback)")
        try:
            inspect.signature(cls).bind(**kwargs)
        except TypeError as e:
            raise HyperparamError(f"{where}: {name}: {e}") from e
        if isinstance(cls, type) and issubclass(cls, SuccessEvalCallback):
            if eval_kwargs is not None:
                raise HyperparamError(f"{where}: more than one {SUCCESS_CALLBACK}")
            eval_kwargs = dict(kwargs)
        else:
            others.append((cls, dict(kwargs)))
    return eval_kwargs or {}, tuple(others)
