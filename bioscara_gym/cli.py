"""The ``bioscara`` command: train, eval, deploy, export, and the operator console.

Every subcommand prints a one-line error and exits non-zero on bad input
(unknown env, algorithm or joint, unreadable file, mismatched policy); it
never leaves the arm enabled behind it. Exit codes: 0 done; 2 refused
(nothing that changes the arm was sent); 3 a failure on the arm (a stall, a
bus error, a timeout, deploy's safety stop; the console and deploy then
disable every joint); 130, 143, 129 Ctrl-C, SIGTERM, SIGHUP; 1 an unexpected error
(``ping``, ``validate`` and ``replay`` give 1 a meaning of their own: a
device that did not answer, a row or a transaction that does not match).
"""

from __future__ import annotations

import argparse
import contextlib
import importlib
import os
import signal
import sys
import threading
import warnings
from collections.abc import Callable, Iterator, Sequence
from pathlib import Path
from typing import Any, NoReturn

from rich.console import Console
from rich.table import Table

from bioscara_gym.errors import (
    EXIT_ERROR,
    EXIT_FAULT,
    EXIT_INTERRUPTED,
    CheckpointWarning,
    CliError,
    MissingExtraError,
    is_refusal,
    one_line,
)
from bioscara_gym.fsutil import output_clash, output_problem, path_argument
from bioscara_gym.hardware.errors import JointError, SitlError
from bioscara_gym.hardware.gripper import GripperStateWarning
from bioscara_gym.hardware.sitl.build import add_firmware_option
from bioscara_gym.stop_signals import after_signal, caught
from bioscara_gym.training.signals import Interrupted

#: The env of ``train`` and ``eval --expert`` when none is given.
DEFAULT_ENV = "Bioscara-Reach"


def _console() -> Console:
    return Console(highlight=False, soft_wrap=True)  # paths stay on one line


# ----------------------------------------------------------------- train
def cmd_train(args: argparse.Namespace) -> int:
    """``bioscara train``; SIGINT, SIGTERM and SIGHUP save a checkpoint and exit 130, 143 and 129."""
    from bioscara_gym.training.signals import Interrupted
    from bioscara_gym.training.train import TrainArgs, TrainingInterrupted, train

    err = Console(stderr=True, highlight=False, markup=False, soft_wrap=True)
    try:
        with warnings.catch_warnings():
            warnings.simplefilter("always", CheckpointWarning)
            warnings.showwarning = _one_line_warnings("train", err, warnings.showwarning)
            result = train(
                TrainArgs(
                    env=args.env,
                    algo=args.algo,
                    config=args.config,
                    timesteps=args.timesteps,
                    seed=args.seed,
                    out=args.out,
                    resume=args.resume,
                    progress=not args.no_progress,
                    threads=args.threads,
                    demos=args.demos,
                    n_envs=args.n_envs,
                )
            )
    except Interrupted as e:
        if isinstance(e, TrainingInterrupted) and e.checkpoint is not None:
            err.print(
                one_line(
                    f"bioscara train: interrupted by {e}; checkpoint {e.checkpoint} "
                    f"(continue with `{_resume_command(args)}`)"
                )
            )
        else:
            err.print(f"bioscara train: interrupted by {e} before training started; nothing saved")
        return e.exit_code
    con = _console()
    final = result.final_eval
    if result.target_reached_at is not None:
        con.print(
            f"target reached after {result.target_reached_at} steps, {result.target_reached_after_s:.0f} s"
        )
    if final is not None:
        con.print(f"final success rate {final.success_rate:.1%} over {final.episodes} episodes")
    con.print(f"model     {result.model_path}")
    con.print(f"metadata  {result.metadata_path}")
    con.print(f"logs      {Path(args.out) / 'tb'}  (tensorboard --logdir {Path(args.out) / 'tb'})")
    return 0


def _resume_command(args: argparse.Namespace) -> str:
    """The command that continues this run (``--env`` and ``--algo`` must match the run's)."""
    command = f"bioscara train --resume --out {args.out}"
    if args.env != DEFAULT_ENV:
        command += f" --env {args.env}"
    if args.algo is not None:
        command += f" --algo {args.algo}"
    return command


#: The package's own warnings, printed as one line (``bioscara CMD: warning: ...``).
ONE_LINE_WARNINGS = (CheckpointWarning, GripperStateWarning)


