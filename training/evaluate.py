"""Evaluation of a policy or the scripted expert: success, distance, return, stalls."""

from __future__ import annotations

import contextlib
import json
import math
import os
from collections.abc import Callable, Iterator, Sequence
from dataclasses import asdict, dataclass
from pathlib import Path
from typing import Any

import gymnasium as gym
import numpy as np

from bioscara_gym.errors import MetadataError
from bioscara_gym.fsutil import atomic_write_text, folders_made_for, replaced_path, temporary_beside
from bioscara_gym.tasks import Policy, task_of
from bioscara_gym.training.extras import needed_by
from bioscara_gym.training.metadata import (
    PolicyShapes,
    check_metadata,
    check_policy_shapes,
    env_kwargs_problem,
    read_metadata,
)

#: The callback told of each finished episode: (success, steps).
EpisodeLog = Callable[[bool, int], None]


@dataclass(frozen=True)
class EvalStats:
    """Aggregate results over ``episodes`` evaluation episodes."""

    episodes: int
    success_rate: float
    mean_final_distance: float
    mean_return: float
    std_return: float
    mean_length: float
    stalls: int

    def as_dict(self) -> dict[str, float | int]:
        """Plain dict for JSON."""
        return asdict(self)

    @classmethod
    def over(cls, results: Sequence[EpisodeResult]) -> EvalStats:
        """The aggregate of some episodes' results (at least one)."""
        successes = sum(r.success for r in results)
        returns = [r.total for r in results]
        return cls(
            episodes=len(results),
            success_rate=successes / len(results),
            mean_final_distance=float(np.mean([r.distance for r in results])),
            mean_return=float(np.mean(returns)),
            std_return=float(np.std(returns)),
            mean_length=float(np.mean([r.steps for r in results])),
            stalls=sum(r.stalled for r in results),
        )


@dataclass(frozen=True)
class EpisodeResult:
    """One evaluation episode: its last step's ``info`` verdicts, its return and length."""

    success: bool
    stalled: bool
    distance: float
    total: float
    steps: int

    @classmethod
    def ended(cls, info: dict[str, Any], total: float, steps: int) -> EpisodeResult:
        """The result of an episode whose last step returned ``info``."""
        return cls(
            success=bool(info.get("is_success", False)),
            stalled=bool(info.get("stalled", False)),
            distance=float(info.get("distance", math.nan)),
            total=total,
            steps=steps,
        )


def stopped_after(results: Sequence[EpisodeResult], max_failures: int | None) -> int | None:
    """After how many of ``results`` an evaluation allowing ``max_failures`` failures stops.

    That is at the episode that fails once more than ``max_failures``; None
    if none of ``results`` does (or ``max_failures`` is None).
    """
    if max_failures is None:
        return None
    failures = 0
    for k, result in enumerate(results):
        failures += not result.success
        if failures > max_failures:
            return k + 1
    return None


def run_episodes(
    env: gym.Env,
    policy: Policy,
    episodes: int,
    seed: int = 0,
    on_reset: Callable[[], None] | None = None,
    on_frame: Callable[[np.ndarray], None] | None = None,
    video_episodes: int | None = None,
    max_failures: int | None = None,
) -> EvalStats:
    """The stats of ``episodes`` seeded episodes (seeds ``seed``, ``seed+1``, ...): :func:`play_episodes`."""
    return EvalStats.over(
        play_episodes(env, policy, episodes, seed, on_reset, on_frame, video_episodes, max_failures)
    )


