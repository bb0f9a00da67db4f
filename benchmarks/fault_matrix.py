"""The fault matrix of issue #24, re-run: each fault injected once on the emulated backend.

Faults an operator can cause go in through the public CLI (``bioscara
deploy``, ``bioscara replay``, as subprocesses); faults that start mid-run go
in through :class:`Deployment`'s ``on_cycle`` hook, as tests/test_deploy.py
injects them (the device stand-ins are the tests', from tests/rigs.py). Each
row is read off the run's own log: what the run detected, how it ended, and
the arm as the emulator holds it. A joint counts as safe only when its own
disable was acknowledged; the emulator's currents are the check.

    python benchmarks/fault_matrix.py          # prints the README's table (Markdown)
"""

from __future__ import annotations

import errno
import io
import json
import os
import signal
import subprocess
import sys
import tempfile
import time
from collections import Counter
from collections.abc import Callable
from pathlib import Path
from typing import Any
from unittest import mock

sys.path.insert(0, str(Path(__file__).resolve().parent.parent / "tests"))

import itertools

import numpy as np
from rich.console import Console
from rigs import (
    J1,
    ConstantPolicy,
    FlipsNextReply,
    build_emulated,
    home_and_enable,
    lose_joint_at,
    nan_actor_weights,
    run_log_disk_filling,
    train_tiny_sac,
)

from bioscara_gym.errors import DeployError
from bioscara_gym.hardware.emulated_bus import FaultPlan
from bioscara_gym.hardware.errors import NotEnabledError
from bioscara_gym.training.deploy import DeployArgs, Deployment

REACH = "Bioscara-Reach-v0"
#: A Reach deploy that moves j2 down and j3 (the lost-joint rows): the deadman trips with current on.
MOVING = [0.0, -0.5, 0.5, 0.0]

Row = tuple[str, str, str, str]


# --------------------------------------------------------------- reading a log
def summary_of(log: Path) -> dict[str, Any]:
    """The run log's last record (the summary; a cycle if the log was cut short)."""
    return json.loads(log.read_text(encoding="utf-8").splitlines()[-1])


def detected(summary: dict[str, Any]) -> str:
    """The bus errors the drivers counted, their retries, and the stop's reason."""
    errors: Counter[str] = Counter()
    retries = 0
    for totals in summary["bus"].values():
        retries += totals["retries"]
        errors.update(totals["errors"])
    parts = [f"{n} {kind}" for kind, n in errors.items() if n]
    text = f"{', '.join(parts)}; {retries} retries" if parts else "no bus error"
    if summary.get("overruns"):
        text += f"; {summary['overruns']} of {summary['cycles']} cycles overran"
    if summary.get("max_silence_s") is not None:
        text += f"; longest joint silence {summary['max_silence_s'] * 1e3:.1f} ms"
    if summary["stop_reason"] != "completed":
        joint = f" ({summary['joint']})" if summary.get("joint") else ""
        text += f"; `{summary['stop_reason']}`{joint}"
    return text


def recovered(summary: dict[str, Any], code: int) -> str:
    """How the run ended."""
    if summary["stop_reason"] == "completed":
        return f"completed, {summary['successes']}/{summary['episodes']} episodes, exit {code}"
    return f"safe stop after {summary['cycles']} cycles, exit {code}"


def arm_after(summary: dict[str, Any]) -> str:
    """Which joints were confirmed disabled, and what the emulator says of their currents."""
    final = summary["final_state"]
    powered = {
        n: s["drive_current"] for n, s in final.items() if s.get("drive_current") or s.get("hold_current")
    }
    unconfirmed = summary["not_confirmed_disabled"]
    text = (
        f"not confirmed disabled: {', '.join(unconfirmed)}"
        if unconfirmed
        else "every joint confirmed disabled"
    )
    currents = ", ".join(f"{n} {c} %" for n, c in powered.items()) if powered else "0 on every joint"
    return f"{text}; emulator currents {currents}"


def from_log(injected: str, log: Path, code: int) -> Row:
    summary = summary_of(log)
    return injected, detected(summary), recovered(summary, code), arm_after(summary)


# ------------------------------------------------------------- the two routes
def cli(*args: str) -> tuple[int, str]:
    """``bioscara <args>`` as a subprocess: exit code and the last line it printed to stderr."""
    proc = subprocess.run([sys.executable, "-m", "bioscara_gym", *args], capture_output=True, text=True)
    lines = proc.stderr.strip().splitlines()
    return proc.returncode, lines[-1] if lines else ""


