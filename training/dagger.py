"""DAgger for Bioscara-PickPlace: behaviour cloning that asks the expert about the learner's own states.

Ross, Gordon & Bagnell, "A Reduction of Imitation Learning and Structured
Prediction to No-Regret Online Learning" (AISTATS 2011). Plain behaviour
cloning trains on the states the expert visits; a small error takes the
learner to states the expert never saw, where it errs more (the
compounding error of long tasks: PickPlace is 200 steps of approach, descend,
squeeze, carry). DAgger closes that gap:

1. clone the expert's episodes (:func:`~bioscara_gym.training.bc.bc_pretrain`);
2. roll out the learner, label every state it visits with the expert's action;
3. add them to the dataset, clone again from the aggregate; repeat.

The scripted :class:`~bioscara_gym.experts.PickPlaceExpert` keeps a phase
(approach, descend, squeeze, carry), a squeeze counter and the elbow chosen
per phase, so its action is not a function of the observation alone and it
cannot label a state it did not reach itself. :class:`ObservationExpert` is
the same controller with that state read from the observation: the phase
from where the block is relative to the TCP and whether the gripper is
commanded closed (the observation holds the commanded width), the squeeze
counter replaced by closing in steps (the width itself counts them), and the
elbow kept by a switching cost instead of a memory. Its phase tests have
tolerances, so a learner's inexact gripper output does not flip the phase.

``bioscara train --env Bioscara-PickPlace`` runs :func:`train_dagger` with
``training/configs/dagger.yaml`` (:class:`DaggerConfig`); the model is a SAC
model whose actor was cloned, so ``eval``, ``export`` and ``deploy`` load it
as ``--algo bc``'s. Measured figures and the choices behind the config: the
README, "Learning PickPlace from demonstrations".
"""

from __future__ import annotations

import contextlib
import dataclasses
import difflib
import io
import json
import math
import signal
import time
import zipfile
from collections.abc import Callable
from dataclasses import dataclass, field
from importlib import resources
from pathlib import Path
from typing import Any

import gymnasium as gym
import numpy as np
import yaml

from bioscara_gym import kinematics
from bioscara_gym.envs.base import BioscaraEnv
from bioscara_gym.envs.pick_place import BLOCK_SIZE, BioscaraPickPlaceEnv
from bioscara_gym.errors import HyperparamError, TrainingError
from bioscara_gym.experts import PickPlaceExpert
from bioscara_gym.fsutil import atomic_write_bytes, atomic_write_text
from bioscara_gym.training.demos import GOAL_KEYS, Demos, check_demos, load_demos
from bioscara_gym.training.evaluate import EvalStats, run_episodes
from bioscara_gym.training.extras import needs_train
from bioscara_gym.training.metadata import build_metadata, save_policy
from bioscara_gym.training.signals import Interrupted, SignalGuard

with needs_train():
    import torch as th
    from gymnasium import spaces
    from stable_baselines3 import SAC
    from stable_baselines3.common.logger import configure as configure_logger
    from stable_baselines3.common.torch_layers import BaseFeaturesExtractor

    from bioscara_gym.training.algos import sb3_policy
    from bioscara_gym.training.bc import fit_actor
    from bioscara_gym.training.run import (
        CHECKPOINT_RE,
        STATE_NAME,
        TrainArgs,
        TrainingInterrupted,
        TrainResult,
    )
    from bioscara_gym.training.zoo import EVAL_SEED_OFFSET


Policy = Callable[[dict[str, np.ndarray]], np.ndarray]


