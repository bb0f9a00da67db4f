"""Gripper drivers: a hobby servo that sets the finger width, with no feedback.

The width ``w`` in m maps to the servo angle ``alpha`` in degrees through
``alpha = reduction * (w - offset)`` (the C++ ``Gripper`` driver, see
``docs/arm.md``); commanded widths are
clamped to ``[min, max]``. The servo reports nothing back, so
:meth:`BaseGripper.get_position` returns the last commanded width, and the
last width is kept across restarts in a small state file.

State file format (JSON, UTF-8, one object)::

    {"width_m": 0.08}

It is written on :meth:`BaseGripper.disable` atomically (temporary file in the
same directory, ``fsync``, ``os.replace``), so a crash leaves either the old or
the new file, never a half-written one. On :meth:`BaseGripper.enable` it is
read back; when it is missing, unreadable, not that JSON object, or holds a
width that is non-finite or outside ``[min, max]``, the backup initial width
is used and a :class:`GripperStateWarning` names the file and the reason.
Extra keys are ignored. :func:`read_saved_width` and :func:`save_width` read
and write the format for other code (the console shows the saved width).

Backends:

- :class:`Gripper`: the real servo on a Linux sysfs PWM channel
  (``/sys/class/pwm/pwmchipN/pwmM``; chip 0 channel 0 is GPIO18 on the Pi).
- :class:`MockGripper`: mirrors commands, touches nothing but the state file.
"""

from __future__ import annotations

import abc
import errno
import json
import math
import os
import warnings
from pathlib import Path
from types import TracebackType

from bioscara_gym.fsutil import atomic_write_text, read_json, replace_problem
from bioscara_gym.hardware.clock import Clock, WallClock
from bioscara_gym.hardware.errors import (
    CommError,
    InvalidArgumentError,
    NotEnabledError,
    NotInitError,
)
from bioscara_gym.hardware.transmission import joint_to_actuator

__all__ = [
    "PWM_FREQUENCY_HZ",
    "PWM_PERIOD_NS",
    "SERVO_CENTER_PULSE_US",
    "SERVO_PULSE_US_PER_90_DEG",
    "BaseGripper",
    "Gripper",
    "GripperStateWarning",
    "MockGripper",
    "read_saved_width",
    "save_width",
    "servo_duty_cycle_ns",
    "servo_pulse_us",
]

#: Servo PWM frequency in Hz (``Gripper::_freq = 50`` in the C++ driver).
PWM_FREQUENCY_HZ = 50
#: PWM period in ns, ``1e9 / 50`` (``RPI_PWM::start``: ``per = 1E9 / frequency``).
PWM_PERIOD_NS = 1_000_000_000 // PWM_FREQUENCY_HZ
#: Pulse on-time in µs at 0 degrees (C++ ``Gripper`` driver: ``α/90 × 500 + 1500``).
SERVO_CENTER_PULSE_US = 1500.0
#: Pulse on-time change in µs per 90 degrees (C++ ``Gripper`` driver).
SERVO_PULSE_US_PER_90_DEG = 500.0

#: Key of the width in the state file.
_STATE_KEY = "width_m"
#: Largest gripper state file read, bytes (it holds one number).
STATE_FILE_MAX_BYTES = 4096
#: Poll interval in s while waiting for the kernel to create an exported channel.
_EXPORT_POLL_S = 0.01
#: Hint for a missing PWM chip (the C++ driver suggests ``pwm-2chan``).
_OVERLAY_HINT = (
    "is the PWM overlay enabled? Add 'dtoverlay=pwm,pin=18,func=2' (or "
    "'dtoverlay=pwm-2chan') to /boot/firmware/config.txt and reboot; on a "
    "Raspberry Pi 5 the header PWM is usually pwmchip2"
)
#: Hint for a sysfs permission error.
_PERMISSION_HINT = (
    "run as a user in group 'gpio' (Raspberry Pi OS ships a udev rule that gives "
    "that group the pwm attributes; elsewhere add a udev rule for "
    'SUBSYSTEM=="pwm" that does the same)'
)


