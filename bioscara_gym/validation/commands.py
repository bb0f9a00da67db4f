"""``bioscara validate`` and ``bioscara calibrate``: the simulated arm against recordings of a real one."""

from __future__ import annotations

import argparse
import os
from collections.abc import Callable
from pathlib import Path

from rich.console import Console

from bioscara_gym.errors import CliError, one_line
from bioscara_gym.fsutil import output_clash, output_problem, path_argument, read_bytes, replace_problem
from bioscara_gym.hardware.config import MAX_CONFIG_BYTES, load_config

#: The seeds scipy's optimizers take (``numpy.random.RandomState``): 0 to 2**32 - 1.
SEED_MAX = 2**32 - 1


def _console() -> Console:
    return Console(highlight=False, soft_wrap=True)


#: What ``calibrate --out`` replaces (:func:`~bioscara_gym.fsutil.replace_problem`).
CONFIG_KIND = "an arm configuration (YAML)"


def _one_line_errors(command: Callable[[argparse.Namespace], int], args: argparse.Namespace) -> int:
    """Run ``command``; its refusals (and a recording's) come out on one line, a name's newline escaped.

    Seen: a recording named with a newline gave a two-line error.
    """
    try:
        return command(args)
    except CliError as e:
        raise CliError(one_line(e), e.code) from e
    except ValueError as e:  # RecordingError, ConfigError: the line cli.main prints for them
        raise CliError(one_line(e)) from e


def _check_output(path: Path | None, what: str, folder: bool = False) -> None:
    """Refuse, before any work, an output that cannot be written (``fsutil.output_problem``)."""
    problem = None if path is None else output_problem(path, folder)
    if problem is not None:
        raise CliError(f"{what} {path}: {problem}")


def _check_replace(path: Path | None, what: str, kind: str, is_kind: Callable[[Path], bool]) -> None:
    """Refuse, before any work, an output over a file the command did not write (``fsutil.replace_problem``).

    Seen: ``validate --json notes.txt`` and ``calibrate --out notes.txt`` replaced the notes.
    """
    problem = None if path is None else replace_problem(path, kind, is_kind)
    if problem is not None:
        raise CliError(f"{what} {path}: {problem}")


def is_arm_config(path: Path) -> bool:
    """Whether ``path`` holds an arm configuration (what ``calibrate --out`` may replace): it loads as one.

    Raises:
        OSError: It cannot be read.
    """
    if os.stat(path).st_size > MAX_CONFIG_BYTES:
        return False
    read_bytes(path, MAX_CONFIG_BYTES)  # unreadable: OSError, not "not a configuration"
    try:
        load_config(path)
    except ValueError:
        return False
    return True


def _plot_paths(args: argparse.Namespace) -> list[Path]:
    """The pictures ``--plots`` may write (one per drawn recording of the folder; none without it)."""
    if args.plots is None:
        return []
    from bioscara_gym.validation.plots import plot_names

    return [args.plots / name for name in plot_names(args.dir)]


def _check_plots(out: Path | None, paths: list[Path]) -> None:
    """Refuse, before any work, a picture's place that holds what is not a picture (a folder, a text file).

    Seen: a folder named like a picture failed the command after the whole
    validation, naming a hidden path; a text file was replaced with a PNG.
    """
    from bioscara_gym.validation.plots import plot_problem

    for path in paths:
        problem = plot_problem(path)
        if problem is not None:
            raise CliError(f"--plots {out}: {path} {problem}")


def _packaged_config() -> Path:
    """The packaged configuration's file (what ``load_config(None)`` reads)."""
    from importlib import resources

    return Path(str(resources.files("bioscara_gym.hardware").joinpath("default_config.yaml")))


