"""Readers of the real arm's recordings, one per kind, in the arm repository's ``test/`` layout.

A folder laid out like ``test/`` of DALSA-Lab/bioscara (the packaged
:data:`DATA_DIR`, or a user's own) is read by :func:`find_recordings`; each
reader takes one file (``.csv`` or ``.csv.gz``) and returns its figures with
the settings its name or header states. Anything a reader cannot use raises
:class:`RecordingError`, whose message is one line naming the file and the
problem: the line and the column or header field, and what was expected.
Every number must be finite (:func:`_number`), every time column must run
forward (:func:`_check_time`), and positions and speeds must be ones the
firmware can report (:func:`_check_position`, :func:`_check_speed`).
"""

from __future__ import annotations

import csv
import errno
import gzip
import io
import math
import os
import re
import zlib
from collections.abc import Iterator, Sequence
from dataclasses import dataclass, field
from importlib import resources
from pathlib import Path

import numpy as np

from bioscara_gym.errors import RecordingError
from bioscara_gym.fsutil import read_bytes
from bioscara_gym.hardware.config import POSITION_MAX_DEG
from bioscara_gym.hardware.registers import (
    CURRENT_MAX_PCT,
    DRIVE_CURRENT_MIN_PCT,
    I2C_MAX_CLOCK_HZ,
    I2C_MIN_CLOCK_HZ,
    MAX_PLAUSIBLE_RPM,
)

__all__ = [
    "DATA_DIR",
    "JOINTS",
    "HandlerTimes",
    "MaxAccelRun",
    "PidErrorTest",
    "RecordingError",
    "Recordings",
    "SettingMaxValRun",
    "StallSignal",
    "TrackingRun",
    "Transactions",
    "find_recordings",
    "recording_files",
]

#: The joints a recording may name.
JOINTS = ("j1", "j2", "j3", "j4")
#: The joints' reductions in the test programs, motor rad per joint unit (rad
#: or m): their ``Joint(...)`` lines (``comm_speed_test.cpp`` builds all four:
#: j1 35, j2 -2π/0.004, j3 24, j4 12; the packaged configuration's). A
#: recording's positions, speeds and limits are checked at the motor with them.
PROGRAM_REDUCTIONS = {"j1": 35.0, "j2": -2 * math.pi / 0.004, "j3": 24.0, "j4": 12.0}
#: Unit of each joint's position (j2 is the lift, in metres).
_UNIT = {"j1": "rad", "j2": "m", "j3": "rad", "j4": "rad"}
#: The largest float32 (FLT_MAX): every limit and speed travels the bus as one
#: (``registers.PAYLOAD_FORMAT``: SETMAXVELOCITY, SETMAXACCELERATION, SETRPM).
FLOAT32_MAX = float(np.finfo(np.float32).max)
#: The longest step of a replayed recording's time, s. A replay runs the
#: simulated arm through every step (one cell of 1e7 s ran ``bioscara
#: validate`` for hours; a minute replays in about 0.06 s). The arm's
#: published recordings pause for up to 19.5 s
#: (``high_speed_stall_test/J3_UP_ramp``), the replayed ones for up to
#: 0.22 s (the controller's log in ``tracking_error/record_0p314_0p157_j1``):
#: a recording of one's own arm may pause longer than those and still be read.
MAX_STEP_S = 60.0
#: The longest replayed recording, s: an hour replays in some 4 s. The arm's
#: longest replayed recording spans 79 s (``high_speed_stall_test``); seen: an
#: 8 kB file of 300 steps of 59 s kept ``validate`` busy for 40 s, and a
#: megabyte of them would have run for hours.
MAX_DURATION_S = 3600.0


def _data_dir() -> Path:
    return Path(str(resources.files("bioscara_gym.validation") / "data"))


#: The packaged recordings (``bioscara_gym/validation/data``).
DATA_DIR = _data_dir()


#: Largest recording read, bytes (the packaged ones are under 0.4 MB gzipped).
MAX_RECORDING_BYTES = 256 * 1024 * 1024


def _open_text(path: Path) -> str:
    try:
        data = read_bytes(path, MAX_RECORDING_BYTES)  # never a device such as /dev/zero
        if path.name.endswith(".gz"):
            with gzip.GzipFile(fileobj=io.BytesIO(data)) as unpacked:
                data = unpacked.read(MAX_RECORDING_BYTES + 1)  # 26 MB of zeros unpack to 6 GB
            if len(data) > MAX_RECORDING_BYTES:
                raise RecordingError(path, f"unpacks to more than {MAX_RECORDING_BYTES} bytes")
        return data.decode("utf-8", errors="replace")
    except OSError as e:
        raise RecordingError(path, f"cannot be read ({e.strerror or e})") from e
    except (EOFError, zlib.error) as e:  # a damaged gzip stream (gzip.BadGzipFile is an OSError)
        raise RecordingError(path, f"cannot be read ({e})") from e


def recording_name(path: Path) -> str:
    """A recording's name: its file's without ``.csv`` or ``.csv.gz`` (``j1_3``)."""
    return _stem(path)


def _stem(path: Path) -> str:
    name = path.name
    for suffix in (".csv.gz", ".csv"):
        if name.endswith(suffix):
            return name[: -len(suffix)]
    return name


