"""What ``eval``, ``export``, ``collect`` and ``--record`` write, and what they refuse to write over.

Findings of a hostile test (2026-11-29), each a case here:

- an output path that was a symlink had the link replaced, not written
  through (``eval --json /dev/stdout`` replaced the system's ``/dev/stdout``);
- an output that named an input destroyed it (``export --onnx model.zip``,
  ``eval --json model.zip``, ``--video`` and ``--json`` on one file);
- ``--record`` appended trace lines to any file (a model's ``metadata.json``);
- options a command ignored were taken silently (``eval --model --env``
  another env, ``--video-episodes`` without ``--video``);
- SIGTERM ended ``eval``, ``export``, ``collect`` and ``monitor`` at once,
  leaving temporary files and, in ``monitor``, the joints as they were.

Every refusal here comes before an env is made, so no model is trained:
a ``metadata.json`` beside a placeholder ``model.zip`` is enough.
"""

from __future__ import annotations

import contextlib
import errno
import json
import os
import signal
import stat
import subprocess
import sys
import time
import weakref
from collections.abc import Callable
from pathlib import Path

import numpy as np
import pytest
from rigs import drive_currents, one_line_error

from bioscara_gym.cli import main
from bioscara_gym.fsutil import atomic_write_text, output_clash, output_problem, read_json, replaced_path
from bioscara_gym.hardware.recording import TRACE_FORMAT, Recording

REACH = "Bioscara-Reach-v0"



@pytest.fixture
def run(tmp_path: Path, monkeypatch: pytest.MonkeyPatch) -> Path:
    """A run folder whose metadata says Reach; its ``model.zip`` is a placeholder never loaded."""
    monkeypatch.chdir(tmp_path)
    folder = tmp_path / "run"
    folder.mkdir()
    (folder / "model.zip").write_bytes(b"not loaded")
    kwargs = {"control_mode": "cartesian", "control_freq": 25}
    metadata = {"env_id": REACH, "env_kwargs": kwargs, "observation_space": {}, "action_space": {}}
    (folder / "metadata.json").write_text(json.dumps(metadata), encoding="utf-8")
    return folder


def _unchanged(run: Path) -> None:
    assert (run / "model.zip").read_bytes() == b"not loaded"
    assert json.loads((run / "metadata.json").read_text(encoding="utf-8"))["env_id"] == REACH


# ------------------------------------------------------------------ symlinks
def test_a_write_through_a_symlink_replaces_its_target_and_keeps_the_link(tmp_path: Path) -> None:
    target, link = tmp_path / "target.json", tmp_path / "link.json"
    target.write_text("old", encoding="utf-8")
    link.symlink_to(target)
    assert replaced_path(link) == target
    atomic_write_text(link, "new")
    assert link.is_symlink() and os.readlink(link) == str(target)
    assert target.read_text(encoding="utf-8") == "new"
    assert replaced_path(target) == target  # a plain file is itself


def test_a_dangling_symlink_is_written_through_to_where_it_points(tmp_path: Path) -> None:
    link = tmp_path / "link.json"
    link.symlink_to(tmp_path / "made.json")
    atomic_write_text(link, "x")
    assert link.is_symlink() and (tmp_path / "made.json").read_text(encoding="utf-8") == "x"


def test_a_video_through_a_symlink_keeps_the_link(tmp_path: Path) -> None:
    from bioscara_gym.training.evaluate import video_writer

    link, target = tmp_path / "v.gif", tmp_path / "real.gif"
    link.symlink_to(target)
    with video_writer(link, fps=5) as sink:
        assert sink is not None
        sink(np.zeros((16, 16, 3), dtype=np.uint8))
        sink(np.full((16, 16, 3), 255, dtype=np.uint8))
    assert link.is_symlink() and target.stat().st_size > 0
    from PIL import Image

    with Image.open(target) as gif:  # 5 frames a second: 200 ms each
        assert (gif.n_frames, gif.info["duration"]) == (2, 200)
    assert sorted(p.name for p in tmp_path.iterdir()) == ["real.gif", "v.gif"]  # no temporary file


