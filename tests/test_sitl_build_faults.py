"""Faults of the firmware-in-the-loop build and cache a hostile tester found (each seen twice).

Every bad input is one line naming what is wrong (the file, the option);
a build that fails or is interrupted leaves no folder in the cache, and a
library that does not link is never cached. Broken firmware is a copy in
``tmp_path``, never the real folder; each test has a cache of its own. The
tests skip without ``BIOSCARA_FIRMWARE`` (the reason says how to run them).
"""

from __future__ import annotations

import _ctypes
import os
import re
import shutil
import signal
import subprocess
import sys
import time
from collections.abc import Callable
from pathlib import Path

import pytest
from rigs import sitl_source

from bioscara_gym.hardware.clock import ManualClock
from bioscara_gym.hardware.errors import SitlError
from bioscara_gym.hardware.motor import KinematicStepper
from bioscara_gym.hardware.sitl import SitlFirmware, build_firmware, firmware_dir
from bioscara_gym.hardware.sitl import build as sitl_build
from bioscara_gym.hardware.sitl.build import CACHE_ENV, FIRMWARE_ENV


@pytest.fixture(scope="module")
def source() -> str:
    """The firmware's folder, or skip (``BIOSCARA_FIRMWARE``)."""
    return sitl_source()


@pytest.fixture
def cache(tmp_path: Path, monkeypatch: pytest.MonkeyPatch) -> Path:
    """A cache of the test's own (``BIOSCARA_SITL_CACHE``), not yet made."""
    root = tmp_path / "cache"
    monkeypatch.setenv(CACHE_ENV, str(root))
    return root


@pytest.fixture(scope="module")
def built_cache(source: str, tmp_path_factory: pytest.TempPathFactory) -> Path:
    """A cache holding the real firmware built for j1 (one build; tests copy it before spoiling it)."""
    root = tmp_path_factory.mktemp("built") / "cache"
    with pytest.MonkeyPatch.context() as mp:
        mp.setenv(CACHE_ENV, str(root))
        build_firmware(source, "j1")
    return root


def _copy(source: str, tmp_path: Path, edit: Callable[[Path], None]) -> Path:
    """The firmware copied into ``tmp_path/joint`` and changed by ``edit(copy)``."""
    copy = tmp_path / "joint"
    shutil.copytree(source, copy)
    edit(copy)
    return copy


def _append(text: bytes) -> Callable[[Path], None]:
    def edit(copy: Path) -> None:
        with open(copy / "joint.ino", "ab") as f:
            f.write(text)

    return edit


def _left_in(cache: Path) -> list[str]:
    """Everything in the cache but the per-build lock files (which stay by design)."""
    if not cache.exists():
        return []
    return sorted(str(p.relative_to(cache)) for p in cache.rglob("*") if p.suffix != ".lock")


def _one_line(e: pytest.ExceptionInfo[BaseException]) -> str:
    message = str(e.value)
    assert "\n" not in message, message
    return message


# --------------------------------------------------- a function missing at link time
def test_a_firmware_missing_a_function_does_not_build_and_is_not_cached(
    source: str, tmp_path: Path, cache: Path, bioscara: Callable[..., tuple[int, str, str]]
) -> None:
    # Seen: built and cached, then "/tmp/bioscara-sitl-….so: undefined symbol: _Z4loopv" on
    # loading, naming a deleted copy, and the same from the cache on every later run.
    def rename_loop(copy: Path) -> None:
        sketch = copy / "joint.ino"
        text = sketch.read_text(encoding="utf-8")
        assert "void loop(void)" in text
        sketch.write_text(text.replace("void loop(void)", "void loop_renamed(void)"), encoding="utf-8")

    broken = _copy(source, tmp_path, rename_loop)
    code, _, err = bioscara("ping", "--backend", "sitl", "--firmware", str(broken))
    assert code != 0
    assert err.startswith("bioscara ping: error: the firmware does not build: "), err
    assert "undefined reference to loop()" in err
    assert str(broken) in err
    assert "bioscara-sitl-" not in err and "_Z4loopv" not in err
    assert _left_in(cache) == []


# ------------------------------------------------------------ a damaged cache entry
@pytest.mark.parametrize("damage", ["another library", "truncated"])
def test_a_damaged_cached_library_is_one_line_naming_it(
    source: str, built_cache: Path, tmp_path: Path, monkeypatch: pytest.MonkeyPatch, damage: str
) -> None:
    # Seen: "AttributeError: /tmp/bioscara-sitl-….so: undefined symbol: sitl_api_version"
    # (a traceback) and "…: file too short", naming a temporary copy.
    cache = tmp_path / "cache"
    shutil.copytree(built_cache, cache)
    monkeypatch.setenv(CACHE_ENV, str(cache))
    (cached,) = cache.rglob("joint_j1.so")
    if damage == "another library":
        shutil.copyfile(_ctypes.__file__, cached)
    else:
        with open(cached, "r+b") as f:
            f.truncate(200)
    with pytest.raises(SitlError) as info:
        SitlFirmware(source, "j1", KinematicStepper(0.0), ManualClock())
    message = _one_line(info)
    assert str(cached) in message and "delete it" in message
    assert "bioscara-sitl-" not in message


