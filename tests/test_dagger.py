"""DAgger on Bioscara-PickPlace (training/dagger.py): the observation-only expert, the aggregation, the runs.

Runs here are tiny (the ``mock`` backend, 16x16 networks, one-episode
iterations); the default config's 90 % target is tests/test_pickplace_learning.py's (slow).
"""

from __future__ import annotations

import dataclasses
import itertools
import json
from pathlib import Path
from typing import Any

import gymnasium as gym
import numpy as np
import pytest
import yaml

import bioscara_gym  # noqa: F401 - registers the tasks
from bioscara_gym.cli import main
from bioscara_gym.errors import HyperparamError, TrainingError
from bioscara_gym.experts import ObservationExpert, PickPlaceExpert
from bioscara_gym.training import dagger
from bioscara_gym.training.algos import load_model, sb3_policy
from bioscara_gym.training.dagger import Labelled, label_episodes
from bioscara_gym.training.dagger_config import DaggerConfig, load_dagger_config
from bioscara_gym.training.evaluate import run_episodes
from bioscara_gym.training.features import PickPlaceExtractor
from bioscara_gym.training.hyperparams import default_config_path
from bioscara_gym.training.train import TrainArgs, TrainingInterrupted, choose_method, train


def uses_dagger(args: TrainArgs, env_id: str) -> bool:
    return choose_method(args, env_id).name == "dagger"


PICK = "Bioscara-PickPlace-v1"
REACH = "Bioscara-Reach-v0"
TINY = {
    "n_timesteps": 1000,
    "env_kwargs": {"control_mode": "cartesian", "backend": "mock"},
    "net_arch": [16, 16],
    "demo_episodes": 2,
    "episodes_per_iteration": 1,
    "bc_steps_first": 20,
    "bc_steps": 10,
    "batch_size": 32,
    "beta": 0.5,
    "eval_episodes": 1,
}


def tiny_config(tmp_path: Path, **changes: object) -> Path:
    path = tmp_path / "dagger.yaml"
    path.write_text(yaml.safe_dump({PICK: {**TINY, **changes}}), encoding="utf-8")
    return path


def tiny_args(tmp_path: Path, out: str = "run", **changes: object) -> TrainArgs:
    fields = {"env": PICK, "algo": "dagger", "config": tiny_config(tmp_path), "out": tmp_path / out}
    return TrainArgs(**{**fields, "progress": False, "verbose": 0, **changes})  # type: ignore[arg-type]


def checkpoint_data(out: Path) -> list[np.lib.npyio.NpzFile]:
    files = sorted((out / "checkpoints").glob("*_dagger.npz"), key=lambda p: int(p.name.split("_")[1]))
    return [np.load(p) for p in files]


@pytest.fixture(scope="module")
def pick_env() -> gym.Env:
    env = gym.make(PICK, control_mode="cartesian", backend="mock")
    yield env
    env.close()


# ---------------------------------------------------------------- the expert
def test_observation_expert_acts_on_the_observation_alone(pick_env: gym.Env) -> None:
    expert = ObservationExpert(pick_env.unwrapped)
    obs, _ = pick_env.reset(seed=3)
    for _ in range(30):
        obs, *_ = pick_env.step(expert(obs))
    first = expert(obs)
    assert np.array_equal(expert(obs), first)  # asking twice changes nothing
    assert np.array_equal(ObservationExpert(pick_env.unwrapped)(obs), first)  # a fresh one agrees


@pytest.mark.parametrize("mode", ["cartesian", "velocity"])
def test_observation_expert_places_the_block_on_sim(mode: str) -> None:
    # 20 of 20: with blocks drawn within 1 rad of bearing (not of j1) the cartesian
    # expert placed 84 % (20 of 20 at that rate: 3 %), the learner's ceiling.
    env = gym.make(PICK, control_mode=mode)
    try:
        stats = run_episodes(env, ObservationExpert(env.unwrapped), 20, seed=10_000)
    finally:
        env.close()
    assert stats.success_rate == 1.0


