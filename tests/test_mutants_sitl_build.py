"""Tests that kill mutants mutmut found surviving in ``hardware/sitl/build.py`` (docs/mutation.md).

Unit level where the rule is the build's own, not the compiler's: the
``--firmware`` option, the messages naming where a folder came from, which
sketch is built, the cache folder, the compiler looked for, the one line a
compiler's or linker's output is turned into, and the cache folder left by a
build that fails as it is published. Compiler output is written here as GCC
and GNU ld print it; expected values are literals from build.py's docstrings
(``undefined reference to loop()``, "GCC 12 or clang 16 or later"). The
tests that build the real firmware skip without ``BIOSCARA_FIRMWARE``.
"""

from __future__ import annotations

import argparse
import json
import os
import re
import shutil
import sys
from pathlib import Path

import pytest
from rigs import sitl_source

from bioscara_gym.hardware.errors import SitlError
from bioscara_gym.hardware.sitl import build as sitl_build
from bioscara_gym.hardware.sitl.build import (
    add_firmware_option,
    build_firmware,
    cache_root,
    find_compiler,
    firmware_dir,
)

SKETCH = Path("/fw/joint")


# ------------------------------------------------------------ --firmware DIR
def test_the_firmware_option_is_a_path_named_dir_defaulting_to_none() -> None:
    parser = argparse.ArgumentParser()
    add_firmware_option(parser)
    assert parser.parse_args(["--firmware", "a/b"]).firmware == Path("a/b")
    assert parser.parse_args([]).firmware is None
    (action,) = [a for a in parser._actions if a.dest == "firmware"]
    assert action.metavar == "DIR"
    assert action.help == (
        "joint firmware source for --backend sitl (Arduino/joint/; default $BIOSCARA_FIRMWARE)"
    )


def test_a_bad_folder_names_the_setting_that_gave_it_and_why(
    tmp_path: Path, monkeypatch: pytest.MonkeyPatch
) -> None:
    monkeypatch.setenv("BIOSCARA_FIRMWARE", str(tmp_path / "missing"))
    with pytest.raises(SitlError) as info:
        firmware_dir()
    missing = tmp_path / "missing"
    assert str(info.value).startswith(f"BIOSCARA_FIRMWARE={missing}: not a folder: it does not exist")
    (tmp_path / "file").write_text("")
    with pytest.raises(SitlError) as info:
        firmware_dir(tmp_path / "file")
    assert str(info.value) == (
        f"--firmware {tmp_path / 'file'}: not a folder: it is a file (expected the firmware's Arduino/joint/)"
    )


def test_an_empty_variable_is_no_firmware_source(monkeypatch: pytest.MonkeyPatch) -> None:
    monkeypatch.setenv("BIOSCARA_FIRMWARE", "")
    with pytest.raises(SitlError) as info:
        firmware_dir(None)
    assert str(info.value) == (
        "no firmware source: pass --firmware DIR or set BIOSCARA_FIRMWARE to the Arduino/joint/ "
        "folder of a checkout of the arm's repository (DALSA-Lab/bioscara)"
    )


def test_the_option_wins_over_the_variable_and_is_resolved(
    tmp_path: Path, monkeypatch: pytest.MonkeyPatch
) -> None:
    (tmp_path / "fw").mkdir()
    (tmp_path / "fw" / "fw.ino").write_text("")
    monkeypatch.setenv("BIOSCARA_FIRMWARE", str(tmp_path / "missing"))
    monkeypatch.chdir(tmp_path)
    assert firmware_dir("fw") == tmp_path / "fw"


# ------------------------------------------------------------- which sketch
def test_the_sketch_named_for_its_folder_is_built_among_several(tmp_path: Path) -> None:
    for name in ("a.ino", "joint.ino", "z.ino"):
        (tmp_path / name).write_text("")
    (tmp_path / "joint.ino").rename(tmp_path / f"{tmp_path.name}.ino")
    assert sitl_build._main_sketch(tmp_path) == tmp_path / f"{tmp_path.name}.ino"


def test_a_folders_only_sketch_is_built_whatever_its_name(tmp_path: Path) -> None:
    (tmp_path / "other.ino").write_text("")
    assert sitl_build._main_sketch(tmp_path) == tmp_path / "other.ino"


