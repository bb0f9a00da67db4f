"""The joint firmware built for the host: where its source is, the compiler, the cache.

The firmware's own sketch (``joint.ino`` with its headers) is compiled
unchanged with the machine's C++ compiler against the project's stand-ins
for ``Arduino.h``, ``Wire.h`` and ``UstepperS32.h`` (``native/``), into a
shared library per joint. ``-D J1`` ... ``-D J4`` selects the joint as the
firmware expects; since the sketch itself defines ``J1`` before it includes
``configuration.h``, the build includes ``configuration.h`` first (its
include guard then makes the sketch's own include a no-op), so the
configuration is the chosen joint's, read from the firmware's own file.

The result is cached under :func:`cache_root` by a hash of everything that
goes into it (the firmware's files, the stand-ins, the compiler and its
flags, the joint), so the first SITL device of a firmware builds it (about
a second a joint) and later ones load it. Two processes building at once
(pytest-xdist) wait for each other on a lock file and the library appears
in the cache by an atomic rename. The library is linked with every symbol
resolved (``--no-undefined``): firmware that lacks a function the runtime
calls (``loop()``) fails to build, with one line, rather than being cached
and failing at every load. A build that fails or is interrupted leaves
nothing in the cache but its lock file.

The repository holds no copy of the firmware: the source is the folder
given as ``--firmware DIR`` or ``BIOSCARA_FIRMWARE`` (``Arduino/joint/`` of
a checkout of the arm's repository, DALSA-Lab/bioscara).
"""

from __future__ import annotations

import argparse
import contextlib
import functools
import hashlib
import os
import re
import shutil
import subprocess
import tempfile
from collections.abc import Iterator
from pathlib import Path

from bioscara_gym.hardware.errors import SitlError

__all__ = [
    "CACHE_ENV",
    "CXX_FLAGS",
    "FIRMWARE_ENV",
    "JOINTS",
    "NATIVE_DIR",
    "add_firmware_option",
    "build_firmware",
    "cache_root",
    "find_compiler",
    "firmware_dir",
]

#: Environment variable naming the firmware's source folder (``Arduino/joint/``).
FIRMWARE_ENV = "BIOSCARA_FIRMWARE"
#: Environment variable overriding the cache folder of built firmware.
CACHE_ENV = "BIOSCARA_SITL_CACHE"
#: The joints the firmware can be built for; ``-D J1`` ... ``-D J4`` (``configuration.h``).
JOINTS = ("j1", "j2", "j3", "j4")
#: The project's stand-in headers (``include/``) and sources (``src/``).
NATIVE_DIR = Path(__file__).parent / "native"
#: Compiler flags of every translation unit. ``-ftrivial-auto-var-init=zero``
#: makes what the firmware reads of an uninitialized local (a short payload
#: into a handler's variable) zero, as the emulator's ``FirmwareCore`` does,
#: and the same run after run; ``-ffp-contract=off`` keeps float arithmetic
#: unfused; ``-fno-gnu-unique`` lets a loaded copy be unloaded.
CXX_FLAGS = (
    "-std=gnu++17",
    "-O2",
    "-fPIC",
    "-fvisibility=hidden",
    "-fno-gnu-unique",
    "-ftrivial-auto-var-init=zero",
    "-ffp-contract=off",
    "-w",
)
#: Linker flags: resolve every symbol at load time, and refuse a library
#: with a symbol nothing defines (else it is cached and fails at every load).
LD_FLAGS = ("-shared", "-Wl,-z,now", "-Wl,--no-undefined")
#: Libraries after the objects: the C library and libstdc++ come with the
#: C++ driver; the maths library is named as not every driver adds it.
LD_LIBS = ("-lm",)
#: Compilers tried in order after ``$CXX``.
COMPILERS = ("g++", "c++", "clang++")
#: Files of the firmware's folder that go into the build (and its hash).
_SOURCE_SUFFIXES = (".ino", ".cpp", ".c", ".h", ".hpp")
#: How long one compiler command may take, s.
_COMPILE_TIMEOUT_S = 600
#: Version of the build recipe; part of the hash.
_RECIPE = "1"


