"""Atomic file writes, a lock file, and bounded reads of the small files the package keeps.

Atomic writes are used for every file the package writes in place (the
gripper's width, the console's ``--state`` file, a policy's metadata,
evaluation results, training checkpoints): a crash leaves either the old
file or the new one. :class:`LockFile` keeps a second process off a file
while one works on it (the console's ``--state`` file). :func:`read_json`
reads such a file back, refusing what is not one (a device, a FIFO, a huge
or absurdly nested file) in one line instead of hanging or overflowing;
:func:`read_bytes` is its check for any file read whole (traces, configurations).
:func:`output_problem` and :func:`replace_problem` say, before a command
works, why its output cannot go where it is asked to: a command replaces
only a file of its own kind (or an empty one), never one it did not write.
"""

from __future__ import annotations

import argparse
import contextlib
import errno
import json
import os
import secrets
import stat
import tempfile
from collections.abc import Callable, Iterator, Mapping
from pathlib import Path
from typing import BinaryIO

#: Largest file :func:`read_json` reads, bytes (a console state file is ~100 kB).
MAX_JSON_BYTES = 16 * 1024 * 1024


def read_json(path: str | os.PathLike[str], max_bytes: int = MAX_JSON_BYTES) -> object:
    """Parse a JSON file the package wrote, refusing anything that cannot be one.

    Raises:
        FileNotFoundError: ``path`` does not exist.
        OSError: It is not a regular file (a directory, a device such as
            ``/dev/zero``, a FIFO that would block), is larger than
            ``max_bytes``, or cannot be read.
        ValueError: It is not UTF-8 (``UnicodeDecodeError``), not JSON
            (``json.JSONDecodeError``), nested too deeply to parse, or an
            object in it has a key twice (JSON keeps the last, silently).
    """
    data = read_bytes(path, max_bytes)
    try:
        return json.loads(data.decode("utf-8"), object_pairs_hook=_once_each)
    except RecursionError as e:
        raise ValueError("nested too deeply to be one of this package's files") from e


def _once_each(pairs: list[tuple[str, object]]) -> dict[str, object]:
    """A JSON object whose keys are each given once (seen: the second drive_current won)."""
    doc: dict[str, object] = {}
    for key, value in pairs:
        if key in doc:
            raise ValueError(f"key {key!r} is given twice")
        doc[key] = value
    return doc


def read_bytes(path: str | os.PathLike[str], max_bytes: int) -> bytes:
    """The bytes of a regular file of at most ``max_bytes``, read whole.

    Raises:
        FileNotFoundError: ``path`` does not exist.
        OSError: It is not a regular file (a directory, a device such as
            ``/dev/zero``, which would fill the memory, a FIFO that would
            block), is larger than ``max_bytes``, or cannot be read.
    """
    path = Path(path)
    mode = os.stat(path).st_mode
    if not stat.S_ISREG(mode):
        raise OSError(errno.EINVAL, "not a regular file", str(path))
    with open(path, "rb") as f:
        data = f.read(max_bytes + 1)
    if len(data) > max_bytes:
        raise OSError(errno.EFBIG, f"larger than {max_bytes} bytes", str(path))
    return data


def path_argument(text: str) -> Path:
    """An argparse ``type`` for a path to write: an empty one is refused (``Path("")`` is ``.``).

    ``--plots ""`` wrote its figures into the current folder, ``--out ""`` a
    whole training run.
    """
    if not text.strip():
        raise argparse.ArgumentTypeError("an empty path; give a file or folder name")
    return Path(text)


def output_problem(path: str | os.PathLike[str], folder: bool = False, parents: bool = False) -> str | None:
    """Why ``path`` cannot be written (a file, or with ``folder`` a folder to fill), or ``None``.

    Checked before the work whose result goes there: a folder that does
    not exist (unless ``parents``, or ``folder``: the writer makes the
    missing ones), a file where a folder must be (or the reverse), a
    device, or a folder that refuses a file (read-only, ``/proc``), which
    only trying tells: a hidden temporary file is made there and removed.
    """
    path = Path(path)
    if _loops(path):
        return "is a loop of symlinks"
    if folder:
        if path.exists() and not path.is_dir():
            return "is a file; give a folder"
    elif path.is_dir():
        return "is a folder; give a file name"
    elif path.exists() and not path.is_file():
        return "is not a regular file"
    elif not parents and not path.parent.exists():
        return f"folder {path.parent} does not exist"
    candidates = (path, *path.parents) if folder else path.parents
    where = next((p for p in candidates if p.exists()), Path("."))
    if not where.is_dir():
        return f"{where} is a file, not a folder"
    try:
        fd, probe = tempfile.mkstemp(dir=where, prefix=".bioscara-", suffix=".probe")
    except OSError as e:
        return f"cannot write in {where}: {e.strerror or e}"
    os.close(fd)
    os.unlink(probe)
    return None