class ObservationExpert(PickPlaceExpert):
    """The PickPlace expert as a function of the observation (see the module docstring).

    Phases, decided afresh every step:

    | phase    | when                                                       | does                          |
    |----------|------------------------------------------------------------|-------------------------------|
    | carry    | gripper commanded fully closed, block between the fingers  | block to the target           |
    | squeeze  | gripper closing, or open at grasp height over the block    | closes in ``SQUEEZE_LEVELS``  |
    | release  | gripper closed, block not between the fingers              | opens, as approach            |
    | descend  | open, within ``ALIGN_M`` of the block (``ALIGN_LOW_M`` low) | down to ``GRASP_Z``           |
    | approach | otherwise                                                  | above the block, wrist square |
    """

    #: Horizontal TCP-block distance (m) from which the gripper descends.
    ALIGN_M = 0.003
    #: The same while already below the approach height (no lift for a small drift).
    ALIGN_LOW_M = 0.008
    #: Block between the fingers: horizontal offset (m) and vertical range of block minus TCP.
    HOLD_XY_M = 0.008
    HOLD_Z_M = (-0.005, 0.012)
    #: Gripper action (unit) within which the width counts as open, and as closed: a
    #: learner's gripper output is never exact, and a phase must not flip on its last digit.
    WIDTH_TOL = 0.15
    CLOSED_TOL = 0.03
    #: Gripper actions of the squeeze, one a step (-1 is 0.04 m, fully closed): the width
    #: itself counts the steps, in steps a learner can tell apart (the scripted expert
    #: waits 8 steps, measured enough from 3).
    SQUEEZE_LEVELS = (-0.4, -0.7, -0.9)
    #: TCP height (m) within which the gripper counts as at grasp height.
    GRASP_TOL_M = 0.003
    #: Cost (s of the slowest joint's travel) of changing elbow.
    ELBOW_SWITCH_S = 0.3

    def __init__(self, env: BioscaraEnv) -> None:
        """Bind to ``env`` (use ``env.unwrapped``)."""
        super().__init__(env)
        self._u_open = self._width_action(self.OPEN)
        self._u_closed = self._width_action(self.CLOSED)

    def _squeeze_step(self, width: float) -> float:
        """The next gripper action of the squeeze: the first of ``SQUEEZE_LEVELS`` below ``width`` by 0.1."""
        return next((level for level in self.SQUEEZE_LEVELS if level < width - 0.1), self._u_closed)

    def phase_of(self, obs: dict[str, np.ndarray]) -> str:
        """The phase ``obs`` is in (see the class docstring)."""
        o, s = obs["observation"], self._slices
        tcp, block = o[s["tcp"]], o[s["block_pos"]]
        width = float(o[s["gripper"]][0])
        d = block - tcp
        xy = math.hypot(d[0], d[1])
        held = xy < self.HOLD_XY_M and self.HOLD_Z_M[0] < d[2] < self.HOLD_Z_M[1]
        if width <= self._u_closed + self.CLOSED_TOL:
            return "carry" if held else "release"
        if width < self._u_open - self.WIDTH_TOL:  # closing
            return "squeeze" if held else "release"
        if abs(tcp[2] - self.GRASP_Z) < self.GRASP_TOL_M and xy < self.ALIGN_M:
            return "squeeze"
        low = tcp[2] < BLOCK_SIZE + 0.01 - 0.002
        if xy < self.ALIGN_M or (low and xy < self.ALIGN_LOW_M):
            return "descend"
        return "approach"

    def __call__(self, obs: dict[str, np.ndarray]) -> np.ndarray:
        """Action for ``obs``."""
        o = obs["observation"]
        q = self.ctrl.joints(o)
        s = self._slices
        tcp, block, yaw = o[s["tcp"]], o[s["block_pos"]], float(o[s["block_yaw"]][0])
        phase = self.phase = self.phase_of(obs)
        width_u = self._u_open
        if phase in ("approach", "release"):
            xyz = np.array([block[0], block[1], max(tcp[2], BLOCK_SIZE + 0.01)])
        elif phase == "descend":
            xyz = np.array([block[0], block[1], self.GRASP_Z])
        elif phase == "squeeze":
            xyz = np.array([block[0], block[1], self.GRASP_Z])
            width_u = self._squeeze_step(float(o[s["gripper"]][0]))
        else:  # carry
            width_u = self._u_closed
            xyz = obs["desired_goal"] - (block - tcp)
            xyz[2] = max(xyz[2], self.GRASP_Z)
        if self.env.control_mode == "cartesian":
            q4_target = self._wrist_for(q, yaw) if phase in ("approach", "descend") else q[3]
            a = self.ctrl.cartesian_action(tcp, xyz, q[3], q4_target)
            return np.append(a, width_u).astype(np.float32)
        target = self._solve_sticky(xyz, q)
        if phase in ("approach", "descend", "release"):
            target[3] = self._wrist_for(target, yaw)
        else:
            target[3] = q[3]
        return np.append(self.ctrl.action(q, target), width_u).astype(np.float32)

    def _solve_sticky(self, xyz: np.ndarray, q: np.ndarray) -> np.ndarray:
        """IK target reached soonest, the other elbow charged ``ELBOW_SWITCH_S``; ``q`` if unreachable."""
        ctrl = self.ctrl
        current = 1.0 if q[2] >= 0 else -1.0
        best, best_cost = q.copy(), math.inf
        for sign in (1.0, -1.0):
            sol = kinematics.inverse(xyz, sign)
            if sol is None:
                continue
            cand = np.array([sol[0], sol[1], sol[2], q[3]])
            if np.any(cand[:3] < ctrl.cmd_lo[:3]) or np.any(cand[:3] > ctrl.cmd_hi[:3]):
                continue
            travel = np.abs(cand[:3] - q[:3]) / ctrl.vmax[:3]
            cost = float(np.max(travel) + 0.1 * np.sum(travel))
            if sign != current:
                cost += self.ELBOW_SWITCH_S
            if cost < best_cost:
                best, best_cost = cand, cost
        return best


