"""The console's ``--state`` file: the simulated arm kept between ``bioscara`` commands.

Only the ``emulated`` and ``sim`` backends have a state to keep. Without the
file every command starts from a powered-up arm (not homed, not enabled), so
``enable`` then ``home`` then ``status`` needs it. The file is JSON (UTF-8),
written after every command, also a failed one, with
:func:`bioscara_gym.fsutil.atomic_write_text`::

    {"format": "bioscara-console-state", "version": 1,
     "backend": "emulated", "config": "<hash of joints and gripper>",
     "time_s": 6.64,                      # simulated time
     "mujoco": [...],                     # mjSTATE_INTEGRATION, floats
     "firmware": {"j1": {...}, ...},      # FirmwareCore.snapshot() per joint;
                                          # enums as {"enum": NAME}, Infinity/NaN
                                          # as Python's json writes them
     "drive": {"j1": {...}, ...},         # the drive model's state per joint
                                          # (its random generator is not kept)
     "host": {"gripper": {"enabled": false, "width_m": 0.08},
              "homing": {"j1": 0.03},     # homings left running (--no-wait)
              "stats": {"j1": {"transactions": 12, ...}}}}

The firmware keeps what the real joints keep across a host restart (flags,
enable state, encoder zero, HOMEOFFSET); ``init`` reads HOMEOFFSET back as on
the real arm. The host part is what the real host would have in memory: the
gripper (no feedback), homings still running, bus statistics. A file that is
not such JSON, or was saved by another backend or with another arm
configuration, or holds a value the firmware cannot (a current above
100 %, a float beyond float32, :data:`FIRMWARE_VALUES`) or the
simulation should not (a number beyond :data:`MAX_SIM_VALUE`, a drive
parameter not the configuration's, a negative count, a gripper width
outside its range), is refused with one line naming the key, and left as it
is (delete it to start over); a missing file means a powered-up arm and is
created (in a folder that exists: a missing one is refused, not made),
unless the command is refused.
Simulated time does not advance between commands, only while a command runs (``home``, ``move``,
``gripper``, ``monitor``). The ``mock`` backend does not persist (``--state``
is refused), nor does ``i2c``: the real arm keeps its own state.

One command at a time: a command holds ``FILE.lock`` (:func:`lock_state`)
from reading the file until it has written it, and a second command on the
same file is refused at once, naming the holder's pid, rather than losing
one of the two updates. ``monitor`` holds it until it quits. The command
that made ``FILE.lock`` removes it when it is done.
"""

from __future__ import annotations

import dataclasses
import hashlib
import json
import math
from collections.abc import Callable, Iterable, Mapping
from dataclasses import dataclass, field
from enum import Enum
from pathlib import Path
from typing import Any

import numpy as np

from bioscara_gym.errors import StateFileError, StateFileInUseError
from bioscara_gym.fsutil import LockFile, atomic_write_text, output_problem, read_json
from bioscara_gym.hardware.backends import Backend
from bioscara_gym.hardware.config import ArmConfig
from bioscara_gym.hardware.motor import KinematicStepper
from bioscara_gym.hardware.stats import CommStats

#: ``format`` and ``version`` of the state file.
STATE_FORMAT = "bioscara-console-state"
STATE_VERSION = 2


@dataclass
class HostFacts:
    """What the host must remember between commands (the rest lives in the firmware).

    Attributes:
        gripper_enabled: Whether the servo is driven.
        gripper_width_m: Last commanded width in m (the servo has no feedback);
            ``None`` when unknown.
        homing: Joint name to signed homing speed of homings still running.
        stats: Joint name to :class:`~bioscara_gym.hardware.stats.CommStats` counters.
    """

    gripper_enabled: bool = False
    gripper_width_m: float | None = None
    homing: dict[str, float] = field(default_factory=dict)
    stats: dict[str, dict[str, int]] = field(default_factory=dict)