def replace_problem(path: str | os.PathLike[str], kind: str, is_kind: Callable[[Path], bool]) -> str | None:
    """Why writing ``path`` would destroy a file that is not ``kind``, or ``None``.

    A command replaces only what it wrote itself: nothing there, an empty
    regular file, or one ``is_kind`` recognises (seen: ``deploy --log
    model.zip`` replaced another run's model with JSON lines, ``export --onnx
    notes.txt`` a text file). What is not a regular file is left to
    :func:`output_problem`. A symlink is judged by its target, which is what
    is written.

    Args:
        path: The output.
        kind: What the command writes, for the message (``"a deploy run log"``).
        is_kind: Whether a non-empty regular file is one; it may raise
            :class:`OSError` (the file could not be read: it is refused).
    """
    path = Path(path)
    try:
        st = os.stat(path)
    except OSError:
        return None  # not there (or a loop of symlinks: output_problem's to say)
    if not stat.S_ISREG(st.st_mode) or st.st_size == 0:
        return None
    try:
        if is_kind(path):
            return None
    except OSError as e:
        return f"exists and cannot be read to tell whether it is {kind} ({e.strerror or e}); give a new file"
    return f"exists and is not {kind}; give a new file, or {kind} to replace"


def read_first_line(path: str | os.PathLike[str], max_bytes: int) -> bytes:
    """The first line of a regular file (at most ``max_bytes``, its newline kept).

    Raises:
        OSError: It cannot be read, or is not a regular file.
    """
    path = Path(path)
    if not stat.S_ISREG(os.stat(path).st_mode):
        raise OSError(errno.EINVAL, "not a regular file", str(path))
    with open(path, "rb") as f:
        return f.readline(max_bytes)


def output_clash(
    outputs: Mapping[str, str | os.PathLike[str] | None],
    inputs: Mapping[str, str | os.PathLike[str] | None] | None = None,
) -> str | None:
    """Why the files a command writes cannot all be written, or ``None``.

    Two options naming one file (a symlink or a hard link to it counts:
    files are compared by device and inode) would leave neither readable, and an output that is one of
    the command's inputs (the model being exported, its metadata) would
    destroy it. ``outputs`` and ``inputs`` map an option (``"--json"``) to
    its path; ``None`` is an option not given.
    """
    read = {_identity(p): option for option, p in (inputs or {}).items() if p is not None}
    seen: dict[object, str] = {}
    for option, path in outputs.items():
        if path is None:
            continue
        if _loops(path):
            return f"{option} {path} is a loop of symlinks"
        identity = _identity(path)
        if identity in seen:
            return f"{seen[identity]} and {option} name the same file {path}; each needs its own"
        seen[identity] = option
        if identity in read:
            return f"{option} {path} is the {read[identity]} file; writing it would destroy it"
    return None


def _identity(path: str | os.PathLike[str]) -> object:
    """Which file ``path`` names: its device and inode, or its resolved path if it is not there yet.

    A hard link, a symlink and ``..`` in a path all name the file they lead to.
    """
    try:
        st = os.stat(path)
    except OSError:
        return Path(os.path.realpath(path))
    return (st.st_dev, st.st_ino)


def _loops(path: str | os.PathLike[str]) -> bool:
    """Whether ``path`` is (or passes through) a loop of symlinks."""
    try:
        os.stat(path)
    except OSError as e:
        return e.errno == errno.ELOOP
    return False


def replaced_path(path: str | os.PathLike[str]) -> Path:
    """The file a write of ``path`` replaces: ``path``, or a symlink's target.

    Files are written to a temporary file and renamed over their path; a
    rename over a symlink replaced the link (seen: ``--json /dev/stdout``
    replaced the system's ``/dev/stdout``), so it is written through.
    """
    path = Path(path)
    if _loops(path):
        raise OSError(errno.ELOOP, "is a loop of symlinks", os.fspath(path))
    return Path(os.path.realpath(path)) if path.is_symlink() else path


