"""Tests that kill mutants mutmut found surviving in ``training/demos.py`` (docs/mutation.md).

Unit level, no env and no Minari: how ``collect`` puts a dataset in place.
It is written into a hidden staging folder of the datasets root (Minari
told so through ``$MINARI_DATASETS_PATH``, restored after), its namespace
folders and metadata made in the root, then renamed into place; with
``--overwrite`` the old one is set aside first and put back if the rename
fails; without it anything at the path (an empty folder, a dangling link)
is kept and the episodes are refused in one line naming ``--overwrite``;
SIGINT and SIGTERM wait for the renames and win over an error. Folders are
written by the tests in ``tmp_path``; a stand-in collector writes the
dataset where the variable points. Expected values are literals from
demos.py's docstrings and messages.
"""

from __future__ import annotations

import errno
import os
import re
import signal
import sys
import warnings
from pathlib import Path
from typing import Any

import numpy as np
import pytest

from bioscara_gym.errors import MissingExtraError, TrainingError
from bioscara_gym.training import demos
from bioscara_gym.training.signals import Interrupted


def _folder(path: Path, name: str) -> Path:
    path.mkdir(parents=True)
    (path / name).write_text(name)
    return path


def _names(path: Path) -> list[str]:
    return sorted(p.name for p in path.iterdir())


# ------------------------------------------------------------ _move_into_place
def test_overwrite_puts_the_new_dataset_in_place_and_the_old_one_aside(tmp_path: Path) -> None:
    new, path = _folder(tmp_path / "new", "n"), _folder(tmp_path / "ds", "o")
    demos._move_into_place(new, path, tmp_path / "replaced", overwrite=True)
    assert _names(path) == ["n"]
    assert _names(tmp_path / "replaced") == ["o"]
    assert not new.exists()


def test_overwrite_without_an_old_dataset_just_renames(tmp_path: Path) -> None:
    new = _folder(tmp_path / "new", "n")
    demos._move_into_place(new, tmp_path / "ds", tmp_path / "replaced", overwrite=True)
    assert _names(tmp_path) == ["ds"]


def test_without_overwrite_an_empty_folder_at_the_path_is_kept(tmp_path: Path) -> None:
    new = _folder(tmp_path / "new", "n")
    (tmp_path / "ds").mkdir()
    with pytest.raises(FileExistsError) as info:
        demos._move_into_place(new, tmp_path / "ds", tmp_path / "replaced", overwrite=False)
    assert info.value.errno == errno.EEXIST
    assert (_names(tmp_path / "ds"), _names(new)) == ([], ["n"])


def test_without_overwrite_a_dangling_link_at_the_path_is_kept(tmp_path: Path) -> None:
    new = _folder(tmp_path / "new", "n")
    (tmp_path / "ds").symlink_to(tmp_path / "nowhere")
    with pytest.raises(FileExistsError):
        demos._move_into_place(new, tmp_path / "ds", tmp_path / "replaced", overwrite=False)
    assert (tmp_path / "ds").is_symlink() and _names(new) == ["n"]


def test_a_failed_rename_puts_the_old_dataset_back(tmp_path: Path) -> None:
    path = _folder(tmp_path / "ds", "o")
    with pytest.raises(FileNotFoundError):
        demos._move_into_place(tmp_path / "gone", path, tmp_path / "replaced", overwrite=True)
    assert _names(path) == ["o"]
    assert not (tmp_path / "replaced").exists()


def _once_set_aside(monkeypatch: pytest.MonkeyPatch, path: Path, then: Any) -> None:
    """``then()`` right after the rename that sets the old dataset at ``path`` aside."""
    rename = os.rename

    def renamed(src: Any, dst: Any) -> None:
        rename(src, dst)
        if src == path:
            then()

    monkeypatch.setattr(os, "rename", renamed)