def add_firmware_option(parser: argparse.ArgumentParser) -> None:
    """Add ``--firmware DIR`` (the firmware source for ``--backend sitl``) to a command's parser."""
    parser.add_argument(
        "--firmware",
        type=Path,
        metavar="DIR",
        help=f"joint firmware source for --backend sitl (Arduino/joint/; default ${FIRMWARE_ENV})",
    )


def firmware_dir(option: str | os.PathLike[str] | None = None) -> Path:
    """The firmware's source folder: ``option``, else ``$BIOSCARA_FIRMWARE``.

    Raises:
        SitlError: Neither is set, the folder does not exist, or it holds no
            ``.ino`` sketch (the message says how to point at the firmware).
    """
    # Every message names where the folder came from: the option, or the variable set long ago.
    where = "--firmware " if option is not None else f"{FIRMWARE_ENV}="
    if option is None:
        option = os.environ.get(FIRMWARE_ENV) or None
    if option is None:
        raise SitlError(
            f"no firmware source: pass --firmware DIR or set {FIRMWARE_ENV} to the Arduino/joint/ "
            "folder of a checkout of the arm's repository (DALSA-Lab/bioscara)"
        )
    path = Path(option).expanduser()
    if not path.is_dir():
        why = "it is a file" if path.exists() else "it does not exist"
        raise SitlError(f"{where}{path}: not a folder: {why} (expected the firmware's Arduino/joint/)")
    _main_sketch(path, where)
    return path.resolve()


def _main_sketch(source: Path, where: str = "") -> Path:
    """The sketch to build: ``<folder>.ino``, or the folder's only ``.ino``.

    ``where`` (``"--firmware "``, ``"BIOSCARA_FIRMWARE="``) leads the error
    message, so it names the setting to change.
    """
    sketches = sorted(source.glob("*.ino"))
    named = source / f"{source.name}.ino"
    if named in sketches:
        return named
    if len(sketches) == 1:
        return sketches[0]
    if not sketches:
        raise SitlError(
            f"{where}{source}: no .ino sketch (expected the firmware's Arduino/joint/ with joint.ino)"
        )
    names = ", ".join(s.name for s in sketches)
    raise SitlError(f"{where}{source}: several sketches ({names}) and none named {source.name}.ino")


def _joint_macro(joint: str) -> str:
    if joint not in JOINTS:
        raise SitlError(f"joint {joint!r}: the firmware is built for one of {', '.join(JOINTS)}")
    return joint.upper()


def cache_root() -> Path:
    """Where built firmware is kept: ``$BIOSCARA_SITL_CACHE``, else ``$XDG_CACHE_HOME/bioscara/sitl``."""
    override = os.environ.get(CACHE_ENV)
    if override:
        return Path(override).expanduser()
    base = os.environ.get("XDG_CACHE_HOME") or os.path.join(os.path.expanduser("~"), ".cache")
    return Path(base) / "bioscara" / "sitl"


def find_compiler() -> str:
    """The C++ compiler: ``$CXX``, else the first of g++, c++, clang++ on the PATH.

    Raises:
        SitlError: None is found (the message says what to install).
    """
    candidates = [os.environ["CXX"]] if os.environ.get("CXX") else list(COMPILERS)
    for name in candidates:
        found = shutil.which(name)
        if found:
            return found
    tried = ", ".join(candidates)
    raise SitlError(
        f"no C++ compiler found (tried {tried}): the firmware in the loop is built on this machine; "
        "install g++ (GCC 12 or later) or set CXX"
    )


@functools.cache
def _compiler_identity(compiler: str) -> str:
    """The compiler's ``--version`` text (part of the cache key)."""
    try:
        done = subprocess.run(
            [compiler, "--version"], capture_output=True, text=True, errors="replace", timeout=60
        )
    except OSError as e:
        raise SitlError(f"C++ compiler {compiler} cannot be run: {e}") from e
    return done.stdout


