"""Tests that kill mutants mutmut found surviving in ``training/dagger.py`` (docs/mutation.md).

No learning: the rule under test is DAgger's schedule, not the network. A
:class:`~bioscara_gym.training.dagger.DAgger` is built without a run and its
steps (roll out, fit, log, evaluate) are replaced by recorders, so a test
sees what each iteration asks for: the expert's share ``beta ** i``
(``DaggerConfig.beta``'s docstring), the stopping rule (the learner's own
rollouts at the target while the expert's share is below
``BETA_NEGLIGIBLE`` = 0.05, then a confirming evaluation on fresh episodes
that stops at the failure that puts the target out of reach and, falling
short, joins the aggregate), the seeds, the checkpoints.
Expected values are literals from the module's and the config's docstrings
and training/configs/dagger.yaml.
"""

from __future__ import annotations

import contextlib
import zipfile
from pathlib import Path
from types import SimpleNamespace
from typing import IO, Any

import gymnasium as gym
import numpy as np
import pytest

import bioscara_gym  # noqa: F401 - registers the tasks
from bioscara_gym.errors import TrainingError
from bioscara_gym.experts import ObservationExpert
from bioscara_gym.training import dagger
from bioscara_gym.training.base import RunPlan
from bioscara_gym.training.checkpoints import write_run_state
from bioscara_gym.training.dagger import DAgger, Labelled, Rollouts, label_episodes
from bioscara_gym.training.dagger_config import DaggerConfig
from bioscara_gym.training.evaluate import EpisodeResult, EvalStats
from bioscara_gym.training.features import PickPlaceExtractor
from bioscara_gym.training.methods import method_spec
from bioscara_gym.training.parallel import label_rollouts, run_episodes_on
from bioscara_gym.training.run import TrainArgs

PICK = "Bioscara-PickPlace-v1"
KEYS = ("observation", "achieved_goal", "desired_goal")
EXPERT_ACTION = [1.0, 1.0]
LEARNER_ACTION = [-1.0, -1.0]


# ------------------------------------------------------------------ helpers
def rows(n: int, iteration: int, value: float = 0.0) -> Labelled:
    """``n`` labelled states, every number ``value``, tagged ``iteration``."""
    obs = {k: np.full((n, 2), value, dtype=np.float32) for k in KEYS}
    return Labelled(obs, np.full((n, 2), value, dtype=np.float32), np.full(n, iteration, dtype=np.int32))


def stats(success_rate: float, episodes: int = 10) -> EvalStats:
    return EvalStats(episodes, success_rate, 0.02, 1.0, 0.0, 50.0, 0)


def rollouts(data: Labelled, successes: int, episodes: int) -> Rollouts:
    """``episodes`` episodes of 50 steps, the first ``successes`` of them successful, and ``data``."""
    results = [EpisodeResult(k < successes, False, 0.02, 1.0, 50) for k in range(episodes)]
    return Rollouts(data, tuple(results))


class Episodes(gym.Env):
    """Episodes of ``lengths[k]`` steps; the k-th ends in ``successes[k]``; records seeds and actions.

    Stepping past an episode's end raises, so a loop that does not stop fails at once.
    """

    observation_space = gym.spaces.Box(-10, 10, (2,))
    action_space = gym.spaces.Box(-1, 1, (2,))

    def __init__(self, lengths: list[int], successes: list[bool | None], terminate: bool = False) -> None:
        self.lengths, self.successes, self.terminate = lengths, successes, terminate
        self.seeds: list[int | None] = []
        self.actions: list[list[float]] = []
        self.t = 0

    def _obs(self) -> dict[str, np.ndarray]:
        ep = len(self.seeds) - 1
        return {k: np.array([ep, self.t], dtype=np.float64) for k in KEYS}

    def reset(self, *, seed: int | None = None, options: object = None) -> tuple[dict, dict]:
        self.seeds.append(seed)
        self.t = 0
        return self._obs(), {}

    def step(self, action: np.ndarray) -> tuple[dict, float, bool, bool, dict]:
        ep = len(self.seeds) - 1
        if self.t >= self.lengths[ep]:
            raise AssertionError("stepped past the end of the episode")
        self.actions.append([float(a) for a in action])
        self.t += 1
        end = self.t == self.lengths[ep]
        success = self.successes[ep]
        info = {} if success is None or not end else {"is_success": success}
        return self._obs(), 0.0, end and self.terminate, end and not self.terminate, info


def expert(obs: dict[str, np.ndarray]) -> np.ndarray:
    return np.array(EXPERT_ACTION)


def learner(obs: dict[str, np.ndarray]) -> np.ndarray:
    return np.array(LEARNER_ACTION)


class Logger:
    """SB3's logger as far as DAgger uses it: records, dumps, close."""

    def __init__(self) -> None:
        self.records: dict[str, Any] = {}
        self.dumps: list[tuple[int, dict[str, Any]]] = []
        self.closed = False

    def record(self, key: str, value: Any) -> None:
        self.records[key] = value

    def dump(self, step: int) -> None:
        self.dumps.append((step, self.records))
        self.records = {}

    def close(self) -> None:
        self.closed = True


class ZipModel:
    """Anything with stable-baselines3's ``save(file)``: writes a zip holding ``data``."""

    def save(self, file: IO[bytes]) -> None:
        with zipfile.ZipFile(file, "w") as archive:
            archive.writestr("data", "{}")
            archive.writestr("policy.pth", "")


def make_dagger(tmp_path: Path, seed: int = 3, verbose: int = 0, **config: Any) -> DAgger:
    """A DAgger run object with its config set and nothing built; a logger that records."""
    args = TrainArgs(
        env=PICK, algo="dagger", seed=seed, out=tmp_path / "run", progress=False, verbose=verbose
    )
    d = DAgger(args, PICK, method_spec("dagger"))
    d.cfg = DaggerConfig(source="test.yaml", **config)
    d.model = "the model"
    d.logger = Logger()
    return d


class Recorder:
    """Records each call's arguments; answers with ``answers`` in turn (the last one repeated)."""

    def __init__(self, *answers: Any) -> None:
        self.calls: list[tuple[tuple[Any, ...], dict[str, Any]]] = []
        self.answers = list(answers)

    def __call__(self, *args: Any, **kwargs: Any) -> Any:
        self.calls.append((args, kwargs))
        return self.answers[min(len(self.calls), len(self.answers)) - 1] if self.answers else None


@pytest.fixture
def policy_of(monkeypatch: pytest.MonkeyPatch) -> None:
    """``sb3_policy(model)`` as a tuple naming the model, so a test can see which policy acts."""
    monkeypatch.setattr(dagger, "sb3_policy", lambda model: ("policy of", model))


