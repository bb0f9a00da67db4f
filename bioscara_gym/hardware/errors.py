"""Error codes and exceptions of the joint and gripper drivers.

The codes are the firmware host library's ``err_type_t`` (``uErr.h`` in the
original C++ stack). Python callers get exceptions instead of return codes:
every :class:`JointError` carries its :class:`ErrType` in ``.code``.
"""

from __future__ import annotations

import difflib
from collections.abc import Iterable
from enum import IntEnum


class ErrType(IntEnum):
    """Error codes of the original ``err_type_t`` enum, same values."""

    OK = 0
    ERROR = -1
    NOT_HOMED = -2
    NOT_ENABLED = -3
    STALLED = -4
    NOT_INIT = -5
    COMM_ERROR = -6
    INVALID_ARGUMENT = -101
    INCORRECT_STATE = -109


_DESCRIPTIONS: dict[ErrType, str] = {
    ErrType.OK: "success",
    ErrType.ERROR: "generic error",
    ErrType.NOT_HOMED: "joint not homed or failed to home",
    ErrType.NOT_ENABLED: "joint not enabled or failed to enable",
    ErrType.STALLED: "joint stalled",
    ErrType.NOT_INIT: "joint not initialized",
    ErrType.COMM_ERROR: "communication error",
    ErrType.INVALID_ARGUMENT: "argument violates conditions",
    ErrType.INCORRECT_STATE: "joint is busy executing another blocking command",
}


def error_to_string(code: ErrType | int) -> str:
    """Return the human-readable text for an error code.

    Args:
        code: An :class:`ErrType` or its integer value.

    Returns:
        The description, e.g. ``"NOT_HOMED: joint not homed or failed to home"``.
        Unknown integers give ``"unknown error code N"``.
    """
    try:
        err = ErrType(code)
    except ValueError:
        return f"unknown error code {int(code)}"
    return f"{err.name}: {_DESCRIPTIONS[err]}"


class JointError(Exception):
    """Base class of every driver error; ``code`` says which one.

    Attributes:
        code: The :class:`ErrType`.
        joint: Name of the joint (or ``"gripper"``) at fault, if any.
        register: The register of the failed transaction, if any
            (a :class:`~bioscara_gym.hardware.registers.Reg`).
    """

    code: ErrType = ErrType.ERROR

    def __init__(
        self,
        message: str = "",
        *,
        joint: str | None = None,
        register: IntEnum | None = None,
        code: ErrType | None = None,
    ) -> None:
        """Create the error.

        Args:
            message: What happened and what was expected. With ``joint``, the
                text is prefixed by the joint's name (``"j2: ..."``) unless it
                already starts with it.
            joint: The joint (or ``"gripper"``) at fault.
            register: The register of the failed transaction.
            code: Overrides the class's code (only for the generic base class).
        """
        if code is not None:
            self.code = code
        self.joint = joint
        self.register = register
        text = message or error_to_string(self.code)
        label = self._label()
        if label is not None and not text.startswith(f"{label}:"):
            text = f"{label}: {text}"
        super().__init__(text)

    def _label(self) -> str | None:
        """What the message is prefixed with: the joint's name."""
        return self.joint


class NotHomedError(JointError):
    """The joint is not homed (or homing failed); motion is refused."""

    code = ErrType.NOT_HOMED


class NotEnabledError(JointError):
    """The joint is not enabled (or enabling failed, or the deadman tripped)."""

    code = ErrType.NOT_ENABLED


class StalledError(JointError):
    """Stall detection tripped; the motor stopped. Re-enable to clear."""

    code = ErrType.STALLED


class NotInitError(JointError):
    """The joint was used before ``init()`` or after ``deinit()``."""

    code = ErrType.NOT_INIT


class CommError(JointError):
    """A bus transaction failed after all retries.

    Attributes:
        address: The 7-bit I2C address of the transaction, if any; with
            ``joint`` the message is prefixed ``"j1 (0x11): ..."``.
    """

    code = ErrType.COMM_ERROR

    def __init__(
        self,
        message: str = "",
        *,
        joint: str | None = None,
        register: IntEnum | None = None,
        address: int | None = None,
    ) -> None:
        """Create the error; the arguments are those of :class:`JointError`, plus ``address``."""
        self.address = address
        super().__init__(message, joint=joint, register=register)

    def _label(self) -> str | None:
        if self.joint is not None and self.address is not None:
            return f"{self.joint} ({self.address:#04x})"
        return self.joint


