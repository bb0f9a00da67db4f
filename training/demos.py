"""Demonstrations as Minari datasets: record them (``bioscara collect``) and read them back.

A dataset holds whole episodes of one env, with the env's spec (id and
``gym.make`` keyword arguments), so ``minari.load_dataset(NAME).recover_environment()``
rebuilds the env the episodes were recorded on (after ``import bioscara_gym``).
Datasets live where Minari keeps them: ``$MINARI_DATASETS_PATH``, else
``~/.minari/datasets``. A name without a version (``pickplace-expert``) means
version 0 (``pickplace-expert-v0``), as Minari ids need one.

:func:`collect` records; :func:`load_demos` flattens a dataset into the
transition arrays training uses (:class:`Demos`). Minari is imported only by
them (the ``[train]`` extra).
"""

from __future__ import annotations

import contextlib
import errno
import os
import re
import shutil
import tempfile
import time
import warnings
from collections.abc import Callable, Iterator
from dataclasses import dataclass
from pathlib import Path
from typing import Any

import gymnasium as gym
import numpy as np

import bioscara_gym  # noqa: F401 - registers the tasks (recover_environment needs them)
from bioscara_gym.errors import TrainingError
from bioscara_gym.tasks import GOAL_KEYS, Policy
from bioscara_gym.training.extras import needs_extra
from bioscara_gym.training.signals import SignalGuard

#: Minari's dataset ids: ``(namespace/)name-v<version>``.
VERSION_RE = re.compile(r"-v\d+$")


def dataset_id(name: str) -> str:
    """Minari's id for ``name``: ``name`` itself if versioned, else ``name-v0``.

    Raises:
        TrainingError: An empty name, or one Minari would not accept.
    """
    name = name.strip()
    if not name or name.startswith("/") or name.endswith("/"):
        raise TrainingError(f"dataset name {name!r} is empty or malformed")
    full = name if VERSION_RE.search(name) else f"{name}-v0"
    with _minari() as minari_ids:
        try:
            minari_ids.parse_dataset_id(full)
        except ValueError as e:  # Minari's message repeats the name as it is, newlines and all
            raise TrainingError(
                f"dataset name {name!r} is malformed: expected (namespace/)name(-vN), "
                "of letters, digits, - and _"
            ) from e
    return full


#: What needs Minari, as a missing [train] extra's message names it.
DATASET_USE = "a demonstration dataset (Minari)"


@contextlib.contextmanager
def _minari() -> Iterator[Any]:
    """``minari.dataset.minari_dataset`` (imported on demand, naming the extra if missing)."""
    with needs_extra(DATASET_USE, "train"):
        from minari.dataset import minari_dataset
    yield minari_dataset


def datasets_root() -> Path:
    """Where Minari keeps local datasets (``$MINARI_DATASETS_PATH`` honoured).

    Raises:
        TrainingError: ``$MINARI_DATASETS_PATH`` is set but empty.
    """
    root = os.environ.get("MINARI_DATASETS_PATH")
    if root == "":  # Minari's own reading and writing failed on "" with a message naming nothing
        raise TrainingError("MINARI_DATASETS_PATH is empty: unset it (~/.minari/datasets) or name a folder")
    return Path(root) if root is not None else Path.home() / ".minari" / "datasets"


def dataset_path(name: str) -> Path:
    """The directory of dataset ``name`` (whether or not it exists)."""
    return datasets_root() / dataset_id(name)


def dataset_exists(name: str) -> bool:
    """Whether a dataset of that name is stored locally."""
    return dataset_path(name).exists()


def _size_bytes(path: Path) -> int:
    return sum(p.stat().st_size for p in path.rglob("*") if p.is_file())


@dataclass(frozen=True)
class CollectResult:
    """What :func:`collect` recorded."""

    dataset_id: str
    path: Path
    episodes: int
    steps: int
    success_rate: float
    size_bytes: int
    wall_time_s: float