def test_observation_expert_phases_follow_the_gripper_and_the_block(pick_env: gym.Env) -> None:
    expert = ObservationExpert(pick_env.unwrapped)
    obs, _ = pick_env.reset(seed=0)
    s = pick_env.unwrapped.OBS_SLICES
    o = obs["observation"].copy()
    o[s["block_pos"]] = o[s["tcp"]] + np.array([0.0, 0.0, 0.004])  # block between the fingers
    o[s["block_from_tcp"]] = o[s["block_pos"]] - o[s["tcp"]]
    o[s["gripper"]] = -1.0  # commanded closed
    assert expert.phase_of({**obs, "observation": o}) == "carry"
    o[s["block_pos"]] += np.array([0.05, 0.0, 0.0])  # closed on nothing
    o[s["block_from_tcp"]] = o[s["block_pos"]] - o[s["tcp"]]
    assert expert.phase_of({**obs, "observation": o}) == "release"


def test_scripted_expert_keeps_a_phase_the_observation_expert_does_not(pick_env: gym.Env) -> None:
    """Why DAgger needs ObservationExpert: the scripted one answers from its history."""
    scripted = PickPlaceExpert(pick_env.unwrapped)
    obs, _ = pick_env.reset(seed=0)
    scripted.phase = "carry"  # as if it had grasped in an earlier episode
    observed = ObservationExpert(pick_env.unwrapped)
    assert observed.phase_of(obs) == "approach"
    assert not np.allclose(scripted(obs), observed(obs))


# ---------------------------------------------------------------- aggregation
def test_label_episodes_labels_the_learners_states_with_the_experts_actions(pick_env: gym.Env) -> None:
    expert = ObservationExpert(pick_env.unwrapped)
    rng = np.random.default_rng(0)

    def learner(obs: dict[str, np.ndarray]) -> np.ndarray:
        return rng.uniform(-1, 1, 5).astype(np.float32)

    rollouts = label_episodes(pick_env, learner, expert, 1, seed=5, iteration=3)
    data = rollouts.data
    first, _ = pick_env.reset(seed=5)
    assert np.allclose(data.obs["observation"][0], first["observation"], atol=1e-6)  # the learner's episode
    for i in range(0, len(data), 17):
        obs = {k: data.obs[k][i] for k in data.obs}
        assert np.allclose(data.actions[i], expert(obs), atol=1e-4)  # labelled by the expert
    assert set(data.iteration) == {3}
    # The learner drove: its random actions moved the arm where the expert would not have.
    expert_run = label_episodes(pick_env, expert, expert, 1, seed=5, iteration=0).data
    assert not np.allclose(expert_run.obs["observation"][20], data.obs["observation"][20])


def test_rollouts_on_two_workers_are_the_same_seeded_episodes(pick_env: gym.Env) -> None:
    # The expert's demonstrations: episode k is seeded seed + k whichever worker runs
    # it, so two subprocesses label the same states as one env does (in another order).
    from bioscara_gym.training.parallel import label_rollouts, make_vec_envs

    expert = ObservationExpert(pick_env.unwrapped)
    one = label_episodes(pick_env, expert, expert, 3, seed=7, iteration=0, beta=1.0)
    venv = make_vec_envs(PICK, 2, {"control_mode": "cartesian", "backend": "mock"})
    try:
        assert type(venv).__name__ == "SubprocVecEnv"
        rows, labels, results = label_rollouts(venv, expert, expert, 3, 7, 1.0, np.random.default_rng(0))
    finally:
        venv.close()
    assert len(rows) == len(one.data) and results == list(one.results)  # in seed order

    def keyed(obs: np.ndarray, actions: np.ndarray) -> np.ndarray:
        rows = np.concatenate([obs, actions], axis=1).astype(np.float32)
        return rows[np.lexsort(rows.T[::-1])]

    parallel = keyed(np.array([r["observation"] for r in rows], dtype=np.float32), np.array(labels))
    np.testing.assert_allclose(parallel, keyed(one.data.obs["observation"], one.data.actions), atol=1e-6)


