"""Feature extractors for goal-conditioned policies.

A policy for a goal task has to act on the goal error ``desired - achieved``.
Fed the two goals side by side in metres, a network must first learn weights
large enough to resolve a centimetre out of a workspace of a metre; that alone
took most of a 5-minute training budget on Bioscara-Reach.
:class:`GoalErrorExtractor` hands it the error directly, in units of ``scale``.
It is computed inside the network from whatever goals the batch holds, so it
stays right when HER relabels ``desired_goal`` (a goal-relative entry in the
env's ``observation`` would not).

By default the absolute goals are left out: the error and the observation
(which holds the arm's joints, so where the goals are) determine the action,
and every extra input is one more source of small, spurious action changes
near the goal, where Reach's 1 cm success radius is decided. Measured with
SAC+HER on Reach (100 episodes): 90 % success at 15k steps without them,
78-84 % with them.

:class:`PickPlaceExtractor` is the DAgger learner's on PickPlace (the task
names it in :data:`bioscara_gym.tasks.TASKS`): lengths in 10 cm, and
block-from-TCP and the goal error also in 5 mm, where the phases are decided.
:class:`PushExtractor` adds the push's frame (the TCP behind and beside the
block on its line to the target, the pushing face's turn) and
:class:`StackExtractor` both blocks' views, and the view of the block being
worked on (which one, where it goes, the wrist's turn to it).
:class:`InsertExtractor` is Insert's: lengths in 10 cm, and the alignment
also in millimetres and hundredths of a radian. All read the observation by
name, from the task's layout.
"""

from __future__ import annotations

import math
from collections.abc import Mapping, Sequence

from gymnasium import spaces

from bioscara_gym.tasks import GOAL_KEYS, load_entry_point, task
from bioscara_gym.training.extras import needs_train

with needs_train():
    import torch as th
    from stable_baselines3.common.torch_layers import BaseFeaturesExtractor


class GoalErrorExtractor(BaseFeaturesExtractor):
    """``observation`` and ``(desired - achieved) / scale`` (and both goals, if asked).

    Args:
        observation_space: A goal env's ``Dict`` space with flat ``Box`` entries
            ``observation``, ``achieved_goal`` and ``desired_goal``.
        scale: Length (in goal units, m for Bioscara) that maps to 1.0.
        include_goals: Also pass ``achieved_goal`` and ``desired_goal`` through.

    Raises:
        ValueError: The space lacks a key, an entry is not flat, the goals'
            shapes differ, or ``scale`` is not positive.
    """

    def __init__(
        self, observation_space: spaces.Dict, scale: float = 0.01, include_goals: bool = False
    ) -> None:
        """Check the space and size the features."""
        if not isinstance(observation_space, spaces.Dict):
            raise ValueError(f"GoalErrorExtractor needs a Dict observation space, got {observation_space}")
        missing = [k for k in GOAL_KEYS if k not in observation_space.spaces]
        if missing:
            raise ValueError(f"GoalErrorExtractor: observation space lacks {', '.join(missing)}")
        shapes = {k: observation_space[k].shape for k in GOAL_KEYS}
        if any(shape is None or len(shape) != 1 for shape in shapes.values()):
            raise ValueError(f"GoalErrorExtractor needs flat entries, got shapes {shapes}")
        if shapes["achieved_goal"] != shapes["desired_goal"]:
            raise ValueError(
                f"GoalErrorExtractor: achieved_goal {shapes['achieved_goal']} and "
                f"desired_goal {shapes['desired_goal']} differ in shape"
            )
        if not scale > 0:
            raise ValueError(f"GoalErrorExtractor: scale {scale} must be > 0")
        n_obs, n_goal = shapes["observation"][0], shapes["desired_goal"][0]
        super().__init__(observation_space, features_dim=n_obs + (3 if include_goals else 1) * n_goal)
        self.scale = float(scale)
        self.include_goals = bool(include_goals)

    def forward(self, observations: dict[str, th.Tensor]) -> th.Tensor:
        """Features of a batch of dict observations."""
        achieved, desired = observations["achieved_goal"], observations["desired_goal"]
        error = (desired - achieved) / self.scale
        if self.include_goals:
            return th.cat((observations["observation"], achieved, desired, error), dim=1)
        return th.cat((observations["observation"], error), dim=1)


