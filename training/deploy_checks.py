"""What ``bioscara deploy`` checks before a byte reaches the arm: its arguments, its outputs, its policy.

Every argument is checked (:func:`check_args`; the files it writes by
:func:`~bioscara_gym.training.deploy_outputs.check_files`), the
policy loaded (:func:`load_policy`: the one ``--model``, ``--onnx`` or
``--expert`` names), its env's keyword arguments checked against the env's
constructor (:func:`check_env_kwargs`) and the policy run once on a probe
observation (:func:`probe_policy`). A refusal is one
:class:`~bioscara_gym.errors.DeployError` line; nothing has been sent.
"""

from __future__ import annotations

import dataclasses
from collections.abc import Callable
from dataclasses import dataclass
from pathlib import Path
from typing import Any

import gymnasium as gym
import numpy as np

import bioscara_gym
from bioscara_gym.errors import DeployError, TrainingError
from bioscara_gym.hardware.arm import check_control_freq
from bioscara_gym.hardware.config import load_config
from bioscara_gym.hardware.emulated_bus import FaultPlan
from bioscara_gym.hardware.errors import SitlError
from bioscara_gym.hardware.registry import backend_names
from bioscara_gym.tasks import Policy, task_of
from bioscara_gym.training.deploy_outputs import check_files, check_outputs
from bioscara_gym.training.extras import needed_by
from bioscara_gym.training.metadata import PolicyShapes, env_kwargs_problem, read_metadata, resolve_env_id

__all__ = [
    "DEPLOY_BACKENDS",
    "DeployArgs",
    "LoadedPolicy",
    "Policy",
    "backend_options",
    "check_args",
    "check_env_kwargs",
    "check_files",
    "check_input_order",
    "check_outputs",
    "load_policy",
    "make_env",
    "probe_policy",
]

#: Backends deploy drives, as the registry says (``sim`` has no bus: use ``bioscara eval``);
#: ``sitl`` runs the firmware's own source behind the emulated bus (``--firmware DIR``).
DEPLOY_BACKENDS = backend_names("deployable")


@dataclass
class DeployArgs:
    """Arguments of ``bioscara deploy`` (the CLI flags map one to one).

    Attributes:
        model: A trained ``model.zip`` (metadata.json beside it).
        onnx: An ONNX policy from ``bioscara export`` (runs without torch).
        expert: Run the scripted expert of ``env`` instead of a policy.
        env: Env id for ``expert``; with a policy, must match its metadata.
        backend: ``i2c`` (the arm), ``emulated`` (real driver, emulated bus), ``sitl``
            (the same with the joint firmware's own source behind the bus) or ``mock``.
        bus: I2C bus number (``/dev/i2c-N``); default the config's.
        config: Arm configuration YAML; default the packaged one.
        episodes: Episodes to run.
        rate: Control rate in Hz; default the policy's. Must match a trained policy's.
        log: Run log (JSON Lines); default ``runs/deploy/deploy-<time>.jsonl``. It
            replaces only an earlier run log or an empty file; missing folders are
            made (:mod:`~bioscara_gym.training.deploy_outputs`, as for the others).
        faults: Fault injection on ``emulated``, e.g. ``nack=0.01,latency_ms=2``.
        seed: Seed of the first episode.
        realtime: On simulated backends, pace the loop on the wall clock too.
        state_file: Gripper state file; default the backend's (on the arm) or
            ``gripper.json`` beside the log (simulated backends). It replaces only
            a gripper state file or an empty file.
        record: Bus trace: every I2C transaction as a JSON line (docs/traces.md);
            a session is added to a trace or an empty file, nothing else.
        firmware: The joint firmware's folder for ``sitl`` (``Arduino/joint/``);
            default ``$BIOSCARA_FIRMWARE``.
    """

    model: Path | None = None
    onnx: Path | None = None
    expert: bool = False
    env: str | None = None
    backend: str = "emulated"
    bus: int | None = None
    config: Path | None = None
    episodes: int = 1
    rate: float | None = None
    log: Path | None = None
    faults: str | None = None
    seed: int = 10_000
    realtime: bool = False
    state_file: Path | None = None
    record: Path | None = None
    firmware: Path | None = None


@dataclass(frozen=True)
class LoadedPolicy:
    """A policy ready to be given its env.

    Attributes:
        make: Builds the policy for the env (the scripted expert needs it).
        metadata: What the policy was trained for (``None`` for the expert).
        description: One line for the operator.
        shapes: What the policy itself takes and gives (``None`` for the expert).
        concatenated: The policy takes the observation as one input, its parts
            concatenated in the order of ``shapes.observation`` (an ONNX graph,
            its ``obs_keys``); else it takes it by key (an SB3 model, the expert).
    """

    make: Callable[[gym.Env], Policy]
    metadata: dict[str, Any] | None
    description: str
    shapes: PolicyShapes | None = None
    concatenated: bool = False


