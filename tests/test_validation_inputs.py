"""A user's own recordings folder, and bad input to ``bioscara validate`` and ``calibrate``.

Every case is a packaged recording copied into ``tmp_path`` with one cell,
header field or name corrupted (each seen in a hostile test); the messages
are literals: one line naming the file, the line and the column or field,
and what was expected.
"""

from __future__ import annotations

import dataclasses
import gzip
import shutil
from collections.abc import Callable
from pathlib import Path

import pytest
import yaml

from bioscara_gym.cli import main
from bioscara_gym.errors import RecordingError
from bioscara_gym.hardware import load_config
from bioscara_gym.hardware.config import config_to_dict
from bioscara_gym.validation import validate
from bioscara_gym.validation.recordings import DATA_DIR, find_recordings

CONFIG = load_config()

TRACKING = "record_0p314_1p57_j1.csv.gz"
VELOCITY = "record_0p314_1p57_j1_vel_p0p5_i0p0_d0p0_kff1p0.csv.gz"
STALL = "j4_LOW_SPEED_STALL_adaptive_stall_threshold_two_levels.csv"
SMV = "accel_test_10000_200000.csv"


def _text(folder: str, name: str) -> str:
    data = (DATA_DIR / folder / name).read_bytes()
    return (gzip.decompress(data) if name.endswith(".gz") else data).decode()


def _put(root: Path, folder: str, name: str, text: str) -> Path:
    path = root / folder / name
    path.parent.mkdir(parents=True, exist_ok=True)
    path.write_text(text)
    return path


def _copy(
    root: Path, folder: str, name: str, edit: Callable[[list[str]], None] | None = None, as_name: str = ""
) -> Path:
    """The packaged ``folder/name`` under ``root`` as plain CSV (or ``as_name``), edited by ``edit``."""
    lines = _text(folder, name).splitlines()
    if edit is not None:
        edit(lines)
    return _put(root, folder, as_name or name.removesuffix(".gz"), "\n".join(lines) + "\n")


def _cell(lines: list[str], line: int, column: int, value: str) -> None:
    """Set a comma-separated cell (line counted from 1)."""
    cells = lines[line - 1].split(",")
    cells[column] = value
    lines[line - 1] = ",".join(cells)


def _pair(lines: list[str], line: int, key: str, value: str) -> None:
    """Set the value after ``key`` in a row of key, value pairs (the controller manager's echo)."""
    cells = lines[line - 1].split(",")
    cells[cells.index(key) + 1] = value
    lines[line - 1] = ",".join(cells)


def _refusal(root: Path) -> str:
    with pytest.raises(RecordingError) as e:
        find_recordings(root)
    return str(e.value).replace(f"{root}/", "")


# ------------------------------------------------------------- the readers
def _replace(old: str, new: str) -> Callable[[list[str]], None]:
    def edit(lines: list[str]) -> None:
        i = lines.index(old)
        lines[i] = new

    return edit


def _swap(a: int, b: int) -> Callable[[list[str]], None]:
    def edit(lines: list[str]) -> None:
        lines[a - 1], lines[b - 1] = lines[b - 1], lines[a - 1]

    return edit


def _last_time(value: str) -> Callable[[list[str]], None]:
    def edit(lines: list[str]) -> None:
        _cell(lines, len(lines), 0, value)

    return edit


def _stamp_after(seconds: int) -> Callable[[list[str]], None]:
    def edit(lines: list[str]) -> None:
        cells = lines[-1].split(",")
        cells[0] = str(int(cells[0]) + seconds)
        lines[-1] = ",".join(cells)

    return edit


def _column(index: int, value: str) -> Callable[[list[str]], None]:
    def edit(lines: list[str]) -> None:
        for i in range(2, len(lines) + 1):
            _cell(lines, i, index, value)

    return edit


def _then(*edits: Callable[[list[str]], None]) -> Callable[[list[str]], None]:
    def edit(lines: list[str]) -> None:
        for e in edits:
            e(lines)

    return edit


def _pair_edit(line: int, key: str, value: str) -> Callable[[list[str]], None]:
    return lambda lines: _pair(lines, line, key, value)


def _cell_edit(line: int, column: int, value: str) -> Callable[[list[str]], None]:
    return lambda lines: _cell(lines, line, column, value)


