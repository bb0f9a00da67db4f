"""A training run's files: its state, its checkpoints, its model; listed, loaded and saved in one way.

``OUT/train_state.json`` says what a run is (env, method, seed, budget,
config, demonstrations): :func:`write_run_state` writes it once the model is
built, :func:`read_run_state` checks it for ``--resume``, and
:func:`check_no_run` keeps a new run out of a folder that holds one. A checkpoint is
``OUT/checkpoints/ckpt_<env steps>_steps.zip`` plus its method's companion
files beside it (the replay buffer, DAgger's aggregate). Every file is
written atomically (:mod:`bioscara_gym.fsutil`), the companions before the
model, so a checkpoint exists only once complete and an interrupted save
leaves the earlier ones as they were. :func:`load_newest` loads the newest
checkpoint that loads, skipping a damaged one with a
:class:`~bioscara_gym.errors.CheckpointWarning`; :func:`check_checkpoint_policies`
first refuses a checkpoint of another algorithm than the run's.
"""

from __future__ import annotations

import base64
import io
import json
import pickle
import re
import warnings
import zipfile
from collections.abc import Callable, Mapping
from pathlib import Path
from typing import Any, BinaryIO, TypeVar

from bioscara_gym.errors import CheckpointWarning, TrainingError
from bioscara_gym.fsutil import atomic_open, atomic_write_bytes, atomic_write_text, read_json

#: The run's state file in its output directory (what ``--resume`` reads).
STATE_NAME = "train_state.json"
#: Where a run's checkpoints go, inside its output directory.
CHECKPOINT_DIR = "checkpoints"
#: A checkpoint's file name; the group is its env step count.
CHECKPOINT_RE = re.compile(r"ckpt_(\d+)_steps\.zip$")
#: The largest seed: numpy seeds its generators with 32 bits (``--seed``, ``train_state.json``).
SEED_MAX = 2**32 - 1
#: The keys of ``train_state.json`` and their JSON types (``None``: may be null).
STATE_KEYS: dict[str, tuple[type | None, ...]] = {
    "env_id": (str,),
    "algo": (str,),
    "seed": (int,),
    "total_timesteps": (int,),
    "config": (str, None),
    "demos": (str, None),
}
#: What loading a damaged checkpoint raises (SB3 turns a broken zip into ValueError).
CHECKPOINT_ERRORS = (
    OSError,
    EOFError,
    ValueError,
    KeyError,
    RuntimeError,
    zipfile.BadZipFile,
    pickle.UnpicklingError,
)
#: Members every stable-baselines3 model zip holds.
MODEL_MEMBERS = frozenset({"data", "policy.pth"})
#: What a run leaves in its output directory that a new run there would overwrite or mix with its own
#: (its TensorBoard logs, ``tb/run_<n>``, are numbered and kept apart; a ``metadata.json`` without
#: its model describes nothing to lose).
RUN_FILES = (STATE_NAME, CHECKPOINT_DIR, "model.zip")

T = TypeVar("T")


# ------------------------------------------------------------------ run state
def write_run_state(out: Path, state: Mapping[str, Any]) -> None:
    """Write ``out/train_state.json`` (``out`` created): the first file a run writes."""
    out.mkdir(parents=True, exist_ok=True)
    atomic_write_text(out / STATE_NAME, json.dumps(dict(state), indent=2))


def check_no_run(out: Path) -> None:
    """Refuse a new run into ``out`` when it holds a run: nothing of an earlier run is lost or mixed in.

    Seen (a hostile test): a new run rewrote ``train_state.json`` and kept
    the earlier run's checkpoints, so ``--resume`` continued a seed-1 SAC
    checkpoint as the seed-2 run, or as a TD3 run (a traceback).

    Raises:
        TrainingError: ``out`` holds any of :data:`RUN_FILES` (named, with what to do instead).
    """
    held = [name for name in RUN_FILES if (out / name).exists() or (out / name).is_symlink()]
    if held:
        names = ", ".join(f"{name}/" if name == CHECKPOINT_DIR else name for name in held)
        raise TrainingError(
            f"--out {out} already holds a run ({names}); continue it with --resume, "
            "or train a new one with another --out"
        )