def test_evaluation_on_two_workers_is_the_one_env_evaluation(pick_env: gym.Env) -> None:
    # DAgger evaluates on its rollouts' workers when it has them: the same seeded
    # episodes give the same stats, and a confirming evaluation (labelled, as its
    # states may join the aggregate) stops where the one-env loop does (after the
    # episode that fails once more than allowed).
    from bioscara_gym.training.parallel import label_rollouts, make_vec_envs, run_episodes_on

    expert = ObservationExpert(pick_env.unwrapped)

    def half(obs: dict[str, np.ndarray]) -> np.ndarray:  # idles on goals on one side: those fail
        return expert(obs) if obs["desired_goal"][1] > 0.0 else np.zeros(5, dtype=np.float32)

    one = [run_episodes(pick_env, half, 8, seed=3, max_failures=m) for m in (None, 3)]
    assert round(one[0].success_rate * 8) == 3  # both kinds of episode among the 8
    assert one[1].episodes == 6 and one[1].success_rate == 2 / 6  # the 4th failure is the 6th episode
    labelled = label_episodes(pick_env, half, expert, 8, seed=3, iteration=1, max_failures=3)
    assert labelled.stats == one[1]
    assert len(labelled.data) == 6 * 200  # the 6 episodes' states (PickPlace: 200 steps)
    venv = make_vec_envs(PICK, 2, {"control_mode": "cartesian", "backend": "mock"})
    try:
        two = [run_episodes_on(venv, half, 8, seed=3, max_failures=m) for m in (None, 3)]
        rng = np.random.default_rng(0)
        rows, labels, results = label_rollouts(venv, half, expert, 8, 3, 0.0, rng, max_failures=3)
    finally:
        venv.close()
    assert two == one
    assert results == list(labelled.results)
    # The two workers ran the 7th episode beside the 6th: its states are kept, its result is not.
    assert len(rows) == len(labels) == 7 * 200


def test_n_envs_below_one_is_one_line(tmp_path: Path, capsys: pytest.CaptureFixture[str]) -> None:
    assert main(["train", "--env", PICK, "--algo", "dagger", "--n-envs", "0", "--out", str(tmp_path)]) != 0
    err = capsys.readouterr().err.strip()
    assert err == "bioscara train: error: --n-envs 0: must be >= 1 (omit it for the config's n_envs)"


def test_labelled_sets_add_up_in_order() -> None:
    def part(n: int, it: int) -> Labelled:
        keys = ("observation", "achieved_goal", "desired_goal")
        obs = {k: np.full((n, 3), it, dtype=np.float32) for k in keys}
        return Labelled(obs, np.full((n, 5), it, dtype=np.float32), np.full(n, it))

    both = part(2, 0) + part(3, 1)
    assert len(both) == 5
    assert list(both.iteration) == [0, 0, 1, 1, 1]
    assert both.actions[-1, 0] == 1


# ---------------------------------------------------------------- runs
@pytest.fixture(scope="module")
def tiny_run(tmp_path_factory: pytest.TempPathFactory) -> Path:
    tmp = tmp_path_factory.mktemp("dagger")
    result = train(tiny_args(tmp))
    assert result.model_path.exists()
    return tmp / "run"


def test_the_dataset_grows_by_the_learners_episodes_each_iteration(tiny_run: Path) -> None:
    data = checkpoint_data(tiny_run)
    assert len(data) >= 3
    sizes = [len(d["actions"]) for d in data]
    assert sizes == sorted(sizes) and len(set(sizes)) == len(sizes)
    for before, after in itertools.pairwise(data):
        new = after["row_iteration"][len(before["actions"]) :]
        assert set(new) == {int(after["iteration"])}  # the rows added are the new iteration's
        assert len(new) == int(after["env_steps"]) - int(before["env_steps"])


def test_the_model_loads_as_a_cloned_sac_model_for_eval_export_and_deploy(tiny_run: Path) -> None:
    model, metadata = load_model(tiny_run / "model.zip")
    assert metadata["algo"] == "bc" and metadata["method"] == "dagger"
    assert metadata["env_kwargs"]["control_mode"] == "cartesian"
    assert isinstance(model.actor.features_extractor, PickPlaceExtractor)
    env = gym.make(PICK, **TINY["env_kwargs"])  # type: ignore[arg-type]
    try:
        obs, _ = env.reset(seed=0)
        action, _ = model.predict(obs, deterministic=True)
    finally:
        env.close()
    assert action.shape == (5,)


