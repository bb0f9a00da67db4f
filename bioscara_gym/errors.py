"""Errors of the layers above the drivers: command line, console, training, deploy.

The driver layer's own errors (:class:`~bioscara_gym.hardware.errors.JointError`
and its subclasses) are in :mod:`bioscara_gym.hardware.errors`. Every error
here is a ``ValueError`` or carries an exit code, and its message is one line
that names the file, key, joint or option at fault; the ``bioscara`` command
prints it as is.
"""

from __future__ import annotations

from pathlib import Path
from typing import Any

from bioscara_gym.hardware.errors import InvalidArgumentError, MissingExtraError

__all__ = [
    "EXIT_ERROR",
    "EXIT_FAULT",
    "EXIT_INTERRUPTED",
    "CheckpointWarning",
    "CliError",
    "ConsoleUsageError",
    "DeployError",
    "ExportError",
    "HyperparamError",
    "MetadataError",
    "MissingExtraError",
    "PolicyFileError",
    "RecordingError",
    "StateFileError",
    "StateFileInUseError",
    "TrainingError",
    "is_refusal",
    "one_line",
    "refusal",
]

#: Exit code of a refused request (bad input; nothing was sent to the arm).
EXIT_ERROR = 2
#: Exit code after a failure on the arm (a stall, a bus error, a timeout, a safety stop):
#: the command had sent it requests; the console then disabled every joint, deploy stopped it safely.
EXIT_FAULT = 3
#: Exit code after Ctrl-C (128 + SIGINT); SIGTERM and SIGHUP exit 143 and 129.
EXIT_INTERRUPTED = 130


def one_line(text: object) -> str:
    r"""``text`` with its control characters escaped (``\n``, ``\x1b``), so that it prints as one line.

    Seen: a recording named with a newline split an error message (and a
    table row) in two; a ``--state`` path holding an escape sequence reached
    the terminal. Every error line the ``bioscara`` command prints goes
    through here.
    """
    return "".join(c if c.isprintable() else c.encode("unicode_escape").decode("ascii") for c in str(text))


#: Attribute marking an error raised before any byte that changes the arm was sent.
_REFUSED = "refused_before_traffic"


def refusal(error: Exception) -> Exception:
    """Mark ``error`` as a refusal made before anything was sent to the arm (exit :data:`EXIT_ERROR`)."""
    setattr(error, _REFUSED, True)
    return error


def is_refusal(error: BaseException) -> bool:
    """Whether ``error`` refused a request before anything was sent to the arm.

    An argument the driver refused (:class:`InvalidArgumentError`, checked
    before its transaction) or an error marked by :func:`refusal` (the
    console's checks of the state the arm is in). Any other driver error
    happened on the arm: exit :data:`EXIT_FAULT`.
    """
    return isinstance(error, InvalidArgumentError) or bool(getattr(error, _REFUSED, False))


class CliError(Exception):
    """An error to print as one line, with the exit code to use."""

    def __init__(self, message: str, code: int = EXIT_ERROR) -> None:
        """Store the message and exit code."""
        super().__init__(message)
        self.code = code


class ConsoleUsageError(ValueError):
    """Options that do not go together (e.g. ``--state`` with ``mock``)."""


class StateFileError(ValueError):
    """A ``--state`` file that cannot be used (corrupt, other backend or configuration).

    Also raised when saving a backend that has no simulated state.
    """


class StateFileInUseError(StateFileError):
    """Another ``bioscara`` command holds the ``--state`` file (its lock).

    Attributes:
        path: The state file.
        pid: The process holding it, ``None`` if it could not be read.
    """

    def __init__(self, path: Path, pid: int | None) -> None:
        """Name the file and its holder."""
        holder = f" (pid {pid})" if pid is not None else ""
        super().__init__(
            f"{path} is in use by another bioscara command{holder}; wait for it to finish "
            "(or stop it), then run this command again"
        )
        self.path = path
        self.pid = pid


class HyperparamError(ValueError):
    """A hyperparameter file that cannot be used; the message names file and key."""


class TrainingError(ValueError):
    """Bad training input (unknown env or algorithm, bad config, nothing to resume)."""


class CheckpointWarning(UserWarning):
    """A checkpoint that cannot be loaded was skipped; training resumes from an older one."""


class MetadataError(ValueError):
    """A policy's metadata is missing, unreadable or does not match the env."""


class PolicyFileError(ValueError):
    """A policy file (``model.zip``) that cannot be loaded: truncated, not a model, another algorithm."""


class ExportError(ValueError):
    """The model cannot be exported, or the export does not reproduce it."""


class DeployError(Exception):
    """Deployment refused or stopped; ``code`` is the exit code, the message names the cause.

    Attributes:
        code: Exit code for the CLI.
        summary: The run's summary, if the run started.
    """

    def __init__(self, message: str, code: int = EXIT_ERROR, summary: dict[str, Any] | None = None) -> None:
        """Record message, exit code and summary."""
        super().__init__(message)
        self.code = code
        self.summary = summary


class RecordingError(ValueError):
    """A recording of the real arm that cannot be used (``bioscara validate``/``calibrate``).

    Attributes:
        path: The file or folder.
        problem: What is wrong with it.
    """

    def __init__(self, path: Path | str, problem: str) -> None:
        """Name the file and the problem: ``str()`` is ``<path>: <problem>``."""
        self.path = Path(path)
        self.problem = problem
        super().__init__(f"{self.path}: {problem}")