#: Entries of PickPlace's ``observation`` given in m (or m/s), scaled by ``coarse_m``.
LENGTH_SLICES = ("tcp", "block_pos", "block_from_tcp", "block_vel")


def task_layout(owner: str, env_id: str, observation_space: spaces.Space) -> tuple[Mapping[str, slice], int]:
    """``env_id``'s observation slices and length, once ``observation_space`` is shown to be that task's.

    Raises:
        ValueError: Not a goal env's ``Dict`` space, or an observation of
            another length; the message starts with ``owner``.
    """
    slices = task(env_id).obs_slices()
    n_obs = max(s.stop for s in slices.values())
    if not isinstance(observation_space, spaces.Dict) or any(
        k not in observation_space.spaces for k in GOAL_KEYS
    ):
        raise ValueError(f"{owner} needs a goal env's Dict space, got {observation_space}")
    if observation_space["observation"].shape != (n_obs,):
        raise ValueError(
            f"{owner}: observation has shape {observation_space['observation'].shape}, "
            f"{env_id}'s is ({n_obs},)"
        )
    return slices, n_obs


class PickPlaceExtractor(BaseFeaturesExtractor):
    """PickPlace's observation with every length in ``coarse_m``, plus a fine view of the two errors.

    Features, in order: ``observation`` with the entries of
    :data:`LENGTH_SLICES` divided by ``coarse_m`` (the rest is already in
    [-1, 1] or rad); the goal error ``desired - achieved`` over ``coarse_m``;
    then block-from-TCP and the goal error over ``fine_m``, clipped to
    ``+-fine_clip``. The phases turn on millimetres (the gripper descends
    within 3 mm of the block), which a network sees in metres only as tiny
    inputs; the whole workspace in ``fine_m`` would be inputs of 50.

    Given ``joint_range`` (the env's: the trainer passes it, ``FROM_ENV``),
    one feature more: the wrist's turn that squares the fingers to the block
    (``TURN_YAW``), the least of the four quarter turns, over pi/4. The
    joints are read back in rad from ``joint_pos``. A network given only the
    raw yaws has to find the quarter-turn wrap itself, and fits the wrist
    worst of all the actions. Models saved without ``joint_range`` load as
    they were trained, without it.

    Args:
        observation_space: Bioscara-PickPlace's ``Dict`` space.
        coarse_m: Length that maps to 1.0 in the coarse view.
        fine_m: Length that maps to 1.0 in the fine view.
        fine_clip: Bound of the fine view.
        joint_range: ``[min, max]`` of each joint (the env's ``joint_range``), or
            ``None``: no wrist feature.

    Raises:
        ValueError: Not PickPlace's observation space, a scale not positive,
            or ``joint_range`` not four ``[min, max]`` pairs.
    """

    #: The task whose observation layout (``OBS_SLICES``) the features are read from.
    TASK = "Bioscara-PickPlace-v1"
    #: Its entries in m (or m/s), scaled by ``coarse_m``.
    LENGTHS: tuple[str, ...] = LENGTH_SLICES
    #: Its entries also seen in ``fine_m``, before the goal error.
    FINE: tuple[str, ...] = ("block_from_tcp",)
    #: The yaw (an ``OBS_SLICES`` name) the wrist's turn squares the fingers to, or ``None``.
    TURN_YAW: str | None = "block_yaw"
    #: Arguments the trainer reads off the env (its public properties of these names).
    FROM_ENV: tuple[str, ...] = ("joint_range",)

    def __init__(
        self,
        observation_space: spaces.Dict,
        coarse_m: float = 0.1,
        fine_m: float = 0.005,
        fine_clip: float = 3.0,
        joint_range: Sequence[Sequence[float]] | None = None,
    ) -> None:
        """Check the space and build the scale vector."""
        name = type(self).__name__
        slices, n_obs = task_layout(name, self.TASK, observation_space)
        if not (coarse_m > 0 and fine_m > 0 and fine_clip > 0):
            raise ValueError(f"{name}: scales {coarse_m}, {fine_m}, {fine_clip} must be > 0")
        n_goal = observation_space["desired_goal"].shape[0]
        self._fine = [slices[name] for name in self.FINE]
        n_fine = sum(s.stop - s.start for s in self._fine)
        super().__init__(observation_space, features_dim=n_obs + 2 * n_goal + n_fine)
        scale = th.ones(n_obs)
        for name in self.LENGTHS:
            scale[slices[name]] = 1.0 / coarse_m
        self.register_buffer("scale", scale)
        self.coarse_m, self.fine_m, self.fine_clip = float(coarse_m), float(fine_m), float(fine_clip)
        self._joint_pos = slices["joint_pos"]
        self._turn_yaw: slice | None = None
        if joint_range is not None:
            lo_hi = th.as_tensor(joint_range, dtype=th.float32)
            if lo_hi.shape != (4, 2) or not bool((lo_hi[:, 1] > lo_hi[:, 0]).all()):
                raise ValueError(f"{name}: joint_range {joint_range} must be 4 [min, max] pairs")
            self.register_buffer("q_lo", lo_hi[:, 0].clone())
            self.register_buffer("q_span", lo_hi[:, 1] - lo_hi[:, 0])
            if self.TURN_YAW is not None:
                self._turn_yaw = slices[self.TURN_YAW]
                self._features_dim += 1

    def forward(self, observations: dict[str, th.Tensor]) -> th.Tensor:
        """Features of a batch of dict observations."""
        o = observations["observation"]
        error = observations["desired_goal"] - observations["achieved_goal"]
        fine = th.cat([o[:, part] for part in self._fine] + [error], dim=1) / self.fine_m
        parts = [o * self.scale, error / self.coarse_m, th.clamp(fine, -self.fine_clip, self.fine_clip)]
        if self._turn_yaw is not None:
            parts.append(self._turn(o, o[:, self._turn_yaw]))
        return th.cat(parts, dim=1)

    def _turn(self, o: th.Tensor, yaw: th.Tensor) -> th.Tensor:
        """The wrist's turn (over pi/4) that squares the fingers to a block at ``yaw``: the least of four."""
        q = self.q_lo + (o[:, self._joint_pos] + 1.0) / 2.0 * self.q_span
        tool = (q[:, 0] + q[:, 2] + q[:, 3]).unsqueeze(1)
        quarter = math.pi / 2
        return (th.remainder(yaw - tool - quarter + quarter / 2, quarter) - quarter / 2) / (quarter / 2)


