"""What a training run is: its arguments, its result, how it ends early.

Shared by the skeleton (:mod:`~bioscara_gym.training.base`), every method
and the CLI, none of which needs torch for these. The run's files are
:mod:`~bioscara_gym.training.checkpoints`'.
"""

from __future__ import annotations

from dataclasses import dataclass
from pathlib import Path

from bioscara_gym.training.evaluate import EvalStats
from bioscara_gym.training.signals import Interrupted


@dataclass
class TrainArgs:
    """Arguments of ``bioscara train`` (the CLI flags map one to one).

    Attributes:
        env: Env id (``Bioscara-Reach`` or a versioned id).
        algo: A method of :data:`~bioscara_gym.training.methods.METHODS` (``sac``,
            ``td3``, ``ppo``, ``bc``, ``dagger``); ``None``: the task's default
            (DAgger on PickPlace unless a ``config`` is given, SAC elsewhere),
            or on ``resume`` the run's own.
        config: Hyperparameter file (rl-zoo3 format); default the packaged one.
        timesteps: Training budget; default the config's ``n_timesteps``.
        seed: Seed of the model, the envs and the evaluation episodes, 0 to
            2**32 - 1; ``None``: 0, or on ``resume`` the run's (another one
            is refused).
        out: Output directory (model, metadata, checkpoints, TensorBoard logs).
        resume: Continue from the newest checkpoint in ``out``.
        progress: Show a progress bar.
        checkpoint_freq: Env steps between checkpoints.
        threads: Torch CPU threads. Default 1: the env steps in the same
            process, and on a 2-core machine a second torch thread only
            contends with it (measured 20x slower matrix products).
            DAgger's fit, during which the env waits, takes its config's
            ``fit_threads`` instead.
        verbose: Print each evaluation.
        demos: Minari dataset of demonstrations to learn from (SAC: Nair et al.
            2018, see :mod:`bioscara_gym.training.imitation`; ``bc``: cloned alone).
        n_envs: Envs stepping in parallel, each in a subprocess when more than
            1 (SB3's ``SubprocVecEnv``: the SB3 methods' training envs,
            DAgger's rollouts); default the config's ``n_envs``.
    """

    env: str = "Bioscara-Reach"
    algo: str | None = None
    config: Path | None = None
    timesteps: int | None = None
    seed: int | None = None
    out: Path = Path("runs/reach")
    resume: bool = False
    progress: bool = True
    checkpoint_freq: int = 10_000
    threads: int | None = None
    verbose: int = 1
    demos: str | None = None
    n_envs: int | None = None


@dataclass(frozen=True)
class TrainResult:
    """What a run produced."""

    model_path: Path
    metadata_path: Path
    timesteps: int
    wall_time_s: float
    final_eval: EvalStats | None
    target_reached_at: int | None
    target_reached_after_s: float | None


class TrainingInterrupted(Interrupted):
    """Training stopped by SIGINT, SIGTERM or SIGHUP, after saving a checkpoint.

    Attributes:
        checkpoint: The checkpoint saved, ``None`` if training had not started.
        out: The run's output directory (what ``--resume`` continues).
    """

    def __init__(self, signum: int, checkpoint: Path | None, out: Path) -> None:
        """Remember the signal, the checkpoint and the run."""
        super().__init__(signum)
        self.checkpoint = checkpoint
        self.out = out