def _keep(n: int) -> Callable[[list[str]], None]:
    def edit(lines: list[str]) -> None:
        del lines[n:]

    return edit


def _all_stamps(value: str) -> Callable[[list[str]], None]:
    def edit(lines: list[str]) -> None:
        for i, line in enumerate(lines):
            cells = line.split(",")
            cells[0], cells[1] = value, "0"
            lines[i] = ",".join(cells)

    return edit


STATE = "state_interface.j1/position"
COMMAND = "command_interface.j1/position"

# (folder, packaged file, edit, name to save as, the message after the folder's path)
REFUSED = {
    # 3: one huge time cell ran the replay for hours
    "maxAccel: a time jump": (
        "maxAccel",
        "j1_1.csv",
        _last_time("1e7"),
        "",
        "maxAccel/j1_1.csv: line 208: time jumps by 1e+07 s; a replay takes steps of up to 60 s",
    ),
    "maxAccel: a time of 1e300": (
        "maxAccel",
        "j1_1.csv",
        _last_time("1e300"),
        "",
        "maxAccel/j1_1.csv: line 208: time jumps by 1e+300 s; a replay takes steps of up to 60 s",
    ),
    "settingMaxVal: a time jump": (
        "settingMaxVal",
        SMV,
        _last_time("1e9"),
        "",
        f"settingMaxVal/{SMV}: line 300: time jumps by 1e+09 s; a replay takes steps of up to 60 s",
    ),
    "tracking: a stamp 8e9 s later": (
        "tracking_error",
        TRACKING,
        _stamp_after(8_000_000_000),
        "",
        "tracking_error/record_0p314_1p57_j1.csv: line 2120: time jumps by 8e+09 s; a replay "
        "takes steps of up to 60 s",
    ),
    # 5: NaN and infinity, refused by every reader as by the maxAccel one
    "tracking: nan feedback": (
        "tracking_error",
        TRACKING,
        _pair_edit(21, STATE, "nan"),
        "",
        f"tracking_error/record_0p314_1p57_j1.csv: line 21: 'nan' is not a finite number ({STATE})",
    ),
    "tracking: inf reference": (
        "tracking_error",
        TRACKING,
        _pair_edit(21, COMMAND, "inf"),
        "",
        f"tracking_error/record_0p314_1p57_j1.csv: line 21: 'inf' is not a finite number ({COMMAND})",
    ),
    "RW_test: nan read time": (
        "RW_test",
        "position_100kHz.csv.gz",
        _cell_edit(6, 3, " nan"),
        "",
        "RW_test/position_100kHz.csv: line 6: 'nan' is not a finite number (read [us])",
    ),
    "RW_test: inf write time": (
        "RW_test",
        "position_100kHz.csv.gz",
        _cell_edit(6, 4, " inf"),
        "",
        "RW_test/position_100kHz.csv: line 6: 'inf' is not a finite number (write [us])",
    ),
    "RW_test: nan handler time": (
        "RW_test",
        "baseline_joint_400kHz.csv.gz",
        _cell_edit(6, 4, " nan"),
        "",
        "RW_test/baseline_joint_400kHz.csv: line 6: 'nan' is not a finite number (t_exec [us])",
    ),
    "settingMaxVal: nan maxAccel": (
        "settingMaxVal",
        SMV,
        _replace("maxAccel: 10000.000000", "maxAccel: nan"),
        "",
        f"settingMaxVal/{SMV}: line 1: 'nan' is not a finite number (header field maxAccel)",
    ),
    "settingMaxVal: nan maxVel": (
        "settingMaxVal",
        SMV,
        _replace("maxVel: 200000.000000", "maxVel: nan"),
        "",
        f"settingMaxVal/{SMV}: line 2: 'nan' is not a finite number (header field maxVel)",
    ),
    "RW_test: a handler time beyond 32 bits": (
        "RW_test",
        "baseline_joint_400kHz.csv.gz",
        _cell_edit(6, 4, " 1e308"),
        "",
        "RW_test/baseline_joint_400kHz.csv: line 6: t_exec [us] 1e+308 is beyond what profiling_test.ino "
        "prints (micros() differences, at most 4294967295)",
    ),
    # 6: messages naming the file, the line and the field
    "tracking: text": (
        "tracking_error",
        TRACKING,
        _pair_edit(21, STATE, "abc"),
        "",
        f"tracking_error/record_0p314_1p57_j1.csv: line 21: not a number: 'abc' ({STATE})",
    ),
    "tracking: an empty cell": (
        "tracking_error",
        TRACKING,
        _pair_edit(21, STATE, ""),
        "",
        f"tracking_error/record_0p314_1p57_j1.csv: line 21: not a number: '' ({STATE})",
    ),
    "tracking: a malformed gain": (
        "tracking_error",
        VELOCITY,
        None,
        "record_0p314_1p57_j1_vel_p0p5p5_i0p0_d0p0_kff1p0.csv",
        "tracking_error/record_0p314_1p57_j1_vel_p0p5p5_i0p0_d0p0_kff1p0.csv: gain p '0p5p5' in the name "
        "is not a number (p for the point: 0p314 is 0.314)",
    ),
    "tracking: max acceleration 0": (
        "tracking_error",
        TRACKING,
        None,
        "record_0p314_0_j1.csv",
        "tracking_error/record_0p314_0_j1.csv: max acceleration '0' in the name must be > 0",
    ),
    "tracking: one time for every row": (
        "tracking_error",
        TRACKING,
        _all_stamps("1760365398"),
        "",
        "tracking_error/record_0p314_1p57_j1.csv: line 2: time 1.76037e+09 s is not after 1.76037e+09 s "
        "(line 1); time must increase",
    ),
    "maxAccel: Vel 1e300": (
        "maxAccel",
        "j1_1.csv",
        _replace("Vel: 1", "Vel: 1e300"),
        "",
        "maxAccel/j1_1.csv: line 6: header field Vel 1e+300 is 2.01e+303 deg/s at the motor; "
        "SETMAXVELOCITY sends a float32, at most 3.403e+38",
    ),
    "maxAccel: max Accel 1e300": (
        "maxAccel",
        "j1_1.csv",
        _replace("max Accel: 2", "max Accel: 1e300"),
        "",
        "maxAccel/j1_1.csv: line 7: header field max Accel 1e+300 is 2.01e+303 deg/s² at the motor; "
        "SETMAXACCELERATION sends a float32, at most 3.403e+38",
    ),
    "maxAccel: max Accel inf": (
        "maxAccel",
        "j1_1.csv",
        _replace("max Accel: 2", "max Accel: inf"),
        "",
        "maxAccel/j1_1.csv: line 7: 'inf' is not a finite number (header field max Accel)",
    ),
    "maxAccel: current 1e-300": (
        "maxAccel",
        "j1_1.csv",
        _replace("current: 20", "current: 1e-300"),
        "",
        "maxAccel/j1_1.csv: line 8: header field current 1e-300 must be a whole percent, 1-100 "
        "(enable() takes an integer)",
    ),
    "settingMaxVal: maxVel 1e300": (
        "settingMaxVal",
        SMV,
        _replace("maxVel: 200000.000000", "maxVel: 1e300"),
        "",
        f"settingMaxVal/{SMV}: line 2: header field maxVel 1e+300; SETMAXVELOCITY sends a float32, "
        "at most 3.403e+38",
    ),
    "settingMaxVal: maxAccel 0": (
        "settingMaxVal",
        SMV,
        _replace("maxAccel: 10000.000000", "maxAccel: 0"),
        "",
        f"settingMaxVal/{SMV}: line 1: header field maxAccel 0 must be > 0 (a limit)",
    ),
    "maxAccel: a header field twice": (
        "maxAccel",
        "j1_1.csv",
        _replace("joint: j1", "joint: j1\njoint: j2"),
        "",
        "maxAccel/j1_1.csv: line 6: header field joint again (first on line 5)",
    ),
    "settingMaxVal: one row": (
        "settingMaxVal",
        SMV,
        _keep(4),
        "",
        f"settingMaxVal/{SMV}: 1 data row; a speed profile needs at least 2",
    ),
    # 7: the wrong joint, two of one name, time that goes back
    "maxAccel: j2's file of j1": (
        "maxAccel",
        "j1_1.csv",
        None,
        "j2_1.csv",
        "maxAccel/j2_1.csv: line 5: header says joint: j1, the file name says j2",
    ),
    "tracking: j2": (
        "tracking_error",
        TRACKING,
        None,
        "record_0p314_1p57_j2.csv",
        "tracking_error/record_0p314_1p57_j2.csv: the name says j2; tracking_error/ holds j1's runs only "
        "(record_<ramp>_<max accel>_j1...)",
    ),
    "settingMaxVal: time goes back": (
        "settingMaxVal",
        SMV,
        _swap(10, 11),
        "",
        f"settingMaxVal/{SMV}: line 11: time 0.072981 s is not after 0.084925 s (line 10); "
        "time must increase",
    ),
    "stall: time goes back": (
        "high_speed_stall_test",
        STALL,
        _swap(10, 11),
        "",
        f"high_speed_stall_test/{STALL}: line 11: Program Time 3171.09 s goes back from 3171.1 s (line 10); "
        "time must never go back",
    ),
    "tracking: time goes back": (
        "tracking_error",
        TRACKING,
        _swap(10, 11),
        "",
        "tracking_error/record_0p314_1p57_j1.csv: line 11: time 1.76037e+09 s is not after 1.76037e+09 s "
        "(line 10); time must increase",
    ),
    "stall: a stall flag of 2": (
        "high_speed_stall_test",
        STALL,
        _cell_edit(5, 11, "2"),
        "",
        f"high_speed_stall_test/{STALL}: line 5: data 10 (the stall flag) is 2, expected 0 or 1",
    ),
    # 8: beyond what the firmware can report
    "maxAccel: q and qd 1e300": (
        "maxAccel",
        "j1_1.csv",
        _then(_cell_edit(16, 1, " 1e300"), _cell_edit(16, 2, " 1e300")),
        "",
        "maxAccel/j1_1.csv: line 16: q 1e+300 rad is 2.01e+303 motor degrees; the firmware's position "
        "(float angleMoved) holds whole degrees up to 16,777,216",
    ),
    "maxAccel: qd beyond any encoder reading": (
        "maxAccel",
        "j1_1.csv",
        _cell_edit(16, 2, " 20"),
        "",
        "maxAccel/j1_1.csv: line 16: qd 20 rad/s is 6.68e+03 RPM at the motor; no encoder reading "
        "(GETENCODERRPM) is above 4500",
    ),
    "settingMaxVal: a position of 1e12": (
        "settingMaxVal",
        SMV,
        _cell_edit(300, 1, " 1e12"),
        "",
        f"settingMaxVal/{SMV}: line 300: position 1e+12 deg; the firmware's position (float angleMoved) "
        "holds whole degrees up to 16,777,216",
    ),
}


