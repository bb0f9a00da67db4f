"""Learning from demonstrations: behaviour cloning, and SAC with demonstrations (Nair et al. 2018).

* :func:`bc_pretrain` fits an SB3 actor's deterministic action to the
  demonstrated actions (mean squared error); SAC's exploration noise is set
  to ``init_std`` at the same time (its state-dependent ``log_std`` regressed
  to ``log(init_std)``), so the first rollouts look like the demonstrations
  rather than like noise.
* :func:`attach_demos` turns a SAC model into one that learns from
  demonstrations as in Nair et al., "Overcoming Exploration in Reinforcement
  Learning with Demonstrations" (ICRA 2018): the demonstrations are kept in a
  buffer of their own and ``demo_batch_size`` of them join every batch; the
  critic learns from them like from any transition, and the actor gets a
  behaviour-cloning loss on them, kept only where the critic rates the
  demonstrated action above the actor's (the Q-filter). HER relabels the
  agent's own transitions (the model's ``HerReplayBuffer``).
* ``bioscara train --algo bc`` (:class:`~bioscara_gym.training.bc.BehaviourCloning`): behaviour
  cloning alone, the offline baseline; the result is a SAC model whose actor
  was only cloned, so ``bioscara eval``, ``export`` and ``deploy`` load it
  like any SAC model (its metadata says ``algo: bc``).
"""

from __future__ import annotations

import contextlib
import math
from collections.abc import Iterator
from dataclasses import dataclass
from typing import Any

import numpy as np

from bioscara_gym.tasks import GOAL_KEYS
from bioscara_gym.training.demos import Demos
from bioscara_gym.training.extras import needs_train
from bioscara_gym.training.literals import ACTION_LOSSES

with needs_train():
    import torch as th
    import torch.nn.functional as F
    from stable_baselines3 import SAC
    from stable_baselines3.common.utils import polyak_update
    from stable_baselines3.sac.policies import LOG_STD_MAX, LOG_STD_MIN


@dataclass
class DemoBuffer:
    """Demonstration transitions as tensors, sampled uniformly."""

    obs: dict[str, th.Tensor]
    next_obs: dict[str, th.Tensor]
    actions: th.Tensor
    rewards: th.Tensor
    dones: th.Tensor

    @classmethod
    def from_demos(cls, demos: Demos, rewards: np.ndarray) -> DemoBuffer:
        """Tensors of ``demos`` with ``rewards`` (recomputed by the training env's reward)."""

        def t(a: np.ndarray) -> th.Tensor:
            return th.as_tensor(np.asarray(a), dtype=th.float32)

        return cls(
            obs={k: t(demos.obs[k]) for k in GOAL_KEYS},
            next_obs={k: t(demos.next_obs[k]) for k in GOAL_KEYS},
            actions=t(demos.actions),
            rewards=t(rewards).reshape(-1, 1),
            dones=t(demos.dones).reshape(-1, 1),
        )

    def __len__(self) -> int:
        """Number of transitions."""
        return len(self.actions)

    def sample(self, n: int, generator: th.Generator | None = None) -> tuple[Any, ...]:
        """``n`` transitions: obs, actions, next_obs, rewards, dones."""
        idx = th.randint(len(self), (n,), generator=generator)
        return (
            {k: v[idx] for k, v in self.obs.items()},
            self.actions[idx],
            {k: v[idx] for k, v in self.next_obs.items()},
            self.rewards[idx],
            self.dones[idx],
        )


def _deterministic(actor: Any, obs: dict[str, th.Tensor]) -> tuple[th.Tensor, th.Tensor | None]:
    """The actor's deterministic action (in [-1, 1]) and, for SAC, its ``log_std``."""
    if hasattr(actor, "get_action_dist_params"):  # SAC
        mean, log_std, _ = actor.get_action_dist_params(obs)
        return th.tanh(mean), log_std
    return actor(obs), None  # TD3