def test_the_learners_actions_are_exactly_sb3s_deterministic_predict(tiny_run: Path) -> None:
    # sb3_policy computes a SAC model's action without predict()'s per-call set-up:
    # the same numbers, one observation or a batch, also right after training
    # has switched the modules back to training mode.
    model, _ = load_model(tiny_run / "model.zip")
    act = sb3_policy(model)
    env = gym.make(PICK, **TINY["env_kwargs"])  # type: ignore[arg-type]
    env.action_space.seed(1)
    observations = []
    try:
        obs, _ = env.reset(seed=4)
        for _ in range(30):
            observations.append(obs)
            obs, *_ = env.step(env.action_space.sample())
    finally:
        env.close()
    for i, obs in enumerate(observations):
        if i == 10:
            model.policy.set_training_mode(True)
        np.testing.assert_array_equal(act(obs), model.predict(obs, deterministic=True)[0])
    batch = {k: np.stack([o[k] for o in observations[:3]]) for k in observations[0]}
    assert act(batch).shape == (3, 5)
    np.testing.assert_array_equal(act(batch), model.predict(batch, deterministic=True)[0])


def test_tensorboard_gets_the_dagger_scalars(tiny_run: Path) -> None:
    assert list((tiny_run / "tb").rglob("events.out.tfevents.*"))


def test_an_interrupted_run_resumes_from_its_newest_checkpoint(
    tmp_path: Path, monkeypatch: pytest.MonkeyPatch
) -> None:
    calls = {"n": 0}
    original = dagger.DAgger.iteration

    def interrupted_at_the_third(self: dagger.DAgger, i: int, *args: object) -> object:
        calls["n"] += 1
        if calls["n"] == 3:
            raise KeyboardInterrupt
        return original(self, i, *args)  # type: ignore[arg-type]

    monkeypatch.setattr(dagger.DAgger, "iteration", interrupted_at_the_third)
    with pytest.raises(TrainingInterrupted) as caught:
        train(tiny_args(tmp_path))
    assert caught.value.checkpoint is not None
    saved = checkpoint_data(tmp_path / "run")[-1]
    assert int(saved["iteration"]) == 2
    monkeypatch.setattr(dagger.DAgger, "iteration", original)
    result = train(tiny_args(tmp_path, resume=True, config=None))
    last = checkpoint_data(tmp_path / "run")[-1]
    assert int(last["iteration"]) > 2
    assert np.array_equal(last["actions"][: len(saved["actions"])], saved["actions"])  # the aggregate kept
    assert result.timesteps >= TINY["n_timesteps"]


# ---------------------------------------------------------------- routing and config
def test_pickplace_trains_with_dagger_by_default_and_reach_does_not(tmp_path: Path) -> None:
    assert uses_dagger(TrainArgs(env="Bioscara-PickPlace", out=tmp_path), PICK)
    assert uses_dagger(TrainArgs(env="Bioscara-PickPlace", demos="pick", out=tmp_path), PICK)
    assert not uses_dagger(TrainArgs(env="Bioscara-Reach", out=tmp_path), REACH)
    assert not uses_dagger(TrainArgs(env="Bioscara-PickPlace", algo="td3", out=tmp_path), PICK)
    assert not uses_dagger(TrainArgs(env="Bioscara-PickPlace", algo="sac", out=tmp_path), PICK)  # as asked
    assert not uses_dagger(TrainArgs(env="Bioscara-PickPlace", config=Path("sac.yaml"), out=tmp_path), PICK)


def test_the_packaged_config_loads() -> None:
    cfg = load_dagger_config(default_config_path("dagger"), PICK)
    assert cfg.target_success == 0.93 and cfg.eval_episodes == 100
    assert cfg.env_kwargs["control_mode"] == "cartesian"


@pytest.mark.parametrize(
    ("env_id", "confirm"),
    [(PICK, 0.93), ("Bioscara-Push-v0", 0.95), ("Bioscara-Stack-v0", 0.93), ("Bioscara-Insert-v0", 0.93)],
)
def test_every_packaged_task_fits_the_absolute_error_and_confirms_above_90_percent(
    env_id: str, confirm: float
) -> None:
    # issue #27's 90 % on the benchmark's own 100 episodes, with a margin of a
    # 100-episode estimate's standard error (3 points) on the confirmation's;
    # Push a wider one (95 %: its seed 1 passed at 93 and scored 87, dagger.yaml)
    cfg = load_dagger_config(default_config_path("dagger"), env_id)
    assert (cfg.loss, cfg.target_success, cfg.eval_episodes) == ("l1", confirm, 100)