def play_episodes(
    env: gym.Env,
    policy: Policy,
    episodes: int,
    seed: int = 0,
    on_reset: Callable[[], None] | None = None,
    on_frame: Callable[[np.ndarray], None] | None = None,
    video_episodes: int | None = None,
    max_failures: int | None = None,
    on_episode: EpisodeLog | None = None,
) -> list[EpisodeResult]:
    """Run ``episodes`` seeded episodes (seeds ``seed``, ``seed+1``, ...); their results in order.

    Args:
        env: The env (``render_mode="rgb_array"`` if ``on_frame`` is given).
        policy: Maps an observation to an action.
        episodes: How many episodes.
        seed: Seed of the first episode.
        on_reset: Called after each reset (e.g. to reset a stateful expert).
        on_frame: If given, receives the rendered frame of every step (streamed,
            so a long evaluation does not hold its video in memory).
        video_episodes: Render only the first this many episodes (all if ``None``):
            headless software rendering costs far more than simulating.
        max_failures: Stop after the episode that fails once more than this
            (a target out of reach); the results are of the episodes run.
        on_episode: Told of each finished episode: its success and steps.
    """
    if episodes < 1:
        raise ValueError(f"episodes must be >= 1, got {episodes}")
    results: list[EpisodeResult] = []
    for ep in range(episodes):
        obs, info = env.reset(seed=seed + ep)
        if on_reset is not None:
            on_reset()
        record = on_frame if video_episodes is None or ep < video_episodes else None
        if record is not None:
            record(env.render())
        total, steps, done = 0.0, 0, False
        while not done:
            obs, reward, terminated, truncated, info = env.step(policy(obs))
            total += float(reward)
            steps += 1
            done = terminated or truncated
            if record is not None:
                record(env.render())
        results.append(EpisodeResult.ended(info, total, steps))
        if on_episode is not None:
            on_episode(results[-1].success, steps)
        if stopped_after(results, max_failures) is not None:
            break
    return results


def make_eval_env(
    metadata: dict[str, Any], backend: str | None = None, render: bool = False, **overrides: Any
) -> gym.Env:
    """The env a policy was trained on, optionally on another backend."""
    kwargs = dict(metadata.get("env_kwargs", {}))
    if backend is not None:
        kwargs["backend"] = backend
    kwargs["render_mode"] = "rgb_array" if render else None  # how training rendered is not the policy's
    kwargs.update(overrides)
    env_id = metadata["env_id"]
    try:
        problem = env_kwargs_problem(env_id, kwargs)
        if problem is None:
            return gym.make(env_id, **kwargs)
    except gym.error.Error as e:
        raise MetadataError(f"policy's env {env_id!r} cannot be made: {e}") from e
    raise MetadataError(f"the policy's env_kwargs (metadata.json) {problem}")


def evaluate_model(
    model_path: Path,
    episodes: int = 100,
    backend: str | None = None,
    video: Path | None = None,
    seed: int = 10_000,
    video_episodes: int = 3,
    backend_options: dict[str, Any] | None = None,
) -> EvalStats:
    """Evaluate a trained policy on its env (refusing a metadata mismatch).

    The video, if asked for, shows the first ``video_episodes`` episodes;
    ``backend_options`` go to the backend (e.g. ``record``, docs/traces.md).
    """
    with needed_by("eval --model"):  # needs the [train] extra: fail early
        from bioscara_gym.training.algos import load_model, sb3_policy

    metadata = read_metadata(Path(model_path))
    overrides = {} if backend_options is None else {"backend_options": backend_options}
    env = make_eval_env(metadata, backend, render=video is not None, **overrides)
    with closed_at_the_end(env):
        check_metadata(metadata, env, metadata["env_id"])
        model, _ = load_model(Path(model_path))
        shapes = PolicyShapes.of_spaces(model.observation_space, model.action_space, f"model {model_path}")
        check_policy_shapes(shapes, env)
        with video_writer(video, fps=int(env.metadata.get("render_fps", 25))) as on_frame:
            return run_episodes(
                env, sb3_policy(model), episodes, seed, on_frame=on_frame, video_episodes=video_episodes
            )


@contextlib.contextmanager
def closed_at_the_end(env: gym.Env) -> Iterator[gym.Env]:
    """Close ``env`` (the arm shut down) however the block ends.

    A Ctrl-C or other stop signal is noted in the bus trace, if one is recorded, where
    it lands (``signals_noted``), so the replay stops where this evaluation
    stopped (docs/traces.md). Noted only here, on its way out, it came too
    late when stopped in the start-up: the arm's failed configure or
    activate disables the joints before it re-raises, and those
    transactions came before the signal line (seen: the replay failed).
    """
    from bioscara_gym.hardware.recording import note_signal, signals_noted

    backend = getattr(env.unwrapped, "backend", None)
    with signals_noted(backend):
        try:
            yield env
        except KeyboardInterrupt as e:  # raised by no signal's handler: noted here
            note_signal(backend, e)
            raise
        finally:
            env.close()