def test_a_webm_video_is_written_as_vp9(tmp_path: Path) -> None:
    # Seen: ffmpeg's default H.264 is no WebM codec: 13 lines of errors and a broken pipe.
    from bioscara_gym.training.evaluate import video_writer

    path = tmp_path / "v.webm"
    with video_writer(path, fps=5) as sink:
        assert sink is not None
        for k in range(3):
            sink(np.full((32, 32, 3), 40 * k, dtype=np.uint8))
    assert path.read_bytes()[:4] == bytes.fromhex("1a45dfa3")  # Matroska/WebM's EBML magic


def test_a_video_gets_the_mode_open_would_give_it(tmp_path: Path) -> None:
    # Seen: every video came out 0600 (tempfile's).
    from bioscara_gym.training.evaluate import video_writer

    mask = os.umask(0o027)
    try:
        with video_writer(tmp_path / "v.gif", fps=5) as sink:
            assert sink is not None
            sink(np.zeros((16, 16, 3), dtype=np.uint8))
    finally:
        os.umask(mask)
    assert stat.S_IMODE((tmp_path / "v.gif").stat().st_mode) == 0o640


# ------------------------------------------------------------ outputs vs inputs
def test_output_clash_names_two_options_on_one_file_and_an_output_that_is_an_input(tmp_path: Path) -> None:
    a, b = tmp_path / "a", tmp_path / "b"
    assert output_clash({"--json": a, "--video": b, "--record": None}, {"--model": tmp_path / "m"}) is None
    assert output_clash({"--json": a, "--video": tmp_path / "x" / ".." / "a"}) == (
        f"--json and --video name the same file {tmp_path / 'x' / '..' / 'a'}; each needs its own"
    )
    b.symlink_to(a)  # one file under two names
    assert output_clash({"--json": b}, {"--model": a}) == (
        f"--json {b} is the --model file; writing it would destroy it"
    )


def test_a_hard_link_to_an_input_is_that_input(tmp_path: Path) -> None:
    # Seen: deploy --log through a hard link to policy.onnx truncated the policy.
    model = tmp_path / "model.zip"
    model.write_bytes(b"m")
    os.link(model, tmp_path / "h.jsonl")
    assert output_clash({"--log": tmp_path / "h.jsonl"}, {"--model": model}) == (
        f"--log {tmp_path / 'h.jsonl'} is the --model file; writing it would destroy it"
    )


def test_a_loop_of_symlinks_is_named_and_never_replaced(tmp_path: Path) -> None:
    # Seen: a RuntimeError traceback from Path.resolve in some commands, the link replaced in others.
    a, b = tmp_path / "a", tmp_path / "b"
    a.symlink_to(b)
    b.symlink_to(a)
    assert output_problem(a) == "is a loop of symlinks"
    assert output_clash({"--json": a}) == f"--json {a} is a loop of symlinks"
    with pytest.raises(OSError) as caught:
        atomic_write_text(a, "x")
    assert (caught.value.errno, caught.value.strerror, caught.value.filename) == (
        errno.ELOOP,
        "is a loop of symlinks",
        str(a),
    )
    assert a.is_symlink() and os.readlink(a) == str(b)