def read_run_state(out: Path) -> dict[str, Any]:
    """``out/train_state.json``, checked: every key of :data:`STATE_KEYS`, of its type and range.

    Raises:
        TrainingError: Missing, unreadable, not JSON, not an object, or a
            key missing, of the wrong type or out of range; the message names file and key.
    """
    path = out / STATE_NAME
    if not path.exists():
        raise TrainingError(f"nothing to resume in {out}: no {STATE_NAME}")
    try:
        state = read_json(path)
    except (OSError, ValueError) as e:  # UnicodeDecodeError and JSONDecodeError are ValueErrors
        raise TrainingError(f"cannot resume from {path}: not readable JSON ({e})") from e
    if not isinstance(state, dict):
        raise TrainingError(f"cannot resume from {path}: expected a JSON object, got {type(state).__name__}")
    for key, types in STATE_KEYS.items():
        if key not in state:
            raise TrainingError(f"cannot resume from {path}: key {key!r} is missing")
        value = state[key]
        if not any(value is None if t is None else isinstance(value, t) for t in types) or isinstance(
            value, bool
        ):
            expected = " or ".join("null" if t is None else t.__name__ for t in types)
            raise TrainingError(f"cannot resume from {path}: {key} is {value!r}; expected {expected}")
    if state["total_timesteps"] < 1:
        total = state["total_timesteps"]
        raise TrainingError(f"cannot resume from {path}: total_timesteps is {total}; expected >= 1")
    if not 0 <= state["seed"] <= SEED_MAX:
        raise TrainingError(f"cannot resume from {path}: seed is {state['seed']}; expected 0 to {SEED_MAX}")
    return state


# ---------------------------------------------------------------- checkpoints
def checkpoint_dir(out: Path) -> Path:
    """The run's checkpoint directory."""
    return out / CHECKPOINT_DIR


def companion_path(checkpoint: Path, suffix: str) -> Path:
    """A file saved with ``checkpoint``: ``ckpt_<n>_steps<suffix>`` beside it."""
    return checkpoint.with_name(checkpoint.stem + suffix)


def list_checkpoints(directory: Path) -> list[Path]:
    """The checkpoints in ``directory``, newest (most steps) first."""
    found = [
        (int(m.group(1)), p)
        for p in directory.glob("ckpt_*_steps.zip")
        if (m := CHECKPOINT_RE.search(p.name))
    ]
    return [p for _, p in sorted(found, reverse=True)]


def checkpoint_steps(checkpoint: Path) -> int:
    """The env steps a checkpoint had taken, from its name."""
    match = CHECKPOINT_RE.search(checkpoint.name)
    if match is None:
        raise ValueError(f"{checkpoint.name} is not a checkpoint's name")
    return int(match.group(1))


def newest_checkpoint(directory: Path) -> Path | None:
    """The checkpoint with the most steps in ``directory``."""
    found = list_checkpoints(directory)
    return found[0] if found else None


def save_model(model: Any, path: Path) -> None:
    """``model.save(path)``, atomically: ``path`` is either the old file or the whole new one."""
    buffer = io.BytesIO()
    model.save(buffer)
    atomic_write_bytes(path, buffer.getvalue())


#: A companion file's writer: given the open (atomic) file, writes it.
Writer = Callable[[BinaryIO], None]


def save_checkpoint(
    model: Any, directory: Path, steps: int, companions: Mapping[str, Writer] | None = None
) -> Path:
    """Save ``model`` as ``ckpt_<steps>_steps.zip``, each companion (suffix to writer) first.

    Every file is written atomically, the companions before the model: a
    checkpoint exists only once complete.
    """
    directory.mkdir(parents=True, exist_ok=True)
    path = directory / f"ckpt_{steps}_steps.zip"
    for suffix, write in (companions or {}).items():
        with atomic_open(companion_path(path, suffix)) as f:
            write(f)
    save_model(model, path)
    return path


