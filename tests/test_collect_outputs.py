"""What ``collect`` and ``eval --video`` leave on disk when they are interrupted or raced.

Findings of a hostile test (2026-11-29), each a case here:

- ``collect --overwrite`` interrupted the moment the old ``main_data.hdf5``
  disappeared left no dataset at all, or an empty ``data/`` folder that
  ``train --demos`` read as "No data found";
- two ``collect``s into one dataset both succeeded: the second silently
  replaced the first's episodes without ``--overwrite``;
- an interrupted ``eval --video nd1/a/b/v.mp4`` left the folders ``nd1/a/b/``
  it had made.

Interruptions are simulated where they did harm (a ``KeyboardInterrupt``
from inside Minari's write, a signal raised by the test itself at the
moment the old data goes), not raced with real signals.
"""

from __future__ import annotations

import os
import shutil
import signal
from collections.abc import Callable
from pathlib import Path
from typing import Any

import numpy as np
import pytest
from rigs import one_line_error

import bioscara_gym  # noqa: F401
from bioscara_gym.cli import main

minari = pytest.importorskip("minari", reason="minari is in the [train] extra")

REACH = "Bioscara-Reach-v0"


pytestmark = pytest.mark.usefixtures("datasets")  # Minari's datasets in the test's tmp_path


def collect(*args: str) -> int:
    return main(["collect", "--no-progress", "--expert", "--env", "Bioscara-Reach", *args])


def episodes_in(dataset_id: str) -> int:
    return minari.load_dataset(dataset_id).total_episodes


# ----------------------------------------------------------- collect --overwrite
@pytest.mark.parametrize("when", ["before", "after"])
def test_overwrite_interrupted_while_minari_writes_keeps_the_old_dataset(
    when: str, datasets: Path, monkeypatch: pytest.MonkeyPatch, capsys: pytest.CaptureFixture[str]
) -> None:
    # Seen: the old dataset was removed first, then Minari's write interrupted: neither was left.
    assert collect("--episodes", "1", "--dataset", "ow") == 0
    write = minari.DataCollector.create_dataset

    def interrupted(self: Any, *args: Any, **kwargs: Any) -> Any:
        if when == "after":
            write(self, *args, **kwargs)
        raise KeyboardInterrupt

    monkeypatch.setattr(minari.DataCollector, "create_dataset", interrupted)
    assert collect("--episodes", "2", "--dataset", "ow", "--overwrite") == 130
    assert episodes_in("ow-v0") == 1
    assert sorted(p.name for p in datasets.iterdir()) == ["ow-v0"]  # no temporary folder left


def _signal_when_gone(data: Path, signum: int, monkeypatch: pytest.MonkeyPatch) -> Callable[[], bool]:
    """Raise ``signum`` once, right after the first rename or removal that leaves no ``data``."""
    fired = {"done": False}

    def watching(call: Callable[..., Any]) -> Callable[..., Any]:
        def watched(*args: Any, **kwargs: Any) -> Any:
            result = call(*args, **kwargs)
            if not fired["done"] and not data.exists():
                fired["done"] = True
                signal.raise_signal(signum)
            return result

        return watched

    monkeypatch.setattr(os, "rename", watching(os.rename))
    monkeypatch.setattr(os, "replace", watching(os.replace))
    monkeypatch.setattr(shutil, "rmtree", watching(shutil.rmtree))
    return lambda: fired["done"]


@pytest.mark.parametrize("signum", [signal.SIGINT, signal.SIGTERM], ids=["SIGINT", "SIGTERM"])
def test_a_signal_the_moment_the_old_data_goes_leaves_a_whole_dataset(
    signum: int, datasets: Path, monkeypatch: pytest.MonkeyPatch, capsys: pytest.CaptureFixture[str]
) -> None:
    # Seen: `ow-v0` gone entirely, or an empty `ow-v0/data/` left.
    assert collect("--episodes", "1", "--dataset", "ow") == 0
    capsys.readouterr()
    with pytest.MonkeyPatch.context() as mp:
        fired = _signal_when_gone(datasets / "ow-v0" / "data" / "main_data.hdf5", signum, mp)
        assert collect("--episodes", "2", "--dataset", "ow", "--overwrite") == 128 + signum
    assert fired()
    assert one_line_error(capsys, "collect", kind="").startswith("interrupted")
    assert episodes_in("ow-v0") in (1, 2)  # the old dataset whole, or the new one
    assert sorted(p.name for p in datasets.iterdir()) == ["ow-v0"]