@pytest.mark.parametrize(
    ("argv", "message"),
    [
        (
            ["export", "--model", "run/model.zip", "--onnx", "run/model.zip"],
            "--onnx run/model.zip is the --model file; writing it would destroy it",
        ),
        (
            ["export", "--model", "run/model.zip", "--onnx", "run/metadata.json", "--check", "0"],
            "--onnx run/metadata.json is the policy's metadata.json file; writing it would destroy it",
        ),
        (  # seen: --model as the run's folder let both through, exit 0
            ["export", "--model", "run", "--onnx", "run/model.zip", "--check", "0"],
            "--onnx run/model.zip is the --model file; writing it would destroy it",
        ),
        (
            ["eval", "--model", "run", "--json", "run/metadata.json"],
            "--json run/metadata.json is the policy's metadata.json file; writing it would destroy it",
        ),
        (
            ["export", "--model", "run/model.zip", "--onnx", "p.onnx", "--check", "100001"],
            "--check 100001: at most 100000 observations (each is kept to compare)",
        ),
        (  # seen: "no metadata.json next to nope.zip: cannot tell what the policy was trained for"
            ["export", "--model", "nope.zip", "--onnx", "p.onnx"],
            "no model at nope.zip",
        ),
        (
            ["export", "--model", "dangling.zip", "--onnx", "p.onnx"],
            "no model at dangling.zip (a symlink to gone.zip, not there)",
        ),
        (  # seen: "no model at /dev/zero"
            ["export", "--model", "/dev/zero", "--onnx", "p.onnx"],
            "/dev/zero is not a regular file; give the model.zip",
        ),
        (
            ["eval", "--model", "run/model.zip", "--json", "run/model.zip"],
            "--json run/model.zip is the --model file; writing it would destroy it",
        ),
        (
            ["eval", "--model", "run/model.zip", "--record", "run/metadata.json", "--backend", "emulated"],
            "--record run/metadata.json is the policy's metadata.json file; writing it would destroy it",
        ),
        (
            ["eval", "--model", "run/model.zip", "--video", "same.mp4", "--json", "same.mp4"],
            "--json and --video name the same file same.mp4; each needs its own",
        ),
        (
            ["eval", "--model", "run/model.zip", "--env", "Bioscara-Push"],
            f"--env Bioscara-Push: the model was trained on {REACH}, where it is evaluated",
        ),
        (
            ["eval", "--model", "run/model.zip", "--video-episodes", "5"],
            "--video-episodes needs --video (the file to write them to)",
        ),
        (
            ["collect", "--model", "run/model.zip", "--env", "Bioscara-Push", "--dataset", "d"],
            f"--env Bioscara-Push: the model was trained on {REACH}, where it acts",
        ),
        (
            ["collect", "--expert", "--env", "Bioscara-Reach", "--dataset", "d", "--seed", str(2**32 - 2)],
            f"--seed {2**32 - 2}: the episodes' seeds must stay within 0-4294967295",
        ),
        (
            ["collect", "--expert", "--env", "Bioscara-Reach", "--dataset", "a\nb", "--episodes", "1"],
            r"dataset name 'a\nb' is malformed: expected (namespace/)name(-vN), of letters, digits, - and _",
        ),
    ],
    ids=[
        "export-over-the-model",
        "export-over-the-metadata",
        "export-over-the-model-named-by-its-folder",
        "eval-json-over-the-metadata-of-a-model-folder",
        "export-check-beyond-the-cap",
        "export-a-model-not-there",
        "export-a-dangling-symlink",
        "export-a-model-that-is-no-file",
        "eval-json-over-the-model",
        "eval-record-into-the-metadata",
        "eval-json-and-video-one-file",
        "eval-model-on-another-env",
        "eval-video-episodes-without-video",
        "collect-model-on-another-env",
        "collect-seeds-past-32-bits",
        "collect-dataset-name-with-a-newline",
    ],
)
def test_bad_outputs_and_ignored_options_are_refused_before_the_work(
    run: Path, capsys: pytest.CaptureFixture[str], argv: list[str], message: str
) -> None:
    Path("dangling.zip").symlink_to("gone.zip")
    assert main(argv) == 2
    assert one_line_error(capsys, argv[0]) == message
    _unchanged(run)
    assert not Path("p.onnx").exists() and not Path("same.mp4").exists()


#: A file name holding a newline and a terminal's "clear the screen".
HOSTILE_NAME = "/nope/a\nb\x1b[2J"


@pytest.mark.parametrize(
    ("argv", "message"),
    [
        (["status", "--state", HOSTILE_NAME], "state file /nope/a\\nb\\x1b[2J: folder /nope does not exist"),
        (
            ["eval", "--model", HOSTILE_NAME],
            "no metadata.json next to /nope/a\\nb\\x1b[2J: cannot tell what the policy was trained for",
        ),
        (["replay", HOSTILE_NAME], "/nope/a\\nb\\x1b[2J: no such trace file"),
        (
            ["deploy", "--backend", "emulated", "--onnx", HOSTILE_NAME],
            "cannot load /nope/a\\nb\\x1b[2J: No such file or directory",
        ),
        (
            ["move", "j1", "0.1", "--config", HOSTILE_NAME],
            "/nope/a\\nb\\x1b[2J: cannot read config file: No such file or directory",
        ),
    ],
    ids=["status", "eval", "replay", "deploy", "move"],
)
def test_a_file_named_with_control_characters_is_named_on_one_line(
    capsys: pytest.CaptureFixture[str], argv: list[str], message: str
) -> None:
    # Seen: the error split in two at the newline, and the escape sequence reached the terminal.
    assert main(argv) == 2
    assert one_line_error(capsys, argv[0]) == message