# ------------------------------------------------------- shared cell checks
def _number(path: Path, line: int, text: str, what: str = "") -> float:
    """The finite number in one cell; anything else is an error naming the file, line and field.

    Every reader takes its numbers through here: NaN and infinity (or a
    number beyond float's range) are no measurement, and broke every figure
    computed after them.
    """
    where = f" ({what})" if what else ""
    cell = text.strip()
    try:
        value = float(cell)
    except ValueError:
        raise RecordingError(path, f"line {line}: not a number: {cell!r}{where}") from None
    if not math.isfinite(value):
        raise RecordingError(path, f"line {line}: {cell!r} is not a finite number{where}")
    return value


def _rows(
    path: Path, rows: Sequence[Sequence[str]], first_line: int, width: int | None = None
) -> tuple[np.ndarray, np.ndarray]:
    """Rows of numbers as a 2-D array, and the file line of each; a bad cell is an error naming its line."""
    out, lines = [], []
    for i, row in enumerate(rows):
        cells = [c.strip() for c in row]
        if not any(cells):
            continue
        line = first_line + i
        if width is not None and len(cells) < width:
            raise RecordingError(path, f"line {line}: {len(cells)} columns, expected {width}")
        out.append([_number(path, line, c) for c in (cells[:width] if width else cells)])
        lines.append(line)
    if not out:
        raise RecordingError(path, "no data rows")
    return np.asarray(out, dtype=float), np.asarray(lines)


def _floats(
    path: Path, rows: Sequence[Sequence[str]], first_line: int, width: int | None = None
) -> np.ndarray:
    """Rows of numbers as a 2-D array (:func:`_rows` without the lines)."""
    return _rows(path, rows, first_line, width)[0]


def _check_time(
    path: Path,
    t: np.ndarray,
    lines: np.ndarray,
    what: str,
    *,
    bounded: bool = False,
    from_zero: bool = False,
    strict: bool = True,
) -> None:
    """Refuse a time column that is not a sampled series, naming the line.

    It must increase (``strict``) or at least never go back; if ``bounded``
    (a recording the simulated arm is run through), no step may exceed
    :data:`MAX_STEP_S`, nor the whole :data:`MAX_DURATION_S`. With
    ``from_zero`` the clock starts at the program's command: the first
    sample is that long after it (at least 0, and within the same bound).
    """
    longest = MAX_STEP_S if bounded else math.inf
    sampled = f"; a replay takes steps of up to {longest:g} s"
    with np.errstate(over="ignore"):  # 1e308 after -1e308: a step of inf, refused below
        steps = np.diff(t)
    back = np.flatnonzero(steps <= 0.0 if strict else steps < 0.0)
    if back.size:
        i = int(back[0])
        rule = "is not after" if strict else "goes back from"
        raise RecordingError(
            path,
            f"line {lines[i + 1]}: {what} {t[i + 1]:g} s {rule} {t[i]:g} s (line {lines[i]}); "
            f"time must {'increase' if strict else 'never go back'}",
        )
    if from_zero and t[0] < 0.0:
        raise RecordingError(path, f"line {lines[0]}: {what} {t[0]:g} s is before the program's start (0 s)")
    if from_zero and t[0] > longest:
        raise RecordingError(
            path, f"line {lines[0]}: time starts {t[0]:g} s after the program's start{sampled}"
        )
    jump = np.flatnonzero(steps > longest)
    if jump.size:
        i = int(jump[0])
        raise RecordingError(path, f"line {lines[i + 1]}: time jumps by {steps[i]:g} s{sampled}")
    span = t[-1] - (0.0 if from_zero else t[0])
    if bounded and span > MAX_DURATION_S:
        raise RecordingError(
            path, f"line {lines[-1]}: {what} spans {span:g} s; a replay runs at most {MAX_DURATION_S:g} s"
        )


def _check_position(path: Path, line: int, value: float, what: str, reduction: float, unit: str) -> None:
    """Refuse a position the firmware cannot report: beyond its float of motor degrees (angleMoved)."""
    degrees = abs(math.degrees(value * reduction))
    if degrees > POSITION_MAX_DEG:
        at = "" if unit == "deg" else f" is {degrees:.3g} motor degrees"
        raise RecordingError(
            path,
            f"line {line}: {what} {value:g} {unit}{at}; the firmware's position (float angleMoved) "
            f"holds whole degrees up to {POSITION_MAX_DEG:,.0f}",
        )


def _check_speed(path: Path, line: int, value: float, what: str, rad_s_per_unit: float, unit: str) -> None:
    """Refuse a speed no encoder reading can be: above ``MAX_PLAUSIBLE_RPM`` at the motor."""
    rpm = abs(value * rad_s_per_unit) * 60.0 / (2.0 * math.pi)
    if rpm > MAX_PLAUSIBLE_RPM:
        raise RecordingError(
            path,
            f"line {line}: {what} {value:g} {unit} is {rpm:.3g} RPM at the motor; no encoder reading "
            f"(GETENCODERRPM) is above {MAX_PLAUSIBLE_RPM:g}",
        )


