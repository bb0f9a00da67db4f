"""Readers of the real arm's recordings, one per kind, in the arm repository's ``test/`` layout.

A folder laid out like ``test/`` of DALSA-Lab/bioscara (the packaged
:data:`DATA_DIR`, or a user's own) is read by :func:`find_recordings`; each
reader takes one file (``.csv`` or ``.csv.gz``) and returns its figures with
the settings its name or header states. Anything a reader cannot use raises
:class:`RecordingError`, whose message is one line naming the file and the
problem.
"""

from __future__ import annotations

import csv
import gzip
import io
import math
import re
import zlib
from collections.abc import Iterator
from dataclasses import dataclass, field
from importlib import resources
from pathlib import Path

import numpy as np

from bioscara_gym.errors import RecordingError
from bioscara_gym.fsutil import read_bytes

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
]

#: The joints a recording may name, with the arm's reductions (motor turns per
#: joint unit; the test programs' ``Joint(...)`` lines, which match the packaged configuration).
JOINTS = ("j1", "j2", "j3", "j4")


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


def _stem(path: Path) -> str:
    name = path.name
    for suffix in (".csv.gz", ".csv"):
        if name.endswith(suffix):
            return name[: -len(suffix)]
    return name


def _floats(path: Path, rows: list[list[str]], first_line: int, width: int | None = None) -> np.ndarray:
    """Rows of numbers as a 2-D array; a bad cell is an error naming its line."""
    out = []
    for i, row in enumerate(rows):
        cells = [c.strip() for c in row]
        if not any(cells):
            continue
        if width is not None and len(cells) < width:
            raise RecordingError(path, f"line {first_line + i}: {len(cells)} columns, expected {width}")
        try:
            values = [float(c) for c in (cells[:width] if width else cells)]
        except ValueError as e:
            raise RecordingError(path, f"line {first_line + i}: not a number ({e})") from e
        bad = next((c for c, v in zip(cells, values, strict=False) if not math.isfinite(v)), None)
        if bad is not None:  # NaN or beyond float's range: no measurement (it broke every figure after)
            raise RecordingError(path, f"line {first_line + i}: {bad!r} is not a finite number")
        out.append(values)
    if not out:
        raise RecordingError(path, "no data rows")
    return np.asarray(out, dtype=float)


def _joint_from(path: Path, text: str) -> str:
    if text not in JOINTS:
        raise RecordingError(path, f"unknown joint {text!r}; expected one of {', '.join(JOINTS)}")
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


def read_max_accel(path: Path | str) -> MaxAccelRun:
    """Read a ``maxAccel/`` file: the program's header, then ``t, q, qd, qdd``."""
    path = Path(path)
    lines = _open_text(path).splitlines()
    settings: dict[str, str] = {}
    start = None
    for i, line in enumerate(lines):
        key, sep, value = line.partition(":")
        if sep and key.strip().lower() in _HEADER_KEYS:
            settings[_HEADER_KEYS[key.strip().lower()]] = value.strip()
        if line.replace(" ", "").lower().startswith("t,q,qd"):
            start = i + 1
            break
    if start is None:
        raise RecordingError(path, "no 't, q, qd, qdd' header line (not a maxAccel recording?)")
    missing = [k for k in _HEADER_KEYS.values() if k not in settings]
    if missing:
        raise RecordingError(path, f"header lacks {', '.join(missing)} (the test program prints them)")
    joint = _joint_from(path, settings["joint"])
    try:
        vel, acc, cur = (float(settings[k]) for k in ("max_velocity", "max_acceleration", "current"))
    except ValueError as e:
        raise RecordingError(path, f"header value is not a number ({e})") from e
    if not (vel > 0 and acc > 0 and 0 < cur <= 100):
        raise RecordingError(path, f"header: vel {vel}, max accel {acc} must be > 0 and current {cur} 1-100")
    data = _floats(path, list(csv.reader(lines[start:])), start + 1, width=3)
    if np.any(np.diff(data[:, 0]) <= 0):
        raise RecordingError(path, "time column t does not increase")
    return MaxAccelRun(path, joint, vel, acc, cur, data[:, 0], data[:, 1], data[:, 2])


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