@pytest.mark.parametrize(
    "argv",
    [
        ["status", "--config", ""],
        ["move", "j1", "0.1", "--record", ""],
        ["deploy", "--expert", "--env", "Bioscara-Reach", "--config", ""],
        ["validate", "--config", ""],
        ["calibrate", "--config", ""],
        ["train", "--config", ""],
    ],
    ids=["status", "record", "deploy", "validate", "calibrate", "train"],
)
def test_an_empty_config_or_record_path_is_named_empty(
    capsys: pytest.CaptureFixture[str], argv: list[str]
) -> None:
    # Seen (a hostile test): --config '' was ". : cannot read config file: not a regular file".
    with pytest.raises(SystemExit) as done:
        main(argv)
    assert done.value.code == 2
    option = argv[-2]
    assert capsys.readouterr().err == (
        f"bioscara {argv[0]}: error: argument {option}: an empty path; give a file or folder name\n"
    )


def test_the_parsers_own_errors_are_one_line_too(capsys: pytest.CaptureFixture[str]) -> None:
    from bioscara_gym.cli import build_parser

    with pytest.raises(SystemExit) as done:
        build_parser().error("argument --json: cannot write /tmp/a\nb")
    assert done.value.code == 2
    assert capsys.readouterr().err == "bioscara: error: argument --json: cannot write /tmp/a\\nb\n"


def test_collect_refuses_an_empty_datasets_path(
    run: Path, capsys: pytest.CaptureFixture[str], monkeypatch: pytest.MonkeyPatch
) -> None:
    monkeypatch.setenv("MINARI_DATASETS_PATH", "")
    assert main(["collect", "--expert", "--env", "Bioscara-Reach", "--dataset", "d", "--episodes", "1"]) == 2
    message = "MINARI_DATASETS_PATH is empty: unset it (~/.minari/datasets) or name a folder"
    assert one_line_error(capsys, "collect") == message


@pytest.mark.parametrize("episodes", ["0", "-1"])
def test_eval_refuses_a_count_of_episodes_below_one_before_any_backend_is_built(
    run: Path, capsys: pytest.CaptureFixture[str], monkeypatch: pytest.MonkeyPatch, episodes: str
) -> None:
    # Seen (a hostile test): on the sitl backend the firmware was built first (7 s, four
    # libraries cached), and with a firmware that did not build the count was never reported.
    from bioscara_gym.hardware import backends

    def built(*args: object, **kwargs: object) -> None:
        raise AssertionError("a backend was built before the refusal")

    monkeypatch.setattr(backends, "make_backend", built)
    assert main(["eval", "--expert", "--backend", "sitl", "--episodes", episodes]) == 2
    assert one_line_error(capsys, "eval") == f"--episodes must be >= 1, got {episodes}"


def test_eval_expert_without_env_evaluates_reach(
    run: Path, capsys: pytest.CaptureFixture[str], tmp_path: Path
) -> None:
    assert main(["eval", "--expert", "--episodes", "1", "--json", "e.json"]) == 0
    assert f"scripted expert on {REACH}" in capsys.readouterr().out
    assert json.loads(Path("e.json").read_text(encoding="utf-8"))["episodes"] == 1


# --------------------------------------------------------------------- traces
def test_record_refuses_a_file_that_is_not_a_trace_and_takes_a_trace_an_empty_or_a_new_one(
    tmp_path: Path,
) -> None:
    (tmp_path / "notes.txt").write_text("garbage\n", encoding="utf-8")
    (tmp_path / "empty.jsonl").write_bytes(b"")
    header = {"type": "header", "format": TRACE_FORMAT, "version": 2}
    (tmp_path / "trace.jsonl").write_text(json.dumps(header) + "\n", encoding="utf-8")
    (tmp_path / "other.jsonl").write_text(json.dumps({**header, "format": "x"}) + "\n", encoding="utf-8")
    for name in ("empty.jsonl", "trace.jsonl", "new.jsonl"):
        Recording(tmp_path / name, "eval")
    for name in ("notes.txt", "other.jsonl"):
        message = (
            f"--record {tmp_path / name}: exists and is not a bus trace ({TRACE_FORMAT}); "
            "give a new file, or a trace to add to"
        )
        with pytest.raises(ValueError) as caught:
            Recording(tmp_path / name, "eval")
        assert str(caught.value) == message
    with pytest.raises(ValueError, match=r": is not a regular file$"):
        Recording(tmp_path, "eval")
    # Seen (a second hostile pass): only the first line was looked at.
    line = (json.dumps(header) + "\n").encode()
    (tmp_path / "glued.jsonl").write_bytes(line[:-1])  # the next session would be glued onto it
    (tmp_path / "tail.jsonl").write_bytes(line + b"\x00\xff garbage\n")
    (tmp_path / "two.jsonl").write_bytes(line + json.dumps({"type": "tx"}).encode() + b"\n")
    Recording(tmp_path / "two.jsonl", "eval")
    for name, problem in (
        ("glued.jsonl", "does not end with a whole line"),
        ("tail.jsonl", "does not end with a trace's line"),
    ):
        with pytest.raises(ValueError) as caught:
            Recording(tmp_path / name, "eval")
        assert str(caught.value) == (
            f"--record {tmp_path / name}: {problem}; it is no trace a session can be added to"
        )
    assert (tmp_path / "notes.txt").read_text(encoding="utf-8") == "garbage\n"


