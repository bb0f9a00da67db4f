"""What a hostile test of ``bioscara deploy`` and ``bioscara export`` found, each pinned.

Crafted ONNX files (an action of the wrong rank, a graph computing another
width than it declares, ``obs_keys`` reordered or not whole numbers), fault
times beyond any bus's timeout, outputs naming files of another kind or
places that refuse a file: each is refused in one line, exit 2, before a
byte reaches the arm, and no file is touched.
"""

from __future__ import annotations

import json
import os
import shutil
from pathlib import Path
from typing import Any

import numpy as np
import pytest

from bioscara_gym.cli import main
from bioscara_gym.errors import DeployError
from bioscara_gym.hardware.emulated_bus import FaultPlan

REACH = "Bioscara-Reach-v0"


def refused(err: str, command: str = "deploy") -> str:
    """The one line of a refusal (``err``: stderr), checked to be one line; without the prefix."""
    assert err.count("\n") == 1 and "Traceback" not in err, err
    prefix = f"bioscara {command}: error: "
    assert err.startswith(prefix), err
    return err[len(prefix) : -1]


def deploy(tmp_path: Path, *argv: str) -> list[str]:
    """Deploy's arguments on ``emulated`` with a log and a gripper state file in ``tmp_path``."""
    return [
        "deploy",
        "--backend",
        "emulated",
        "--log",
        str(tmp_path / "deploy.jsonl"),
        "--state-file",
        str(tmp_path / "gripper.json"),
        *argv,
    ]


# ------------------------------------------------------------- crafted ONNX files
def with_props(onnx_path: Path, out: Path, **props: str) -> Path:
    """The exported file with some metadata_props replaced."""
    import onnx

    proto = onnx.load(str(onnx_path))
    values = {p.key: p.value for p in proto.metadata_props}
    values.update(props)
    del proto.metadata_props[:]
    for key, value in values.items():
        proto.metadata_props.add(key=key, value=value)
    onnx.save(proto, str(out))
    return out


def graph(onnx_path: Path, out: Path, width: int, rank3: bool = False, rank1: bool = False) -> Path:
    """A graph ``obs [batch, 18] -> action``, with the exported file's metadata, as mkgraph.py made them.

    ``width``: the values it computes per row (it declares 4); ``rank3``: it
    gives ``[batch, 1, 4]``; ``rank1``: ``[4]``.
    """
    import onnx
    from onnx import TensorProto, helper, numpy_helper

    base = onnx.load(str(onnx_path))
    weights = numpy_helper.from_array(np.full((18, width), 0.01, np.float32), "W")
    nodes = [helper.make_node("MatMul", ["obs", "W"], ["action" if not (rank3 or rank1) else "m"])]
    inits = [weights]
    shape: list[Any] = ["batch", 4]
    if rank3:
        inits.append(numpy_helper.from_array(np.array([1], np.int64), "ax"))
        nodes.append(helper.make_node("Unsqueeze", ["m", "ax"], ["action"]))
        shape = ["batch", 1, 4]
    elif rank1:
        inits.append(numpy_helper.from_array(np.array([-1], np.int64), "shp"))
        nodes.append(helper.make_node("Reshape", ["m", "shp"], ["action"]))
        shape = [4]
    g = helper.make_graph(
        nodes,
        "g",
        [helper.make_tensor_value_info("obs", TensorProto.FLOAT, ["batch", 18])],
        [helper.make_tensor_value_info("action", TensorProto.FLOAT, shape)],
        inits,
    )
    model = helper.make_model(g, opset_imports=[helper.make_opsetid("", 17)])
    model.ir_version = base.ir_version
    model.graph.doc_string = base.graph.doc_string  # its seal of the metadata
    for p in base.metadata_props:
        model.metadata_props.add(key=p.key, value=p.value)
    onnx.save(model, str(out))
    return out


@pytest.mark.parametrize("kind", ["fifo", "folder"])
def test_an_onnx_path_that_is_no_regular_file_is_refused_in_one_line(
    kind: str, tmp_path: Path, bus_traffic: list[tuple[int, bytes]], capsys: pytest.CaptureFixture[str]
) -> None:
    # Seen: a FIFO hung deploy --onnx until killed; a folder was "Protobuf parsing failed".
    path = tmp_path / "policy.onnx"
    if kind == "fifo":
        os.mkfifo(path)
    else:
        path.mkdir()
    assert main(deploy(tmp_path, "--onnx", str(path))) == 2
    assert refused(capsys.readouterr().err) == (
        f"{path} is not a regular file; give the .onnx file of `bioscara export`"
    )
    assert bus_traffic == []