#: Entries of PickPlace's ``observation`` given in m (or m/s), scaled by ``coarse_m``.
LENGTH_SLICES = ("tcp", "block_pos", "block_from_tcp", "block_vel")


class PickPlaceExtractor(BaseFeaturesExtractor):
    """PickPlace's observation with every length in ``coarse_m``, plus a fine view of the two errors.

    Features, in order: ``observation`` with the entries of
    :data:`LENGTH_SLICES` divided by ``coarse_m`` (the rest is already in
    [-1, 1] or rad); the goal error ``desired - achieved`` over ``coarse_m``;
    then block-from-TCP and the goal error over ``fine_m``, clipped to
    ``+-fine_clip``. The phases turn on millimetres (the gripper descends
    within 3 mm of the block), which a network sees in metres only as tiny
    inputs; the whole workspace in ``fine_m`` would be inputs of 50.

    Args:
        observation_space: Bioscara-PickPlace's ``Dict`` space.
        coarse_m: Length that maps to 1.0 in the coarse view.
        fine_m: Length that maps to 1.0 in the fine view.
        fine_clip: Bound of the fine view.

    Raises:
        ValueError: Not PickPlace's observation space, or a scale not positive.
    """

    def __init__(
        self,
        observation_space: spaces.Dict,
        coarse_m: float = 0.1,
        fine_m: float = 0.005,
        fine_clip: float = 3.0,
    ) -> None:
        """Check the space and build the scale vector."""
        slices = BioscaraPickPlaceEnv.OBS_SLICES
        n_obs = max(s.stop for s in slices.values())
        if not isinstance(observation_space, spaces.Dict) or any(
            k not in observation_space.spaces for k in GOAL_KEYS
        ):
            raise ValueError(f"PickPlaceExtractor needs a goal env's Dict space, got {observation_space}")
        if observation_space["observation"].shape != (n_obs,):
            raise ValueError(
                f"PickPlaceExtractor: observation has shape {observation_space['observation'].shape}, "
                f"PickPlace's is ({n_obs},)"
            )
        if not (coarse_m > 0 and fine_m > 0 and fine_clip > 0):
            raise ValueError(f"PickPlaceExtractor: scales {coarse_m}, {fine_m}, {fine_clip} must be > 0")
        n_goal = observation_space["desired_goal"].shape[0]
        super().__init__(observation_space, features_dim=n_obs + 2 * n_goal + 3)
        scale = th.ones(n_obs)
        for name in LENGTH_SLICES:
            scale[slices[name]] = 1.0 / coarse_m
        self.register_buffer("scale", scale)
        self._bft = slices["block_from_tcp"]
        self.coarse_m, self.fine_m, self.fine_clip = float(coarse_m), float(fine_m), float(fine_clip)

    def forward(self, observations: dict[str, th.Tensor]) -> th.Tensor:
        """Features of a batch of dict observations."""
        o = observations["observation"]
        error = observations["desired_goal"] - observations["achieved_goal"]
        fine = th.cat((o[:, self._bft], error), dim=1) / self.fine_m
        return th.cat(
            (o * self.scale, error / self.coarse_m, th.clamp(fine, -self.fine_clip, self.fine_clip)), dim=1
        )


@dataclass(frozen=True)
class Labelled:
    """States and the expert's actions in them (DAgger's aggregate dataset).

    Attributes:
        obs: ``observation``, ``achieved_goal``, ``desired_goal``, one row per state.
        actions: The expert's action in each state.
        iteration: The DAgger iteration each row was collected in (0: the expert's own episodes).
    """

    obs: dict[str, np.ndarray]
    actions: np.ndarray
    iteration: np.ndarray

    def __len__(self) -> int:
        """Number of labelled states."""
        return len(self.actions)

    def __add__(self, other: Labelled) -> Labelled:
        """Both datasets, ``self``'s rows first."""
        return Labelled(
            obs={k: np.concatenate((self.obs[k], other.obs[k])) for k in GOAL_KEYS},
            actions=np.concatenate((self.actions, other.actions)),
            iteration=np.concatenate((self.iteration, other.iteration)),
        )

    @classmethod
    def from_demos(cls, demos: Demos) -> Labelled:
        """A demonstration dataset's states and actions, as iteration 0."""
        return cls({k: demos.obs[k] for k in GOAL_KEYS}, demos.actions, np.zeros(len(demos), dtype=np.int32))


