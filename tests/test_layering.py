"""The package's structure, as rules that a change cannot quietly break.

- The driver layer (``bioscara_gym.hardware``: drivers, emulator, arm,
  config) imports with Gymnasium, MuJoCo, torch and stable-baselines3 all
  absent, as on a robot computer; a backend that needs MuJoCo says which
  extra to install.
- Importing ``bioscara_gym`` has no side effects beyond registering the
  tasks: no environment variables, and no warning filter but the one scoped
  to Gymnasium's unversioned-id message for the package's own ids.
- No import cycles among the project's modules, function-local imports
  included; ``training/`` imports no env module (it reaches the envs through
  ``gym.make`` and the task registry).
- The wheel installs one top-level import package, ``bioscara_gym``, with
  the hyperparameter files and the model inside it.
"""

from __future__ import annotations

import ast
import shutil
import subprocess
import sys
import tomllib
import zipfile
from pathlib import Path

import pytest
from rigs import run_blocked

ROOT = Path(__file__).resolve().parents[1]
#: Import name to source folder (the repository's training/ is installed as bioscara_gym.training).
PACKAGES = {"bioscara_gym": ROOT / "bioscara_gym", "bioscara_gym.training": ROOT / "training"}
HEAVY = ("gymnasium", "mujoco", "torch", "stable_baselines3")


def test_hardware_layer_imports_without_gymnasium_mujoco_torch_sb3() -> None:
    result = run_blocked(
        """
        import bioscara_gym.hardware
        from bioscara_gym.hardware import arm, backends, config, emulated_bus, firmware, joint, mock
        from bioscara_gym.hardware.arm import Arm
        from bioscara_gym.hardware.backends import make_backend

        with Arm(make_backend("mock")) as a:
            a.home()
        loaded = sorted(m for m in sys.modules if m.split(".")[0] in {heavy!r})
        print("loaded:", loaded)
        """.replace("{heavy!r}", repr(HEAVY)),
        HEAVY,
    )
    assert result.returncode == 0, result.stderr
    assert result.stdout.strip() == "loaded: []"


@pytest.mark.parametrize("backend", ["sim", "emulated"])
def test_mujoco_backend_without_mujoco_names_the_extra(backend: str) -> None:
    result = run_blocked(
        f"""
        from bioscara_gym.hardware.backends import make_backend
        from bioscara_gym.hardware.errors import MissingExtraError
        try:
            make_backend({backend!r})
        except MissingExtraError as e:
            print(e)
        """,
        ("mujoco",),
    )
    assert result.returncode == 0, result.stderr
    assert result.stdout.strip() == (
        f"the {backend} backend needs the [sim] extra: pip install 'bioscara-gym[sim]'"
    )


def test_collect_without_minari_names_the_train_extra(tmp_path: Path) -> None:
    # minari comes with [train]; without it `bioscara collect` printed a traceback.
    result = run_blocked(
        f"""
        import os
        os.environ["MINARI_DATASETS_PATH"] = {str(tmp_path)!r}
        from bioscara_gym.cli import main
        raise SystemExit(main(["collect", "--expert", "--env", "Bioscara-Reach", "--episodes", "1",
                               "--dataset", "reach-blocked"]))
        """,
        ("minari",),
    )
    assert result.returncode == 2, result.stderr
    assert result.stderr == (
        "bioscara collect: error: bioscara collect needs the [train] extra: "
        "pip install 'bioscara-gym[train]'\n"
    )