# ------------------------------------------- 1: an action of the wrong shape
@pytest.mark.parametrize(
    ("kind", "shape"), [("rank3", "[batch, 1, 4]"), ("rank1", "[4]")], ids=["batch-1-4", "rank-1"]
)
def test_an_onnx_action_of_the_wrong_rank_is_refused_before_the_arm_is_touched(
    kind: str,
    shape: str,
    onnx_path: Path,
    tmp_path: Path,
    bus_traffic: list[tuple[int, bytes]],
    capsys: pytest.CaptureFixture[str],
) -> None:
    # Seen: "acts finitely; nothing sent to the arm yet", configured and homed, then the first
    # cycle failed "policy returned an action of shape (1, 4); the env expects (4,)", exit 1.
    crafted = graph(onnx_path, tmp_path / f"{kind}.onnx", 4, **{kind: True})
    code = main(deploy(tmp_path, "--onnx", str(crafted)))
    line = refused(capsys.readouterr().err)
    assert code == 2
    assert line == (
        f"{crafted}: the graph's output 'action' has shape {shape}; `bioscara export` writes "
        "[batch, n]: one row per observation"
    )
    assert bus_traffic == [] and not (tmp_path / "deploy.jsonl").exists()


def test_a_graph_computing_another_width_than_it_declares_is_one_accurate_line(
    onnx_path: Path, tmp_path: Path, bus_traffic: list[tuple[int, bytes]], capfd: pytest.CaptureFixture[str]
) -> None:
    # Seen: onnxruntime's own coloured warning line first, then "the graph's last input and
    # output dimensions must be fixed", which they were (it declares [batch, 4], computes 8).
    crafted = graph(onnx_path, tmp_path / "lie8.onnx", 8)
    code = main(deploy(tmp_path, "--onnx", str(crafted)))
    out, err = capfd.readouterr()
    assert code == 2
    assert refused(err) == (
        f"{crafted}: onnxruntime reads the graph's output 'action' as [batch, ?], no fixed width "
        "(what the graph computes is not what it declares, or it declares none); "
        "run once it gives shape (1, 8)"
    )
    assert out == "" and bus_traffic == []


def test_a_policy_whose_probe_action_has_the_wrong_shape_is_refused(
    sac_dir: Path, tmp_path: Path, bus_traffic: list[tuple[int, bytes]]
) -> None:
    from rich.console import Console

    from bioscara_gym.training.deploy import DeployArgs, Deployment

    metadata = json.loads((sac_dir / "metadata.json").read_text())
    args = DeployArgs(backend="emulated", log=tmp_path / "run.jsonl", state_file=tmp_path / "g.json")
    batched = Deployment(args, lambda obs: np.zeros((1, 4)), metadata, console=Console(file=None, quiet=True))
    with pytest.raises(DeployError) as caught:
        batched.run()
    assert caught.value.code == 2
    assert str(caught.value) == (
        "refused: given policy gives an action of shape (1, 4) on a probe observation; "
        "the env takes shape (4,); nothing was sent to the arm"
    )
    assert bus_traffic == [] and not (tmp_path / "run.jsonl").exists()


# ------------------------------------------------------------------ 2: obs_keys
def test_obs_keys_in_another_order_than_the_export_concatenates_are_refused(
    onnx_path: Path, tmp_path: Path, bus_traffic: list[tuple[int, bytes]], capsys: pytest.CaptureFixture[str]
) -> None:
    # Seen: accepted, the graph fed desired_goal where it takes achieved_goal: misses of
    # 170-422 mm, exit 0.
    swapped = json.dumps([["desired_goal", 3], ["achieved_goal", 3], ["observation", 12]])
    crafted = with_props(onnx_path, tmp_path / "swap.onnx", obs_keys=swapped)
    code = main(deploy(tmp_path, "--onnx", str(crafted)))
    assert code == 2
    assert refused(capsys.readouterr().err) == (
        f"refused: ONNX {crafted} concatenates its input as desired_goal, achieved_goal, observation "
        "(its obs_keys), but `bioscara export` concatenates the env's observation as achieved_goal, "
        "desired_goal, observation; nothing was sent to the arm"
    )
    assert bus_traffic == []