# -------------------------------------------------------------------- SIGTERM
def _terminated(argv: list[str], cwd: Path, ready: float) -> subprocess.CompletedProcess[str]:
    """``bioscara ARGV`` sent SIGTERM after ``ready`` seconds."""
    env = {**os.environ, "MUJOCO_GL": "egl", "MINARI_DATASETS_PATH": str(cwd / "minari")}
    proc = subprocess.Popen(
        [sys.executable, "-m", "bioscara_gym", *argv],
        cwd=cwd,
        env=env,
        stdout=subprocess.DEVNULL,
        stderr=subprocess.PIPE,
        text=True,
    )
    try:
        time.sleep(ready)
        assert proc.poll() is None, "the command ended before the signal"
        proc.send_signal(signal.SIGTERM)
        _, err = proc.communicate(timeout=60)
    finally:
        proc.kill()
    return subprocess.CompletedProcess(argv, proc.returncode, "", err)


def test_sigterm_stops_eval_as_ctrl_c_does_leaving_no_partial_video(tmp_path: Path) -> None:
    # Seen: exit 143 with nothing said, and a 48-byte hidden .mp4 left behind.
    argv = ["eval", "--expert", "--episodes", "500", "--video", "v/v.mp4", "--video-episodes", "500"]
    done = _terminated(argv, tmp_path, ready=8.0)
    assert (done.returncode, done.stderr.strip()) == (143, "bioscara eval: interrupted by SIGTERM")
    assert not (tmp_path / "v").exists()  # the folder it made for the video is gone too


def test_sigterm_stops_monitor_as_ctrl_c_does_disabling_the_joints(tmp_path: Path) -> None:
    # Seen: exit 143 with nothing said, the state not saved and the joints left enabled.
    assert main(["enable", "--state", str(tmp_path / "st.json")]) == 0
    enabled = json.loads((tmp_path / "st.json").read_text(encoding="utf-8"))["firmware"]
    assert all(state["drive_current"] > 0 for state in enabled.values())
    done = _terminated(["monitor", "--duration", "60", "--state", "st.json"], tmp_path, ready=8.0)
    assert (done.returncode, done.stderr.strip()) == (143, "bioscara monitor: interrupted by SIGTERM")
    assert drive_currents(tmp_path / "st.json") == {"j1": 0, "j2": 0, "j3": 0, "j4": 0}


@pytest.mark.parametrize("signum", [signal.SIGINT, signal.SIGTERM, signal.SIGHUP], ids=["INT", "TERM", "HUP"])
def test_a_signal_while_a_command_saves_its_state_does_not_cut_the_save_short(
    tmp_path: Path, monkeypatch: pytest.MonkeyPatch, signum: int, sighup_default: None
) -> None:
    # Seen: a SIGTERM 1-4 ms after enable printed its result: exit 143, the state file not written
    # (the emulated arm forgot the enables the bus trace shows), at times an empty temp file left.
    from bioscara_gym.console import session

    state = tmp_path / "st.json"
    save = session.save_state

    def signalled_save(*args: object) -> None:
        signal.raise_signal(signum)
        save(*args)  # type: ignore[arg-type]

    monkeypatch.setattr(session, "save_state", signalled_save)
    assert main(["enable", "--state", str(state)]) == 0  # it had done its work
    assert drive_currents(state) == {"j1": 20, "j2": 40, "j3": 20, "j4": 20}
    assert sorted(p.name for p in tmp_path.iterdir()) == ["st.json"]