def collect(
    env_id: str,
    episodes: int,
    name: str,
    policy_factory: Callable[[gym.Env], tuple[Policy, Callable[[], None]]],
    env_kwargs: dict[str, Any] | None = None,
    seed: int = 0,
    overwrite: bool = False,
    progress: bool = True,
    algorithm_name: str = "scripted expert",
    description: str | None = None,
) -> CollectResult:
    """Record ``episodes`` episodes of a policy on ``env_id`` as the Minari dataset ``name``.

    Episodes are seeded ``seed``, ``seed + 1``, ..., every step recorded (to the
    time limit or a stall). Nothing is left behind on failure or interruption:
    the dataset is written beside the others and moved into place only once
    it is complete; an old one (``overwrite``) is removed only after that.

    Args:
        env_id: Registered env id.
        episodes: How many episodes (> 0).
        name: Dataset name (``-v0`` appended if unversioned).
        policy_factory: Given the env, returns the policy and a per-episode reset.
        env_kwargs: ``gym.make`` keyword arguments (stored in the dataset's env spec).
        seed: Seed of the first episode.
        overwrite: Replace an existing dataset of that name.
        progress: Show a progress bar.
        algorithm_name: Who acted, for the dataset's metadata.
        description: The dataset's description (default: env, policy and success).

    Raises:
        TrainingError: ``episodes`` <= 0, or the dataset exists and ``overwrite``
            is false (checked before the episodes, and again when they are written).
    """
    full_id, path = _new_dataset(name, episodes, overwrite)
    with needs_extra("bioscara collect", "train"):
        import minari
    env = gym.make(env_id, **(env_kwargs or {}))
    collector = minari.DataCollector(env, record_infos=False)
    start = time.perf_counter()
    try:
        policy, on_reset = policy_factory(env)
        bar = _progress(episodes, progress, f"collect {full_id}")
        successes, steps = _record(collector, policy, on_reset, episodes, seed, bar)
        success_rate = successes / episodes
        text = description or (
            f"{episodes} episodes of {algorithm_name} on {env_id} ({env_kwargs or {}}); "
            f"success {success_rate:.1%}"
        )
        metadata = {"eval_env": env.spec, "algorithm_name": algorithm_name, "description": text}
        _write_dataset(collector, path, full_id, episodes, overwrite, metadata)
    finally:
        collector.close()  # removes the collector's temporary directory
    size, wall_time_s = _size_bytes(path), time.perf_counter() - start
    return CollectResult(full_id, path, episodes, steps, success_rate, size, wall_time_s)


def _new_dataset(name: str, episodes: int, overwrite: bool) -> tuple[str, Path]:
    """The id and directory of the dataset :func:`collect` is to write, checked.

    Raises:
        TrainingError: ``episodes`` <= 0, or the dataset exists and ``overwrite`` is false.
    """
    if episodes <= 0:
        raise TrainingError(f"episodes must be > 0, got {episodes}")
    full_id = dataset_id(name)
    path = datasets_root() / full_id
    if path.exists() and not overwrite:
        raise TrainingError(f"dataset {full_id} exists at {path}; pass --overwrite to replace it")
    return full_id, path


def _record(
    collector: Any, policy: Policy, on_reset: Callable[[], None], episodes: int, seed: int, bar: Any
) -> tuple[int, int]:
    """Run the seeded episodes through Minari's collector; the successes and the steps."""
    successes, steps = 0, 0
    for ep in range(episodes):
        obs, _ = collector.reset(seed=seed + ep)
        on_reset()
        done, info = False, {}
        while not done:
            obs, _, terminated, truncated, info = collector.step(policy(obs))
            steps += 1
            done = terminated or truncated
        successes += bool(info.get("is_success", False))
        bar.update(1)
        bar.set_postfix(success=f"{successes / (ep + 1):.0%}")
    bar.close()
    return successes, steps