def test_several_sketches_none_named_for_the_folder_are_listed(tmp_path: Path) -> None:
    (tmp_path / "b.ino").write_text("")
    (tmp_path / "a.ino").write_text("")
    with pytest.raises(SitlError) as info:
        firmware_dir(tmp_path)
    assert str(info.value) == (
        f"--firmware {tmp_path}: several sketches (a.ino, b.ino) and none named {tmp_path.name}.ino"
    )


def test_an_unknown_joint_lists_the_four_joints() -> None:
    with pytest.raises(SitlError) as info:
        sitl_build._joint_macro("j5")
    assert str(info.value) == "joint 'j5': the firmware is built for one of j1, j2, j3, j4"
    assert sitl_build._joint_macro("j3") == "J3"


# ------------------------------------------------------------ cache, compiler
def test_the_cache_is_the_variable_else_xdg_else_home(
    tmp_path: Path, monkeypatch: pytest.MonkeyPatch
) -> None:
    monkeypatch.setenv("HOME", str(tmp_path / "home"))
    monkeypatch.setenv("BIOSCARA_SITL_CACHE", "~/c")
    assert cache_root() == tmp_path / "home" / "c"
    monkeypatch.setenv("BIOSCARA_SITL_CACHE", "")
    monkeypatch.setenv("XDG_CACHE_HOME", str(tmp_path / "xdg"))
    assert cache_root() == tmp_path / "xdg" / "bioscara" / "sitl"
    monkeypatch.delenv("XDG_CACHE_HOME")
    assert cache_root() == tmp_path / "home" / ".cache" / "bioscara" / "sitl"


def _compilers(folder: Path, *names: str) -> None:
    folder.mkdir()
    for name in names:
        (folder / name).write_text("#!/bin/sh\n")
        (folder / name).chmod(0o755)


def test_cxx_is_the_compiler_when_set(tmp_path: Path, monkeypatch: pytest.MonkeyPatch) -> None:
    _compilers(tmp_path / "bin", "g++", "mycxx")
    monkeypatch.setenv("PATH", str(tmp_path / "bin"))
    monkeypatch.setenv("CXX", "mycxx")
    assert find_compiler() == str(tmp_path / "bin" / "mycxx")
    monkeypatch.setenv("CXX", "")
    assert find_compiler() == str(tmp_path / "bin" / "g++")


def test_no_compiler_says_what_to_install(tmp_path: Path, monkeypatch: pytest.MonkeyPatch) -> None:
    monkeypatch.delenv("CXX", raising=False)
    monkeypatch.setenv("PATH", str(tmp_path))
    with pytest.raises(SitlError) as info:
        find_compiler()
    assert str(info.value) == (
        "no C++ compiler found (tried g++, c++, clang++): the firmware in the loop is built on this "
        "machine; install g++ (GCC 12 or later) or set CXX"
    )


def test_the_compilers_are_tried_in_order(tmp_path: Path, monkeypatch: pytest.MonkeyPatch) -> None:
    _compilers(tmp_path / "bin", "clang++", "c++")
    monkeypatch.delenv("CXX", raising=False)
    monkeypatch.setenv("PATH", str(tmp_path / "bin"))
    assert find_compiler() == str(tmp_path / "bin" / "c++")


# ------------------------------------------------------ the compiler's one line
LINK_ERRORS = """\
/usr/bin/ld: /tmp/bioscara-sitl-x/0_joint.o: in function `setup':
joint.ino:(.text+0x1): undefined reference to `loop()'
/usr/bin/ld: /tmp/bioscara-sitl-x/3_Wire.o:(.bss+0x0): multiple definition of `Wire'; first defined here
/usr/bin/ld: joint.ino:(.text+0x9): undefined reference to `loop()'
ld.lld: error: undefined symbol: stall_check()
collect2: error: ld returned 1 exit status
"""


def test_a_link_error_names_the_folder_and_every_undefined_symbol_once() -> None:
    assert sitl_build._first_error(LINK_ERRORS, SKETCH, link=True) == (
        "/fw/joint: undefined reference to loop(), stall_check()"
    )


def test_a_multiple_definition_is_named_as_such() -> None:
    stderr = "/usr/bin/ld: a.o: multiple definition of `Wire'; b.o: first defined here\n"
    assert sitl_build._first_error(stderr, SKETCH, link=True) == "/fw/joint: multiple definition of Wire"


