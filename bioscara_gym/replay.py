"""``bioscara replay FILE``: run a recorded command again against its recorded bus replies.

Each session of a trace (``docs/traces.md``) names the command that made it
and its arguments. Replay runs that command again, with the real
:class:`~bioscara_gym.hardware.joint.Joint` drivers, on the backend it was
recorded on, but with a :class:`~bioscara_gym.hardware.recording.ReplayBus`
in place of the bus: every transaction must write exactly the recorded bytes
in the recorded order, and gets the recorded reply (or error) back.

=============  =================================================================
recorded on    replayed on
=============  =================================================================
``emulated``   the emulated backend (its simulation paces time as recorded, and
               ``reset`` poses the arm as recorded), joints on the replay bus
``i2c``        the ``i2c`` backend on the replay bus, a
               :class:`~bioscara_gym.hardware.recording.ReplayClock` that follows
               the recorded times, and a mock gripper (no sysfs)
=============  =================================================================

Everything a command writes besides the bus (run log, gripper and console
state files) goes to a temporary directory; its output is not shown. Exit
codes: 0 every transaction matched, 1 a mismatch (or a trace that cannot be
replayed), 2 a trace that cannot be read, or that was cut (a session without
its closing line that the driver goes on past: the recorder was killed, the
disk filled, or the file was truncated, so nothing can be said of the driver).
"""

from __future__ import annotations

import argparse
import contextlib
import dataclasses
import io
import json
import os
import signal
import tempfile
import threading
import warnings
from collections.abc import Callable, Iterator
from dataclasses import dataclass
from pathlib import Path
from typing import Any

import yaml

from bioscara_gym.errors import EXIT_ERROR, one_line
from bioscara_gym.hardware.backends import mock_gripper
from bioscara_gym.hardware.config import config_from_dict
from bioscara_gym.hardware.recording import (
    ReplayBus,
    ReplayClock,
    TraceCut,
    TraceError,
    TraceMismatch,
    TraceSession,
    describe,
    read_trace,
)
from bioscara_gym.stop_signals import STOP_SIGNALS
from bioscara_gym.training.signals import Interrupted

#: Exit code of a trace the driver does not follow.
EXIT_MISMATCH = 1
#: Console commands a trace can replay (``monitor`` is paced by the wall clock and keys).
CONSOLE_COMMANDS = ("status", "ping", "enable", "disable", "home", "move", "gripper", "reboot")


class ReplayError(Exception):
    """A session that cannot be replayed (its command is not one replay can run)."""


@dataclass
class SessionResult:
    """How one session's replay went.

    Attributes:
        command: The recorded command.
        matched: Transactions served as recorded.
        recorded: Transactions in the session.
        errors_replayed: Recorded bus errors raised again to the driver.
        mismatch: The first difference, or ``None``.
        cut_off: The driver went on past the end of a session that was cut
            (no closing line): the trace is damaged, nothing is said of the driver.
        stopped_early: The driver stopped with recorded transactions left.
        error: What the replayed command raised, if anything (a recorded
            safety stop raises as it did, a recorded signal interrupts it
            again; only the bytes are judged).
    """

    command: str
    matched: int
    recorded: int
    errors_replayed: int
    mismatch: TraceMismatch | None = None
    cut_off: TraceCut | None = None
    stopped_early: bool = False
    error: BaseException | None = None

    @property
    def ok(self) -> bool:
        """Whether every recorded transaction, and nothing else, was sent."""
        return self.mismatch is None and self.cut_off is None and not self.stopped_early


@dataclass
class ReplayResult:
    """How a trace's replay went: one result per session, up to the first that failed.

    Attributes:
        sessions: The sessions replayed.
    """

    sessions: list[SessionResult]

    @property
    def ok(self) -> bool:
        """Whether every session matched."""
        return all(s.ok for s in self.sessions)

    @property
    def matched(self) -> int:
        """Transactions matched over all sessions."""
        return sum(s.matched for s in self.sessions)

    @property
    def errors_replayed(self) -> int:
        """Recorded bus errors raised again over all sessions."""
        return sum(s.errors_replayed for s in self.sessions)


# ---------------------------------------------------------------- backends
def _backend_options(session: TraceSession, bus: ReplayBus, config: Any) -> dict[str, object]:
    """The options that put the replay bus (and, for ``i2c``, its clock) under the recorded backend."""
    if session.backend == "emulated":
        return {"wrap_bus": bus.bind}
    if session.backend == "i2c":
        clock = ReplayClock(float(session.header.get("t0", 0.0)))
        bus.clock = clock
        return {"bus": bus, "clock": clock, "gripper": mock_gripper(config)}
    raise ReplayError(f"backend {session.backend!r} cannot be replayed; traces come from i2c or emulated")


def _paths(args: dict[str, Any], keys: tuple[str, ...]) -> None:
    """Recorded paths (strings in the header) back to ``Path`` objects."""
    for key in keys:
        if args.get(key) is not None:
            args[key] = Path(args[key])


