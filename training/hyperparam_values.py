"""The values of a hyperparameter entry, each refused in one line naming file, key and what was expected.

:mod:`~bioscara_gym.training.hyperparams` reads an entry; this checks what
it holds: a number written so that YAML reads a string (``9e-1``), an
infinity or NaN anywhere, a rate, coefficient or schedule (``lin_<x>``) out
of its range (:data:`ALGO_REALS`), a count below 1 (:data:`ALGO_COUNTS`),
``train_freq`` and ``gradient_steps``, and a ``net_arch`` too wide or too
deep. Values are shown in messages with :func:`shown`, bounded: a YAML alias
bomb is never expanded.
"""

from __future__ import annotations

import math
import reprlib
from typing import Any

from bioscara_gym.errors import HyperparamError

#: How the message names a key of the success callback given inside ``callback``.
IN_CALLBACK = "callback.SuccessEvalCallback."

#: Widest hidden layer ``net_arch`` may ask (seen: ``[1000000000]`` asked torch for 72 GB).
MAX_LAYER_WIDTH = 4096
#: Most hidden layers ``net_arch`` may ask, per network.
MAX_LAYERS = 16


_REPR = reprlib.Repr()
_REPR.maxlevel = 2
_REPR.maxlist = _REPR.maxtuple = _REPR.maxset = _REPR.maxfrozenset = _REPR.maxdeque = 4
_REPR.maxdict = 4
_REPR.maxstring = _REPR.maxother = 60
_REPR.maxlong = 30


def shown(value: Any) -> str:
    """``repr(value)`` cut short: a few items, levels and characters (an alias bomb is not expanded)."""
    return _REPR.repr(value)


def as_number(value: Any) -> float | None:
    """``value`` as a float: a number, or a string of one (YAML reads ``3e4`` as text); else ``None``."""
    if isinstance(value, bool):
        return None
    if isinstance(value, int | float):
        return float(value)
    if isinstance(value, str):
        try:
            return float(value)
        except ValueError:
            return None
    return None


def _yaml_number(number: float) -> str:
    """``number`` written so that YAML reads a number: ``0.9``, ``100000``, ``1.0e-05`` (not ``1e-05``)."""
    if number.is_integer() and abs(number) < 1e16:
        return str(int(number))
    mantissa, e, exponent = repr(number).partition("e")
    if not e:
        return mantissa
    return f"{mantissa if '.' in mantissa else mantissa + '.0'}e{exponent}"


def refuse_number_string(value: Any, where: str) -> None:
    """Refuse a string that reads as a number (YAML reads ``9e-1``, without a dot, as text).

    SB3 would get the string (seen: ``gamma: 9e-1`` failed in numpy mid-training).

    Raises:
        HyperparamError: ``{where} is '9e-1', a string; write 0.9``.
    """
    if not isinstance(value, str):
        return
    try:
        number = float(value)
    except ValueError:
        return
    fix = f"write {_yaml_number(number)}" if math.isfinite(number) else "expected a finite number"
    raise HyperparamError(f"{where} is {shown(value)}, a string; {fix}")


def refuse_non_finite(value: Any, where: str, seen: set[int] | None = None) -> None:
    """Refuse an infinity or NaN anywhere in ``value`` (mappings and lists walked, each object once).

    ``seen`` holds the ids of the containers walked: YAML aliases share
    objects, so an alias bomb is walked once per distinct list.

    Raises:
        HyperparamError: ``{where}.KEY[INDEX] is nan; expected a finite number``,
            or ``value`` nested past Python's recursion limit (named at ``where``).
    """
    try:
        _refuse_non_finite(value, where, set() if seen is None else seen)
    except RecursionError as e:  # named where the walk began: the path to the depth is thousands of keys
        raise HyperparamError(f"{where} is nested too deeply to be a hyperparameter") from e