def stub_iteration(d: DAgger, r: Rollouts, check: Rollouts | None = None) -> dict[str, Recorder]:
    """Replace the steps ``iteration`` calls by recorders: rollouts ``r``, a confirmation ``check``."""
    steps = {
        "_rollouts": Recorder(r),
        "_fit": Recorder(0.125),
        "_log": Recorder(),
        "confirmation": Recorder(check),
    }
    for name, recorder in steps.items():
        setattr(d, name, recorder)
    return steps


# ------------------------------------------------------------------ data
def test_a_labelled_set_counts_its_rows_and_adds_in_order() -> None:
    both = rows(2, 0, 1.0) + rows(3, 4, 2.0)
    assert len(both) == 5
    assert both.iteration.tolist() == [0, 0, 4, 4, 4]
    for k in KEYS:
        assert both.obs[k][:, 0].tolist() == [1.0, 1.0, 2.0, 2.0, 2.0]
    assert both.actions[:, 0].tolist() == [1.0, 1.0, 2.0, 2.0, 2.0]


def test_demos_are_iteration_zero() -> None:
    class Demos:
        obs = {k: np.ones((3, 2), dtype=np.float32) for k in (*KEYS, "extra")}
        actions = np.full((3, 2), 0.5, dtype=np.float32)

        def __len__(self) -> int:
            return 3

    data = Labelled.from_demos(Demos())  # type: ignore[arg-type]
    assert set(data.obs) == set(KEYS)
    assert data.iteration.tolist() == [0, 0, 0] and data.iteration.dtype == np.int32
    assert data.actions.tolist() == [[0.5, 0.5]] * 3


def test_a_rollouts_success_rate_is_its_successes_over_its_episodes() -> None:
    assert rollouts(rows(0, 1), 3, 4).success_rate == 0.75


# ------------------------------------------------------------------ label_episodes
def test_label_episodes_seeds_each_episode_and_labels_every_state_with_the_expert() -> None:
    env = Episodes([2, 3], [True, False])
    seen: list[tuple[bool, int]] = []
    r = label_episodes(
        env, learner, expert, 2, seed=40, iteration=5, on_episode=lambda s, n: seen.append((s, n))
    )
    assert env.seeds == [40, 41]
    assert env.actions == [LEARNER_ACTION] * 5  # beta 0: the learner alone acts
    assert (r.successes, r.episodes) == (1, 2)
    assert seen == [(True, 2), (False, 3)]
    data = r.data
    assert len(data) == 5
    assert data.actions.tolist() == [EXPERT_ACTION] * 5
    assert data.actions.dtype == np.float32 and data.iteration.dtype == np.int32
    assert data.iteration.tolist() == [5] * 5
    for k in KEYS:  # the states before each step, in order
        assert data.obs[k].dtype == np.float32
        assert data.obs[k].tolist() == [[0, 0], [0, 1], [1, 0], [1, 1], [1, 2]]


def test_an_episode_ends_on_termination_too_and_without_is_success_it_failed() -> None:
    env = Episodes([2, 1], [None, None], terminate=True)
    r = label_episodes(env, learner, expert, 2, seed=0, iteration=1)
    assert len(r.data) == 3 and r.successes == 0


def test_label_episodes_stops_after_the_failure_its_allowance_cannot_take() -> None:
    # One failure allowed: the second (episode 2, which ends without is_success) stops it.
    env = Episodes([2, 3, 1, 2, 4], [True, False, None, False, True])
    r = label_episodes(env, learner, expert, 5, seed=0, iteration=1, max_failures=1)
    assert env.seeds == [0, 1, 2]
    assert len(r.data) == 6 and [x.steps for x in r.results] == [2, 3, 1]
    assert (r.successes, r.episodes) == (1, 3)
    env = Episodes([2, 3, 1, 2, 4], [True, False, None, False, True])
    assert label_episodes(env, learner, expert, 5, seed=0, iteration=1).episodes == 5  # no allowance


def test_every_episode_loop_refuses_zero_episodes_before_anything_runs() -> None:
    env = Episodes([2], [True])
    with pytest.raises(ValueError, match="episodes must be >= 1, got 0"):
        label_episodes(env, learner, expert, 0, seed=0, iteration=1)
    assert env.seeds == []
    with pytest.raises(ValueError, match="episodes must be >= 1, got 0"):  # before the workers are asked
        label_rollouts(None, learner, expert, 0, 0, 0.0, np.random.default_rng(0))
    with pytest.raises(ValueError, match="episodes must be >= 1, got 0"):
        run_episodes_on(None, learner, 0)


def test_the_expert_acting_itself_acts_in_every_step_whatever_beta() -> None:
    env = Episodes([4], [True])
    label_episodes(env, expert, expert, 1, seed=0, iteration=0)
    assert env.actions == [EXPERT_ACTION] * 4


def test_a_mixture_of_one_is_the_expert_alone() -> None:
    env = Episodes([6], [True])
    label_episodes(env, learner, expert, 1, seed=0, iteration=1, beta=1.0)
    assert env.actions == [EXPERT_ACTION] * 6


def test_a_mixture_of_a_half_mixes_both_and_follows_its_generator() -> None:
    env = Episodes([400], [True])
    label_episodes(env, learner, expert, 1, seed=0, iteration=1, beta=0.5, rng=np.random.default_rng(7))
    by_expert = [a == EXPERT_ACTION for a in env.actions]
    assert 160 < sum(by_expert) < 240  # about half: 200 +- 4 sigma
    draws = np.random.default_rng(7).random(400)
    assert by_expert == [bool(x < 0.5) for x in draws]  # a step is the expert's when its draw is below beta


def test_without_a_generator_the_mixture_is_drawn_from_the_seed() -> None:
    def actions(seed: int) -> list[list[float]]:
        env = Episodes([100], [True])
        label_episodes(env, learner, expert, 1, seed=seed, iteration=1, beta=0.5)
        return env.actions

    assert actions(11) == actions(11)
    assert actions(11) != actions(12)


# ------------------------------------------------------------------ the expert
def test_the_labeller_is_the_tasks_observation_expert() -> None:
    env = gym.make(PICK, control_mode="cartesian", backend="mock")
    try:
        assert isinstance(dagger.expert_labeller(env), ObservationExpert)
    finally:
        env.close()


def test_a_task_without_an_observation_expert_is_refused_in_one_line() -> None:
    env = gym.make("Bioscara-Reach-v0", backend="mock")
    try:
        with pytest.raises(TrainingError) as caught:
            dagger.expert_labeller(env)
    finally:
        env.close()
    assert str(caught.value) == (
        "DAgger needs an expert that can label any state; Bioscara-Reach-v0 has none "
        "(train it with --algo sac)"
    )