def _write_dataset(
    collector: Any, path: Path, full_id: str, episodes: int, overwrite: bool, metadata: dict[str, Any]
) -> None:
    """Write the recorded episodes (``metadata``: ``create_dataset``'s arguments) as ``full_id`` at ``path``.

    Minari writes into a hidden folder of the root (it lists none), renamed to
    ``path`` once complete. Seen: the old dataset removed first, so an
    interruption left neither; a second ``collect`` into the name replacing
    the first's without ``--overwrite``.

    Raises:
        TrainingError: Without ``overwrite``, a dataset appeared at ``path`` meanwhile (it is kept).
    """
    root = datasets_root()
    staging = Path(tempfile.mkdtemp(dir=root, prefix=".collect-", suffix=".tmp"))
    try:
        with _datasets_path(staging), warnings.catch_warnings():
            warnings.filterwarnings("ignore", message=r"`(author|author_email|code_permalink)` is set")
            collector.create_dataset(dataset_id=full_id, **metadata)
        _adopt_namespaces(staging, root, full_id)
        try:
            _move_into_place(staging / full_id, path, staging / ".replaced", overwrite)
        except OSError as e:
            if e.errno not in (errno.EEXIST, errno.ENOTEMPTY, errno.ENOTDIR):  # others say what failed
                raise
            hint = "" if overwrite else ": pass --overwrite to replace it, or name another dataset"
            raise TrainingError(
                f"dataset {full_id} was written at {path} by another command while these {episodes} "
                f"episodes were recorded; they are not kept{hint}"
            ) from e
    finally:
        shutil.rmtree(staging, ignore_errors=True)  # never a half-written dataset, nor the replaced one


@contextlib.contextmanager
def _datasets_path(root: Path) -> Iterator[None]:
    """``$MINARI_DATASETS_PATH`` set to ``root`` for the block: Minari's only way to write elsewhere."""
    before = os.environ.get("MINARI_DATASETS_PATH")
    os.environ["MINARI_DATASETS_PATH"] = str(root)
    try:
        yield
    finally:
        if before is None:
            del os.environ["MINARI_DATASETS_PATH"]
        else:
            os.environ["MINARI_DATASETS_PATH"] = before


def _adopt_namespaces(staging: Path, root: Path, full_id: str) -> None:
    """Make in ``root`` the namespace folders and metadata of ``full_id`` that Minari made in ``staging``."""
    for level in reversed(Path(full_id).parents[:-1]):  # outermost first
        (root / level).mkdir(exist_ok=True)
        for made in (staging / level).iterdir():
            if made.is_file() and not (root / level / made.name).exists():  # a namespace's own is kept
                shutil.copyfile(made, root / level / made.name)


def _move_into_place(new: Path, path: Path, replaced: Path, overwrite: bool) -> None:
    """Rename the complete dataset ``new`` to ``path``; with ``overwrite`` the old one goes to ``replaced``.

    The stop signals wait for the renames (between them no dataset is at ``path``).
    Without ``overwrite`` nothing is replaced: a rename onto a folder that is not empty fails.

    Raises:
        OSError: A rename failed (``EEXIST``, ``ENOTEMPTY``: something is at ``path``; the old one is kept).
    """
    with SignalGuard() as guard, contextlib.ExitStack() as stack:
        stack.callback(guard.check)  # a signal wins over an error
        with guard.shielded():
            if overwrite:
                with contextlib.suppress(FileNotFoundError):
                    os.rename(path, replaced)
            elif os.path.lexists(path):  # the rename would replace an empty folder
                raise FileExistsError(errno.EEXIST, "exists", os.fspath(path))
            try:
                os.rename(new, path)
            except OSError:
                if os.path.lexists(replaced):
                    with contextlib.suppress(OSError):
                        os.rename(replaced, path)
                raise


def _progress(total: int, enabled: bool, desc: str) -> Any:
    """A tqdm bar (a silent stand-in when disabled)."""
    from tqdm.auto import tqdm

    return tqdm(total=total, desc=desc, unit="ep", disable=not enabled, leave=False)


