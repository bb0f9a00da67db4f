"""Atomic file writes: a crash leaves either the old file or the new one, never half of one.

Used for every small file the package writes in place (the gripper's width,
the console's ``--state`` file, a policy's metadata, evaluation results).
"""

from __future__ import annotations

import contextlib
import os
import tempfile
from pathlib import Path


def atomic_write_bytes(path: str | os.PathLike[str], data: bytes) -> None:
    """Replace ``path`` with ``data`` atomically.

    ``data`` goes to a temporary file in the same directory (so the rename
    cannot cross file systems), which is flushed and ``fsync``-ed, then
    renamed over ``path`` with :func:`os.replace`; finally the directory is
    ``fsync``-ed so the rename itself survives a power cut (skipped where
    directories cannot be opened). Missing parent directories are created.
    The new file has the temporary file's mode (0600, as :func:`tempfile.mkstemp`).

    Args:
        path: The file to write.
        data: Its new contents.

    Raises:
        OSError: The file could not be written or replaced; the temporary
            file is removed and ``path`` is left as it was.
    """
    path = Path(path)
    directory = path.parent
    directory.mkdir(parents=True, exist_ok=True)
    fd, tmp = tempfile.mkstemp(dir=directory, prefix=f".{path.name}.", suffix=".tmp")
    try:
        with os.fdopen(fd, "wb") as f:
            f.write(data)
            f.flush()
            os.fsync(f.fileno())
        os.replace(tmp, path)
    except BaseException:
        with contextlib.suppress(FileNotFoundError):
            os.unlink(tmp)
        raise
    _fsync_directory(directory)


def atomic_write_text(path: str | os.PathLike[str], text: str, encoding: str = "utf-8") -> None:
    """Replace ``path`` with ``text`` atomically, as :func:`atomic_write_bytes`.

    The text is encoded with ``encoding`` and written as is (no newline
    translation).

    Raises:
        OSError: The file could not be written or replaced (``path`` is
            left as it was).
        UnicodeEncodeError: ``text`` cannot be encoded (nothing is written).
    """
    atomic_write_bytes(path, text.encode(encoding))


def _fsync_directory(directory: Path) -> None:
    """Make a rename in ``directory`` durable; best effort (not possible on every platform)."""
    try:
        dir_fd = os.open(directory, os.O_RDONLY)
    except OSError:
        return
    try:
        with contextlib.suppress(OSError):
            os.fsync(dir_fd)
    finally:
        os.close(dir_fd)