class GripperStateWarning(UserWarning):
    """The stored gripper width could not be used; the backup width was."""


def servo_pulse_us(angle_deg: float) -> float:
    """Servo pulse on-time in µs for a servo angle in degrees.

    ``on_time_us = angle_deg / 90 * 500 + 1500`` (the C++ ``Gripper`` driver).

    Args:
        angle_deg: Servo angle in degrees; 0 is the servo's centre.

    Returns:
        The on-time in µs.

    Raises:
        InvalidArgumentError: ``angle_deg`` is not finite, or the on-time is
            not strictly between 0 and the 20 ms period.
    """
    if not math.isfinite(angle_deg):
        raise InvalidArgumentError(f"servo angle {angle_deg!r} deg is not finite")
    on_us = angle_deg / 90.0 * SERVO_PULSE_US_PER_90_DEG + SERVO_CENTER_PULSE_US
    period_us = PWM_PERIOD_NS / 1000.0
    if not 0.0 < on_us < period_us:
        raise InvalidArgumentError(
            f"servo angle {angle_deg:g} deg gives a {on_us:g} us pulse; "
            f"must be between 0 and {period_us:g} us (the 50 Hz period)"
        )
    return on_us


def servo_duty_cycle_ns(angle_deg: float) -> int:
    """PWM ``duty_cycle`` in ns (the sysfs attribute) for a servo angle in degrees.

    ``duty_cycle_ns = round(on_time_us * 1000)`` with the on-time from
    :func:`servo_pulse_us`; the period is :data:`PWM_PERIOD_NS`.

    Args:
        angle_deg: Servo angle in degrees.

    Returns:
        The duty cycle in whole ns.

    Raises:
        InvalidArgumentError: As :func:`servo_pulse_us`.
    """
    return round(servo_pulse_us(angle_deg) * 1000.0)


class _UnusableStateFile(Exception):
    """The state file holds no usable width; the message names the file and the reason."""

    def __init__(self, message: str, missing: bool = False) -> None:
        super().__init__(message)
        self.missing = missing


def _read_width(path: Path) -> float:
    """Read the width in m from a state file, as stored (not range-checked).

    Raises:
        _UnusableStateFile: The file is missing, unreadable, not JSON or not
            ``{"width_m": <number>}``.
    """
    try:
        data = read_json(path, max_bytes=STATE_FILE_MAX_BYTES)
    except FileNotFoundError as e:
        raise _UnusableStateFile(f"state file {path} does not exist (first run?)", missing=True) from e
    except OSError as e:
        raise _UnusableStateFile(f"cannot read state file {path} ({e.strerror or e})") from e
    except UnicodeDecodeError as e:
        raise _UnusableStateFile(f"cannot read state file {path} ({e})") from e
    except ValueError as e:
        raise _UnusableStateFile(f"state file {path} is not valid JSON ({e})") from e
    value = data.get(_STATE_KEY) if isinstance(data, dict) else None
    if isinstance(value, bool) or not isinstance(value, (int, float)):
        raise _UnusableStateFile(
            f'state file {path} does not hold {{"{_STATE_KEY}": <number>}} (got {str(data)[:80]!r})'
        )
    return float(value)


def read_saved_width(path: str | os.PathLike[str] | None) -> float | None:
    """The width in m saved in a gripper state file, or ``None`` if there is none.

    Reads the format of the module docstring without warning; the width is
    returned as stored (a gripper checks it against its limits on ``enable()``).

    Args:
        path: The state file; ``None`` (no persistence) gives ``None``.

    Returns:
        The saved width in m, or ``None`` when the file is missing,
        unreadable or not ``{"width_m": <number>}``.
    """
    if path is None:
        return None
    try:
        return _read_width(Path(path))
    except _UnusableStateFile:
        return None


#: What a gripper state file holds, for the messages of a command that would replace another file.
STATE_FILE_KIND = 'a gripper state file ({"width_m": ...})'


