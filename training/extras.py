"""Optional dependencies: an import of a missing extra becomes a one-line install hint.

``bioscara train``, evaluating an SB3 model, exporting and demonstration
datasets need the ``[train]`` extra (torch, stable-baselines3, Minari);
running an ONNX policy needs ``[onnx]`` (onnxruntime). Wrap their imports::

    with needs_train():
        import torch
"""

from __future__ import annotations

import contextlib
from collections.abc import Iterator

from bioscara_gym.errors import MissingExtraError

#: Top-level modules of each extra the training package uses (``pyproject.toml``'s extras).
EXTRA_MODULES = {
    "train": ("torch", "stable_baselines3", "tensorboard", "tqdm", "minari"),
    "onnx": ("onnx", "onnxruntime"),
}


@contextlib.contextmanager
def needs_extra(what: str, extra: str) -> Iterator[None]:
    """Turn a missing module of ``extra`` into :class:`MissingExtraError` naming ``what``.

    Any other missing module (something an installed package needs) is
    raised as is, so a broken installation is not hidden.
    """
    try:
        yield
    except ModuleNotFoundError as e:
        if e.name is None or e.name.split(".")[0] not in EXTRA_MODULES[extra]:
            raise
        raise MissingExtraError(what, extra) from e


def needs_train(what: str = "bioscara train") -> contextlib.AbstractContextManager[None]:
    """Imports of torch and stable-baselines3 (``bioscara train``, SB3 models, export)."""
    return needs_extra(what, "train")


@contextlib.contextmanager
def needed_by(what: str) -> Iterator[None]:
    """Name ``what`` (``deploy --model``) in a :class:`MissingExtraError` raised inside.

    The modules that need an extra say so when they are imported, naming
    the command they were written for; the command importing them is the
    one the user ran.
    """
    try:
        yield
    except MissingExtraError as e:
        raise MissingExtraError(what, e.extra) from e


def needs_onnx(what: str = "deploy --onnx") -> contextlib.AbstractContextManager[None]:
    """Imports of onnx and onnxruntime (running or writing an ONNX policy)."""
    return needs_extra(what, "onnx")
