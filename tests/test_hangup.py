"""SIGHUP: the terminal a command runs in closes (its window, an SSH session that drops).

Found 2026-11-29, run under a pseudo-terminal that was then closed, as a
terminal emulator or ``sshd`` closes it:

- ``monitor`` died at once (killed by SIGHUP): every joint stayed enabled,
  its currents on, and the ``--state`` file's lock stayed behind;
- ``deploy`` died at once with no safe stop and no summary in its run log
  (on the arm the firmware's deadman stops a joint in velocity mode after
  50 ms, with its currents left on; a position move runs on);
- ``emulate dynamixel`` died at once, its link left pointing at a pty gone;
- a refused command whose terminal had gone away without a SIGHUP printed a
  traceback (exit 1) where it meant one line and exit 2: the line could
  not be written.

Now SIGHUP takes Ctrl-C's way out, exit 129, the run log's ``stop_reason``
``hung_up``; under ``nohup`` (SIGHUP ignored) a command runs on.
"""

from __future__ import annotations

import errno
import fcntl
import os
import pty
import select
import signal
import stat
import subprocess
import sys
import termios
import time
from pathlib import Path

import pytest
from rigs import drive_currents, read_log
from test_deploy import REACH, assert_every_joint_disabled

from bioscara_gym.cli import main
from bioscara_gym.stop_signals import after_signal, caught
from bioscara_gym.training.signals import Interrupted, SignalGuard


# ------------------------------------------------------------- in process
def test_sighup_is_caught_unless_ignored_as_nohup_ignores_it(sighup_default: None) -> None:
    assert caught() == (signal.SIGINT, signal.SIGTERM, signal.SIGHUP)
    signal.signal(signal.SIGHUP, signal.SIG_IGN)
    assert caught() == (signal.SIGINT, signal.SIGTERM)
    before = signal.signal(signal.SIGINT, signal.SIG_IGN)  # a shell's background job: still caught
    try:
        assert caught() == (signal.SIGINT, signal.SIGTERM)
    finally:
        signal.signal(signal.SIGINT, before)


def test_the_signal_guard_turns_sighup_into_exit_129(sighup_default: None) -> None:
    with SignalGuard(), pytest.raises(Interrupted) as caught_hup:
        signal.raise_signal(signal.SIGHUP)
    assert (caught_hup.value.exit_code, str(caught_hup.value)) == (129, "SIGHUP")
    signal.signal(signal.SIGHUP, signal.SIG_IGN)
    with SignalGuard() as guard:
        signal.raise_signal(signal.SIGHUP)  # nohup: nothing happens
    assert guard.pending is None


def _is_dev_null(fd: int) -> bool:
    null = os.stat(os.devnull)
    return os.fstat(fd).st_rdev == null.st_rdev and stat.S_ISCHR(os.fstat(fd).st_mode)


def test_after_sighup_only_the_hung_up_terminal_goes_to_dev_null() -> None:
    hung_master, hung = pty.openpty()
    live_master, live = pty.openpty()
    reader, writer = os.pipe()
    try:
        os.close(hung_master)  # the terminal goes away: every request on its other end is EIO
        with pytest.raises(OSError) as gone:
            os.write(hung, b"x")
        assert gone.value.errno == errno.EIO
        after_signal(signal.SIGTERM, fds=(hung,))  # not a hang-up: nothing changes
        with pytest.raises(OSError):
            os.write(hung, b"x")
        after_signal(signal.SIGHUP, fds=(live, writer, hung))  # the hung-up one last: each is looked at
        assert os.write(hung, b"the last line") == 13 and _is_dev_null(hung)
        assert os.isatty(live) and not _is_dev_null(live)
        assert stat.S_ISFIFO(os.fstat(writer).st_mode)
    finally:
        for fd in (hung, live_master, live, reader, writer):
            os.close(fd)