@dataclass(frozen=True)
class Rollouts:
    """What :func:`label_episodes` recorded."""

    data: Labelled
    successes: int
    episodes: int

    @property
    def success_rate(self) -> float:
        """Fraction of the episodes that ended in success."""
        return self.successes / self.episodes


def label_episodes(
    env: gym.Env,
    act: Policy,
    expert: Policy,
    episodes: int,
    seed: int,
    iteration: int,
    beta: float = 0.0,
    rng: np.random.Generator | None = None,
    on_episode: Callable[[bool, int], None] | None = None,
) -> Rollouts:
    """Run ``episodes`` seeded episodes acting with ``act``; label every state with ``expert``.

    With ``act`` the expert itself, these are demonstrations; with the
    learner, DAgger's new data (the states the learner reaches). With
    ``beta`` > 0 each step takes the expert's action with that probability
    (drawn from ``rng``): DAgger's mixture policy, which carries a weak
    learner into the later phases of the task.
    """
    rng = rng if rng is not None else np.random.default_rng(seed)
    obs_rows: list[dict[str, np.ndarray]] = []
    labels: list[np.ndarray] = []
    successes = 0
    for ep in range(episodes):
        obs, _ = env.reset(seed=seed + ep)
        done, info, steps = False, {}, 0
        while not done:
            steps += 1
            label = np.asarray(expert(obs), dtype=np.float32)
            action = label if act is expert or (beta > 0 and rng.random() < beta) else act(obs)
            obs_rows.append(obs)
            labels.append(label)
            obs, _, terminated, truncated, info = env.step(action)
            done = terminated or truncated
        success = bool(info.get("is_success", False))
        successes += success
        if on_episode is not None:
            on_episode(success, steps)
    data = Labelled(
        obs={k: np.array([o[k] for o in obs_rows], dtype=np.float32) for k in GOAL_KEYS},
        actions=np.array(labels, dtype=np.float32),
        iteration=np.full(len(labels), iteration, dtype=np.int32),
    )
    return Rollouts(data, successes, episodes)


# ------------------------------------------------------------------ configuration
#: The packaged DAgger entries (not an rl-zoo3 file: rl-zoo3 has no imitation learning).
CONFIG_NAME = "dagger.yaml"


@dataclass(frozen=True)
class DaggerConfig:
    """One env's entry of ``training/configs/dagger.yaml``, checked on load.

    Attributes:
        source: File the entry came from.
        n_timesteps: Budget in env steps, the expert's episodes included.
        env_kwargs: Keyword arguments for ``gym.make``.
        net_arch: Hidden layers of the actor.
        features: Keyword arguments of :class:`PickPlaceExtractor`.
        demo_episodes: Expert episodes cloned first (iteration 0).
        episodes_per_iteration: Learner episodes labelled per iteration.
        bc_steps_first: Gradient steps of the first cloning.
        bc_steps: Gradient steps after each aggregation (warm-started).
        batch_size: Labelled states per gradient step.
        learning_rate: Adam's learning rate.
        beta: The expert acts a share ``beta ** i`` of iteration ``i``'s steps.
        eval_episodes: Episodes of the confirming success evaluation.
        target_success: Success rate at which training stops.
    """

    source: str
    n_timesteps: int = 72_000
    env_kwargs: dict[str, Any] = field(default_factory=dict)
    net_arch: tuple[int, ...] = (256, 256)
    features: dict[str, float] = field(default_factory=dict)
    demo_episodes: int = 60
    episodes_per_iteration: int = 20
    bc_steps_first: int = 3000
    bc_steps: int = 2000
    batch_size: int = 256
    learning_rate: float = 1e-3
    beta: float = 0.5
    eval_episodes: int = 100
    target_success: float = 0.9

    def __post_init__(self) -> None:
        """Refuse counts below 1 and rates outside their range.

        Raises:
            HyperparamError: The first bad value, named with the file.
        """
        where = f"config {self.source}"
        counts = ("n_timesteps", "demo_episodes", "episodes_per_iteration", "bc_steps_first", "batch_size")
        for name in (*counts, "eval_episodes"):
            value = getattr(self, name)
            if isinstance(value, bool) or not isinstance(value, int) or value < 1:
                raise HyperparamError(f"{where}: {name} is {value!r}; expected a whole number >= 1")
        if isinstance(self.bc_steps, bool) or not isinstance(self.bc_steps, int) or self.bc_steps < 0:
            raise HyperparamError(f"{where}: bc_steps is {self.bc_steps!r}; expected a whole number >= 0")
        if not 0.0 < self.target_success <= 1.0:
            raise HyperparamError(f"{where}: target_success is {self.target_success!r}; expected (0, 1]")
        if not 0.0 <= self.beta < 1.0:
            raise HyperparamError(f"{where}: beta is {self.beta!r}; expected [0, 1)")
        if not self.learning_rate > 0:
            raise HyperparamError(f"{where}: learning_rate is {self.learning_rate!r}; expected > 0")
        if not self.net_arch or any(
            isinstance(n, bool) or not isinstance(n, int) or n < 1 for n in self.net_arch
        ):
            raise HyperparamError(f"{where}: net_arch is {list(self.net_arch)!r}; expected layer widths >= 1")

    def as_dict(self) -> dict[str, Any]:
        """A JSON-friendly view (for the metadata)."""
        out = dataclasses.asdict(self)
        out["net_arch"] = list(self.net_arch)
        return out


