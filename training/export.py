"""ONNX export of a trained policy, and :class:`OnnxPolicy` to run it without torch.

``bioscara export --model runs/reach/model.zip --onnx reach.onnx`` writes the
policy's deterministic action as an ONNX graph:

============  ============================  =====================================================
name          shape                         content
============  ============================  =====================================================
``obs``       (batch, n) float32            the dict observation flattened in the order of the
                                            ``obs_keys`` metadata (the model's observation space
                                            order: ``achieved_goal``, ``desired_goal``,
                                            ``observation``)
``action``    (batch, act_dim) float32      what ``model.predict(obs, deterministic=True)``
                                            returns: SAC/TD3 squashed and rescaled, PPO clipped
============  ============================  =====================================================

The file's ``metadata_props`` carry the training metadata (``bioscara_metadata``,
the same JSON as ``metadata.json``) and ``obs_keys`` (JSON ``[[key, size], ...]``),
so ``bioscara deploy --onnx FILE`` checks the policy against the env without
the ``.zip``. Only :func:`export_onnx` needs torch (the ``[train]`` extra) and
onnx; :class:`OnnxPolicy` needs numpy and onnxruntime (the ``[onnx]`` extra).
"""

from __future__ import annotations

import argparse
import hashlib
import json
import os
import stat
import warnings
from dataclasses import dataclass
from pathlib import Path
from typing import Any

import numpy as np
from rich.console import Console

from bioscara_gym.errors import CliError, ExportError, MetadataError
from bioscara_gym.fsutil import (
    folders_made_for,
    output_clash,
    output_problem,
    path_argument,
    replace_problem,
    replaced_path,
    temporary_beside,
)
from bioscara_gym.training.extras import needed_by, needs_onnx, needs_train
from bioscara_gym.training.metadata import PolicyShapes, policy_files, validate_metadata

#: metadata_props key holding the training metadata (JSON).
METADATA_KEY = "bioscara_metadata"
#: metadata_props key holding the observation layout (JSON ``[[key, size], ...]``).
OBS_KEYS_KEY = "obs_keys"
INPUT_NAME = "obs"
OUTPUT_NAME = "action"
OPSET = 17


@dataclass(frozen=True)
class ExportResult:
    """What :func:`export_onnx` wrote.

    Attributes:
        path: The ONNX file.
        obs_keys: Observation keys and sizes, in input order.
        max_abs_error: Largest difference to ``model.predict`` over the check set.
        checked: How many observations were compared.
    """

    path: Path
    obs_keys: list[tuple[str, int]]
    max_abs_error: float
    checked: int


def obs_layout(observation_space: Any) -> list[tuple[str, int]]:
    """Keys and flat sizes of a Dict observation space, in the space's order.

    Raises:
        ExportError: Not a Dict of Boxes.
    """
    spaces = getattr(observation_space, "spaces", None)
    if not isinstance(spaces, dict):
        raise ExportError(f"only Dict observation spaces are supported, not {observation_space}")
    return [(key, int(np.prod(space.shape))) for key, space in spaces.items()]


def flatten_obs(obs: dict[str, np.ndarray], layout: list[tuple[str, int]]) -> np.ndarray:
    """One float32 row (or a batch) from a dict observation, in ``layout`` order."""
    parts = []
    for key, size in layout:
        value = np.asarray(obs[key], dtype=np.float32)
        parts.append(value.reshape(-1, size))
    return np.concatenate(parts, axis=1)


def _actor_module(model: Any, layout: list[tuple[str, int]]) -> Any:
    """A torch module: flat float32 observation -> the action ``predict`` gives."""
    import torch

    policy = model.policy
    space = policy.action_space
    low = torch.as_tensor(space.low, dtype=torch.float32)
    high = torch.as_tensor(space.high, dtype=torch.float32)
    squash = bool(policy.squash_output)

    class Actor(torch.nn.Module):
        def __init__(self) -> None:
            super().__init__()
            self.policy = policy
            self.register_buffer("low", low)
            self.register_buffer("high", high)

        def forward(self, flat: torch.Tensor) -> torch.Tensor:
            obs, start = {}, 0
            for key, size in layout:
                obs[key] = flat[:, start : start + size]
                start += size
            actions = self.policy._predict(obs, deterministic=True)
            if squash:
                return self.low + 0.5 * (actions + 1.0) * (self.high - self.low)
            return torch.maximum(torch.minimum(actions, self.high), self.low)

    return Actor().eval()