def test_a_compile_error_quoting_undefined_reference_is_the_error_line() -> None:
    stderr = (
        "joint.ino: In function 'void f()':\n"
        "joint.ino:3:5: error: 'x' was not declared in this scope\n"
        "    3 | // undefined reference to `y'\n"
    )
    expected = "joint.ino:3:5: error: 'x' was not declared in this scope"
    assert sitl_build._first_error(stderr, SKETCH) == expected


def test_a_fatal_error_is_the_first_error_line() -> None:
    stderr = "In file included from joint.ino:1:\n  joint.h:2:10: fatal error: gone.h: No such file\n"
    assert sitl_build._first_error(stderr, SKETCH) == "joint.h:2:10: fatal error: gone.h: No such file"


def test_an_old_compiler_refusing_the_zero_init_flag_is_told_which_it_needs() -> None:
    stderr = "g++: error: unrecognized command-line option '-ftrivial-auto-var-init=zero'\n"
    assert sitl_build._first_error(stderr, SKETCH) == (
        "g++: error: unrecognized command-line option '-ftrivial-auto-var-init=zero'"
        " (GCC 12 or clang 16 or later is needed)"
    )


def test_output_without_an_error_line_is_its_last_line_or_says_there_was_none() -> None:
    stderr = "note: a\nnote: b\n  Killed signal terminated program cc1plus  \n\n"
    assert sitl_build._first_error(stderr, SKETCH) == "/fw/joint: Killed signal terminated program cc1plus"
    assert sitl_build._first_error(" \n", SKETCH) == "/fw/joint: the compiler failed without a message"


def test_a_compiler_that_cannot_be_run_is_named(tmp_path: Path) -> None:
    with pytest.raises(SitlError) as info:
        sitl_build._run([str(tmp_path / "no-cxx"), "--version"], SKETCH)
    assert str(info.value).startswith(f"C++ compiler {tmp_path / 'no-cxx'} cannot be run: ")


def test_a_failing_compiler_is_one_line_of_its_error(tmp_path: Path) -> None:
    # A compiler quotes source lines, which may say anything: only a link is read for symbols.
    script = tmp_path / "cxx"
    script.write_text(
        "#!/bin/sh\necho '    3 | // undefined reference to y' >&2\n"
        "echo 'a.cpp:1:1: error: boom \\260' >&2\nexit 1\n"
    )
    script.chmod(0o755)
    with pytest.raises(SitlError) as info:
        sitl_build._run([str(script)], SKETCH)
    assert str(info.value) == "the firmware does not build: a.cpp:1:1: error: boom \ufffd"


def test_a_compiler_past_its_time_is_stopped_and_named(monkeypatch: pytest.MonkeyPatch) -> None:
    monkeypatch.setattr(sitl_build, "_COMPILE_TIMEOUT_S", 0.2)
    with pytest.raises(SitlError) as info:
        sitl_build._run(["sleep", "5"], SKETCH)
    assert str(info.value) == "the firmware does not build: /fw/joint: the compiler took over 0.2 s"


# ----------------------------------------------------------- publishing
def test_a_failed_publish_removes_the_folder_it_made(tmp_path: Path) -> None:
    (tmp_path / "cache").mkdir()
    with pytest.raises(FileNotFoundError):
        sitl_build._publish(tmp_path / "not-built.so", tmp_path / "cache" / "h" / "joint_j1.so")
    assert sorted(p.name for p in (tmp_path / "cache").iterdir()) == []


def test_a_failed_publish_keeps_a_folder_another_process_wrote_into(
    tmp_path: Path, monkeypatch: pytest.MonkeyPatch
) -> None:
    target = tmp_path / "h" / "joint_j1.so"

    def replaced_meanwhile(built: Path, to: Path) -> None:
        (tmp_path / "h" / "joint_j2.so").write_bytes(b"theirs")
        raise PermissionError(13, "denied")

    monkeypatch.setattr(os, "replace", replaced_meanwhile)
    with pytest.raises(PermissionError):  # the error, not the folder's removal failing
        sitl_build._publish(tmp_path / "built.so", target)
    assert sorted(p.name for p in target.parent.iterdir()) == ["joint_j2.so"]