# ------------------------------------------------------------------ the schedule
@pytest.mark.parametrize(("i", "beta"), [(1, 0.5), (2, 0.25), (3, 0.125)])
def test_iteration_i_mixes_in_the_expert_with_a_share_of_beta_to_the_i(
    tmp_path: Path, policy_of: None, i: int, beta: float
) -> None:
    d = make_dagger(tmp_path, beta=0.5, episodes_per_iteration=20)
    steps = stub_iteration(d, rollouts(rows(7, i), 20, 20))
    d.iteration(i, rows(5, 0), 100)
    ((args, _),) = steps["_rollouts"].calls
    assert args[0] == ("policy of", "the model")  # the learner acts
    assert args[1:3] == (
        20,
        2_030_000 + 20 * (i - 1),
    )  # seeds: 2,000,000 + 10,000 x run seed 3, then by episode
    assert args[3:] == (i, beta)
    assert steps["_log"].calls[0][0][5] == beta


def test_an_iteration_adds_the_learners_states_and_refits_on_the_aggregate(
    tmp_path: Path, policy_of: None
) -> None:
    d = make_dagger(tmp_path, beta=0.5, bc_steps=7, target_success=0.9)
    new = rows(4, 2, 9.0)
    steps = stub_iteration(d, rollouts(new, 9, 20))
    data, env_steps, final = d.iteration(2, rows(3, 0, 1.0), 100)
    assert (len(data), env_steps, final) == (7, 104, None)
    assert data.iteration.tolist() == [0, 0, 0, 2, 2, 2, 2]  # the old rows first
    assert steps["confirmation"].calls == []
    ((fit_args, _),) = steps["_fit"].calls
    assert fit_args[0] is data and fit_args[1:] == (7, 2)  # bc_steps, the iteration
    ((log_args, _),) = steps["_log"].calls
    assert log_args[0:2] == (2, 104) and log_args[2] is data
    assert log_args[3:] == (0.125, 0.45, 0.25)  # the fit's loss, the rollouts' success, beta


@pytest.mark.parametrize("beta", [0.5, 0.05])
def test_while_the_experts_share_is_not_negligible_even_a_perfect_rollout_does_not_stop(
    tmp_path: Path, policy_of: None, beta: float
) -> None:
    # beta 0.05 ** 1 = 0.05: not below BETA_NEGLIGIBLE, so the expert still carries the learner.
    d = make_dagger(tmp_path, beta=beta, target_success=0.9)
    steps = stub_iteration(d, rollouts(rows(4, 1), 20, 20), check=rollouts(rows(9, 1), 10, 10))
    *_, final = d.iteration(1, rows(3, 0), 100)
    assert final is None and steps["confirmation"].calls == []
    assert len(steps["_fit"].calls) == 1


def test_the_expert_s_share_becomes_negligible_after_enough_iterations(
    tmp_path: Path, policy_of: None
) -> None:
    # 0.5 ** 4 = 0.0625 still counts; 0.5 ** 5 = 0.03125 is the learner alone.
    d = make_dagger(tmp_path, beta=0.5, target_success=0.9)
    check = rollouts(rows(9, 5), 10, 10)
    steps = stub_iteration(d, rollouts(rows(4, 4), 20, 20), check=check)
    assert d.iteration(4, rows(3, 0), 100)[2] is None
    assert d.iteration(5, rows(3, 0), 100)[2] == check.stats
    assert len(steps["confirmation"].calls) == 1


def test_rollouts_at_the_target_ask_for_a_confirming_evaluation_which_stops_training(
    tmp_path: Path, policy_of: None
) -> None:
    d = make_dagger(tmp_path, beta=0.01, target_success=0.9)
    new = rows(4, 1)
    check = rollouts(rows(9, 1), 9, 10)  # 90 %: confirmed
    steps = stub_iteration(d, rollouts(new, 18, 20), check=check)  # 18 of 20: the target exactly
    old = rows(3, 0)
    data, env_steps, final = d.iteration(1, old, 100)
    assert steps["confirmation"].calls == [((1, 104), {})]
    assert final == check.stats  # stop, with the confirmation's figures
    assert data is old and env_steps == 104  # nothing aggregated, nothing refitted
    assert steps["_fit"].calls == [] and steps["_log"].calls == []
    assert d.reached_at == 104 and 0 <= d.reached_after_s < 5


def test_rollouts_below_the_target_are_not_confirmed(tmp_path: Path, policy_of: None) -> None:
    d = make_dagger(tmp_path, beta=0.01, target_success=0.9)
    steps = stub_iteration(d, rollouts(rows(4, 1), 17, 20), check=rollouts(rows(9, 1), 10, 10))
    assert d.iteration(1, rows(3, 0), 100)[2] is None
    assert steps["confirmation"].calls == [] and d.reached_at is None


def test_an_evaluation_that_does_not_confirm_the_target_goes_on_aggregating(
    tmp_path: Path, policy_of: None
) -> None:
    d = make_dagger(tmp_path, beta=0.01, target_success=0.9)
    # 89 % of 100 falls short; its 6 states join the aggregate after the rollouts' 4, and count.
    check = rollouts(rows(6, 1, 2.0), 89, 100)
    steps = stub_iteration(d, rollouts(rows(4, 1, 1.0), 20, 20), check=check)
    data, env_steps, final = d.iteration(1, rows(3, 0), 100)
    assert final is None and env_steps == 110 and d.reached_at is None
    assert data.actions[:, 0].tolist() == [0.0] * 3 + [1.0] * 4 + [2.0] * 6
    ((fit_args, _),) = steps["_fit"].calls
    assert fit_args[0] is data
    assert steps["_log"].calls[0][0][:2] == (1, 110)


def test_an_iteration_says_what_the_learner_did(
    tmp_path: Path, policy_of: None, capsys: pytest.CaptureFixture[str]
) -> None:
    d = make_dagger(tmp_path, verbose=1, beta=0.5)
    stub_iteration(d, rollouts(rows(4, 2), 9, 20))
    d.start = dagger.time.perf_counter()
    d.iteration(2, rows(3, 0), 100)
    assert (
        capsys.readouterr().out
        == "[dagger] iteration 2: learner (expert 25%) 45% success over 20 episodes, 0 s\n"
    )


def test_an_iteration_without_the_expert_names_the_learner_alone_and_a_reached_target(
    tmp_path: Path, policy_of: None, capsys: pytest.CaptureFixture[str]
) -> None:
    d = make_dagger(tmp_path, verbose=1, beta=0.0, target_success=0.5)
    stub_iteration(d, rollouts(rows(4, 1), 1, 2), check=rollouts(rows(4, 1), 1, 2))
    d.start = dagger.time.perf_counter()
    d.iteration(1, rows(3, 0), 100)
    assert capsys.readouterr().out == (
        "[dagger] iteration 1: learner 50% success over 2 episodes, 0 s\n"
        "[dagger] target reached after 104 steps, 0 s\n"
    )


