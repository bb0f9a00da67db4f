"""The skeleton every training method fills in: one run as named steps, in order.

As SB3's ``BaseAlgorithm.learn`` and Gymnasium-Robotics' ``robot_env``:
:meth:`TrainingMethod.run` is the loop, a method module fills in the hooks.

====================  =============================================================
step                  what it does
====================  =============================================================
:meth:`~TrainingMethod.plan`         check every input, settle the config and the budget;
                                     on ``--resume`` read the run's state (nothing written)
(the checks)                         what needs the plan: the config's env kwargs (one env
                                     made and closed), its envs, what HER needs of it,
                                     the demonstrations against the env (nothing written)
:meth:`~TrainingMethod.make_envs`    the training env(s) and the evaluation env
:meth:`~TrainingMethod.callbacks`    what runs alongside learning (SB3 callbacks)
:meth:`~TrainingMethod.build_model`  a new model, or the newest checkpoint that loads
(the run's state)                    ``train_state.json``: the first file written
:meth:`~TrainingMethod.learn`        train until the target or the budget
:meth:`~TrainingMethod.evaluate`     the final success rate
(save)                               ``model.zip`` and ``metadata.json``, atomically,
                                     signals held off
====================  =============================================================

SIGINT, SIGTERM and SIGHUP at any step save a checkpoint (:meth:`~TrainingMethod.checkpoint`)
and raise :class:`~bioscara_gym.training.run.TrainingInterrupted`; bad input
is a :class:`~bioscara_gym.errors.TrainingError` before anything is written.
"""

from __future__ import annotations

import abc
import contextlib
import signal
import time
from collections.abc import Mapping
from dataclasses import dataclass
from pathlib import Path
from typing import Any

import gymnasium as gym

from bioscara_gym.errors import HyperparamError, TrainingError
from bioscara_gym.training.checkpoints import (
    STATE_NAME,
    check_checkpoint_policies,
    checkpoint_dir,
    checkpoint_steps,
    newest_checkpoint,
    read_run_state,
    write_run_state,
)
from bioscara_gym.training.demos import dataset_id, load_demos
from bioscara_gym.training.evaluate import EvalStats
from bioscara_gym.training.extras import needs_train
from bioscara_gym.training.hyperparams import check_her_episodes
from bioscara_gym.training.metadata import build_metadata, env_kwargs_problem, save_policy
from bioscara_gym.training.methods import MethodSpec
from bioscara_gym.training.run import TrainArgs, TrainingInterrupted, TrainResult
from bioscara_gym.training.signals import Interrupted, SignalGuard
from bioscara_gym.training.train import check_n_envs

with needs_train():
    import torch

    from bioscara_gym.training.algos import policy_base, sb3_class
    from bioscara_gym.training.zoo import DemonstrationCallback


@dataclass(frozen=True)
class RunPlan:
    """What a run will do, settled before anything is built or written.

    Attributes:
        config: The method's configuration (a ``Hyperparams``, a ``DaggerConfig``).
        env_kwargs: Keyword arguments of ``gym.make``.
        total: Training budget (env steps; ``bc``: gradient steps).
        state: The ``train_state.json`` to write once the model is built
            (``None``: the method cannot resume, nothing is written for it).
        n_envs: The envs training steps when the plan settles them (on ``--resume``
            the run's own); ``None``: ``--n-envs``, else the config's ``n_envs``.
    """

    config: Any
    env_kwargs: dict[str, Any]
    total: int
    state: dict[str, Any] | None
    n_envs: int | None = None


@dataclass(frozen=True)
class Resumed:
    """What ``--resume`` continues, read from the run's ``train_state.json`` and checked.

    Attributes:
        seed: The run's seed.
        total: Its budget.
        config: Its hyperparameter file (``None``: the packaged one).
        demos: Its demonstration dataset.
        newest: Its newest checkpoint (what it resumes from, unless that one does not load).
    """

    seed: int
    total: int
    config: str | None
    demos: str | None
    newest: Path