def _firmware_files(source: Path) -> list[Path]:
    return sorted(p for p in source.iterdir() if p.is_file() and p.suffix in _SOURCE_SUFFIXES)


def _native_files() -> list[Path]:
    return sorted(p for p in NATIVE_DIR.rglob("*") if p.is_file() and p.suffix in (".h", ".cpp"))


def _digest(compiler: str, source: Path, joint: str) -> str:
    """The cache key; file names go in as the file system's bytes (a name need not be UTF-8)."""
    h = hashlib.sha256()
    h.update(f"recipe {_RECIPE}\njoint {joint}\n".encode())
    h.update(" ".join((*CXX_FLAGS, *LD_FLAGS, *LD_LIBS)).encode())
    h.update(_compiler_identity(compiler).encode())
    for base, files in ((NATIVE_DIR, _native_files()), (source, _firmware_files(source))):
        for path in files:
            h.update(b"\n" + os.fsencode(path.relative_to(base)) + b"\n")
            h.update(path.read_bytes())
    return h.hexdigest()


@contextlib.contextmanager
def _locked(path: Path) -> Iterator[None]:
    """Hold an exclusive lock on ``path`` (waiting for another process's build to end).

    The lock file stays when the build is done: removing it could happen
    while another process waits on it, and a third would then lock a new
    file of that name and build the same library alongside the second.
    """
    import fcntl

    path.parent.mkdir(parents=True, exist_ok=True)
    fd = os.open(path, os.O_RDWR | os.O_CREAT, 0o644)
    try:
        fcntl.flock(fd, fcntl.LOCK_EX)
        yield
    finally:
        os.close(fd)


def build_firmware(source: str | os.PathLike[str], joint: str) -> Path:
    """The firmware of ``source`` built for ``joint`` as a shared library, from the cache or built now.

    Args:
        source: The firmware's folder (see :func:`firmware_dir`).
        joint: ``"j1"`` ... ``"j4"``: the configuration ``-D J1`` ... ``-D J4`` selects.

    Returns:
        The cached library's path.

    Raises:
        SitlError: Unknown joint, no compiler, the cache is not writable, or
            the firmware does not build (one line: the compiler's first
            error, naming the file and line, or the function nothing defines).
    """
    source = Path(source)
    macro = _joint_macro(joint)
    compiler = find_compiler()
    digest = _digest(compiler, source, joint)
    root = cache_root()
    target = root / digest[:24] / f"joint_{joint}.so"
    if target.is_file():
        return target
    try:
        with _locked(root / f"{digest[:24]}.lock"):
            if target.is_file():  # built by another process while this one waited
                return target
            with tempfile.TemporaryDirectory(dir=root, prefix=".build-") as tmp:
                built = _compile(compiler, source, macro, Path(tmp))
                _publish(built, target)
    except OSError as e:
        if os.environ.get(CACHE_ENV):
            raise SitlError(f"the firmware cache {CACHE_ENV}={root} is not writable ({e})") from e
        raise SitlError(
            f"the firmware cache {root} is not writable ({e}); set {CACHE_ENV} to a writable folder"
        ) from e
    return target


def _publish(built: Path, target: Path) -> None:
    """Move the built library into its cache folder, made only now (never left empty).

    A folder made before the build stayed empty when the build failed or was
    interrupted (SIGINT, or the CLI's SIGTERM, arriving as an exception).
    """
    made = not target.parent.is_dir()
    try:
        target.parent.mkdir(parents=True, exist_ok=True)
        os.replace(built, target)
    except BaseException:
        if made:
            with contextlib.suppress(OSError):
                target.parent.rmdir()
        raise