@pytest.mark.parametrize("case", list(REFUSED))
def test_a_bad_recording_is_one_line_naming_the_file_line_and_field(tmp_path: Path, case: str) -> None:
    folder, name, edit, as_name, message = REFUSED[case]
    _copy(tmp_path, folder, name, edit, as_name)
    assert _refusal(tmp_path) == message


@pytest.mark.parametrize(("pause_s", "read"), [(59.9, True), (60.1, False)])
def test_a_pause_of_up_to_a_minute_is_read_a_longer_one_refused(
    tmp_path: Path, pause_s: float, read: bool
) -> None:
    # The arm's own recordings pause for up to 19.5 s (J3_UP_ramp); a user's may pause
    # longer. One cell of 1e7 s ran validate for hours: a step of over 60 s is refused.
    def pause(lines: list[str]) -> None:
        _cell(lines, len(lines), 0, f"{float(lines[-2].split(',')[0]) + pause_s:.6f}")

    _copy(tmp_path, "maxAccel", "j1_1.csv", pause)
    if read:
        assert len(find_recordings(tmp_path)) == 1
    else:
        assert _refusal(tmp_path).startswith("maxAccel/j1_1.csv: line 208: time jumps by 60.1 s; ")


@pytest.mark.parametrize(("steps", "read"), [(60, True), (61, False)])
def test_a_recording_of_up_to_an_hour_is_read_a_longer_one_refused(
    tmp_path: Path, steps: int, read: bool
) -> None:
    # Seen: 300 rows 59 s apart (8 kB) kept validate busy for 40 s; a megabyte would run for hours.
    def stretch(lines: list[str]) -> None:  # the header, the first sample, then one every 59.99 s
        del lines[11:]
        row = lines[10].split(",")
        for k in range(1, steps + 1):
            lines.append(",".join([f"{float(row[0]) + 59.99 * k:.6f}", *row[1:]]))

    _copy(tmp_path, "maxAccel", "j1_1.csv", stretch)
    if read:
        assert len(find_recordings(tmp_path)) == 1
    else:
        assert _refusal(tmp_path) == (  # 0.0101051 s + 61 x 59.99 s from the program's start
            "maxAccel/j1_1.csv: line 72: t spans 3659.4 s; a replay runs at most 3600 s"
        )