@dataclass(frozen=True)
class Demos:
    """A dataset's transitions, flattened over episodes (arrays of one row per step).

    Attributes:
        dataset_id: The dataset's id.
        env_id: The env the episodes were recorded on.
        env_kwargs: Its ``gym.make`` keyword arguments.
        obs: ``observation``, ``achieved_goal``, ``desired_goal`` before each step.
        next_obs: The same keys after each step.
        actions: The actions taken.
        dones: Whether the step ended the episode by termination (a stall).
        episode_starts: Row index where each episode begins.
        successes: Whether each episode ended in success.
    """

    dataset_id: str
    env_id: str
    env_kwargs: dict[str, Any]
    obs: dict[str, np.ndarray]
    next_obs: dict[str, np.ndarray]
    actions: np.ndarray
    dones: np.ndarray
    episode_starts: np.ndarray
    successes: np.ndarray

    def __len__(self) -> int:
        """Number of transitions."""
        return len(self.actions)

    @property
    def success_rate(self) -> float:
        """Fraction of the episodes that ended in success."""
        return float(np.mean(self.successes)) if len(self.successes) else 0.0


def load_demos(name: str, env: gym.Env | None = None, successful_only: bool = False) -> Demos:
    """Read dataset ``name`` as transition arrays.

    Args:
        name: Dataset name or id.
        env: If given, refuse a dataset recorded on another task, control mode
            or spaces than this env's.
        successful_only: Keep only the episodes that ended in success.

    Raises:
        TrainingError: No such dataset, a damaged one, not a goal env's dataset, or
            another env than ``env``.
    """
    full_id = dataset_id(name)
    if not (datasets_root() / full_id).exists():
        raise TrainingError(
            f"no dataset {full_id} in {datasets_root()}; record one with "
            f"`bioscara collect --expert --env ENV --dataset {name}`"
        )
    with needs_extra(DATASET_USE, "train"):
        import minari
    try:  # Minari reading its files only: whatever a damaged one makes it raise (OSError, JSON, ...)
        dataset = minari.load_dataset(full_id)
        episodes = list(dataset.iterate_episodes())
    except (OSError, ValueError, KeyError, TypeError, AttributeError, AssertionError) as e:
        why = str(e) or f"Minari's {type(e).__name__}"  # its assertions say nothing
        raise TrainingError(f"dataset {full_id} in {datasets_root()} cannot be read: {why}") from e
    return _read_demos(dataset, episodes, full_id, env, successful_only)


def _read_demos(
    dataset: Any, episodes: list[Any], full_id: str, env: gym.Env | None, successful_only: bool
) -> Demos:
    """:func:`load_demos` once the dataset's episodes are read."""
    spec = dataset.spec.env_spec
    if spec is None:
        raise TrainingError(f"dataset {full_id} has no env spec")
    env_kwargs = dict(spec.kwargs)
    parts: dict[str, list[Any]] = {"obs": [], "next": [], "act": [], "done": [], "start": [], "success": []}
    threshold = float(env_kwargs.get("distance_threshold", 0.01))
    n = 0
    for episode in episodes:
        observations = episode.observations
        if not isinstance(observations, dict) or any(k not in observations for k in GOAL_KEYS):
            raise TrainingError(f"dataset {full_id} is not a goal env's (no {', '.join(GOAL_KEYS)})")
        last = observations["achieved_goal"][-1] - observations["desired_goal"][-1]
        success = bool(np.linalg.norm(last) < threshold) and not bool(episode.terminations[-1])
        if successful_only and not success:
            continue
        parts["obs"].append({k: np.asarray(observations[k][:-1]) for k in GOAL_KEYS})
        parts["next"].append({k: np.asarray(observations[k][1:]) for k in GOAL_KEYS})
        parts["act"].append(np.asarray(episode.actions, dtype=np.float32))
        parts["done"].append(np.asarray(episode.terminations, dtype=bool))
        parts["start"].append(n)
        parts["success"].append(success)
        n += len(episode.actions)
    if not parts["act"]:
        raise TrainingError(f"dataset {full_id} holds no {'successful ' if successful_only else ''}episodes")
    demos = Demos(
        dataset_id=full_id,
        env_id=spec.id,
        env_kwargs=env_kwargs,
        obs={k: np.concatenate([o[k] for o in parts["obs"]]) for k in GOAL_KEYS},
        next_obs={k: np.concatenate([o[k] for o in parts["next"]]) for k in GOAL_KEYS},
        actions=np.concatenate(parts["act"]),
        dones=np.concatenate(parts["done"]),
        episode_starts=np.asarray(parts["start"]),
        successes=np.asarray(parts["success"]),
    )
    if env is not None:
        check_demos(demos, env)
    return demos