def test_the_first_signal_interrupts_and_later_ones_let_the_clean_up_finish() -> None:
    # Seen: a second SIGTERM 20 ms after the first interrupted move's safe stop: joints left enabled.
    from bioscara_gym.cli import _signals_as_interrupt
    from bioscara_gym.training.signals import Interrupted

    before = {s: signal.getsignal(s) for s in (signal.SIGINT, signal.SIGTERM)}
    with _signals_as_interrupt():
        with pytest.raises(Interrupted) as caught:
            signal.getsignal(signal.SIGTERM)(signal.SIGTERM, None)  # type: ignore[operator]
        assert caught.value.exit_code == 143
        for s in (signal.SIGINT, signal.SIGTERM):  # the clean-up runs on
            assert signal.getsignal(s)(s, None) is None  # type: ignore[operator]
    assert {s: signal.getsignal(s) for s in before} == before
    with _signals_as_interrupt(), pytest.raises(KeyboardInterrupt) as caught_int:
        signal.getsignal(signal.SIGINT)(signal.SIGINT, None)  # type: ignore[operator]
    assert type(caught_int.value) is KeyboardInterrupt  # Ctrl-C: exit 130, "interrupted"


@pytest.mark.parametrize(
    ("interrupt", "code", "line"),
    [
        (KeyboardInterrupt(), 130, "bioscara status: interrupted"),
        (None, 143, "bioscara status: interrupted by SIGTERM"),
    ],
)
def test_a_library_error_raised_while_an_interrupt_was_handled_is_the_interrupt(
    monkeypatch: pytest.MonkeyPatch,
    capsys: pytest.CaptureFixture[str],
    interrupt: KeyboardInterrupt | None,
    code: int,
    line: str,
) -> None:
    # Seen: a signal landing in MuJoCo's import: "ImportError: initialization failed", 40 lines.
    from bioscara_gym.console import commands
    from bioscara_gym.training.signals import Interrupted

    def status(args: object) -> int:
        try:
            raise interrupt or Interrupted(signal.SIGTERM)
        except KeyboardInterrupt as e:
            raise ImportError("initialization failed") from e

    monkeypatch.setattr(commands, "cmd_status", status)
    assert main(["status"]) == code
    assert capsys.readouterr().err.strip() == line


@pytest.mark.parametrize(
    ("signum", "code", "line"),
    [
        (signal.SIGINT, 130, "bioscara status: interrupted"),
        (signal.SIGTERM, 143, "bioscara status: interrupted by SIGTERM"),
    ],
)
def test_an_interrupt_a_library_turned_into_its_own_error_without_a_trace_is_the_interrupt(
    monkeypatch: pytest.MonkeyPatch, capsys: pytest.CaptureFixture[str], signum: int, code: int, line: str
) -> None:
    # Seen: Ctrl-C in MuJoCo's EGL set-up (a ctypes call) during eval: exit 1 and a 40-line traceback
    # ending "ctypes.ArgumentError: argument 1: KeyboardInterrupt: ", the interrupt itself gone.
    import ctypes

    from bioscara_gym.console import commands

    def status(args: object) -> int:
        with contextlib.suppress(KeyboardInterrupt):  # what ctypes does: nothing of it stays but text
            signal.raise_signal(signum)
        # ctypes' text for it: "argument 1: Interrupted: SIGTERM" for the CLI's SIGTERM (checked)
        name = "KeyboardInterrupt: " if signum == signal.SIGINT else "Interrupted: SIGTERM"
        raise ctypes.ArgumentError(f"argument 1: {name}")

    monkeypatch.setattr(commands, "cmd_status", status)
    assert main(["status"]) == code
    assert capsys.readouterr().err.strip() == line


def test_an_error_after_an_interrupt_the_command_caught_itself_is_not_the_interrupt(
    monkeypatch: pytest.MonkeyPatch,
) -> None:
    # A reviewer's experiment: a KeyError after a Ctrl-C the command caught (as replay catches the
    # signals it replays) was reported "interrupted", exit 130, the error's traceback hidden.
    from bioscara_gym.console import commands

    def status(args: object) -> int:
        with contextlib.suppress(KeyboardInterrupt):
            signal.raise_signal(signal.SIGINT)
        raise KeyError("a fault of its own")

    monkeypatch.setattr(commands, "cmd_status", status)
    with pytest.raises(KeyError):
        main(["status"])