def config_fingerprint(config: ArmConfig) -> str:
    """A short hash of the joints and gripper, to refuse a state saved with another arm."""
    return hashlib.sha256(repr((config.joints, config.gripper)).encode()).hexdigest()[:16]


def _encode(value: object) -> object:
    """Firmware snapshot value to JSON: enums by name, tuples as lists, numpy scalars as Python."""
    if isinstance(value, Enum):
        return {"enum": value.name}
    if isinstance(value, tuple):
        return [_encode(v) for v in value]
    if isinstance(value, bool) or value is None or isinstance(value, str):
        return value
    if isinstance(value, int):
        return int(value)
    if isinstance(value, float):
        return float(value)
    item = getattr(value, "item", None)  # numpy scalars
    if callable(item):
        return _encode(item())
    raise TypeError(f"cannot store {type(value).__name__} {value!r} in the state file")


def _decode(saved: object, like: object, where: str) -> object:
    """Decode ``saved`` into the type of ``like`` (the fresh firmware's value)."""
    if isinstance(like, Enum):
        cls = type(like)
        if isinstance(saved, dict) and set(saved) == {"enum"} and saved["enum"] in cls.__members__:
            return cls[saved["enum"]]
        if isinstance(saved, int) and not isinstance(saved, bool):
            try:  # IntEnum registers may hold an unknown register byte
                return cls(saved)
            except ValueError:
                return saved
        raise StateFileError(f"{where}: {saved!r} is not a {cls.__name__}")
    if isinstance(like, tuple):
        if not isinstance(saved, list) or len(saved) != len(like):
            raise StateFileError(f"{where}: {saved!r} is not a list of {len(like)}")
        return tuple(_decode(s, ref, where) for s, ref in zip(saved, like, strict=True))
    if isinstance(like, bool):
        if not isinstance(saved, bool):
            raise StateFileError(f"{where}: {saved!r} is not true or false")
        return saved
    if isinstance(like, (int, float)):
        if isinstance(saved, bool) or not isinstance(saved, (int, float)):
            raise StateFileError(f"{where}: {saved!r} is not a number")
        return saved
    return saved


def lock_path(path: Path) -> Path:
    """The lock file of the state file ``path``: ``path`` plus ``.lock``."""
    return path.with_name(path.name + ".lock")


def lock_state(path: Path) -> LockFile:
    """Hold the state file ``path`` for one command; release the returned lock when done.

    The lock file is removed when the lock is released if this call made it
    (:class:`~bioscara_gym.fsutil.LockFile`). A path whose folder does not
    exist is refused, not made (seen: ``--state nodir/x.json`` made ``nodir``).

    Raises:
        StateFileInUseError: Another command holds it (the message names its pid).
        StateFileError: The path cannot be a state file (its folder is missing,
            a file, or refuses a file), or the lock file cannot be created.
    """
    above = next((p for p in Path(path).parents if p.exists()), None)
    if above is not None and not above.is_dir():  # the lock's error said "File exists"
        raise StateFileError(f"state file {path}: {above} is a file, not a folder")
    if Path(path).exists() and not Path(path).is_file():  # refused before its lock is made beside it
        raise StateFileError(
            f"state file {path} is not a regular file (a directory or a device); pick another path"
        )
    problem = output_problem(path)
    if problem is not None:
        raise StateFileError(f"state file {path}: {problem}")
    lock = LockFile(lock_path(path))
    try:
        lock.acquire()
    except BlockingIOError as e:
        raise StateFileInUseError(path, lock.holder()) from e
    except OSError as e:
        raise StateFileError(f"cannot lock state file {path}: {lock.path}: {e.strerror or e}") from e
    return lock