def is_state_file(path: str | os.PathLike[str]) -> bool:
    """Whether ``path`` is a gripper state file, ours to replace: a JSON object of ``width_m`` alone.

    Its value may be one a gripper cannot use (``"x"``, NaN, beyond the
    limits): a damaged state, which the next save mends. A file that is not
    such JSON at all is not replaced, whatever made it (a configuration, notes,
    a state file damaged past reading): the save's warning says to delete it.

    Raises:
        OSError: The file cannot be read.
    """
    try:
        data = read_json(path, max_bytes=STATE_FILE_MAX_BYTES)
    except (ValueError, UnicodeDecodeError):  # not JSON
        return False
    except OSError as e:
        if e.errno == errno.EFBIG:  # larger than any state file
            return False
        raise
    return isinstance(data, dict) and set(data) == {_STATE_KEY}


def save_width(path: str | os.PathLike[str], width_m: float) -> None:
    """Write a width in m to a gripper state file, atomically; another file there is not replaced.

    Args:
        path: The state file; its directory is created if needed.
        width_m: The width in m (finite).

    Raises:
        OSError: The file could not be written, or a non-empty file there is
            not a gripper state file (seen: a configuration's ``state_file``
            naming the configuration itself replaced it with ``{"width_m": 0.06}``).
        ValueError: ``width_m`` is not finite (JSON has no NaN).
    """
    problem = replace_problem(path, STATE_FILE_KIND, is_state_file)
    if problem is not None:
        raise FileExistsError(errno.EEXIST, f"{problem} (or delete it)", os.fspath(path))
    atomic_write_text(path, json.dumps({_STATE_KEY: width_m}, allow_nan=False) + "\n")


def _finite(value: float, what: str, name: str) -> float:
    """Return ``value`` as float, or raise naming the gripper if it is not finite."""
    try:
        value = float(value)
    except (TypeError, ValueError) as e:
        raise InvalidArgumentError(f"{what} {value!r} is not a number", joint=name) from e
    if not math.isfinite(value):
        raise InvalidArgumentError(f"{what} {value!r} is not finite", joint=name)
    return value


