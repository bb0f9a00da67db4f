"""Tests that kill mutants of training/hyperparam_values.py (docs/mutation.md).

The functions are called directly, with literals from rl-zoo3's format
(``train_freq``: ``n`` or ``[n, "step"|"episode"]``; ``gradient_steps``:
``-1`` for as many as env steps collected; schedules ``lin_<x>``;
``ent_coef: auto`` or ``auto_<x>``), stable-baselines3's ranges as
:data:`ALGO_REALS` states them, and the module's bounds (at most 16 layers of
4096 units). YAML reads ``1e16`` (no dot) as a string: the suggested
spelling must be one it reads as a number.
"""

from __future__ import annotations

import re

import pytest

from bioscara_gym.errors import HyperparamError
from bioscara_gym.training.hyperparam_values import (
    check_net_arch,
    check_numbers,
    check_real,
    check_train_freq,
    net_arch_problem,
    refuse_non_finite,
    refuse_number_string,
)


def refused(call: object, *args: object) -> str:
    """The message ``call(*args)`` refuses with."""
    with pytest.raises(HyperparamError) as info:
        call(*args)  # type: ignore[operator]
    return str(info.value)


# ----------------------------------------------------------- numbers as text
@pytest.mark.parametrize(
    ("text", "write"),
    [("1e16", "1.0e+16"), ("1.5e20", "1.5e+20"), ("9999999999999998", "9999999999999998"), ("9e-1", "0.9")],
)
def test_a_number_written_as_text_gets_a_spelling_yaml_reads_as_a_number(text: str, write: str) -> None:
    assert refused(refuse_number_string, text, "f: E.k") == f"f: E.k is {text!r}, a string; write {write}"


def test_a_nan_inside_a_list_is_named_by_its_index_and_one_in_a_mapping_by_its_key() -> None:
    nan = refused(refuse_non_finite, [1.0, float("nan")], "f: E.k")
    inf = refused(refuse_non_finite, {"a": float("inf")}, "f: E.k")
    assert nan == "f: E.k[1] is nan; expected a finite number"
    assert inf == "f: E.k.a is inf; expected a finite number"


def test_a_value_nested_past_recursion_is_one_line() -> None:
    deep: list = []
    for _ in range(5000):
        deep = [deep]
    assert refused(refuse_non_finite, deep, "f: E.k") == "f: E.k is nested too deeply to be a hyperparameter"


# ----------------------------------------------------------- ranges
@pytest.mark.parametrize("key", ["clip_range_vf", "target_kl"])
def test_null_is_taken_where_sb3_takes_none_and_only_there(key: str) -> None:
    check_real(None, key, "f: E")
    assert refused(check_real, None, "gamma", "f: E") == "f: E.gamma is None; expected a number in (0, 1]"


def test_a_schedule_is_checked_by_its_start() -> None:
    check_real("lin_0.001", "learning_rate", "f: E")
    message = refused(check_real, "lin_-1", "learning_rate", "f: E")
    assert message.startswith("f: E.learning_rate is 'lin_-1'; expected a finite number > 0")


@pytest.mark.parametrize("value", ["auto", "auto_0.1"])
def test_sacs_automatic_entropy_coefficient_is_taken(value: str) -> None:
    check_real(value, "ent_coef", "f: E")


@pytest.mark.parametrize("value", ["auto_0", "auto_x", "autox", "0.1"])
def test_an_automatic_entropy_coefficient_must_start_above_zero(value: str) -> None:
    assert refused(check_real, value, "ent_coef", "f: E").startswith(f"f: E.ent_coef is {value!r}; expected")


# ----------------------------------------------------------- train_freq, gradient_steps
@pytest.mark.parametrize("freq", [1, 4, [1, "step"], [2, "episode"], (3, "step")])
def test_train_freq_is_n_or_n_and_a_unit(freq: object) -> None:
    check_train_freq({"train_freq": freq}, "f: E")


@pytest.mark.parametrize(
    "freq", [0, 1.5, True, [1, "steps"], [0, "step"], ["step", 1], [1, "step", 2], [1], "1"]
)
def test_a_train_freq_that_is_neither_is_refused(freq: object) -> None:
    assert refused(check_train_freq, {"train_freq": freq}, "f: E") == (
        f"f: E.train_freq is {freq!r}; expected a whole number >= 1, or [n, step] or [n, episode]"
    )