def load_model(path: Path) -> tuple[Any, dict[str, Any]]:
    """:func:`bioscara_gym.training.algos.load_model`, imported on use (it needs the [train] extra)."""
    from bioscara_gym.training.algos import load_model as load

    return load(Path(path))


def sb3_policy(model: Any) -> Policy:
    """:func:`bioscara_gym.training.algos.sb3_policy`, imported on use."""
    from bioscara_gym.training.algos import sb3_policy as policy

    return policy(model)


def evaluate_expert(
    env_id: str,
    episodes: int = 100,
    backend: str = "sim",
    video: Path | None = None,
    seed: int = 10_000,
    video_episodes: int = 3,
    **env_kwargs: Any,
) -> EvalStats:
    """Evaluate the scripted expert of ``env_id`` (video: the first ``video_episodes``).

    ``env_kwargs`` go to ``gym.make`` (``backend_options={"record": ...}`` records the bus).
    """
    env = gym.make(env_id, backend=backend, render_mode="rgb_array" if video else None, **env_kwargs)
    with closed_at_the_end(env):
        expert = task_of(env).make_expert(env.unwrapped)
        with video_writer(video, fps=int(env.metadata.get("render_fps", 25))) as on_frame:
            return run_episodes(
                env, expert, episodes, seed, expert.reset, on_frame=on_frame, video_episodes=video_episodes
            )


#: Suffixes :func:`video_writer` writes (imageio's ffmpeg formats, and GIF): checked before the episodes.
VIDEO_SUFFIXES = (".mp4", ".mkv", ".mov", ".avi", ".webm", ".gif")


def _writer_settings(suffix: str, fps: int) -> dict[str, Any]:
    """The imageio writer's settings for a video file ending in ``suffix``.

    ffmpeg's default codec (H.264) fits all but WebM, which takes VP8, VP9 or
    AV1 only (seen: 13 lines of ffmpeg's errors and a broken pipe); a GIF is
    written by Pillow, which takes a frame's duration in ms, not ``fps``.
    """
    if suffix == ".gif":
        return {"duration": 1000.0 / fps, "loop": 0}
    if suffix == ".webm":
        return {"fps": fps, "codec": "libvpx-vp9", "output_params": ["-crf", "32", "-b:v", "0"]}
    return {"fps": fps}


@contextlib.contextmanager
def video_writer(path: Path | None, fps: int) -> Iterator[Callable[[np.ndarray], None] | None]:
    """Stream frames into an MP4 (or GIF, by suffix) through imageio.

    Yields a frame sink (``None`` when ``path`` is ``None``). The video is
    written to a temporary file beside ``path`` and moved into place only when
    the block completes, so an interrupted evaluation leaves no broken video,
    nor the folders made for it (seen: ``--video nd1/a/b/v.mp4`` left ``nd1/a/b/``).
    """
    if path is None:
        yield None
        return
    import imageio.v2 as imageio

    path = replaced_path(path)
    with folders_made_for(path.parent):
        fd, tmp = temporary_beside(path, prefix=f".{path.stem}.", suffix=path.suffix)  # path's mode
        os.close(fd)
        try:
            with imageio.get_writer(tmp, **_writer_settings(path.suffix.lower(), fps)) as writer:
                yield writer.append_data
            os.replace(tmp, path)
        finally:
            Path(tmp).unlink(missing_ok=True)


def write_json(path: Path, stats: EvalStats, **extra: Any) -> None:
    """Write the stats (plus ``extra``) as JSON, atomically."""
    atomic_write_text(Path(path), json.dumps({**stats.as_dict(), **extra}, indent=2) + "\n")