def _check_clash(
    outputs: dict[str, Path | None], args: argparse.Namespace, plots: list[Path] | None = None
) -> None:
    """Refuse, before any work, an output that is one of the inputs or another output.

    The inputs: every recording file of the folder (default: the packaged
    ones) and the configuration (``--config``, or the packaged one). Each
    of ``plots`` (the pictures ``--plots`` writes) is an output too (seen:
    ``--json`` naming one was lost under the picture).
    """
    from bioscara_gym.validation.recordings import DATA_DIR, recording_files

    root = args.dir if args.dir is not None else DATA_DIR
    inputs: dict[str, Path | None] = {f"recording {p.relative_to(root)}": p for p in recording_files(root)}
    if args.config is not None:
        inputs["--config"] = args.config
    else:
        inputs["packaged configuration"] = _packaged_config()
    clash = output_clash(outputs, inputs)
    for plot in plots or []:
        if clash is not None:
            break
        clash = output_clash({"--json": args.json, "--plots": plot}, inputs)
    if clash is not None:
        raise CliError(clash)


def cmd_validate(args: argparse.Namespace) -> int:
    """``bioscara validate``: exit 0 only if every comparison passes."""
    return _one_line_errors(_validate, args)


def _validate(args: argparse.Namespace) -> int:
    from bioscara_gym.validation import validate
    from bioscara_gym.validation.report import ROWS_KIND, is_rows_json, print_table, rows_to_json, summary

    _check_output(args.json, "--json")
    _check_output(args.plots, "--plots", folder=True)
    plots = _plot_paths(args)
    _check_clash({"--json": args.json, "--plots": args.plots}, args, plots)
    _check_replace(args.json, "--json", ROWS_KIND, is_rows_json)
    _check_plots(args.plots, plots)
    if args.plots is not None:
        from bioscara_gym.hardware.errors import require_extra

        require_extra("matplotlib", "--plots", "validate")
    config = load_config(args.config)
    result = validate(args.dir, config)
    print_table(result.rows)
    passed, total = summary(result.rows)
    con = _console()
    con.print(
        f"{passed} of {total} comparisons pass "
        f"({len(result.recordings)} recordings in {one_line(result.recordings.root)})"
    )
    # All or none: the pictures are drawn first (a recording that cannot be
    # drawn fails here, before the JSON), their places checked again, then
    # the JSON is written, then the pictures are moved into place.
    staged = None
    if args.plots:
        from bioscara_gym.validation.plots import stage_plots

        staged = stage_plots(result, args.plots)
        problem = staged.problem()  # made meanwhile (the checks before the work found none)
        if problem is not None:
            staged.discard()
            raise CliError(f"--plots {args.plots}: {problem}")
    if args.json:
        try:
            rows_to_json(result.rows, args.json)
        except BaseException:
            if staged is not None:
                staged.discard()
            raise
        con.print(f"json      {one_line(args.json)}")
    if staged is not None:
        paths = staged.commit()
        con.print(f"plots     {one_line(args.plots)} ({len(paths)} PNG)")
    return 0 if result.passed else 1


def cmd_calibrate(args: argparse.Namespace) -> int:
    """``bioscara calibrate``: fit, print the error per experiment before and after, write the config."""
    return _one_line_errors(_calibrate, args)


