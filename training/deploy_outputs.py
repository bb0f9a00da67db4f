"""The files ``bioscara deploy`` writes, checked before a byte reaches the arm.

- the **run log**: ``--log``, default ``runs/deploy/deploy-<time>.jsonl``;
  it replaces only an earlier run log (its first line a run log's header) or
  an empty file;
- the **gripper state file**: ``--state-file``; by default on ``mock``,
  ``emulated`` and ``sitl`` ``gripper.json`` in the run log's folder, on
  ``i2c`` the configuration's ``gripper.state_file`` or
  ``$XDG_STATE_HOME/bioscara/gripper.json``; it replaces only a gripper
  state file (``{"width_m": ...}``) or an empty file;
- the **bus trace**: ``--record``; a session is added to a trace or an
  empty file, nothing else (:class:`~bioscara_gym.hardware.recording.Recording`).

Each must be a regular file of its own (no two options naming one file, none
naming an input such as the policy), in a place that takes a file. A folder
that does not exist is made, for all three alike, as ``eval --json`` and
``export --onnx`` make theirs (the default ``runs/deploy/`` is made so); a
file where a folder must be, or a folder that refuses a file (read-only), is
refused. (Seen: ``--state-file notes.txt`` replaced the notes, ``--log
model.zip`` another run's model, with a warning or none; an unwritable
``--state-file`` was found only after the run, ``--record new/t.jsonl`` failed
where ``--log new/run.jsonl`` made its folder.)
"""

from __future__ import annotations

from pathlib import Path
from typing import Any

from bioscara_gym.errors import DeployError
from bioscara_gym.fsutil import output_clash, output_problem, replace_problem
from bioscara_gym.hardware.gripper import STATE_FILE_KIND, is_state_file
from bioscara_gym.training.deploy_log import is_deploy_log
from bioscara_gym.training.metadata import policy_files

#: What each output replaces, for :func:`~bioscara_gym.fsutil.replace_problem`.
LOG_KIND = "a deploy run log"
STATE_KIND = STATE_FILE_KIND


def arm_state_file(args: Any, state_file: Path | None) -> Path | None:
    """The gripper state file the run writes: ``state_file``, else on ``i2c`` the backend's default."""
    if state_file is not None or args.backend != "i2c":
        return state_file
    from bioscara_gym.hardware.backends import gripper_state_file
    from bioscara_gym.hardware.config import load_config

    try:
        config = load_config(args.config)
    except ValueError:  # the env's making names what is wrong with it
        return None
    return gripper_state_file(config, None, default=True)


def check_files(args: Any, log: Path, state_file: Path | None) -> None:
    """Refuse, before the arm is touched, outputs that cannot be written or would destroy a file.

    Args:
        args: The run's :class:`~bioscara_gym.training.deploy_checks.DeployArgs`
            (its inputs, ``--record``).
        log: The run log.
        state_file: The gripper state file deploy passes to the backend (``None``: the backend's).

    Raises:
        DeployError: As :func:`check_outputs`; an output that cannot be written
            there, or an existing file that is not of its kind (module docstring).
    """
    inputs: dict[str, Path | None] = {"--config": args.config, "--onnx": args.onnx}
    if args.model is not None:  # model.zip or its folder
        inputs.update(policy_files(args.model))
    if args.onnx is not None:
        inputs["policy's metadata.json"] = Path(args.onnx).parent / "metadata.json"
    state = arm_state_file(args, state_file)
    check_outputs({"--log": log, "--state-file": state, "--record": args.record}, inputs)
    name = (
        "--state-file" if args.state_file is not None else "the gripper state file (--state-file's default)"
    )
    for option, path, kind in (
        ("--log", log, LOG_KIND),
        (name, state, STATE_KIND),
        ("--record", args.record, ""),
    ):
        if path is None:
            continue
        problem = output_problem(path, parents=True)  # deploy makes the missing folders
        if problem is None and kind:
            problem = replace_problem(path, kind, is_deploy_log if kind == LOG_KIND else is_state_file)
        if problem is not None:
            raise DeployError(f"{option} {path}: {problem}")
    if args.record is not None:
        from bioscara_gym.hardware.recording import Recording

        try:
            Recording(args.record, "deploy", args)  # a session is added only to a trace
        except ValueError as e:
            raise DeployError(str(e)) from e


def check_outputs(outputs: dict[str, Path | None], inputs: dict[str, Path | None] | None = None) -> None:
    """Refuse output files that are one and the same, that cannot be files, or that are inputs.

    The run log, the gripper state file (``None``: the backend's, on the arm)
    and the bus trace are written side by side: one path for two of them
    would leave neither readable. An output that names an input (the
    configuration, the policy) would overwrite it before it is read.

    Raises:
        DeployError: Two options name one file, or one names a directory, a
            device or a FIFO, or a path under something that is not a directory,
            or an input file.
    """
    clash = output_clash(outputs, inputs)
    if clash is not None:
        raise DeployError(clash)
    for option, path in outputs.items():
        if path is None:
            continue
        resolved = Path(path).resolve()
        if resolved.exists() and not resolved.is_file():
            raise DeployError(f"{option} {path} is not a regular file")
        parent = next((p for p in resolved.parents if p.exists()), None)
        if parent is not None and not parent.is_dir():
            raise DeployError(f"{option} {path}: {parent} is not a directory")