def test_a_recording_and_its_gzipped_twin_are_refused_as_two_of_one_name(tmp_path: Path) -> None:
    # Seen: j1_1.csv beside j1_1.csv.gz gave two rows named maxAccel/j1_1.
    _copy(tmp_path, "maxAccel", "j3_6.csv")
    (tmp_path / "maxAccel" / "j3_6.csv.gz").write_bytes(gzip.compress(_text("maxAccel", "j3_6.csv").encode()))
    assert _refusal(tmp_path) == (
        "maxAccel/j3_6.csv.gz: j3_6.csv beside it is a recording of the same name (j3_6); keep one"
    )


def test_the_packaged_recordings_pass_every_check() -> None:
    rec = find_recordings()
    assert len(rec) == 45


# ------------------------------------------------------- what is replayed
def test_a_setting_max_val_profile_that_did_not_move_is_one_failing_row(tmp_path: Path) -> None:
    # Seen: ZeroDivisionError in 100 * rms / moved, a traceback.
    header = "maxAccel: 5000.000000\nmaxVel: 10000.000000\ntime, position, velocity, accleration\n"
    rows = "".join(f"{i * 0.012:.3f}, 1.0, 0.0, 0.0\n" for i in range(50))
    _put(tmp_path, "settingMaxVal", "accel_test_5000_10000_online_change.csv", header + rows)
    result = validate(tmp_path, CONFIG)
    assert [(r.experiment, r.quantity, r.real, r.sim, r.passed, r.note) for r in result.rows] == [
        (
            "settingMaxVal/accel_test_5000_10000_online_change",
            "the motor moved",
            "no",
            "-",
            False,
            "its position never changes: nothing to compare (not replayed)",
        )
    ]
    assert result.replays["setting_max_val"] == {}