def load_policy(args: DeployArgs) -> LoadedPolicy:
    """Load the policy the arguments name.

    Only ``--model`` imports torch and stable-baselines3, only ``--onnx`` onnxruntime.

    Raises:
        DeployError: No policy source, or more than one; ``--expert`` without ``--env``.
        MetadataError: Missing, incomplete or unreadable metadata.
        PolicyFileError: A ``model.zip`` that cannot be loaded.
        ExportError: An ONNX file that cannot be loaded.
        MissingExtraError: The extra the policy source needs is not installed.
    """
    sources = [s for s in (args.model is not None, args.onnx is not None, args.expert) if s]
    if len(sources) != 1:
        raise DeployError("deploy needs exactly one of --model PATH, --onnx FILE or --expert --env ID")
    if args.expert:
        if args.env is None:
            raise DeployError("--expert needs --env ID: the task is never guessed")
        return LoadedPolicy(lambda env: task_of(env).make_expert(env.unwrapped), None, "scripted expert")
    if args.onnx is not None:
        from bioscara_gym.training.export import OnnxPolicy

        onnx_policy = OnnxPolicy(args.onnx)
        return LoadedPolicy(
            lambda env: onnx_policy, onnx_policy.metadata, f"ONNX {args.onnx}", onnx_policy.shapes, True
        )
    read_metadata(Path(args.model))  # a missing metadata.json is refused before torch loads
    with needed_by("deploy --model"):
        from bioscara_gym.training.algos import load_model, sb3_policy

    # What the policy was trained for is proven by its own copy, not by an editable file.
    model, metadata = load_model(Path(args.model), require_embedded=True)
    sb3 = sb3_policy(model)
    shapes = PolicyShapes.of_spaces(model.observation_space, model.action_space, f"model {args.model}")
    return LoadedPolicy(lambda env: sb3, metadata, f"{metadata['algo'].upper()} {args.model}", shapes)


def probe_policy(loaded: LoadedPolicy, env: gym.Env, seed: int) -> None:
    """Run the policy once on an observation of the env's space, before the arm is touched.

    The env's first real observation needs the arm homed, so the probe is an
    observation drawn from the env's observation space with the run's seed: a
    policy whose own numbers are broken (a NaN weight) gives NaN or infinity,
    or fails inside its library, for any input.

    Raises:
        DeployError: One line naming the policy and what it gave.
    """
    space = env.observation_space
    space.seed(seed)
    probe = space.sample()
    try:
        action = np.asarray(loaded.make(env)(probe), dtype=np.float64)
    except Exception as e:  # torch's distribution checks, onnxruntime: one line, not their traceback
        raise DeployError(
            f"refused: {loaded.description} fails on a probe observation ({type(e).__name__}: "
            f"{first_line(e)}); are its weights NaN or infinite? nothing was sent to the arm"
        ) from e
    expected = tuple(env.action_space.shape or ())
    if action.shape != expected:  # seen: an ONNX graph's [batch, 1, 4] passed, homed, then stopped
        raise DeployError(
            f"refused: {loaded.description} gives an action of shape {action.shape} on a probe "
            f"observation; the env takes shape {expected}; nothing was sent to the arm"
        )
    if not np.all(np.isfinite(action)):
        raise DeployError(
            f"refused: {loaded.description} gives a non-finite action "
            f"{np.array2string(action, precision=3, separator=', ')} on a probe observation; "
            "nothing was sent to the arm"
        )


def check_input_order(loaded: LoadedPolicy, env: gym.Env) -> None:
    """Refuse a policy whose one input concatenates the observation in another order than the env's.

    ``bioscara export`` concatenates the observation in the order of the
    model's observation space, which is the env's (:func:`~bioscara_gym.training.export.obs_layout`);
    an ONNX file whose ``obs_keys`` name another order would be fed each part
    where the graph expects another (seen: ``desired_goal`` first, misses of
    170-422 mm, exit 0).

    Raises:
        DeployError: One line naming both orders.
    """
    spaces = getattr(env.observation_space, "spaces", None)
    if not loaded.concatenated or loaded.shapes is None or not isinstance(spaces, dict):
        return
    given, order = tuple(loaded.shapes.observation), tuple(spaces)
    if given != order:
        raise DeployError(
            f"refused: {loaded.description} concatenates its input as {', '.join(given)} "
            f"(its obs_keys), but `bioscara export` concatenates the env's observation as "
            f"{', '.join(order)}; nothing was sent to the arm"
        )


