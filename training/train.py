"""Train a policy with stable-baselines3 on CPU: ``bioscara train``.

Reads top to bottom: resolve the env and its hyperparameters, build the envs,
build (or resume) the model, learn with periodic success evaluation, early
stop and checkpoints, then save ``model.zip`` next to ``metadata.json``.

Bad input (a key the algorithm does not take, an evaluation schedule or a
budget below 1, a damaged ``train_state.json``, nothing to resume) is refused
with a :class:`~bioscara_gym.errors.TrainingError` before anything is written.
Ctrl-C and SIGTERM save a checkpoint and raise :class:`TrainingInterrupted`;
checkpoints and the model are written atomically, and ``--resume`` skips a
damaged newest checkpoint with a :class:`~bioscara_gym.errors.CheckpointWarning`.
"""

from __future__ import annotations

import contextlib
import io
import json
import pickle
import signal
import time
import warnings
import zipfile
from dataclasses import dataclass
from pathlib import Path
from typing import Any

import gymnasium as gym
import numpy as np

import bioscara_gym  # noqa: F401 - registers the tasks
from bioscara_gym.errors import CheckpointWarning, HyperparamError, TrainingError
from bioscara_gym.fsutil import atomic_open, atomic_write_bytes, atomic_write_text
from bioscara_gym.training.evaluate import run_episodes
from bioscara_gym.training.extras import needs_train
from bioscara_gym.training.hyperparams import (
    Hyperparams,
    check_algo_kwargs,
    default_config_path,
    load_hyperparams,
)
from bioscara_gym.training.metadata import build_metadata, resolve_env_id, save_policy
from bioscara_gym.training.run import (
    CHECKPOINT_RE,
    STATE_NAME,
    TrainArgs,
    TrainingInterrupted,
    TrainResult,
)
from bioscara_gym.training.signals import Interrupted, SignalGuard

with needs_train():
    import torch
    from stable_baselines3 import SAC, HerReplayBuffer
    from stable_baselines3.common.base_class import BaseAlgorithm
    from stable_baselines3.common.callbacks import BaseCallback, CallbackList
    from stable_baselines3.common.env_util import make_vec_env
    from stable_baselines3.common.noise import NormalActionNoise, OrnsteinUhlenbeckActionNoise
    from stable_baselines3.common.off_policy_algorithm import OffPolicyAlgorithm

    from bioscara_gym.training.algos import ALGOS
    from bioscara_gym.training.bc import bc_pretrain
    from bioscara_gym.training.zoo import EVAL_SEED_OFFSET, DemonstrationCallback, SuccessEvalCallback

REPLAY_BUFFERS = {"HerReplayBuffer": HerReplayBuffer}
#: Keys whose value may be one of rl-zoo3's schedule strings ``lin_<initial value>``.
SCHEDULE_KEYS = ("learning_rate", "clip_range", "clip_range_vf")
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


def load_run_hyperparams(args: TrainArgs, env_id: str, config: Path | None = None) -> Hyperparams:
    """The hyperparameters of this run (``config``, else ``args.config``, else the packaged ones).

    ``bc`` reads SAC's. Keys the algorithm does not take are refused here,
    before anything is built.
    """
    name = args.algo or "sac"
    if name not in ALGOS and name != "bc":
        raise TrainingError(f"unknown algo {name!r}; choose one of {', '.join(ALGOS)}, bc, dagger")
    algo = "sac" if name == "bc" else name
    path = Path(config or args.config or default_config_path(algo))
    try:
        hp = load_hyperparams(path, env_id)
        check_algo_kwargs(hp, ALGOS[algo], env_id)
    except HyperparamError as e:
        raise TrainingError(str(e)) from e
    return hp