def test_importing_the_package_has_no_side_effects() -> None:
    result = subprocess.run(
        [
            sys.executable,
            "-c",
            "import os, sys, warnings\n"
            "import gymnasium\n"  # Gymnasium's own import-time settings are not ours
            "env, filters = dict(os.environ), list(warnings.filters)\n"
            "import bioscara_gym\n"
            "assert dict(os.environ) == env, set(os.environ.items()) ^ set(env.items())\n"
            "(added,) = [f for f in warnings.filters if f not in filters]\n"
            "assert warnings.filters == [added, *filters], warnings.filters[:3]\n"
            "action, message, category, module, _ = added\n"
            "assert (action, category) == ('ignore', UserWarning), added\n"
            "assert message.pattern == bioscara_gym.UNVERSIONED_MESSAGE, message\n"
            "assert module.pattern == r'gymnasium\\.envs\\.registration', module\n"
            "assert 'mujoco' not in sys.modules and 'bioscara_gym.envs' not in sys.modules\n"
            "assert 'Bioscara-Reach-v0' in gymnasium.registry\n",
        ],
        capture_output=True,
        text=True,
        timeout=120,
        env={"PATH": "/usr/bin:/bin"},  # no MUJOCO_GL, no DISPLAY: nothing may set them
    )
    assert result.returncode == 0, result.stderr


# ------------------------------------------------------------------ import cycles
def _module_name(path: Path) -> str:
    for package, folder in PACKAGES.items():
        if folder in path.parents or path.parent == folder:
            rel = path.relative_to(folder).with_suffix("")
            parts = [p for p in rel.parts if p != "__init__"]
            return ".".join([package, *parts])
    raise AssertionError(path)


def _modules() -> dict[str, Path]:
    found = {}
    for folder in PACKAGES.values():
        for path in folder.rglob("*.py"):
            if "configs" not in path.parts:
                found[_module_name(path)] = path
    return found


def _imports(path: Path, name: str, known: dict[str, Path]) -> set[str]:
    """The project modules ``path`` imports anywhere in it (function bodies included)."""
    is_package = path.name == "__init__.py"
    out = set()
    for node in ast.walk(ast.parse(path.read_text(encoding="utf-8"))):
        if isinstance(node, ast.Import):
            targets = [a.name for a in node.names]
        elif isinstance(node, ast.ImportFrom):
            base = node.module or ""
            if node.level:
                anchor = name.split(".") if is_package else name.split(".")[:-1]
                anchor = anchor[: len(anchor) - (node.level - 1)]
                base = ".".join([*anchor, base] if base else anchor)
            targets = [f"{base}.{a.name}" if f"{base}.{a.name}" in known else base for a in node.names]
        else:
            continue
        out.update(t for t in targets if t in known and t != name)
    return out


def _cycles(graph: dict[str, set[str]]) -> list[list[str]]:
    """Strongly connected components with more than one module (Tarjan)."""
    index: dict[str, int] = {}
    low: dict[str, int] = {}
    stack: list[str] = []
    on_stack: set[str] = set()
    found: list[list[str]] = []

    def visit(v: str) -> None:
        index[v] = low[v] = len(index)
        stack.append(v)
        on_stack.add(v)
        for w in graph[v]:
            if w not in index:
                visit(w)
                low[v] = min(low[v], low[w])
            elif w in on_stack:
                low[v] = min(low[v], index[w])
        if low[v] == index[v]:
            component = []
            while True:
                w = stack.pop()
                on_stack.discard(w)
                component.append(w)
                if w == v:
                    break
            if len(component) > 1:
                found.append(sorted(component))

    for v in graph:
        if v not in index:
            visit(v)
    return found


def test_cycle_finder_finds_a_function_local_cycle(tmp_path: Path) -> None:
    a = tmp_path / "a.py"
    a.write_text("def f():\n    from pkg.b import g\n")
    known = {"pkg.a": a, "pkg.b": tmp_path / "b.py"}
    (tmp_path / "b.py").write_text("import pkg.a\n")
    graph = {n: _imports(p, n, known) for n, p in known.items()}
    assert _cycles(graph) == [["pkg.a", "pkg.b"]]


def test_no_import_cycles() -> None:
    known = _modules()
    assert "bioscara_gym.training.train" in known and "bioscara_gym.hardware.arm" in known
    graph = {name: _imports(path, name, known) for name, path in known.items()}
    assert _cycles(graph) == []