def first_line(e: BaseException) -> str:
    """The first line of an exception's message (torch's span several)."""
    text = str(e).strip()
    return text.splitlines()[0] if text else "no message"


def check_env_kwargs(env_id: str, kwargs: dict[str, Any]) -> None:
    """Refuse a policy's env kwargs that the env does not take, naming them.

    Raises:
        DeployError: Unknown env id, or a kwarg the env's constructor lacks.
    """
    try:
        problem = env_kwargs_problem(env_id, kwargs)
    except gym.error.Error as e:
        raise DeployError(f"cannot make env {env_id!r}: {e}") from e
    if problem is not None:
        raise DeployError(f"the policy's env_kwargs {problem}")


def check_args(args: DeployArgs) -> None:
    """Refuse a bad argument before anything is built or sent.

    Raises:
        DeployError: One line naming the argument and what was expected.
    """
    if args.backend not in DEPLOY_BACKENDS:
        raise DeployError(
            f"backend {args.backend!r} is not deployable; expected one of {', '.join(DEPLOY_BACKENDS)}"
        )
    if args.episodes < 1:
        raise DeployError(f"--episodes must be >= 1, got {args.episodes}")
    if args.seed < 0:
        raise DeployError(f"--seed must be >= 0, got {args.seed}")
    if args.bus is not None and args.bus < 0:
        raise DeployError(f"--bus must be an I2C bus number >= 0 (/dev/i2c-N), got {args.bus}")
    if args.rate is not None:
        try:
            check_control_freq(args.rate, "--rate")
        except ValueError as e:
            raise DeployError(str(e)) from e
    if args.firmware is not None and args.backend != "sitl":
        raise DeployError("--firmware needs --backend sitl (the firmware in the loop)")
    if args.faults is not None:
        if not args.faults.strip():
            raise DeployError("--faults names no fault; give KEY=VALUE,... e.g. nack=0.01")
        if args.backend not in ("emulated", "sitl"):
            raise DeployError(
                "--faults needs --backend emulated or sitl (faults are injected by the emulated bus)"
            )
        try:
            FaultPlan.parse(args.faults)
        except ValueError as e:
            raise DeployError(f"--faults: {e}") from e


def make_env(
    args: DeployArgs,
    state_file: Path | None,
    metadata: dict[str, Any] | None,
    extra_options: dict[str, Any] | None = None,
) -> gym.Env:
    """Build the policy's env (or ``--env``'s) on the chosen backend; nothing is sent yet.

    ``extra_options`` are laid over the backend's options (a replay's bus).

    Raises:
        DeployError: An unknown env, env kwargs it does not take, or an env that cannot be made.
    """
    kwargs: dict[str, Any] = dict(metadata["env_kwargs"]) if metadata else {}
    # With a policy the metadata names the env (--env, if given, must agree: Deployment._check);
    # the expert has --env (load_policy).
    try:
        env_id = resolve_env_id(args.env if args.env is not None else metadata["env_id"])
    except TrainingError as e:
        raise DeployError(str(e)) from e
    if env_id not in bioscara_gym.TASKS:  # seen: CartPole's TypeError, the whole ArmConfig in 5 kB
        raise DeployError(
            f"env {env_id!r} is not a Bioscara env: deploy drives the arm through one of "
            f"{', '.join(bioscara_gym.TASKS)}"
        )
    check_env_kwargs(env_id, kwargs)
    config = load_config(args.config)
    if args.bus is not None:
        config = dataclasses.replace(config, bus=args.bus)
    options = {**backend_options(args, state_file), **(extra_options or {})}
    kwargs.update(backend=args.backend, backend_options=options, config=config)
    kwargs["render_mode"] = None
    if args.rate is not None:
        kwargs["control_freq"] = float(args.rate)
    try:
        return gym.make(env_id, **kwargs)
    except (gym.error.Error, ValueError, TypeError, SitlError) as e:
        raise DeployError(f"cannot make env {env_id!r}: {e}") from e


def backend_options(args: DeployArgs, state_file: Path | None) -> dict[str, Any]:
    """The backend's options: the gripper state file, the emulated bus's faults, the trace, the firmware."""
    options: dict[str, Any] = {}
    if state_file is not None:
        options["state_file"] = state_file
    if args.faults:
        options["faults"] = FaultPlan.parse(args.faults)  # checked in check_args
    if args.record is not None:  # every bus transaction to a trace (docs/traces.md)
        from bioscara_gym.hardware.recording import Recording

        Path(args.record).parent.mkdir(parents=True, exist_ok=True)  # as the run log's (deploy_outputs)
        options["record"] = Recording(args.record, "deploy", args)
    if args.backend == "sitl":
        options["firmware"] = args.firmware  # None: $BIOSCARA_FIRMWARE
    return options
