"""Console requests refused for their arguments touch nothing, and what the console writes.

Findings of a hostile test (2026-11-29), each a case here:

- a refused ``move``, ``gripper``, ``enable``... opened the session first: its
  ``--record`` trace held 12 transactions (PING and two reads per joint),
  and its ``--state`` file and a ``.lock`` beside it were created;
- ``--state nodir/x.json`` made the folder ``nodir``; a ``.lock`` file stayed
  beside every state path after the command;
- ``reboot gripper`` said "the gripper has no homing";
- every atomic write left its file at 0600 (tempfile's), also over a 0644 file;
- a state file whose ``max_velocity`` was NaN or negative was used.

In process through ``bioscara_gym.cli.main``, as ``tests/test_console.py``.
"""

from __future__ import annotations

import contextlib
import errno
import json
import os
import stat
from collections.abc import Callable, Iterator
from pathlib import Path

import pytest

from bioscara_gym import fsutil
from bioscara_gym.console.state import lock_path
from bioscara_gym.fsutil import LockFile, atomic_open, atomic_write_bytes, atomic_write_text

#: ``bioscara ARGS`` -> exit code, stdout, stderr (whitespace joined).
Run = Callable[..., tuple[int, str, str]]

REBOOT_J1 = (
    "j1: the emulated backend's joints have no REBOOT; only Dynamixel joints do "
    "(power-cycle a Bioscara joint instead)"
)
UNKNOWN_GROUP = "unknown joint or group 'j9'; joints: j1, j2, j3, j4, gripper; groups: all, arm, gripper"

#: Requests refused for their arguments, and the line each prints.
REFUSED = [
    (
        ["move", "j1", "9"],
        "bioscara move: error: j1: 9 rad is outside the joint limits [-3.04647, 3.04647] rad",
    ),
    (["move", "j2", "nan"], "bioscara move: error: j2: nan m is outside the joint limits [-0.0016, 0.338] m"),
    (  # seen: "the following arguments are required: VALUE" (Python 3.11 took -5e1 for an option)
        ["move", "j1", "-5e1"],
        "bioscara move: error: j1: -50 rad is outside the joint limits [-3.04647, 3.04647] rad",
    ),
    (
        ["gripper", "-1e-2"],
        "bioscara gripper: error: gripper: width -0.01 m is outside the limits [0.04, 0.12] m",
    ),
    (["move", "j9", "0"], "bioscara move: error: unknown joint 'j9'; known joints: j1, j2, j3, j4"),
    (["gripper", "5"], "bioscara gripper: error: gripper: width 5 m is outside the limits [0.04, 0.12] m"),
    (["enable", "j9"], f"bioscara enable: error: {UNKNOWN_GROUP}"),
    (["disable", "j9"], f"bioscara disable: error: {UNKNOWN_GROUP}"),
    (["home", "j9"], f"bioscara home: error: {UNKNOWN_GROUP}"),
    (["home", "j9", "--abort"], f"bioscara home: error: {UNKNOWN_GROUP}"),
    (
        ["home", "gripper"],
        "bioscara home: error: gripper: the gripper has no homing; name a joint or a group of joints",
    ),
    (["reboot", "j1"], f"bioscara reboot: error: {REBOOT_J1}"),
    (["reboot", "arm"], f"bioscara reboot: error: {REBOOT_J1}"),
    (
        ["reboot", "gripper"],
        "bioscara reboot: error: gripper: the gripper has no REBOOT (only Dynamixel joints have one); "
        "name a joint or a group of joints",
    ),
]
REFUSED_IDS = ["-".join(argv) for argv, _ in REFUSED]


@contextlib.contextmanager
def umask(mask: int) -> Iterator[None]:
    """Run the block under ``mask``."""
    before = os.umask(mask)
    try:
        yield
    finally:
        os.umask(before)


def mode(path: Path) -> int:
    """The permission bits of ``path``."""
    return stat.S_IMODE(path.stat().st_mode)