def default_dagger_config() -> Path:
    """The packaged DAgger file, ``training/configs/dagger.yaml``."""
    return Path(str(resources.files("bioscara_gym.training") / "configs" / CONFIG_NAME))


def has_dagger_default(env_id: str) -> bool:
    """Whether the packaged DAgger file has an entry for ``env_id`` (its default method)."""
    try:
        data = yaml.safe_load(default_dagger_config().read_text(encoding="utf-8"))
    except (OSError, yaml.YAMLError):
        return False
    return isinstance(data, dict) and env_id in data


def uses_dagger(args: TrainArgs, env_id: str) -> bool:
    """Whether ``bioscara train`` runs DAgger: ``--algo dagger``, or ``env_id``'s default.

    An env with an entry in the packaged DAgger file (PickPlace) trains with
    DAgger unless an algorithm (``--algo sac`` included) or a ``--config`` is
    given. ``--resume`` continues whatever the run in ``--out`` is.
    """
    if args.algo == "dagger":
        return True
    if args.resume and args.algo is None:
        try:
            state = json.loads((Path(args.out) / STATE_NAME).read_text(encoding="utf-8"))
        except (OSError, ValueError):
            return False  # train.py says what is wrong with the run
        return isinstance(state, dict) and state.get("algo") == "dagger"
    return args.algo is None and args.config is None and has_dagger_default(env_id)


def load_dagger_config(path: Path, env_id: str) -> DaggerConfig:
    """``env_id``'s entry of DAgger file ``path``.

    Raises:
        HyperparamError: Unreadable, not YAML, no entry, an unknown key (with
            the closest known one), or a bad value.
    """
    try:
        data = yaml.safe_load(Path(path).read_text(encoding="utf-8"))
    except OSError as e:
        raise HyperparamError(f"cannot read config {path}: {e.strerror or e}") from e
    except yaml.YAMLError as e:
        raise HyperparamError(f"config {path} is not valid YAML: {e}") from e
    if not isinstance(data, dict) or not isinstance(data.get(env_id), dict):
        known = ", ".join(data) if isinstance(data, dict) else "none"
        raise HyperparamError(f"config {path} has no DAgger entry for {env_id}; entries: {known}")
    entry = dict(data[env_id])
    names = [f.name for f in dataclasses.fields(DaggerConfig) if f.name != "source"]
    for key in entry:
        if key not in names:
            close = difflib.get_close_matches(key, names, n=1)
            hint = f"; did you mean {close[0]!r}?" if close else f"; known keys: {', '.join(names)}"
            raise HyperparamError(f"config {path}: {env_id}.{key} is not a DAgger setting{hint}")
    for key in ("env_kwargs", "features"):
        if not isinstance(entry.get(key, {}), dict):
            raise HyperparamError(f"config {path}: {env_id}.{key} must be a mapping")
    if "net_arch" in entry:
        if not isinstance(entry["net_arch"], list):
            raise HyperparamError(f"config {path}: {env_id}.net_arch must be a list of layer widths")
        entry["net_arch"] = tuple(entry["net_arch"])
    for key in ("n_timesteps",):  # YAML writes 3e5 as a float
        value = entry.get(key)
        if isinstance(value, float) and value.is_integer():
            entry[key] = int(value)
    return DaggerConfig(source=str(path), **entry)