@contextlib.contextmanager
def atomic_open(path: str | os.PathLike[str]) -> Iterator[BinaryIO]:
    """A binary file that replaces ``path`` atomically when the ``with`` block ends without error.

    What is written goes to a temporary file in the same directory (so the
    rename cannot cross file systems, :func:`temporary_beside`), which is
    flushed and ``fsync``-ed, then renamed over ``path`` with :func:`os.replace`;
    finally the directory is ``fsync``-ed so the rename itself survives a
    power cut (skipped where directories cannot be opened). Missing parent
    directories are created. A file replaced keeps its permission bits; a
    new one gets those a plain :func:`open` would give it (``0o666`` less the
    umask; seen: every write left 0600, tempfile's, also over a 0644 file).
    If the block raises (Ctrl-C included), the temporary file is removed and
    ``path`` is left as it was. A symlink is written through: its target is
    replaced, not the link (which may be someone else's, as ``/dev/stdout``).

    Raises:
        OSError: The file could not be written or replaced.
    """
    path = replaced_path(path)
    directory = path.parent
    with folders_made_for(directory):
        fd, tmp = temporary_beside(path)
        try:
            with os.fdopen(fd, "wb") as f:
                yield f
                f.flush()
                os.fsync(f.fileno())
            os.replace(tmp, path)
        except BaseException:
            with contextlib.suppress(FileNotFoundError):
                os.unlink(tmp)
            raise
    _fsync_directory(directory)


@contextlib.contextmanager
def folders_made_for(folder: str | os.PathLike[str]) -> Iterator[None]:
    """Make ``folder`` and its missing parents; if the block fails, remove those it made again.

    Only folders made here are removed, deepest first, and only while empty:
    one that another process made meanwhile, or that holds something else's
    file, stays (seen: ``eval --video nd1/a/b/v.mp4`` and ``export --onnx``
    interrupted left ``nd1/a/b/``).
    """
    made: list[Path] = []
    try:
        missing = [p for p in (Path(folder), *Path(folder).parents) if not os.path.lexists(p)]
        for p in reversed(missing):
            with contextlib.suppress(FileExistsError):
                p.mkdir()
                made.append(p)
        yield
    except BaseException:
        for p in reversed(made):
            with contextlib.suppress(OSError):
                p.rmdir()
        raise


def temporary_beside(
    path: str | os.PathLike[str], prefix: str | None = None, suffix: str = ".tmp"
) -> tuple[int, str]:
    """A new temporary file beside ``path``, to be renamed over it, with the mode ``path`` is to have.

    As :func:`tempfile.mkstemp` (a new name, created exclusively, a symlink
    never followed; open for reading and writing), but not 0600: if
    ``path`` is a regular file, the temporary file gets its permission bits
    (so the rename keeps them), else those a plain :func:`open` would give a
    new file (``0o666`` less the umask, or what the folder's default ACL says).
    Where the file system keeps no modes the mode is left as it comes.

    Args:
        path: The file the temporary one will replace (a symlink's target:
            :func:`replaced_path`).
        prefix: Start of the name; default ``.NAME.`` (a hidden file).
        suffix: End of the name.

    Returns:
        The open descriptor and the temporary file's path; the caller closes
        it, and renames or removes the file.

    Raises:
        OSError: No file can be created in the folder.
    """
    path = Path(path)
    prefix = f".{path.name}." if prefix is None else prefix
    kept = _permission_bits(path)
    flags = os.O_RDWR | os.O_CREAT | os.O_EXCL
    for name in ("O_NOFOLLOW", "O_CLOEXEC", "O_BINARY"):
        flags |= getattr(os, name, 0)
    for _ in range(tempfile.TMP_MAX):
        tmp = os.fspath(path.parent / f"{prefix}{secrets.token_hex(4)}{suffix}")
        try:  # the kernel applies the umask (and a default ACL) to 0o666, as for open()
            fd = os.open(tmp, flags, 0o600 if kept is not None else 0o666)
        except FileExistsError:
            continue
        if kept is not None:
            with contextlib.suppress(OSError):  # a file system without modes (FAT)
                os.fchmod(fd, kept)
        return fd, tmp
    raise FileExistsError(errno.EEXIST, "no free temporary file name", os.fspath(path.parent))


def _permission_bits(path: Path) -> int | None:
    """The permission bits of the regular file ``path``, or ``None`` if there is none."""
    try:
        st = os.stat(path)
    except OSError:
        return None
    return st.st_mode & 0o777 if stat.S_ISREG(st.st_mode) else None


def atomic_write_bytes(path: str | os.PathLike[str], data: bytes) -> None:
    """Replace ``path`` with ``data`` atomically (see :func:`atomic_open`).

    Args:
        path: The file to write.
        data: Its new contents.

    Raises:
        OSError: The file could not be written or replaced; the temporary
            file is removed and ``path`` is left as it was.
    """
    with atomic_open(path) as f:
        f.write(data)


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