def _one_line_warnings(command: str, err: Console, fallback: Callable[..., None]) -> Callable[..., None]:
    """A ``warnings.showwarning`` printing the package's own warnings as one line on stderr."""

    def show(message: Warning | str, category: type[Warning], *rest: object, **kwargs: object) -> None:
        if issubclass(category, ONE_LINE_WARNINGS):
            err.print(one_line(f"bioscara {command}: warning: {message}"))
        else:
            fallback(message, category, *rest, **kwargs)

    return show


# ------------------------------------------------------------------ eval
def _stats_table(title: str, stats: object) -> Table:
    table = Table(title=title)
    table.add_column("metric")
    table.add_column("value", justify="right")
    s = stats
    table.add_row("episodes", str(s.episodes))  # type: ignore[attr-defined]
    table.add_row("success rate", f"{s.success_rate:.1%}")  # type: ignore[attr-defined]
    table.add_row("mean final distance", f"{s.mean_final_distance * 1000:.1f} mm")  # type: ignore[attr-defined]
    table.add_row("mean return", f"{s.mean_return:.2f} ± {s.std_return:.2f}")  # type: ignore[attr-defined]
    table.add_row("mean length", f"{s.mean_length:.1f} steps")  # type: ignore[attr-defined]
    table.add_row("stalls", str(s.stalls))  # type: ignore[attr-defined]
    return table


def cmd_eval(args: argparse.Namespace) -> int:
    """``bioscara eval``."""
    from bioscara_gym.training.evaluate import VIDEO_SUFFIXES, evaluate_expert, evaluate_model, write_json

    if args.episodes < 1:  # before a backend is built (sitl: seconds of compiling)
        raise CliError(f"--episodes must be >= 1, got {args.episodes}")
    if args.seed < 0:
        raise CliError(f"--seed must be >= 0, got {args.seed}")
    if args.video_episodes is not None and args.video is None:
        raise CliError("--video-episodes needs --video (the file to write them to)")
    video_episodes = 3 if args.video_episodes is None else args.video_episodes
    if video_episodes < 1:
        raise CliError(f"--video-episodes must be >= 1, got {video_episodes}")
    if args.expert and args.model is not None:
        raise CliError("--expert and --model both name a policy; give one")
    outputs = {"--json": args.json, "--video": args.video, "--record": args.record}
    for option, path in outputs.items():  # refused before the episodes run
        problem = None if path is None else output_problem(path, parents=True)  # eval makes the folders
        if problem is not None:
            raise CliError(f"{option} {path}: {problem}")
    clash = output_clash(outputs, {} if args.model is None else _policy_files(args.model))
    if clash is not None:
        raise CliError(clash)
    if args.video is not None and Path(args.video).suffix.lower() not in VIDEO_SUFFIXES:
        raise CliError(f"--video {args.video}: a video file name ends in {', '.join(VIDEO_SUFFIXES)}")
    options = eval_backend_options(args)
    if args.expert:
        from bioscara_gym.training.metadata import resolve_env_id

        env_id = resolve_env_id(args.env or DEFAULT_ENV)
        stats = evaluate_expert(
            env_id,
            args.episodes,
            args.backend or "sim",
            args.video,
            args.seed,
            video_episodes,
            backend_options=options,
        )
        title, source = f"scripted expert on {env_id} ({args.backend or 'sim'})", "expert"
    else:
        if args.model is None:
            raise CliError("eval needs --model PATH (or --expert --env ID)")
        if args.env is not None:
            _check_model_env(args.model, args.env)
        stats = evaluate_model(
            args.model, args.episodes, args.backend, args.video, args.seed, video_episodes, options
        )
        title, source = f"{args.model} ({args.backend or 'as trained'})", str(args.model)
    con = _console()
    con.print(_stats_table(title, stats))
    if args.video:
        con.print(f"video     {args.video}")
    if args.json:
        write_json(args.json, stats, source=source, backend=args.backend or "sim")
        con.print(f"json      {args.json}")
    return 0


def _policy_files(model: Path) -> dict[str, Path]:
    """The model's files (:func:`bioscara_gym.training.metadata.policy_files`), imported on use."""
    from bioscara_gym.training.metadata import policy_files

    return policy_files(model)