# ------------------------------------------------------------------ training
#: Seeds of the expert's episodes and of the learner's, relative to the run's seed.
DEMO_SEED = 1_000_000
ROLLOUT_SEED = 2_000_000
#: Mixture shares below this count as the learner alone (its rollouts then serve as a quick evaluation).
BETA_NEGLIGIBLE = 0.05
CHECKPOINT_DATA = "_dagger.npz"


def expert_labeller(env: gym.Env) -> ObservationExpert:
    """The expert that labels any state of ``env``.

    Raises:
        TrainingError: The task has no observation-only expert (only PickPlace has one).
    """
    if not isinstance(env.unwrapped, BioscaraPickPlaceEnv):
        raise TrainingError(
            f"DAgger needs an expert that can label any state; {env.spec.id if env.spec else env} has none "
            "(train it with --algo sac)"
        )
    return ObservationExpert(env.unwrapped)


def build_learner(env: gym.Env, cfg: DaggerConfig, seed: int) -> Any:
    """A SAC model (``buffer_size`` 1) whose actor DAgger trains; ``eval``, ``export``, ``deploy`` load it."""
    policy_kwargs = {
        "net_arch": list(cfg.net_arch),
        "features_extractor_class": PickPlaceExtractor,
        "features_extractor_kwargs": dict(cfg.features),
    }
    try:
        return SAC(
            "MultiInputPolicy", env, buffer_size=1, seed=seed, device="cpu", policy_kwargs=policy_kwargs
        )
    except (TypeError, ValueError) as e:
        raise TrainingError(f"config {cfg.source}: {e}") from e


def save_checkpoint(model: Any, data: Labelled, iteration: int, env_steps: int, directory: Path) -> Path:
    """Model and aggregate as ``ckpt_<env steps>_steps.zip`` and ``…_dagger.npz``, data first, atomically."""
    directory.mkdir(parents=True, exist_ok=True)
    path = directory / f"ckpt_{env_steps}_steps.zip"
    buffer = io.BytesIO()
    np.savez(
        buffer,
        actions=data.actions,
        row_iteration=data.iteration,
        iteration=iteration,
        env_steps=env_steps,
        **{f"obs_{k}": data.obs[k] for k in GOAL_KEYS},
    )
    atomic_write_bytes(data_path(path), buffer.getvalue())
    buffer = io.BytesIO()
    model.save(buffer)
    atomic_write_bytes(path, buffer.getvalue())
    return path


def data_path(checkpoint: Path) -> Path:
    """The aggregate saved with ``checkpoint``."""
    return checkpoint.with_name(checkpoint.stem + CHECKPOINT_DATA)


def load_checkpoint(directory: Path, env: gym.Env) -> tuple[Any, Labelled, int, int]:
    """The newest checkpoint whose model and aggregate both load: model, aggregate, iteration, env steps.

    Raises:
        TrainingError: None does.
    """
    found = sorted(
        (
            (int(m.group(1)), p)
            for p in directory.glob("ckpt_*_steps.zip")
            if (m := CHECKPOINT_RE.search(p.name))
        ),
        reverse=True,
    )
    errors = []
    for _, path in found:
        try:
            with np.load(data_path(path)) as z:
                data = Labelled(
                    obs={k: z[f"obs_{k}"] for k in GOAL_KEYS},
                    actions=z["actions"],
                    iteration=z["row_iteration"],
                )
                iteration, env_steps = int(z["iteration"]), int(z["env_steps"])
            model = SAC.load(path, env=env, device="cpu")
        except (OSError, EOFError, ValueError, KeyError, RuntimeError, zipfile.BadZipFile) as e:
            errors.append(f"{path.name}: {type(e).__name__}: {e}")
            continue
        return model, data, iteration, env_steps
    detail = f" ({'; '.join(errors)})" if errors else ""
    raise TrainingError(f"nothing to resume in {directory}: no DAgger checkpoint that loads{detail}")


def _read_state(out: Path) -> dict[str, Any]:
    """The run's ``train_state.json``, checked to be a DAgger run."""
    path = out / STATE_NAME
    try:
        state = json.loads(path.read_text(encoding="utf-8"))
    except (OSError, json.JSONDecodeError) as e:
        raise TrainingError(f"nothing to resume in {out}: {path} is missing or not JSON ({e})") from e
    if not isinstance(state, dict) or state.get("algo") != "dagger" or not isinstance(state.get("seed"), int):
        raise TrainingError(f"{path} does not describe a DAgger run")
    return state


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