class BaseGripper(abc.ABC):
    """A servo gripper commanded by width in m, with no position feedback.

    Contract, shared by every backend:

    - Life cycle: ``init()`` → ``enable()`` → ``set_position()``… →
      ``disable()`` → ``deinit()``. Use as a context manager: ``with`` calls
      ``init()``; leaving the block disables (if enabled) and deinitialises,
      so the servo is left unpowered whatever happened inside.
    - Every method but ``init()``/``deinit()`` raises :class:`NotInitError`
      before ``init()`` or after ``deinit()``. ``set_position`` raises
      :class:`NotEnabledError` while disabled (the C++ ``Gripper::enable``
      "must be called before a position is set").
    - Widths are in m and clamped to ``[min, max]``; NaN or infinite widths
      raise :class:`InvalidArgumentError` (a ``ValueError``).
    - ``enable()`` restores the width saved by the last ``disable()`` from
      ``state_file`` and commands it; see the module docstring for the
      format and the fallback to ``backup_init_pos``.
    - Backend failures raise :class:`CommError` chained to the ``OSError``.

    Subclasses implement :meth:`set_servo_position` and may override the
    hooks ``_open``, ``_close``, ``_start_output`` and ``_stop_output``.
    """

    def __init__(
        self,
        reduction: float,
        offset: float,
        min: float,  # noqa: A002 - the C++ API's parameter name
        max: float,  # noqa: A002
        backup_init_pos: float,
        state_file: str | os.PathLike[str] | None = None,
        name: str = "gripper",
    ) -> None:
        """Create the gripper (no I/O happens until :meth:`init`).

        Args:
            reduction: Servo degrees per m of width (``r`` in
                ``alpha = r * (w - o)``); finite and non-zero.
            offset: Width in m at which the servo angle is 0 (``o``).
            min: Lower width limit in m.
            max: Upper width limit in m; greater than ``min``.
            backup_init_pos: Width in m assumed and commanded on ``enable()``
                when none can be read from ``state_file``; within
                ``[min, max]``.
            state_file: Where the last width is kept across restarts;
                ``None`` disables persistence (``enable()`` then always uses
                ``backup_init_pos``, without a warning).
            name: Name used in error messages and warnings.

        Raises:
            InvalidArgumentError: A parameter is non-finite, ``reduction`` is
                0, ``min >= max`` or ``backup_init_pos`` is outside the limits.
        """
        self._name = name
        self._reduction = self._check_reduction(reduction)
        self._offset_m = _finite(offset, "offset", name)
        self._min_m = _finite(min, "min width", name)
        self._max_m = _finite(max, "max width", name)
        if not self._min_m < self._max_m:
            raise InvalidArgumentError(
                f"width limits [{self._min_m:g}, {self._max_m:g}] m; min must be less than max",
                joint=name,
            )
        backup = _finite(backup_init_pos, "backup initial width", name)
        if not self._min_m <= backup <= self._max_m:
            raise InvalidArgumentError(
                f"backup initial width {backup:g} m is outside [{self._min_m:g}, {self._max_m:g}] m",
                joint=name,
            )
        self._backup_init_pos_m = backup
        self._state_file = Path(state_file) if state_file is not None else None
        self._width_m = backup
        self._initialized = False
        self._enabled = False
        #: The width the last ``disable()`` wrote to the state file (``None``: nothing written yet).
        self.saved_width_m: float | None = None
        #: Why the last save failed (``None`` if it did not).
        self.save_error: OSError | None = None

    # -- properties ---------------------------------------------------------

    @property
    def name(self) -> str:
        """Name used in messages."""
        return self._name

    @property
    def reduction(self) -> float:
        """Servo degrees per m of width."""
        return self._reduction

    @property
    def offset(self) -> float:
        """Width in m at which the servo angle is 0."""
        return self._offset_m

    @property
    def min(self) -> float:
        """Lower width limit in m."""
        return self._min_m

    @property
    def max(self) -> float:
        """Upper width limit in m."""
        return self._max_m

    @property
    def backup_init_pos(self) -> float:
        """Width in m used on ``enable()`` when the state file is unusable."""
        return self._backup_init_pos_m

    @property
    def state_file(self) -> Path | None:
        """Path of the last-width file, or ``None`` without persistence."""
        return self._state_file

    def save_status(self) -> str:
        """Whether the last :meth:`disable` wrote the width to the state file, in words (for operators)."""
        path = self._state_file
        if path is None:
            return "not kept (no state file)"
        if self.save_error is not None:
            return f"NOT saved to {path}: {self.save_error.strerror or self.save_error}"
        if self.saved_width_m is None:
            return f"not saved (the gripper was not enabled; {path} unchanged)"
        return f"saved to {path}"

    @property
    def is_initialized(self) -> bool:
        """Whether :meth:`init` ran and :meth:`deinit` has not."""
        return self._initialized

    @property
    def is_enabled(self) -> bool:
        """Whether the servo is driven (between ``enable()`` and ``disable()``)."""
        return self._enabled

    @property
    def output_enabled(self) -> bool:
        """Whether the servo's signal is on, as far as the backend can tell (else :attr:`is_enabled`)."""
        return self._enabled

    # -- transmission ---------------------------------------------------------

    def check_width(self, width_m: float) -> None:
        """Refuse a width whose servo pulse the driver cannot send, before anything is driven.

        Raises:
            InvalidArgumentError: As :func:`servo_pulse_us`, for the clamped width's angle.
        """
        servo_pulse_us(self.width_to_angle_deg(self.clamp_width(width_m)))

    def clamp_width(self, width_m: float) -> float:
        """Clamp a width in m to ``[min, max]``.

        Args:
            width_m: Desired width in m.

        Returns:
            The width limited to ``[min, max]``.

        Raises:
            InvalidArgumentError: ``width_m`` is NaN or infinite.
        """
        width_m = _finite(width_m, "width (m)", self._name)
        return min(max(width_m, self._min_m), self._max_m)

    def width_to_angle_deg(self, width_m: float) -> float:
        """Servo angle in degrees for a width in m: ``reduction * (w - offset)``.

        The width is used as given (not clamped).

        Args:
            width_m: Width in m.

        Returns:
            The servo angle in degrees.
        """
        return joint_to_actuator(width_m, self._reduction, self._offset_m)

    def set_reduction(self, reduction: float) -> None:
        """Set the servo degrees per m of width (calibration, C++ ``setReduction``).

        Takes effect with the next command.

        Args:
            reduction: Finite, non-zero degrees per m.

        Raises:
            InvalidArgumentError: ``reduction`` is 0 or not finite.
        """
        self._reduction = self._check_reduction(reduction)

    def set_offset(self, offset: float) -> None:
        """Set the width in m at which the servo angle is 0 (C++ ``setOffset``).

        Takes effect with the next command.

        Args:
            offset: Finite width in m.

        Raises:
            InvalidArgumentError: ``offset`` is not finite.
        """
        self._offset_m = _finite(offset, "offset", self._name)

    # -- life cycle -------------------------------------------------------------

    def init(self) -> None:
        """Acquire the backend (open the PWM channel); no motion.

        Calling it again re-runs the backend's set-up.

        Raises:
            CommError: The backend could not be set up.
        """
        self._open()
        self._initialized = True

    def deinit(self) -> None:
        """Release the backend, disabling the servo first if it is enabled.

        Does nothing if not initialised, so it is safe in clean-up code.

        Raises:
            CommError: Disabling the output failed (the gripper stays
                initialised and enabled so the caller can retry).
        """
        if not self._initialized:
            return
        if self._enabled:
            self.disable()
        self._close()
        self._initialized = False

    def enable(self) -> None:
        """Drive the servo, at the width saved by the last ``disable()``.

        The width comes from ``state_file``; if that is unusable the
        backup initial width is used and a :class:`GripperStateWarning` is
        emitted. The width is commanded before the output is switched on.
        Does nothing if already enabled.

        Raises:
            NotInitError: Called before ``init()``.
            CommError: The backend refused the command.
        """
        self._require_init()
        if self._enabled:
            return
        width_m = self._load_width()
        self.set_servo_position(self.width_to_angle_deg(width_m))
        self._width_m = width_m
        self._start_output()
        self._enabled = True

    def disable(self) -> None:
        """Save the last width to ``state_file``, then stop driving the servo.

        A failure to save is reported as a :class:`GripperStateWarning` and
        does not keep the output on. Does nothing if not enabled (so a
        never-enabled gripper never overwrites the saved width).

        Raises:
            NotInitError: Called before ``init()``.
            CommError: The backend could not switch the output off.
        """
        self._require_init()
        if not self._enabled:
            return
        self._save_width(self._width_m)
        self._stop_output()
        self._enabled = False

    def release(self) -> None:
        """Stop driving the servo, whoever switched it on: :meth:`disable` if enabled.

        A servo an earlier process left driven (its output on, this driver
        never enabled) is switched off without saving a width: this process
        does not know it, and the width last saved stays.

        Raises:
            NotInitError: Called before ``init()``.
            CommError: The backend could not switch the output off.
        """
        self._require_init()
        if self._enabled:
            self.disable()
        elif self.output_enabled:
            self._stop_output()

    def set_position(self, width_m: float) -> None:
        """Command a width in m; values outside ``[min, max]`` are clamped.

        Args:
            width_m: Desired width in m.

        Raises:
            NotInitError: Called before ``init()``.
            NotEnabledError: Called while disabled.
            InvalidArgumentError: ``width_m`` is NaN or infinite.
            CommError: The backend refused the command.
        """
        self._require_init()
        if not self._enabled:
            raise NotEnabledError(
                f"set_position({width_m!r}) while disabled; call enable() first",
                joint=self._name,
            )
        width_m = self.clamp_width(width_m)
        self.set_servo_position(self.width_to_angle_deg(width_m))
        self._width_m = width_m

    def get_position(self) -> float:
        """Width in m: the last commanded (clamped) width, as there is no feedback.

        Before the first ``enable()`` this is the backup initial width.

        Returns:
            The width in m.

        Raises:
            NotInitError: Called before ``init()``.
        """
        self._require_init()
        return self._width_m

    @abc.abstractmethod
    def set_servo_position(self, angle_deg: float) -> None:
        """Drive the servo to an angle in degrees (the backend's hook).

        Called by :meth:`set_position` and :meth:`enable`; may be called
        directly to calibrate ``reduction`` and ``offset``. A direct call
        bypasses the width limits and the enabled check and does not change
        what :meth:`get_position` reports.

        Args:
            angle_deg: Servo angle in degrees; 0 is the servo's centre.

        Raises:
            NotInitError: Called before ``init()``.
            InvalidArgumentError: The angle is not finite or out of the
                servo's pulse range.
            CommError: The backend refused the command.
        """

    # -- context manager ---------------------------------------------------------

    def __enter__(self) -> BaseGripper:
        """Initialise and return the gripper (it is not enabled)."""
        self.init()
        return self

    def __exit__(
        self,
        exc_type: type[BaseException] | None,
        exc: BaseException | None,
        tb: TracebackType | None,
    ) -> None:
        """Disable (if enabled) and deinitialise; exceptions propagate."""
        self.deinit()

    def __repr__(self) -> str:
        """Show the name, state and last width."""
        state = "enabled" if self._enabled else ("initialized" if self._initialized else "not initialized")
        return f"{type(self).__name__}(name={self._name!r}, {state}, width_m={self._width_m:g})"

    # -- backend hooks -----------------------------------------------------------

    def _open(self) -> None:  # noqa: B027 - optional hook, empty by default
        """Acquire backend resources (called by :meth:`init`)."""

    def _close(self) -> None:  # noqa: B027 - optional hook, empty by default
        """Release backend resources (called by :meth:`deinit`)."""

    def _start_output(self) -> None:  # noqa: B027 - optional hook, empty by default
        """Switch the servo signal on (after the first angle is set)."""

    def _stop_output(self) -> None:  # noqa: B027 - optional hook, empty by default
        """Switch the servo signal off."""

    # -- helpers ------------------------------------------------------------------

    def _require_init(self) -> None:
        """Raise :class:`NotInitError` unless initialised."""
        if not self._initialized:
            raise NotInitError("not initialized; call init() first", joint=self._name)

    def _check_reduction(self, reduction: float) -> float:
        """Return ``reduction`` if finite and non-zero, else raise."""
        reduction = _finite(reduction, "reduction", self._name)
        if reduction == 0.0:
            raise InvalidArgumentError("reduction must be non-zero", joint=self._name)
        return reduction

    def _warn_state(self, message: str) -> None:
        """Emit a :class:`GripperStateWarning` pointing at the caller's call."""
        # stacklevel: _warn_state <- _load/_save_width <- enable/disable <- caller
        warnings.warn(f"{self._name}: {message}", GripperStateWarning, stacklevel=4)

    def _load_width(self) -> float:
        """Read the saved width in m, or return the backup width with a warning."""
        path = self._state_file
        if path is None:
            return self._backup_init_pos_m
        fallback = f"using the backup initial width {self._backup_init_pos_m:g} m"
        try:
            width_m = _read_width(path)
        except _UnusableStateFile as e:
            hint = "; it is written on disable()" if e.missing else ""
            self._warn_state(f"{e}; {fallback}{hint}")
            return self._backup_init_pos_m
        if not math.isfinite(width_m) or not self._min_m <= width_m <= self._max_m:
            self._warn_state(
                f"state file {path} holds width {width_m!r} m, outside "
                f"[{self._min_m:g}, {self._max_m:g}] m; {fallback}"
            )
            return self._backup_init_pos_m
        return width_m

    def _save_width(self, width_m: float) -> None:
        """Write the width atomically to the state file; warn if that fails."""
        path = self._state_file
        if path is None:
            return
        try:
            save_width(path, width_m)
        except OSError as e:
            self.save_error = e
            self._warn_state(
                f"cannot save width {width_m:g} m to state file {path} ({e.strerror or e}); "
                "the next enable() will not know where the fingers are"
            )
        else:
            self.saved_width_m, self.save_error = width_m, None