def load_newest(directory: Path, load: Callable[[Path], T]) -> tuple[T, Path]:
    """``load`` of the newest checkpoint in ``directory`` that loads, and its path.

    ``load`` is given a checkpoint whose zip is whole (:func:`check_model_zip`)
    and loads it with its companions. A damaged checkpoint (truncated, not a
    zip, a companion unreadable or missing) is skipped with a
    :class:`~bioscara_gym.errors.CheckpointWarning` naming it and the one used instead.

    Raises:
        TrainingError: No checkpoint, none that loads, or one reached that is
            not a regular file (a FIFO would block its reader).
    """
    found = list_checkpoints(directory)
    if not found:
        raise TrainingError(f"nothing to resume in {directory}: no checkpoint")
    failures: list[tuple[Path, BaseException]] = []
    for path in found:
        check_regular_files(path)
        try:
            check_model_zip(path)
            loaded = load(path)
        except CHECKPOINT_ERRORS as e:
            failures.append((path, e))
            continue
        if failures:
            newest, error = failures[0]
            warnings.warn(
                f"checkpoint {newest} cannot be loaded ({reason(error)}); resuming from {path.name} instead",
                CheckpointWarning,
                stacklevel=2,
            )
        return loaded, path
    newest, error = failures[0]
    more = f" nor the {len(found) - 1} older ones" if len(found) > 1 else ""
    raise TrainingError(f"cannot resume: checkpoint {newest} cannot be loaded ({reason(error)}){more}")


def checkpoint_policy(checkpoint: Path) -> type | None:
    """The policy class a checkpoint's model was saved with; ``None`` if it cannot be read.

    Read from the zip's ``data`` as stable-baselines3 reads it when loading
    (its ``policy_class``, pickled); a checkpoint that does not say is left
    to :func:`load_newest`, which names it as damaged.
    """
    try:
        with zipfile.ZipFile(checkpoint) as archive:
            policy = json.loads(archive.read("data"))["policy_class"]
        found = pickle.loads(base64.b64decode(policy[":serialized:"].encode()))
    except (*CHECKPOINT_ERRORS, TypeError, AttributeError, ImportError):
        return None
    return found if isinstance(found, type) else None


def check_checkpoint_policies(directory: Path, policy_base: type, run: str) -> None:
    """Refuse to resume when a checkpoint in ``directory`` holds a policy that is not a ``policy_base``.

    Loading it as the run's algorithm failed deep inside stable-baselines3
    (seen: ``AttributeError: 'SACGoalErrorPolicy' object has no attribute
    'actor_target'``, a SAC checkpoint under a TD3 run's state), or would
    continue another run. ``run`` says in the message whose policy that is
    (``TD3, the algorithm of this td3 run``).

    Raises:
        TrainingError: The first such checkpoint, its policy class and the run's algorithm named.
    """
    for path in list_checkpoints(directory):
        check_regular_files(path)
        policy = checkpoint_policy(path)
        if policy is not None and not issubclass(policy, policy_base):
            raise TrainingError(
                f"cannot resume from {path}: its policy is {policy.__module__}.{policy.__qualname__}, "
                f"not a {policy_base.__qualname__} ({run}); the checkpoint is another run's"
            )


def check_regular_files(checkpoint: Path) -> None:
    """Refuse a checkpoint, or a companion file beside it, that is not a regular file.

    A FIFO would block the load until something writes to it (seen: a hang);
    a device such as ``/dev/zero`` would fill the memory.

    Raises:
        TrainingError: One of them exists and is not a regular file (a symlink to one is).
    """
    for path in (checkpoint, *sorted(checkpoint.parent.glob(checkpoint.stem + "_*"))):
        if path.exists() and not path.is_file():
            raise TrainingError(f"cannot resume from {path}: not a regular file")


def check_model_zip(path: Path) -> None:
    """Refuse a checkpoint that is not a whole model zip, before anything is unpickled.

    A truncated one may still open as a zip: the torch archive stored inside
    it has a directory of its own, which :mod:`zipfile` then finds.

    Raises:
        zipfile.BadZipFile: Not a zip, a member's CRC is wrong, or a model's members are missing.
    """
    with zipfile.ZipFile(path) as archive:
        missing = MODEL_MEMBERS - set(archive.namelist())
        if missing:
            raise zipfile.BadZipFile(f"no {', '.join(sorted(missing))} in it (truncated?)")
        bad = archive.testzip()
    if bad is not None:
        raise zipfile.BadZipFile(f"{bad} is corrupt")


def reason(error: BaseException) -> str:
    """A one-line reason for a failed load."""
    text = str(error).splitlines()[0] if str(error) else ""
    return f"{type(error).__name__}: {text}" if text else type(error).__name__