def _swallowing(signum: int, then: Callable[[], None]) -> Callable[[object], int]:
    """A command whose ``signum`` lands in a garbage-collector callback (Python ignores it); then ``then``."""

    def command(args: object) -> int:
        class Thing:
            pass

        def collected(ref: object) -> None:
            signal.raise_signal(signum)  # its handler runs in here, where Python ignores what it raises
            sum(range(100))

        thing = Thing()
        ref = weakref.ref(thing, collected)
        del thing
        assert ref() is None
        then()
        return 0

    return command


STOPS = pytest.mark.parametrize(
    ("signum", "code", "line"),
    [
        (signal.SIGINT, 130, "bioscara status: interrupted"),
        (signal.SIGTERM, 143, "bioscara status: interrupted by SIGTERM"),
    ],
)


@STOPS
def test_an_interrupt_python_ignored_ends_the_command_as_interrupted(
    monkeypatch: pytest.MonkeyPatch, capsys: pytest.CaptureFixture[str], signum: int, code: int, line: str
) -> None:
    # Seen: SIGTERM to validate landed in a WeakSet's garbage-collector callback: "Exception
    # ignored in ...", and the command ran on, wrote its JSON and 41 plots, and exited 1.
    from bioscara_gym.console import commands

    ran_on: list[str] = []
    monkeypatch.setattr(commands, "cmd_status", _swallowing(signum, lambda: ran_on.append("to its end")))
    before = {s: signal.getsignal(s) for s in (signal.SIGINT, signal.SIGTERM, signal.SIGHUP)}
    assert main(["status"]) == code
    assert capsys.readouterr().err.strip() == line
    assert ran_on == ["to its end"]  # it runs on, but does not end as if nothing had come
    assert {s: signal.getsignal(s) for s in before} == before


@STOPS
def test_after_an_interrupt_python_ignored_the_next_signal_interrupts_at_once(
    monkeypatch: pytest.MonkeyPatch, capsys: pytest.CaptureFixture[str], signum: int, code: int, line: str
) -> None:
    from bioscara_gym.console import commands

    ran_on: list[str] = []

    def second_signal() -> None:
        signal.raise_signal(signum)
        ran_on.append("past the second signal")

    monkeypatch.setattr(commands, "cmd_status", _swallowing(signum, second_signal))
    assert main(["status"]) == code
    assert capsys.readouterr().err.strip() == line
    assert ran_on == []


def test_status_read_by_a_reader_that_leaves_early_leaves_the_arm_enabled(
    tmp_path: Path, monkeypatch: pytest.MonkeyPatch
) -> None:
    # Seen: `bioscara status | head -1` disabled every joint (the print failed inside the session).
    from rich.console import Console

    from bioscara_gym.console import commands

    class ClosedPipe:
        def write(self, text: str) -> int:
            raise BrokenPipeError(32, "Broken pipe")

        def flush(self) -> None:
            raise BrokenPipeError(32, "Broken pipe")

    class PipeConsole(Console):
        def on_broken_pipe(self) -> None:  # rich's own exits 1 after pointing fd 1 at /dev/null
            raise SystemExit(1)

    state = tmp_path / "st.json"
    assert main(["enable", "--state", str(state)]) == 0
    monkeypatch.setattr(commands, "make_console", lambda: PipeConsole(file=ClosedPipe()))  # type: ignore[arg-type]
    with pytest.raises(SystemExit):
        main(["status", "--state", str(state)])
    firmware = json.loads(state.read_text(encoding="utf-8"))["firmware"]
    assert all(joint["drive_current"] > 0 for joint in firmware.values())


def test_a_json_file_with_a_key_twice_is_refused(tmp_path: Path) -> None:
    # Seen (a hostile test): "drive_current": 200, "drive_current": 20 in a state file; the last won.
    path = tmp_path / "s.json"
    path.write_text('{"a": {"b": 1, "c": 2, "b": 3}}', encoding="utf-8")
    with pytest.raises(ValueError, match=r"^key 'b' is given twice$"):
        read_json(path)
    path.write_text('{"a": {"b": 1}, "c": [{"b": 2}]}', encoding="utf-8")
    assert read_json(path) == {"a": {"b": 1}, "c": [{"b": 2}]}