# ------------------------------------------- refused before the session opens
@pytest.mark.parametrize(("argv", "line"), REFUSED, ids=REFUSED_IDS)
def test_a_refused_request_records_no_transaction(
    bioscara: Run, tmp_path: Path, argv: list[str], line: str
) -> None:
    # Seen: 12 transactions (PING to 0x11-0x14, reads of 0x18 and 0x2C) before the refusal.
    trace = tmp_path / "t.jsonl"
    code, out, err = bioscara(*argv, "--record", str(trace))
    assert (code, out, err) == (2, "", line)
    assert not trace.exists()


@pytest.mark.parametrize(("argv", "line"), REFUSED, ids=REFUSED_IDS)
def test_a_refused_request_creates_no_state_file_and_no_lock(
    bioscara: Run, tmp_path: Path, argv: list[str], line: str
) -> None:
    # Seen: a 9.4 kB state file and its .lock, made by the refused command.
    code, out, err = bioscara(*argv, "--state", str(tmp_path / "new.json"))
    assert (code, out, err) == (2, "", line)
    assert list(tmp_path.iterdir()) == []


def test_a_refused_request_leaves_a_state_file_and_a_trace_as_they_were(
    bioscara: Run, tmp_path: Path
) -> None:
    state, trace = tmp_path / "arm.json", tmp_path / "t.jsonl"
    assert bioscara("enable", "--state", str(state), "--record", str(trace))[0] == 0
    saved, recorded = state.read_bytes(), trace.read_bytes()
    code, _, err = bioscara("move", "j1", "9", "--state", str(state), "--record", str(trace))
    assert code == 2
    assert err == "bioscara move: error: j1: 9 rad is outside the joint limits [-3.04647, 3.04647] rad"
    assert (state.read_bytes(), trace.read_bytes()) == (saved, recorded)
    assert sorted(p.name for p in tmp_path.iterdir()) == ["arm.json", "t.jsonl"]


def test_a_request_refused_for_the_arms_state_creates_no_state_file(bioscara: Run, tmp_path: Path) -> None:
    # Not enabled is known only once the arm is read; still no file is left behind.
    code, _, err = bioscara("move", "j1", "1", "--state", str(tmp_path / "new.json"))
    assert code == 2
    assert err == "bioscara move: error: j1: not enabled; run `bioscara enable j1` first"
    assert list(tmp_path.iterdir()) == []


def test_a_refused_argument_is_named_before_a_held_state_file(bioscara: Run, tmp_path: Path) -> None:
    state = tmp_path / "arm.json"
    with LockFile(lock_path(state)):
        code, _, err = bioscara("gripper", "5", "--state", str(state))
    assert code == 2
    assert err == "bioscara gripper: error: gripper: width 5 m is outside the limits [0.04, 0.12] m"


def test_reboot_of_the_gripper_on_dynamixel_names_reboot(bioscara: Run, tmp_path: Path) -> None:
    # Seen: "gripper: the gripper has no homing; name a joint or a group of joints".
    code, out, err = bioscara("reboot", "gripper", "--backend", "dynamixel-emulated")
    assert (code, out) == (2, "")
    assert err == (
        "bioscara reboot: error: gripper: the gripper has no REBOOT (only Dynamixel joints have one); "
        "name a joint or a group of joints"
    )


def test_a_valid_move_still_runs_after_its_check(bioscara: Run, tmp_path: Path) -> None:
    state = tmp_path / "arm.json"
    assert bioscara("enable", "--state", str(state))[0] == 0
    assert bioscara("home", "j4", "--state", str(state))[0] == 0
    code, out, _ = bioscara("move", "j4", "1.0", "--state", str(state))
    assert code == 0
    assert out.startswith("j4 at +1.0000 rad (target +1.0000)")


# ----------------------------------------------------- state path, lock file
def test_a_state_file_in_a_missing_folder_is_refused_not_made(bioscara: Run, tmp_path: Path) -> None:
    # Seen: --state nodir/x.json made the folder nodir.
    state = tmp_path / "nodir" / "x.json"
    code, out, err = bioscara("status", "--state", str(state))
    assert (code, out) == (2, "")
    assert err == f"bioscara status: error: state file {state}: folder {tmp_path / 'nodir'} does not exist"
    assert list(tmp_path.iterdir()) == []