def test_hardware_layer_imports_nothing_above_it() -> None:
    known = _modules()
    above = (
        "bioscara_gym.envs",
        "bioscara_gym.training",
        "bioscara_gym.console",
        "bioscara_gym.cli",
        "bioscara_gym.errors",
        "bioscara_gym.experts",
        "bioscara_gym.tasks",
        "bioscara_gym.replay",
        "bioscara_gym.validation",
    )
    offenders = {
        name: sorted(t for t in _imports(path, name, known) if t.startswith(above))
        for name, path in known.items()
        if name.startswith("bioscara_gym.hardware")
    }
    assert {n: t for n, t in offenders.items() if t} == {}


def test_training_reaches_the_envs_only_through_gym_make() -> None:
    # No env class, no env module: a task's experts, layout and extractor come from
    # bioscara_gym.tasks, keyed by env id.
    known = _modules()
    offenders = {
        name: sorted(t for t in _imports(path, name, known) if t.startswith("bioscara_gym.envs"))
        for name, path in known.items()
        if name.startswith("bioscara_gym.training")
    }
    assert {n: t for n, t in offenders.items() if t} == {}


# ------------------------------------------------------------------------ wheel
def test_training_modules_stay_small_enough_to_read() -> None:
    """Issue #26: no function in training/ over 60 lines, no file over 500."""
    too_long = []
    for path in sorted((ROOT / "training").glob("*.py")):
        text = path.read_text(encoding="utf-8")
        if len(text.splitlines()) > 500:
            too_long.append(f"{path.name}: {len(text.splitlines())} lines")
        for node in ast.walk(ast.parse(text)):
            if isinstance(node, ast.FunctionDef | ast.AsyncFunctionDef):
                length = (node.end_lineno or node.lineno) - node.lineno + 1
                if length > 60:
                    too_long.append(f"{path.name}:{node.lineno} {node.name}: {length} lines")
    assert not too_long, too_long


def test_core_dependencies_leave_out_the_heavy_ones() -> None:
    project = tomllib.loads((ROOT / "pyproject.toml").read_text())["project"]
    core = {d.split(">")[0].split("=")[0].split("[")[0].lower() for d in project["dependencies"]}
    assert core == {"numpy", "gymnasium", "smbus2", "pyyaml", "rich"}
    extras = project["optional-dependencies"]
    assert {"sim", "train", "onnx", "all"} <= set(extras)
    assert any(d.startswith("mujoco") for d in extras["sim"])
    assert any(d.startswith("torch") for d in extras["train"])
    assert any(d.startswith("onnxruntime") for d in extras["onnx"])


def test_wheel_holds_one_top_level_package(tmp_path: Path) -> None:
    # Build from a copy: a stale build/ folder in the tree must not leak into the wheel.
    source = tmp_path / "src"
    shutil.copytree(
        ROOT, source, ignore=shutil.ignore_patterns(".*", "build", "runs", "*.egg-info", "__pycache__")
    )
    result = subprocess.run(
        [
            sys.executable,
            "-m",
            "pip",
            "wheel",
            "--no-deps",
            "--no-build-isolation",
            "-q",
            "-w",
            str(tmp_path),
            str(source),
        ],
        capture_output=True,
        text=True,
        timeout=300,
    )
    assert result.returncode == 0, result.stderr
    # e.g. a folder of package data absent from `packages`, a deprecated license table
    assert "Warning" not in result.stdout + result.stderr
    (wheel,) = tmp_path.glob("bioscara_gym-*.whl")
    names = zipfile.ZipFile(wheel).namelist()
    top = {n.split("/")[0] for n in names if not n.split("/")[0].endswith((".dist-info", ".data"))}
    assert top == {"bioscara_gym"}
    for member in (
        "bioscara_gym/training/train.py",
        "bioscara_gym/training/configs/sac.yaml",
        "bioscara_gym/assets/scene.xml",
        "bioscara_gym/hardware/sitl/native/include/UstepperS32.h",
        "bioscara_gym/hardware/sitl/native/src/runtime.cpp",
        "bioscara_gym/hardware/default_config.yaml",
    ):
        assert member in names