def deploy_cli(tmp: Path, name: str, *args: str, episodes: int = 2) -> tuple[int, str, Path]:
    """``bioscara deploy`` on ``emulated`` (Reach's expert unless ``args`` names a policy)."""
    log = tmp / f"{name}.jsonl"
    policy = [] if "--model" in args else ["--expert", "--env", REACH]
    code, err = cli(
        "deploy", *policy, "--episodes", str(episodes), "--log", str(log),
        "--state-file", str(tmp / f"{name}-gripper.json"), *args,
    )  # fmt: skip
    return code, err, log


def deploy_api(
    tmp: Path,
    name: str,
    on_cycle: Callable[[int, Any], None],
    policy: Any = None,
    output: io.StringIO | None = None,
    record: Path | None = None,
    backend_options: dict[str, Any] | None = None,
) -> tuple[int, Deployment]:
    """A Reach deploy in-process with a hook that injects a fault mid-run."""
    args = DeployArgs(
        expert=policy is None,
        env=REACH,
        episodes=1 if backend_options else 2,
        log=tmp / f"{name}.jsonl",
        state_file=tmp / f"{name}-gripper.json",
        record=record,
    )
    console = Console(file=output or io.StringIO(), width=200)
    deployment = Deployment(
        args, policy=policy, console=console, on_cycle=on_cycle, backend_options=backend_options or {}
    )
    try:
        deployment.run()
        return 0, deployment
    except DeployError as e:
        return e.code, deployment


# ---------------------------------------------------------------------- rows
def bus_faults(tmp: Path) -> list[Row]:
    rows = []
    for spec, episodes in (
        ("nack=0.05", 2),
        ("short_read=0.05", 2),
        ("corrupt=0.05", 20),
        ("latency_ms=2,jitter_ms=3", 2),
        ("latency_ms=30", 2),
        ("nack=1.0", 2),
    ):
        code, _, log = deploy_cli(
            tmp, spec.replace("=", "-").replace(",", "_"), "--faults", spec, episodes=episodes
        )
        shown = f"`--faults {spec}`" + (f", {episodes} episodes" if episodes != 2 else "")
        rows.append(from_log(shown, log, code))
    return rows


def lost_joints(tmp: Path) -> list[Row]:
    rows = []
    for what, name, address in (("NACKs", "j2", 0x12), ("answers 0xFF", "j3", 0x13)):
        lose = lose_joint_at(5, name, address, nacks=what == "NACKs")
        code, run = deploy_api(tmp, f"lost-{name}", lose, policy=ConstantPolicy(MOVING))
        rows.append(from_log(f"{name} {what} from cycle 5, its deadman tripped", run.args.log, code))
    return rows


def flipped_bit(tmp: Path) -> Row:
    def flip(cycle: int, env: Any) -> None:
        if cycle == 20:
            devices = env.unwrapped.backend.bus.devices
            devices[0x12] = FlipsNextReply(devices[0x12], bit=30)

    code, run = deploy_api(tmp, "flip", flip, policy=ConstantPolicy([0.0, -0.5, 0.0, 0.0]))
    injected, found, ended, arm = from_log(
        "bit 30 flipped in j2's position reply at cycle 20", run.args.log, code
    )
    records = [json.loads(line) for line in run.args.log.read_text().splitlines()]
    cycles = [r for r in records if r["type"] == "cycle"]
    pairs = [(a, b) for a, b in itertools.pairwise(cycles) if a["episode"] == b["episode"]]
    steps = [abs(b["q"]["j2"] - a["q"]["j2"]) for a, b in pairs]  # a reset moves the arm between episodes
    largest = max(steps)
    return injected, found, f"{ended}; j2's largest step between cycles {largest * 1e3:.2f} mm", arm


def nan_action(tmp: Path) -> Row:
    code, run = deploy_api(tmp, "nan", lambda cycle, env: None, policy=ConstantPolicy([0.0] * 4, bad_from=3))
    return from_log("the policy returns NaN at cycle 3", run.args.log, code)


def full_disk(tmp: Path) -> Row:
    output = io.StringIO()
    with run_log_disk_filling(5, full_for=None) as fill:
        code, run = deploy_api(tmp, "disk", fill, output=output)
    lines = run.args.log.read_text().splitlines()
    parsed = sum(1 for line in lines if json.loads(line))
    said = next(x.strip() for x in output.getvalue().splitlines() if "log incomplete" in x)
    return (
        "the disk fills at cycle 5 and stays full (half of each write lands)",
        f"`{run.summary['stop_reason']}`",
        f'safe stop, exit {code}; {parsed} of {len(lines)} lines parse; "{said}"',
        arm_after(run.summary),
    )