def _fixed_features(actor: Any, obs: dict[str, th.Tensor]) -> th.Tensor | None:
    """Every row's features, computed once, or ``None`` if they can change while the actor learns.

    They are fixed when the features extractor has no parameters (every
    extractor of this package, and SB3's flattening one) and the actor is
    TD3's or SAC's without gSDE (:func:`_deterministic_of_features` is then
    what ``get_action_dist_params`` and ``forward`` compute after the
    extractor). The extractors work row by row, so a row's features are the
    same whether it is computed alone, in a batch or in the whole set.
    """
    if any(True for _ in actor.features_extractor.parameters()) or getattr(actor, "use_sde", False):
        return None
    with th.no_grad():
        return actor.extract_features(obs, actor.features_extractor)


def _deterministic_of_features(actor: Any, features: th.Tensor) -> tuple[th.Tensor, th.Tensor | None]:
    """:func:`_deterministic` from the extractor's output (SAC without gSDE, or TD3)."""
    if hasattr(actor, "get_action_dist_params"):  # SAC: its get_action_dist_params after the extractor
        latent = actor.latent_pi(features)
        log_std = th.clamp(actor.log_std(latent), LOG_STD_MIN, LOG_STD_MAX)
        return th.tanh(actor.mu(latent)), log_std
    return actor.mu(features), None  # TD3: its forward after the extractor (mu ends in tanh)


def bc_pretrain(
    model: Any,
    demos: Demos,
    steps: int = 3000,
    batch_size: int = 256,
    learning_rate: float = 1e-3,
    init_std: float = 0.1,
    seed: int = 0,
) -> float:
    """Fit ``model``'s actor to the demonstrated actions; the final loss.

    Uses its own Adam optimizer (the model's keeps its state). For TD3 the
    target actor is synced afterwards.
    """
    return fit_actor(model, demos.obs, demos.actions, steps, batch_size, learning_rate, init_std, seed)


#: torch's function of each action loss a fit knows (:data:`~bioscara_gym.training.literals.ACTION_LOSSES`).
LOSS_FUNCTIONS = {"mse": F.mse_loss, "l1": F.l1_loss}


def fit_actor(
    model: Any,
    obs: dict[str, np.ndarray],
    actions: np.ndarray,
    steps: int = 3000,
    batch_size: int = 256,
    learning_rate: float = 1e-3,
    init_std: float = 0.1,
    seed: int = 0,
    threads: int | None = None,
    loss: str = "mse",
) -> float:
    """Fit ``model``'s actor to ``actions`` in ``obs`` (rows of :data:`GOAL_KEYS` arrays); the final loss.

    The loss is the deterministic action's error, squared (``loss="mse"``)
    or absolute (``"l1"``: where the labels of like states disagree, the fit
    takes their median, not their mean), plus, for SAC, ``log_std`` pulled
    to ``log(init_std)``. Uses its own Adam optimizer (the model's keeps its
    state); for TD3 the target actor is synced afterwards. ``threads``:
    torch's CPU threads during the fit (then back to what they were);
    ``None``: as they are. The fit's numbers depend on the count.

    Raises:
        ValueError: ``loss`` is not one of
            :data:`~bioscara_gym.training.literals.ACTION_LOSSES`.
    """
    if loss not in ACTION_LOSSES:
        raise ValueError(f"loss {loss!r}: expected one of {', '.join(ACTION_LOSSES)}")
    with torch_threads(threads):
        return _fit_actor(model, obs, actions, steps, batch_size, learning_rate, init_std, seed, loss)


@contextlib.contextmanager
def torch_threads(n: int | None) -> Iterator[None]:
    """Set torch's CPU threads to ``n`` inside the block, and back after it (``None``: untouched)."""
    if n is None:
        yield
        return
    before = th.get_num_threads()
    th.set_num_threads(n)
    try:
        yield
    finally:
        th.set_num_threads(before)