def _check_columns(
    path: Path, data: np.ndarray, lines: np.ndarray, check: Sequence[tuple[int, str, str, float, str]]
) -> None:
    """Positions (``kind`` ``"position"``) and speeds (``"speed"``) of a table, each against its bound.

    ``check``: (column, kind, name, motor rad per unit, unit).
    """
    for column, kind, name, scale, unit in check:
        values = data[:, column]
        with np.errstate(over="ignore"):  # 1e307 m of j2 is inf at the motor: refused all the same
            if kind == "position":
                bad = np.abs(np.degrees(values * scale)) > POSITION_MAX_DEG
            else:
                bad = np.abs(values * scale) * 60.0 / (2.0 * math.pi) > MAX_PLAUSIBLE_RPM
        if bad.any():
            i = int(np.argmax(bad))
            if kind == "position":
                _check_position(path, int(lines[i]), float(values[i]), name, scale, unit)
            else:
                _check_speed(path, int(lines[i]), float(values[i]), name, scale, unit)


def _check_limit(
    path: Path, line: int | None, what: str, value: float, register: str, deg_per_unit: float, unit: str
) -> None:
    """A limit a program sends: > 0, and within the float32 its register packs it in (at the motor)."""
    at = "" if line is None else f"line {line}: "
    if value <= 0:
        raise RecordingError(path, f"{at}{what} {value:g} must be > 0 (a limit)")
    motor = abs(value * deg_per_unit)
    if motor > FLOAT32_MAX:
        there = ";" if deg_per_unit == 1.0 else f" is {motor:.3g} {unit} at the motor;"
        raise RecordingError(
            path, f"{at}{what} {value:g}{there} {register} sends a float32, at most {FLOAT32_MAX:.4g}"
        )


def _joint_from(path: Path, text: str, line: int | None = None) -> str:
    if text not in JOINTS:
        at = f" on line {line}" if line is not None else ""
        raise RecordingError(path, f"unknown joint {text!r}{at}; expected one of {', '.join(JOINTS)}")
    return text


# ------------------------------------------------------------------ maxAccel
@dataclass(frozen=True)
class MaxAccelRun:
    """One ``maxAccel/`` run (``max_accel_test.cpp``), joint units.

    Attributes:
        path: The file.
        joint: ``j1`` .. ``j4``.
        max_velocity: Max velocity set, also the velocity commanded (rad/s or m/s).
        max_acceleration: Max acceleration set (rad/s² or m/s²).
        current: Drive and hold current, percent.
        t: The program's time base, s: the sum of the 10 ms sleeps only
            (the two transactions of each sample are not counted).
        q: ``getPosition`` after each sleep.
        qd: ``getVelocity`` right after it (the encoder's speed estimate).
    """

    path: Path
    joint: str
    max_velocity: float
    max_acceleration: float
    current: float
    t: np.ndarray
    q: np.ndarray
    qd: np.ndarray

    @property
    def name(self) -> str:
        """File name without extension (``j1_3``)."""
        return _stem(self.path)


_HEADER_KEYS = {
    "joint": "joint",
    "vel": "max_velocity",
    "max accel": "max_acceleration",
    "current": "current",
}
#: A maxAccel file's name starts with its joint (``j1_3.csv``).
_NAMED_JOINT = re.compile(r"([jJ]\d+)_")


def read_max_accel(path: Path | str) -> MaxAccelRun:
    """Read a ``maxAccel/`` file: the program's header, then ``t, q, qd, qdd``."""
    path = Path(path)
    lines = _open_text(path).splitlines()
    settings: dict[str, tuple[str, str, int]] = {}  # field -> (its key as written, value, line)
    start = None
    for i, line in enumerate(lines):
        key, sep, value = line.partition(":")
        if sep and key.strip().lower() in _HEADER_KEYS:
            attr = _HEADER_KEYS[key.strip().lower()]
            if attr in settings:
                raise RecordingError(
                    path,
                    f"line {i + 1}: header field {key.strip()} again (first on line {settings[attr][2]})",
                )
            settings[attr] = (key.strip(), value.strip(), i + 1)
        if line.replace(" ", "").lower().startswith("t,q,qd"):
            start = i + 1
            break
    if start is None:
        raise RecordingError(path, "no 't, q, qd, qdd' header line (not a maxAccel recording?)")
    missing = [k for k in _HEADER_KEYS.values() if k not in settings]
    if missing:
        raise RecordingError(path, f"header lacks {', '.join(missing)} (the test program prints them)")
    key, text, at = settings["joint"]
    joint = _joint_from(path, text, at)
    named = _NAMED_JOINT.match(path.name)
    if named and named.group(1).lower() != joint:
        raise RecordingError(
            path, f"line {at}: header says {key}: {joint}, the file name says {named.group(1).lower()}"
        )
    values = {}
    for attr in ("max_velocity", "max_acceleration", "current"):
        key, text, at = settings[attr]
        values[attr] = (_number(path, at, text, f"header field {key}"), key, at)
    deg_per_unit = math.degrees(abs(PROGRAM_REDUCTIONS[joint]))
    unit = _UNIT[joint]
    for attr, register, per in (
        ("max_velocity", "SETMAXVELOCITY", "deg/s"),
        ("max_acceleration", "SETMAXACCELERATION", "deg/s²"),
    ):
        value, key, at = values[attr]
        _check_limit(path, at, f"header field {key}", value, register, deg_per_unit, per)
    cur, key, at = values["current"]
    if not (cur == round(cur) and DRIVE_CURRENT_MIN_PCT <= cur <= CURRENT_MAX_PCT):
        raise RecordingError(
            path,
            f"line {at}: header field {key} {cur:g} must be a whole percent, "
            f"{DRIVE_CURRENT_MIN_PCT}-{CURRENT_MAX_PCT} (enable() takes an integer)",
        )
    data, rows_at = _rows(path, list(csv.reader(lines[start:])), start + 1, width=3)
    _check_time(
        path,
        data[:, 0],
        rows_at,
        "t",
        bounded=True,
        from_zero=True,
    )
    reduction = PROGRAM_REDUCTIONS[joint]
    _check_columns(
        path,
        data,
        rows_at,
        [(1, "position", "q", reduction, unit), (2, "speed", "qd", reduction, f"{unit}/s")],
    )
    return MaxAccelRun(
        path,
        joint,
        values["max_velocity"][0],
        values["max_acceleration"][0],
        cur,
        data[:, 0],
        data[:, 1],
        data[:, 2],
    )