class TrainingMethod(abc.ABC):
    """One way of training a policy: the hooks :meth:`run` calls (see the module docstring).

    Args:
        args: The run's arguments (``seed`` and ``demos`` are settled by :meth:`plan`).
        env_id: The registered, versioned env id.
        spec: The method's entry in :data:`~bioscara_gym.training.methods.METHODS`.

    Attributes:
        model: The model, once :meth:`build_model` made it.
        reached_at: Env steps at which the target was reached (``None``: not reached).
        reached_after_s: Seconds it took.
    """

    def __init__(self, args: TrainArgs, env_id: str, spec: MethodSpec) -> None:
        """Bind to the run; nothing is checked or built yet."""
        self.args = args
        self.env_id = env_id
        self.spec = spec
        self.out = Path(args.out)
        self.model: Any = None
        self.reached_at: int | None = None
        self.reached_after_s: float | None = None
        self.start = time.perf_counter()

    # ------------------------------------------------------------- the steps
    @abc.abstractmethod
    def plan(self) -> RunPlan:
        """Check every input and settle the config and budget; nothing is written.

        Raises:
            TrainingError: Bad input, one line.
        """

    @abc.abstractmethod
    def make_envs(self, plan: RunPlan, stack: contextlib.ExitStack) -> gym.Env:
        """Make the envs (``stack`` closes them); return the one the metadata describes."""

    def callbacks(self, plan: RunPlan) -> list[Any]:
        """What runs alongside :meth:`learn` (SB3 callbacks); none by default.

        Raises:
            TrainingError: A callback the config describes cannot be made.
        """
        return []

    @abc.abstractmethod
    def build_model(self, plan: RunPlan) -> Any:
        """A new model, or on ``--resume`` the newest checkpoint that loads."""

    @abc.abstractmethod
    def learn(self, plan: RunPlan, callbacks: list[Any], guard: SignalGuard) -> None:
        """Train until the target or the budget (checkpoints on the way, signals held off while saving)."""

    @abc.abstractmethod
    def evaluate(self, plan: RunPlan) -> EvalStats:
        """The final success rate (the stopping evaluation's, when it reached the target)."""

    def checkpoint(self) -> Path | None:
        """Save a checkpoint now (a stop signal); ``None`` if there is nothing to save."""
        return None

    @property
    @abc.abstractmethod
    def timesteps(self) -> int:
        """Env steps trained on so far."""

    def metadata(self, plan: RunPlan) -> dict[str, Any]:
        """What the metadata records of the run besides the env, the spaces and the final evaluation."""
        return {}

    # --------------------------------------------------------------- the loop
    def run(self) -> TrainResult:
        """Plan, make the envs, build the model, learn, evaluate, save (see the module docstring).

        Raises:
            TrainingError: Bad input (nothing trained, nothing written).
            HyperparamError: The config's env_kwargs has a keyword the env does not take.
            TrainingInterrupted: a stop signal (a checkpoint saved, if there was a model).
        """
        plan = self.plan()
        self.check_plan(plan)
        torch.set_num_threads(self.args.threads or 1)
        self.start = time.perf_counter()
        with SignalGuard() as guard, contextlib.ExitStack() as stack:
            try:
                env = self.make_envs(plan, stack)
                callbacks = self.callbacks(plan)
                self.model = self.build_model(plan)
                if plan.state is not None:
                    write_run_state(self.out, plan.state)
                self.learn(plan, callbacks, guard)
                final = self.evaluate(plan)
            except KeyboardInterrupt as e:  # Ctrl-C, or SIGTERM through the guard
                with guard.shielded():
                    saved = self.checkpoint() if self.model is not None else None
                signum = e.signum if isinstance(e, Interrupted) else signal.SIGINT
                raise TrainingInterrupted(signum, saved, self.out) from None
            with guard.shielded():  # a signal now would cut the final model in half
                metadata = self._metadata(env, plan, final)
                model_path, metadata_path = save_policy(self.model, self.out, metadata)
                # The envs closed (workers joined) in here too: a signal then was reported as one
                # "before training started; nothing saved", the model saved (a reviewer's find).
                stack.close()
        return TrainResult(
            model_path=model_path,
            metadata_path=metadata_path,
            timesteps=self.timesteps,
            wall_time_s=time.perf_counter() - self.start,
            final_eval=final,
            target_reached_at=self.reached_at,
            target_reached_after_s=self.reached_after_s,
        )

    def check_plan(self, plan: RunPlan) -> None:
        """Check what needs the plan, before an env is built for training or a file written.

        Each of these was seen refused only once the run had written
        ``train_state.json`` and ``tb/`` (or by a traceback): the config's
        env kwargs (an unknown keyword, a value the env refuses, such as
        ``reward_type: bogus``), its ``n_envs``, a ``learning_starts`` or
        ``buffer_size`` HER cannot sample from, and demonstrations recorded
        on another task, control mode or spaces (``--demos``, or the
        config's :class:`~bioscara_gym.training.zoo.DemonstrationCallback`).

        Raises:
            HyperparamError: A bad value of the config, the file and entry named.
            TrainingError: Demonstrations that do not fit the env, or cannot be read.
        """
        where = f"config {plan.config.source}: {self.env_id}"
        problem = env_kwargs_problem(self.env_id, plan.env_kwargs)
        if problem is not None:  # before an env is made: the file named, not a traceback
            raise HyperparamError(f"{where}.env_kwargs {problem}")
        n_envs = self.args.n_envs  # --n-envs was checked with the arguments; a config's here
        if plan.n_envs is not None:  # the run's own, on --resume: HER's check for the envs it steps
            n_envs = plan.n_envs
            check_n_envs(n_envs, f"--resume continues {self.out}'s n_envs")
        elif n_envs is None:
            n_envs = getattr(plan.config, "n_envs", None)
            check_n_envs(n_envs, f"{where}.n_envs")
        if self.spec.rl_zoo:  # the runner adds HER on the goal tasks (training/sb3.py)
            steps = self.episode_steps(plan.env_kwargs)
            check_her_episodes(plan.config, sb3_class(self.spec.model), self.env_id, steps, n_envs or 1)
        try:  # one env, as training makes it, closed at once: a value it refuses names the file
            env = gym.make(self.env_id, **plan.env_kwargs)
        except (TypeError, ValueError) as e:
            raise HyperparamError(f"{where}.env_kwargs: {e}") from e
        with contextlib.closing(env):
            for dataset in self.datasets(plan):  # a missing, damaged or unfitting one is one line
                load_demos(dataset, env)

    def datasets(self, plan: RunPlan) -> list[str]:
        """The demonstration datasets the run learns from: ``--demos``, else the config's callback's."""
        if self.args.demos:
            return [self.args.demos]
        callbacks = getattr(plan.config, "callbacks", ())
        return [k["dataset"] for c, k in callbacks if c is DemonstrationCallback and k.get("dataset")]

    def _metadata(self, env: gym.Env, plan: RunPlan, final: EvalStats) -> dict[str, Any]:
        """``metadata.json``: the env, the method (as it loads), the run's facts, the final evaluation."""
        method = {} if self.spec.algo == self.spec.name else {"method": self.spec.name}
        return build_metadata(
            env,
            self.env_id,
            plan.env_kwargs,
            algo=self.spec.algo,
            **method,
            seed=self.args.seed,
            timesteps=self.timesteps,
            config=plan.config.as_dict(),
            final_eval=final.as_dict(),
            **self.metadata(plan),
        )

    # ------------------------------------------------------- shared by plans
    def resumed(self) -> Resumed:
        """The run ``--resume`` continues: its state, checked against the arguments; seed and demos set.

        Raises:
            TrainingError: No or a damaged state, a run of another env or
                method, a ``--timesteps``, ``--seed``, ``--config`` or
                ``--demos`` that would change its budget, seed, config or
                demonstrations, no checkpoint, or one of another algorithm.
        """
        args, out = self.args, self.out
        saved = read_run_state(out)
        if saved["env_id"] != self.env_id or saved["algo"] != self.spec.name:
            held = f"{saved['algo']} run on {saved['env_id']}"
            raise TrainingError(f"{out} holds a {held}, not {self.spec.name} on {self.env_id}")
        total = saved["total_timesteps"]
        if args.timesteps is not None and args.timesteps != total:
            raise TrainingError(
                f"--resume continues {out}'s budget of {total} steps; --timesteps {args.timesteps} "
                "would change it (drop it, or train a new run with --out elsewhere)"
            )
        if args.seed is not None and args.seed != saved["seed"]:
            raise TrainingError(
                f"--resume continues {out}'s seed {saved['seed']}; --seed {args.seed} "
                "would change it (drop it, or train a new run with --out elsewhere)"
            )
        self._check_config(saved["config"])
        self._check_demos(saved["demos"])
        newest = newest_checkpoint(checkpoint_dir(out))
        if newest is None:
            raise TrainingError(f"nothing to resume in {checkpoint_dir(out)}: no checkpoint")
        algo = self.spec.model  # a checkpoint of another algorithm fails deep inside SB3's load
        check_checkpoint_policies(
            checkpoint_dir(out), policy_base(algo), f"{algo}, the algorithm of this {self.spec.name} run"
        )
        args.seed = saved["seed"]
        args.demos = saved["demos"]
        return Resumed(
            seed=saved["seed"], total=total, config=saved["config"], demos=saved["demos"], newest=newest
        )

    def _check_config(self, recorded: str | None) -> None:
        """Refuse a ``--config`` other than the run's, ``recorded`` (``None``: the packaged file).

        Seen: a run on the packaged config, resumed with ``--config FILE``,
        trained on FILE's entry and recorded FILE in ``train_state.json``; a
        run on a file of its own ignored ``--config`` without a word.

        Raises:
            TrainingError: ``--config`` names another file than the run's.
        """
        given = self.args.config
        own = Path(recorded) if recorded is not None else self.spec.default_config()
        if given is not None and Path(given).resolve() != own.resolve():
            shown = recorded if recorded is not None else f"the packaged {own.name}"
            raise TrainingError(
                f"--resume continues {self.out}'s config {shown}; --config {given} would change it "
                "(drop it, or train a new run with --out elsewhere)"
            )

    def _check_demos(self, recorded: str | None) -> None:
        """Refuse a ``--demos`` other than the run's, ``recorded`` (``None``: none), as Minari names them.

        Before, the run trained on the dataset given while its state still
        named the one it was started with.

        Raises:
            TrainingError: ``--demos`` names another dataset than the run's.
        """
        given = self.args.demos
        if given is None or (recorded is not None and dataset_id(given) == dataset_id(recorded)):
            return
        shown = f"demonstrations {recorded}" if recorded is not None else "run without demonstrations"
        raise TrainingError(
            f"--resume continues {self.out}'s {shown}; --demos {given} would change them "
            "(drop it, or train a new run with --out elsewhere)"
        )

    def episode_steps(self, env_kwargs: Mapping[str, Any]) -> int | None:
        """An episode's most steps: the config's ``max_episode_steps``, else the registered one."""
        limit = env_kwargs.get("max_episode_steps") or gym.spec(self.env_id).max_episode_steps
        return int(limit) if limit is not None else None

    def check_budget(self, resumed: Resumed, overshoot: int | None) -> None:
        """Refuse a budget below the steps the newest checkpoint has taken (an edited ``train_state.json``).

        A run may end up to one collection (``overshoot`` env steps: a PPO
        rollout, an off-policy ``train_freq``; ``None``: unbounded) past
        its budget, and a Ctrl-C during the final evaluation checkpoints that.

        Raises:
            TrainingError: The checkpoint's steps exceed the budget by more than ``overshoot``.
        """
        taken = checkpoint_steps(resumed.newest)
        if overshoot is not None and taken > resumed.total + overshoot:
            raise TrainingError(
                f"cannot resume from {self.out / STATE_NAME}: total_timesteps is {resumed.total}, below "
                f"the {taken} steps its checkpoint {resumed.newest.name} has taken"
            )

    def run_state(self, total: int, config: str | None, demos: str | None) -> dict[str, Any]:
        """The ``train_state.json`` of this run."""
        return {
            "env_id": self.env_id,
            "algo": self.spec.name,
            "seed": self.args.seed,
            "total_timesteps": int(total),
            "config": config,
            "demos": demos,
        }