def test_after_sighup_a_failure_to_open_dev_null_raises_nothing(monkeypatch: pytest.MonkeyPatch) -> None:
    # Called from signal handlers: its own error would take the interrupt's place (a reviewer's find).
    hung_master, hung = pty.openpty()
    os.close(hung_master)

    def no_descriptor_left(*args: object) -> int:
        raise OSError(errno.EMFILE, "Too many open files")

    try:
        monkeypatch.setattr(os, "open", no_descriptor_left)
        after_signal(signal.SIGHUP, fds=(hung,))
        monkeypatch.undo()
        with pytest.raises(OSError):  # left as it was
            os.write(hung, b"x")
    finally:
        os.close(hung)


# ------------------------------------------------------------ a real terminal
def _under_a_terminal(
    argv: list[str], cwd: Path, ignore_hup: bool = False
) -> tuple[subprocess.Popen[bytes], int]:
    """``bioscara ARGV`` with a new pseudo-terminal as its controlling terminal; returns it and the master."""
    master, slave = pty.openpty()

    def controlling_terminal() -> None:
        os.setsid()
        fcntl.ioctl(0, termios.TIOCSCTTY, 0)
        signal.signal(signal.SIGHUP, signal.SIG_IGN if ignore_hup else signal.SIG_DFL)

    proc = subprocess.Popen(
        [sys.executable, "-m", "bioscara_gym", *argv],
        cwd=cwd,
        stdin=slave,
        stdout=slave,
        stderr=slave,
        env={**os.environ, "MUJOCO_GL": "egl", "COLUMNS": "100", "LINES": "40"},
        preexec_fn=controlling_terminal,
    )
    os.close(slave)
    return proc, master


def _drain(master: int) -> bytes:
    """What the command wrote to its terminal so far (reading keeps it from blocking on a full one)."""
    out = b""
    while select.select([master], [], [], 0.05)[0]:
        try:
            chunk = os.read(master, 65536)
        except OSError:  # EIO: the command has gone
            break
        if not chunk:
            break
        out += chunk
    return out


def _hang_up_when(proc: subprocess.Popen[bytes], master: int, ready: object, what: str) -> int:
    """Close the terminal once ``ready()`` is true; the command's exit code."""
    try:
        deadline = time.monotonic() + 90
        seen = b""
        while not ready(seen):  # type: ignore[operator]
            seen += _drain(master)
            assert proc.poll() is None, f"the command ended before {what}: {seen[-500:]!r}"
            assert time.monotonic() < deadline, f"never {what}"
        os.close(master)
        return proc.wait(timeout=60)
    finally:
        if proc.poll() is None:
            proc.kill()
            proc.wait()


def test_monitor_whose_terminal_closes_disables_the_joints_and_removes_its_lock(tmp_path: Path) -> None:
    # Seen: killed by SIGHUP at once, the joints left enabled (20/40/20/20 % current), st.json.lock left.
    assert main(["enable", "--state", str(tmp_path / "st.json")]) == 0
    proc, master = _under_a_terminal(["monitor", "--duration", "120", "--state", "st.json"], tmp_path)
    code = _hang_up_when(proc, master, lambda seen: b"quit" in seen, "drew the dashboard")
    assert code == 129
    assert drive_currents(tmp_path / "st.json") == {"j1": 0, "j2": 0, "j3": 0, "j4": 0}
    assert sorted(p.name for p in tmp_path.iterdir()) == ["st.json"]


def deploy_argv(episodes: int) -> list[str]:
    """The scripted expert's Reach deployment on the emulated arm, logged to ``run.jsonl``."""
    return ["deploy", "--expert", "--env", REACH, "--backend", "emulated",
            "--episodes", str(episodes), "--log", "run.jsonl"]  # fmt: skip