#: How often :meth:`LockFile.acquire` tries to open a lock file that vanishes between its checks.
_LOCK_OPEN_ROUNDS = 1000


class LockFile:
    """An exclusive, non-blocking lock held through a lock file (``fcntl.flock``, POSIX).

    The lock file is created if missing and holds the holder's pid while it
    is held. A holder that created the file removes it on :meth:`release`
    (seen: a ``.lock`` left beside every state file, even beside a refused
    one), while it still holds the lock; one that found it leaves it. Removal
    is safe because every :meth:`acquire` checks, once it has the lock, that
    its path still names the file it locked, and starts again if not: a
    process that opened the file just before its holder removed it would
    otherwise lock the removed file while a third locks a new one of the same
    name. (A process following the older rule, which made no such check, may
    still race a removal: run one version of the package on one file.) The
    operating system releases the lock when its holder exits, so a crash never
    leaves a stale lock, only the file. Use as a context manager, or
    :meth:`acquire` and :meth:`release`.

    Args:
        path: The lock file (by convention the guarded file's name plus ``.lock``).
    """

    def __init__(self, path: str | os.PathLike[str]) -> None:
        """Remember the path; nothing is locked before :meth:`acquire`."""
        self.path = Path(path)
        self._fd: int | None = None
        self._created = False

    @property
    def held(self) -> bool:
        """Whether this object holds the lock."""
        return self._fd is not None

    def acquire(self) -> None:
        """Take the lock at once, or fail.

        The lock file's folder must exist (it is not made: a mistyped folder
        is the caller's to refuse).

        Raises:
            BlockingIOError: Another process (or another :class:`LockFile`
                on the same path) holds it; :meth:`holder` names it.
            OSError: The lock file cannot be created or opened.
        """
        import fcntl  # POSIX only; imported here so the rest of the module works everywhere

        if self._fd is not None:
            return
        while True:
            fd, created = self._open()
            try:
                fcntl.flock(fd, fcntl.LOCK_EX | fcntl.LOCK_NB)
                if self._names(fd):
                    break
            except BaseException:
                os.close(fd)
                raise
            os.close(fd)  # its holder removed the file we locked: lock the one there now
        self._fd, self._created = fd, created
        os.ftruncate(fd, 0)
        os.pwrite(fd, f"{os.getpid()}\n".encode(), 0)

    def _open(self) -> tuple[int, bool]:
        """Open the lock file, creating it if missing; whether this call created it.

        Raises:
            OSError: The path is a symlink (a lock file is a plain file of its
                own; seen: a dangling one had this loop spin for ever, neither
                creatable nor there), or it keeps appearing and vanishing.
        """
        flags = os.O_RDWR | getattr(os, "O_CLOEXEC", 0) | getattr(os, "O_NOFOLLOW", 0)
        for _ in range(_LOCK_OPEN_ROUNDS):
            if self.path.is_symlink():
                raise OSError(errno.ELOOP, "a symlink; a lock file must be a plain file", str(self.path))
            try:
                return os.open(self.path, flags | os.O_CREAT | os.O_EXCL, 0o644), True
            except FileExistsError:
                pass
            try:
                return os.open(self.path, flags), False
            except FileNotFoundError:
                continue  # removed by its holder in between: create it
        raise OSError(errno.EAGAIN, "it keeps being made and removed", str(self.path))

    def _names(self, fd: int) -> bool:
        """Whether the lock file's path still names the file open as ``fd``."""
        try:
            st = os.stat(self.path)
        except FileNotFoundError:
            return False
        here = os.fstat(fd)
        return (st.st_dev, st.st_ino) == (here.st_dev, here.st_ino)

    def release(self) -> None:
        """Let go of the lock: remove the file if this object created it, else clear its pid.

        Does nothing when not held.
        """
        fd, self._fd = self._fd, None
        if fd is None:
            return
        try:
            with contextlib.suppress(OSError):
                os.ftruncate(fd, 0)
            if self._created:
                with contextlib.suppress(OSError):
                    if self._names(fd):  # removed while held: a process that opened it starts again
                        os.unlink(self.path)
        finally:
            self._created = False
            os.close(fd)  # closing the descriptor releases the flock

    def holder(self) -> int | None:
        """The pid written by the lock's holder, ``None`` if unknown (none, or not written yet)."""
        try:
            text = self.path.read_text(encoding="ascii").strip()
        except (OSError, UnicodeDecodeError):
            return None
        return int(text) if text.isdigit() else None

    def __enter__(self) -> LockFile:
        """Acquire (see :meth:`acquire`)."""
        self.acquire()
        return self

    def __exit__(self, *exc: object) -> None:
        """Release."""
        self.release()