def _fit_actor(
    model: Any,
    obs: dict[str, np.ndarray],
    actions: np.ndarray,
    steps: int,
    batch_size: int,
    learning_rate: float,
    init_std: float,
    seed: int,
    loss_name: str,
) -> float:
    actor = model.actor
    action_loss = LOSS_FUNCTIONS[loss_name]
    actor.set_training_mode(True)
    obs_t = {k: th.as_tensor(np.asarray(obs[k]), dtype=th.float32) for k in GOAL_KEYS}
    act_t = th.as_tensor(np.asarray(actions), dtype=th.float32)
    # fused: one kernel for the whole update, not a loop over the parameters
    # (foreach's multi-tensor update was a quarter of a gradient step)
    opt = th.optim.Adam(actor.parameters(), lr=learning_rate, fused=True)
    gen = th.Generator().manual_seed(seed)
    target_log_std = math.log(init_std)
    loss = th.zeros(())
    # the features of every row once, not of every batch again (14 % of a step)
    features = _fixed_features(actor, obs_t)
    for _ in range(int(steps)):
        idx = th.randint(len(act_t), (batch_size,), generator=gen)
        if features is None:
            pred, log_std = _deterministic(actor, {k: v[idx] for k, v in obs_t.items()})
        else:
            pred, log_std = _deterministic_of_features(actor, features[idx])
        loss = action_loss(pred, act_t[idx])
        if log_std is not None:
            loss = loss + 0.1 * F.mse_loss(log_std, th.full_like(log_std, target_log_std))
        opt.zero_grad()
        loss.backward()
        opt.step()
    actor.set_training_mode(False)
    if getattr(model, "actor_target", None) is not None:
        model.actor_target.load_state_dict(actor.state_dict())
    return float(loss.item())