def _check_model_env(model: Path, env: str) -> None:
    """Refuse ``--env`` naming another env than the one ``model`` was trained on (it was ignored)."""
    from bioscara_gym.training.metadata import read_metadata, resolve_env_id

    trained = read_metadata(Path(model))["env_id"]
    if resolve_env_id(env) != resolve_env_id(trained):
        raise CliError(f"--env {env}: the model was trained on {trained}, where it is evaluated")


def eval_backend_options(args: argparse.Namespace) -> dict[str, object] | None:
    """The backend options of ``bioscara eval``: ``--record`` (a bus to record), ``--firmware``; else none."""
    options: dict[str, object] = {}
    firmware = getattr(args, "firmware", None)
    if firmware is not None and args.backend != "sitl":
        raise CliError("--firmware needs --backend sitl (the firmware in the loop)")
    if args.backend == "sitl":
        options["firmware"] = firmware  # None: $BIOSCARA_FIRMWARE
    if getattr(args, "record", None) is not None:
        from bioscara_gym.hardware.recording import RECORDABLE_BACKENDS, Recording

        if args.backend not in RECORDABLE_BACKENDS:
            backend = args.backend or "sim"
            raise CliError(f"--record needs --backend emulated (a bus to record); {backend} has none")
        options["record"] = Recording(args.record, "eval", args)
    return options or None


# ---------------------------------------------------------------- parser
class _Parser(argparse.ArgumentParser):
    """argparse's parser, whose errors are one line naming the command (``--help`` shows the usage).

    argparse prints its usage block above the error: five to seven lines
    for ``--episodes abc``, where a value refused by a command's own check
    is one. Subcommands' parsers are of this class too.
    """

    def error(self, message: str) -> NoReturn:
        """Print ``PROG: error: MESSAGE`` and exit 2."""
        self.exit(EXIT_ERROR, f"{self.prog}: error: {one_line(message)}\n")


def build_parser() -> argparse.ArgumentParser:
    """The ``bioscara`` argument parser."""
    parser = _Parser(prog="bioscara", description="Bioscara SCARA arm: train, evaluate and deploy policies.")
    sub = parser.add_subparsers(dest="command", required=True)

    from bioscara_gym.training.methods import METHODS  # names only: no torch

    p = sub.add_parser("train", help="train a policy with stable-baselines3 on CPU")
    p.add_argument("--env", default=DEFAULT_ENV, help=f"env id (default: {DEFAULT_ENV})")
    p.add_argument(
        "--algo",
        metavar="{" + ",".join(METHODS) + "}",  # checked by the registry: one line naming them
        help=", ".join(f"{name}: {spec.help}" for name, spec in METHODS.items())
        + " (default: the task's without --config: dagger on PickPlace, Push, Stack and Insert, sac on Reach;"
        + " sac with --config; on --resume the run's)",
    )
    p.add_argument("--config", type=path_argument, help="hyperparameter YAML (rl-zoo3 format)")
    p.add_argument("--timesteps", type=int, help="training budget (default: the config's n_timesteps)")
    p.add_argument("--seed", type=int, help="seed of the model and envs (default 0; on --resume the run's)")
    p.add_argument("--out", type=path_argument, default=Path("runs/reach"), help="output directory")
    p.add_argument("--resume", action="store_true", help="continue from the newest checkpoint in --out")
    p.add_argument(
        "--threads", type=int, help="torch CPU threads (default 1; DAgger fits on its config's fit_threads)"
    )
    p.add_argument("--demos", help="Minari dataset of demonstrations to learn from (bioscara collect)")
    p.add_argument(
        "--n-envs",
        type=int,
        help="envs stepping in parallel subprocesses (training envs, DAgger's rollouts); default: config's",
    )
    p.add_argument("--no-progress", action="store_true", help="no progress bar")
    p.set_defaults(func=cmd_train)

    p = sub.add_parser("eval", help="evaluate a trained policy or the scripted expert")
    p.add_argument("--model", type=Path, help="model.zip (its metadata.json must sit beside it)")
    p.add_argument("--expert", action="store_true", help="evaluate the scripted expert instead")
    p.add_argument(
        "--env", help=f"env id for --expert (default {DEFAULT_ENV}); a model's is the one it was trained on"
    )
    p.add_argument("--episodes", type=int, default=100)
    p.add_argument("--backend", choices=("sim", "emulated", "sitl", "mock"), help="default: as trained (sim)")
    add_firmware_option(p)
    p.add_argument("--video", type=path_argument, help="write an MP4 of the first --video-episodes episodes")
    p.add_argument("--video-episodes", type=int, help="episodes in the video (default 3)")
    p.add_argument("--json", type=path_argument, help="write the results as JSON")
    p.add_argument("--seed", type=int, default=10_000, help="seed of the first episode")
    p.add_argument(
        "--record", type=Path, metavar="FILE", help="record every bus transaction (docs/traces.md)"
    )
    p.set_defaults(func=cmd_eval)

    for module in EXTRA_COMMAND_MODULES:
        importlib.import_module(module).register(sub)
    return parser