def read_setting_max_val(path: Path | str) -> SettingMaxValRun:
    """Read a ``settingMaxVal/`` file: ``maxAccel:``, ``maxVel:``, then ``time, position, velocity, ...``."""
    path = Path(path)
    lines = _open_text(path).splitlines()
    values: dict[str, float] = {}
    start = None
    for i, line in enumerate(lines):
        key, sep, value = line.partition(":")
        if sep and key.strip() in ("maxAccel", "maxVel"):
            try:
                values[key.strip()] = float(value)
            except ValueError as e:
                raise RecordingError(path, f"line {i + 1}: {key.strip()} is not a number") from e
        elif line.replace(" ", "").startswith("time,position,velocity"):
            start = i + 1
            break
    if start is None or len(values) < 2:
        raise RecordingError(
            path, "needs 'maxAccel:' and 'maxVel:' lines, then a 'time, position, velocity' header"
        )
    data = _floats(path, list(csv.reader(lines[start:])), start + 1, width=3)
    return SettingMaxValRun(
        path,
        values["maxAccel"],
        values["maxVel"],
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
    match = re.match(r"([jJ][1-4])_", path.name)
    if not match:
        raise RecordingError(path, "file name must start with the joint (j1_ .. j4_)")
    joint = _joint_from(path, match.group(1).lower())
    d = _floats(path, rows[1:], 2, width=12)
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
    d = _floats(path, rows[1:], 2, width=6)
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


def _pnum(text: str) -> float:
    return float(text.replace("p", "."))


def parse_tracking_name(path: Path) -> tuple[float, float, str, str, dict[str, float]]:
    """Ramp speed, max acceleration, joint, interface and gains from a tracking file's name."""
    m = _TRACKING_NAME.fullmatch(_stem(path))
    if not m:
        raise RecordingError(
            path, "name must be record_<ramp rad/s>_<max accel rad/s²>_j1[_vel_p.._i.._d.._kff..]"
        )
    joint = _joint_from(path, m.group("joint"))
    rest = m.group("rest")
    interface = "velocity" if rest.startswith("_vel") else "position"
    gains = {k: _pnum(v) for k, v in _GAIN.findall(rest)} if interface == "velocity" else {}
    try:
        return _pnum(m.group("ramp")), _pnum(m.group("acc")), joint, interface, gains
    except ValueError as e:
        raise RecordingError(path, f"ramp or acceleration in the name is not a number ({e})") from e


def _introspection_columns(path: Path, rows: list[list[str]], joint: str) -> tuple[np.ndarray, ...]:
    """``ros2 topic echo --csv`` of the controller manager's introspection: key, value pairs."""
    t, ref, fb = [], [], []
    for row in rows:
        if len(row) < 4:
            continue
        try:
            stamp = float(row[0]) + float(row[1]) * 1e-9
        except ValueError:
            continue
        pairs = dict(zip(row[3::2], row[4::2], strict=False))
        q = pairs.get(f"state_interface.{joint}/position")
        r = pairs.get(f"command_interface.{joint}/position")
        if q is None or r is None:
            continue
        t.append(stamp)
        ref.append(float(r))
        fb.append(float(q))
    return np.asarray(t), np.asarray(ref), np.asarray(fb)


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
    d = _floats(path, [[r[it], r[ir], r[iq]] for r in rows[1:] if len(r) > max(it, ir, iq)], 2)
    return d[:, 0], d[:, 1], d[:, 2]


def read_tracking(path: Path | str) -> TrackingRun:
    """Read a ``tracking_error/`` file (the controller manager's or the controller's own export)."""
    path = Path(path)
    ramp, acc, joint, interface, gains = parse_tracking_name(path)
    rows = list(csv.reader(io.StringIO(_open_text(path))))
    if not rows:
        raise RecordingError(path, "empty file")
    if rows[0] and rows[0][0] == "__time":
        t, ref, fb = _plotjuggler_columns(path, rows, JOINTS.index(joint))
    elif _stem(path).endswith("_JTC"):
        raise RecordingError(path, "the controller's raw state echo is not read (its _CM or plain twin is)")
    else:
        t, ref, fb = _introspection_columns(path, rows, joint)
    if len(t) < 10:
        raise RecordingError(
            path, f"no {joint} position reference and feedback found (need the position interface)"
        )
    order = np.argsort(t, kind="stable")
    t, ref, fb = t[order], ref[order], fb[order]
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


def read_transactions(path: Path | str) -> Transactions:
    """Read an ``RW_test/`` timing file: ``time [ms], iteration, joint, read [us], write [us]``."""
    path = Path(path)
    m = _RW_NAME.fullmatch(_stem(path))
    if not m:
        raise RecordingError(path, "name must be <what>_<bus speed>kHz (e.g. position_100kHz)")
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
        joints.append(_joint_from(path, row[2].strip()))
        try:
            values.append((float(row[3]), float(row[4])))
        except ValueError as e:
            raise RecordingError(path, f"line {i}: not a number ({e})") from e
    if not values:
        raise RecordingError(path, "no data rows")
    v = np.asarray(values)
    return Transactions(
        path, m.group("what"), float(m.group("khz")) * 1e3, np.asarray(joints), v[:, 0], v[:, 1]
    )


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
        try:
            nums.append((float(row[2]), float(row[3]), float(row[4])))
        except ValueError as e:
            raise RecordingError(path, f"line {i}: not a number ({e})") from e
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


def _csvs(folder: Path) -> list[Path]:
    """Everything in ``folder`` named as a recording: one that is no regular file is refused when read."""
    if not folder.is_dir():
        return []
    return sorted(p for p in folder.iterdir() if p.name.endswith((".csv", ".csv.gz")))


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
    if not root.is_dir():
        raise RecordingError(root, "is not a folder")
    rec = Recordings(root)
    rec.max_accel = [read_max_accel(p) for p in _csvs(root / "maxAccel")]
    rec.setting_max_val = [read_setting_max_val(p) for p in _csvs(root / "settingMaxVal")]
    rec.stall_signal = [read_stall_signal(p) for p in _csvs(root / "high_speed_stall_test")]
    rec.pid_error_test = [read_pid_error_test(p) for p in _csvs(root / "stall_detection_test")]
    tracking = [p for p in _csvs(root / "tracking_error") if not _stem(p).endswith(("_JTC", "_CM"))]
    rec.tracking = [read_tracking(p) for p in tracking]
    for p in _csvs(root / "RW_test"):
        if _stem(p).startswith("baseline_joint"):
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
