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
configuration, is refused with a message (delete it to start over); a
missing file means a powered-up arm and is created. Simulated time does not
advance between commands, only while a command runs (``home``, ``move``,
``gripper``, ``monitor``). The ``mock`` backend does not persist (``--state``
is refused), nor does ``i2c``: the real arm keeps its own state.

One command at a time: a command holds ``FILE.lock`` (:func:`lock_state`)
from reading the file until it has written it, and a second command on the
same file is refused at once, naming the holder's pid, rather than losing
one of the two updates. ``monitor`` holds it until it quits.
"""

from __future__ import annotations

import dataclasses
import hashlib
import json
import math
from collections.abc import Iterable, Mapping
from dataclasses import dataclass, field
from enum import Enum
from pathlib import Path
from typing import Any

import numpy as np

from bioscara_gym.errors import StateFileError, StateFileInUseError
from bioscara_gym.fsutil import LockFile, atomic_write_text, read_json
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

    Raises:
        StateFileInUseError: Another command holds it (the message names its pid).
        StateFileError: The lock file cannot be created.
    """
    above = next((p for p in Path(path).parents if p.exists()), None)
    if above is not None and not above.is_dir():  # the lock's error said "File exists"
        raise StateFileError(f"state file {path}: {above} is a file, not a folder")
    if Path(path).exists() and not Path(path).is_file():  # refused before its lock is made beside it
        raise StateFileError(
            f"state file {path} is not a regular file (a directory or a device); pick another path"
        )
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


def _host_facts(doc: Mapping[str, Any], names: Iterable[str], where: str) -> HostFacts:
    host = doc.get("host")
    if not isinstance(host, dict):
        raise StateFileError(f"{where}: no 'host' object")
    gripper = host.get("gripper", {})
    enabled = gripper.get("enabled") if isinstance(gripper, dict) else None
    width = gripper.get("width_m") if isinstance(gripper, dict) else None
    if not isinstance(enabled, bool) or not (
        width is None
        or (isinstance(width, (int, float)) and not isinstance(width, bool) and math.isfinite(width))
    ):
        raise StateFileError(f"{where}: host.gripper must be {{'enabled': bool, 'width_m': number}}")
    names = set(names)
    homing = host.get("homing", {})
    if not isinstance(homing, dict) or not all(
        n in names and isinstance(s, (int, float)) and not isinstance(s, bool) and s != 0
        for n, s in homing.items()
    ):
        raise StateFileError(f"{where}: host.homing must map joint names to non-zero speeds")
    stats = host.get("stats", {})
    counters = {f.name for f in dataclasses.fields(CommStats)}
    if not isinstance(stats, dict) or not all(
        n in names
        and isinstance(c, dict)
        and set(c) <= counters  # a file saved by an older version has fewer counters
        and all(isinstance(v, int) for v in c.values())
        for n, c in stats.items()
    ):
        raise StateFileError(f"{where}: host.stats must map joint names to {sorted(counters)}")
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
    if doc.get("version") != STATE_VERSION:
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
    facts = _host_facts(doc, fresh_cores, where)
    sim.restore((np.asarray(mj, dtype=float), cores, drives))  # type: ignore[union-attr]
    return facts