def test_a_config_without_a_loss_fits_the_squared_error_as_runs_before_it_did() -> None:
    assert DaggerConfig(source="x.yaml").loss == "mse"


def test_a_misspelt_config_key_is_refused_with_the_closest_one(tmp_path: Path) -> None:
    path = tmp_path / "d.yaml"
    path.write_text(yaml.safe_dump({PICK: {"demo_episode": 3}}), encoding="utf-8")
    with pytest.raises(HyperparamError, match="did you mean 'demo_episodes'"):
        load_dagger_config(path, PICK)


@pytest.mark.parametrize(
    ("key", "value"),
    [
        ("demo_episodes", 0),
        ("target_success", 1.5),
        ("beta", 1.0),
        ("net_arch", []),
        ("fit_threads", 0),
        ("loss", "huber"),
    ],
)
def test_a_bad_config_value_is_refused(key: str, value: object) -> None:
    with pytest.raises(HyperparamError, match=key):
        DaggerConfig(source="x.yaml", **{key: value})  # type: ignore[arg-type]


def test_dagger_refuses_a_task_without_an_observation_expert(tmp_path: Path) -> None:
    path = tmp_path / "d.yaml"
    path.write_text(yaml.safe_dump({REACH: {"net_arch": [8]}}), encoding="utf-8")
    args = TrainArgs(env=REACH, algo="dagger", config=path, out=tmp_path / "r", progress=False)
    with pytest.raises(TrainingError, match="label any state"):
        train(args)


def test_bioscara_train_algo_dagger_runs_from_the_command_line(tmp_path: Path) -> None:
    config = str(tiny_config(tmp_path))
    out = str(tmp_path / "cli")
    argv = ["train", "--env", "Bioscara-PickPlace", "--algo", "dagger", "--config", config, "--out", out]
    code = main([*argv, "--no-progress", "--timesteps", "500"])
    assert code == 0
    state = json.loads((tmp_path / "cli" / "train_state.json").read_text(encoding="utf-8"))
    assert state["algo"] == "dagger" and state["total_timesteps"] == 500


def test_models_saved_before_the_extractor_moved_still_find_it() -> None:
    # SB3 pickles policy_kwargs' features_extractor_class by module path.
    assert dagger.PickPlaceExtractor is PickPlaceExtractor


def test_extractor_sees_millimetres_near_the_block(pick_env: gym.Env) -> None:
    import torch as th

    ext = PickPlaceExtractor(pick_env.observation_space, coarse_m=0.1, fine_m=0.005)
    obs, _ = pick_env.reset(seed=0)
    batch = {k: th.as_tensor(v[None], dtype=th.float32) for k, v in obs.items()}
    features = ext(batch)
    assert features.shape == (1, ext.features_dim)
    assert float(features.abs().max()) < 20  # lengths in 10 cm, the fine view clipped at 3
    with pytest.raises(ValueError, match="PickPlace"):
        reach = gym.make(REACH)
        PickPlaceExtractor(reach.observation_space)


def test_stack_learner_reads_the_joint_ranges_off_the_env(tmp_path: Path) -> None:
    # StackExtractor turns joint_pos back into radians for the wrist's turn; the trainer
    # hands it the env's ranges (the packaged URDF limits), and the saved model keeps them.
    path = tmp_path / "stack.yaml"
    path.write_text(yaml.safe_dump({"Bioscara-Stack-v0": {**TINY, "n_timesteps": 700}}), encoding="utf-8")
    train(tiny_args(tmp_path, env="Bioscara-Stack-v0", config=path))
    model, _ = load_model(tmp_path / "run" / "model.zip")
    extractor = model.policy.actor.features_extractor
    lo = [-3.04647, -0.0016, -2.62672, -3.01069]
    span = [2 * 3.04647, 0.338 + 0.0016, 2 * 2.62672, 2 * 3.01069]
    np.testing.assert_allclose(extractor.q_lo.numpy(), lo, rtol=1e-6)
    np.testing.assert_allclose(extractor.q_span.numpy(), span, rtol=1e-6)


