"""Re-record the shipped bus traces on the emulated bus: ``python tests/traces/record.py``.

Run it on purpose, after a change that alters bytes on the wire (or their
timing), and commit the new traces with the change: ``tests/test_replay.py``
replays every ``*.jsonl`` here and fails until then. See README.md here.
Every run and its files other than the trace go to a temporary directory.
"""

from __future__ import annotations

import contextlib
import shutil
import sys
import tempfile
from collections.abc import Callable
from pathlib import Path

from bioscara_gym.cli import main

HERE = Path(__file__).resolve().parent

#: ``bioscara deploy`` of the Reach expert, 2 episodes of 50 cycles, homing first.
DEPLOY_REACH = [
    "deploy",
    "--expert",
    "--env",
    "Bioscara-Reach-v0",
    "--backend",
    "emulated",
    "--episodes",
    "2",
]
#: Trace file name to the ``bioscara`` commands that record it (``{trace}``, ``{tmp}`` filled in).
TRACES: dict[str, list[list[str]]] = {
    # Homing, then 2 Reach episodes of 50 cycles with the scripted expert.
    "deploy_reach_expert.jsonl": [DEPLOY_REACH],
    # The same with NACKs, short and corrupted replies (the emulated bus's FaultPlan, seed 0).
    "deploy_reach_faults.jsonl": [
        [*DEPLOY_REACH, "--faults", "nack=0.02,short_read=0.01,corrupt=0.01"],
    ],
    # A console session, one command after another on one --state file, appended to one trace.
    "console_session.jsonl": [
        ["enable"],
        ["home"],
        ["move", "j1", "2.5"],
        ["move", "j2", "0.2"],
        ["gripper", "0.06"],
        ["status"],
        ["disable"],
    ],
    # One episode of the expert under `bioscara eval` on the emulated backend.
    "eval_reach_expert.jsonl": [
        ["eval", "--expert", "--env", "Bioscara-Reach-v0", "--backend", "emulated", "--episodes", "1"],
    ],
}


def _with_files(command: list[str], trace: str) -> list[str]:
    """The command with ``--record`` and its side files (log, state), all relative to the working folder."""
    extra = ["--record", trace]
    if command[0] == "deploy":
        extra += ["--log", "deploy.jsonl"]
    elif command[0] != "eval":
        extra += ["--state", "state.json"]
    return [*command, *extra]


def record(name: str, run: Callable[[list[str]], int] = main) -> Path:
    """Record trace ``name`` afresh (the old file is replaced).

    The commands run in a temporary folder with relative file names, so the
    trace's headers name no path of the machine that recorded it.
    """
    trace = HERE / name
    with tempfile.TemporaryDirectory(prefix="bioscara-record-") as tmp, contextlib.chdir(tmp):
        for command in TRACES[name]:
            code = run(_with_files(command, name))
            if code not in (0, 3):  # 3: a safety stop, which a fault trace may well record
                raise SystemExit(f"{' '.join(command)} exited with {code}")
        shutil.move(Path(tmp) / name, trace)
    return trace


if __name__ == "__main__":
    for name in sys.argv[1:] or TRACES:
        path = record(name)
        print(f"{path.relative_to(HERE.parent.parent)}: {sum(1 for _ in path.open())} lines")
