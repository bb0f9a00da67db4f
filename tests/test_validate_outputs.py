"""What ``bioscara validate --json --plots`` and ``calibrate --out`` write, and refuse to write over.

Findings of a hostile test (2026-11-29), each a case here: ``--json`` and
``--out`` replaced files of another kind (notes, a script, a hard link to a
CSV); ``--plots`` replaced a text file named like a picture, and a symlink
by a file; a folder named like a picture failed the command after the whole
validation, naming a hidden path, with the JSON already replaced; ``--json``
naming a picture was lost under it; a recording's name with a newline split
the error in two, and a loop of symlinks was "not a folder".

Every refusal comes before the work: the folder's recordings are one or two
packaged ones, and ``validate`` itself fails the test if it is reached.
"""

from __future__ import annotations

import shutil
from pathlib import Path

import pytest
from rigs import one_line_error

from bioscara_gym.cli import main
from bioscara_gym.hardware import load_config
from bioscara_gym.validation.recordings import DATA_DIR

PNG = b"\x89PNG\r\n\x1a\n"



def _recordings(root: Path, *names: str) -> Path:
    (root / "maxAccel").mkdir(parents=True)
    for name in names:
        shutil.copy(DATA_DIR / "maxAccel" / name, root / "maxAccel")
    return root


@pytest.fixture
def data(tmp_path: Path, monkeypatch: pytest.MonkeyPatch) -> Path:
    """``data/`` with maxAccel j1_1 and j3_6 in ``tmp_path`` (the working folder); no replay may run."""
    import bioscara_gym.validation as validation

    def no_replay(*args: object, **kwargs: object) -> None:
        raise AssertionError("a replay ran before the outputs were checked")

    monkeypatch.setattr(validation, "validate", no_replay)
    monkeypatch.chdir(tmp_path)
    return _recordings(tmp_path / "data", "j1_1.csv", "j3_6.csv")


@pytest.mark.parametrize(
    "content",
    [b"my notes\n", b"#!/bin/sh\nrm -rf /\n", bytes(range(256)), b"joints: []\n", b'{"rows": []}\n'],
    ids=["notes", "script", "binary", "yaml", "other-json"],
)
def test_validate_json_refuses_a_file_that_is_not_its_rows(
    data: Path, content: bytes, capsys: pytest.CaptureFixture[str]
) -> None:
    # Seen: --json notes.txt (a script, a binary, a YAML config, the data's README.md) was overwritten.
    Path("notes.txt").write_bytes(content)
    assert main(["validate", "data", "--json", "notes.txt"]) == 2
    assert one_line_error(capsys, "validate") == (
        "--json notes.txt: exists and is not a validate --json rows file; "
        "give a new file, or a validate --json rows file to replace"
    )
    assert Path("notes.txt").read_bytes() == content


def test_calibrate_out_refuses_a_file_that_is_not_an_arm_configuration(
    data: Path, capsys: pytest.CaptureFixture[str]
) -> None:
    # Seen: --out notes.txt turned the notes into YAML; so did --out on a hard link to a CSV.
    pytest.importorskip("scipy")
    Path("notes.txt").write_text("my notes\n")
    shutil.copy("data/maxAccel/j1_1.csv", "kept.csv")  # a CSV that is no input of the command
    Path("link.yaml").hardlink_to("kept.csv")
    for out in ("notes.txt", "link.yaml"):
        assert main(["calibrate", "data", "--out", out, "--maxiter", "1", "--workers", "1"]) == 2
        assert one_line_error(capsys, "calibrate") == (
            f"--out {out}: exists and is not an arm configuration (YAML); "
            "give a new file, or an arm configuration (YAML) to replace"
        )
    assert Path("notes.txt").read_text() == "my notes\n"
    assert Path("kept.csv").read_bytes() == (DATA_DIR / "maxAccel" / "j1_1.csv").read_bytes()
    # An arm configuration (calibrate's own output) is replaced: the work starts.
    shutil.copy(DATA_DIR.parent.parent / "hardware" / "default_config.yaml", "arm.yaml")
    with pytest.raises(AssertionError, match="a replay ran"):
        main(["calibrate", "data", "--out", "arm.yaml", "--maxiter", "1", "--workers", "1"])


def test_plots_refuse_a_text_file_named_like_a_picture(
    data: Path, capsys: pytest.CaptureFixture[str]
) -> None:
    # Seen: pl/maxAccel_j1_1.png holding text was replaced by a PNG.
    Path("pl").mkdir()
    Path("pl/maxAccel_j1_1.png").write_text("not a picture")
    assert main(["validate", "data", "--plots", "pl"]) == 2
    assert one_line_error(capsys, "validate") == (
        "--plots pl: pl/maxAccel_j1_1.png exists and is not a PNG image; "
        "a picture is written there: move it, or give another folder"
    )
    assert Path("pl/maxAccel_j1_1.png").read_text() == "not a picture"