def test_demos_from_a_dataset_replace_the_experts_own_episodes(
    tmp_path: Path, monkeypatch: pytest.MonkeyPatch
) -> None:
    pytest.importorskip("minari", reason="minari is in the [train] extra")
    monkeypatch.setenv("MINARI_DATASETS_PATH", str(tmp_path / "minari"))
    argv = ["collect", "--expert", "--env", "Bioscara-PickPlace", "--backend", "mock", "--episodes", "1"]
    assert main([*argv, "--dataset", "pp", "--no-progress"]) == 0
    result = train(tiny_args(tmp_path, demos="pp", timesteps=300))
    first = checkpoint_data(tmp_path / "run")[0]
    assert len(first["actions"]) == 200 and int(first["env_steps"]) == 0  # the dataset's episode, no env step
    assert json.loads(result.metadata_path.read_text(encoding="utf-8"))["dagger"]["demos"] == "pp"


class _Outcomes(gym.Env):
    """One-step episodes that succeed as ``outcomes`` says, in turn."""

    observation_space = gym.spaces.Box(-1, 1, (1,))
    action_space = gym.spaces.Box(-1, 1, (1,))

    def __init__(self, outcomes: list[bool]) -> None:
        self.outcomes, self.resets = list(outcomes), 0

    def reset(self, *, seed: int | None = None, options: object = None) -> tuple[np.ndarray, dict]:
        self.resets += 1
        return np.zeros(1, dtype=np.float32), {}

    def step(self, action: np.ndarray) -> tuple[np.ndarray, float, bool, bool, dict]:
        success = self.outcomes[self.resets - 1]
        return np.zeros(1, dtype=np.float32), 0.0, False, True, {"is_success": success}


def test_an_evaluation_can_stop_once_more_failures_than_allowed() -> None:
    # 10 allowed (a 90 % target over 100): the 11th failure, in episode 13, ends it.
    env = _Outcomes([True, False, True] + [False] * 10 + [True] * 87)
    stats = run_episodes(env, lambda obs: np.zeros(1), 100, max_failures=10)
    assert (env.resets, stats.episodes) == (13, 13)
    assert stats.success_rate == 2 / 13
    # Never more than the episodes asked for, and all of them when the failures stay within.
    env = _Outcomes([False] * 10 + [True] * 90)
    assert run_episodes(env, lambda obs: np.zeros(1), 100, max_failures=10).episodes == 100


def test_dagger_confirms_its_target_no_longer_than_the_target_stays_in_reach(
    tmp_path: Path, monkeypatch: pytest.MonkeyPatch
) -> None:
    labelled: list[tuple[int | None, dagger.Rollouts]] = []
    evaluated: list[tuple[int, int | None]] = []
    label, run = dagger.label_episodes, dagger.run_episodes

    def label_spy(*args: Any, max_failures: int | None = None, **kwargs: Any) -> dagger.Rollouts:
        r = label(*args, max_failures=max_failures, **kwargs)
        labelled.append((max_failures, r))
        if max_failures is None:  # the learner's own rollouts "reach" the target
            r = dagger.Rollouts(r.data, tuple(dataclasses.replace(x, success=True) for x in r.results))
        return r

    def run_spy(*args: Any, max_failures: int | None = None, **kwargs: Any) -> Any:
        stats = run(*args, max_failures=max_failures, **kwargs)
        evaluated.append((stats.episodes, max_failures))
        return stats

    monkeypatch.setattr(dagger, "label_episodes", label_spy)
    monkeypatch.setattr(dagger, "run_episodes", run_spy)
    # The expert's share is negligible from iteration 1; 10 confirming episodes at a
    # target of 0.7 allow 3 failures.
    (tmp_path / "cfg").mkdir()  # tiny_args writes its own tmp_path / "dagger.yaml"
    config = tiny_config(tmp_path / "cfg", target_success=0.7, eval_episodes=10, beta=0.01)
    train(tiny_args(tmp_path, config=config))
    # The expert's 2 episodes, the learner's 1, then the confirmation: the tiny learner
    # fails, so it stops at its 4th failure and its 4 episodes join the aggregate.
    assert [m for m, _ in labelled] == [None, None, 3]
    check = labelled[2][1]
    assert check.episodes == 4 and check.successes == 0
    meta = json.loads((tmp_path / "run" / "metadata.json").read_text(encoding="utf-8"))
    assert meta["dagger"]["labelled_states"] == 7 * 200 == meta["timesteps"]  # the budget (1000) spent
    # Then the budget's own evaluation runs all 10, on its own seeds.
    assert evaluated == [(10, None)]