# ------------------------------------------------ failed or interrupted builds
@pytest.mark.parametrize(
    "edit",
    [
        pytest.param(_append(b"\nthis is not C++;\n"), id="syntax-error"),
        pytest.param(lambda copy: (copy / "stall.h").write_text('#error "broken"\n'), id="error-in-stall.h"),
    ],
)
def test_a_failed_build_leaves_no_folder_in_the_cache(
    source: str, tmp_path: Path, cache: Path, edit: Callable[[Path], None]
) -> None:
    # Seen: an empty <cache>/<hash>/ after every failed build.
    broken = _copy(source, tmp_path, edit)
    with pytest.raises(SitlError, match=r"^the firmware does not build: "):
        build_firmware(broken, "j1")
    assert _left_in(cache) == []


def test_an_interrupted_build_leaves_no_folder_in_the_cache(
    source: str, cache: Path, monkeypatch: pytest.MonkeyPatch
) -> None:
    def interrupted(*args: object, **kwargs: object) -> None:
        raise KeyboardInterrupt  # Ctrl-C while the first unit compiles

    monkeypatch.setattr(sitl_build, "_run", interrupted)
    with pytest.raises(KeyboardInterrupt):
        build_firmware(source, "j1")
    assert _left_in(cache) == []


def test_sigterm_during_a_build_leaves_no_folder_in_the_cache(source: str, tmp_path: Path) -> None:
    # Seen: SIGTERM 4 s into `bioscara ping --backend sitl` left an empty <cache>/<hash>/.
    cache = tmp_path / "cache"
    env = {**os.environ, "MUJOCO_GL": "egl", CACHE_ENV: str(cache)}
    argv = [sys.executable, "-m", "bioscara_gym", "ping", "--backend", "sitl", "--firmware", source]
    proc = subprocess.Popen(argv, env=env, stdout=subprocess.DEVNULL, stderr=subprocess.PIPE, text=True)
    try:
        deadline = time.monotonic() + 60
        while not any(cache.glob(".build-*")) and time.monotonic() < deadline:
            time.sleep(0.02)
        time.sleep(0.3)  # the compiler is running
        assert proc.poll() is None, "the command ended before the signal"
        proc.send_signal(signal.SIGTERM)
        _, err = proc.communicate(timeout=60)
    finally:
        proc.kill()
    assert (proc.returncode, err.strip()) == (143, "bioscara ping: interrupted by SIGTERM")
    left = _left_in(cache)
    assert not [p for p in left if ".build-" in p]
    assert all(p.endswith(".so") for p in left if "/" in p)  # every <hash>/ holds its library
    assert all(any(q.startswith(p + "/") for q in left) for p in left if "/" not in p), left


# ----------------------------------------------------------------- not UTF-8
def test_a_sketch_not_in_utf8_gives_the_compilers_error(source: str, tmp_path: Path, cache: Path) -> None:
    # Seen: "'utf-8' codec can't decode byte 0xb0" in place of the syntax error.
    broken = _copy(source, tmp_path, _append(b"\nint y = ; // Winkel in \xb0\n"))
    line = (broken / "joint.ino").read_bytes().count(b"\n")
    with pytest.raises(SitlError) as info:
        build_firmware(broken, "j1")
    message = _one_line(info)
    assert message.startswith("the firmware does not build: ")
    assert f"joint.ino:{line}:" in message
    assert _left_in(cache) == []


def test_a_file_name_not_in_utf8_does_not_stop_the_build(source: str, tmp_path: Path, cache: Path) -> None:
    # Seen: "'utf-8' codec can't encode character '\udcff'" for a header named x\xff.h.
    def edit(copy: Path) -> None:
        (copy / os.fsdecode(b"x\xff.h")).write_bytes(b"// not included\n")
        _append(b"\nthis is not C++;\n")(copy)

    broken = _copy(source, tmp_path, edit)
    with pytest.raises(SitlError, match=r"^the firmware does not build: .*joint\.ino:"):
        build_firmware(broken, "j1")


# ------------------------------------------------------------------- wording
def test_a_firmware_folder_that_does_not_exist_says_so(tmp_path: Path) -> None:
    with pytest.raises(SitlError) as info:
        firmware_dir(tmp_path / "missing")
    assert _one_line(info).startswith(f"--firmware {tmp_path / 'missing'}: ")
    assert "does not exist" in str(info.value)
    (tmp_path / "file").write_text("")
    with pytest.raises(SitlError, match="not a folder") as info:
        firmware_dir(tmp_path / "file")
    assert "does not exist" not in str(info.value)


def test_a_folder_without_a_sketch_names_the_option_that_gave_it(
    tmp_path: Path, monkeypatch: pytest.MonkeyPatch
) -> None:
    folder = re.escape(str(tmp_path))
    with pytest.raises(SitlError, match=rf"^--firmware {folder}: no \.ino sketch"):
        firmware_dir(tmp_path)
    monkeypatch.setenv(FIRMWARE_ENV, str(tmp_path))
    with pytest.raises(SitlError, match=rf"^{FIRMWARE_ENV}={folder}: no \.ino sketch"):
        firmware_dir(None)


def test_an_unwritable_cache_names_where_it_was_set(
    source: str, tmp_path: Path, monkeypatch: pytest.MonkeyPatch
) -> None:
    (tmp_path / "file").write_text("")
    given = tmp_path / "file" / "cache"
    monkeypatch.setenv(CACHE_ENV, str(given))
    with pytest.raises(SitlError) as info:
        build_firmware(source, "j1")
    message = _one_line(info)
    assert f"{CACHE_ENV}={given}" in message and f"set {CACHE_ENV}" not in message
    monkeypatch.delenv(CACHE_ENV)
    monkeypatch.setenv("XDG_CACHE_HOME", str(tmp_path / "file"))
    with pytest.raises(SitlError) as info:
        build_firmware(source, "j1")
    assert f"set {CACHE_ENV}" in _one_line(info)
