"""Train a policy on CPU: ``bioscara train``.

Reads top to bottom: resolve the env, check the arguments every method
shares, choose the method (``--algo``; on ``--resume`` the run's; else the
task's default, :data:`bioscara_gym.tasks.TASKS`) from the registry
(:data:`~bioscara_gym.training.methods.METHODS`), and run its steps
(:meth:`~bioscara_gym.training.base.TrainingMethod.run`: plan, make the
envs, callbacks, build or resume the model, learn, evaluate, save
``model.zip`` next to ``metadata.json``).

Bad input (an unknown method, a key the algorithm does not take, an
evaluation schedule or a budget below 1, a damaged ``train_state.json``,
nothing to resume, an ``--out`` that cannot be made or that holds another
run) is refused with a :class:`~bioscara_gym.errors.TrainingError`
before anything is written. Ctrl-C and SIGTERM save a checkpoint and raise
:class:`TrainingInterrupted`; checkpoints and the model are written
atomically, and ``--resume`` skips a damaged newest checkpoint with a
:class:`~bioscara_gym.errors.CheckpointWarning`.
"""

from __future__ import annotations

import os
from pathlib import Path

import bioscara_gym  # noqa: F401 - registers the tasks
from bioscara_gym.errors import TrainingError
from bioscara_gym.fsutil import output_problem
from bioscara_gym.tasks import TASKS
from bioscara_gym.training.checkpoints import SEED_MAX, check_no_run, read_run_state
from bioscara_gym.training.metadata import resolve_env_id
from bioscara_gym.training.methods import MethodSpec, method_spec
from bioscara_gym.training.run import TrainArgs, TrainingInterrupted, TrainResult

__all__ = [
    "TrainArgs",
    "TrainResult",
    "TrainingInterrupted",
    "check_n_envs",
    "check_timesteps",
    "choose_method",
    "train",
]


def check_timesteps(timesteps: int | None) -> None:
    """Refuse ``--timesteps`` below 1 (``None``: the config's budget).

    Raises:
        TrainingError: ``timesteps`` is 0 or negative.
    """
    if timesteps is not None and timesteps < 1:
        raise TrainingError(f"--timesteps {timesteps}: must be >= 1 (omit it for the config's n_timesteps)")


#: Workers (``--n-envs``) per CPU this process may run on: each is a process with a MuJoCo of its own.
WORKERS_PER_CPU = 8


def check_n_envs(n_envs: int | None, what: str = "--n-envs") -> None:
    """Refuse ``--n-envs`` below 1 or above :data:`WORKERS_PER_CPU` a CPU (``None``: the config's).

    ``what`` names the value in the message (a config's ``n_envs``).

    Raises:
        TrainingError: ``n_envs`` is 0 or negative, or more workers than the
            machine can start (100,000 ended in "Too many open files").
    """
    if n_envs is not None and n_envs < 1:
        raise TrainingError(f"{what} {n_envs}: must be >= 1 (omit it for the config's n_envs)")
    cpus = len(os.sched_getaffinity(0)) if hasattr(os, "sched_getaffinity") else os.cpu_count() or 1
    if n_envs is not None and n_envs > WORKERS_PER_CPU * cpus:
        raise TrainingError(
            f"{what} {n_envs}: at most {WORKERS_PER_CPU * cpus} on this machine's {cpus} CPUs "
            f"({WORKERS_PER_CPU} a CPU; each is a process of its own)"
        )


def check_out(out: Path, resume: bool) -> None:
    """Refuse an ``--out`` the run cannot write in, and (a new run) one that holds a run already.

    Checked before an env or model is built: ``/proc/foo`` and a dangling
    symlink failed only once the model was to be saved, 6-7 s in, naming
    neither ``--out`` nor the symlink ("File exists: dangl").

    Raises:
        TrainingError: A file, a folder that takes no file, a path through a
            symlink to nothing, or (not ``resume``) a folder holding a run.
    """
    if out.exists() and not out.is_dir():
        raise TrainingError(f"--out {out} is a file; give a folder for the run")
    problem = output_problem(out, folder=True)
    if problem is not None:
        raise TrainingError(f"--out {out}: {problem}")
    for path in (out, *out.parents):
        if path.exists():
            break
        if path.is_symlink():  # the folder cannot be made there
            raise TrainingError(
                f"--out {out}: {path} is a symlink to {os.readlink(path)}, which does not exist; "
                "make its target or give another --out"
            )
    if not resume:
        check_no_run(out)


def choose_method(args: TrainArgs, env_id: str) -> MethodSpec:
    """The method ``bioscara train`` runs: ``--algo``; on ``--resume`` the run's; else the task's default.

    The task's default (DAgger on PickPlace, Push, Stack and Insert) applies only without ``--config``:
    a hyperparameter file of rl-zoo3's format trains SAC.

    Raises:
        TrainingError: An unknown ``--algo``, or (``--resume``) a missing or damaged run state.
    """
    if args.algo is not None:
        return method_spec(args.algo)
    if args.resume:
        return method_spec(read_run_state(Path(args.out))["algo"])
    if args.config is None and env_id in TASKS:
        return method_spec(TASKS[env_id].default_method)
    return method_spec("sac")


def train(args: TrainArgs) -> TrainResult:
    """Train, evaluate and save a policy (see the module docstring).

    Every input is checked before anything is written; the output directory
    appears once the model is built. A new run never goes into a folder that
    holds a run (:func:`~bioscara_gym.training.checkpoints.check_no_run`).
    SIGINT, SIGTERM and SIGHUP save a checkpoint (``--resume`` continues from it)
    and raise :class:`TrainingInterrupted`.

    Raises:
        TrainingError: Bad input (nothing trained, nothing written).
        TrainingInterrupted: a stop signal.
    """
    env_id = resolve_env_id(args.env)
    check_timesteps(args.timesteps)
    check_n_envs(args.n_envs)
    if args.seed is not None and args.seed < 0:
        raise TrainingError(f"--seed must be >= 0, got {args.seed}")
    if args.seed is not None and args.seed > SEED_MAX:  # numpy's limit: refused as the model is seeded
        raise TrainingError(f"--seed must be <= {SEED_MAX} (2**32 - 1), got {args.seed}")
    if args.seed is None and not args.resume:  # a resumed run's is its own (TrainingMethod.resumed)
        args.seed = 0
    if args.threads is not None and args.threads < 1:
        raise TrainingError(f"--threads must be >= 1, got {args.threads}")
    check_out(Path(args.out), args.resume)
    spec = choose_method(args, env_id)
    return spec.method_class()(args, env_id, spec).run()