def export_onnx(
    model_path: Path, onnx_path: Path, check_samples: int = 256, atol: float = 1e-5, seed: int = 0
) -> ExportResult:
    """Export a trained model's deterministic policy to ONNX, atomically, and check it.

    The check compares :class:`OnnxPolicy` with ``model.predict(...,
    deterministic=True)`` on ``check_samples`` observations the policy would
    see: its own env (from the metadata) on the mock backend, from a seeded
    reset through random actions.

    Args:
        model_path: ``model.zip`` (with ``metadata.json`` beside it) or its directory.
        onnx_path: The file to write; what it holds is replaced (``bioscara export``
            lets it replace only an ONNX model or an empty file: :func:`is_onnx_file`).
        check_samples: Observations to compare; 0 skips the check.
        atol: Largest difference accepted.
        seed: Seed of the check observations.

    Raises:
        ExportError: Unsupported observation space, or the check failed (nothing written).
        MetadataError: No metadata next to the model, a model without its own
            copy of it, or a ``metadata.json`` that differs from that copy in
            any setting (it goes into the ONNX file, which has no other copy).
    """
    with needs_train("bioscara export"), needed_by("bioscara export"):
        import torch

        from bioscara_gym.training.algos import load_model
    with needs_onnx("bioscara export"):
        import onnx

    # The metadata goes into the ONNX file, which has no other copy to check it by: all of it
    # must be the model's own (seen: a success rate and net_arch edited by hand were exported).
    model, metadata = load_model(Path(model_path), require_embedded=True, keys=None)
    layout = obs_layout(model.observation_space)
    actor = _actor_module(model, layout)
    n_obs = sum(size for _, size in layout)
    onnx_path = replaced_path(onnx_path)
    with folders_made_for(onnx_path.parent):  # an interrupted export leaves none of them
        fd, tmp = temporary_beside(onnx_path)  # the mode the file has, or a new file's
        os.close(fd)
        try:
            _write_graph(torch, onnx, actor, n_obs, tmp, metadata, layout)
            error = 0.0
            if check_samples:
                observations = _check_observations(metadata, check_samples, seed)
                error = _max_error(model, OnnxPolicy(tmp), observations)
                if not error <= atol:
                    raise ExportError(f"ONNX actions differ from model.predict by {error:.2e} (> {atol:g})")
            os.replace(tmp, onnx_path)
        except BaseException:
            Path(tmp).unlink(missing_ok=True)
            raise
    return ExportResult(onnx_path, layout, error, check_samples)


def _write_graph(
    torch: Any, onnx: Any, actor: Any, n_obs: int, path: str, metadata: dict[str, Any], layout: list
) -> None:
    """Export ``actor`` to ``path``, the metadata and observation layout in its props; checked, synced."""
    with warnings.catch_warnings():
        # torch >= 2.9 defaults to the dynamo exporter, which needs onnxscript;
        # the TorchScript exporter needs nothing more and warns that it is legacy.
        warnings.simplefilter("ignore")
        torch.onnx.export(
            actor,
            (torch.zeros(1, n_obs),),
            path,
            dynamo=False,
            input_names=[INPUT_NAME],
            output_names=[OUTPUT_NAME],
            dynamic_axes={INPUT_NAME: {0: "batch"}, OUTPUT_NAME: {0: "batch"}},
            opset_version=OPSET,
        )
    proto = onnx.load(path)
    text = json.dumps(metadata, sort_keys=True, default=str)
    for key, value in ((METADATA_KEY, text), (OBS_KEYS_KEY, json.dumps(layout))):
        entry = proto.metadata_props.add()
        entry.key, entry.value = key, value
    proto.graph.doc_string = metadata_seal(text)
    onnx.checker.check_model(proto)
    with open(path, "wb") as f:
        f.write(proto.SerializeToString())
        f.flush()
        os.fsync(f.fileno())