def _refuse_non_finite(value: Any, where: str, seen: set[int]) -> None:
    if isinstance(value, float) and not math.isfinite(value):
        raise HyperparamError(f"{where} is {shown(value)}; expected a finite number")
    if not isinstance(value, dict | list | tuple) or id(value) in seen:
        return
    seen.add(id(value))
    items = value.items() if isinstance(value, dict) else enumerate(value)
    for key, item in items:
        _refuse_non_finite(item, f"{where}.{key}" if isinstance(value, dict) else f"{where}[{key}]", seen)


#: Real-valued stable-baselines3 settings: (low, low allowed, high, high allowed, None allowed).
ALGO_REALS: dict[str, tuple[float, bool, float, bool, bool]] = {
    "learning_rate": (0.0, False, math.inf, False, False),
    "gamma": (0.0, False, 1.0, True, False),
    "tau": (0.0, False, 1.0, True, False),
    "gae_lambda": (0.0, True, 1.0, True, False),
    "clip_range": (0.0, False, math.inf, False, False),
    "clip_range_vf": (0.0, False, math.inf, False, True),
    "max_grad_norm": (0.0, False, math.inf, False, False),
    "ent_coef": (0.0, True, math.inf, False, False),
    "vf_coef": (0.0, True, math.inf, False, False),
    "target_kl": (0.0, False, math.inf, False, True),
    "target_policy_noise": (0.0, True, math.inf, False, False),
    "target_noise_clip": (0.0, True, math.inf, False, False),
}


#: Keys of :data:`ALGO_REALS` that may be rl-zoo3's schedule ``lin_<x>`` (from x down to 0).
SCHEDULES = ("learning_rate", "clip_range", "clip_range_vf")


def _in_range(number: float | None, key: str) -> bool:
    low, low_ok, high, high_ok, _ = ALGO_REALS[key]
    return (
        number is not None
        and math.isfinite(number)
        and (low < number or (low_ok and low == number))
        and (number < high or (high_ok and high == number))
    )


def _expected(key: str) -> str:
    """What ``key`` of :data:`ALGO_REALS` takes, for the message: ``a number in (0, 1]``."""
    low, low_ok, high, high_ok, none_ok = ALGO_REALS[key]
    if math.isinf(high):
        text = f"a finite number {'>=' if low_ok else '>'} {low:g}"
    else:
        text = f"a number in {'[' if low_ok else '('}{low:g}, {high:g}{']' if high_ok else ')'}"
    if key in SCHEDULES:
        text += ", or lin_<x> with such an x (a schedule from x down to 0)"
    if key == "ent_coef":
        text += ", or (SAC) auto or auto_<x> with x a finite number > 0"
    return text + (", or null" if none_ok else "")


def schedule_start(value: str) -> float | None:
    """The x of rl-zoo3's schedule ``lin_<x>``; ``None`` if ``value`` is not one."""
    kind, _, initial = value.partition("_")
    return as_number(initial) if kind == "lin" else None


def check_real(value: Any, key: str, where: str) -> None:
    """Refuse ``value`` of ``key`` (:data:`ALGO_REALS`) out of range, infinite, NaN or not a number."""
    if value is None and ALGO_REALS[key][4]:
        return
    if isinstance(value, str) and key in SCHEDULES:
        number = schedule_start(value)
    elif isinstance(value, str) and key == "ent_coef" and value.partition("_")[0] == "auto":
        initial = value.partition("_")[2]
        number = as_number(initial) if initial else 1.0
        number = number if number is None or number > 0 else None
    else:
        number = None if isinstance(value, str) else as_number(value)
    if not _in_range(number, key):
        raise HyperparamError(f"{where}.{key} is {shown(value)}; expected {_expected(key)}")


#: stable-baselines3 settings that count something and must be at least 1 (SB3 takes 0
#: and trains on nothing: ``batch_size: 0`` trained and saved a model), with what they count.
ALGO_COUNTS = {
    "batch_size": "samples per gradient step",
    "buffer_size": "transitions the replay buffer holds",
    "n_steps": "env steps per rollout",
    "n_epochs": "passes over each rollout",
    "policy_delay": "critic updates per actor update",
    "target_update_interval": "env steps between target updates",
}