class Gripper(BaseGripper):
    """The real servo on a Linux sysfs PWM channel at 50 Hz.

    ``init()`` exports ``pwmchip{pwm_chip}/pwm{pwm_channel}`` if needed and
    sets the 20 ms period; ``enable()`` writes the duty cycle for the
    restored width, then ``enable=1``; ``disable()`` saves the width, then
    writes ``enable=0``. The channel stays exported after ``deinit()``.
    Sysfs errors raise :class:`CommError` naming the file, with a hint.
    """

    def __init__(
        self,
        reduction: float,
        offset: float,
        min: float,  # noqa: A002 - the C++ API's parameter name
        max: float,  # noqa: A002
        backup_init_pos: float,
        state_file: str | os.PathLike[str] | None = None,
        name: str = "gripper",
        *,
        pwm_chip: int = 0,
        pwm_channel: int = 0,
        sysfs_root: str | os.PathLike[str] = "/sys/class/pwm",
        export_timeout_s: float = 1.0,
        clock: Clock | None = None,
    ) -> None:
        """Create the driver; see :class:`BaseGripper` for the common arguments.

        Args:
            reduction: Servo degrees per m of width.
            offset: Width in m at which the servo angle is 0.
            min: Lower width limit in m.
            max: Upper width limit in m.
            backup_init_pos: Width in m used when the state file is unusable.
            state_file: Last-width file, or ``None``.
            name: Name used in messages.
            pwm_chip: ``N`` of ``pwmchipN`` (0 on a Pi 4: GPIO18).
            pwm_channel: ``M`` of ``pwmM`` on that chip.
            sysfs_root: Directory holding the ``pwmchipN`` entries.
            export_timeout_s: How long to wait in s for the kernel (and udev)
                to make a newly exported channel writable.
            clock: Clock used to wait for the export; wall time by default.

        Raises:
            InvalidArgumentError: As :class:`BaseGripper`, or a negative chip,
                channel or timeout.
        """
        super().__init__(reduction, offset, min, max, backup_init_pos, state_file, name)
        for label, value in (("pwm_chip", pwm_chip), ("pwm_channel", pwm_channel)):
            if isinstance(value, bool) or not isinstance(value, int) or value < 0:
                raise InvalidArgumentError(f"{label} {value!r} must be a non-negative integer", joint=name)
        if not math.isfinite(export_timeout_s) or export_timeout_s < 0:
            raise InvalidArgumentError(
                f"export_timeout_s {export_timeout_s!r} must be finite and >= 0",
                joint=name,
            )
        self._pwm_channel = pwm_channel
        self._chip_path = Path(sysfs_root) / f"pwmchip{pwm_chip}"
        self._pwm_path = self._chip_path / f"pwm{pwm_channel}"
        self._export_timeout_s = float(export_timeout_s)
        self._clock: Clock = clock if clock is not None else WallClock()

    @property
    def pwm_path(self) -> Path:
        """The channel's sysfs directory, e.g. ``/sys/class/pwm/pwmchip0/pwm0``."""
        return self._pwm_path

    @property
    def output_enabled(self) -> bool:
        """Whether the servo's PWM output is on (sysfs ``enable`` reads 1); ``False`` if unreadable."""
        try:
            return (self._pwm_path / "enable").read_text().strip() == "1"
        except OSError:
            return False

    def set_servo_position(self, angle_deg: float) -> None:
        """Write ``duty_cycle`` for a servo angle in degrees.

        See :func:`servo_duty_cycle_ns` for the conversion.
        """
        self._require_init()
        self._write(self._pwm_path / "duty_cycle", servo_duty_cycle_ns(angle_deg))

    def _open(self) -> None:
        """Export the channel if needed, wait for it, set the 50 Hz period."""
        if not self._chip_path.is_dir():
            missing = FileNotFoundError(errno.ENOENT, os.strerror(errno.ENOENT))
            missing.filename = str(self._chip_path)
            raise CommError(
                f"PWM chip {self._chip_path} does not exist; {_OVERLAY_HINT}",
                joint=self._name,
            ) from missing
        if not self._pwm_path.is_dir():
            self._write(self._chip_path / "export", self._pwm_channel)
            self._wait_for_export()
        self._write(self._pwm_path / "period", PWM_PERIOD_NS)

    def _wait_for_export(self) -> None:
        """Poll until the kernel created the channel and udev made it writable."""
        period = self._pwm_path / "period"
        deadline = self._clock.now() + self._export_timeout_s
        while not (period.is_file() and os.access(period, os.W_OK)):
            if self._clock.now() >= deadline:
                raise CommError(
                    f"{period} is not writable "
                    f"{self._export_timeout_s:g} s after exporting channel "
                    f"{self._pwm_channel} via "
                    f"{self._chip_path / 'export'}; {_PERMISSION_HINT}",
                    joint=self._name,
                )
            self._clock.sleep(_EXPORT_POLL_S)

    def _start_output(self) -> None:
        """Write ``enable=1``."""
        self._write(self._pwm_path / "enable", 1)

    def _stop_output(self) -> None:
        """Write ``enable=0``."""
        self._write(self._pwm_path / "enable", 0)

    def _write(self, path: Path, value: int) -> None:
        """Write an integer to a sysfs attribute in one ``write`` call."""
        data = str(value).encode("ascii")
        try:
            fd = os.open(path, os.O_WRONLY)
            try:
                os.write(fd, data)
            finally:
                os.close(fd)
        except PermissionError as e:
            raise CommError(
                f"permission denied writing {value} to {path}; {_PERMISSION_HINT}",
                joint=self._name,
            ) from e
        except FileNotFoundError as e:
            raise CommError(
                f"{path} does not exist; was the channel unexported? call init() again",
                joint=self._name,
            ) from e
        except OSError as e:
            raise CommError(f"writing {value} to {path} failed: {e.strerror or e}", joint=self._name) from e