# ------------------------------------------------------------- settingMaxVal
@dataclass(frozen=True)
class SettingMaxValRun:
    """One ``settingMaxVal/`` profile: a long move under the header's limits (motor units).

    Attributes:
        path: The file.
        max_acceleration: deg/s² as sent (SETMAXACCELERATION).
        max_velocity: deg/s as sent (SETMAXVELOCITY).
        online_change: Whether the limits were changed during the move (file name).
        t: Sample times, s (the log's own clock, about 12 ms apart).
        position: Motor degrees.
        velocity: deg/s (the encoder's estimate).
    """

    path: Path
    max_acceleration: float
    max_velocity: float
    online_change: bool
    t: np.ndarray
    position: np.ndarray
    velocity: np.ndarray

    @property
    def name(self) -> str:
        """File name without extension."""
        return _stem(self.path)


#: Fewest samples of a settingMaxVal profile: its speed's slope needs two.
SETTING_MAX_VAL_MIN_ROWS = 2


def read_setting_max_val(path: Path | str) -> SettingMaxValRun:
    """Read a ``settingMaxVal/`` file: ``maxAccel:``, ``maxVel:``, then ``time, position, velocity, ...``."""
    path = Path(path)
    lines = _open_text(path).splitlines()
    values: dict[str, tuple[float, int]] = {}
    start = None
    for i, line in enumerate(lines):
        key, sep, value = line.partition(":")
        name = key.strip()
        if sep and name in ("maxAccel", "maxVel"):
            if name in values:
                raise RecordingError(
                    path, f"line {i + 1}: header field {name} again (first on line {values[name][1]})"
                )
            values[name] = (_number(path, i + 1, value, f"header field {name}"), i + 1)
        elif line.replace(" ", "").startswith("time,position,velocity"):
            start = i + 1
            break
    if start is None or len(values) < 2:
        raise RecordingError(
            path, "needs 'maxAccel:' and 'maxVel:' lines, then a 'time, position, velocity' header"
        )
    for key, register, unit in (
        ("maxAccel", "SETMAXACCELERATION", "deg/s²"),
        ("maxVel", "SETMAXVELOCITY", "deg/s"),
    ):
        value, at = values[key]
        _check_limit(path, at, f"header field {key}", value, register, 1.0, unit)
    data, rows_at = _rows(path, list(csv.reader(lines[start:])), start + 1, width=3)
    if len(data) < SETTING_MAX_VAL_MIN_ROWS:
        raise RecordingError(
            path, f"{len(data)} data row; a speed profile needs at least {SETTING_MAX_VAL_MIN_ROWS}"
        )
    _check_time(
        path,
        data[:, 0],
        rows_at,
        "time",
        bounded=True,
        from_zero=True,
    )
    _check_columns(
        path,
        data,
        rows_at,
        [
            (1, "position", "position", math.radians(1.0), "deg"),
            (2, "speed", "velocity", math.radians(1.0), "deg/s"),
        ],
    )
    return SettingMaxValRun(
        path,
        values["maxAccel"][0],
        values["maxVel"][0],
        "online_change" in path.name,
        data[:, 0],
        data[:, 1],
        data[:, 2],
    )


# -------------------------------------------------------- the stall signal
@dataclass(frozen=True)
class StallSignal:
    """One ``high_speed_stall_test/`` log: the firmware's serial output, one row per main-loop pass.

    Attributes:
        path: The file.
        joint: From the file name (``j4_...``, ``J3_...``).
        t: Program time of each row, s (the serial capture's clock).
        raw: data 0, raw |PID error| (1/256 microsteps).
        despiked: data 1, after the spike filter.
        filtered: data 2, after the low-pass filter.
        speed: data 7, measured motor speed, rad/s.
        set_speed: data 8, the last SETRPM value, motor rad/s.
        threshold: data 9.
        stalled: data 10, 0 or 1.
    """

    path: Path
    joint: str
    t: np.ndarray
    raw: np.ndarray
    despiked: np.ndarray
    filtered: np.ndarray
    speed: np.ndarray
    set_speed: np.ndarray
    threshold: np.ndarray
    stalled: np.ndarray

    @property
    def name(self) -> str:
        """File name without extension."""
        return _stem(self.path)