def test_a_dataset_written_between_the_renames_is_kept_and_the_error_is_the_renames(
    tmp_path: Path, monkeypatch: pytest.MonkeyPatch
) -> None:
    new, path = _folder(tmp_path / "new", "n"), _folder(tmp_path / "ds", "o")
    _once_set_aside(monkeypatch, path, lambda: _folder(path, "theirs"))  # another command's lands
    with pytest.raises(OSError) as info:
        demos._move_into_place(new, path, tmp_path / "replaced", overwrite=True)
    assert info.value.errno in (errno.EEXIST, errno.ENOTEMPTY)
    assert (_names(path), _names(tmp_path / "replaced")) == (["theirs"], ["o"])


def test_a_signal_during_the_renames_is_raised_after_both(
    tmp_path: Path, monkeypatch: pytest.MonkeyPatch
) -> None:
    new, path = _folder(tmp_path / "new", "n"), _folder(tmp_path / "ds", "o")
    _once_set_aside(monkeypatch, path, lambda: signal.raise_signal(signal.SIGTERM))  # none at the path
    with pytest.raises(Interrupted) as info:
        demos._move_into_place(new, path, tmp_path / "replaced", overwrite=True)
    assert info.value.exit_code == 143
    assert _names(path) == ["n"]


def test_a_signal_wins_over_a_failed_rename(tmp_path: Path, monkeypatch: pytest.MonkeyPatch) -> None:
    (tmp_path / "ds").mkdir()

    def signalled_exists(path: Any) -> bool:
        signal.raise_signal(signal.SIGINT)
        return True

    monkeypatch.setattr(os.path, "lexists", signalled_exists)
    with pytest.raises(Interrupted) as info:
        demos._move_into_place(tmp_path / "new", tmp_path / "ds", tmp_path / "replaced", overwrite=False)
    assert info.value.exit_code == 130
    assert isinstance(info.value.__context__, FileExistsError)


# ------------------------------------------------------------- _datasets_path
def test_the_datasets_variable_is_set_for_the_block_and_restored(
    tmp_path: Path, monkeypatch: pytest.MonkeyPatch
) -> None:
    monkeypatch.setenv("MINARI_DATASETS_PATH", "/before")
    with demos._datasets_path(tmp_path):
        assert os.environ["MINARI_DATASETS_PATH"] == str(tmp_path)
    assert os.environ["MINARI_DATASETS_PATH"] == "/before"
    monkeypatch.delenv("MINARI_DATASETS_PATH")
    with pytest.raises(RuntimeError), demos._datasets_path(tmp_path):
        raise RuntimeError
    assert "MINARI_DATASETS_PATH" not in os.environ


# ---------------------------------------------------------- _adopt_namespaces
def test_namespace_folders_and_their_metadata_are_made_in_the_root(tmp_path: Path) -> None:
    staging, root = tmp_path / "staging", tmp_path / "root"
    _folder(staging / "a" / "b" / "x-v0", "data")
    (staging / "a" / "namespace_metadata.json").write_text("new a")
    (staging / "a" / "b" / "namespace_metadata.json").write_text("new b")
    _folder(root / "a", "namespace_metadata.json")  # a namespace's own metadata is kept
    demos._adopt_namespaces(staging, root, "a/b/x-v0")
    assert _names(root / "a") == ["b", "namespace_metadata.json"]
    assert (root / "a" / "namespace_metadata.json").read_text() == "namespace_metadata.json"
    assert _names(root / "a" / "b") == ["namespace_metadata.json"]  # the dataset itself is renamed later
    assert (root / "a" / "b" / "namespace_metadata.json").read_text() == "new b"


def test_a_nested_namespace_is_made_from_the_outermost(tmp_path: Path) -> None:
    staging, root = tmp_path / "staging", tmp_path / "root"
    _folder(staging / "a" / "b" / "x-v0", "data")
    (staging / "a" / "namespace_metadata.json").write_text("new a")
    root.mkdir()
    demos._adopt_namespaces(staging, root, "a/b/x-v0")
    assert _names(root / "a") == ["b", "namespace_metadata.json"]
    assert (root / "a" / "namespace_metadata.json").read_text() == "new a"