# ---------------------------------------------------------------- commands
def _run_deploy(args: dict[str, Any], options: dict[str, object], tmp: Path) -> None:
    from rich.console import Console

    from bioscara_gym.errors import DeployError
    from bioscara_gym.training.deploy import DeployArgs, Deployment

    known = {f.name for f in dataclasses.fields(DeployArgs)}
    args = {k: v for k, v in args.items() if k in known}
    _paths(args, ("model", "onnx", "config", "log", "state_file", "record"))
    args.update(log=tmp / "deploy.jsonl", state_file=None, faults=None, realtime=False, record=None)

    with contextlib.suppress(DeployError):  # a recorded safety stop ends the replay the same way
        Deployment(DeployArgs(**args), console=Console(file=io.StringIO()), backend_options=options).run()


def _run_eval(args: dict[str, Any], options: dict[str, object], tmp: Path) -> None:
    from bioscara_gym.training.evaluate import evaluate_expert, evaluate_model

    if args.get("expert"):
        from bioscara_gym.cli import DEFAULT_ENV
        from bioscara_gym.training.metadata import resolve_env_id

        evaluate_expert(
            resolve_env_id(args.get("env") or DEFAULT_ENV),  # None: eval's default
            args["episodes"],
            args.get("backend") or "sim",
            None,
            args["seed"],
            backend_options=options,
        )
    else:
        evaluate_model(
            Path(args["model"]), args["episodes"], args.get("backend"), None, args["seed"], 0, options
        )


def _console_runner(command: str) -> Callable[[dict[str, Any], dict[str, object], Path], None]:
    def run(args: dict[str, Any], options: dict[str, object], tmp: Path) -> None:
        from bioscara_gym.console import commands

        _paths(args, ("config", "state", "record"))
        if args.get("state") is not None:
            args["state"] = tmp / "state.json"
        ns = argparse.Namespace(**{**args, "record": None, "backend_options": options, "command": command})
        getattr(commands, f"cmd_{command}")(ns)

    return run


RUNNERS: dict[str, Callable[[dict[str, Any], dict[str, object], Path], None]] = {
    "deploy": _run_deploy,
    "eval": _run_eval,
    **{c: _console_runner(c) for c in CONSOLE_COMMANDS},
}


@contextlib.contextmanager
def _quiet() -> Iterator[None]:
    """Hide what the replayed command prints and warns."""
    with (
        contextlib.redirect_stdout(io.StringIO()),
        contextlib.redirect_stderr(io.StringIO()),
        warnings.catch_warnings(),
    ):
        warnings.simplefilter("ignore")
        yield


def replay_session(session: TraceSession) -> SessionResult:
    """Run one recorded session's command again against its recorded replies.

    Raises:
        ReplayError: The session's command or backend cannot be replayed.
    """
    runner = RUNNERS.get(session.command)
    if runner is None:
        why = (
            " (its refresh count follows the wall clock and the keys)" if session.command == "monitor" else ""
        )
        raise ReplayError(f"a {session.command or 'bare'!r} session cannot be replayed{why}")
    bus = ReplayBus(session)
    config = config_from_dict(session.header["config"], "the trace's header")
    options = _backend_options(session, bus, config)
    with tempfile.TemporaryDirectory(prefix="bioscara-replay-") as tmp_name:
        tmp = Path(tmp_name)
        args = dict(session.header["args"])
        for key in ("episodes", "seed"):  # a hand-edited header (--unchecked): said, not a TypeError
            value = args.get(key)
            if value is not None and (isinstance(value, bool) or not isinstance(value, int)):
                raise ReplayError(f"the trace's header gives {key} {value!r}; expected a whole number")
        config_path = tmp / "config.yaml"
        config_path.write_text(yaml.safe_dump(dict(session.header["config"])), encoding="utf-8")
        args["config"] = str(config_path)
        state = session.header.get("context", {}).get("state")
        if state is not None:
            (tmp / "state.json").write_text(json.dumps(state), encoding="utf-8")
        error = None
        with _quiet(), _own_stop_handlers():
            try:
                bus.start()
                runner(args, options, tmp)
            except Exception as e:  # what the command made of the replies is not the question
                error = e
            except KeyboardInterrupt as e:
                if not bus.signals_delivered:
                    raise  # a Ctrl-C of this replay, not a recorded one
                error = e
    return SessionResult(
        command=session.command,
        matched=bus.served,
        recorded=len(session.transactions),
        errors_replayed=bus.errors_served,
        mismatch=bus.mismatch,
        cut_off=bus.cut_off,
        stopped_early=bus.mismatch is None and bus.remaining > 0,
        error=error,
    )


def replay(
    path: str | Path,
    on_session: Callable[[SessionResult], None] | None = None,
    check_digests: bool = True,
) -> ReplayResult:
    """Replay every session of a trace, in order, up to the first that does not match.

    ``check_digests=False`` replays a hand-made or hand-edited trace (lines
    without digests, or whose digests no longer match).

    Raises:
        TraceError: The trace cannot be read, or a line was changed after recording.
        ReplayError: A session's command or backend cannot be replayed.
    """
    results = []
    for session in read_trace(path, check_digests):
        result = replay_session(session)
        results.append(result)
        if on_session is not None:
            on_session(result)
        if not result.ok:
            break
    return ReplayResult(results)