@pytest.mark.parametrize(
    ("size", "shown"), [("3.7", "3.7"), ("1e400", "inf"), ("true", "True")], ids=["float", "huge", "bool"]
)
def test_obs_keys_sizes_that_are_not_whole_numbers_are_not_what_export_writes(
    size: str,
    shown: str,
    onnx_path: Path,
    tmp_path: Path,
    bus_traffic: list[tuple[int, bytes]],
    capsys: pytest.CaptureFixture[str],
) -> None:
    # Seen: 3.7 silently read as 3; 1e400 an OverflowError traceback from int(n).
    keys = f'[["achieved_goal",{size}],["desired_goal",3],["observation",12]]'
    crafted = with_props(onnx_path, tmp_path / "keys.onnx", obs_keys=keys)
    code = main(deploy(tmp_path, "--onnx", str(crafted)))
    assert code == 2
    assert refused(capsys.readouterr().err) == (
        f"{crafted}: its bioscara_metadata/obs_keys metadata is not what `bioscara export` writes "
        f"(ValueError: entry ['achieved_goal', {shown}] is not [key, size] with size a whole number >= 1)"
    )
    assert bus_traffic == []


# --------------------------------------------------------------- 3: fault times
@pytest.mark.parametrize(
    ("faults", "expected"),
    [
        ("latency_ms=1e308", "fault 'latency_ms': 1e308 must be within 0-1000 ms"),
        ("latency_ms=100000", "fault 'latency_ms': 100000 must be within 0-1000 ms"),
        ("jitter_ms=1000.5", "fault 'jitter_ms': 1000.5 must be within 0-1000 ms"),
        ("jitter_s=2", "fault 'jitter_s': 2 must be within 0-1 s"),
    ],
    ids=["latency-1e308", "latency-100s", "jitter-over", "jitter-seconds"],
)
def test_fault_times_beyond_the_bus_timeout_are_refused(
    faults: str,
    expected: str,
    tmp_path: Path,
    bus_traffic: list[tuple[int, bytes]],
    capsys: pytest.CaptureFixture[str],
) -> None:
    # Seen: latency_ms=1e308 hung deploy at 100 % CPU, deaf to SIGTERM; 100000 took 85 s to
    # act on SIGTERM (each disable of the safe stop simulated 100 s). The log is a folder,
    # refused after the arguments: without the bound this fails at once instead of hanging.
    code = main([*deploy(tmp_path, "--expert", "--env", REACH, "--faults", faults), "--log", str(tmp_path)])
    assert code == 2
    assert refused(capsys.readouterr().err) == (
        f"--faults: {expected} "
        "(the bus's timeout: a longer transaction is a lost one, the nack or drop fault)"
    )
    assert bus_traffic == []


def test_the_fault_plan_bounds_latency_and_jitter_to_the_bus_timeout() -> None:
    plan = FaultPlan.parse("latency_ms=1000,jitter_ms=1000")
    assert (plan.latency_s, plan.jitter_s) == (1.0, 1.0)
    with pytest.raises(ValueError) as caught:
        FaultPlan(latency_s=1e305)
    assert str(caught.value) == (
        "latency_s=1e+305 must be within 0-1 s "
        "(the bus's timeout: a longer transaction is a lost one, the nack or drop fault)"
    )


# ------------------------------------------------ 4, 6: the gripper state file
NOTES = "my notes\n" * 400


def test_a_state_file_that_is_not_one_is_refused_before_the_arm_is_touched(
    tmp_path: Path, bus_traffic: list[tuple[int, bytes]], capsys: pytest.CaptureFixture[str]
) -> None:
    # Seen: notes.txt (3,893 bytes) became {"width_m": 0.08}, with only a warning.
    notes = tmp_path / "notes.txt"
    notes.write_text(NOTES)
    code = main(deploy(tmp_path, "--expert", "--env", REACH, "--state-file", str(notes)))
    assert code == 2
    assert refused(capsys.readouterr().err) == (
        f'--state-file {notes}: exists and is not a gripper state file ({{"width_m": ...}}); '
        'give a new file, or a gripper state file ({"width_m": ...}) to replace'
    )
    assert notes.read_text() == NOTES and bus_traffic == []