def test_a_dataset_without_a_namespace_makes_nothing(tmp_path: Path) -> None:
    (tmp_path / "root").mkdir()
    _folder(tmp_path / "staging" / "x-v0", "data")
    demos._adopt_namespaces(tmp_path / "staging", tmp_path / "root", "x-v0")
    assert _names(tmp_path / "root") == []


# ------------------------------------------------------------- _write_dataset
class Collector:
    """Writes ``<$MINARI_DATASETS_PATH>/<id>/data`` as Minari's ``create_dataset`` would."""

    def __init__(self, nags: bool = False) -> None:
        self.nags = nags
        self.metadata: dict[str, Any] = {}
        self.staging = Path()

    def create_dataset(self, dataset_id: str, **metadata: Any) -> None:
        if self.nags:  # Minari's warnings on the fields collect leaves unset, and another
            for field in ("author", "author_email", "code_permalink"):
                warnings.warn(f"`{field}` is set to None. For longevity ...", UserWarning, stacklevel=1)
            warnings.warn("another warning", UserWarning, stacklevel=1)
        self.metadata = metadata
        self.staging = Path(os.environ["MINARI_DATASETS_PATH"])
        _folder(self.staging / dataset_id, "data")


def test_a_written_dataset_is_moved_into_place_and_no_staging_is_left(
    tmp_path: Path, monkeypatch: pytest.MonkeyPatch
) -> None:
    monkeypatch.setenv("MINARI_DATASETS_PATH", str(tmp_path))
    collector = Collector(nags=True)
    with warnings.catch_warnings(record=True) as shown:
        warnings.simplefilter("always")
        demos._write_dataset(collector, tmp_path / "x-v0", "x-v0", 3, False, {"description": "d"})
    assert [str(w.message) for w in shown] == ["another warning"]  # only Minari's nagging is hidden
    assert _names(tmp_path) == ["x-v0"] and _names(tmp_path / "x-v0") == ["data"]
    assert collector.metadata == {"description": "d"}
    assert collector.staging.parent == tmp_path  # beside the datasets: a rename, never a copy
    assert re.fullmatch(r"\.collect-\w+\.tmp", collector.staging.name)  # hidden: Minari lists none
    assert os.environ["MINARI_DATASETS_PATH"] == str(tmp_path)


def test_a_dataset_written_meanwhile_is_one_line_naming_overwrite(
    tmp_path: Path, monkeypatch: pytest.MonkeyPatch
) -> None:
    monkeypatch.setenv("MINARI_DATASETS_PATH", str(tmp_path))
    _folder(tmp_path / "x-v0", "other")
    with pytest.raises(TrainingError) as info:
        demos._write_dataset(Collector(), tmp_path / "x-v0", "x-v0", 3, False, {})
    assert str(info.value) == (
        f"dataset x-v0 was written at {tmp_path / 'x-v0'} by another command while these 3 episodes "
        "were recorded; they are not kept: pass --overwrite to replace it, or name another dataset"
    )
    assert _names(tmp_path) == ["x-v0"] and _names(tmp_path / "x-v0") == ["other"]


@pytest.mark.parametrize("code", [errno.ENOTEMPTY, errno.ENOTDIR])
def test_with_overwrite_a_refused_rename_has_no_hint(
    code: int, tmp_path: Path, monkeypatch: pytest.MonkeyPatch
) -> None:
    monkeypatch.setenv("MINARI_DATASETS_PATH", str(tmp_path))

    def refused(*args: Any) -> None:
        raise OSError(code, os.strerror(code))

    monkeypatch.setattr(demos, "_move_into_place", refused)
    with pytest.raises(TrainingError) as info:
        demos._write_dataset(Collector(), tmp_path / "x-v0", "x-v0", 2, True, {})
    assert str(info.value).endswith("while these 2 episodes were recorded; they are not kept")
    assert _names(tmp_path) == []