def test_nothing_is_said_unless_verbose(
    tmp_path: Path, policy_of: None, capsys: pytest.CaptureFixture[str]
) -> None:
    d = make_dagger(tmp_path, verbose=0, beta=0.0, target_success=0.5)
    stub_iteration(d, rollouts(rows(4, 1), 1, 2), check=rollouts(rows(4, 1), 1, 2))
    d.iteration(1, rows(3, 0), 100)
    assert capsys.readouterr().out == ""


def test_with_a_progress_bar_the_words_go_through_the_bar(
    tmp_path: Path, capsys: pytest.CaptureFixture[str]
) -> None:
    d = make_dagger(tmp_path, verbose=1)
    d.args.progress = True
    written: list[str] = []
    d.progress = SimpleNamespace(bar=SimpleNamespace(write=written.append))
    d._say("hello")
    assert written == ["hello"] and capsys.readouterr().out == ""


# ------------------------------------------------------------------ iteration 0
def test_iteration_zero_clones_the_experts_own_episodes(
    tmp_path: Path, capsys: pytest.CaptureFixture[str]
) -> None:
    d = make_dagger(tmp_path, seed=3, verbose=1, demo_episodes=2, bc_steps_first=11)
    d.expert = expert
    demos = rows(6, 0)
    steps = stub_iteration(d, rollouts(demos, 1, 2))
    d._fit = Recorder(0.12345)
    data, env_steps = d.first_iteration(None)
    assert data is demos and env_steps == 6
    # The expert alone (share 1.0), 2 episodes seeded from 1,000,000 + 10,000 x run seed 3.
    assert steps["_rollouts"].calls == [((expert, 2, 1_030_000, 0, 1.0), {})]
    assert d._fit.calls == [((demos, 11, 0), {})]
    assert steps["_log"].calls == [((0, 6, demos, 0.12345, None, 1.0), {})]
    assert capsys.readouterr().out == (
        "[dagger] iteration 0: cloned 6 states of 2 expert episodes (50% success), loss 0.1235\n"
    )


def test_iteration_zero_from_a_dataset_takes_no_env_step(
    tmp_path: Path, capsys: pytest.CaptureFixture[str]
) -> None:
    d = make_dagger(tmp_path, verbose=1, bc_steps_first=11)
    steps = stub_iteration(d, rollouts(rows(1, 0), 1, 1))

    class Dataset:
        obs = {k: np.zeros((5, 2), dtype=np.float32) for k in KEYS}
        actions = np.zeros((5, 2), dtype=np.float32)
        dataset_id = "bioscara/pp-v0"

        def __len__(self) -> int:
            return 5

    demos = Dataset()
    data, env_steps = d.first_iteration(demos)
    assert len(data) == 5 and env_steps == 0
    assert steps["_rollouts"].calls == []
    assert steps["_fit"].calls[0][0][1:] == (11, 0)
    assert steps["_log"].calls[0][0][:2] == (0, 0)
    assert (
        capsys.readouterr().out
        == "[dagger] iteration 0: cloned 5 states of dataset bioscara/pp-v0, loss 0.1250\n"
    )


# ------------------------------------------------------------------ rollouts and fitting
def test_rollouts_in_one_env_report_each_episode_to_the_progress_bar(
    tmp_path: Path, monkeypatch: pytest.MonkeyPatch
) -> None:
    d = make_dagger(tmp_path, seed=3)
    d.env, d.expert, d.venv = "env", expert, None
    episodes: list[tuple[int, dict[str, str]]] = []
    d.progress = SimpleNamespace(episode=lambda steps, **postfix: episodes.append((steps, postfix)))
    calls = Recorder("rollouts")
    monkeypatch.setattr(dagger, "label_episodes", calls)
    assert d._rollouts(learner, 4, 500, 2, 0.25) == "rollouts"
    ((args, _),) = calls.calls
    assert args[:7] == ("env", learner, expert, 4, 500, 2, 0.25)
    rng, on_episode = args[7], args[8]
    assert isinstance(rng, np.random.Generator)
    on_episode(True, 17)
    assert episodes == [(17, {"iteration": "2"})]


def test_the_mixtures_draws_depend_on_the_run_seed_and_the_iteration_only(
    tmp_path: Path, monkeypatch: pytest.MonkeyPatch
) -> None:
    monkeypatch.setattr(dagger, "label_episodes", lambda *args, **kwargs: args[7].random(3).tolist())

    def draws(seed: int, iteration: int) -> list[float]:
        d = make_dagger(tmp_path, seed=seed)
        d.env, d.expert, d.venv, d.progress = "env", expert, None, None
        return d._rollouts(learner, 1, 0, iteration, 0.5)

    assert draws(3, 2) == draws(3, 2)
    assert draws(3, 2) != draws(3, 1)
    assert draws(3, 2) != draws(4, 2)


def test_rollouts_on_workers_are_labelled_with_their_iteration(
    tmp_path: Path, monkeypatch: pytest.MonkeyPatch
) -> None:
    d = make_dagger(tmp_path)
    d.env, d.expert, d.venv = "env", expert, "venv"
    obs = [{k: np.array([i, 0.0]) for k in KEYS} for i in range(3)]
    results = [EpisodeResult(k < 2, False, 0.02, 1.0, 50) for k in range(4)]
    calls = Recorder((obs, [np.array(EXPERT_ACTION)] * 3, results))
    monkeypatch.setattr(dagger, "label_rollouts", calls)
    episodes: list[tuple[int, dict[str, str]]] = []
    d.progress = SimpleNamespace(episode=lambda steps, **postfix: episodes.append((steps, postfix)))
    r = d._rollouts(learner, 4, 500, 6, 0.25)
    ((args, kwargs),) = calls.calls
    assert args[:6] == ("venv", learner, expert, 4, 500, 0.25) and kwargs == {"max_failures": None}
    assert isinstance(args[6], np.random.Generator)  # the mixture's draws
    args[7](False, 30)  # each episode ends on the progress bar
    assert episodes == [(30, {"iteration": "6"})]
    assert (r.successes, r.episodes) == (2, 4)
    assert r.data.iteration.tolist() == [6, 6, 6]
    assert r.data.obs["observation"][:, 0].tolist() == [0.0, 1.0, 2.0]