def save_state(path: Path, backend: Backend, facts: HostFacts) -> None:
    """Write the simulated arm and the host facts to ``path`` (format: module docstring).

    Raises:
        StateFileError: The backend has no simulation to save.
        OSError: The file could not be written.
    """
    if backend.sim is None:
        raise StateFileError(f"--state: the {backend.name} backend has no simulated state to save")
    mj_state, cores, drives = backend.sim.snapshot()  # type: ignore[attr-defined]
    doc = {
        "format": STATE_FORMAT,
        "version": STATE_VERSION,
        "backend": backend.name,
        "config": config_fingerprint(backend.config),
        "time_s": backend.clock.now(),
        "mujoco": [float(x) for x in mj_state],
        "firmware": {name: {k: _encode(v) for k, v in core.items()} for name, core in cores.items()},
        "drive": {
            name: {k: _encode(v) for k, v in drive.items() if k != "rng"} for name, drive in drives.items()
        },
        "host": {
            "gripper": {"enabled": facts.gripper_enabled, "width_m": facts.gripper_width_m},
            "homing": dict(facts.homing),
            "stats": facts.stats,
        },
    }
    atomic_write_text(path, json.dumps(doc, indent=1) + "\n")


def _host_facts(
    doc: Mapping[str, Any], names: Iterable[str], gripper_range: tuple[float, float], where: str
) -> HostFacts:
    host = doc.get("host")
    if not isinstance(host, dict):
        raise StateFileError(f"{where}: no 'host' object")
    gripper = host.get("gripper", {})
    unknown = _unknown_keys(host, HOST_KEYS, "host.") or (
        _unknown_keys(gripper, GRIPPER_KEYS, "host.gripper.") if isinstance(gripper, dict) else None
    )
    if unknown is not None:  # seen: accepted, and dropped when the file was written again
        raise StateFileError(f"{where}: {unknown}")
    enabled = gripper.get("enabled") if isinstance(gripper, dict) else None
    width = gripper.get("width_m") if isinstance(gripper, dict) else None
    if not isinstance(enabled, bool) or not (width is None or _finite_number(width)):
        raise StateFileError(f"{where}: host.gripper must be {{'enabled': bool, 'width_m': number}}")
    low, high = gripper_range
    if width is not None and not low <= width <= high:  # was shown as the servo's nearest width
        raise StateFileError(
            f"{where}: host.gripper.width_m {width!r} is outside the gripper's {low:g} to {high:g} m"
        )
    names = set(names)
    homing = host.get("homing", {})
    if not isinstance(homing, dict) or not all(
        n in names and _finite_number(s) and s != 0 for n, s in homing.items()
    ):
        raise StateFileError(f"{where}: host.homing must map joint names to non-zero speeds")
    stats = host.get("stats", {})
    counters = {f.name for f in dataclasses.fields(CommStats)}
    if not isinstance(stats, dict) or not all(
        n in names
        and isinstance(c, dict)
        and set(c) <= counters  # a file saved by an older version has fewer counters
        for n, c in stats.items()
    ):
        raise StateFileError(f"{where}: host.stats must map joint names to {sorted(counters)}")
    for n, c in stats.items():
        wrong = next((k for k, v in c.items() if not _is_count(v)), None)
        if wrong is not None:
            raise StateFileError(f"{where}: host.stats.{n}.{wrong} is {c[wrong]!r}; expected {COUNT}")
    return HostFacts(bool(enabled), None if width is None else float(width), dict(homing), stats)


#: Largest magnitude of a number in a state's simulation (positions, speeds, the time in s).
MAX_SIM_VALUE = 1e9


def _finite_number(x: object) -> bool:
    """Whether ``x`` is a number of at most :data:`MAX_SIM_VALUE` (not a bool; 10**400 overflows).

    The time 1e308 is finite, yet the firmware's ``millis()`` of it is not.
    """
    if isinstance(x, bool) or not isinstance(x, int | float):
        return False
    try:
        return math.isfinite(x) and abs(x) <= MAX_SIM_VALUE
    except OverflowError:
        return False


