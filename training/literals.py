"""Values of hyperparameter files: Python literals and dotted paths, parsed, never evaluated.

rl-zoo3 writes ``policy_kwargs: "dict(net_arch=[256, 256], activation_fn=nn.ReLU)"``
and names classes by dotted path; :func:`parse_literal_call` reads the first
with :mod:`ast` (literals, nested ``dict(...)`` calls and the names of
:data:`NAMES` only), :func:`import_dotted` imports the second, as rl-zoo3 does.
"""

from __future__ import annotations

import ast
import importlib
from typing import Any

from bioscara_gym.errors import HyperparamError

#: Names a value may use (rl-zoo3 writes ``activation_fn=nn.ReLU``), as ``module:attribute``.
NAMES = {
    "nn.ReLU": "torch.nn:ReLU",
    "nn.Tanh": "torch.nn:Tanh",
    "nn.ELU": "torch.nn:ELU",
    "nn.LeakyReLU": "torch.nn:LeakyReLU",
    "GoalErrorExtractor": "bioscara_gym.training.features:GoalErrorExtractor",
}

#: The action losses of an imitation fit, by name (a DAgger entry's ``loss``; their torch
#: functions: ``imitation.LOSS_FUNCTIONS``). Here, so a config is checked without torch.
ACTION_LOSSES = ("mse", "l1")


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


def import_dotted(name: str, where: str) -> Any:
    """The attribute a dotted path ``package.module.Name`` names (imported, as rl-zoo3 does).

    Raises:
        HyperparamError: Not a dotted path, or nothing importable by that name.
    """
    module, _, attribute = name.rpartition(".")
    if not module or not attribute or module.startswith("."):  # ".foo.Bar" is relative: a TypeError
        raise HyperparamError(f"{where}: {name!r} is not a dotted path package.module.Name")
    try:
        return getattr(importlib.import_module(module), attribute)
    except ImportError as e:
        raise HyperparamError(f"{where}: cannot import {module}: {e}") from e
    except AttributeError as e:
        raise HyperparamError(f"{where}: {module} has no {attribute}") from e