def test_fitting_uses_the_configs_batch_rate_threads_and_loss_and_a_seed_per_iteration(
    tmp_path: Path, monkeypatch: pytest.MonkeyPatch
) -> None:
    d = make_dagger(tmp_path, seed=3, batch_size=64, learning_rate=0.01, fit_threads=3, loss="l1")
    calls = Recorder(0.5)
    monkeypatch.setattr(dagger, "fit_actor", calls)
    data = rows(2, 1)
    assert d._fit(data, 9, 2) == 0.5
    kwargs = {"seed": 3002, "threads": 3, "loss": "l1"}
    assert calls.calls == [(("the model", data.obs, data.actions, 9, 64, 0.01), kwargs)]


# ------------------------------------------------------------------ evaluation
def test_a_confirming_evaluation_allows_the_failures_the_target_leaves(
    tmp_path: Path, policy_of: None
) -> None:
    def confirm(n: int, target: float, i: int = 1) -> tuple[tuple[Any, ...], dict[str, Any]]:
        d = make_dagger(tmp_path, seed=3, eval_episodes=n, target_success=target)
        d._rollouts = Recorder(rollouts(rows(2, i), 1, 1))
        d.confirmation(i, 0)
        ((call,),) = [d._rollouts.calls]
        return call

    # The learner alone (beta 0), labelled as iteration i's rollouts are.
    args, kwargs = confirm(100, 0.9)
    assert args == (("policy of", "the model"), 100, 3_300_000, 1, 0.0)
    assert kwargs == {"max_failures": 10}
    assert confirm(10, 0.7)[1] == {"max_failures": 3}  # 10 x 0.7 is 7.000000000000001 in floating point
    assert confirm(3, 1.0)[1] == {"max_failures": 0}


def test_every_confirmation_runs_episodes_no_other_one_ran(tmp_path: Path, policy_of: None) -> None:
    # 3,000,000 + 100,000 x run seed 3 + (i - 1) x eval_episodes: fresh seeds in every
    # iteration, away from the rollouts' (2,030,000...) and the final evaluation's (10,003...).
    def seed(i: int, n: int) -> int:
        d = make_dagger(tmp_path, seed=3, eval_episodes=n)
        d._rollouts = Recorder(rollouts(rows(2, i), 1, 1))
        d.confirmation(i, 0)
        return d._rollouts.calls[0][0][2]

    assert [seed(i, 100) for i in (1, 2, 7)] == [3_300_000, 3_300_100, 3_300_600]
    assert seed(2, 30) == 3_300_030


def test_a_confirmation_returns_its_labelled_episodes_and_reports_them(
    tmp_path: Path, policy_of: None
) -> None:
    d = make_dagger(tmp_path, eval_episodes=10)
    check = rollouts(rows(5, 2), 7, 8)
    d._rollouts = Recorder(check)
    assert d.confirmation(2, 4321) is check
    assert d.logger.dumps == [(4321, {"eval/success_rate": 0.875, "eval/mean_final_distance": 0.02})]


def test_the_final_evaluation_runs_on_the_rollouts_workers_when_there_are_some(
    tmp_path: Path, policy_of: None, monkeypatch: pytest.MonkeyPatch
) -> None:
    one, workers = Recorder(stats(1.0, 10)), Recorder(stats(0.9, 10))
    monkeypatch.setattr(dagger, "run_episodes", one)
    monkeypatch.setattr(dagger, "run_episodes_on", workers)
    d = make_dagger(tmp_path, seed=3, eval_episodes=10, target_success=0.9)
    d.eval_env, d.venv = "eval env", "workers"
    assert d.evaluation(0) == stats(0.9, 10)
    assert one.calls == []
    assert workers.calls == [(("workers", ("policy of", "the model"), 10), {"seed": 10_003})]
    d.venv = None
    assert d.evaluation(0) == stats(1.0, 10)
    assert one.calls == [(("eval env", ("policy of", "the model"), 10), {"seed": 10_003})]


def test_an_evaluation_is_logged_at_its_env_step(
    tmp_path: Path, policy_of: None, monkeypatch: pytest.MonkeyPatch
) -> None:
    monkeypatch.setattr(dagger, "run_episodes", Recorder(stats(0.7, 10)))
    d = make_dagger(tmp_path, eval_episodes=10)
    d.eval_env = "eval env"
    assert d.evaluation(1234) == stats(0.7, 10)
    assert d.logger.dumps == [(1234, {"eval/success_rate": 0.7, "eval/mean_final_distance": 0.02})]


def test_an_evaluation_says_its_success_and_where_it_stopped(
    tmp_path: Path, policy_of: None, monkeypatch: pytest.MonkeyPatch, capsys: pytest.CaptureFixture[str]
) -> None:
    monkeypatch.setattr(dagger, "run_episodes", Recorder(stats(0.7, 10)))
    d = make_dagger(tmp_path, verbose=1, eval_episodes=10)
    d.eval_env = "eval env"
    d._rollouts = Recorder(rollouts(rows(3, 1), 3, 7))
    d.start = dagger.time.perf_counter()
    d.evaluation(1234)
    d.confirmation(1, 1300)
    assert capsys.readouterr().out == (
        "[eval] step    1234  0 s  success 70.0% over 10\n"
        "[eval] step    1300  0 s  success 42.9% over 7 (stopped: 4 failures)\n"
    )


def test_the_final_evaluation_is_the_confirming_one_else_one_run_now(tmp_path: Path) -> None:
    d = make_dagger(tmp_path)
    d.env_steps = 321
    d.evaluation = Recorder(stats(0.2))
    d.final = stats(0.95)
    assert d.evaluate(None) == stats(0.95) and d.evaluation.calls == []
    d.final = None
    assert d.evaluate(None) == stats(0.2)
    assert d.evaluation.calls == [((321,), {})]


# ------------------------------------------------------------------ the loop
class Guard:
    """A signal guard that counts the saves it shields."""

    def __init__(self) -> None:
        self.shielded_calls = 0

    @contextlib.contextmanager
    def shielded(self) -> Any:
        self.shielded_calls += 1
        yield


def loop_dagger(
    tmp_path: Path, monkeypatch: pytest.MonkeyPatch, finals: list[EvalStats | None], steps_each: int = 100
) -> tuple[DAgger, list[tuple[int, int, int]], list[tuple[int, int]], Logger]:
    """A DAgger whose iterations add ``steps_each`` env steps and end with ``finals`` in turn."""
    d = make_dagger(tmp_path)
    d.stack = contextlib.ExitStack()
    logger = Logger()
    made: list[tuple[str, list[str]]] = []
    monkeypatch.setattr(
        dagger, "configure_logger", lambda folder, formats: made.append((folder, formats)) or logger
    )
    iterations: list[tuple[int, int, int]] = []
    saves: list[tuple[int, int]] = []

    def first_iteration(demos: Any) -> tuple[Labelled, int]:
        return rows(2, 0), 50

    def iteration(i: int, data: Labelled, env_steps: int) -> tuple[Labelled, int, EvalStats | None]:
        iterations.append((i, len(data), env_steps))
        return data + rows(1, i), env_steps + steps_each, finals[len(iterations) - 1]

    d.first_iteration = first_iteration
    d.iteration = iteration
    d.checkpoint = lambda: saves.append((d.iteration_done, d.env_steps))
    d.demos = None
    d.made = made
    return d, iterations, saves, logger


