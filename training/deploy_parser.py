"""The options of ``bioscara deploy`` (:func:`add_options`) and what its help says of its files.

:mod:`~bioscara_gym.training.deploy` registers the subcommand; the options
live here so that module stays one deployment's story.
"""

from __future__ import annotations

import argparse
from pathlib import Path

from bioscara_gym.fsutil import path_argument
from bioscara_gym.hardware.emulated_bus import MAX_DRIFT_PPM, MAX_EXTRA_S
from bioscara_gym.hardware.sitl.build import add_firmware_option
from bioscara_gym.training.deploy_checks import DEPLOY_BACKENDS

#: The help's last paragraph: the files deploy writes (deploy_outputs.py) and the faults' bounds.
EPILOG = (
    "Files: --log replaces only an earlier run log or an empty file; --state-file (the gripper's "
    "saved width) only a gripper state file or an empty file, and defaults on mock, emulated and sitl "
    "to gripper.json in the run log's folder (on i2c: the configuration's gripper.state_file, else "
    "$XDG_STATE_HOME/bioscara/gripper.json); --record adds a session to a trace or an empty file. "
    "Missing folders are made; each file is checked before the arm is touched. --faults: latency_ms "
    f"and jitter_ms within 0-{MAX_EXTRA_S * 1000:g} ms each (the bus's timeout), drift_ppm within "
    f"±{MAX_DRIFT_PPM:g}."
)


def add_options(p: argparse.ArgumentParser) -> None:
    """Add deploy's options to its parser."""
    src = p.add_mutually_exclusive_group(required=True)
    src.add_argument("--model", type=Path, help="model.zip (metadata.json beside it)")
    src.add_argument("--onnx", type=Path, help="ONNX policy from `bioscara export` (no torch needed)")
    src.add_argument("--expert", action="store_true", help="run the scripted expert of --env")
    p.add_argument("--env", help="env id (for --expert; with a policy it must match the metadata)")
    p.add_argument("--backend", choices=DEPLOY_BACKENDS, default="emulated", help="default: emulated")
    add_firmware_option(p)
    p.add_argument("--bus", type=int, help="I2C bus number, /dev/i2c-N (default: the config's)")
    p.add_argument("--config", type=path_argument, help="arm configuration YAML (default: the packaged one)")
    p.add_argument("--episodes", type=int, default=1)
    p.add_argument(
        "--rate",
        type=float,
        help="control rate in Hz (default: the policy's; a trained policy refuses another)",
    )
    p.add_argument("--log", type=Path, help="run log, JSON Lines (default: runs/deploy/deploy-<time>.jsonl)")
    p.add_argument(
        "--faults",
        help="emulated bus faults: nack, short_read, corrupt (rates per transaction), latency_ms, "
        "jitter_ms (extra time per transaction), drift_ppm (host clock), seed (of the faults' draws, "
        "default 0; --seed is the episodes'), e.g. latency_ms=2,jitter_ms=3,seed=7",
    )
    p.add_argument("--seed", type=int, default=10_000, help="seed of the first episode")
    p.add_argument("--realtime", action="store_true", help="pace mock/emulated on the wall clock too")
    p.add_argument("--state-file", type=Path, help="gripper state file")
    p.add_argument("--record", type=Path, metavar="FILE", help="bus trace to write (docs/traces.md)")