def test_another_os_error_is_raised_as_it_is_and_leaves_nothing(
    tmp_path: Path, monkeypatch: pytest.MonkeyPatch
) -> None:
    monkeypatch.setenv("MINARI_DATASETS_PATH", str(tmp_path))

    def refused(*args: Any) -> None:
        raise PermissionError(errno.EACCES, "denied")

    monkeypatch.setattr(demos, "_move_into_place", refused)
    with pytest.raises(PermissionError):
        demos._write_dataset(Collector(), tmp_path / "x-v0", "x-v0", 2, False, {})
    assert _names(tmp_path) == []


# --------------------------------------------------------------- _new_dataset
def test_a_new_dataset_is_checked_before_the_episodes(
    tmp_path: Path, monkeypatch: pytest.MonkeyPatch
) -> None:
    monkeypatch.setenv("MINARI_DATASETS_PATH", str(tmp_path))
    with pytest.raises(TrainingError, match=r"^episodes must be > 0, got 0$"):
        demos._new_dataset("x", 0, False)
    assert demos._new_dataset("x", 1, False) == ("x-v0", tmp_path / "x-v0")
    (tmp_path / "x-v0").mkdir()
    with pytest.raises(TrainingError) as info:
        demos._new_dataset("x", 1, False)
    assert str(info.value) == f"dataset x-v0 exists at {tmp_path / 'x-v0'}; pass --overwrite to replace it"
    assert demos._new_dataset("x", 1, True) == ("x-v0", tmp_path / "x-v0")


# ----------------------------------------------------------------- collect
def _still(env: Any) -> tuple[Any, Any]:
    """A policy that never moves (a failed episode at the time limit), and no reset of its own."""
    return (lambda obs: np.zeros(env.action_space.shape, dtype=np.float32)), (lambda: None)


def test_collect_keeps_an_existing_dataset_by_default(datasets: Path) -> None:
    (datasets / "x-v0").mkdir(parents=True)
    with pytest.raises(TrainingError, match=r"^dataset x-v0 exists at .*; pass --overwrite to replace it$"):
        demos.collect("Bioscara-Reach-v0", 1, "x", _still)


def test_collect_names_the_train_extra_when_minari_is_missing(
    datasets: Path, monkeypatch: pytest.MonkeyPatch
) -> None:
    monkeypatch.setitem(sys.modules, "minari", None)
    with pytest.raises(MissingExtraError) as info:
        demos.collect("Bioscara-Reach-v0", 1, "x", _still)
    assert str(info.value) == "bioscara collect needs the [train] extra: pip install 'bioscara-gym[train]'"
    assert not datasets.exists()


def test_collect_records_seeded_episodes_with_the_default_metadata(
    datasets: Path, capsys: pytest.CaptureFixture[str]
) -> None:
    minari = pytest.importorskip("minari", reason="minari is in the [train] extra")
    result = demos.collect("Bioscara-Reach-v0", 1, "x", _still)
    assert (result.dataset_id, result.path) == ("x-v0", datasets / "x-v0")
    assert (result.episodes, result.success_rate) == (1, 0.0)
    assert 0 < result.wall_time_s < 60
    dataset = minari.load_dataset("x-v0")
    metadata = dataset.storage.metadata
    assert metadata["algorithm_name"] == "scripted expert"
    assert metadata["description"] == "1 episodes of scripted expert on Bioscara-Reach-v0 ({}); success 0.0%"
    (meta,) = dataset.storage.get_episode_metadata([0])
    assert meta["seed"] == 0
    (episode,) = dataset.iterate_episodes()
    assert episode.infos == {}  # record_infos=False
    err = capsys.readouterr().err
    assert "collect x-v0" in err and "/1" in err  # the bar, shown by default