def moving_stop(tmp: Path) -> Row:
    """NaN while j3 and j4 turn fast: do the joints brake before their current is cut?"""
    code, run = deploy_api(
        tmp, "coast", lambda cycle, env: None, policy=ConstantPolicy([0.0, -0.5, 1.0, 1.0], 10)
    )
    backend = run.env.unwrapped.backend
    before = backend.sim.joint_positions().copy()
    for _ in range(15):
        backend.step(0.2)
    travel = np.abs(backend.sim.joint_positions() - before).max()
    injected, found, ended, arm = from_log(
        "the policy returns NaN at cycle 10, j3 and j4 turning at full speed", run.args.log, code
    )
    return injected, found, ended, f"{arm}; largest joint travel in the 3 s after: {travel:.4f} rad"


def trace_disk_full(tmp: Path) -> Row:
    """``--record`` onto a disk that fills at its 500th write."""
    writes = [0]

    def filling(fd: int, data: Any) -> int:
        writes[0] += 1
        if writes[0] < 500:
            return os.write(fd, data)
        if writes[0] == 500:
            os.write(fd, bytes(data)[: len(data) // 2])
        raise OSError(errno.ENOSPC, os.strerror(errno.ENOSPC))

    trace = tmp / "full-trace.jsonl"
    with mock.patch("bioscara_gym.hardware.recording._os_write", filling):
        code, run = deploy_api(tmp, "tracefull", lambda cycle, env: None, record=trace)
    lines = trace.read_text().splitlines()
    whole = sum(1 for line in lines if json.loads(line))
    injected, _, ended, arm = from_log(
        "`--record` onto a disk that fills (half of a line lands)", run.args.log, code
    )
    return (
        injected,
        f"`trace_error`: {run.summary['trace_error']}",
        f"{ended}; {whole} of {len(lines)} lines whole",
        arm,
    )


def corrupt_seeds(tmp: Path, seeds: int = 40) -> Row:
    """``corrupt=0.05`` on many fault seeds, one Reach episode each: bring-ups stopped on a flipped bit."""
    stops = []
    for seed in range(seeds):
        code, run = deploy_api(
            tmp,
            f"seed{seed}",
            lambda cycle, env: None,
            backend_options={"faults": FaultPlan(corrupt=0.05, seed=seed)},
        )
        if code:
            stops.append(f"seed {seed}: {run.summary['message'][:60]}")
    return (
        f"`corrupt=0.05` on fault seeds 0-{seeds - 1}, one episode each",
        f"{len(stops)} of {seeds} runs stopped" + (f" ({'; '.join(stops)})" if stops else ""),
        f"{seeds - len(stops)} of {seeds} completed",
        "every stop a safe stop",
    )


def host_pause(tmp: Path) -> Row:
    """The bare driver: j1 turning in velocity mode, the host silent 80 ms, then ``set_velocity``."""
    emu = home_and_enable(build_emulated(J1, 3.0))
    j = emu.joint
    j.set_velocity(-0.5)
    emu.advance(0.3)
    emu.advance(0.08)
    try:
        j.set_velocity(-0.5)
        raised = "no error"
    except NotEnabledError as e:
        raised = f"`NotEnabledError` ({'STOP sent' if 'sent STOP' in str(e) else 'no STOP'})"
    at = emu.motor.position_deg
    emu.advance(3.0)
    moved = abs(emu.motor.position_deg - at) / abs(J1.reduction) * 3.141592653589793 / 180
    return (
        "host pauses 80 ms in velocity mode, then one `set_velocity` (bare driver)",
        "the reply's NOT_ENABLED",
        raised,
        f"j1 moves {moved:.3f} rad in the next 3 s",
    )


def refusals(tmp: Path) -> list[Row]:
    run = tmp / "model"
    train_tiny_sac(run)
    rows = []
    meta = json.loads((run / "metadata.json").read_text())
    meta["env_kwargs"]["control_mode"] = "velocity"
    (run / "metadata.json").write_text(json.dumps(meta))
    code, err, _ = deploy_cli(tmp, "meta", "--model", str(run / "model.zip"))
    rows.append(("`control_mode` edited in `metadata.json`", err, f"refused, exit {code}", "untouched"))
    bad = tmp / "nan"
    train_tiny_sac(bad)
    nan_actor_weights(bad)
    code, err, _ = deploy_cli(tmp, "nanw", "--model", str(bad / "model.zip"))
    rows.append(("actor weights NaN in `model.zip`", err, f"refused, exit {code}", "untouched"))
    for field, joint, path, value in (
        ("j4 `max_velocity: 1.0e+6`", "j4", ("max_velocity",), 1.0e6),
        ("j1 `homing.threshold: 0`", "j1", ("homing", "threshold"), 0),
    ):
        config = edited_config(tmp, joint, path, value)
        code, err, _ = deploy_cli(tmp, "config", "--config", str(config))
        rows.append((f"config: {field}", err, f"refused, exit {code}", "untouched"))
    return rows


def edited_config(tmp: Path, joint: str, path: tuple[str, ...], value: float) -> Path:
    """The packaged configuration with one field of one joint set to ``value``."""
    import yaml

    import bioscara_gym.hardware

    doc = yaml.safe_load((Path(bioscara_gym.hardware.__file__).parent / "default_config.yaml").read_text())
    entry = next(j for j in doc["joints"] if j["name"] == joint)
    for key in path[:-1]:
        entry = entry[key]
    entry[path[-1]] = value
    out = tmp / f"config-{joint}.yaml"
    out.write_text(yaml.safe_dump(doc))
    return out


def tampered_trace(tmp: Path) -> Row:
    trace = tmp / "recorded-trace.jsonl"
    deploy_cli(tmp, "trace", "--record", str(trace), episodes=1)
    lines = trace.read_text().splitlines()
    for i, line in enumerate(lines):
        doc = json.loads(line)
        if doc.get("type") == "tx" and doc.get("write") == "18" and i > 100:
            reply = bytearray.fromhex(doc["read"])
            reply[2] ^= 0x01
            doc["read"] = reply.hex()
            lines[i] = json.dumps(doc)
            break
    tampered = tmp / "tampered.jsonl"
    tampered.write_text("\n".join(lines) + "\n")
    code, err = cli("replay", str(tampered))
    unchecked = subprocess.run(
        [sys.executable, "-m", "bioscara_gym", "replay", str(tampered), "--unchecked"],
        capture_output=True,
        text=True,
    )
    matched = next((x.strip() for x in unchecked.stdout.splitlines() if "matched" in x), "no match line")
    return (
        "one reply byte changed in a recorded trace",
        f"`bioscara replay`: {err}",
        f"exit {code}; `--unchecked`: {matched}",
        "-",
    )


def ctrl_c_replayed(tmp: Path) -> Row:
    """Ctrl-C to a recorded deploy after 20 cycles, then ``bioscara replay`` of its trace."""
    log, trace = tmp / "ctrl-c.jsonl", tmp / "ctrl-c-trace.jsonl"
    cmd = [sys.executable, "-m", "bioscara_gym", "deploy", "--expert", "--env", REACH,
           "--episodes", "1000", "--log", str(log), "--state-file", str(tmp / "ctrl-c-gripper.json"),
           "--record", str(trace)]  # fmt: skip
    proc = subprocess.Popen(cmd, stdout=subprocess.DEVNULL, stderr=subprocess.DEVNULL)
    while not (log.exists() and log.read_text(encoding="utf-8").count('"type":"cycle"') >= 20):
        if proc.poll() is not None:
            raise RuntimeError(f"the deploy ended before its 20th cycle (exit {proc.returncode})")
        time.sleep(0.02)
    proc.send_signal(signal.SIGINT)
    code = proc.wait(timeout=60)
    notes = [json.loads(x) for x in trace.read_text().splitlines() if '"type": "signal"' in x]
    replayed = subprocess.run(
        [sys.executable, "-m", "bioscara_gym", "replay", str(trace)], capture_output=True, text=True
    )
    said = (replayed.stdout + replayed.stderr).strip().splitlines()
    _, detected_as, ended, arm = from_log("", log, code)
    at = ", ".join(f"`{n['signal']}` at transaction {n['i']} ({n['at']})" for n in notes) or "no signal line"
    return (
        "Ctrl-C (SIGINT) to a deploy under `--record` after 20 cycles, then `bioscara replay`",
        f"{detected_as}; trace: {at}",
        f"{ended}; replay exit {replayed.returncode}: {said[-1] if said else ''}",
        arm,
    )


def main() -> None:
    t0 = time.perf_counter()
    with tempfile.TemporaryDirectory() as d:
        tmp = Path(d)
        rows = [
            *bus_faults(tmp),
            *lost_joints(tmp),
            flipped_bit(tmp),
            host_pause(tmp),
            nan_action(tmp),
            moving_stop(tmp),
            full_disk(tmp),
            trace_disk_full(tmp),
            *refusals(tmp),
            tampered_trace(tmp),
            ctrl_c_replayed(tmp),
            corrupt_seeds(tmp),
        ]
        print("| fault injected | detected as | recovered | arm after |")
        print("|---|---|---|---|")
        for row in rows:
            cells = (cell.replace(f"{tmp}/", "").replace("|", "\\|") for cell in row)
            print("| " + " | ".join(cells) + " |")
    print(f"\n{len(rows)} faults, {time.perf_counter() - t0:.0f} s")


if __name__ == "__main__":
    main()