def test_the_default_state_file_beside_the_log_is_checked_too(
    tmp_path: Path, bus_traffic: list[tuple[int, bytes]], capsys: pytest.CaptureFixture[str]
) -> None:
    folder = tmp_path / "runs"
    folder.mkdir()
    (folder / "gripper.json").write_text('{"colour": "red"}\n')
    log = folder / "run.jsonl"
    code = main(["deploy", "--expert", "--env", REACH, "--backend", "mock", "--log", str(log)])
    assert code == 2
    assert refused(capsys.readouterr().err) == (
        f"the gripper state file (--state-file's default) {folder / 'gripper.json'}: exists and is not "
        'a gripper state file ({"width_m": ...}); give a new file, or a gripper state file '
        '({"width_m": ...}) to replace'
    )
    assert (folder / "gripper.json").read_text() == '{"colour": "red"}\n' and not log.exists()


def test_an_unwritable_state_file_is_refused_before_the_arm_is_touched(
    tmp_path: Path,
    bus_traffic: list[tuple[int, bytes]],
    capsys: pytest.CaptureFixture[str],
    monkeypatch: pytest.MonkeyPatch,
) -> None:
    # Seen: found only at the end, "gripper width 0.080 m NOT saved ...", exit 0.
    import tempfile

    locked = tmp_path / "locked"
    locked.mkdir()
    locked.chmod(0o555)  # read-only; root writes anyway, so the folder's refusal is played too
    mkstemp = tempfile.mkstemp

    def refuse(*args: Any, dir: Any = None, **kwargs: Any) -> tuple[int, str]:  # noqa: A002
        if dir is not None and Path(dir) == locked:
            raise PermissionError(13, "Permission denied", str(dir))
        return mkstemp(*args, dir=dir, **kwargs)

    monkeypatch.setattr(tempfile, "mkstemp", refuse)
    try:
        code = main(deploy(tmp_path, "--expert", "--env", REACH, "--state-file", str(locked / "g.json")))
    finally:
        locked.chmod(0o755)
    assert code == 2
    assert refused(capsys.readouterr().err) == (
        f"--state-file {locked / 'g.json'}: cannot write in {locked}: Permission denied"
    )
    assert bus_traffic == [] and not (tmp_path / "deploy.jsonl").exists()


def test_an_earlier_log_an_empty_state_file_and_a_state_file_are_replaced(tmp_path: Path) -> None:
    log, state = tmp_path / "run.jsonl", tmp_path / "gripper.json"
    state.write_text("")
    argv = ["deploy", "--expert", "--env", REACH, "--backend", "mock", "--log", str(log)]
    assert main([*argv, "--state-file", str(state)]) == 0
    assert json.loads(state.read_text()) == {"width_m": 0.08}
    assert main([*argv, "--state-file", str(state)]) == 0  # the log and the state file of a run before
    assert json.loads(log.read_text().splitlines()[0])["type"] == "header"


# ----------------------------------------------------- 5: --log and --onnx
def test_a_log_naming_another_runs_model_is_refused_and_nothing_is_written(
    sac_dir: Path, tmp_path: Path, bus_traffic: list[tuple[int, bytes]], capsys: pytest.CaptureFixture[str]
) -> None:
    # Seen: the zip replaced by JSON lines, and a gripper.json dropped in the model's folder.
    other = tmp_path / "other"
    shutil.copytree(sac_dir, other)
    model = other / "model.zip"
    before = model.read_bytes()
    code = main(["deploy", "--expert", "--env", REACH, "--log", str(model)])
    assert code == 2
    assert refused(capsys.readouterr().err) == (
        f"--log {model}: exists and is not a deploy run log; give a new file, or a deploy run log to replace"
    )
    assert model.read_bytes() == before and not (other / "gripper.json").exists() and bus_traffic == []