def read_stall_signal(path: Path | str) -> StallSignal:
    """Read a ``high_speed_stall_test/`` file: ``Program Time [s]`` and 11 data columns."""
    path = Path(path)
    rows = list(csv.reader(io.StringIO(_open_text(path))))
    if not rows or not rows[0] or not rows[0][0].strip().lower().startswith("program time"):
        raise RecordingError(path, "first line must be the 'Program Time [s], data 0 .. data 10' header")
    if len(rows[0]) < 12:
        raise RecordingError(
            path, f"header has {len(rows[0])} columns, expected 12 (time and data 0 .. data 10)"
        )
    match = re.match(r"([jJ]\d+)_", path.name)
    if not match:
        raise RecordingError(path, "file name must start with the joint (j1_ .. j4_)")
    joint = _joint_from(path, match.group(1).lower())
    d, lines = _rows(path, rows[1:], 2, width=12)
    # The firmware prints its time to 10 ms: passes may share one, none goes back.
    _check_time(path, d[:, 0], lines, "Program Time", strict=False)
    odd = np.flatnonzero((d[:, 11] != 0.0) & (d[:, 11] != 1.0))
    if odd.size:
        i = int(odd[0])
        raise RecordingError(
            path, f"line {lines[i]}: data 10 (the stall flag) is {d[i, 11]:g}, expected 0 or 1"
        )
    _check_columns(
        path,
        d,
        lines,
        [
            (8, "speed", "data 7 (measured speed)", 1.0, "rad/s"),
            (9, "speed", "data 8 (set speed)", 1.0, "rad/s"),
        ],
    )
    return StallSignal(path, joint, d[:, 0], d[:, 1], d[:, 2], d[:, 3], d[:, 8], d[:, 9], d[:, 10], d[:, 11])


@dataclass(frozen=True)
class PidErrorTest:
    """``stall_detection_test/PID_error_test.csv``: an early firmware's moves between ±1200°.

    Attributes:
        path: The file.
        t: Program time, s.
        pid_error: |PID error| (1/256 microsteps).
        threshold: The stall threshold then.
        q: Position, motor degrees.
        q_set: The move's target, motor degrees.
        stalled: 0 or 1.
    """

    path: Path
    t: np.ndarray
    pid_error: np.ndarray
    threshold: np.ndarray
    q: np.ndarray
    q_set: np.ndarray
    stalled: np.ndarray


def read_pid_error_test(path: Path | str) -> PidErrorTest:
    """Read ``PID_error_test.csv``: ``Program Time [s], PID error, Threshold, q, q_set, Stalled``."""
    path = Path(path)
    rows = list(csv.reader(io.StringIO(_open_text(path))))
    if not rows or len(rows[0]) < 6 or "pid error" not in ",".join(rows[0]).lower():
        raise RecordingError(path, "header must be 'Program Time [s],PID error,Threshold,q,q_set,Stalled'")
    d, lines = _rows(path, rows[1:], 2, width=6)
    _check_time(path, d[:, 0], lines, "Program Time", strict=False)
    deg = math.radians(1.0)
    _check_columns(path, d, lines, [(3, "position", "q", deg, "deg"), (4, "position", "q_set", deg, "deg")])
    return PidErrorTest(path, d[:, 0], d[:, 1], d[:, 2], d[:, 3], d[:, 4], d[:, 5])


# ------------------------------------------------------------ tracking error
@dataclass(frozen=True)
class TrackingRun:
    """One ``tracking_error/`` run: j1 following a ramp under the ROS 2 trajectory controller.

    Attributes:
        path: The file.
        ramp_speed: The ramp's gradient, rad/s (file name: ``record_<ramp>_<accel>_j1...``).
        max_acceleration: j1's max acceleration, rad/s².
        interface: ``position`` or ``velocity`` (file name: ``_vel_`` for velocity).
        gains: The velocity controller's ``p, i, d, kff`` (empty for position).
        t: Controller time, s from the first row.
        reference: j1's reference position, rad.
        feedback: j1's measured position, rad.
    """

    path: Path
    ramp_speed: float
    max_acceleration: float
    interface: str
    gains: dict[str, float]
    t: np.ndarray
    reference: np.ndarray
    feedback: np.ndarray

    @property
    def name(self) -> str:
        """File name without extension."""
        return _stem(self.path)


_TRACKING_NAME = re.compile(r"record_(?P<ramp>[0-9p]+)_(?P<acc>[0-9p]+)_(?P<joint>j\d)(?P<rest>.*)")
_GAIN = re.compile(r"_(p|i|d|kff)([0-9p]+)")
#: The joint the tracking test recorded (tracking_error/README.md): the replay drives j1.
TRACKING_JOINT = "j1"


def _pnum(text: str) -> float:
    return float(text.replace("p", "."))


def _name_number(path: Path, what: str, text: str) -> float:
    try:
        value = _pnum(text)
    except ValueError:
        raise RecordingError(
            path, f"{what} {text!r} in the name is not a number (p for the point: 0p314 is 0.314)"
        ) from None
    if not math.isfinite(value):
        raise RecordingError(path, f"{what} {text!r} in the name is not a finite number")
    return value