def metadata_seal(text: str) -> str:
    """The graph's own word on its metadata (its ``doc_string``): the metadata prop's SHA-256.

    The ONNX file has no second copy of its metadata, as ``model.zip`` has:
    an edited ``control_freq`` prop ran a 25 Hz policy at 50 Hz (a hostile
    test). A prop edited after export no longer matches the seal.
    """
    return f"{METADATA_KEY} sha256:{hashlib.sha256(text.encode('utf-8')).hexdigest()}"


def _check_observations(metadata: dict[str, Any], n: int, seed: int) -> list[dict[str, np.ndarray]]:
    """``n`` observations of the policy's env on ``mock``: a seeded reset, then random actions."""
    from bioscara_gym.training.evaluate import make_eval_env

    env = make_eval_env(metadata, backend="mock")
    try:
        env.action_space.seed(seed)
        obs, _ = env.reset(seed=seed)
        observations = []
        while len(observations) < n:
            observations.append(obs)
            obs, _, terminated, truncated, _ = env.step(env.action_space.sample())
            if terminated or truncated:
                obs, _ = env.reset()
        return observations
    finally:
        env.close()


def _max_error(model: Any, onnx_policy: OnnxPolicy, observations: list[dict[str, np.ndarray]]) -> float:
    worst = 0.0
    for obs in observations:
        want, _ = model.predict(obs, deterministic=True)
        worst = max(worst, float(np.max(np.abs(onnx_policy(obs) - want))))
    return worst


def parse_obs_keys(text: str) -> list[tuple[str, int]]:
    """The ``obs_keys`` metadata as :func:`export_onnx` writes it: ``[[key, size], ...]``.

    Keys are distinct strings, sizes whole numbers >= 1 (seen: 3.7 read as 3,
    ``1e400`` an OverflowError traceback).

    Raises:
        ValueError: Not JSON, or not that list; the message names the entry.
    """
    entries = json.loads(text)
    if not isinstance(entries, list) or not entries:
        raise ValueError(
            f"expected a list of [key, size] pairs, got {type(entries).__name__} {entries!r:.60}"
        )
    layout: list[tuple[str, int]] = []
    for entry in entries:
        valid = isinstance(entry, list) and len(entry) == 2 and isinstance(entry[0], str)
        size = entry[1] if valid else None
        if not valid or isinstance(size, bool) or not isinstance(size, int) or size < 1:
            raise ValueError(f"entry {entry!r:.60} is not [key, size] with size a whole number >= 1")
        if any(entry[0] == key for key, _ in layout):
            raise ValueError(f"key {entry[0]!r} is given twice")
        layout.append((entry[0], size))
    return layout


def _dims(shape: list[Any]) -> str:
    """An onnxruntime shape as ``[batch, 18]`` (``?`` for a dimension it does not know)."""
    return "[" + ", ".join("?" if d is None else str(d) for d in shape) + "]"


