"""Fitting an actor to labelled states (`fit_actor`: DAgger's and behaviour cloning's fit).

The features of a fixed extractor are computed once for the whole set, not
again for every batch: the fit must be the same, bit for bit, and fall back
to the per-batch path wherever the features could change while it learns.
"""

from __future__ import annotations

import gymnasium as gym
import numpy as np
import pytest

import bioscara_gym  # noqa: F401

th = pytest.importorskip("torch", reason="torch is in the [train] extra")
from stable_baselines3 import SAC, TD3  # noqa: E402
from stable_baselines3.common.torch_layers import BaseFeaturesExtractor  # noqa: E402

from bioscara_gym.tasks import GOAL_KEYS  # noqa: E402
from bioscara_gym.training import imitation  # noqa: E402
from bioscara_gym.training.features import PickPlaceExtractor  # noqa: E402

PICK = "Bioscara-PickPlace-v1"


class LearningExtractor(BaseFeaturesExtractor):
    """An extractor with weights of its own: its features change as the actor learns."""

    def __init__(self, observation_space: gym.spaces.Dict) -> None:
        n = sum(observation_space[k].shape[0] for k in GOAL_KEYS)
        super().__init__(observation_space, features_dim=8)
        self.layer = th.nn.Linear(n, 8)

    def forward(self, observations: dict[str, th.Tensor]) -> th.Tensor:
        return self.layer(th.cat([observations[k] for k in GOAL_KEYS], dim=1))


@pytest.fixture(scope="module")
def env() -> gym.Env:
    e = gym.make(PICK, backend="mock", control_mode="cartesian")
    yield e
    e.close()


def model_of(
    env: gym.Env, algo: type = SAC, extractor: type = PickPlaceExtractor, **kwargs: object
) -> object:
    policy_kwargs = {"net_arch": [32, 32], "features_extractor_class": extractor}
    if extractor is PickPlaceExtractor:
        policy_kwargs["features_extractor_kwargs"] = {"joint_range": env.unwrapped.joint_range}
    return algo(
        "MultiInputPolicy", env, buffer_size=1, seed=0, device="cpu", policy_kwargs=policy_kwargs, **kwargs
    )


def labelled(env: gym.Env, n: int = 500) -> tuple[dict[str, np.ndarray], np.ndarray]:
    env.observation_space.seed(1)
    samples = [env.observation_space.sample() for _ in range(n)]
    obs = {k: np.stack([s[k] for s in samples]).astype(np.float32) for k in GOAL_KEYS}
    actions = np.random.default_rng(2).uniform(-1, 1, (n, env.action_space.shape[0])).astype(np.float32)
    return obs, actions


def weights(model: object) -> th.Tensor:
    return th.cat([p.detach().flatten() for p in model.actor.parameters()])


@pytest.mark.parametrize("algo", [SAC, TD3])
def test_a_fit_on_features_computed_once_is_the_per_batch_fit_bit_for_bit(
    env: gym.Env, algo: type, monkeypatch: pytest.MonkeyPatch
) -> None:
    obs, actions = labelled(env)
    once, per_batch = model_of(env, algo), model_of(env, algo)  # seeded: the same start
    start = weights(once).clone()
    assert th.equal(start, weights(per_batch))
    loss_once = imitation.fit_actor(once, obs, actions, steps=40, batch_size=32, seed=5)
    monkeypatch.setattr(imitation, "_fixed_features", lambda actor, obs: None)
    loss_per_batch = imitation.fit_actor(per_batch, obs, actions, steps=40, batch_size=32, seed=5)
    assert not th.equal(weights(once), start)  # it learned
    assert th.equal(weights(once), weights(per_batch))
    assert loss_once == loss_per_batch


def test_sacs_action_and_log_std_from_the_features_are_its_own_also_where_log_std_is_clamped(
    env: gym.Env,
) -> None:
    actor = model_of(env).actor
    with th.no_grad():  # SB3 clamps log_std to [-20, 2]: push two outputs past each end
        actor.log_std.bias[:] = th.tensor([40.0, -40.0, 0.5, -1.0, 0.0])
    obs, _ = labelled(env, 64)
    obs_t = {k: th.as_tensor(v) for k, v in obs.items()}
    features = imitation._fixed_features(actor, obs_t)
    with th.no_grad():
        action, log_std = imitation._deterministic_of_features(actor, features)
        want_action, want_log_std = imitation._deterministic(actor, obs_t)
    assert th.equal(action, want_action)
    assert th.equal(log_std, want_log_std)
    assert float(log_std[:, 0].max()) == 2.0 and float(log_std[:, 1].min()) == -20.0


def test_td3s_action_from_the_features_is_its_own(env: gym.Env) -> None:
    actor = model_of(env, TD3).actor
    obs, _ = labelled(env, 64)
    obs_t = {k: th.as_tensor(v) for k, v in obs.items()}
    with th.no_grad():
        action, log_std = imitation._deterministic_of_features(actor, imitation._fixed_features(actor, obs_t))
        want, _ = imitation._deterministic(actor, obs_t)
    assert log_std is None
    assert th.equal(action, want)
    assert float(action.abs().max()) <= 1.0