class PushExtractor(PickPlaceExtractor):
    """PickPlace's features of Push's observation, plus the geometry of the push.

    Pushing is decided in the frame of the push, ``u`` from the block to the
    target and ``v`` to its left: how far behind the block the TCP is (``s``)
    and how far off the line (``t``), and how far the pushing face is turned
    from ``u``. On raw coordinates a network has to rotate the workspace
    into that frame itself. Added after PickPlace's features: ``u``, the
    block's distance to the target, ``s`` and ``t`` over ``coarse_m`` and over
    ``fine_m`` (clipped to ``+-fine_clip``), and the cosine and sine of twice
    the face's turn from ``u`` (the face pushes either way round).
    """

    TASK = "Bioscara-Push-v0"
    #: The pushing face is turned by the push's own features, not squared to the block.
    TURN_YAW = None
    FROM_ENV = ()
    #: Features added to PickPlace's.
    N_PUSH = 9

    def __init__(
        self,
        observation_space: spaces.Dict,
        coarse_m: float = 0.1,
        fine_m: float = 0.005,
        fine_clip: float = 3.0,
    ) -> None:
        """PickPlace's checks and scales, and the slices of the push's geometry."""
        super().__init__(observation_space, coarse_m, fine_m, fine_clip)
        slices = task(self.TASK).obs_slices()
        self._tcp, self._tool = slices["tcp"], slices["tool_dir"]
        self._features_dim += self.N_PUSH

    def forward(self, observations: dict[str, th.Tensor]) -> th.Tensor:
        """PickPlace's features and the push's geometry."""
        o = observations["observation"]
        block, goal = observations["achieved_goal"][:, :2], observations["desired_goal"][:, :2]
        error = goal - block
        dist = th.linalg.vector_norm(error, dim=1, keepdim=True)
        u = error / th.clamp(dist, min=1e-6)
        v = th.stack((-u[:, 1], u[:, 0]), dim=1)
        rel = o[:, self._tcp][:, :2] - block
        st = th.stack(((rel * u).sum(dim=1), (rel * v).sum(dim=1)), dim=1)
        c, s = o[:, self._tool][:, 0], o[:, self._tool][:, 1]
        cos_turn, sin_turn = c * u[:, 0] + s * u[:, 1], s * u[:, 0] - c * u[:, 1]
        double = th.stack((cos_turn**2 - sin_turn**2, 2 * cos_turn * sin_turn), dim=1)
        push = th.cat(
            (
                u,
                dist / self.coarse_m,
                st / self.coarse_m,
                th.clamp(st / self.fine_m, -self.fine_clip, self.fine_clip),
                double,
            ),
            dim=1,
        )
        return th.cat((super().forward(observations), push), dim=1)