def test_the_lock_file_is_removed_when_the_command_ends(bioscara: Run, tmp_path: Path) -> None:
    state = tmp_path / "arm.json"
    assert bioscara("enable", "j1", "--state", str(state))[0] == 0
    assert bioscara("status", "--state", str(state))[0] == 0
    assert [p.name for p in tmp_path.iterdir()] == ["arm.json"]


def test_the_lock_file_is_removed_when_the_state_file_is_refused(bioscara: Run, tmp_path: Path) -> None:
    # Seen: rec_copy.csv.lock beside a recording given as --state.
    state = tmp_path / "rec_copy.csv"
    state.write_text("t,q\n0,1\n")
    code, _, err = bioscara("status", "--state", str(state))
    assert code == 2
    assert err.startswith(f"bioscara status: error: state file {state} cannot be read")
    assert [p.name for p in tmp_path.iterdir()] == ["rec_copy.csv"]
    assert state.read_text() == "t,q\n0,1\n"


def test_a_lock_file_this_command_did_not_make_is_left(bioscara: Run, tmp_path: Path) -> None:
    state = tmp_path / "arm.json"
    lock_path(state).write_text("")
    assert bioscara("status", "--state", str(state))[0] == 0
    assert lock_path(state).exists()


def test_a_lock_file_removed_by_its_holder_is_never_held_by_two(
    tmp_path: Path, monkeypatch: pytest.MonkeyPatch
) -> None:
    # The race removal opens: B opens the lock file, its holder A removes it and lets go,
    # B locks the removed file while C makes and locks a new one. B must see and start again.
    path = tmp_path / "s.json.lock"
    a, b, c = LockFile(path), LockFile(path), LockFile(path)
    a.acquire()
    real_open = os.open

    def open_then_holder_lets_go(name: object, flags: int, *args: object) -> int:
        fd = real_open(name, flags, *args)  # type: ignore[arg-type]
        if a.held and Path(os.fspath(name)) == path:  # type: ignore[arg-type]
            a.release()
        return fd

    monkeypatch.setattr(os, "open", open_then_holder_lets_go)
    b.acquire()
    monkeypatch.setattr(os, "open", real_open)
    try:
        assert os.stat(path).st_ino == os.fstat(b._fd).st_ino  # type: ignore[arg-type]
        with pytest.raises(BlockingIOError):
            c.acquire()
        assert c.holder() == os.getpid()
    finally:
        b.release()
    assert not path.exists()


# ---------------------------------------------------------------- file modes
def test_an_atomic_write_keeps_the_mode_of_the_file_it_replaces(tmp_path: Path) -> None:
    # Seen: `calibrate --out my.yaml` over a 0644 configuration left it 0600.
    path = tmp_path / "my.yaml"
    for before in (0o644, 0o600, 0o755):
        path.write_text("old")
        path.chmod(before)
        with umask(0o077):
            atomic_write_text(path, "new")
        assert (path.read_text(), mode(path)) == ("new", before)


@pytest.mark.parametrize(("mask", "expected"), [(0o022, 0o644), (0o027, 0o640), (0o002, 0o664)])
def test_an_atomic_write_gives_a_new_file_the_mode_open_would(
    tmp_path: Path, mask: int, expected: int
) -> None:
    path = tmp_path / "new.json"
    with umask(mask):
        atomic_write_bytes(path, b"{}")
        with atomic_open(tmp_path / "other.bin") as f:
            f.write(b"x")
    assert (mode(path), mode(tmp_path / "other.bin")) == (expected, expected)
    assert sorted(p.name for p in tmp_path.iterdir()) == ["new.json", "other.bin"]


def test_an_atomic_write_through_a_symlink_keeps_its_targets_mode(tmp_path: Path) -> None:
    target, link = tmp_path / "target.json", tmp_path / "link.json"
    target.write_text("old")
    target.chmod(0o640)
    link.symlink_to(target)
    with umask(0o077):
        atomic_write_text(link, "new")
    assert link.is_symlink() and target.read_text() == "new" and mode(target) == 0o640