def _explain(result: SessionResult, session_no: int, sessions: list[TraceSession]) -> str:
    """One line on the first failure of a session."""
    head = f"session {session_no} ({result.command})"
    if result.mismatch is not None:
        return f"{head}: mismatch at {result.mismatch}"
    nxt = sessions[session_no - 1].transactions[result.matched]
    ended = (
        ""
        if result.error is None
        else f" (the command ended with {type(result.error).__name__}: {result.error})"
    )
    return (
        f"{head}: the driver stopped after {result.matched} of {result.recorded} transactions{ended}; "
        f"transaction {result.matched} (trace line {nxt.line}) was {describe(nxt.request)}"
    )


def cmd_replay(args: argparse.Namespace) -> int:
    """``bioscara replay FILE``: 0 when every transaction matched, else the first mismatch."""
    from rich.console import Console

    out = Console(highlight=False, markup=False, soft_wrap=True)
    err = Console(stderr=True, highlight=False, markup=False, soft_wrap=True)
    check = not getattr(args, "unchecked", False)
    with _stop_signals_received() as received:
        try:
            sessions = read_trace(args.file, check)
            result = replay(args.file, check_digests=check)
        except TraceError as e:
            err.print(one_line(f"bioscara replay: error: {e}"))
            return EXIT_ERROR
        except (ReplayError, ValueError) as e:
            err.print(one_line(f"bioscara replay: error: {args.file}: {e}"))
            return EXIT_MISMATCH
        signum = received()
    if signum is not None and not result.ok:
        # The replayed command stopped for this replay's own stop signal (a deploy's safe
        # stop sends what the trace has not): no difference of the driver's. Seen: "mismatch", exit 1.
        raise KeyboardInterrupt if signum == signal.SIGINT else Interrupted(signum)
    if result.ok:
        n = len(result.sessions)
        out.print(f"{result.matched} transactions matched ({n} session{'s' if n != 1 else ''})")
        return 0
    failed = result.sessions[-1]
    if failed.cut_off is not None:  # the trace's damage, not the driver's: no count of matches
        where = f"session {len(result.sessions)} ({failed.command})"
        err.print(one_line(f"bioscara replay: error: {args.file}: {where} {failed.cut_off}"))
        return EXIT_ERROR
    out.print(f"{result.matched} transactions matched before the first difference")
    err.print(one_line(f"bioscara replay: {args.file}: {_explain(failed, len(result.sessions), sessions)}"))
    return EXIT_MISMATCH


@contextlib.contextmanager
def _own_stop_handlers() -> Iterator[None]:
    """The stop signals' handlers as they were before a session, whatever it did to them.

    A recorded signal calls the installed handler; the CLI's turns every later
    signal into a note (seen: a real Ctrl-C ignored for the rest of the replay).
    During the session SIGHUP is at its default, not ignored: a replay run
    under ``nohup`` left the recorded SIGHUP to no handler, and the replayed
    deploy ran on past where the recorded one stopped (a reviewer's find).
    """
    if threading.current_thread() is not threading.main_thread():
        yield
        return
    before = {s: signal.getsignal(s) for s in STOP_SIGNALS}
    if before[signal.SIGHUP] == signal.SIG_IGN:
        signal.signal(signal.SIGHUP, signal.SIG_DFL)
    try:
        yield
    finally:
        for s, handler in before.items():
            signal.signal(s, handler)


@contextlib.contextmanager
def _stop_signals_received() -> Iterator[Callable[[], int | None]]:
    """A function telling the first stop signal this process really received in the block.

    Replayed signals call their handlers directly; a real one also writes
    its number to the wakeup file descriptor set here, whichever handler the
    replayed command installed.
    """
    if threading.current_thread() is not threading.main_thread():
        yield lambda: None
        return
    r, w = os.pipe()
    os.set_blocking(r, False)
    os.set_blocking(w, False)
    previous = signal.set_wakeup_fd(w, warn_on_full_buffer=False)

    def first() -> int | None:
        try:
            data = os.read(r, 4096)
        except BlockingIOError:
            return None
        return next((b for b in data if b in STOP_SIGNALS), None)

    try:
        yield first
    finally:
        signal.set_wakeup_fd(previous)
        os.close(r)
        os.close(w)


def register(sub: argparse._SubParsersAction) -> None:
    """Add the ``replay`` subcommand."""
    p = sub.add_parser(
        "replay",
        help="run a recorded bus trace's commands again and check every byte the driver sends",
        description="Replay a trace written with --record: the recorded command runs again against the "
        "recorded replies; exit 0 if the driver sent exactly the recorded bytes in the recorded order, "
        "1 at the first difference (index, expected bytes, bytes sent), 2 if the trace cannot be read, was "
        "cut short (a session without its closing line) or a line was changed after recording (its digest "
        "names it).",
    )
    p.add_argument("file", type=Path, metavar="FILE", help="trace (JSON Lines) written with --record")
    p.add_argument(
        "--unchecked",
        action="store_true",
        help="replay a hand-made or hand-edited trace: lines without digests, or whose digests do not match",
    )
    p.set_defaults(func=cmd_replay)