def train_dagger(args: TrainArgs, env_id: str) -> TrainResult:
    """``bioscara train`` with DAgger (see the module docstring): clone, roll out, label, aggregate, repeat.

    ``--timesteps`` is the budget in env steps, the expert's episodes
    included; ``--demos NAME`` replaces the expert's own episodes by a
    dataset's. A checkpoint (model and aggregate) is written after every
    iteration; ``--resume`` continues from the newest. Training stops once
    the learner's own rollouts reach the target and a full evaluation
    (``eval_episodes`` seeded episodes) confirms it.

    Raises:
        TrainingError: Bad input (nothing written).
        TrainingInterrupted: SIGINT or SIGTERM (a checkpoint saved).
    """
    out = Path(args.out)
    if args.resume:
        state = _read_state(out)
        if state.get("env_id") != env_id:
            raise TrainingError(f"{out} holds a DAgger run on {state.get('env_id')}, not {env_id}")
        args.seed = state["seed"]
        args.demos = args.demos or state.get("demos")
        config = Path(state["config"]) if state.get("config") else default_dagger_config()
        budget = int(state["total_timesteps"])
        if args.timesteps is not None and args.timesteps != budget:
            raise TrainingError(f"--timesteps {args.timesteps}: the run in {out} has a budget of {budget}")
    else:
        config = Path(args.config) if args.config else default_dagger_config()
    try:
        cfg = load_dagger_config(config, env_id)
    except HyperparamError as e:
        raise TrainingError(str(e)) from e
    if not args.resume:
        budget = int(args.timesteps or cfg.n_timesteps)
    if budget < 1:
        raise TrainingError(f"--timesteps {budget}: must be >= 1")
    th.set_num_threads(args.threads or 1)
    start = time.perf_counter()
    with (
        SignalGuard() as guard,
        contextlib.closing(gym.make(env_id, **cfg.env_kwargs)) as env,
        contextlib.closing(gym.make(env_id, **cfg.env_kwargs)) as eval_env,
    ):
        expert = expert_labeller(env)
        demos = None
        if args.demos:
            demos = load_demos(args.demos)
            check_demos(demos, env)
        if args.resume:
            model, data, iteration, env_steps = load_checkpoint(out / "checkpoints", env)
        else:
            model, data, iteration, env_steps = build_learner(env, cfg, args.seed), None, 0, 0
        out.mkdir(parents=True, exist_ok=True)
        state = {"env_id": env_id, "algo": "dagger", "seed": args.seed, "total_timesteps": budget}
        state.update(config=str(args.config) if args.config else None, demos=args.demos)
        atomic_write_text(out / STATE_NAME, json.dumps(state, indent=2))
        logger = configure_logger(str(out / "tb" / "dagger"), ["tensorboard"])
        progress = _Progress(budget, args.progress, env_steps)
        run = _Run(args, cfg, env, eval_env, expert, model, logger, progress, start)
        try:
            if data is None:
                data, env_steps = run.first_iteration(demos)
                save_checkpoint(model, data, 0, env_steps, out / "checkpoints")
            final = None
            while env_steps < budget:
                data, env_steps, final = run.iteration(iteration + 1, data, env_steps)
                iteration += 1  # only once done: an interrupted iteration is run again on --resume
                if final is not None:
                    break
                with guard.shielded():
                    save_checkpoint(model, data, iteration, env_steps, out / "checkpoints")
            if final is None:
                final = run.evaluate(env_steps)
        except KeyboardInterrupt as e:
            with guard.shielded():
                ckpt = (
                    save_checkpoint(model, data, iteration, env_steps, out / "checkpoints") if data else None
                )
            progress.close()
            signum = e.signum if isinstance(e, Interrupted) else signal.SIGINT
            raise TrainingInterrupted(signum, ckpt, out) from None
        progress.close()
        with guard.shielded():
            model_path, metadata_path = save_policy(
                model,
                out,
                build_metadata(
                    env,
                    env_id,
                    cfg.env_kwargs,
                    algo="bc",  # a SAC model whose actor was cloned: loads as --algo bc's
                    method="dagger",
                    seed=args.seed,
                    timesteps=env_steps,
                    dagger={
                        "iterations": iteration,
                        "labelled_states": len(data),
                        "demos": args.demos,
                        "wall_time_s": round(time.perf_counter() - start, 1),
                    },
                    config=cfg.as_dict(),
                    final_eval=final.as_dict(),
                ),
            )
    logger.close()
    return TrainResult(
        model_path=model_path,
        metadata_path=metadata_path,
        timesteps=env_steps,
        wall_time_s=time.perf_counter() - start,
        final_eval=final,
        target_reached_at=run.reached_at,
        target_reached_after_s=run.reached_after_s,
    )