class StackExtractor(PickPlaceExtractor):
    """PickPlace's features of Stack's observation, plus a view of the block being worked on.

    Features, in order: ``observation`` with every length over ``coarse_m``;
    the goal error (both blocks, 6 values) over ``coarse_m``; then each
    block's position from the TCP and the goal error over ``fine_m``, clipped
    to ``+-fine_clip``. Then the active block's view, as the observation
    expert (:class:`~bioscara_gym.experts.StackExpert`) decides it:

    - 1 once the lower block is in place (the expert's own test,
      ``PLACED_M`` and ``PLACED_Z``), else 0; 1 once the upper one is too;
    - the active block from the TCP and from where it goes (the lower one:
      the target; the upper one: a block height over the lower one,
      wherever that is), over ``coarse_m`` and over ``fine_m`` (clipped);
    - its yaw (rad), and the wrist's turn that squares the fingers to it,
      the least of the four (over pi/4, so in [-1, 1)); the joints are read
      back in rad from ``joint_pos`` with ``joint_range``, the env's
      (``FROM_ENV``: the trainer passes it).

    Without the view the network has to find the switch between the blocks
    and the wrist's quarter-turn wrap itself: seed 0, 120k steps, 12 %
    success over 100 episodes (learners froze beside the block they were
    to fetch or lower); with the switch and the active block 55 %; with
    the second switch 59 %; with the yaw 68 %; with the wrist's turn 87 %
    (the wrist's share of the squared error on the learner's own states
    fell from 10.9e-3 to 1.9e-3).

    Raises:
        ValueError: As PickPlace's, or ``joint_range`` missing (Stack's features need it).
    """

    TASK = "Bioscara-Stack-v0"
    LENGTHS = (
        "tcp",
        "lower_pos",
        "lower_from_tcp",
        "lower_vel",
        "upper_pos",
        "upper_from_tcp",
        "upper_vel",
    )
    FINE = ("lower_from_tcp", "upper_from_tcp")
    #: Features added to PickPlace's: the two switches, two 3-vectors twice, the active
    #: block's yaw and the wrist's turn to it.
    N_ACTIVE = 16
    #: The wrist's turn is the active block's, added with the rest of its view.
    TURN_YAW = None

    def __init__(
        self,
        observation_space: spaces.Dict,
        coarse_m: float = 0.1,
        fine_m: float = 0.005,
        fine_clip: float = 3.0,
        joint_range: Sequence[Sequence[float]] | None = None,
    ) -> None:
        """PickPlace's checks and scales, the slices of both blocks and the expert's placing test."""
        if joint_range is None:
            raise ValueError(f"{type(self).__name__}: joint_range is needed (the env's joint_range)")
        super().__init__(observation_space, coarse_m, fine_m, fine_clip, joint_range)
        spec = task(self.TASK)
        slices = spec.obs_slices()
        self._lower, self._lower_tcp = slices["lower_pos"], slices["lower_from_tcp"]
        self._upper, self._upper_tcp = slices["upper_pos"], slices["upper_from_tcp"]
        self._yaws = (slices["lower_yaw"], slices["upper_yaw"])
        expert = load_entry_point(spec.observation_expert)
        self.placed_m, self.placed_z = float(expert.PLACED_M), float(expert.PLACED_Z)
        self._features_dim += self.N_ACTIVE

    def forward(self, observations: dict[str, th.Tensor]) -> th.Tensor:
        """PickPlace's features and the active block's view."""
        o, goal = observations["observation"], observations["desired_goal"]
        lower, upper = o[:, self._lower], o[:, self._upper]
        target, on_target = goal[:, :3], goal[:, 3:6]
        off = target - lower
        on_lower = lower + (on_target - target) - upper
        p = self._placed(off).unsqueeze(1)
        done = p * self._placed(on_lower).unsqueeze(1)
        from_tcp = p * o[:, self._upper_tcp] + (1 - p) * o[:, self._lower_tcp]
        error = p * on_lower + (1 - p) * off
        view = th.cat((from_tcp, error), dim=1)
        fine = th.clamp(view / self.fine_m, -self.fine_clip, self.fine_clip)
        yaw = p * o[:, self._yaws[1]] + (1 - p) * o[:, self._yaws[0]]
        return th.cat(
            (super().forward(observations), p, done, view / self.coarse_m, fine, yaw, self._turn(o, yaw)),
            dim=1,
        )

    def _placed(self, off: th.Tensor) -> th.Tensor:
        """1.0 where a block ``off`` from its place (m, ``(n, 3)``) counts as there, else 0.0."""
        near = th.linalg.vector_norm(off[:, :2], dim=1) < self.placed_m
        return (near & (off[:, 2].abs() < self.placed_z)).to(off.dtype)