def test_the_loop_runs_iterations_until_the_budget_with_a_checkpoint_after_each(
    tmp_path: Path, monkeypatch: pytest.MonkeyPatch
) -> None:
    d, iterations, saves, logger = loop_dagger(tmp_path, monkeypatch, [None] * 5)
    guard = Guard()
    d.learn(RunPlan(d.cfg, {}, 350, None), [], guard)
    # 50 steps of demonstrations, then 100 an iteration: 150, 250, 350 (the budget: stop).
    assert iterations == [(1, 2, 50), (2, 3, 150), (3, 4, 250)]
    assert saves == [(0, 50), (1, 150), (2, 250), (3, 350)]
    assert guard.shielded_calls == 3  # every save after iteration 0 is shielded from signals
    assert d.iteration_done == 3 and d.env_steps == 350 and d.final is None
    assert d.made == [(str(tmp_path / "run" / "tb" / "dagger"), ["tensorboard"])]
    assert not logger.closed
    d.stack.close()
    assert logger.closed


def test_the_loop_stops_at_the_confirmed_target_without_a_checkpoint(
    tmp_path: Path, monkeypatch: pytest.MonkeyPatch
) -> None:
    d, iterations, saves, _ = loop_dagger(tmp_path, monkeypatch, [None, stats(0.95), None])
    d.learn(RunPlan(d.cfg, {}, 10_000, None), [], Guard())
    assert [i for i, *_ in iterations] == [1, 2]
    assert saves == [(0, 50), (1, 150)]  # the model that reached it is saved as model.zip
    assert d.iteration_done == 2 and d.final == stats(0.95)


def test_a_resumed_loop_continues_after_the_checkpoints_iteration(
    tmp_path: Path, monkeypatch: pytest.MonkeyPatch
) -> None:
    d, iterations, saves, _ = loop_dagger(tmp_path, monkeypatch, [None] * 5)
    d.data, d.iteration_done, d.env_steps = rows(4, 0), 3, 300
    d.learn(RunPlan(d.cfg, {}, 500, None), [], Guard())
    assert iterations == [(4, 4, 300), (5, 5, 400)]
    assert saves == [(4, 400), (5, 500)]


def test_a_resumed_loop_already_at_its_budget_runs_no_iteration_and_has_no_final_evaluation(
    tmp_path: Path, monkeypatch: pytest.MonkeyPatch
) -> None:
    d, iterations, saves, _ = loop_dagger(tmp_path, monkeypatch, [None])
    d.data, d.iteration_done, d.env_steps = rows(4, 0), 3, 500
    d.evaluation = Recorder(stats(0.3))
    d.learn(RunPlan(d.cfg, {}, 500, None), [], Guard())
    assert iterations == [] and saves == [] and d.final is None
    assert d.evaluate(None) == stats(0.3)  # the final evaluation then runs now


def test_the_progress_bar_starts_at_the_steps_done_and_is_closed_even_on_an_error(
    tmp_path: Path, monkeypatch: pytest.MonkeyPatch
) -> None:
    bars: list[Any] = []

    class Bar:
        def __init__(self, total: int, enabled: bool, done: int) -> None:
            self.made, self.closed = (total, enabled, done), False
            bars.append(self)

        def close(self) -> None:
            self.closed = True

    monkeypatch.setattr(dagger, "_Progress", Bar)
    d, *_ = loop_dagger(tmp_path, monkeypatch, [None])
    d.args.progress = True
    d.data, d.env_steps = rows(1, 0), 300

    def broken(*args: Any) -> None:
        raise KeyboardInterrupt

    d.iteration = broken
    with pytest.raises(KeyboardInterrupt):
        d.learn(RunPlan(d.cfg, {}, 500, None), [], Guard())
    assert bars[0].made == (500, True, 300) and bars[0].closed
    assert d.iteration_done == 0  # an interrupted iteration is run again on --resume


def test_the_progress_bar_counts_env_steps(monkeypatch: pytest.MonkeyPatch) -> None:
    # A stand-in for tqdm: a real bar left open in a forked test process can hang it.
    class Bar:
        def __init__(self, **kwargs: Any) -> None:
            self.kwargs, self.n, self.postfixes, self.closed = kwargs, kwargs.get("initial", 0), [], False

        def update(self, n: int) -> None:
            self.n += n

        def set_postfix(self, postfix: dict[str, str]) -> None:
            self.postfixes.append(postfix)

        def close(self) -> None:
            self.closed = True

    monkeypatch.setattr("tqdm.auto.tqdm", Bar)
    progress = dagger._Progress(500, True, 120)
    bar = progress.bar
    assert bar.kwargs == {"total": 500, "initial": 120, "desc": "dagger", "unit": "step", "disable": False}
    progress.episode(30, iteration="2")
    progress.episode(5)
    assert bar.n == 155 and bar.postfixes == [{"iteration": "2"}]
    progress.close()
    assert bar.closed
    assert dagger._Progress(10, False, 0).bar.kwargs["disable"] is True


# ------------------------------------------------------------------ checkpoints
def test_a_checkpoint_holds_the_model_the_aggregate_the_iteration_and_the_env_steps(tmp_path: Path) -> None:
    d = make_dagger(tmp_path)
    d.model = ZipModel()
    d.data, d.iteration_done, d.env_steps = rows(2, 0, 1.0) + rows(1, 2, 3.0), 2, 340
    path = d.checkpoint()
    assert path == tmp_path / "run" / "checkpoints" / "ckpt_340_steps.zip"
    assert zipfile.ZipFile(path).namelist() == ["data", "policy.pth"]
    with np.load(tmp_path / "run" / "checkpoints" / "ckpt_340_steps_dagger.npz") as z:
        assert sorted(z.files) == [
            "actions",
            "env_steps",
            "iteration",
            "obs_achieved_goal",
            "obs_desired_goal",
            "obs_observation",
            "row_iteration",
        ]
        assert (int(z["iteration"]), int(z["env_steps"])) == (2, 340)
        assert z["row_iteration"].tolist() == [0, 0, 2]
        assert z["actions"][:, 0].tolist() == [1.0, 1.0, 3.0]
        for k in KEYS:
            assert z[f"obs_{k}"][:, 1].tolist() == [1.0, 1.0, 3.0]