def _holds_nan(value: object) -> bool:
    """Whether ``value`` is NaN or a tuple holding one (the drive's closed loop and estimator)."""
    if isinstance(value, tuple):
        return any(_holds_nan(v) for v in value)
    return isinstance(value, float) and math.isnan(value)


#: The largest float32: the firmware's float registers hold nothing larger but inf (and NaN).
FLOAT32_MAX = 3.4028234663852886e38


#: What a counter of the state file is.
COUNT = "a count (a whole number, 0 to 2**63 - 1)"


def _is_count(x: object) -> bool:
    """Whether ``x`` is a whole number from 0 to 2**63 - 1 (not a bool; seen: 10**400 kept)."""
    return isinstance(x, int) and not isinstance(x, bool) and 0 <= x < 2**63


#: The keys of a state file, of its ``host`` and of ``host.gripper`` (:func:`save_state` writes them).
STATE_KEYS = frozenset(
    {"format", "version", "backend", "config", "time_s", "mujoco", "firmware", "drive", "host"}
)
HOST_KEYS = frozenset({"gripper", "homing", "stats"})
GRIPPER_KEYS = frozenset({"enabled", "width_m"})


def _unknown_keys(doc: Mapping[str, object], known: frozenset[str], prefix: str) -> str | None:
    """A line naming the first key of ``doc`` not in ``known``, or ``None``."""
    unknown = sorted(k for k in doc if k not in known)
    if not unknown:
        return None
    keys = ", ".join(sorted(known))
    return f"has {prefix}{unknown[0]}, which a state file does not; it has {prefix}{{{keys}}}"


def _in_bytes(high: int) -> Callable[[object], bool]:
    """A test of a whole number from 0 to ``high``."""
    return lambda x: _is_count(x) and x <= high  # type: ignore[operator]


def _float32(x: object) -> bool:
    """Whether ``x`` is a value a float32 register can hold: inf and NaN too, as the firmware takes them."""
    if isinstance(x, bool) or not isinstance(x, int | float):
        return False
    try:
        return not math.isfinite(x) or abs(x) <= FLOAT32_MAX
    except OverflowError:
        return False


def _payload(x: object) -> bool:
    """Whether ``x`` is a blocking command's payload as decoded: a 32-bit integer or a finite float32."""
    if isinstance(x, int) and not isinstance(x, bool):
        return -(2**31) <= x < 2**32
    return _float32(x) and math.isfinite(x)  # type: ignore[arg-type]  # HOME's int() of inf failed


def _homing(x: object) -> bool:
    """Whether ``x`` is the firmware's homing tuple: direction, RPM, sensitivity, current (HOME's bytes)."""
    if not isinstance(x, tuple) or len(x) != 4 or x[0] not in (1, -1) or isinstance(x[0], bool):
        return False
    rpm = x[1]
    number = isinstance(rpm, int | float) and not isinstance(rpm, bool)
    return (
        number and 0 <= rpm <= 0xFF and _is_count(x[2]) and x[2] <= 0xFF and _is_count(x[3]) and x[3] <= 0xFF
    )


_BYTE = (_in_bytes(0xFF), "a byte (0-255)")
_PERCENT = (_in_bytes(100), "a current in % (0-100: the firmware caps it)")
_FLOAT32 = (_float32, f"a float32 (at most {FLOAT32_MAX:.8g} in size, or inf or NaN)")
#: What each firmware value can be: what its register or variable holds (firmware.py, codec.py).
#: A value not named is a number of the simulation (:data:`MAX_SIM_VALUE`) or a flag.
FIRMWARE_VALUES: dict[str, tuple[Callable[[object], bool], str]] = {
    "drive_current": _PERCENT,  # SETUP byte0 and SETCURRENT, capped at 100
    "hold_current": _PERCENT,  # SETUP byte1 and SETHOLDCURRENT, capped at 100
    "motor_current": (_in_bytes(0xFF), "a current in % (0-255: HOME's current byte is not capped)"),
    "brake_mode": _BYTE,
    "stall_sensitivity": _BYTE,
    "_pending_reg": (_in_bytes(0xFF), "a register byte (0-255)"),
    "qd_set": _FLOAT32,
    "q_set": _FLOAT32,
    "home_offset": _FLOAT32,  # NaN until the host stores one
    "max_velocity": _FLOAT32,
    "max_acceleration": _FLOAT32,
    "target_rpm": _FLOAT32,  # SETRPM's value (±inf: the top speed) or the homing's RPM
    "_pending_arg": (_payload, "a finite payload: a 32-bit integer or float32"),
    "_homing": (_homing, "[direction 1 or -1, RPM 0-255, sensitivity 0-255, current 0-255]"),
}