def _compile(compiler: str, source: Path, macro: str, tmp: Path) -> Path:
    """Compile the sketch, its other sources and the stand-ins in ``tmp``; link; return the library."""
    include = ["-I", str(NATIVE_DIR / "include"), "-I", str(source)]
    defines = [f"-D{macro}="]
    config = ["-include", "configuration.h"] if (source / "configuration.h").is_file() else []
    units: list[tuple[list[str], Path]] = [
        ([*include, *defines, *config, "-x", "c++"], _main_sketch(source)),
    ]
    for path in _firmware_files(source):
        if path.suffix in (".cpp", ".c"):
            units.append(([*include, *defines], path))
    for path in sorted((NATIVE_DIR / "src").glob("*.cpp")):
        units.append((["-I", str(NATIVE_DIR / "include")], path))
    objects = []
    for i, (flags, path) in enumerate(units):
        obj = tmp / f"{i}_{path.stem}.o"
        _run([compiler, *CXX_FLAGS, *flags, "-c", str(path), "-o", str(obj)], path)
        objects.append(str(obj))
    library = tmp / "joint.so"
    _run([compiler, *LD_FLAGS, *objects, *LD_LIBS, "-o", str(library)], source, link=True)
    return library


def _run(command: list[str], path: Path, link: bool = False) -> None:
    """Run one compiler command; a failure is a :class:`SitlError` with the first error line.

    The output is decoded leniently: a source file not in UTF-8 (a comment
    in Latin-1) is quoted in it, and must not hide the error it reports.
    Interrupted (Ctrl-C, the CLI's SIGTERM), the compiler is asked to stop
    rather than killed: killed, the driver left its ``/tmp/cc*.s`` behind.
    """
    try:
        proc = subprocess.Popen(
            command, stdout=subprocess.PIPE, stderr=subprocess.PIPE, text=True, errors="replace"
        )
    except OSError as e:
        raise SitlError(f"C++ compiler {command[0]} cannot be run: {e}") from e
    with proc:
        try:
            _, stderr = proc.communicate(timeout=_COMPILE_TIMEOUT_S)
        except BaseException as e:
            proc.terminate()
            try:
                proc.wait(timeout=10)
            except subprocess.TimeoutExpired:
                proc.kill()
            if isinstance(e, subprocess.TimeoutExpired):
                raise SitlError(
                    f"the firmware does not build: {path}: the compiler took over {e.timeout:g} s"
                ) from e
            raise
    if proc.returncode != 0:
        raise SitlError(f"the firmware does not build: {_first_error(stderr, path, link)}")


#: A linker's complaint about a symbol (GNU ld and lld demangle C++ names by default).
_LINK_ERROR = re.compile(
    r"(undefined reference to|undefined symbol:|multiple definition of) *[`'\"]?([^`'\"]+)"
)


def _first_error(stderr: str, path: Path, link: bool = False) -> str:
    """The compiler's first error line (``file:line:col: error: ...``), else its last line.

    A link error (``link``) names no source line, and the linker's lines
    name temporary objects: it is the firmware's folder and the symbols,
    e.g. ``undefined reference to loop()`` for a sketch without ``loop()``.
    (Only then: a compiler's message quotes source lines, which may say anything.)
    """
    lines = [line.strip() for line in stderr.splitlines() if line.strip()]
    symbols: dict[str, list[str]] = {}
    for line in lines if link else ():
        if found := _LINK_ERROR.search(line):
            kind = "undefined reference to" if found.group(1).startswith("undefined") else found.group(1)
            names = symbols.setdefault(kind, [])
            if found.group(2).strip() not in names:
                names.append(found.group(2).strip())
    if symbols:
        kind, names = next(iter(symbols.items()))
        return f"{path}: {kind} {', '.join(names)}"
    for line in lines:
        if re.search(r"\b(error|fatal error)\b", line):
            if "trivial-auto-var-init" in line:
                return f"{line} (GCC 12 or clang 16 or later is needed)"
            return line
    return f"{path}: {lines[-1] if lines else 'the compiler failed without a message'}"
