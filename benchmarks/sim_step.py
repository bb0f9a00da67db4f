"""Control steps/s of the ``sim`` backend against raw ``mujoco.mj_step``.

Both run the same model from the same homed, mid-range state through the same
motion: all four joints swept sinusoidally at 30 % of their max velocity.
The backend commands them through ``BaseJoint.set_velocity`` every 40 ms
control step (25 Hz), which runs four 10 ms firmware ticks (set-point ramp,
stall detection, deadman per joint) between blocks of five 2 ms physics
steps; the reference writes the same velocities straight into the actuators
and calls ``mj_step(model, data, nstep=20)``. Target: ratio >= 0.7.
"""

from __future__ import annotations

import argparse
import math
import time

import mujoco

from bioscara_gym.hardware.arm import Arm
from bioscara_gym.hardware.backends import make_backend

CONTROL_DT = 0.04


def _homed_arm() -> Arm:
    arm = Arm(make_backend("sim"))
    arm.configure()
    arm.activate()
    arm.home()
    for name in arm.names:  # park mid-range so the oscillation stays clear of the end stops
        cfg = arm.config.joint(name)
        arm.claim(name, "position")
        arm.set_command(name, (cfg.min + cfg.max) / 2)
    for _ in range(400):
        arm.cycle(CONTROL_DT)
    for name in arm.names:
        arm.release(name)
        arm.claim(name, "velocity")
    return arm


def bench_backend(steps: int) -> float:
    """Control steps per second of the sim backend through BaseJoint calls."""
    arm = _homed_arm()
    joints = list(arm.joints.values())
    amplitude = [0.3 * arm.config.joint(j.name).max_velocity for j in joints]
    backend = arm.backend
    start = time.perf_counter()
    for k in range(steps):
        s = math.sin(2 * math.pi * k * CONTROL_DT / 2.0)
        for joint, a in zip(joints, amplitude, strict=True):
            joint.set_velocity(a * s)
        backend.step(CONTROL_DT)
    return steps / (time.perf_counter() - start)


def bench_raw(steps: int) -> float:
    """Control steps per second of bare mj_step: same model, state and motion, no firmware."""
    arm = _homed_arm()
    model, data = arm.backend.sim.model, arm.backend.sim.data
    n = round(CONTROL_DT / model.opt.timestep)
    amplitude = [0.3 * arm.config.joint(name).max_velocity for name in arm.names]
    start = time.perf_counter()
    for k in range(steps):
        s = math.sin(2 * math.pi * k * CONTROL_DT / 2.0)
        for i, a in enumerate(amplitude):
            data.ctrl[i] = a * s
        mujoco.mj_step(model, data, nstep=n)
    return steps / (time.perf_counter() - start)


def main() -> None:
    """Measure both and print the ratio."""
    parser = argparse.ArgumentParser(description=__doc__)
    parser.add_argument("--steps", type=int, default=3000)
    args = parser.parse_args()
    bench_backend(200)  # warm-up
    # Interleave and keep the best of three, so background load hits both alike.
    raw = max(bench_raw(args.steps) for _ in range(3))
    sim = max(bench_backend(args.steps) for _ in range(3))
    print(f"raw mj_step      : {raw:9.0f} control steps/s ({raw * 20:.0f} mj_step/s)")
    print(f"sim backend      : {sim:9.0f} control steps/s")
    print(f"ratio sim / raw  : {sim / raw:9.3f}  (target >= 0.7)")


if __name__ == "__main__":
    main()
