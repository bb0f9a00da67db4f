"""``bioscara train --algo bc``: behaviour cloning alone, the offline baseline.

The demonstrations (``--demos NAME``, else the scripted expert's episodes)
are cloned into the actor of a SAC model (:func:`~bioscara_gym.training.imitation.bc_pretrain`),
so ``bioscara eval``, ``export`` and ``deploy`` load the result like any SAC
model (its metadata says ``algo: bc``).
"""

from __future__ import annotations

import contextlib
from pathlib import Path
from typing import Any

import gymnasium as gym
import numpy as np

from bioscara_gym.errors import TrainingError
from bioscara_gym.tasks import task_of
from bioscara_gym.training.base import RunPlan, TrainingMethod
from bioscara_gym.training.demos import check_demos, load_demos, rollout_demos
from bioscara_gym.training.evaluate import EvalStats, run_episodes
from bioscara_gym.training.extras import needs_train
from bioscara_gym.training.signals import SignalGuard

with needs_train():
    from stable_baselines3 import SAC

    from bioscara_gym.training.imitation import bc_pretrain
    from bioscara_gym.training.sb3 import algo_kwargs, load_run_hyperparams
    from bioscara_gym.training.zoo import EVAL_SEED_OFFSET, DemonstrationCallback

#: Behaviour-cloning steps of ``bioscara train --algo bc`` without ``--timesteps``.
BC_STEPS = 10_000


class BehaviourCloning(TrainingMethod):
    """``bioscara train --algo bc``: clone the demonstrations into a SAC actor, evaluate, save.

    The policy, its kwargs and the env's kwargs are those of the SAC config's
    entry; ``--timesteps`` counts gradient steps (default :data:`BC_STEPS`).
    Without ``--demos`` the scripted expert's episodes are collected first,
    as many as the entry's :class:`~bioscara_gym.training.zoo.DemonstrationCallback`
    says (100 by default). It trains in one go: nothing to resume.
    """

    def plan(self) -> RunPlan:
        """SAC's entry (``--config``, else the packaged ``sac.yaml``) and the gradient steps."""
        if self.args.resume:
            raise TrainingError("--algo bc trains in one go; there is nothing to resume")
        path = Path(self.args.config) if self.args.config else self.spec.default_config()
        hp = load_run_hyperparams(self.spec.model, path, self.env_id)
        return RunPlan(hp, hp.env_kwargs, int(self.args.timesteps or BC_STEPS), None)

    def make_envs(self, plan: RunPlan, stack: contextlib.ExitStack) -> gym.Env:
        """The env the demonstrations run on and the evaluation env."""
        self.env = stack.enter_context(contextlib.closing(gym.make(self.env_id, **plan.env_kwargs)))
        self.eval_env = stack.enter_context(contextlib.closing(gym.make(self.env_id, **plan.env_kwargs)))
        return self.env

    def build_model(self, plan: RunPlan) -> SAC:
        """A SAC model of the entry's policy, without a replay buffer (nothing is replayed)."""
        kwargs = algo_kwargs(plan.config, self.env, "sac")
        kwargs.update(replay_buffer_class=None, replay_buffer_kwargs=None, buffer_size=1, action_noise=None)
        return SAC(plan.config.policy, self.env, seed=self.args.seed, device="cpu", verbose=0, **kwargs)

    def learn(self, plan: RunPlan, callbacks: list[Any], guard: SignalGuard) -> None:
        """Load (``--demos``) or collect the demonstrations, clone them for ``plan.total`` gradient steps."""
        settings = next((k for c, k in plan.config.callbacks if c is DemonstrationCallback), {})
        if self.args.demos:
            self.demos = load_demos(self.args.demos, successful_only=True)
            check_demos(self.demos, self.env)
        else:
            expert = task_of(self.env).make_expert(self.env.unwrapped)
            episodes, seed = int(settings.get("episodes", 100)), int(settings.get("seed", 1_000_000))
            self.demos = rollout_demos(self.env, expert, expert.reset, episodes, seed=seed)
        init_std = float(settings.get("init_std", 0.1))
        self.loss = bc_pretrain(self.model, self.demos, plan.total, init_std=init_std, seed=self.args.seed)
        if self.args.verbose:
            print(f"[bc] {plan.total} steps on {len(self.demos)} demonstration steps, loss {self.loss:.4f}")

    def evaluate(self, plan: RunPlan) -> EvalStats:
        """``eval_episodes`` seeded episodes of the cloned actor (seeds from the run's seed + 10000)."""

        def act(obs: dict[str, np.ndarray]) -> np.ndarray:
            return self.model.predict(obs, deterministic=True)[0]

        episodes, seed = plan.config.eval_episodes, self.args.seed + EVAL_SEED_OFFSET
        return run_episodes(self.eval_env, act, episodes, seed=seed)

    @property
    def timesteps(self) -> int:
        """None: the demonstrations' steps are not the learner's."""
        return 0

    def metadata(self, plan: RunPlan) -> dict[str, Any]:
        """The gradient steps, the final loss and the demonstrations."""
        demos = {"dataset": self.args.demos, "episodes": len(self.demos.successes), "steps": len(self.demos)}
        return {"bc_steps": plan.total, "bc_loss": self.loss, "demos": demos}