def read_train_state(out: Path) -> dict[str, Any]:
    """``out/train_state.json``, checked: every key of :data:`STATE_KEYS`, of its type.

    Raises:
        TrainingError: Missing, unreadable, not JSON, not an object, or a
            key missing or of the wrong type; the message names file and key.
    """
    path = out / STATE_NAME
    if not path.exists():
        raise TrainingError(f"nothing to resume in {out}: no {STATE_NAME}")
    try:
        state = json.loads(path.read_text(encoding="utf-8"))
    except (OSError, UnicodeDecodeError, json.JSONDecodeError) as e:
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
    return state


def check_timesteps(timesteps: int | None) -> None:
    """Refuse ``--timesteps`` below 1 (``None``: the config's budget).

    Raises:
        TrainingError: ``timesteps`` is 0 or negative.
    """
    if timesteps is not None and timesteps < 1:
        raise TrainingError(f"--timesteps {timesteps}: must be >= 1 (omit it for the config's n_timesteps)")


class CheckpointEvery(BaseCallback):
    """Save the model (and replay buffer) every ``freq`` env steps."""

    def __init__(self, directory: Path, freq: int) -> None:
        """Checkpoints go to ``directory``."""
        super().__init__()
        self.directory = directory
        self.freq = freq
        self._next = freq

    def _on_training_start(self) -> None:
        self._next = (self.num_timesteps // self.freq + 1) * self.freq

    def _on_step(self) -> bool:
        if self.num_timesteps >= self._next:
            self._next += self.freq
            save_checkpoint(self.model, self.directory)
        return True


def save_checkpoint(model: BaseAlgorithm, directory: Path) -> Path:
    """Save ``model`` (and its replay buffer) as ``ckpt_<steps>_steps.zip``.

    Each file is written atomically (:func:`~bioscara_gym.fsutil.atomic_open`),
    the replay buffer first: a checkpoint exists only once complete, and an
    interrupted save leaves the previous checkpoints as they were.
    """
    directory.mkdir(parents=True, exist_ok=True)
    path = directory / f"ckpt_{model.num_timesteps}_steps.zip"
    if isinstance(model, OffPolicyAlgorithm):
        with atomic_open(replay_path(path)) as f:
            model.save_replay_buffer(f)
    _save_model(model, path)
    return path


def _save_model(model: BaseAlgorithm, path: Path) -> None:
    """``model.save(path)``, atomically: ``path`` is either the old file or the whole new one."""
    buffer = io.BytesIO()
    model.save(buffer)
    atomic_write_bytes(path, buffer.getvalue())


def replay_path(checkpoint: Path) -> Path:
    """The replay buffer saved with ``checkpoint``."""
    return checkpoint.with_name(checkpoint.stem + "_replay.pkl")


def checkpoints(directory: Path) -> list[Path]:
    """The checkpoints in ``directory``, newest (most steps) first."""
    found = [
        (int(m.group(1)), p)
        for p in directory.glob("ckpt_*_steps.zip")
        if (m := CHECKPOINT_RE.search(p.name))
    ]
    return [p for _, p in sorted(found, reverse=True)]


def newest_checkpoint(directory: Path) -> Path | None:
    """The checkpoint with the most steps in ``directory``."""
    found = checkpoints(directory)
    return found[0] if found else None


def load_checkpoint(algo_cls: type[BaseAlgorithm], directory: Path, env: Any) -> tuple[BaseAlgorithm, Path]:
    """The newest checkpoint in ``directory`` that loads, with its replay buffer.

    A damaged checkpoint (truncated, not a zip, its replay buffer unreadable)
    is skipped with a :class:`~bioscara_gym.errors.CheckpointWarning` naming
    it and the one used instead.

    Raises:
        TrainingError: No checkpoint, or none that loads.
    """
    found = checkpoints(directory)
    if not found:
        raise TrainingError(f"nothing to resume in {directory}: no checkpoint")
    failures: list[tuple[Path, BaseException]] = []
    for path in found:
        try:
            _check_checkpoint_zip(path)
            model = algo_cls.load(path, env=env, device="cpu")
            if isinstance(model, OffPolicyAlgorithm) and replay_path(path).exists():
                _load_replay_buffer(model, replay_path(path))
        except CHECKPOINT_ERRORS as e:
            failures.append((path, e))
            continue
        if failures:
            newest, error = failures[0]
            warnings.warn(
                f"checkpoint {newest} cannot be loaded ({_reason(error)}); resuming from {path.name} instead",
                CheckpointWarning,
                stacklevel=2,
            )
        return model, path
    newest, error = failures[0]
    more = f" nor the {len(found) - 1} older ones" if len(found) > 1 else ""
    raise TrainingError(f"cannot resume: checkpoint {newest} cannot be loaded ({_reason(error)}){more}")


def _load_replay_buffer(model: OffPolicyAlgorithm, path: Path) -> None:
    """Load a checkpoint's replay buffer; stable-baselines3's warnings become one line each.

    HER's buffer drops the episode the checkpoint cut short (training
    restarts the env, so it never ends); stable-baselines3 says so in a
    four-line warning that suggests ``truncate_last_trajectory=False``, which
    would be wrong here.
    """
    with warnings.catch_warnings(record=True) as caught:
        warnings.simplefilter("always")
        model.load_replay_buffer(path)
    for warning in caught:
        text = str(warning.message)
        if "last trajectory in the replay buffer will be truncated" in text:
            text = (
                "the episode the checkpoint cut short was dropped from the replay buffer "
                "(HER relabels whole episodes; training starts a new one)"
            )
        warnings.warn(" ".join(text.split()), CheckpointWarning, stacklevel=3)


#: Members every stable-baselines3 model zip holds.
MODEL_MEMBERS = frozenset({"data", "policy.pth"})


def _check_checkpoint_zip(path: Path) -> None:
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


def _reason(error: BaseException) -> str:
    """A one-line reason for a failed load."""
    text = str(error).splitlines()[0] if str(error) else ""
    return f"{type(error).__name__}: {text}" if text else type(error).__name__


def _linear_schedule(initial: float) -> Any:
    """rl-zoo3's ``lin_<initial>``: from ``initial`` at the start down to 0 at the end."""

    def schedule(progress_remaining: float) -> float:
        return progress_remaining * initial

    return schedule


def _algo_kwargs(hp: Hyperparams, env: Any, algo: str) -> dict[str, Any]:
    kwargs = dict(hp.algo_kwargs)
    for key in SCHEDULE_KEYS:
        value = kwargs.get(key)
        if isinstance(value, str):
            kind, _, initial = value.partition("_")
            try:
                if kind != "lin":
                    raise ValueError(kind)
                kwargs[key] = _linear_schedule(float(initial))
            except ValueError as e:
                raise TrainingError(f"config {hp.source}: {key} {value!r} is not a number or lin_<x>") from e
    if isinstance(kwargs.get("train_freq"), list):
        kwargs["train_freq"] = tuple(kwargs["train_freq"])  # YAML has no tuples; SB3 wants (n, unit)
    rb = kwargs.get("replay_buffer_class")
    if isinstance(rb, str):
        if rb not in REPLAY_BUFFERS:
            raise TrainingError(f"config {hp.source}: unknown replay_buffer_class {rb!r}")
        kwargs["replay_buffer_class"] = REPLAY_BUFFERS[rb]
    space = env.observation_space
    is_goal_env = isinstance(space, gym.spaces.Dict) and "desired_goal" in space.spaces
    if algo in ("sac", "td3") and is_goal_env and "replay_buffer_class" not in kwargs:
        kwargs["replay_buffer_class"] = HerReplayBuffer  # goal env: HER automatically
        kwargs.setdefault("replay_buffer_kwargs", {"goal_selection_strategy": "future", "n_sampled_goal": 4})
    if hp.noise_type:
        n = env.action_space.shape[0]
        noise_cls = {"normal": NormalActionNoise, "ornstein-uhlenbeck": OrnsteinUhlenbeckActionNoise}.get(
            hp.noise_type
        )
        if noise_cls is None:
            raise TrainingError(f"config {hp.source}: unknown noise_type {hp.noise_type!r}")
        kwargs["action_noise"] = noise_cls(np.zeros(n), hp.noise_std * np.ones(n))
    return kwargs


def _callbacks(hp: Hyperparams, eval_env: gym.Env, args: TrainArgs) -> tuple[Any, list[BaseCallback]]:
    """The config's success evaluation (on ``eval_env``) and its other callbacks, as rl-zoo3 builds them."""
    eval_kwargs = {"seed": args.seed + 10_000, **hp.eval_kwargs, "verbose": args.verbose}
    evaluator = SuccessEvalCallback(
        eval_freq=hp.eval_freq,
        eval_episodes=hp.eval_episodes,
        target_success=hp.target_success,
        env=eval_env,
        **eval_kwargs,
    )
    specs = list(hp.callbacks)
    if args.demos:  # --demos: this dataset, in the config's demonstration callback or a default one
        specs = [
            (c, {**k, "dataset": args.demos}) if c is DemonstrationCallback else (c, k) for c, k in specs
        ]
        if not any(c is DemonstrationCallback for c, _ in specs):
            specs.append((DemonstrationCallback, {"dataset": args.demos}))
    if any(c is DemonstrationCallback for c, _ in specs) and args.algo != "sac":
        raise TrainingError(f"demonstrations are learned with --algo sac (or bc), not {args.algo}")
    try:
        others = [cls(**kwargs) for cls, kwargs in specs]
    except (TypeError, ValueError) as e:
        raise TrainingError(f"config {hp.source}: callback: {e}") from e
    return evaluator, others


def _demo_facts(callbacks: list[BaseCallback]) -> dict[str, Any]:
    """What the run learned from besides its own experience (for the metadata)."""
    for cb in callbacks:
        if isinstance(cb, DemonstrationCallback) and cb.demos is not None:
            return {
                "demos": {
                    "dataset": cb.dataset,
                    "episodes": len(cb.demos.successes),
                    "steps": len(cb.demos),
                    "collect_s": round(cb.collect_s, 1),
                    "pretrain_steps": cb.pretrain_steps,
                }
            }
    return {}


@dataclass(frozen=True)
class RunPlan:
    """What :func:`train` will do, settled before anything is built or written.

    Attributes:
        hp: The run's hyperparameters.
        total: Training budget in env steps (on ``--resume``: the original run's).
        state: The ``train_state.json`` to write once the model is built.
    """

    hp: Hyperparams
    total: int
    state: dict[str, Any]


def plan_run(args: TrainArgs, env_id: str, out: Path) -> RunPlan:
    """Check every input of a (resumed) run and settle its hyperparameters and budget.

    Raises:
        TrainingError: Bad input; nothing has been written.
    """
    if args.resume:
        saved = read_train_state(out)
        if saved["env_id"] != env_id or saved["algo"] != args.algo:
            raise TrainingError(
                f"{out} holds a {saved['algo']} run on {saved['env_id']}, not {args.algo} on {env_id}"
            )
        args.seed, total = saved["seed"], saved["total_timesteps"]
        if args.timesteps is not None and args.timesteps != total:
            raise TrainingError(
                f"--resume continues {out}'s budget of {total} steps; --timesteps {args.timesteps} "
                "would change it (drop it, or train a new run with --out elsewhere)"
            )
        args.demos = args.demos or saved["demos"]
        config = saved["config"] or (str(args.config) if args.config else None)
        hp = load_run_hyperparams(args, env_id, Path(config) if config else None)
        if newest_checkpoint(out / "checkpoints") is None:
            raise TrainingError(f"nothing to resume in {out / 'checkpoints'}: no checkpoint")
        demos = saved["demos"]
    else:
        hp = load_run_hyperparams(args, env_id)
        total = args.timesteps or hp.n_timesteps
        config = str(args.config) if args.config else None
        demos = args.demos
    if args.demos and args.algo != "sac":
        raise TrainingError(f"demonstrations are learned with --algo sac (or bc), not {args.algo}")
    state = {
        "env_id": env_id,
        "algo": args.algo,
        "seed": args.seed,
        "total_timesteps": int(total),
        "config": config,
        "demos": demos,
    }
    return RunPlan(hp=hp, total=int(total), state=state)


def train(args: TrainArgs) -> TrainResult:
    """Train, evaluate and save a policy (see the module docstring).

    Every input is checked before anything is written; the output directory
    appears once the model is built. SIGINT and SIGTERM save a checkpoint
    (``--resume`` continues from it) and raise :class:`TrainingInterrupted`.

    Raises:
        TrainingError: Bad input (nothing trained, nothing written).
        TrainingInterrupted: SIGINT or SIGTERM.
    """
    env_id = resolve_env_id(args.env)
    check_timesteps(args.timesteps)
    if args.seed < 0:
        raise TrainingError(f"--seed must be >= 0, got {args.seed}")
    if args.algo == "bc":
        return train_bc(args, env_id, load_run_hyperparams(args, env_id))
    from bioscara_gym.training import dagger  # PickPlace's default, and --algo dagger

    if dagger.uses_dagger(args, env_id):
        return dagger.train_dagger(args, env_id)
    if args.algo is None:  # not DAgger's env (above): SAC, or what the resumed run trained
        args.algo = read_train_state(Path(args.out))["algo"] if args.resume else "sac"
    out = Path(args.out)
    plan = plan_run(args, env_id, out)
    hp = plan.hp
    torch.set_num_threads(args.threads or 1)
    with SignalGuard() as guard, contextlib.closing(gym.make(env_id, **hp.env_kwargs)) as eval_env:
        model: BaseAlgorithm | None = None
        env = None
        try:
            algo_kwargs = _algo_kwargs(hp, eval_env, args.algo)  # the training envs' spaces are the same
            evaluator, others = _callbacks(hp, eval_env, args)
            env = make_vec_env(env_id, n_envs=hp.n_envs, seed=args.seed, env_kwargs=hp.env_kwargs)
            model = _build_model(args, hp, env, env_id, out, algo_kwargs)
            out.mkdir(parents=True, exist_ok=True)  # the first thing written
            atomic_write_text(out / STATE_NAME, json.dumps(plan.state, indent=2))
            start = time.perf_counter()
            model.learn(
                total_timesteps=max(plan.total - model.num_timesteps, 0),
                callback=CallbackList(
                    [evaluator, *others, CheckpointEvery(out / "checkpoints", args.checkpoint_freq)]
                ),
                reset_num_timesteps=not args.resume,
                progress_bar=args.progress,
                tb_log_name="run",
            )
            reached = evaluator.reached_at is not None
            final = evaluator.last if reached else evaluator.evaluate(hp.eval_episodes)
        except KeyboardInterrupt as e:  # Ctrl-C, or SIGTERM through the guard
            with guard.shielded():
                checkpoint = save_checkpoint(model, out / "checkpoints") if model is not None else None
            signum = e.signum if isinstance(e, Interrupted) else signal.SIGINT
            raise TrainingInterrupted(signum, checkpoint, out) from None
        finally:
            if env is not None:
                env.close()
        with guard.shielded():  # a signal now would cut the final model in half
            model_path, metadata_path = save_policy(
                model,
                out,
                build_metadata(
                    eval_env,
                    env_id,
                    hp.env_kwargs,
                    algo=args.algo,
                    seed=args.seed,
                    timesteps=model.num_timesteps,
                    config=hp.as_dict(),
                    final_eval=final.as_dict() if final else None,
                    **_demo_facts(others),
                ),
            )
    return TrainResult(
        model_path=model_path,
        metadata_path=metadata_path,
        timesteps=model.num_timesteps,
        wall_time_s=time.perf_counter() - start,
        final_eval=final,
        target_reached_at=evaluator.reached_at,
        target_reached_after_s=evaluator.reached_after_s,
    )


def _build_model(
    args: TrainArgs, hp: Hyperparams, env: Any, env_id: str, out: Path, algo_kwargs: dict[str, Any]
) -> BaseAlgorithm:
    """A new model, or (``--resume``) the newest checkpoint that loads."""
    algo_cls = ALGOS[args.algo]
    if args.resume:
        return load_checkpoint(algo_cls, out / "checkpoints", env)[0]
    try:
        return algo_cls(
            hp.policy,
            env,
            seed=args.seed,
            device="cpu",
            tensorboard_log=str(out / "tb"),
            verbose=0,
            **algo_kwargs,
        )
    except (TypeError, ValueError) as e:  # e.g. a key inside policy_kwargs the policy does not take
        raise TrainingError(f"config {hp.source}: {env_id}: {_reason(e)}") from e


#: Behaviour-cloning steps of ``bioscara train --algo bc`` without ``--timesteps``.
BC_STEPS = 10_000


def train_bc(args: TrainArgs, env_id: str, hp: Hyperparams) -> TrainResult:
    """``bioscara train --algo bc``: clone the demonstrations into a SAC actor, evaluate, save.

    The policy, its kwargs and the env's kwargs are those of the SAC config's
    entry; ``--timesteps`` counts gradient steps (default :data:`BC_STEPS`).
    Without ``--demos`` the scripted expert's episodes are collected first.
    """
    from bioscara_gym.experts import expert_for
    from bioscara_gym.training.demos import check_demos, load_demos, rollout_demos

    if args.resume:
        raise TrainingError("--algo bc trains in one go; there is nothing to resume")
    steps = int(args.timesteps or BC_STEPS)
    if steps <= 0:
        raise TrainingError(f"timesteps must be > 0, got {steps}")
    torch.set_num_threads(args.threads or 1)
    settings = next((k for c, k in hp.callbacks if c is DemonstrationCallback), {})
    start = time.perf_counter()
    env = gym.make(env_id, **hp.env_kwargs)
    try:
        if args.demos:
            demos = load_demos(args.demos, successful_only=True)
            check_demos(demos, env)
        else:
            expert = expert_for(env.unwrapped)
            episodes, seed = int(settings.get("episodes", 100)), int(settings.get("seed", 1_000_000))
            demos = rollout_demos(env, expert, expert.reset, episodes, seed=seed)
        kwargs = _algo_kwargs(hp, env, "sac")
        kwargs.update(replay_buffer_class=None, replay_buffer_kwargs=None, buffer_size=1, action_noise=None)
        model = SAC(hp.policy, env, seed=args.seed, device="cpu", verbose=0, **kwargs)
        loss = bc_pretrain(
            model, demos, steps, init_std=float(settings.get("init_std", 0.1)), seed=args.seed
        )
        eval_env = gym.make(env_id, **hp.env_kwargs)
        try:

            def act(obs: dict[str, np.ndarray]) -> np.ndarray:
                return model.predict(obs, deterministic=True)[0]

            final = run_episodes(eval_env, act, hp.eval_episodes, seed=args.seed + EVAL_SEED_OFFSET)
        finally:
            eval_env.close()
        model_path, metadata_path = save_policy(
            model,
            Path(args.out),
            build_metadata(
                env,
                env_id,
                hp.env_kwargs,
                algo="bc",
                seed=args.seed,
                timesteps=0,
                bc_steps=steps,
                bc_loss=loss,
                demos={"dataset": args.demos, "episodes": len(demos.successes), "steps": len(demos)},
                config=hp.as_dict(),
                final_eval=final.as_dict(),
            ),
        )
    finally:
        env.close()
    if args.verbose:
        print(f"[bc] {steps} steps on {len(demos)} demonstration steps, loss {loss:.4f}", flush=True)
    return TrainResult(
        model_path=model_path,
        metadata_path=metadata_path,
        timesteps=0,
        wall_time_s=time.perf_counter() - start,
        final_eval=final,
        target_reached_at=None,
        target_reached_after_s=None,
    )