@pytest.mark.parametrize(("steps", "taken"), [(1, True), (-1, True), (0, False), (-2, False), (1.0, False)])
def test_gradient_steps_is_at_least_one_or_minus_one(steps: object, taken: bool) -> None:
    if taken:
        check_train_freq({"gradient_steps": steps}, "f: E")
    else:
        assert refused(check_train_freq, {"gradient_steps": steps}, "f: E").startswith(
            f"f: E.gradient_steps is {steps!r}; expected a whole number >= 1, or -1"
        )


# ----------------------------------------------------------- net_arch
@pytest.mark.parametrize(
    ("layers", "problem"),
    [
        ([1], False),
        ([4096], False),
        ([64] * 16, False),
        ([64] * 17, True),
        ([0], True),
        ([4097], True),
        ([64.0], True),
        ((64, 64), True),
    ],
)
def test_a_network_is_1_to_16_layers_of_1_to_4096_units(layers: object, problem: bool) -> None:
    assert net_arch_problem(layers) is problem


def test_each_network_of_a_mapping_is_checked() -> None:
    check_net_arch({"pi": [64, 64], "qf": [256]}, "f: E.net_arch")
    message = refused(check_net_arch, {"pi": [64], "qf": [5000]}, "f: E.net_arch")
    assert message.startswith("f: E.net_arch is {'pi': [64], 'qf': [5000]}; expected layer widths")


# ----------------------------------------------------------- the whole entry
class _Callback:
    """A callback class as ``_split_callbacks`` gives it (only its name is used)."""


@pytest.mark.parametrize(
    ("part", "message"),
    [
        ({"extras": {"n_envs": "2"}}, "f: E.n_envs is '2', a string; write 2"),
        ({"extras": {"noise_std": "1e-1"}}, "f: E.noise_std is '1e-1', a string; write 0.1"),
        ({"extras": {"noise_std": float("nan")}}, "f: E.noise_std is nan; expected a finite number"),
        ({"values": {"gamma": "9e-1"}}, "f: E.gamma is '9e-1', a string; write 0.9"),
        (
            {"env_kwargs": {"goal_radius": float("inf")}},
            "f: E.env_kwargs.goal_radius is inf; expected a finite number",
        ),
        (
            {"eval_kwargs": {"eval_freq": "1e3"}},
            "f: E.callback.SuccessEvalCallback.eval_freq is '1e3', a string; write 1000",
        ),
        (
            {"eval_kwargs": {"eval_freq": "1e3"}, "legacy": {"eval_freq": "1e3"}},
            "f: E.eval_freq is '1e3', a string; write 1000",
        ),
        (
            {"eval_kwargs": {"target_success": float("nan")}},
            "f: E.callback.SuccessEvalCallback.target_success is nan; expected a finite number",
        ),
        (
            {"eval_kwargs": {"target_success": float("nan")}, "legacy": {"target_success": 1}},
            "f: E.target_success is nan; expected a finite number",
        ),
        (
            {"callbacks": ((_Callback, {"every": float("inf")}),)},
            "f: E.callback._Callback.every is inf; expected a finite number",
        ),
    ],
    ids=[
        "n-envs",
        "noise-std-text",
        "noise-std-nan",
        "algo-value",
        "env-kwargs",
        "in-callback",
        "legacy",
        "in-callback-nan",
        "legacy-nan",
        "other-callback",
    ],
)
def test_every_part_of_an_entry_is_checked_and_named(part: dict, message: str) -> None:
    parts = {"values": {}, "extras": {}, "env_kwargs": {}, "eval_kwargs": {}, "legacy": {}, "callbacks": ()}
    parts.update(part)
    with pytest.raises(HyperparamError, match=f"^{re.escape(message)}$"):
        check_numbers(**parts, where="f: E")


def test_an_entry_of_plain_numbers_passes() -> None:
    check_numbers(
        {"gamma": 0.9, "policy_kwargs": "dict(net_arch=[64])"},
        {"n_envs": 1, "noise_std": 0.1},
        {"control_mode": "cartesian"},
        {"eval_freq": 1000},
        {},
        ((_Callback, {"every": 3}),),
        "f: E",
    )