def test_a_folder_named_like_a_picture_is_refused_before_the_work(
    data: Path, capsys: pytest.CaptureFixture[str]
) -> None:
    # Seen: the whole validation ran, then "Is a directory: p7/pl/.drawing-XXXX/maxAccel_j3_9.png",
    # after j.json had been replaced and 16 of the 41 PNGs moved in.
    Path("p7/pl/maxAccel_j3_6.png").mkdir(parents=True)
    Path("p7/j.json").write_text("[]\n")
    assert main(["validate", "data", "--plots", "p7/pl", "--json", "p7/j.json"]) == 2
    assert one_line_error(capsys, "validate") == (
        "--plots p7/pl: p7/pl/maxAccel_j3_6.png is a folder; "
        "a picture is written there: move it, or give another folder"
    )
    assert Path("p7/j.json").read_text() == "[]\n"
    assert sorted(p.name for p in Path("p7/pl").iterdir()) == ["maxAccel_j3_6.png"]


def test_json_naming_a_picture_of_plots_is_refused_before_the_work(
    data: Path, capsys: pytest.CaptureFixture[str]
) -> None:
    # Seen: "json p5/maxAccel_j1_1.png" and "plots p5 (41 PNG)" printed; the JSON lost under the PNG.
    Path("p5").mkdir()
    assert main(["validate", "data", "--plots", "p5", "--json", "p5/maxAccel_j1_1.png"]) == 2
    assert one_line_error(capsys, "validate") == (
        "--json and --plots name the same file p5/maxAccel_j1_1.png; each needs its own"
    )
    assert list(Path("p5").iterdir()) == []


def test_a_recording_named_with_a_newline_is_named_on_one_line(
    tmp_path: Path, monkeypatch: pytest.MonkeyPatch, capsys: pytest.CaptureFixture[str]
) -> None:
    # Seen: the error came out on two lines, split inside the file's name.
    monkeypatch.chdir(tmp_path)
    Path("data/maxAccel").mkdir(parents=True)
    Path("data/maxAccel/j1\n_1.csv").write_text("garbage\n")
    assert main(["validate", "data"]) == 2
    assert one_line_error(capsys, "validate") == (
        "data/maxAccel/j1\\n_1.csv: no 't, q, qd, qdd' header line (not a maxAccel recording?)"
    )


def test_a_loop_of_symlinks_as_the_folder_is_named_a_loop(
    tmp_path: Path, monkeypatch: pytest.MonkeyPatch, capsys: pytest.CaptureFixture[str]
) -> None:
    # Seen: "loop: is not a folder".
    monkeypatch.chdir(tmp_path)
    Path("loop").symlink_to("back")
    Path("back").symlink_to("loop")
    assert main(["validate", "loop"]) == 2
    assert one_line_error(capsys, "validate") == "loop: is a loop of symlinks"


# ------------------------------------------------------- pictures drawn
@pytest.fixture(scope="module")
def validation(tmp_path_factory: pytest.TempPathFactory) -> object:
    """The validation of maxAccel j1_1 and j3_6 (two pictures), done once."""
    pytest.importorskip("matplotlib")
    from bioscara_gym.validation import validate

    root = _recordings(tmp_path_factory.mktemp("rec") / "data", "j1_1.csv", "j3_6.csv")
    return validate(root, load_config())


def test_a_picture_is_written_through_a_symlink_the_link_kept(
    tmp_path: Path, validation: object, monkeypatch: pytest.MonkeyPatch, capsys: pytest.CaptureFixture[str]
) -> None:
    # Seen: pl/maxAccel_j3_6.png -> victim.txt was replaced by a regular file. A picture is
    # written through to the link's target, as every output is (README): if that is a picture.
    import bioscara_gym.validation as package

    monkeypatch.setattr(package, "validate", lambda *args, **kwargs: validation)
    monkeypatch.chdir(tmp_path)
    _recordings(tmp_path / "data", "j1_1.csv", "j3_6.csv")
    Path("pl").mkdir()
    Path("victim.txt").write_text("kept")
    Path("pl/maxAccel_j3_6.png").symlink_to("../victim.txt")
    assert main(["validate", "data", "--plots", "pl"]) == 2
    assert one_line_error(capsys, "validate") == (
        f"--plots pl: pl/maxAccel_j3_6.png is a symlink to {tmp_path}/victim.txt, which exists and is not "
        "a PNG image; a picture is written there: move it, or give another folder"
    )
    assert Path("victim.txt").read_text() == "kept" and not Path("pl/maxAccel_j1_1.png").exists()
    Path("victim.txt").write_bytes(PNG)  # an earlier picture: replaced through the link
    assert main(["validate", "data", "--plots", "pl"]) == 0
    assert Path("pl/maxAccel_j3_6.png").is_symlink() and Path("victim.txt").read_bytes()[:8] == PNG
    assert Path("victim.txt").stat().st_size > 1000
    assert sorted(p.name for p in Path("pl").iterdir()) == ["maxAccel_j1_1.png", "maxAccel_j3_6.png"]


def test_a_place_taken_after_drawing_leaves_every_picture_out_naming_its_path(
    tmp_path: Path, validation: object
) -> None:
    # Seen: "Is a directory: .../.drawing-XXXX/maxAccel_j3_9.png" with some pictures moved in.
    from bioscara_gym.validation import plots

    out = tmp_path / "pl"
    out.mkdir()
    staged = plots.stage_plots(validation, out)  # type: ignore[arg-type]
    (out / "maxAccel_j3_6.png").mkdir()
    with pytest.raises(OSError) as e:
        staged.commit()
    assert e.value.strerror == (
        f"{out}/maxAccel_j3_6.png is a folder; a picture is written there: move it, or give another folder"
    )
    assert sorted(p.name for p in out.iterdir()) == ["maxAccel_j3_6.png"]