class MockGripper(BaseGripper):
    """Mirrors commands without hardware; only the state file is touched.

    :attr:`servo_angle_deg` holds the last angle sent and :attr:`output_enabled`
    whether the (virtual) servo signal is on.
    """

    def __init__(
        self,
        reduction: float,
        offset: float,
        min: float,  # noqa: A002 - the C++ API's parameter name
        max: float,  # noqa: A002
        backup_init_pos: float,
        state_file: str | os.PathLike[str] | None = None,
        name: str = "gripper",
    ) -> None:
        """Create the mock; the arguments are those of :class:`BaseGripper`.

        Args:
            reduction: Servo degrees per m of width.
            offset: Width in m at which the servo angle is 0.
            min: Lower width limit in m.
            max: Upper width limit in m.
            backup_init_pos: Width in m used when the state file is unusable.
            state_file: Last-width file, or ``None``.
            name: Name used in messages.
        """
        super().__init__(reduction, offset, min, max, backup_init_pos, state_file, name)
        self._servo_angle_deg: float | None = None
        self._output_enabled = False

    @property
    def servo_angle_deg(self) -> float | None:
        """Last servo angle in degrees sent, or ``None`` if none yet."""
        return self._servo_angle_deg

    @property
    def output_enabled(self) -> bool:
        """Whether the virtual servo signal is on."""
        return self._output_enabled

    def set_servo_position(self, angle_deg: float) -> None:
        """Store the servo angle in degrees (validated like the real pulse)."""
        self._require_init()
        servo_pulse_us(angle_deg)
        self._servo_angle_deg = float(angle_deg)

    def _start_output(self) -> None:
        """Mark the virtual signal on."""
        self._output_enabled = True

    def _stop_output(self) -> None:
        """Mark the virtual signal off."""
        self._output_enabled = False