def test_the_temporary_file_of_a_write_is_cleared_when_it_fails(tmp_path: Path) -> None:
    path = tmp_path / "x.json"
    path.write_text("old")
    with pytest.raises(KeyboardInterrupt), atomic_open(path) as f:
        f.write(b"half")
        raise KeyboardInterrupt
    assert [p.name for p in tmp_path.iterdir()] == ["x.json"] and path.read_text() == "old"


def test_a_temporary_name_taken_is_skipped(tmp_path: Path, monkeypatch: pytest.MonkeyPatch) -> None:
    names = iter(["aaaa", "aaaa", "bbbb"])
    monkeypatch.setattr(fsutil.secrets, "token_hex", lambda n: next(names))
    path = tmp_path / "x"
    fd1, tmp1 = fsutil.temporary_beside(path)
    fd2, tmp2 = fsutil.temporary_beside(path)
    os.close(fd1)
    os.close(fd2)
    assert (Path(tmp1).name, Path(tmp2).name) == (".x.aaaa.tmp", ".x.bbbb.tmp")


def test_the_console_state_file_keeps_its_mode(bioscara: Run, tmp_path: Path) -> None:
    state = tmp_path / "arm.json"
    with umask(0o022):
        assert bioscara("enable", "j1", "--state", str(state))[0] == 0
    assert mode(state) == 0o644
    state.chmod(0o664)
    with umask(0o077):
        assert bioscara("disable", "j1", "--state", str(state))[0] == 0
    assert mode(state) == 0o664


# ------------------------------------------------------- state file values
@pytest.mark.parametrize("value", [-2700.0, 0.0, float("nan")], ids=["signed", "zero", "nan"])
def test_a_state_keeps_any_max_velocity_the_firmware_takes(
    bioscara: Run, tmp_path: Path, value: float
) -> None:
    # The firmware stores SETMAXVELOCITY's float as sent (the library takes its
    # magnitude later); the arm's original driver sends j2's signed (-2700, issue #23).
    state = tmp_path / "arm.json"
    assert bioscara("enable", "--state", str(state))[0] == 0
    doc = json.loads(state.read_text())
    doc["firmware"]["j2"]["max_velocity"] = value
    state.write_text(json.dumps(doc))
    code, _, err = bioscara("status", "--state", str(state))
    assert (code, err) == (0, "")


@pytest.mark.parametrize("target", ["missing.json", "notes.txt"])
def test_a_lock_path_that_is_a_symlink_is_one_line_not_a_hang(
    bioscara: Run, tmp_path: Path, target: str
) -> None:
    # Seen (a reviewer): a dangling symlink as arm.json.lock span at 100 % CPU for ever.
    state = tmp_path / "arm.json"
    (tmp_path / "notes.txt").write_text("mine")
    (tmp_path / "arm.json.lock").symlink_to(tmp_path / target)
    code, _, err = bioscara("status", "--state", str(state))
    assert code == 2
    assert err == (
        f"bioscara status: error: cannot lock state file {state}: {tmp_path / 'arm.json.lock'}: "
        "a symlink; a lock file must be a plain file"
    )
    assert (tmp_path / "notes.txt").read_text() == "mine" and not (tmp_path / "missing.json").exists()


def test_a_lock_file_that_keeps_vanishing_gives_up_with_one_error(
    tmp_path: Path, monkeypatch: pytest.MonkeyPatch
) -> None:
    # There on the exclusive create, gone on the plain open, every round: acquire must
    # not spin for ever (the rounds are bounded), and says why.
    rounds = []

    def flaky_open(path: object, flags: int, mode: int = 0o777) -> int:
        rounds.append(flags & os.O_EXCL)
        raise FileExistsError if flags & os.O_EXCL else FileNotFoundError

    monkeypatch.setattr(fsutil.os, "open", flaky_open)
    lock = LockFile(tmp_path / "arm.json.lock")
    with pytest.raises(OSError) as e:
        lock.acquire()
    assert (e.value.errno, e.value.strerror) == (errno.EAGAIN, "it keeps being made and removed")
    assert len(rounds) == 2 * 1000 and not lock.held