#: The drive model's counters: whole numbers >= 0.
DRIVE_COUNTERS = frozenset({"lost_sync", "pole_slips", "resyncs"})
#: The drive model's parameters (from the configuration, never changed by a command): as a fresh model's.
DRIVE_PARAMETERS = frozenset({"lower_stop_deg", "upper_stop_deg", "load_accel", "max_speed_dps"})
_SIM_NUMBER = f"a finite number, at most {MAX_SIM_VALUE:g} in size"


def _sim_numbers(value: object) -> bool:
    """Whether ``value`` (a number or a tuple of them) is finite and at most :data:`MAX_SIM_VALUE`."""
    if isinstance(value, tuple):
        return all(_sim_numbers(v) for v in value)
    return _finite_number(value) if isinstance(value, int | float) and not isinstance(value, bool) else True


def _check_firmware(values: Mapping[str, object], key: str, where: str) -> None:
    """Refuse a firmware value its register or variable cannot hold (``key``: ``firmware.j1``)."""
    for k, v in values.items():
        test, expected = FIRMWARE_VALUES.get(k, (_sim_numbers, _SIM_NUMBER))
        if not test(v):
            raise StateFileError(f"{where}: {key}.{k} is {_shown(v)}; expected {expected}")


def _check_drive(values: Mapping[str, object], fresh: Mapping[str, object], key: str, where: str) -> None:
    """Refuse a drive value no drive model has (``key``: ``drive.j1``); NaN was refused before."""
    for k, v in values.items():
        if k in DRIVE_PARAMETERS:
            if v != fresh[k]:
                raise StateFileError(
                    f"{where}: {key}.{k} is {_shown(v)}; expected {fresh[k]!r}, this configuration's "
                    "(a parameter of the drive model, not state)"
                )
        elif k in DRIVE_COUNTERS:
            if not _is_count(v):
                raise StateFileError(f"{where}: {key}.{k} is {_shown(v)}; expected {COUNT}")
        elif not _sim_numbers(v):
            raise StateFileError(f"{where}: {key}.{k} is {_shown(v)}; expected {_SIM_NUMBER}")


def _shown(value: object) -> str:
    """``value`` as the file has it (a tuple as a list)."""
    return repr(list(value)) if isinstance(value, tuple) else repr(value)


