"""DAgger: behaviour cloning that asks the expert about the learner's own states (``--algo dagger``).

Ross, Gordon & Bagnell, "A Reduction of Imitation Learning and Structured
Prediction to No-Regret Online Learning" (AISTATS 2011). Plain behaviour
cloning trains on the states the expert visits; a small error takes the
learner to states the expert never saw, where it errs more (the
compounding error of long tasks: PickPlace is 200 steps of approach, descend,
squeeze, carry). DAgger closes that gap:

1. clone the expert's episodes (:func:`~bioscara_gym.training.imitation.fit_actor`);
2. roll out the learner, label every state it visits with the expert's action;
3. add them to the dataset, clone again from the aggregate; repeat.

Labelling a state the expert did not reach itself needs an expert whose
action is a function of the observation: the task's ``observation_expert``
(:data:`bioscara_gym.tasks.TASKS`; PickPlace's is
:class:`~bioscara_gym.experts.ObservationExpert`), and the learner reads the
observation through the task's ``extractor``
(:class:`~bioscara_gym.training.features.PickPlaceExtractor`).

It is PickPlace's default method (``bioscara train --env Bioscara-PickPlace``),
configured by ``training/configs/dagger.yaml``
(:class:`~bioscara_gym.training.dagger_config.DaggerConfig`); the model is a
SAC model whose actor was cloned, so ``eval``, ``export`` and ``deploy`` load
it as ``--algo bc``'s. Measured figures and the choices behind the config:
the README, "Learning PickPlace from demonstrations".
"""

from __future__ import annotations

import contextlib
import io
import math
import time
from collections.abc import Callable
from pathlib import Path
from typing import Any, BinaryIO

import gymnasium as gym
import numpy as np

from bioscara_gym.errors import HyperparamError, TrainingError
from bioscara_gym.tasks import GOAL_KEYS, Expert, Policy, task_of
from bioscara_gym.training.base import RunPlan, TrainingMethod
from bioscara_gym.training.checkpoints import checkpoint_dir, companion_path, load_newest, save_checkpoint
from bioscara_gym.training.dagger_config import DaggerConfig
from bioscara_gym.training.demos import Demos, check_demos, load_demos
from bioscara_gym.training.evaluate import EvalStats, run_episodes
from bioscara_gym.training.extras import needs_train
from bioscara_gym.training.labelling import Labelled, Rollouts, label_episodes, labelled
from bioscara_gym.training.parallel import label_rollouts, make_vec_envs, run_episodes_on
from bioscara_gym.training.signals import SignalGuard

with needs_train():
    from stable_baselines3 import SAC
    from stable_baselines3.common.logger import configure as configure_logger
    from stable_baselines3.common.vec_env import VecEnv

    from bioscara_gym.training.algos import sb3_policy

    # Models saved before issue #26 name their extractor here (SB3 pickles the class by path).
    from bioscara_gym.training.features import PickPlaceExtractor  # noqa: F401
    from bioscara_gym.training.imitation import fit_actor
    from bioscara_gym.training.zoo import EVAL_SEED_OFFSET

#: Seeds of the expert's episodes and of the learner's, relative to the run's seed.
DEMO_SEED = 1_000_000
ROLLOUT_SEED = 2_000_000
#: Seeds of the confirming evaluations, 100,000 per run seed: fresh episodes in every one, as a
#: failed one's states join the aggregate (the final evaluation's, seeds 10000..., never do).
CONFIRM_SEED = 3_000_000
#: Mixture shares below this count as the learner alone (its rollouts then serve as a quick evaluation).
BETA_NEGLIGIBLE = 0.05
#: The aggregate saved with each checkpoint, beside it.
CHECKPOINT_DATA = "_dagger.npz"


def expert_labeller(env: gym.Env) -> Expert:
    """The expert that labels any state of ``env``: its task's observation expert.

    Raises:
        TrainingError: The task has none (only PickPlace has one).
    """
    try:
        return task_of(env).make_observation_expert(env.unwrapped)
    except LookupError as e:
        raise TrainingError(
            f"DAgger needs an expert that can label any state; {env.spec.id if env.spec else env} has none "
            "(train it with --algo sac)"
        ) from e


# ------------------------------------------------------------------ checkpoints
def _write_aggregate(data: Labelled, iteration: int, env_steps: int) -> Callable[[BinaryIO], None]:
    """A writer of the aggregate, the iteration and the env steps, as ``numpy.savez``."""

    def write(f: BinaryIO) -> None:
        buffer = io.BytesIO()
        np.savez(
            buffer,
            actions=data.actions,
            row_iteration=data.iteration,
            iteration=iteration,
            env_steps=env_steps,
            **{f"obs_{k}": data.obs[k] for k in GOAL_KEYS},
        )
        f.write(buffer.getvalue())

    return write


