"""Error codes and exceptions of the joint and gripper drivers.

The codes are the firmware host library's ``err_type_t`` (``uErr.h`` in the
original C++ stack). Python callers get exceptions instead of return codes:
every :class:`JointError` carries its :class:`ErrType` in ``.code``.
"""

from __future__ import annotations

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
        if joint is not None and not text.startswith(f"{joint}:"):
            text = f"{joint}: {text}"
        super().__init__(text)


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
    """A bus transaction failed after all retries."""

    code = ErrType.COMM_ERROR


class InvalidArgumentError(JointError, ValueError):
    """An argument is outside what the joint accepts."""

    code = ErrType.INVALID_ARGUMENT


class IncorrectStateError(JointError):
    """Another blocking command (homing, orientation check) is running."""

    code = ErrType.INCORRECT_STATE


class ArmStateError(IncorrectStateError):
    """A request that the arm's lifecycle state or command mode does not allow."""


_BY_CODE: dict[ErrType, type[JointError]] = {
    cls.code: cls
    for cls in (
        NotHomedError,
        NotEnabledError,
        StalledError,
        NotInitError,
        CommError,
        InvalidArgumentError,
        IncorrectStateError,
    )
}


def error_for_code(code: ErrType, message: str = "") -> JointError:
    """Build the exception that matches ``code`` (``JointError`` for ERROR).

    Args:
        code: The error code.
        message: Message for the exception.

    Returns:
        An instance of the subclass for ``code``.
    """
    cls = _BY_CODE.get(ErrType(code))
    if cls is None:
        return JointError(message, code=ErrType(code))
    return cls(message)


class ConfigError(ValueError):
    """A configuration file or value is invalid; the message names the field."""