class OnnxPolicy:
    """A policy exported by :func:`export_onnx`, run with onnxruntime (no torch).

    Args:
        path: The ``.onnx`` file.

    Attributes:
        metadata: The training metadata stored in the file (validated).
        obs_keys: Observation keys and sizes, in input order.
        shapes: What the graph itself takes and gives, for
            :func:`~bioscara_gym.training.metadata.check_policy_shapes`.

    Raises:
        ExportError: The file cannot be loaded or lacks the metadata
            :func:`export_onnx` writes.
        MetadataError: The embedded metadata is incomplete, or the graph's
            input width disagrees with its ``obs_keys``.
    """

    def __init__(self, path: str | os.PathLike[str]) -> None:
        """Load the graph on the CPU, single-threaded (the control loop owns the other core)."""
        with needs_onnx("deploy --onnx"):
            import onnxruntime as ort

        self.path = Path(path)
        try:  # seen: a FIFO hung deploy --onnx; a folder was "Protobuf parsing failed"
            regular = stat.S_ISREG(os.stat(self.path).st_mode)
        except OSError as e:
            raise ExportError(f"cannot load {self.path}: {e.strerror}") from e
        if not regular:
            raise ExportError(f"{self.path} is not a regular file; give the .onnx file of `bioscara export`")
        options = ort.SessionOptions()
        options.intra_op_num_threads = 1
        options.inter_op_num_threads = 1
        options.log_severity_level = 3  # errors only: its warnings are lines before ours (a shape merge)
        try:
            self.session = ort.InferenceSession(
                str(self.path), sess_options=options, providers=["CPUExecutionProvider"]
            )
        except Exception as e:  # onnxruntime raises its own exception types
            raise ExportError(f"cannot load {self.path}: {e}") from e
        props = self.session.get_modelmeta().custom_metadata_map
        missing = [k for k in (METADATA_KEY, OBS_KEYS_KEY) if k not in props]
        if missing:
            raise ExportError(
                f"{self.path} has no {'/'.join(missing)} metadata; export it with `bioscara export`"
            )
        seal = self.session.get_modelmeta().graph_description
        if seal != metadata_seal(props[METADATA_KEY]):
            said = (
                f"its {METADATA_KEY} was changed after export (the graph's seal of it differs)"
                if seal.startswith(f"{METADATA_KEY} sha256:")
                else "has no seal of its metadata (exported by an older bioscara-gym)"
            )
            raise ExportError(f"{self.path}: {said}; export it again from its model.zip")
        try:
            metadata = json.loads(props[METADATA_KEY])
            self.obs_keys: list[tuple[str, int]] = parse_obs_keys(props[OBS_KEYS_KEY])
        except (ValueError, TypeError, RecursionError) as e:
            raise ExportError(
                f"{self.path}: its {METADATA_KEY}/{OBS_KEYS_KEY} metadata is not what `bioscara export` "
                f"writes ({type(e).__name__}: {' '.join(str(e).split())[:120]})"
            ) from e
        self.metadata: dict[str, Any] = validate_metadata(metadata, f"{self.path} (embedded metadata)")
        self.shapes = self._graph_shapes()

    def _graph_shapes(self) -> PolicyShapes:
        """The graph's own input and output widths, checked against its ``obs_keys``.

        Raises:
            MetadataError: The graph's input width is not what ``obs_keys`` adds up to,
                or its input or output is not the one :func:`export_onnx` writes
                (``[batch, n]``, ``n`` fixed: seen, an output ``[batch, 1, 4]``
                passed and stopped the arm at the first cycle).
        """
        inputs = {i.name: i.shape for i in self.session.get_inputs()}
        outputs = {o.name: o.shape for o in self.session.get_outputs()}
        if INPUT_NAME not in inputs or OUTPUT_NAME not in outputs:
            raise MetadataError(
                f"{self.path}: expected a graph from `bioscara export` with input '{INPUT_NAME}' and output "
                f"'{OUTPUT_NAME}', got inputs {sorted(inputs)} and outputs {sorted(outputs)}"
            )
        for kind, name, shape in (
            ("input", INPUT_NAME, inputs[INPUT_NAME]),
            ("output", OUTPUT_NAME, outputs[OUTPUT_NAME]),
        ):
            if len(shape) != 2:
                raise MetadataError(
                    f"{self.path}: the graph's {kind} '{name}' has shape {_dims(shape)}; `bioscara export` "
                    "writes [batch, n]: one row per observation"
                )
        width, act = inputs[INPUT_NAME][-1], outputs[OUTPUT_NAME][-1]
        if not isinstance(width, int):
            raise MetadataError(
                f"{self.path}: the graph's input '{INPUT_NAME}' has shape {_dims(inputs[INPUT_NAME])}: "
                "its width is not a fixed number, as `bioscara export` writes it"
            )
        if not isinstance(act, int):
            raise MetadataError(self._unknown_width(width, outputs[OUTPUT_NAME]))
        layout = sum(n for _, n in self.obs_keys)
        if layout != width:
            raise MetadataError(
                f"{self.path}: the graph's input '{INPUT_NAME}' takes {width} values, but its "
                f"{OBS_KEYS_KEY} add up to {layout}"
            )
        return PolicyShapes(dict(self.obs_keys), act, f"ONNX graph {self.path}")

    def _unknown_width(self, width: int, shape: list[Any]) -> str:
        """Why an output with no fixed width is refused, with what the graph gives run once on zeros.

        Seen: a graph declaring ``[batch, 4]`` that computes 8 values, which
        onnxruntime reads as ``[batch, ?]`` (after a warning of its own).
        """
        try:
            (given,) = self.session.run([OUTPUT_NAME], {INPUT_NAME: np.zeros((1, width), np.float32)})
            gives = f"run once it gives shape {tuple(np.shape(given))}"
        except Exception as e:  # onnxruntime's own exception types
            gives = f"run once it fails ({type(e).__name__})"
        return (
            f"{self.path}: onnxruntime reads the graph's output '{OUTPUT_NAME}' as {_dims(shape)}, no fixed "
            f"width (what the graph computes is not what it declares, or it declares none); {gives}"
        )

    def __call__(self, obs: dict[str, np.ndarray]) -> np.ndarray:
        """The deterministic action for one observation (float32, shape of the action space)."""
        (action,) = self.session.run([OUTPUT_NAME], {INPUT_NAME: flatten_obs(obs, self.obs_keys)})
        return action[0]

    def reset(self) -> None:
        """Stateless: nothing to reset."""