def test_a_failed_publish_keeps_a_folder_it_did_not_make(tmp_path: Path) -> None:
    (tmp_path / "h").mkdir()
    with pytest.raises(FileNotFoundError):
        sitl_build._publish(tmp_path / "not-built.so", tmp_path / "h" / "joint_j1.so")
    assert (tmp_path / "h").is_dir()


def test_publish_moves_the_library_into_a_new_folder(tmp_path: Path) -> None:
    (tmp_path / "built.so").write_bytes(b"lib")
    sitl_build._publish(tmp_path / "built.so", tmp_path / "c" / "h" / "joint_j1.so")
    assert (tmp_path / "c" / "h" / "joint_j1.so").read_bytes() == b"lib"
    assert not (tmp_path / "built.so").exists()


# ---------------------------------------------------------------- the key
def test_the_cache_key_changes_with_the_joint_and_a_files_name(tmp_path: Path) -> None:
    (tmp_path / "joint.ino").write_text("void setup() {}\n")
    key = sitl_build._digest("g++", tmp_path, "j1")
    assert re.fullmatch(r"[0-9a-f]{64}", key)
    assert sitl_build._digest("g++", tmp_path, "j1") == key
    assert sitl_build._digest("g++", tmp_path, "j2") != key
    (tmp_path / "joint.ino").rename(tmp_path / "other.ino")
    assert sitl_build._digest("g++", tmp_path, "j1") != key


def test_the_stand_ins_go_into_the_key() -> None:
    names = [p.relative_to(sitl_build.NATIVE_DIR).as_posix() for p in sitl_build._native_files()]
    assert names == [
        "include/Arduino.h",
        "include/UstepperS32.h",
        "include/Wire.h",
        "src/arduino.cpp",
        "src/runtime.cpp",
        "src/sitl.h",
        "src/ustepper.cpp",
    ]


def test_only_sources_go_into_the_key(tmp_path: Path) -> None:
    (tmp_path / "joint.ino").write_text("void setup() {}\n")
    key = sitl_build._digest("g++", tmp_path, "j1")
    (tmp_path / "notes.txt").write_text("x")
    (tmp_path / "sub.h").mkdir()
    assert sitl_build._digest("g++", tmp_path, "j1") == key
    for name in ("a.cpp", "b.c", "c.h", "d.hpp"):
        (tmp_path / name).write_text("")
        assert sitl_build._digest("g++", tmp_path, "j1") != key, name
        key = sitl_build._digest("g++", tmp_path, "j1")


# ------------------------------------------------ the commands, by a stand-in compiler
FAKE_CXX = """\
#!{python}
import json, sys
args = sys.argv[1:]
if args == ["--version"]:
    print("fake c++ 1.0")
    sys.exit(0)
with open({log!r}, "a") as f:
    f.write(json.dumps(args) + "\\n")
print("compiling", args[-3])  # on stdout: not the user's
if {fail!r} and "-c" in args:
    print("cc1plus: Killed signal terminated program", file=sys.stderr)
    sys.exit(1)
open(args[args.index("-o") + 1], "w").close()
"""


def _fake_cxx(tmp_path: Path, monkeypatch: pytest.MonkeyPatch, fail: bool = False) -> Path:
    """``$CXX``: a stand-in logging each command (one JSON list a line) and making its ``-o`` file."""
    log, cxx = tmp_path / "commands.log", tmp_path / "fake-cxx"
    cxx.write_text(FAKE_CXX.format(python=sys.executable, log=str(log), fail=fail))
    cxx.chmod(0o755)
    monkeypatch.setenv("CXX", str(cxx))
    monkeypatch.setenv("BIOSCARA_SITL_CACHE", str(tmp_path / "cache"))
    return log


def _firmware(folder: Path, *names: str) -> Path:
    folder.mkdir()
    for name in (f"{folder.name}.ino", *names):
        (folder / name).write_text("")
    return folder


def _commands(log: Path) -> list[list[str]]:
    return [json.loads(line) for line in log.read_text().splitlines()]


def _has(command: list[str], *run: str) -> bool:
    """Whether ``run`` appears in ``command`` as consecutive arguments."""
    return any(command[i : i + len(run)] == list(run) for i in range(len(command)))