def _calibrate(args: argparse.Namespace) -> int:
    import dataclasses

    import yaml

    from bioscara_gym.fsutil import atomic_write_text
    from bioscara_gym.hardware.config import config_to_dict
    from bioscara_gym.hardware.errors import require_extra
    from bioscara_gym.validation import validate
    from bioscara_gym.validation.calibrate import calibrate, check_fittable, hypotheses_line
    from bioscara_gym.validation.recordings import find_recordings
    from bioscara_gym.validation.report import summary

    require_extra("scipy", "bioscara calibrate", "validate")
    _check_output(args.out, "--out")
    _check_clash({"--out": args.out}, args)
    _check_replace(args.out, "--out", CONFIG_KIND, is_arm_config)
    if args.maxiter < 1:
        raise CliError(f"--maxiter must be >= 1, got {args.maxiter}")
    if not 0 <= args.seed <= SEED_MAX:
        raise CliError(f"--seed must be 0-{SEED_MAX} (the optimizer's seeds are 32-bit), got {args.seed}")
    if args.workers < 1:
        raise CliError(f"--workers must be >= 1, got {args.workers}")
    config = load_config(args.config)
    rec = find_recordings(args.dir)  # a folder without recordings fails here, before the fit
    check_fittable(config, rec)  # and one the fit cannot use, before the validation
    con = _console()
    before = validate(args.dir, config)
    # SIGTERM is an interrupt here too (bioscara_gym.cli): the pool's workers are stopped with it.
    result = calibrate(
        config, rec, seed=args.seed, maxiter=args.maxiter, workers=args.workers, progress=con.print
    )
    after = validate(args.dir, result.config)
    con.print("experiment                               rows passing before -> after")
    by_experiment: dict[str, list[int]] = {}
    for rows, slot in ((before.rows, 0), (after.rows, 1)):
        for r in rows:
            counts = by_experiment.setdefault(r.experiment, [0, 0, 0])
            counts[slot] += r.passed
            if slot == 0:
                counts[2] += 1
    for name, (b, a, n) in by_experiment.items():
        con.print(f"{name:<60} {b}/{n} -> {a}/{n}")
    for joint, cost in result.drive_cost_after.items():
        tried = hypotheses_line(result.drive_cost_by_hypothesis[joint])
        con.print(f"{joint}: drive fit cost {result.drive_cost_before[joint]:.4f} -> {cost:.4f} ({tried})")
    pb, total = summary(before.rows)
    pa, _ = summary(after.rows)
    con.print(f"all: {pb} -> {pa} of {total} comparisons pass")
    header = (
        f"# Calibrated by `bioscara calibrate {args.dir or '(packaged recordings)'}` from "
        f"{len(rec)} recordings in {rec.root}\n"
        "# (docs/validation.md): drive, pid_noise and bus_timing come from the fit; the rest from "
        f"{args.config or 'the packaged configuration'}.\n"
    )
    data = config_to_dict(dataclasses.replace(result.config))
    atomic_write_text(args.out, header + yaml.safe_dump(data, sort_keys=False))
    con.print(f"config    {one_line(args.out)}")
    return 0


def register(sub: argparse._SubParsersAction) -> None:
    """Add ``validate`` and ``calibrate`` to the ``bioscara`` command."""
    p = sub.add_parser("validate", help="replay the real arm's recordings on the simulated arm and compare")
    p.add_argument(
        "dir",
        nargs="?",
        type=Path,
        help="recordings laid out like the arm repository's test/ (default: the packaged ones)",
    )
    p.add_argument(
        "--config", type=path_argument, help="arm configuration to judge (default: the packaged one)"
    )
    p.add_argument(
        "--json",
        type=path_argument,
        metavar="FILE",
        help="write every row as JSON (it replaces only an earlier --json file or an empty file)",
    )
    p.add_argument(
        "--plots",
        type=path_argument,
        metavar="DIR",
        help="write one PNG per recording, simulated over real (replacing only PNG images or empty files)",
    )
    p.set_defaults(func=cmd_validate)

    p = sub.add_parser("calibrate", help="fit the motor, drive and bus model to recordings of a real arm")
    p.add_argument(
        "dir",
        nargs="?",
        type=Path,
        help="recordings laid out like the arm repository's test/ (default: the packaged ones)",
    )
    p.add_argument(
        "--out",
        type=path_argument,
        required=True,
        metavar="CONFIG",
        help="where to write the configuration (it replaces only an arm configuration or an empty file)",
    )
    p.add_argument(
        "--config", type=path_argument, help="configuration to start from (default: the packaged one)"
    )
    p.add_argument("--seed", type=int, default=0, help="seed of the optimizer")
    p.add_argument("--maxiter", type=int, default=40, help="generations of the drive fit per joint")
    p.add_argument(
        "--workers",
        type=int,
        default=os.cpu_count() or 1,
        help="processes fitting joints' drives side by side (default: one per CPU; same result)",
    )
    p.set_defaults(func=cmd_calibrate)