#: Entries of Insert's ``observation`` given in m, scaled by ``coarse_m``.
INSERT_LENGTH_SLICES = ("tcp", "peg_tip", "goal_from_tip", "above_top")


class InsertExtractor(BaseFeaturesExtractor):
    """Insert's observation with every length in ``coarse_m``, plus a fine view of the alignment.

    Features, in order: ``observation`` with the entries of
    :data:`INSERT_LENGTH_SLICES` divided by ``coarse_m`` (the rest is in
    [-1, 1] or rad); the goal error ``desired - achieved`` over ``coarse_m``;
    then its x and y and the tip's height above the fixture's top over
    ``fine_m``, and the wrist turn over ``fine_rad``, clipped to
    ``+-fine_clip``. The peg goes in only within 0.5 mm and about 3
    degrees, and the expert lowers it at 0.25 mm and 0.86 degrees: in metres
    and radians those are inputs of 1e-4 to 1e-2.

    Args:
        observation_space: Bioscara-Insert's ``Dict`` space.
        coarse_m: Length that maps to 1.0 in the coarse view.
        fine_m: Length that maps to 1.0 in the fine view.
        fine_rad: Angle that maps to 1.0 in the fine view.
        fine_clip: Bound of the fine view.

    Raises:
        ValueError: Not Insert's observation space, or a scale not positive.
    """

    #: The task whose observation layout (``OBS_SLICES``) the features are read from.
    TASK = "Bioscara-Insert-v0"

    def __init__(
        self,
        observation_space: spaces.Dict,
        coarse_m: float = 0.1,
        fine_m: float = 0.001,
        fine_rad: float = 0.01,
        fine_clip: float = 3.0,
    ) -> None:
        """Check the space and build the scale vectors."""
        slices, n_obs = task_layout("InsertExtractor", self.TASK, observation_space)
        if not (coarse_m > 0 and fine_m > 0 and fine_rad > 0 and fine_clip > 0):
            raise ValueError(
                f"InsertExtractor: scales {coarse_m}, {fine_m}, {fine_rad}, {fine_clip} must be > 0"
            )
        n_goal = observation_space["desired_goal"].shape[0]
        super().__init__(observation_space, features_dim=n_obs + n_goal + 4)
        scale = th.ones(n_obs)
        for name in INSERT_LENGTH_SLICES:
            scale[slices[name]] = 1.0 / coarse_m
        self.register_buffer("scale", scale)
        xy = slices["goal_from_tip"]
        self._fine = [xy.start, xy.start + 1, slices["above_top"].start, slices["wrist_turn"].start]
        self.register_buffer("fine_scale", th.tensor([1.0 / fine_m] * 3 + [1.0 / fine_rad]))
        self.coarse_m, self.fine_clip = float(coarse_m), float(fine_clip)

    def forward(self, observations: dict[str, th.Tensor]) -> th.Tensor:
        """Features of a batch of dict observations."""
        o = observations["observation"]
        error = observations["desired_goal"] - observations["achieved_goal"]
        fine = th.clamp(o[:, self._fine] * self.fine_scale, -self.fine_clip, self.fine_clip)
        return th.cat((o * self.scale, error / self.coarse_m, fine), dim=1)