def _load_dagger_checkpoint(path: Path, env: gym.Env) -> tuple[Any, Labelled, int, int]:
    """Model, aggregate, iteration and env steps of one checkpoint."""
    with np.load(companion_path(path, CHECKPOINT_DATA)) as z:
        data = Labelled(
            obs={k: z[f"obs_{k}"] for k in GOAL_KEYS}, actions=z["actions"], iteration=z["row_iteration"]
        )
        iteration, env_steps = int(z["iteration"]), int(z["env_steps"])
    return SAC.load(path, env=env, device="cpu"), data, iteration, env_steps


class _Progress:
    """A tqdm bar over env steps (silent when disabled)."""

    def __init__(self, total: int, enabled: bool, done: int) -> None:
        from tqdm.auto import tqdm

        self.bar = tqdm(total=total, initial=done, desc="dagger", unit="step", disable=not enabled)

    def episode(self, steps: int, **postfix: str) -> None:
        self.bar.update(steps)
        if postfix:
            self.bar.set_postfix(postfix)

    def close(self) -> None:
        self.bar.close()


# ---------------------------------------------------------------------- method
class DAgger(TrainingMethod):
    """``bioscara train`` with DAgger (see the module docstring): clone, roll out, label, aggregate, repeat.

    ``--timesteps`` is the budget in env steps, the expert's episodes
    included; ``--demos NAME`` replaces the expert's own episodes by a
    dataset's. A checkpoint (model and aggregate) is written after every
    iteration; ``--resume`` continues from the newest. Training stops once
    the learner's own rollouts reach the target and a confirmation
    (:meth:`confirmation`: ``eval_episodes`` fresh episodes of the learner
    alone) confirms it; a confirmation that falls short joins the aggregate.
    """

    data: Labelled | None = None
    iteration_done = 0
    env_steps = 0
    #: The rollouts' and evaluations' workers (``n_envs`` above 1), else None.
    venv: VecEnv | None = None

    def plan(self) -> RunPlan:
        """The DAgger entry (``--config``, the run's on ``--resume``, else ``dagger.yaml``) and budget."""
        args = self.args
        if args.resume:
            resumed = self.resumed()
            cfg = self._config(resumed.config)
            # A run ends at most one phase past its budget: the expert's episodes, or an
            # iteration's rollouts and a confirmation.
            episodes = max(cfg.demo_episodes, cfg.episodes_per_iteration + cfg.eval_episodes)
            steps = self.episode_steps(cfg.env_kwargs)
            self.check_budget(resumed, None if steps is None else episodes * steps)
            total, config, demos = resumed.total, resumed.config, resumed.demos
        else:
            config = str(args.config) if args.config else None
            cfg = self._config(config)
            total, demos = int(args.timesteps or cfg.n_timesteps), args.demos
        self.cfg = cfg
        return RunPlan(cfg, cfg.env_kwargs, int(total), self.run_state(total, config, demos))

    def _config(self, config: str | None) -> DaggerConfig:
        path = Path(config) if config else self.spec.default_config()
        try:
            return self.spec.load_config(path, self.env_id)
        except HyperparamError as e:
            raise TrainingError(str(e)) from e

    def make_envs(self, plan: RunPlan, stack: contextlib.ExitStack) -> gym.Env:
        """The env the learner and the expert act in, the evaluation env, the expert, the demonstrations."""
        self.stack = stack
        self.env = stack.enter_context(contextlib.closing(gym.make(self.env_id, **plan.env_kwargs)))
        self.eval_env = stack.enter_context(contextlib.closing(gym.make(self.env_id, **plan.env_kwargs)))
        self.expert = expert_labeller(self.env)
        n_envs = self.args.n_envs or plan.config.n_envs
        if n_envs > 1:  # the rollouts run on workers in subprocesses (training/parallel.py)
            self.venv = make_vec_envs(self.env_id, n_envs, plan.env_kwargs)
            stack.callback(self.venv.close)
        self.demos = None
        if self.args.demos:
            self.demos = load_demos(self.args.demos)
            check_demos(self.demos, self.env)
        return self.env

    def build_model(self, plan: RunPlan) -> Any:
        """A SAC model (``buffer_size`` 1) for DAgger to train, or on ``--resume`` the newest checkpoint."""
        if self.args.resume:
            loaded, _ = load_newest(
                checkpoint_dir(self.out), lambda path: _load_dagger_checkpoint(path, self.env)
            )
            model, self.data, self.iteration_done, self.env_steps = loaded
            return model
        cfg = plan.config
        extractor = task_of(self.env).extractor_class()
        # What the extractor takes from the env (FROM_ENV: names of its public properties).
        from_env = {name: getattr(self.env.unwrapped, name) for name in getattr(extractor, "FROM_ENV", ())}
        policy_kwargs = {
            "net_arch": list(cfg.net_arch),
            "features_extractor_class": extractor,
            "features_extractor_kwargs": {**cfg.features, **from_env},
        }
        try:
            return SAC(
                "MultiInputPolicy",
                self.env,
                buffer_size=1,
                seed=self.args.seed,
                device="cpu",
                policy_kwargs=policy_kwargs,
            )
        except (TypeError, ValueError) as e:
            raise TrainingError(f"config {cfg.source}: {e}") from e

    def learn(self, plan: RunPlan, callbacks: list[Any], guard: SignalGuard) -> None:
        """Iteration 0 (or the checkpoint's), then iterations until the target or the budget."""
        self.logger = configure_logger(str(self.out / "tb" / "dagger"), ["tensorboard"])
        self.stack.callback(self.logger.close)
        self.progress = _Progress(plan.total, self.args.progress, self.env_steps)
        self.final: EvalStats | None = None
        try:
            if self.data is None:
                self.data, self.env_steps = self.first_iteration(self.demos)
                self.checkpoint()
            while self.env_steps < plan.total:
                self.data, self.env_steps, self.final = self.iteration(
                    self.iteration_done + 1, self.data, self.env_steps
                )
                self.iteration_done += 1  # only once done: an interrupted iteration is run again on --resume
                if self.final is not None:
                    break
                with guard.shielded():
                    self.checkpoint()
        finally:
            self.progress.close()

    def evaluate(self, plan: RunPlan) -> EvalStats:
        """The evaluation that confirmed the target, else ``eval_episodes`` episodes now."""
        return self.final if self.final is not None else self.evaluation(self.env_steps)

    def checkpoint(self) -> Path | None:
        """Model and aggregate as ``ckpt_<env steps>_steps.zip`` and ``..._dagger.npz``.

        Nothing is saved before iteration 0 has labelled its states.
        """
        if not self.data:
            return None
        write = _write_aggregate(self.data, self.iteration_done, self.env_steps)
        return save_checkpoint(self.model, checkpoint_dir(self.out), self.env_steps, {CHECKPOINT_DATA: write})

    @property
    def timesteps(self) -> int:
        """Env steps, the expert's included."""
        return self.env_steps

    def metadata(self, plan: RunPlan) -> dict[str, Any]:
        """The iterations, the labelled states and the demonstrations."""
        dagger = {
            "iterations": self.iteration_done,
            "labelled_states": len(self.data) if self.data else 0,
            "demos": self.args.demos,
            "wall_time_s": round(time.perf_counter() - self.start, 1),
        }
        return {"dagger": dagger}

    # ------------------------------------------------------------- iterations
    def _say(self, text: str) -> None:
        if self.args.verbose:
            self.progress.bar.write(text) if self.args.progress else print(text, flush=True)

    def _rollouts(
        self,
        act: Policy,
        episodes: int,
        seed: int,
        iteration: int,
        beta: float,
        max_failures: int | None = None,
    ) -> Rollouts:
        def on_episode(success: bool, steps: int) -> None:
            self.progress.episode(steps, iteration=str(iteration))

        rng = np.random.default_rng([self.args.seed, iteration])
        expert = self.expert
        if self.venv is None:
            args = (self.env, act, expert, episodes, seed, iteration, beta, rng, on_episode)
            return label_episodes(*args, max_failures=max_failures)
        rows, labels, results = label_rollouts(
            self.venv, act, expert, episodes, seed, beta, rng, on_episode, max_failures=max_failures
        )
        return Rollouts(labelled(rows, labels, iteration), tuple(results))

    def _fit(self, data: Labelled, steps: int, iteration: int) -> float:
        cfg, seed = self.cfg, self.args.seed * 1000 + iteration
        return fit_actor(
            self.model,
            data.obs,
            data.actions,
            steps,
            cfg.batch_size,
            cfg.learning_rate,
            seed=seed,
            threads=cfg.fit_threads,
            loss=cfg.loss,
        )

    def first_iteration(self, demos: Demos | None) -> tuple[Labelled, int]:
        """Iteration 0: the expert's episodes (or the dataset's), cloned."""
        cfg = self.cfg
        if demos is None:
            seed = DEMO_SEED + 10_000 * self.args.seed
            r = self._rollouts(self.expert, cfg.demo_episodes, seed, 0, 1.0)
            data, steps = r.data, len(r.data)
            source = f"{r.episodes} expert episodes ({r.success_rate:.0%} success)"
        else:
            data, steps, source = Labelled.from_demos(demos), 0, f"dataset {demos.dataset_id}"
        loss = self._fit(data, cfg.bc_steps_first, 0)
        self._log(0, steps, data, loss, None, 1.0)
        self._say(f"[dagger] iteration 0: cloned {len(data)} states of {source}, loss {loss:.4f}")
        return data, steps

    def iteration(self, i: int, data: Labelled, env_steps: int) -> tuple[Labelled, int, EvalStats | None]:
        """Roll out the learner (mixed with the expert); stop if it is good enough, else aggregate, refit."""
        cfg = self.cfg
        beta = cfg.beta**i
        seed = ROLLOUT_SEED + 10_000 * self.args.seed + (i - 1) * cfg.episodes_per_iteration
        r = self._rollouts(sb3_policy(self.model), cfg.episodes_per_iteration, seed, i, beta)
        env_steps += len(r.data)
        mixed = f" (expert {beta:.0%})" if beta else ""
        elapsed = time.perf_counter() - self.start
        self._say(
            f"[dagger] iteration {i}: learner{mixed} {r.success_rate:.0%} success over "
            f"{r.episodes} episodes, {elapsed:.0f} s"
        )
        new = r.data
        if beta < BETA_NEGLIGIBLE and r.success_rate >= cfg.target_success:
            check = self.confirmation(i, env_steps)
            if check.success_rate >= cfg.target_success:
                self.reached_at, self.reached_after_s = env_steps, time.perf_counter() - self.start
                self._say(f"[dagger] target reached after {env_steps} steps, {self.reached_after_s:.0f} s")
                return data, env_steps, check.stats
            new, env_steps = new + check.data, env_steps + len(check.data)
        data = data + new
        loss = self._fit(data, cfg.bc_steps, i)
        self._log(i, env_steps, data, loss, r.success_rate, beta)
        return data, env_steps, None

    def confirmation(self, i: int, env_steps: int) -> Rollouts:
        """The learner alone on ``eval_episodes`` fresh, labelled episodes, cut once the target is lost.

        Fresh seeds in every iteration (``CONFIRM_SEED``): when it fails, its
        states join the aggregate as the iteration's rollouts do, rather than
        being thrown away (on Stack the confirmations were a third of a run),
        and no confirmation sees an episode the learner was fitted on. The
        decision is the one-env evaluation's: at most the failures the target
        leaves.
        """
        n = self.cfg.eval_episodes
        allowed = n - math.ceil(n * self.cfg.target_success - 1e-9)
        seed = CONFIRM_SEED + 100_000 * self.args.seed + (i - 1) * n
        check = self._rollouts(sb3_policy(self.model), n, seed, i, 0.0, max_failures=allowed)
        self._report(check.stats, env_steps, n)
        return check

    def evaluation(self, env_steps: int) -> EvalStats:
        """Success over ``eval_episodes`` seeded episodes (seeds from the run's seed + 10000)."""
        n = self.cfg.eval_episodes
        seed, act = self.args.seed + EVAL_SEED_OFFSET, sb3_policy(self.model)
        if self.venv is None:
            stats = run_episodes(self.eval_env, act, n, seed=seed)
        else:  # on the rollouts' workers: the same episodes, the same stats
            stats = run_episodes_on(self.venv, act, n, seed=seed)
        self._report(stats, env_steps, n)
        return stats

    def _report(self, stats: EvalStats, env_steps: int, n: int) -> None:
        """An evaluation's success to tensorboard and (verbose) the console; ``n``: the episodes asked for."""
        elapsed = time.perf_counter() - self.start
        self.logger.record("eval/success_rate", stats.success_rate)
        self.logger.record("eval/mean_final_distance", stats.mean_final_distance)
        self.logger.dump(env_steps)
        cut = f" (stopped: {stats.episodes - round(stats.success_rate * stats.episodes)} failures)"
        self._say(
            f"[eval] step {env_steps:>7}  {elapsed:.0f} s  success {stats.success_rate * 100:.1f}% "
            f"over {stats.episodes}{cut if stats.episodes < n else ''}"
        )

    def _log(
        self, i: int, env_steps: int, data: Labelled, loss: float, success: float | None, beta: float
    ) -> None:
        self.logger.record("dagger/iteration", i)
        self.logger.record("dagger/labelled_states", len(data))
        self.logger.record("dagger/bc_loss", loss)
        self.logger.record("dagger/beta", beta)
        if success is not None:
            self.logger.record("dagger/rollout_success", success)
        self.logger.record("time/wall_s", time.perf_counter() - self.start)
        self.logger.dump(env_steps)