class InvalidArgumentError(JointError, ValueError):
    """An argument is outside what the joint accepts."""

    code = ErrType.INVALID_ARGUMENT


class IncorrectStateError(JointError):
    """Another blocking command (homing, orientation check) is running."""

    code = ErrType.INCORRECT_STATE


class AlreadyInitializedError(IncorrectStateError):
    """``init()`` on a joint already initialized: ``deinit()`` it first (LeRobot's ``connect()`` twice)."""


class ArmStateError(IncorrectStateError):
    """A request that the arm's lifecycle state or command mode does not allow."""


class ConfigError(ValueError):
    """A configuration file or value is invalid; the message names the field."""


class MissingExtraError(ImportError):
    """An optional dependency is not installed; the message names the extra to install.

    Attributes:
        extra: The extra, e.g. ``"sim"`` for ``pip install 'bioscara-gym[sim]'``.
    """

    def __init__(self, what: str, extra: str) -> None:
        """Say what needs the extra, and how to install it."""
        super().__init__(f"{what} needs the [{extra}] extra: pip install 'bioscara-gym[{extra}]'")
        self.extra = extra


def require_extra(module: str, what: str, extra: str) -> None:
    """Import ``module``, or raise :class:`MissingExtraError` naming ``extra``.

    Args:
        module: The module the feature needs, e.g. ``"mujoco"``.
        what: The feature, for the message (``"the sim backend"``).
        extra: The extra that installs it (``"sim"``).
    """
    import importlib

    try:
        importlib.import_module(module)
    except ModuleNotFoundError as e:
        if e.name is not None and e.name.split(".")[0] != module.split(".")[0]:
            raise  # the module is there but something it needs is broken: show that
        raise MissingExtraError(what, extra) from e


def closest_name(name: object, known: Iterable[str]) -> str | None:
    """The name of ``known`` closest to a misspelt ``name``, if one is close enough ("did you mean").

    The one rule behind every "did you mean" the package prints: the
    configuration's fields, the hyperparameters, the DAgger settings.
    """
    close = difflib.get_close_matches(str(name), list(known), n=1)
    return close[0] if close else None


class UnknownJointError(InvalidArgumentError, ConfigError):
    """A joint name that the configuration does not have; the message lists the known ones.

    Both an :class:`InvalidArgumentError` (a bad request to the driver layer)
    and a :class:`ConfigError` (raised by
    :meth:`~bioscara_gym.hardware.config.ArmConfig.joint`).
    """


class DeadmanError(Exception):
    """The host's deadman guard saw a joint go longer than the firmware's deadman without a transaction.

    Its firmware would have stopped it (docs/firmware.md, deadman). Raised by
    :meth:`~bioscara_gym.hardware.safety.DeadmanGuard.check`; ``bioscara
    deploy`` stops on it (``deadman``).

    Attributes:
        joint: The joint silent the longest.
        silence_s: How long it was silent, s.
        limit_s: The longest silence allowed, s.
    """

    def __init__(self, joint: str, silence_s: float, limit_s: float) -> None:
        """Say which joint was silent, how long, and the limit."""
        super().__init__(
            f"deadman guard: {joint} went {silence_s * 1000:.1f} ms without a transaction "
            f"(limit {limit_s * 1000:.0f} ms); its firmware would stop it"
        )
        self.joint = joint
        self.silence_s = silence_s
        self.limit_s = limit_s


class SitlError(RuntimeError):
    """The joint firmware cannot run in the loop.

    No firmware source was given, no C++ compiler is found, the firmware
    does not build (the message is the compiler's first error, naming the
    file, or the function nothing defines: "undefined reference to
    loop()"), a cached library cannot be loaded (named, to be deleted), or
    the stand-in saw the firmware do what the chip could not (a wait inside
    an interrupt handler).
    """