def _unhomable_j1(tmp_path: Path) -> tuple[Path, Path]:
    """A folder with j1_1 and j2_1, and a configuration under which j1 cannot home."""
    stuck = CONFIG.joint("j1").drive.with_values(pullout_accel=2000.0, friction_coulomb=5000.0)
    joints = tuple(dataclasses.replace(j, drive=stuck) if j.name == "j1" else j for j in CONFIG.joints)
    config = tmp_path / "nohome.yaml"
    config.write_text(
        yaml.safe_dump(config_to_dict(dataclasses.replace(CONFIG, joints=joints)), sort_keys=False)
    )
    root = tmp_path / "test"
    for name in ("j1_1.csv", "j2_1.csv"):
        _copy(root, "maxAccel", name)
    return root, config


def test_plots_leave_out_the_recordings_of_a_joint_that_cannot_home(tmp_path: Path) -> None:
    # Seen: KeyError 'j1_1' in plots._max_accel, after the JSON had been written.
    pytest.importorskip("matplotlib")
    from bioscara_gym.validation import plots

    root, config = _unhomable_j1(tmp_path)
    result = validate(root, load_config(config))
    assert [r.experiment for r in result.rows if not r.passed] == ["homing/j1"]
    assert [p.name for p in plots.write_plots(result, tmp_path / "plots")] == ["maxAccel_j2_1.png"]