def test_overwrite_replaces_the_dataset_once_the_new_one_is_whole(datasets: Path) -> None:
    assert collect("--episodes", "1", "--dataset", "ns/ow") == 0
    assert collect("--episodes", "2", "--dataset", "ns/ow", "--overwrite") == 0
    dataset = minari.load_dataset("ns/ow-v0")
    assert (dataset.total_episodes, dataset.spec.dataset_id) == (2, "ns/ow-v0")
    from minari.namespace import list_local_namespaces

    assert list_local_namespaces() == ["ns"]
    assert sorted(p.name for p in datasets.iterdir()) == ["ns"]
    assert sorted(p.name for p in (datasets / "ns").iterdir()) == ["namespace_metadata.json", "ow-v0"]


# ---------------------------------------------------------- two collects at once
def _competing_writer(monkeypatch: pytest.MonkeyPatch, name: str) -> None:
    """Another ``collect`` writes dataset ``name`` (1 episode) after this one's start check."""
    from bioscara_gym.training import collect as collect_command
    from bioscara_gym.training.demos import collect as record

    expert = collect_command.expert_factory

    def factory(env: Any) -> tuple[Any, Any]:
        record(REACH, 1, name, expert, progress=False)
        return expert(env)

    monkeypatch.setattr(collect_command, "expert_factory", factory)


def test_a_dataset_written_meanwhile_is_not_replaced_without_overwrite(
    datasets: Path, monkeypatch: pytest.MonkeyPatch, capsys: pytest.CaptureFixture[str]
) -> None:
    # Seen: both collects exited 0; the disk held the second's 30 episodes.
    _competing_writer(monkeypatch, "race")
    assert collect("--episodes", "3", "--dataset", "race") == 2
    error = one_line_error(capsys, "collect", kind="")
    assert error.startswith("error: dataset race-v0 ") and "3 episodes" in error and "--overwrite" in error
    assert episodes_in("race-v0") == 1
    assert sorted(p.name for p in datasets.iterdir()) == ["race-v0"]


def test_with_overwrite_a_dataset_written_meanwhile_is_replaced(
    datasets: Path, monkeypatch: pytest.MonkeyPatch
) -> None:
    _competing_writer(monkeypatch, "race")
    assert collect("--episodes", "3", "--dataset", "race", "--overwrite") == 0
    assert episodes_in("race-v0") == 3
    assert sorted(p.name for p in datasets.iterdir()) == ["race-v0"]


# ------------------------------------------------------------------ eval --video
def test_an_interrupted_video_removes_the_folders_it_made_and_only_those(tmp_path: Path) -> None:
    # Seen: `eval --video nd1/a/b/v.mp4` interrupted left nd1/a/b/.
    from bioscara_gym.training.evaluate import video_writer

    (tmp_path / "nd1").mkdir()
    with pytest.raises(KeyboardInterrupt), video_writer(tmp_path / "nd1/a/b/v.gif", fps=5) as sink:
        assert sink is not None
        sink(np.zeros((16, 16, 3), dtype=np.uint8))
        raise KeyboardInterrupt
    assert [p.name for p in tmp_path.iterdir()] == ["nd1"]  # there before: kept
    assert list((tmp_path / "nd1").iterdir()) == []


def test_a_folder_that_gains_another_file_meanwhile_is_kept(tmp_path: Path) -> None:
    from bioscara_gym.training.evaluate import video_writer

    with pytest.raises(ValueError), video_writer(tmp_path / "nd1/a/v.gif", fps=5):
        (tmp_path / "nd1" / "notes.txt").write_text("someone else's")
        raise ValueError("the evaluation failed")
    assert sorted(p.relative_to(tmp_path).as_posix() for p in tmp_path.rglob("*")) == [
        "nd1",
        "nd1/notes.txt",
    ]


def test_a_completed_video_keeps_the_folders_it_made(tmp_path: Path) -> None:
    from bioscara_gym.training.evaluate import video_writer

    with video_writer(tmp_path / "nd1/a/v.gif", fps=5) as sink:
        assert sink is not None
        sink(np.zeros((16, 16, 3), dtype=np.uint8))
    assert [p.name for p in (tmp_path / "nd1" / "a").iterdir()] == ["v.gif"]


def test_eval_interrupted_removes_the_video_folders_it_made(
    tmp_path: Path, monkeypatch: pytest.MonkeyPatch, capsys: pytest.CaptureFixture[str]
) -> None:
    from bioscara_gym.training import evaluate

    def interrupted(env: Any, policy: Any, episodes: int, seed: int, *args: Any, **kwargs: Any) -> Any:
        kwargs["on_frame"](np.zeros((16, 16, 3), dtype=np.uint8))
        raise KeyboardInterrupt

    monkeypatch.setattr(evaluate, "run_episodes", interrupted)
    monkeypatch.chdir(tmp_path)
    argv = ["eval", "--expert", "--env", "Bioscara-Reach", "--episodes", "30", "--video", "nd1/a/b/v.mp4"]
    assert main(argv) == 130
    assert one_line_error(capsys, "eval", kind="") == "interrupted"
    assert list(tmp_path.iterdir()) == []
