"""At which speeds the firmware's stall detection, and the arm's field watch, see j1 run into an obstacle.

j1 homed, stall detection at its sensitivity, running at a set speed into the
scene's obstacle (5 mm gap) of the MuJoCo arm; 1.5 s of polling at 100 Hz.
Prints, per speed: the speed at the motor, the PID error a blocked rotor
shows each pass (step rate x 1 ms), whether and when STALL came, and the
largest rise of the error the firmware saw in one pass (its spike filter
drops rises above 100). Then the same through the arm layer (velocity
interface, 100 Hz cycles): which stopped the joint first, the firmware's
flag or the arm's field watch (``hardware/field_watch.py``), and when.

    python benchmarks/collision_speeds.py [--config FILE]
"""

from __future__ import annotations

import argparse
import math
import sys
from pathlib import Path

sys.path.insert(0, str(Path(__file__).resolve().parent.parent / "tests"))

import itertools

from rigs import place_obstacle

from bioscara_gym.hardware import load_config
from bioscara_gym.hardware.arm import Arm
from bioscara_gym.hardware.backends import make_backend
from bioscara_gym.hardware.drive import USTEPS_PER_DEG
from bioscara_gym.hardware.errors import StalledError
from bioscara_gym.hardware.field_watch import FieldLostError
from bioscara_gym.hardware.registers import Flag

SPEEDS = (0.2, 0.3, 0.35, 0.4, 0.5, 0.6, 0.8, 1.0)


def run(speed: float, config_path: Path | None) -> tuple[float | None, float]:
    """Seconds to STALL after contact (None: never within 1.5 s) and the largest rise per pass."""
    backend = make_backend("sim", load_config(config_path))
    joint, j = backend.joints["j1"], backend.config.joint("j1")
    sim = backend.sim
    joint.init()
    joint.enable(j.drive_current, j.hold_current)
    joint.home(j.homing.speed, j.homing.threshold, j.homing.current)
    joint.set_max_velocity(j.max_velocity)
    joint.set_max_acceleration(j.max_acceleration)
    joint.enable_stallguard(j.stall_threshold)
    core = sim.cores["j1"]
    core.stall_log = []
    joint.set_velocity(-speed)
    for _ in range(40):
        backend.step(0.01)
        joint.get_velocity()
    place_obstacle(sim, "j1", direction=-1, gap=0.005)
    start = backend.clock.now()
    tripped = None
    for _ in range(150):
        backend.step(0.01)
        if joint.get_flags() & Flag.STALL:
            tripped = backend.clock.now() - start
            break
    raws = [row[1] for row in core.stall_log]
    rise = max((b - a for a, b in itertools.pairwise(raws)), default=0.0)
    backend.close()
    return tripped, rise


def run_arm(speed: float, config_path: Path | None) -> str:
    """Through the arm layer: which detector stopped j1, and how long after contact."""
    arm = Arm(make_backend("sim", load_config(config_path)))
    arm.configure()
    arm.activate()
    arm.home()
    arm.claim("j1", "velocity")
    arm.set_command("j1", -speed)
    for _ in range(40):
        arm.cycle(0.01)
    backend = arm.backend
    place_obstacle(backend.sim, "j1", direction=-1, gap=0.005)
    start = backend.clock.now()
    passed = 0.0  # to the end of the cycle that stopped it (the arm's safe stop takes longer)
    try:
        for _ in range(150):
            passed = backend.clock.now() - start + 0.01
            arm.cycle(0.01)
    except FieldLostError:
        return f"field watch, {passed:.2f} s"
    except StalledError:
        return f"stall flag, {passed:.2f} s"
    finally:
        arm.shutdown()
    return "**neither**"


def main() -> None:
    parser = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    parser.add_argument("--config", type=Path)
    args = parser.parse_args()
    reduction = load_config(args.config).joint("j1").reduction
    print(
        "| j1 speed | motor rad/s | blocked error per pass | firmware alone: flagged "
        "| largest rise per pass | the arm: stopped by |"
    )
    print("|---|---|---|---|---|---|")
    for speed in SPEEDS:
        tripped, rise = run(speed, args.config)
        motor = speed * reduction
        per_pass = math.degrees(motor) * 1e-3 * USTEPS_PER_DEG
        seen = f"yes, {tripped:.2f} s" if tripped is not None else "**no**"
        by = run_arm(speed, args.config)
        print(f"| {speed:g} rad/s | {motor:.1f} | {per_pass:.0f} | {seen} | {rise:.0f} | {by} |")


if __name__ == "__main__":
    main()