def test_deploy_whose_terminal_closes_makes_the_arm_safe_and_says_hung_up(tmp_path: Path) -> None:
    # Seen: killed by SIGHUP at once, no safe stop, the run log without its summary.
    log = tmp_path / "run.jsonl"
    argv = deploy_argv(episodes=1000)

    def twenty_cycles(seen: bytes) -> bool:
        return log.exists() and log.read_text(encoding="utf-8").count('"type":"cycle"') >= 20

    proc, master = _under_a_terminal(argv, tmp_path)
    assert _hang_up_when(proc, master, twenty_cycles, "ran 20 cycles") == 129
    summary = read_log(log)[-1]
    assert (summary["type"], summary["stop_reason"], summary["exit_code"]) == ("summary", "hung_up", 129)
    assert_every_joint_disabled(summary)


def test_under_nohup_a_deploy_runs_on_after_a_sighup(tmp_path: Path) -> None:
    # nohup: SIGHUP ignored, the output in a file (nohup.out), no input.
    log = tmp_path / "run.jsonl"
    argv = deploy_argv(episodes=2)
    with (tmp_path / "nohup.out").open("wb") as out:
        proc = subprocess.Popen(
            [sys.executable, "-m", "bioscara_gym", *argv],
            cwd=tmp_path,
            stdin=subprocess.DEVNULL,
            stdout=out,
            stderr=out,
            env={**os.environ, "MUJOCO_GL": "egl"},
            preexec_fn=lambda: signal.signal(signal.SIGHUP, signal.SIG_IGN),
        )
        try:
            deadline = time.monotonic() + 90
            while not (log.exists() and '"type":"cycle"' in log.read_text(encoding="utf-8")):
                assert proc.poll() is None and time.monotonic() < deadline, "deploy never got going"
                time.sleep(0.05)
            proc.send_signal(signal.SIGHUP)
            assert proc.wait(timeout=90) == 0
        finally:
            if proc.poll() is None:
                proc.kill()
                proc.wait()
    summary = read_log(log)[-1]
    assert (summary["stop_reason"], summary["episodes"], summary["exit_code"]) == ("completed", 2, 0)


def test_a_refusal_whose_terminal_has_gone_is_still_exit_2_not_a_traceback(tmp_path: Path) -> None:
    # Seen: exit 1, a traceback (itself unwritable) where the one line could not be written.
    master, slave = pty.openpty()
    os.close(master)  # gone before the command starts; no SIGHUP: it is not the controlling terminal
    try:
        done = subprocess.run(
            [sys.executable, "-m", "bioscara_gym", "move", "j9", "0"],
            cwd=tmp_path,
            stdin=subprocess.DEVNULL,
            stdout=slave,
            stderr=slave,
            timeout=60,
        )
    finally:
        os.close(slave)
    assert done.returncode == 2


@pytest.mark.parametrize(("parent", "worker"), [("handled", "SIG_DFL"), ("SIG_IGN", "SIG_IGN")])
def test_a_calibration_worker_dies_of_sighup_unless_ignored(parent: str, worker: str) -> None:
    # A forked worker starts with the parent's handlers: the CLI's would raise its interrupt there.
    code = f"""
import signal
from bioscara_gym.validation.calibrate import _worker_signals
signal.signal(signal.SIGHUP, {"lambda *a: None" if parent == "handled" else "signal.SIG_IGN"})
_worker_signals()
print(*(getattr(h, "name", "handled") for h in map(signal.getsignal, (2, 15, 1))))
"""
    done = subprocess.run([sys.executable, "-c", code], capture_output=True, text=True, timeout=60)
    assert done.stdout.split() == ["SIG_IGN", "SIG_DFL", worker], done.stderr


def test_an_emulator_whose_terminal_closes_removes_its_link(tmp_path: Path) -> None:
    # Before: killed by SIGHUP, the link left pointing at a pty that was gone.
    proc, master = _under_a_terminal(["emulate", "dynamixel", "--ids", "1", "--link", "dxl"], tmp_path)
    assert _hang_up_when(proc, master, lambda seen: b"Ctrl-C stops" in seen, "served") == 0
    assert list(tmp_path.iterdir()) == []