def test_the_sketch_is_built_for_the_joint_with_its_configuration_first(
    tmp_path: Path, monkeypatch: pytest.MonkeyPatch, capfd: pytest.CaptureFixture[str]
) -> None:
    log = _fake_cxx(tmp_path, monkeypatch)
    fw = _firmware(tmp_path / "fw", "configuration.h", "extra.c", "more.cpp", "notes.h")
    library = build_firmware(fw, "j2")
    assert library.name == "joint_j2.so" and library.is_file()
    sketch, *units, link = _commands(log)
    assert _has(sketch, "-DJ2=", "-include", "configuration.h", "-x", "c++", "-c", str(fw / "fw.ino"))
    built = [u[u.index("-c") + 1] for u in units]
    assert built[:2] == [str(fw / "extra.c"), str(fw / "more.cpp")]
    assert all(_has(u, "-I", str(fw), "-DJ2=", "-c") for u in units[:2])
    assert len(units) == len(list((sitl_build.NATIVE_DIR / "src").glob("*.cpp"))) + 2
    assert _has(link, "-shared", "-Wl,-z,now", "-Wl,--no-undefined")
    assert link[-4:-2] == [units[-1][-1], "-lm"] and link[-2] == "-o"  # -lm after the objects
    assert capfd.readouterr().out == ""
    build = Path(sketch[sketch.index("-o") + 1]).parent  # a hidden folder of the cache, gone after
    assert build.parent == tmp_path / "cache" and build.name.startswith(".build-") and not build.exists()


def test_a_library_is_cached_in_a_folder_named_by_its_key_beside_its_lock(
    tmp_path: Path, monkeypatch: pytest.MonkeyPatch
) -> None:
    _fake_cxx(tmp_path, monkeypatch)
    library = build_firmware(_firmware(tmp_path / "fw"), "j4")
    folder = library.parent.name
    assert (library.parent.parent, library.name) == (tmp_path / "cache", "joint_j4.so")
    assert re.fullmatch(r"[0-9a-f]{24}", folder)
    assert sorted(p.name for p in (tmp_path / "cache").iterdir()) == [folder, f"{folder}.lock"]
    assert sorted(p.name for p in library.parent.iterdir()) == ["joint_j4.so"]


def test_a_firmware_without_a_configuration_is_built_without_one(
    tmp_path: Path, monkeypatch: pytest.MonkeyPatch
) -> None:
    log = _fake_cxx(tmp_path, monkeypatch)
    build_firmware(_firmware(tmp_path / "fw"), "j1")
    assert not any("-include" in command for command in _commands(log))


def test_a_compiler_failing_without_an_error_line_names_the_unit(
    tmp_path: Path, monkeypatch: pytest.MonkeyPatch
) -> None:
    _fake_cxx(tmp_path, monkeypatch, fail=True)
    fw = _firmware(tmp_path / "fw")
    with pytest.raises(SitlError) as info:
        build_firmware(fw, "j1")
    assert str(info.value) == (
        f"the firmware does not build: {fw / 'fw.ino'}: cc1plus: Killed signal terminated program"
    )
    assert [p.suffix for p in (tmp_path / "cache").iterdir()] == [".lock"]


def test_building_a_folder_without_a_sketch_names_the_folder(
    tmp_path: Path, monkeypatch: pytest.MonkeyPatch
) -> None:
    _fake_cxx(tmp_path, monkeypatch)
    (tmp_path / "fw").mkdir()
    with pytest.raises(SitlError) as info:
        build_firmware(tmp_path / "fw", "j1")
    assert str(info.value) == (
        f"{tmp_path / 'fw'}: no .ino sketch (expected the firmware's Arduino/joint/ with joint.ino)"
    )


# ------------------------------------------------------------- real builds
@pytest.fixture(scope="module")
def source() -> str:
    return sitl_source()


def test_a_firmware_with_a_c_source_builds_it_too(
    source: str, tmp_path: Path, monkeypatch: pytest.MonkeyPatch
) -> None:
    copy = tmp_path / "joint"
    shutil.copytree(source, copy)
    (copy / "extra.cpp").write_text("this is not C++;\n")
    monkeypatch.setenv("BIOSCARA_SITL_CACHE", str(tmp_path / "cache"))
    with pytest.raises(SitlError, match=r"^the firmware does not build: .*extra\.cpp:1:"):
        build_firmware(copy, "j1")
    assert [p.suffix for p in (tmp_path / "cache").iterdir()] == [".lock"]