def check_demos(demos: Demos, env: gym.Env) -> None:
    """Refuse demonstrations recorded on another task, control mode or spaces than ``env``'s.

    Raises:
        TrainingError: What differs.
    """
    env_id = env.spec.id if env.spec is not None else None
    if env_id is not None and demos.env_id != env_id:
        raise TrainingError(f"dataset {demos.dataset_id} was recorded on {demos.env_id}, not {env_id}")
    unwrapped = env.unwrapped
    for key in ("control_mode", "control_freq"):
        have = getattr(unwrapped, key, None)
        want = demos.env_kwargs.get(key, _default_kwarg(demos.env_id, key))
        if want is not None and have is not None and want != have:
            raise TrainingError(
                f"dataset {demos.dataset_id} was recorded with {key}={want!r}, the env has {key}={have!r}"
            )
    space = env.observation_space
    for key in GOAL_KEYS:
        shape = space[key].shape if isinstance(space, gym.spaces.Dict) and key in space.spaces else None
        if shape != demos.obs[key].shape[1:]:
            raise TrainingError(
                f"dataset {demos.dataset_id}: {key} has shape {demos.obs[key].shape[1:]}, the env's {shape}"
            )
    if demos.actions.shape[1:] != env.action_space.shape:
        raise TrainingError(
            f"dataset {demos.dataset_id}: actions have shape {demos.actions.shape[1:]}, "
            f"the env's {env.action_space.shape}"
        )


def _default_kwarg(env_id: str, key: str) -> Any:
    """The env's default for constructor argument ``key`` (recorded specs omit defaults)."""
    import inspect

    spec = gym.spec(env_id)
    entry = spec.entry_point
    cls = gym.envs.registration.load_env_creator(entry) if isinstance(entry, str) else entry
    param = inspect.signature(cls).parameters.get(key)
    default = spec.kwargs.get(key, param.default if param is not None else None)
    return None if default is inspect.Parameter.empty else default


def rollout_demos(
    env: gym.Env,
    policy: Callable[[dict[str, np.ndarray]], np.ndarray],
    on_reset: Callable[[], None],
    episodes: int,
    seed: int = 0,
    successful_only: bool = True,
) -> Demos:
    """Record ``episodes`` episodes in memory (no dataset), as :func:`load_demos` returns them.

    Used when a run collects the demonstrations it needs itself.

    Raises:
        TrainingError: ``episodes`` <= 0, or no episode is kept.
    """
    if episodes <= 0:
        raise TrainingError(f"episodes must be > 0, got {episodes}")
    kept: list[tuple[Any, ...]] = []  # (obs, action, next obs, terminated) of the episodes kept
    starts, successes = [], []
    for ep in range(episodes):
        obs, _ = env.reset(seed=seed + ep)
        on_reset()
        rows: list[tuple[Any, ...]] = []
        done, info = False, {}
        while not done:
            action = np.asarray(policy(obs), dtype=np.float32)
            nxt, _, terminated, truncated, info = env.step(action)
            rows.append((obs, action, nxt, bool(terminated)))
            obs, done = nxt, terminated or truncated
        success = bool(info.get("is_success", False))
        if successful_only and not success:
            continue
        starts.append(len(kept))
        successes.append(success)
        kept.extend(rows)
    if not kept:
        raise TrainingError(f"none of the {episodes} demonstration episodes succeeded")
    spec = env.spec
    return Demos(
        dataset_id="(collected in memory)",
        env_id=spec.id if spec is not None else "",
        env_kwargs=dict(spec.kwargs) if spec is not None else {},
        obs={k: np.array([row[0][k] for row in kept]) for k in GOAL_KEYS},
        next_obs={k: np.array([row[2][k] for row in kept]) for k in GOAL_KEYS},
        actions=np.array([row[1] for row in kept]),
        dones=np.array([row[3] for row in kept]),
        episode_starts=np.asarray(starts),
        successes=np.asarray(successes),
    )