def test_the_json_is_not_written_when_the_plots_fail(
    tmp_path: Path, monkeypatch: pytest.MonkeyPatch, capsys: pytest.CaptureFixture[str]
) -> None:
    pytest.importorskip("matplotlib")
    from bioscara_gym.validation import plots

    def fails(v: object, folder: Path) -> list[Path]:
        raise ValueError("a picture cannot be drawn")

    monkeypatch.setattr(plots, "_max_accel", fails)
    root = tmp_path / "test"
    _copy(root, "maxAccel", "j3_6.csv")
    out, rows = tmp_path / "plots", tmp_path / "rows.json"
    assert main(["validate", str(root), "--json", str(rows), "--plots", str(out)]) == 2
    assert capsys.readouterr().err.strip() == "bioscara validate: error: a picture cannot be drawn"
    assert not rows.exists() and not out.exists()


# ------------------------------------------- outputs never replace inputs
@pytest.fixture
def folder(tmp_path: Path, monkeypatch: pytest.MonkeyPatch) -> Path:
    """A recordings folder; any replay is an error (every refusal comes before the work)."""
    import bioscara_gym.validation as validation

    def no_replay(*args: object, **kwargs: object) -> None:
        raise AssertionError("a replay ran before the arguments were checked")

    monkeypatch.setattr(validation, "validate", no_replay)
    root = tmp_path / "test"
    _copy(root, "maxAccel", "j3_6.csv")
    (root / "RW_test").mkdir()
    shutil.copy(DATA_DIR / "RW_test" / "position_100kHz.csv.gz", root / "RW_test")
    (tmp_path / "my.yaml").write_text(yaml.safe_dump(config_to_dict(CONFIG), sort_keys=False))
    return root


@pytest.mark.parametrize(
    ("argv", "message"),
    [
        (
            ["validate", "{root}", "--json", "{root}/maxAccel/j3_6.csv"],
            "--json {root}/maxAccel/j3_6.csv is the recording maxAccel/j3_6.csv file; "
            "writing it would destroy it",
        ),
        (
            ["validate", "{root}", "--config", "{tmp}/my.yaml", "--json", "{tmp}/my.yaml"],
            "--json {tmp}/my.yaml is the --config file; writing it would destroy it",
        ),
        (
            ["calibrate", "{root}", "--config", "{tmp}/my.yaml", "--out", "{tmp}/my.yaml"],
            "--out {tmp}/my.yaml is the --config file; writing it would destroy it",
        ),
        (
            ["calibrate", "{root}", "--out", "{root}/RW_test/position_100kHz.csv.gz"],
            "--out {root}/RW_test/position_100kHz.csv.gz is the recording RW_test/position_100kHz.csv.gz "
            "file; writing it would destroy it",
        ),
        (
            ["calibrate", "{root}", "--out", "{tmp}/new.yaml", "--seed", "99999999999"],
            "--seed must be 0-4294967295 (the optimizer's seeds are 32-bit), got 99999999999",
        ),
    ],
)
def test_an_output_that_is_an_input_is_refused_before_any_replay(
    folder: Path, argv: list[str], message: str, capsys: pytest.CaptureFixture[str]
) -> None:
    # Seen: each of these replaced the recording or the configuration (or ran the
    # 'before' validation, then printed scipy's "Seed must be between 0 and 2**32 - 1").
    pytest.importorskip("scipy")
    tmp = folder.parent
    before = {p: p.read_bytes() for p in [*folder.rglob("*.csv*"), tmp / "my.yaml"]}
    fill = {"root": str(folder), "tmp": str(tmp)}
    assert main([a.format(**fill) for a in argv]) == 2
    assert capsys.readouterr().err.strip() == f"bioscara {argv[0]}: error: " + message.format(**fill)
    assert {p: p.read_bytes() for p in before} == before


def test_calibrate_names_the_runs_it_looked_at_for_a_constant_speed(
    tmp_path: Path, capsys: pytest.CaptureFixture[str]
) -> None:
    # Seen: "no maxAccel run reaches a constant speed" naming no file, after the 'before' validation.
    pytest.importorskip("scipy")
    root = tmp_path / "test"
    _copy(root, "maxAccel", "j4_1.csv")
    assert main(["calibrate", str(root), "--out", str(tmp_path / "arm.yaml")]) == 2
    assert capsys.readouterr().err.strip() == (
        "bioscara calibrate: error: no maxAccel run reaches a constant speed (within 1 % of its Vel for 5 "
        "samples): the program's overhead cannot be measured; looked at maxAccel/j4_1.csv"
    )