@dataclass
class _Run:
    """The steps of one DAgger run, sharing its envs, model and logger."""

    args: TrainArgs
    cfg: DaggerConfig
    env: gym.Env
    eval_env: gym.Env
    expert: ObservationExpert
    model: Any
    logger: Any
    progress: _Progress
    start: float
    reached_at: int | None = None
    reached_after_s: float | None = None

    def _say(self, text: str) -> None:
        if self.args.verbose:
            self.progress.bar.write(text) if self.args.progress else print(text, flush=True)

    def _rollouts(self, act: Policy, episodes: int, seed: int, iteration: int, beta: float) -> Rollouts:
        def on_episode(success: bool, steps: int) -> None:
            self.progress.episode(steps, iteration=str(iteration))

        rng = np.random.default_rng([self.args.seed, iteration])
        return label_episodes(self.env, act, self.expert, episodes, seed, iteration, beta, rng, on_episode)

    def _fit(self, data: Labelled, steps: int, iteration: int) -> float:
        cfg = self.cfg
        seed = self.args.seed * 1000 + iteration
        return fit_actor(
            self.model, data.obs, data.actions, steps, cfg.batch_size, cfg.learning_rate, seed=seed
        )

    def first_iteration(self, demos: Demos | None) -> tuple[Labelled, int]:
        """Iteration 0: the expert's episodes (or the dataset's), cloned."""
        if demos is None:
            seed = DEMO_SEED + 10_000 * self.args.seed
            r = self._rollouts(self.expert, self.cfg.demo_episodes, seed, 0, 1.0)
            data, steps, source = (
                r.data,
                len(r.data),
                f"{r.episodes} expert episodes ({r.success_rate:.0%} success)",
            )
        else:
            data, steps, source = Labelled.from_demos(demos), 0, f"dataset {demos.dataset_id}"
        loss = self._fit(data, self.cfg.bc_steps_first, 0)
        self._log(0, steps, data, loss, None, 1.0)
        self._say(f"[dagger] iteration 0: cloned {len(data)} states of {source}, loss {loss:.4f}")
        return data, steps

    def iteration(self, i: int, data: Labelled, env_steps: int) -> tuple[Labelled, int, EvalStats | None]:
        """Roll out the learner (mixed with the expert); stop if it is good enough, else aggregate, refit."""
        beta = self.cfg.beta**i
        seed = ROLLOUT_SEED + 10_000 * self.args.seed + (i - 1) * self.cfg.episodes_per_iteration
        r = self._rollouts(sb3_policy(self.model), self.cfg.episodes_per_iteration, seed, i, beta)
        env_steps += len(r.data)
        mixed = f" (expert {beta:.0%})" if beta else ""
        elapsed = time.perf_counter() - self.start
        self._say(
            f"[dagger] iteration {i}: learner{mixed} {r.success_rate:.0%} success over "
            f"{r.episodes} episodes, {elapsed:.0f} s"
        )
        if beta < BETA_NEGLIGIBLE and r.success_rate >= self.cfg.target_success:
            final = self.evaluate(env_steps)
            if final.success_rate >= self.cfg.target_success:
                self.reached_at, self.reached_after_s = env_steps, time.perf_counter() - self.start
                self._say(f"[dagger] target reached after {env_steps} steps, {self.reached_after_s:.0f} s")
                return data, env_steps, final
        data = data + r.data
        loss = self._fit(data, self.cfg.bc_steps, i)
        self._log(i, env_steps, data, loss, r.success_rate, beta)
        return data, env_steps, None

    def evaluate(self, env_steps: int) -> EvalStats:
        """Success over ``eval_episodes`` seeded episodes (seeds from the run's seed + 10000)."""
        stats = run_episodes(
            self.eval_env,
            sb3_policy(self.model),
            self.cfg.eval_episodes,
            seed=self.args.seed + EVAL_SEED_OFFSET,
        )
        elapsed = time.perf_counter() - self.start
        self.logger.record("eval/success_rate", stats.success_rate)
        self.logger.record("eval/mean_final_distance", stats.mean_final_distance)
        self.logger.dump(env_steps)
        self._say(
            f"[eval] step {env_steps:>7}  {elapsed:.0f} s  success {stats.success_rate * 100:.1f}% "
            f"over {stats.episodes}"
        )
        return stats

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