def check_train_freq(kwargs: dict[str, Any], where: str) -> None:
    """Refuse a ``train_freq`` not ``n`` or ``[n, step|episode]``, a ``gradient_steps`` < 1 (not -1)."""
    if "train_freq" in kwargs:
        freq = kwargs["train_freq"]
        n, unit = (freq[0], freq[1]) if isinstance(freq, list | tuple) and len(freq) == 2 else (freq, "step")
        if not (_whole(n) and n >= 1 and unit in ("step", "episode")):
            raise HyperparamError(
                f"{where}.train_freq is {shown(freq)}; expected a whole number >= 1, "
                "or [n, step] or [n, episode]"
            )
    if "gradient_steps" in kwargs:
        steps = kwargs["gradient_steps"]
        if not (_whole(steps) and (steps >= 1 or steps == -1)):
            raise HyperparamError(
                f"{where}.gradient_steps is {shown(steps)}; expected a whole number >= 1, "
                "or -1 (as many as env steps collected)"
            )


def _whole(value: Any) -> bool:
    """``value`` is an int (not a bool)."""
    return isinstance(value, int) and not isinstance(value, bool)


def net_arch_problem(layers: Any) -> bool:
    """``layers`` is not a list of 1 to :data:`MAX_LAYERS` widths, whole numbers in [1, MAX_LAYER_WIDTH]."""
    return (
        not isinstance(layers, list)
        or len(layers) > MAX_LAYERS
        or any(not _whole(w) or not 1 <= w <= MAX_LAYER_WIDTH for w in layers)
    )


def check_net_arch(net_arch: Any, where: str) -> None:
    """SB3's ``net_arch``: a list of layer widths, or a mapping of such lists (``pi``, ``qf``, ``vf``).

    Raises:
        HyperparamError: A width that is not a whole number >= 1 (torch
            failed on a negative one with a 47-line traceback) or wider than
            :data:`MAX_LAYER_WIDTH` (torch asked for 72 GB), or more than
            :data:`MAX_LAYERS` layers.
    """
    if net_arch is None:  # SB3's default network
        return
    groups = list(net_arch.values()) if isinstance(net_arch, dict) else [net_arch]
    if any(net_arch_problem(layers) for layers in groups):
        raise HyperparamError(
            f"{where} is {shown(net_arch)}; expected layer widths, whole numbers >= 1 and at most "
            f"{MAX_LAYER_WIDTH}, at most {MAX_LAYERS} layers (a list, or a mapping of pi, qf or vf to lists)"
        )


def check_numbers(
    values: dict[str, Any],
    extras: dict[str, Any],
    env_kwargs: dict[str, Any],
    eval_kwargs: dict[str, Any],
    legacy: dict[str, Any],
    callbacks: tuple[tuple[type, dict[str, Any]], ...],
    where: str,
) -> None:
    """Refuse a number YAML read as text (``9e-1``) and an infinity or NaN, anywhere in an entry."""
    for key in ("n_envs", "noise_std"):
        if key in extras:
            refuse_number_string(extras[key], f"{where}.{key}")
    for key, value in eval_kwargs.items():
        refuse_number_string(value, f"{where}.{key if key in legacy else IN_CALLBACK + key}")
    for key, value in values.items():
        refuse_number_string(value, f"{where}.{key}")
    seen: set[int] = set()
    refuse_non_finite(extras.get("noise_std"), f"{where}.noise_std", seen)
    refuse_non_finite(env_kwargs, f"{where}.env_kwargs", seen)
    for key, value in eval_kwargs.items():
        refuse_non_finite(value, f"{where}.{key if key in legacy else IN_CALLBACK + key}", seen)
    for cls, kwargs in callbacks:
        refuse_non_finite(kwargs, f"{where}.callback.{cls.__name__}", seen)