def parse_tracking_name(path: Path) -> tuple[float, float, str, str, dict[str, float]]:
    """Ramp speed, max acceleration, joint, interface and gains from a tracking file's name."""
    m = _TRACKING_NAME.fullmatch(_stem(path))
    if not m:
        raise RecordingError(
            path, "name must be record_<ramp rad/s>_<max accel rad/s²>_j1[_vel_p.._i.._d.._kff..]"
        )
    joint = _joint_from(path, m.group("joint"))
    if joint != TRACKING_JOINT:
        raise RecordingError(
            path,
            f"the name says {joint}; tracking_error/ holds j1's runs only (record_<ramp>_<max accel>_j1...)",
        )
    rest = m.group("rest")
    interface = "velocity" if rest.startswith("_vel") else "position"
    gains = (
        {k: _name_number(path, f"gain {k}", v) for k, v in _GAIN.findall(rest)}
        if interface == "velocity"
        else {}
    )
    ramp = _name_number(path, "ramp speed", m.group("ramp"))
    acc = _name_number(path, "max acceleration", m.group("acc"))
    for what, value, text in (
        ("ramp speed", ramp, m.group("ramp")),
        ("max acceleration", acc, m.group("acc")),
    ):
        if value <= 0:
            raise RecordingError(path, f"{what} {text!r} in the name must be > 0")
    deg_per_rad = math.degrees(abs(PROGRAM_REDUCTIONS[joint]))
    _check_limit(path, None, "max acceleration in the name", acc, "SETMAXACCELERATION", deg_per_rad, "deg/s²")
    return ramp, acc, joint, interface, gains


def _introspection_columns(path: Path, rows: list[list[str]], joint: str) -> tuple[np.ndarray, ...]:
    """``ros2 topic echo --csv`` of the controller manager's introspection: key, value pairs."""
    state, command = f"state_interface.{joint}/position", f"command_interface.{joint}/position"
    t, ref, fb, lines = [], [], [], []
    for i, row in enumerate(rows):
        if len(row) < 4:
            continue
        pairs = dict(zip(row[3::2], row[4::2], strict=False))
        q = pairs.get(state)
        r = pairs.get(command)
        if q is None or r is None:
            continue
        line = i + 1
        stamp = _number(path, line, row[0], "stamp, s") + _number(path, line, row[1], "stamp, ns") * 1e-9
        t.append(stamp)
        ref.append(_number(path, line, r, command))
        fb.append(_number(path, line, q, state))
        lines.append(line)
    return np.asarray(t), np.asarray(ref), np.asarray(fb), np.asarray(lines, dtype=int)


def _plotjuggler_columns(path: Path, rows: list[list[str]], index: int) -> tuple[np.ndarray, ...]:
    """A ``__time`` CSV of the velocity controller's state (reference and feedback by name)."""
    header = rows[0]
    prefix = "/velocity_joint_trajectory_controller/controller_state/"
    try:
        it = header.index("__time")
        ir = header.index(f"{prefix}reference/positions[{index}]")
        iq = header.index(f"{prefix}feedback/positions[{index}]")
    except ValueError as e:
        raise RecordingError(path, f"no reference/feedback positions[{index}] columns ({e})") from e
    width = max(it, ir, iq) + 1
    picked = []
    for i, r in enumerate(rows[1:], start=2):
        if any(c.strip() for c in r) and len(r) < width:
            raise RecordingError(path, f"line {i}: {len(r)} columns, expected {len(header)} (the header's)")
        picked.append([r[it], r[ir], r[iq]] if len(r) >= width else [])
    d, lines = _rows(path, picked, 2)
    return d[:, 0], d[:, 1], d[:, 2], lines


#: Fewest rows of j1's reference and feedback a tracking file must hold.
TRACKING_MIN_ROWS = 10


def read_tracking(path: Path | str) -> TrackingRun:
    """Read a ``tracking_error/`` file (the controller manager's or the controller's own export)."""
    path = Path(path)
    ramp, acc, joint, interface, gains = parse_tracking_name(path)
    rows = list(csv.reader(io.StringIO(_open_text(path))))
    if not rows:
        raise RecordingError(path, "empty file")
    if rows[0] and rows[0][0] == "__time":
        t, ref, fb, lines = _plotjuggler_columns(path, rows, JOINTS.index(joint))
    elif _stem(path).endswith("_JTC"):
        raise RecordingError(path, "the controller's raw state echo is not read (its _CM or plain twin is)")
    else:
        t, ref, fb, lines = _introspection_columns(path, rows, joint)
    if len(t) < TRACKING_MIN_ROWS:
        raise RecordingError(
            path,
            f"{len(t)} rows of {joint}'s position reference and feedback, expected at least "
            f"{TRACKING_MIN_ROWS} (need the position interface)",
        )
    _check_time(
        path,
        t,
        lines,
        "time",
        bounded=True,
    )
    reduction = PROGRAM_REDUCTIONS[joint]
    _check_columns(
        path,
        np.column_stack([ref, fb]),
        lines,
        [(0, "position", "reference", reduction, "rad"), (1, "position", "feedback", reduction, "rad")],
    )
    return TrackingRun(path, ramp, acc, interface, gains, t - t[0], ref, fb)