class DemoSAC(SAC):
    """SAC whose batches include demonstrations, with a Q-filtered BC loss (see the module docstring).

    Made from a plain SAC model by :func:`attach_demos`; saved, it loads as a
    plain SAC (the demonstrations are not saved with it).
    """

    demo_buffer: DemoBuffer | None = None
    demo_batch_size: int = 128
    bc_weight: float = 1.0
    q_filter: bool = True

    def _excluded_save_params(self) -> list[str]:
        return [*super()._excluded_save_params(), "demo_buffer", "demo_batch_size", "bc_weight", "q_filter"]

    def train(self, gradient_steps: int, batch_size: int = 64) -> None:
        """SAC's update (stable-baselines3 2.x) with demonstrations in every batch."""
        if self.demo_buffer is None:
            return super().train(gradient_steps, batch_size)
        self.policy.set_training_mode(True)
        optimizers = [self.actor.optimizer, self.critic.optimizer]
        if self.ent_coef_optimizer is not None:
            optimizers += [self.ent_coef_optimizer]
        self._update_learning_rate(optimizers)
        keys = ("actor_loss", "critic_loss", "bc_loss", "q_filter_kept")
        losses: dict[str, list[float]] = {k: [] for k in keys}
        for gradient_step in range(gradient_steps):
            batch, demo = self._mixed_batch(batch_size)
            obs = batch[0]
            actions_pi, log_prob = self.actor.action_log_prob(obs)
            log_prob = log_prob.reshape(-1, 1)
            ent_coef = self._entropy_coefficient(log_prob)
            losses["critic_loss"].append(self._critic_step(batch, ent_coef))
            for key, value in self._actor_step(obs, actions_pi, log_prob, ent_coef, demo).items():
                losses[key].append(value)
            if gradient_step % self.target_update_interval == 0:
                polyak_update(self.critic.parameters(), self.critic_target.parameters(), self.tau)
                polyak_update(self.batch_norm_stats, self.batch_norm_stats_target, 1.0)
        self._n_updates += gradient_steps
        self.logger.record("train/n_updates", self._n_updates, exclude="tensorboard")
        for key, values in losses.items():
            self.logger.record(f"train/{key}", np.mean(values))
        return None

    def _mixed_batch(self, batch_size: int) -> tuple[tuple[Any, ...], tuple[Any, Any]]:
        """``batch_size`` replayed transitions and ``demo_batch_size`` demonstrations, concatenated.

        Returns:
            (obs, actions, next_obs, rewards, dones) of both, and the demonstrations' (obs, actions).
        """
        data = self.replay_buffer.sample(batch_size, env=self._vec_normalize_env)  # type: ignore[union-attr]
        d_obs, d_act, d_next, d_rew, d_done = self.demo_buffer.sample(self.demo_batch_size)
        obs = {k: th.cat((data.observations[k], d_obs[k])) for k in GOAL_KEYS}
        next_obs = {k: th.cat((data.next_observations[k], d_next[k])) for k in GOAL_KEYS}
        actions = th.cat((data.actions, d_act))
        rewards = th.cat((data.rewards, d_rew))
        dones = th.cat((data.dones, d_done))
        return (obs, actions, next_obs, rewards, dones), (d_obs, d_act)

    def _entropy_coefficient(self, log_prob: th.Tensor) -> th.Tensor:
        """SAC's entropy coefficient, after its own update where it is learned."""
        if self.ent_coef_optimizer is None or self.log_ent_coef is None:
            return self.ent_coef_tensor
        ent_coef = th.exp(self.log_ent_coef.detach())
        ent_coef_loss = -(self.log_ent_coef * (log_prob + self.target_entropy).detach()).mean()
        self.ent_coef_optimizer.zero_grad()
        ent_coef_loss.backward()
        self.ent_coef_optimizer.step()
        return ent_coef

    def _critic_step(self, batch: tuple[Any, ...], ent_coef: th.Tensor) -> float:
        """One critic update on the mixed batch; its loss."""
        obs, actions, next_obs, rewards, dones = batch
        with th.no_grad():
            next_actions, next_log_prob = self.actor.action_log_prob(next_obs)
            next_q = th.cat(self.critic_target(next_obs, next_actions), dim=1)
            next_q, _ = th.min(next_q, dim=1, keepdim=True)
            next_q = next_q - ent_coef * next_log_prob.reshape(-1, 1)
            target_q = rewards + (1 - dones) * self.gamma * next_q
        current_q = self.critic(obs, actions)
        critic_loss = 0.5 * sum(F.mse_loss(q, target_q) for q in current_q)
        assert isinstance(critic_loss, th.Tensor)
        self.critic.optimizer.zero_grad()
        critic_loss.backward()
        self.critic.optimizer.step()
        return critic_loss.item()

    def _actor_step(
        self, obs: Any, actions_pi: th.Tensor, log_prob: th.Tensor, ent_coef: th.Tensor, demo: tuple[Any, Any]
    ) -> dict[str, float]:
        """One actor update: SAC's loss plus behaviour cloning where the critic prefers the demonstration."""
        d_obs, d_act = demo
        q_pi = th.cat(self.critic(obs, actions_pi), dim=1)
        min_q_pi, _ = th.min(q_pi, dim=1, keepdim=True)
        actor_loss = (ent_coef * log_prob - min_q_pi).mean()
        pred, _ = _deterministic(self.actor, d_obs)
        bc_err = ((pred - d_act) ** 2).sum(dim=1, keepdim=True)
        if self.q_filter:  # the Q-filter
            with th.no_grad():
                q_demo = th.min(th.cat(self.critic(d_obs, d_act), dim=1), dim=1, keepdim=True)[0]
                q_actor = th.min(th.cat(self.critic(d_obs, pred), dim=1), dim=1, keepdim=True)[0]
                mask = (q_demo > q_actor).float()
        else:
            mask = th.ones_like(bc_err)
        bc_loss = (mask * bc_err).mean()
        actor_loss = actor_loss + self.bc_weight * bc_loss
        self.actor.optimizer.zero_grad()
        actor_loss.backward()
        self.actor.optimizer.step()
        kept = mask.mean().item()
        return {"actor_loss": actor_loss.item(), "bc_loss": bc_loss.item(), "q_filter_kept": kept}


def attach_demos(
    model: Any,
    demos: Demos,
    rewards: np.ndarray,
    demo_batch_size: int = 128,
    bc_weight: float = 1.0,
    q_filter: bool = True,
) -> None:
    """Make SAC ``model`` learn from ``demos`` too (its class becomes :class:`DemoSAC`).

    Raises:
        TypeError: ``model`` is not a SAC model.
    """
    if not isinstance(model, SAC):
        raise TypeError(f"demonstrations need a SAC model, got {type(model).__name__}")
    model.__class__ = DemoSAC
    model.demo_buffer = DemoBuffer.from_demos(demos, rewards)
    model.demo_batch_size = int(demo_batch_size)
    model.bc_weight = float(bc_weight)
    model.q_filter = bool(q_filter)