def test_export_replaces_only_an_onnx_file(
    sac_dir: Path, onnx_path: Path, tmp_path: Path, capsys: pytest.CaptureFixture[str]
) -> None:
    # Seen: export --onnx notes.txt replaced the text file.
    notes = tmp_path / "notes.txt"
    notes.write_text(NOTES)
    code = main(["export", "--model", str(sac_dir / "model.zip"), "--onnx", str(notes), "--check", "0"])
    assert code == 2
    assert refused(capsys.readouterr().err, "export") == (
        f"--onnx {notes}: exists and is not an ONNX model; give a new file, or an ONNX model to replace"
    )
    assert notes.read_text() == NOTES
    again = tmp_path / "again.onnx"
    shutil.copy(onnx_path, again)
    assert main(["export", "--model", str(sac_dir / "model.zip"), "--onnx", str(again), "--check", "0"]) == 0


def test_the_help_says_where_the_default_state_file_goes_and_what_each_output_replaces(
    capsys: pytest.CaptureFixture[str],
) -> None:
    with pytest.raises(SystemExit):
        main(["deploy", "--help"])
    text = " ".join(capsys.readouterr().out.split())
    assert "--state-file (the gripper's saved width) only a gripper state file or an empty file" in text
    assert "defaults on mock, emulated and sitl to gripper.json in the run log's folder" in text
    assert "--log replaces only an earlier run log or an empty file" in text


# ------------------------------------------------------------------- 7: smaller
def test_a_policy_refused_after_the_options_are_parsed_writes_no_trace(
    onnx_path: Path, tmp_path: Path, bus_traffic: list[tuple[int, bytes]], capsys: pytest.CaptureFixture[str]
) -> None:
    # Seen: a header-only trace; an existing trace would have taken an empty session.
    trace = tmp_path / "trace.jsonl"
    code = main(
        deploy(tmp_path, "--onnx", str(onnx_path), "--env", "Bioscara-Push-v0", "--record", str(trace))
    )
    assert code == 2
    assert refused(capsys.readouterr().err) == (
        "refused: policy was trained on Bioscara-Reach-v0, not Bioscara-Push-v0; nothing was sent to the arm"
    )
    assert not trace.exists() and bus_traffic == []


def test_an_env_that_is_not_a_bioscara_env_is_named_in_one_short_line(
    tmp_path: Path, capsys: pytest.CaptureFixture[str]
) -> None:
    # Seen: a 5.4 kB line dumping the whole ArmConfig.
    log = tmp_path / "run.jsonl"
    code = main(["deploy", "--expert", "--env", "CartPole-v1", "--backend", "mock", "--log", str(log)])
    assert code == 2
    assert refused(capsys.readouterr().err) == (
        "env 'CartPole-v1' is not a Bioscara env: deploy drives the arm through one of Bioscara-Reach-v0, "
        "Bioscara-PickPlace-v1, Bioscara-Push-v0, Bioscara-Stack-v0, Bioscara-Insert-v0"
    )


def test_record_makes_its_missing_folder_as_the_log_does(tmp_path: Path) -> None:
    # Seen: --record new/tr.jsonl failed "No such file or directory" where --log made its folder.
    from bioscara_gym.training.deploy import DeployArgs
    from bioscara_gym.training.deploy_checks import check_files, make_env

    trace = tmp_path / "new" / "deeper" / "trace.jsonl"
    args = DeployArgs(expert=True, env=REACH, backend="emulated", record=trace)
    check_files(args, tmp_path / "logs" / "run.jsonl", None)
    env = make_env(args, None, None)
    env.close()
    assert json.loads(trace.read_text().splitlines()[0])["format"] == "bioscara-bus-trace"


@pytest.mark.parametrize(
    ("rate", "why"),
    [
        ("100.0000001", "the joint firmware's loop runs every 10 ms"),
        ("19.9999999", "the joints' 50 ms deadman would stop them between commands"),
    ],
)
def test_a_rate_just_outside_its_range_is_printed_as_given(
    rate: str, why: str, tmp_path: Path, capsys: pytest.CaptureFixture[str]
) -> None:
    # Seen: "--rate 100 Hz must be within 20-100 Hz".
    code = main(deploy(tmp_path, "--expert", "--env", REACH, "--rate", rate))
    assert code == 2
    assert refused(capsys.readouterr().err) == f"--rate {rate} Hz must be within 20-100 Hz: {why}"