# ---------------------------------------------------------------- RW_test
@dataclass(frozen=True)
class Transactions:
    """``RW_test/<what>_<speed>kHz.csv``: time of each read and write call, per joint.

    Attributes:
        path: The file.
        what: ``position`` (getPosition/setPosition), ``velocity`` (getVelocity/setVelocity)
            or another test's name.
        clock_hz: Bus clock from the file name.
        joint: Joint of each row.
        read_us: Time of the read call, microseconds.
        write_us: Time of the write call, microseconds.
    """

    path: Path
    what: str
    clock_hz: float
    joint: np.ndarray
    read_us: np.ndarray
    write_us: np.ndarray

    @property
    def name(self) -> str:
        """File name without extension."""
        return _stem(self.path)


_RW_NAME = re.compile(r"(?P<what>.+)_(?P<khz>\d+)kHz")


def _duration(path: Path, line: int, text: str, what: str) -> float:
    """A measured time: a finite number, not negative."""
    value = _number(path, line, text, what)
    if value < 0:
        raise RecordingError(path, f"line {line}: {what} {value:g} is negative; a time measured is >= 0")
    return value


def read_transactions(path: Path | str) -> Transactions:
    """Read an ``RW_test/`` timing file: ``time [ms], iteration, joint, read [us], write [us]``."""
    path = Path(path)
    m = _RW_NAME.fullmatch(_stem(path))
    if not m:
        raise RecordingError(path, "name must be <what>_<bus speed>kHz (e.g. position_100kHz)")
    clock_hz = float(m.group("khz")) * 1e3
    if not I2C_MIN_CLOCK_HZ <= clock_hz <= I2C_MAX_CLOCK_HZ:
        raise RecordingError(
            path,
            f"bus speed {m.group('khz')} kHz in the name is outside {I2C_MIN_CLOCK_HZ / 1e3:g}-"
            f"{I2C_MAX_CLOCK_HZ / 1e3:g} kHz (100 standard mode, 400 fast mode)",
        )
    rows = list(csv.reader(io.StringIO(_open_text(path))))
    if not rows or len(rows[0]) < 5 or "read" not in rows[0][3].lower():
        raise RecordingError(
            path, "header must be 'time [ms], iteration [-], joint [-], read [us], write [us]'"
        )
    joints, values = [], []
    for i, row in enumerate(rows[1:], start=2):
        if not row:
            continue
        if len(row) < 5:
            raise RecordingError(path, f"line {i}: {len(row)} columns, expected 5")
        joints.append(_joint_from(path, row[2].strip(), i))
        values.append((_duration(path, i, row[3], "read [us]"), _duration(path, i, row[4], "write [us]")))
    if not values:
        raise RecordingError(path, "no data rows")
    v = np.asarray(values)
    return Transactions(path, m.group("what"), clock_hz, np.asarray(joints), v[:, 0], v[:, 1])


@dataclass(frozen=True)
class HandlerTimes:
    """``RW_test/baseline_joint_*.csv``: the firmware handler's time per command (``profiling_test.ino``).

    Attributes:
        path: The file.
        command: Register name of each row.
        rx_length: Payload bytes received.
        tx_length: Bytes answered.
        t_exec_us: Execution time of ``non_blocking_handler``, microseconds.
    """

    path: Path
    command: np.ndarray
    rx_length: np.ndarray
    tx_length: np.ndarray
    t_exec_us: np.ndarray

    def mean_us(self) -> dict[str, float]:
        """Mean execution time per command, microseconds."""
        return {c: float(self.t_exec_us[self.command == c].mean()) for c in dict.fromkeys(self.command)}


#: The largest handler time ``profiling_test.ino`` can print, microseconds: ``now - start``
#: of two ``unsigned long`` ``micros()`` readings, 32 bits on the joint's STM32.
HANDLER_US_MAX = 2**32 - 1


def read_handler_times(path: Path | str) -> HandlerTimes:
    """Read ``baseline_joint_*.csv``: ``time [ms], command, rx_length, tx_length, t_exec [us]``."""
    path = Path(path)
    rows = list(csv.reader(io.StringIO(_open_text(path))))
    if not rows or len(rows[0]) < 5 or "t_exec" not in rows[0][4]:
        raise RecordingError(path, "header must be 'time [ms], command, rx_length, tx_length, t_exec [us]'")
    cmds, nums = [], []
    for i, row in enumerate(rows[1:], start=2):
        if not row:
            continue
        if len(row) < 5:
            raise RecordingError(path, f"line {i}: {len(row)} columns, expected 5")
        cmds.append(row[1].strip())
        nums.append(
            (
                _number(path, i, row[2], "rx_length"),
                _number(path, i, row[3], "tx_length"),
                _duration(path, i, row[4], "t_exec [us]"),
            )
        )
        if nums[-1][2] > HANDLER_US_MAX:
            raise RecordingError(
                path,
                f"line {i}: t_exec [us] {nums[-1][2]:g} is beyond what profiling_test.ino prints "
                f"(micros() differences, at most {HANDLER_US_MAX})",
            )
    if not nums:
        raise RecordingError(path, "no data rows")
    n = np.asarray(nums)
    return HandlerTimes(path, np.asarray(cmds), n[:, 0], n[:, 1], n[:, 2])