# ----------------------------------------------------------------------- CLI
#: Largest file :func:`is_onnx_file` reads: protobuf's limit for one message, 2 GiB.
MAX_ONNX_BYTES = 2**31


def is_onnx_file(path: Path) -> bool:
    """Whether ``path`` holds an ONNX model (what ``export --onnx`` may replace): onnx parses it as one.

    Raises:
        OSError: It cannot be read.
        MissingExtraError: onnx is not installed.
    """
    if os.stat(path).st_size > MAX_ONNX_BYTES:
        return False
    with needs_onnx("bioscara export"):
        import onnx
    data = Path(path).read_bytes()
    try:
        proto = onnx.load_model_from_string(data)
    except Exception:  # protobuf's DecodeError and its like: not an ONNX model
        return False
    return proto.ir_version > 0 and proto.HasField("graph")


#: Most observations ``--check`` compares (the default 256 takes a second; seen: 10^9 ran on, growing).
MAX_CHECK = 100_000


def cmd_export(ns: argparse.Namespace) -> int:
    """``bioscara export``: write the ONNX file and report the check against torch."""
    if ns.check < 0:
        raise CliError(f"--check must be >= 0 (0: no check against torch), got {ns.check}")
    if ns.check > MAX_CHECK:
        raise CliError(f"--check {ns.check}: at most {MAX_CHECK} observations (each is kept to compare)")
    problem = output_problem(ns.onnx, parents=True)  # export makes the folders
    if problem is not None:
        raise CliError(f"--onnx {ns.onnx}: {problem}")
    clash = output_clash({"--onnx": ns.onnx}, policy_files(ns.model))
    if clash is not None:
        raise CliError(clash)
    problem = replace_problem(ns.onnx, "an ONNX model", is_onnx_file)  # seen: --onnx notes.txt replaced
    if problem is not None:
        raise CliError(f"--onnx {ns.onnx}: {problem}")
    result = export_onnx(ns.model, ns.onnx, check_samples=ns.check)
    con = Console(highlight=False, markup=False, soft_wrap=True)
    con.print(f"onnx      {result.path}")
    con.print(f"input     obs = {' + '.join(f'{k}[{n}]' for k, n in result.obs_keys)}")
    if result.checked:
        con.print(
            f"check     max |onnx - predict| = {result.max_abs_error:.2e} over {result.checked} observations"
        )
    else:
        con.print("check     none (--check 0): the graph was not compared with torch")
    return 0


def register(sub: argparse._SubParsersAction) -> None:
    """Add the ``export`` subcommand."""
    p = sub.add_parser("export", help="export a trained policy to ONNX (checked against torch)")
    p.add_argument("--model", type=Path, required=True, help="model.zip (metadata.json beside it)")
    p.add_argument(
        "--onnx",
        type=path_argument,
        required=True,
        help="ONNX file to write (it replaces only an ONNX model or an empty file; missing folders are made)",
    )
    p.add_argument(
        "--check",
        type=int,
        default=256,
        help=f"observations to compare with model.predict (0: none; at most {MAX_CHECK})",
    )
    p.set_defaults(func=cmd_export)