#: Modules that add subcommands: each has ``register(subparsers)`` and sets ``func``.
EXTRA_COMMAND_MODULES = (
    "bioscara_gym.training.collect",
    "bioscara_gym.training.deploy",
    "bioscara_gym.training.export",
    "bioscara_gym.console.commands",
    "bioscara_gym.console.emulate",
    "bioscara_gym.replay",
    "bioscara_gym.validation.commands",
)


def main(argv: Sequence[str] | None = None) -> int:
    """Entry point of the ``bioscara`` console script."""
    try:  # building the parser imports every command's module: a Ctrl-C there is one line too
        _choose_headless_gl()
        parser = build_parser()
    except KeyboardInterrupt:
        print("bioscara: interrupted", file=sys.stderr)
        return EXIT_INTERRUPTED
    args = parser.parse_args(argv)
    # One line per error whatever the width, and the text printed as is (no markup).
    err = Console(stderr=True, highlight=False, markup=False, soft_wrap=True)
    warnings.showwarning = _one_line_warnings(args.command, err, warnings.showwarning)
    raised: list[KeyboardInterrupt] = []
    try:
        with _signals_as_interrupt(raised):
            return int(args.func(args) or 0)
    except CliError as e:
        _last_line(err, f"bioscara {args.command}: error: {e}")
        return e.code
    except KeyboardInterrupt as e:  # Ctrl-C, SIGTERM or SIGHUP: the command cleaned up on the way out
        if isinstance(e, Interrupted):
            _last_line(err, f"bioscara {args.command}: interrupted by {e}")
            return e.exit_code
        _last_line(err, f"bioscara {args.command}: interrupted")
        return EXIT_INTERRUPTED
    except OSError as e:
        _last_line(err, f"bioscara {args.command}: error: {_os_error(e)}")
        return EXIT_ERROR
    except JointError as e:  # refused before anything was sent (2), or went wrong on the arm (3)
        _last_line(err, f"bioscara {args.command}: error: {e}")
        return EXIT_ERROR if is_refusal(e) else EXIT_FAULT
    except (ValueError, MissingExtraError, SitlError) as e:
        _last_line(err, f"bioscara {args.command}: error: {e}")
        return EXIT_ERROR
    except RecursionError:  # a file nested deeper than any of ours; the loaders name the file
        _last_line(err, f"bioscara {args.command}: error: an input file is nested too deeply to be read")
        return EXIT_ERROR
    except Exception as e:
        interrupt = _interrupt_behind(e) or _named_in(e, raised)
        if interrupt is None:
            raise
        # Seen: a signal landing in MuJoCo's import became "ImportError: initialization failed",
        # or, in a ctypes call of its EGL set-up, "ctypes.ArgumentError: argument 1:
        # KeyboardInterrupt" with the interrupt itself gone (no cause, no context).
        by = f" by {interrupt}" if interrupt.args else ""
        _last_line(err, f"bioscara {args.command}: interrupted{by}")
        return interrupt.exit_code if isinstance(interrupt, Interrupted) else EXIT_INTERRUPTED


def _last_line(err: Console, line: str) -> None:
    """Print a command's last line, one line; a terminal gone (EIO) or a reader gone takes nothing."""
    with contextlib.suppress(OSError):
        err.print(one_line(line))


def _named_in(e: BaseException, raised: list[KeyboardInterrupt]) -> KeyboardInterrupt | None:
    """The interrupt raised last if ``e``'s text names its kind, as ctypes does with one it swallowed.

    An error that does not name it is its own (a reviewer's experiment: a
    KeyError after an interrupt the command caught itself, as replay catches
    the signals it replays, was reported "interrupted").
    """
    last = raised[-1] if raised else None
    return last if last is not None and type(last).__name__ in str(e) else None