# ------------------------------------------------------------------ a folder
@dataclass
class Recordings:
    """Every recording of a folder, by kind (each list sorted by file name)."""

    root: Path
    max_accel: list[MaxAccelRun] = field(default_factory=list)
    setting_max_val: list[SettingMaxValRun] = field(default_factory=list)
    stall_signal: list[StallSignal] = field(default_factory=list)
    pid_error_test: list[PidErrorTest] = field(default_factory=list)
    tracking: list[TrackingRun] = field(default_factory=list)
    transactions: list[Transactions] = field(default_factory=list)
    handler_times: list[HandlerTimes] = field(default_factory=list)

    def __len__(self) -> int:
        """Number of recordings."""
        return sum(len(v) for k, v in vars(self).items() if k != "root")

    def kinds(self) -> Iterator[tuple[str, list]]:
        """(kind, recordings) for every kind with at least one."""
        for k, v in vars(self).items():
            if k != "root" and v:
                yield k, v


#: The folders of the arm repository's ``test/`` layout, one per kind.
FOLDERS = (
    "maxAccel",
    "settingMaxVal",
    "high_speed_stall_test",
    "stall_detection_test",
    "tracking_error",
    "RW_test",
)


#: Endings of ``tracking_error/`` files that are not read (the controller's raw echo, its JTC twin).
TRACKING_NOT_READ = ("_JTC", "_CM")
#: Start of the ``RW_test/`` files that are handler times (the others are transactions).
HANDLER_TIMES_PREFIX = "baseline_joint"


def _csvs(folder: Path) -> list[Path]:
    """Everything in ``folder`` named as a recording: one that is no regular file is refused when read.

    Two of one name (``j1_1.csv`` beside ``j1_1.csv.gz``) are refused: each
    recording's rows and replay go by its name.
    """
    if not folder.is_dir():
        return []
    found = sorted(p for p in folder.iterdir() if p.name.endswith((".csv", ".csv.gz")))
    seen: dict[str, Path] = {}
    for p in found:
        other = seen.setdefault(_stem(p), p)
        if other is not p:
            raise RecordingError(
                p, f"{other.name} beside it is a recording of the same name ({_stem(p)}); keep one"
            )
    return found


def recording_files(root: Path | str | None = None) -> list[Path]:
    """Every file :func:`find_recordings` reads under ``root`` (default: the packaged ones), or would.

    Also those of ``tracking_error/`` it leaves out (``_CM``, ``_JTC``): a
    command's outputs must not replace any of them.
    """
    root = Path(root) if root is not None else DATA_DIR
    if not root.is_dir():
        return []
    files = []
    for folder in FOLDERS:
        path = root / folder
        if path.is_dir():
            files += sorted(p for p in path.iterdir() if p.name.endswith((".csv", ".csv.gz")))
    return files


def find_recordings(root: Path | str | None = None) -> Recordings:
    """Read every recording under ``root`` (default: the packaged ones).

    Folders follow the arm repository's ``test/``: ``maxAccel/``,
    ``settingMaxVal/``, ``high_speed_stall_test/``, ``stall_detection_test/``,
    ``tracking_error/``, ``RW_test/``. Missing folders are fine; a folder
    with none of them is an error, and so is any file a reader refuses.

    Raises:
        RecordingError: ``root`` holds no recordings, or one cannot be read.
    """
    root = Path(root) if root is not None else DATA_DIR
    try:
        os.stat(root)
    except OSError as e:
        if e.errno == errno.ELOOP:  # seen: "is not a folder"
            raise RecordingError(root, "is a loop of symlinks") from e
    if not root.is_dir():
        raise RecordingError(root, "is not a folder")
    rec = Recordings(root)
    rec.max_accel = [read_max_accel(p) for p in _csvs(root / "maxAccel")]
    rec.setting_max_val = [read_setting_max_val(p) for p in _csvs(root / "settingMaxVal")]
    rec.stall_signal = [read_stall_signal(p) for p in _csvs(root / "high_speed_stall_test")]
    rec.pid_error_test = [read_pid_error_test(p) for p in _csvs(root / "stall_detection_test")]
    tracking = [p for p in _csvs(root / "tracking_error") if not _stem(p).endswith(TRACKING_NOT_READ)]
    rec.tracking = [read_tracking(p) for p in tracking]
    for p in _csvs(root / "RW_test"):
        if _stem(p).startswith(HANDLER_TIMES_PREFIX):
            rec.handler_times.append(read_handler_times(p))
        else:
            rec.transactions.append(read_transactions(p))
    if not len(rec):
        raise RecordingError(
            root,
            "holds no recordings: expected maxAccel/, settingMaxVal/, high_speed_stall_test/, "
            "stall_detection_test/, tracking_error/ or RW_test/ with .csv files "
            "(the arm repository's test/ layout)",
        )
    return rec


def finite(x: float) -> bool:
    """Whether ``x`` is a finite number."""
    return isinstance(x, int | float) and math.isfinite(x)
