"""``bioscara collect``: record demonstrations as a Minari dataset.

    bioscara collect --expert --env Bioscara-PickPlace --episodes 100 --dataset pickplace-expert
    bioscara collect --model runs/reach/model.zip --episodes 50 --dataset reach-sac
    bioscara collect --expert --env Bioscara-Reach --backend emulated --episodes 5 --dataset reach-emu

With ``--expert`` the env's keyword arguments are those of the packaged config
of the task's default training method (PickPlace: the DAgger entry, else the
SAC one), so the demonstrations fit ``bioscara train --demos`` out of the box
(``--control-mode`` overrides); with ``--model`` they are the model's (from
its metadata). A task with an observation-only expert (PickPlace:
:class:`~bioscara_gym.experts.ObservationExpert`, the one DAgger labels the
learner's states with) is recorded acting with it, so demonstrations and
labels agree. See :mod:`bioscara_gym.training.demos`.
"""

from __future__ import annotations

import argparse
from pathlib import Path
from typing import Any

import gymnasium as gym

from bioscara_gym.errors import CliError, HyperparamError, TrainingError
from bioscara_gym.tasks import task_of
from bioscara_gym.training.checkpoints import SEED_MAX
from bioscara_gym.training.extras import needed_by


def default_env_kwargs(env_id: str) -> dict[str, Any]:
    """The ``env_kwargs`` of ``env_id``'s default config: its default method's entry (``{}``: none)."""
    from bioscara_gym.training.methods import default_env_kwargs as method_env_kwargs

    try:
        return method_env_kwargs(env_id)
    except HyperparamError:
        return {}


def expert_factory(env: gym.Env) -> tuple[Any, Any]:
    """The expert of ``env``'s task and its per-episode reset: the observation-only one where there is one."""
    task = task_of(env)
    if task.observation_expert is not None:
        expert = task.make_observation_expert(env.unwrapped)
    else:
        expert = task.make_expert(env.unwrapped)
    return expert, expert.reset


def model_factory(model_path: Path) -> Any:
    """A factory of the trained model's deterministic policy (no per-episode state)."""
    with needed_by("collect --model"):
        from bioscara_gym.training.algos import load_model, sb3_policy

    model, _ = load_model(model_path)
    policy = sb3_policy(model)

    def factory(env: gym.Env) -> tuple[Any, Any]:
        return policy, lambda: None

    return factory


#: The env of ``--expert`` when none is given.
DEFAULT_ENV = "Bioscara-PickPlace"


def cmd_collect(args: argparse.Namespace) -> int:
    """``bioscara collect``."""
    from bioscara_gym.training.demos import collect
    from bioscara_gym.training.metadata import read_metadata, resolve_env_id

    if args.expert == (args.model is not None):
        raise CliError("collect needs exactly one of --expert or --model PATH")
    if args.episodes <= 0:
        raise CliError(f"--episodes must be > 0, got {args.episodes}")
    if args.seed < 0:
        raise CliError(f"--seed must be >= 0, got {args.seed}")
    if args.seed + args.episodes - 1 > SEED_MAX:
        raise CliError(f"--seed {args.seed}: the episodes' seeds must stay within 0-{SEED_MAX}")
    try:
        if args.expert:
            env_id = resolve_env_id(args.env or DEFAULT_ENV)
            env_kwargs = default_env_kwargs(env_id)
            factory, who = expert_factory, "scripted expert"
        else:
            metadata = read_metadata(args.model)
            env_id, env_kwargs = metadata["env_id"], dict(metadata.get("env_kwargs", {}))
            if args.env is not None and resolve_env_id(args.env) != resolve_env_id(env_id):
                raise CliError(f"--env {args.env}: the model was trained on {env_id}, where it acts")
            if args.control_mode and args.control_mode != env_kwargs.get("control_mode"):
                raise CliError(f"the model acts in control_mode {env_kwargs.get('control_mode')!r}")
            factory, who = model_factory(args.model), f"{metadata.get('algo', 'model')} {args.model}"
        if args.control_mode:
            env_kwargs["control_mode"] = args.control_mode
        if args.backend:
            env_kwargs["backend"] = args.backend
        with needed_by("bioscara collect"):
            result = collect(
                env_id,
                args.episodes,
                args.dataset,
                factory,
                env_kwargs=env_kwargs,
                seed=args.seed,
                overwrite=args.overwrite,
                progress=not args.no_progress,
                algorithm_name=who,
            )
    except TrainingError as e:
        raise CliError(str(e)) from e
    from bioscara_gym.cli import _console

    con = _console()
    con.print(
        f"dataset   {result.dataset_id}: {result.episodes} episodes, {result.steps} steps, "
        f"{result.size_bytes / 1e6:.1f} MB, success {result.success_rate:.1%} "
        f"({result.wall_time_s:.0f} s)"
    )
    con.print(f"path      {result.path}")
    return 0


def register(sub: Any) -> None:
    """Add ``bioscara collect`` to the CLI's subparsers."""
    p = sub.add_parser("collect", help="record demonstrations (expert or model) as a Minari dataset")
    p.add_argument("--expert", action="store_true", help="act with the scripted expert of --env")
    p.add_argument("--model", type=Path, help="act with a trained model.zip instead")
    p.add_argument("--env", help="env id for --expert (default: PickPlace); a model's is its own")
    p.add_argument("--episodes", type=int, default=100, help="episodes to record (default 100)")
    p.add_argument("--dataset", required=True, help="dataset name (Minari id; -v0 appended if unversioned)")
    p.add_argument("--backend", choices=("sim", "emulated", "mock"), help="default: sim")
    modes = ("velocity", "position", "cartesian")
    p.add_argument("--control-mode", choices=modes, help="default: the config's")
    p.add_argument("--seed", type=int, default=0, help="seed of the first episode")
    p.add_argument("--overwrite", action="store_true", help="replace an existing dataset of that name")
    p.add_argument("--no-progress", action="store_true", help="no progress bar")
    p.set_defaults(func=cmd_collect)