@pytest.mark.parametrize("data", [None, rows(0, 0)], ids=["none", "empty"])
def test_nothing_is_saved_before_iteration_zero_has_labelled_its_states(
    tmp_path: Path, data: Labelled | None
) -> None:
    d = make_dagger(tmp_path)
    d.model, d.data = ZipModel(), data
    assert d.checkpoint() is None
    assert not (tmp_path / "run").exists()


def test_resume_loads_the_newest_checkpoint_with_its_aggregate(
    tmp_path: Path, monkeypatch: pytest.MonkeyPatch
) -> None:
    loads: list[tuple[Path, Any, str]] = []

    class SAC:
        @staticmethod
        def load(path: Path, env: Any, device: str) -> str:
            loads.append((Path(path), env, device))
            return "loaded model"

    monkeypatch.setattr(dagger, "SAC", SAC)
    d = make_dagger(tmp_path)
    d.model = ZipModel()
    d.data, d.iteration_done, d.env_steps = rows(2, 0), 0, 100
    d.checkpoint()
    d.data, d.iteration_done, d.env_steps = rows(2, 0, 1.0) + rows(1, 1, 5.0), 1, 160
    d.checkpoint()
    r = make_dagger(tmp_path)
    r.args.resume = True
    r.env = "env"
    assert r.build_model(None) == "loaded model"
    assert loads == [(tmp_path / "run" / "checkpoints" / "ckpt_160_steps.zip", "env", "cpu")]
    assert (r.iteration_done, r.env_steps) == (1, 160)
    assert r.data.iteration.tolist() == [0, 0, 1]
    assert r.data.actions[:, 0].tolist() == [1.0, 1.0, 5.0]
    assert r.data.obs["desired_goal"][:, 0].tolist() == [1.0, 1.0, 5.0]


# ------------------------------------------------------------------ plan, envs, model, metadata
def write_config(tmp_path: Path, **entry: Any) -> Path:
    import yaml

    path = tmp_path / "dagger.yaml"
    body = {"n_timesteps": 1000, "env_kwargs": {"control_mode": "cartesian", "backend": "mock"}, **entry}
    path.write_text(yaml.safe_dump({PICK: body}), encoding="utf-8")
    return path


def test_the_plan_takes_the_configs_budget_unless_timesteps_are_given(tmp_path: Path) -> None:
    config = write_config(tmp_path, net_arch=[16])
    d = make_dagger(tmp_path, seed=3)
    d.args.config = config
    plan = d.plan()
    assert plan.total == 1000 and plan.config is d.cfg and d.cfg.net_arch == (16,)
    assert plan.env_kwargs == {"control_mode": "cartesian", "backend": "mock"}
    assert plan.state == {
        "env_id": PICK,
        "algo": "dagger",
        "seed": 3,
        "total_timesteps": 1000,
        "config": str(config),
        "demos": None,
    }
    d.args.timesteps, d.args.demos = 300, "pp"
    plan = d.plan()
    assert plan.total == 300 and plan.state["total_timesteps"] == 300 and plan.state["demos"] == "pp"


def test_the_plan_without_a_config_reads_the_packaged_one(tmp_path: Path) -> None:
    d = make_dagger(tmp_path)
    d.args.config = None
    plan = d.plan()
    assert plan.total == 120_000 and d.cfg.beta == 0.5 and plan.state["config"] is None


def test_a_resumed_plan_keeps_the_runs_budget_config_and_demos(tmp_path: Path) -> None:
    config = write_config(tmp_path, net_arch=[16])
    out = tmp_path / "run"
    state = {
        "env_id": PICK,
        "algo": "dagger",
        "seed": 7,
        "total_timesteps": 600,
        "config": str(config),
        "demos": "pp",
    }
    write_run_state(out, state)
    (out / "checkpoints").mkdir()
    (out / "checkpoints" / "ckpt_100_steps.zip").write_bytes(b"")
    d = make_dagger(tmp_path)
    d.args.resume, d.args.config, d.args.seed = True, None, None  # --seed not given: the run's
    plan = d.plan()
    assert plan.total == 600 and plan.state == state and d.cfg.net_arch == (16,)


def test_a_bad_config_is_a_training_error_with_the_configs_words(tmp_path: Path) -> None:
    d = make_dagger(tmp_path)
    d.args.config = write_config(tmp_path, beta=1.0)
    with pytest.raises(TrainingError) as caught:
        d.plan()
    assert str(caught.value) == f"config {tmp_path / 'dagger.yaml'}: beta is 1.0; expected [0, 1)"


def test_the_envs_are_one_to_act_one_to_evaluate_and_workers_only_when_asked(
    tmp_path: Path, monkeypatch: pytest.MonkeyPatch
) -> None:
    made = Recorder(SimpleNamespace(close=lambda: closed.append(True)))
    closed: list[bool] = []
    monkeypatch.setattr(dagger, "make_vec_envs", made)
    kwargs = {"control_mode": "cartesian", "backend": "mock"}
    for n_envs, workers in ((None, None), (1, None), (2, 2)):
        d = make_dagger(tmp_path, n_envs=1)
        d.args.n_envs = n_envs
        with contextlib.ExitStack() as stack:
            env = d.make_envs(RunPlan(d.cfg, kwargs, 100, None), stack)
            assert env is d.env and d.eval_env is not d.env
            assert env.spec.id == PICK and env.unwrapped.control_mode == "cartesian"
            assert isinstance(d.expert, ObservationExpert) and d.demos is None
            assert (d.venv is None) == (workers is None)
        if workers:
            assert made.calls == [((PICK, 2, kwargs), {})] and closed == [True]
    d = make_dagger(tmp_path, n_envs=2)
    with contextlib.ExitStack() as stack:
        d.make_envs(RunPlan(d.cfg, kwargs, 100, None), stack)
        assert d.venv is not None  # the config's n_envs


def test_demos_named_are_loaded_and_checked_against_the_env(
    tmp_path: Path, monkeypatch: pytest.MonkeyPatch
) -> None:
    checked: list[tuple[str, Any]] = []
    monkeypatch.setattr(dagger, "load_demos", lambda name: f"demos {name}")
    monkeypatch.setattr(dagger, "check_demos", lambda demos, env: checked.append((demos, env)))
    d = make_dagger(tmp_path)
    d.args.demos = "pp"
    with contextlib.ExitStack() as stack:
        env = d.make_envs(RunPlan(d.cfg, {"control_mode": "cartesian", "backend": "mock"}, 100, None), stack)
    assert d.demos == "demos pp" and checked == [("demos pp", env)]