def load_state(path: Path, backend: Backend) -> HostFacts:
    """Restore the simulated arm from ``path`` and return the host facts.

    Raises:
        StateFileError: Unreadable, not a state file, or saved by another
            backend or with another arm configuration; nothing is changed.
    """
    where = f"state file {path}"
    if path.exists() and not path.is_file():
        raise StateFileError(f"{where} is not a regular file (a directory or a device); pick another path")
    try:
        doc = read_json(path)
    except (OSError, ValueError) as e:
        raise StateFileError(f"{where} cannot be read ({e}); delete it to start from a powered-up arm") from e
    if not isinstance(doc, dict) or doc.get("format") != STATE_FORMAT:
        raise StateFileError(f"{where} is not a bioscara console state file; delete it or pick another")
    if type(doc.get("version")) is not int or doc["version"] != STATE_VERSION:  # 2.0 is no version
        raise StateFileError(
            f"{where} has version {doc.get('version')!r}; this console reads {STATE_VERSION}"
        )
    if doc.get("backend") != backend.name:
        raise StateFileError(
            f"{where} was saved by the {doc.get('backend')} backend; use --backend {doc.get('backend')} "
            "or another file"
        )
    if doc.get("config") != config_fingerprint(backend.config):
        raise StateFileError(
            f"{where} was saved with another arm configuration (joints or gripper differ); use the same "
            "--config or another file"
        )
    unknown = _unknown_keys(doc, STATE_KEYS, "")
    if unknown is not None:
        raise StateFileError(f"{where}: {unknown}")
    if not _finite_number(doc.get("time_s")) or doc["time_s"] < 0:
        raise StateFileError(
            f"{where}: 'time_s' is {doc.get('time_s')!r}; expected the simulated time in s, "
            f"0 to {MAX_SIM_VALUE:g}"
        )
    sim = backend.sim
    fresh_state, fresh_cores, fresh_drives = sim.snapshot()  # type: ignore[union-attr]
    mj = doc.get("mujoco")
    if not isinstance(mj, list) or len(mj) != len(fresh_state) or not all(_finite_number(x) for x in mj):
        # NaN here made MuJoCo's state NaN: the joints then read NaN, blamed on the wiring.
        n, most = len(fresh_state), f"{MAX_SIM_VALUE:g}"
        raise StateFileError(f"{where}: 'mujoco' must be a list of {n} finite numbers, at most {most}")
    saved_cores = doc.get("firmware")
    if not isinstance(saved_cores, dict) or set(saved_cores) != set(fresh_cores):
        raise StateFileError(f"{where}: 'firmware' must hold the joints {', '.join(fresh_cores)}")
    cores: dict[str, dict[str, object]] = {}
    for name, fresh in fresh_cores.items():
        saved = saved_cores[name]
        if not isinstance(saved, dict) or set(saved) != set(fresh):
            raise StateFileError(f"{where}: firmware state of {name} does not match this firmware emulation")
        cores[name] = {k: _decode(saved[k], fresh[k], f"{where}: {name}.{k}") for k in fresh}
        if not 0 <= cores[name]["flags"] <= 0xFF:  # type: ignore[operator]  # the reply's flags byte
            raise StateFileError(f"{where}: {name}.flags {cores[name]['flags']!r} is not a byte (0-255)")
        _check_firmware(cores[name], f"firmware.{name}", where)
    saved_drives = doc.get("drive")
    if not isinstance(saved_drives, dict) or set(saved_drives) != set(fresh_drives):
        raise StateFileError(f"{where}: 'drive' must hold the joints {', '.join(fresh_drives)}")
    drives: dict[str, dict[str, object]] = {}
    for name, fresh in fresh_drives.items():
        keep = {k: v for k, v in fresh.items() if k != "rng"}
        saved = saved_drives[name]
        if isinstance(saved, dict):
            saved = {**{k: v for k, v in KinematicStepper.LATER_STATE.items() if k in keep}, **saved}
        if not isinstance(saved, dict) or set(saved) != set(keep):
            raise StateFileError(f"{where}: drive state of {name} does not match this drive model")
        drives[name] = {k: _decode(saved[k], keep[k], f"{where}: {name}.{k}") for k in keep}
        nan = next((k for k, v in drives[name].items() if _holds_nan(v)), None)
        if nan is not None:  # (an end stop may be infinite: none on that side)
            raise StateFileError(f"{where}: drive state {name}.{nan} is NaN")
        _check_drive(drives[name], keep, f"drive.{name}", where)
    gripper = backend.config.gripper
    facts = _host_facts(doc, fresh_cores, (gripper.min, gripper.max), where)
    sim.restore((np.asarray(mj, dtype=float), cores, drives))  # type: ignore[union-attr]
    return facts