def _interrupt_behind(e: BaseException) -> KeyboardInterrupt | None:
    """The stop signal an exception was raised while handling (a library's error in its place)."""
    seen: set[int] = set()
    cause: BaseException | None = e
    while cause is not None and id(cause) not in seen:
        if isinstance(cause, KeyboardInterrupt):
            return cause
        seen.add(id(cause))
        cause = cause.__cause__ or cause.__context__
    return None


@contextlib.contextmanager
def _signals_as_interrupt(raised: list[KeyboardInterrupt] | None = None) -> Iterator[None]:
    """The first stop signal interrupts a command; later ones do not interrupt its clean-up.

    By default SIGTERM and SIGHUP (the terminal closed) ended the process at
    once: temporary files stayed behind (``export``, ``eval --video``,
    ``collect``) and ``monitor`` left the joints as they were, where Ctrl-C
    cleans up and makes the arm safe. Now all take that way out
    (``KeyboardInterrupt`` for SIGINT, exit 130; :class:`Interrupted` for
    SIGTERM and SIGHUP, exit 143 and 129; :mod:`bioscara_gym.stop_signals`),
    and a second signal while the command makes the arm safe and removes its
    files is only noted (seen: a second SIGTERM 20 ms after the first left
    ``move``'s joints enabled). ``train`` and ``deploy`` install their own
    guard inside this one. The interrupt raised is appended to ``raised``:
    a library may turn it into an error of its own that keeps no trace of it.
    """
    if threading.current_thread() is not threading.main_thread():
        yield
        return
    signals = caught()

    def noted(signum: int, frame: object) -> None:
        """A signal after the first: the clean-up it interrupted runs to its end."""
        after_signal(signum)

    hook = sys.unraisablehook
    own: list[KeyboardInterrupt] = []  # every interrupt raised here
    swallowed: list[KeyboardInterrupt] = []  # one of them Python ignored

    def interrupt(signum: int, frame: object) -> None:
        for s in signals:
            signal.signal(s, noted)
        after_signal(signum)
        error = KeyboardInterrupt() if signum == signal.SIGINT else Interrupted(signum)
        own.append(error)
        if raised is not None:
            raised.append(error)
        raise error

    def unraisable(info: Any) -> None:
        """One of this guard's interrupts that Python ignored is raised as the command returns.

        Seen: a SIGTERM to ``validate`` landed in a garbage-collector callback
        (a ``WeakSet``'s); Python printed "Exception ignored in ..." and the
        command ran on to its end, exit 1. Now it still runs on (sending the
        signal again from a thread raced with this hook, which ignores
        exceptions too: a reviewer lost the interrupt in 200 of 1500 runs
        under load), but it ends as interrupted, and a second signal
        interrupts it at once.
        """
        if not any(info.exc_value is e for e in own):
            hook(info)
            return
        swallowed.append(info.exc_value)
        for s in signals:
            if signal.getsignal(s) is noted:
                signal.signal(s, interrupt)

    before = {s: signal.signal(s, interrupt) for s in signals}
    sys.unraisablehook = unraisable
    try:
        yield
    finally:
        sys.unraisablehook = hook
        for s, handler in before.items():
            signal.signal(s, handler)
    if swallowed:  # the command returned: it did not stop for the interrupt Python ignored
        raise swallowed[0]


def _os_error(e: OSError) -> str:
    """An ``OSError`` as a user reads it: the message and the file, without ``[Errno N]``."""
    if e.strerror is None:
        return str(e)
    return f"{e.strerror}: {e.filename}" if e.filename is not None else e.strerror


def _choose_headless_gl() -> None:
    """On a machine without a display, have MuJoCo render with EGL, as ``make`` does.

    MuJoCo reads ``MUJOCO_GL`` once, when it is imported, and a command may
    import it (for its env) long before it renders (a video after training):
    the command line is the one place early enough. The library itself sets
    nothing (``bioscara_gym.envs.rendering.prepare`` only when a renderer is made).
    """
    from bioscara_gym.envs.rendering import has_display

    if "MUJOCO_GL" not in os.environ and not has_display():
        os.environ["MUJOCO_GL"] = "egl"


if __name__ == "__main__":
    # Run the module's canonical copy, so exceptions such as CliError raised by
    # subcommand modules are the same classes main() catches.
    from bioscara_gym.cli import main as _main

    sys.exit(_main())