def test_features_that_can_change_while_the_actor_learns_are_computed_per_batch(env: gym.Env) -> None:
    obs, _ = labelled(env, 16)
    obs_t = {k: th.as_tensor(v) for k, v in obs.items()}
    assert imitation._fixed_features(model_of(env).actor, obs_t) is not None
    assert imitation._fixed_features(model_of(env, extractor=LearningExtractor).actor, obs_t) is None
    assert imitation._fixed_features(model_of(env, use_sde=True).actor, obs_t) is None


def test_a_fit_through_an_extractor_with_weights_trains_them(env: gym.Env) -> None:
    obs, actions = labelled(env)
    model = model_of(env, extractor=LearningExtractor)
    before = model.actor.features_extractor.layer.weight.detach().clone()
    imitation.fit_actor(model, obs, actions, steps=20, batch_size=32)
    assert not th.equal(model.actor.features_extractor.layer.weight, before)


def test_the_fit_runs_on_the_threads_asked_and_gives_them_back(
    env: gym.Env, monkeypatch: pytest.MonkeyPatch
) -> None:
    obs, actions = labelled(env)
    seen = []
    step = imitation._deterministic_of_features

    def counting(actor: object, features: th.Tensor) -> tuple[th.Tensor, th.Tensor | None]:
        seen.append(th.get_num_threads())
        return step(actor, features)

    monkeypatch.setattr(imitation, "_deterministic_of_features", counting)
    before = th.get_num_threads()
    model = model_of(env)
    imitation.fit_actor(model, obs, actions, steps=3, batch_size=8, threads=before + 1)
    assert seen == [before + 1] * 3
    assert th.get_num_threads() == before
    imitation.fit_actor(model, obs, actions, steps=2, batch_size=8)  # None: as they are
    assert seen[3:] == [before] * 2


@pytest.mark.filterwarnings("ignore:Using a target size")  # torch warns before it refuses
def test_the_threads_come_back_when_the_fit_fails(env: gym.Env) -> None:
    before = th.get_num_threads()
    obs, actions = labelled(env)
    with pytest.raises(RuntimeError, match="size"):  # labels of 3 actions for an actor of 5
        imitation.fit_actor(model_of(env), obs, actions[:, :3], steps=5, batch_size=8, threads=before + 1)
    assert th.get_num_threads() == before


def one_state_two_labels(env: gym.Env) -> tuple[dict[str, np.ndarray], np.ndarray]:
    """One state, 400 times: three of four rows labelled +0.6 in every action, one -0.6."""
    obs, _ = labelled(env, 1)
    rows = {k: np.repeat(v, 400, axis=0) for k, v in obs.items()}
    n = env.action_space.shape[0]
    actions = np.where(np.arange(400)[:, None] % 4 == 0, -0.6, 0.6) * np.ones((1, n))
    return rows, actions.astype(np.float32)


def fitted(env: gym.Env, loss: str) -> np.ndarray:
    """The action fitted, with ``loss``, to :func:`one_state_two_labels`."""
    obs, actions = one_state_two_labels(env)
    model = model_of(env)
    imitation.fit_actor(model, obs, actions, steps=400, batch_size=64, learning_rate=3e-3, loss=loss)
    with th.no_grad():
        action, _ = imitation._deterministic(model.actor, {k: th.as_tensor(v[:1]) for k, v in obs.items()})
    return action.numpy()[0]


# Where the expert's labels of like states disagree (the edge between two of a task's
# phases), the squared error fits their mean (0.75 x 0.6 - 0.25 x 0.6 = 0.3), the
# absolute error their median: one of the labels (0.6), not a blend of them.
def test_the_squared_error_fits_the_labels_mean(env: gym.Env) -> None:
    np.testing.assert_allclose(fitted(env, "mse"), 0.3, atol=0.05)


def test_the_absolute_error_fits_the_labels_median(env: gym.Env) -> None:
    action = fitted(env, "l1")
    assert (action > 0.45).all() and (action < 0.65).all(), action  # nearer 0.6 than the mean's 0.3


def test_every_loss_a_config_may_name_has_its_torch_function() -> None:
    from bioscara_gym.training.literals import ACTION_LOSSES

    functions = imitation.LOSS_FUNCTIONS
    assert functions["mse"] is th.nn.functional.mse_loss and functions["l1"] is th.nn.functional.l1_loss
    assert tuple(imitation.LOSS_FUNCTIONS) == ACTION_LOSSES


def test_a_fit_refuses_a_loss_it_does_not_know(env: gym.Env) -> None:
    obs, actions = labelled(env, 16)
    with pytest.raises(ValueError, match="loss 'huber': expected one of mse, l1"):
        imitation.fit_actor(model_of(env), obs, actions, steps=1, batch_size=8, loss="huber")