def test_the_model_is_a_sac_model_with_the_configs_network_and_no_replay_buffer(tmp_path: Path) -> None:
    d = make_dagger(tmp_path, seed=3, net_arch=(8, 4), features={"coarse_m": 0.2})
    d.env = gym.make(PICK, control_mode="cartesian", backend="mock")
    try:
        model = d.build_model(RunPlan(d.cfg, {}, 100, None))
    finally:
        d.env.close()
    assert model.policy_kwargs["net_arch"] == [8, 4]
    assert model.policy_kwargs["features_extractor_class"] is PickPlaceExtractor
    # With what the extractor takes from the env (FROM_ENV): the packaged URDF's joint ranges.
    joint_range = [[-3.04647, 3.04647], [-0.0016, 0.338], [-2.62672, 2.62672], [-3.01069, 3.01069]]
    kwargs = model.policy_kwargs["features_extractor_kwargs"]
    assert kwargs.keys() == {"coarse_m", "joint_range"} and kwargs["coarse_m"] == 0.2
    np.testing.assert_allclose(kwargs["joint_range"], joint_range, rtol=1e-6)
    assert model.buffer_size == 1 and model.seed == 3 and model.device.type == "cpu"
    assert model.actor.features_extractor.coarse_m == 0.2


def test_a_model_the_config_cannot_build_is_a_training_error_naming_the_config(tmp_path: Path) -> None:
    d = make_dagger(tmp_path, features={"no_such_setting": 1.0})
    d.env = gym.make(PICK, control_mode="cartesian", backend="mock")
    try:
        with pytest.raises(TrainingError, match=r"^config test\.yaml: .*no_such_setting"):
            d.build_model(RunPlan(d.cfg, {}, 100, None))
    finally:
        d.env.close()


def test_the_metadata_records_the_iterations_the_states_and_the_demos(tmp_path: Path) -> None:
    d = make_dagger(tmp_path)
    d.args.demos = "pp"
    d.iteration_done, d.data, d.env_steps = 4, rows(7, 0), 900
    d.start = dagger.time.perf_counter() - 12.34
    assert d.metadata(None) == {
        "dagger": {"iterations": 4, "labelled_states": 7, "demos": "pp", "wall_time_s": 12.3}
    }
    assert d.timesteps == 900
    d.data = None
    assert d.metadata(None)["dagger"]["labelled_states"] == 0


def test_each_cloning_is_logged_with_its_loss_share_and_rollout_success(tmp_path: Path) -> None:
    d = make_dagger(tmp_path)
    d.start = dagger.time.perf_counter()
    d._log(2, 400, rows(9, 0), 0.25, 0.45, 0.25)
    d._log(0, 100, rows(3, 0), 0.5, None, 1.0)
    (step, first), (step0, zeroth) = d.logger.dumps
    assert step == 400 and step0 == 100
    wall = first.pop("time/wall_s")
    assert 0 <= wall < 5
    assert first == {
        "dagger/iteration": 2,
        "dagger/labelled_states": 9,
        "dagger/bc_loss": 0.25,
        "dagger/beta": 0.25,
        "dagger/rollout_success": 0.45,
    }
    assert "dagger/rollout_success" not in zeroth and zeroth["dagger/beta"] == 1.0


# ------------------------------------------------------------------ after the first run's survivors
def test_the_action_the_expert_takes_is_the_label_recorded_bit_for_bit() -> None:
    # 0.1 has no exact float32: the env is sent the float32 label, not the expert's float64.
    env = Episodes([3], [True])

    def tenths(obs: dict[str, np.ndarray]) -> np.ndarray:
        return np.array([0.1, 0.3])

    r = label_episodes(env, learner, tenths, 1, seed=0, iteration=1, beta=1.0)
    sent = np.array(env.actions)
    np.testing.assert_array_equal(sent, r.data.actions.astype(np.float64))
    assert sent[0, 0] == float(np.float32(0.1)) != 0.1


def test_a_task_without_a_spec_is_named_by_the_env_itself(monkeypatch: pytest.MonkeyPatch) -> None:
    def no_expert(env: Any) -> Any:
        raise LookupError("none")

    monkeypatch.setattr(dagger, "task_of", no_expert)
    env = SimpleNamespace(spec=None, unwrapped=None)
    with pytest.raises(
        TrainingError, match=r"^DAgger needs an expert that can label any state; namespace\(spec="
    ):
        dagger.expert_labeller(env)


def test_the_evaluation_env_is_made_with_the_runs_env_kwargs(tmp_path: Path) -> None:
    d = make_dagger(tmp_path)
    with contextlib.ExitStack() as stack:
        d.make_envs(RunPlan(d.cfg, {"control_mode": "cartesian", "backend": "mock"}, 100, None), stack)
        assert d.eval_env.unwrapped.control_mode == "cartesian"
        assert type(d.eval_env.unwrapped.backend).__name__ == type(d.env.unwrapped.backend).__name__


def test_an_extractor_that_takes_nothing_from_the_env_builds_too(tmp_path: Path) -> None:
    # InsertExtractor declares no FROM_ENV: nothing of the env is passed to it.
    d = make_dagger(tmp_path, net_arch=(8,))
    d.env = gym.make("Bioscara-Insert-v0", backend="mock")
    try:
        model = d.build_model(RunPlan(d.cfg, {}, 100, None))
    finally:
        d.env.close()
    assert model.policy_kwargs["features_extractor_kwargs"] == {}


def test_the_model_is_built_on_the_cpu_even_where_a_gpu_is_seen(
    tmp_path: Path, monkeypatch: pytest.MonkeyPatch
) -> None:
    # train.py: "Train a policy on CPU". With SB3's default device "auto" this would ask for CUDA.
    import torch

    monkeypatch.setattr(torch.cuda, "is_available", lambda: True)
    d = make_dagger(tmp_path, net_arch=(8,))
    d.env = gym.make(PICK, control_mode="cartesian", backend="mock")
    try:
        model = d.build_model(RunPlan(d.cfg, {}, 100, None))
    finally:
        d.env.close()
    assert model.device.type == "cpu"


def test_each_line_said_is_flushed_at_once(tmp_path: Path, monkeypatch: pytest.MonkeyPatch) -> None:
    # A run piped to a file shows each iteration as it ends.
    class Stdout:
        def __init__(self) -> None:
            self.events: list[str] = []

        def write(self, text: str) -> None:
            self.events.append(f"write {text!r}")

        def flush(self) -> None:
            self.events.append("flush")

    stdout = Stdout()
    monkeypatch.setattr("sys.stdout", stdout)
    make_dagger(tmp_path, verbose=1)._say("iteration 1")
    assert stdout.events[-1] == "flush" and "write 'iteration 1'" in stdout.events
