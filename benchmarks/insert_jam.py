"""When the firmware feels the Insert peg jam: lift speed and stall sensitivity against STALL.

Bioscara-Insert (sim backend, cartesian control) with the fixture moved 5 mm
after the reset, so the peg lands on the fixture's top; the policy only
lowers the lift. For each lift speed (``lift_speed``, j2's max velocity) and
stall sensitivity (``lift_sensitivity``), over ``--episodes`` seeded
episodes whose start heights put the contact at different phases of the
firmware's 10 ms pass, prints: the speed at the motor, the PID error a held
rotor shows each pass (its field's travel in the library's 1 ms loop), the
threshold, how many jams STALL caught, how long after contact, the largest
low-pass value the firmware reached, and the force the lift pressed with.
Nothing here decides a stall: the emulated firmware's rule does
(``docs/firmware.md``, "Stall detection").

    python benchmarks/insert_jam.py
    python benchmarks/insert_jam.py --speeds 6 --sensitivities 4 12 --episodes 32
    python benchmarks/insert_jam.py --config my_arm.yaml   # another drive (e.g. a new calibration)
"""

from __future__ import annotations

import argparse
import math
import time
from pathlib import Path

import gymnasium as gym
import numpy as np

import bioscara_gym  # noqa: F401 - registers the tasks
from bioscara_gym.envs.insert import FIXTURE_TOP, PEG_TIP_BELOW_TCP, START_GAP_M
from bioscara_gym.hardware.drive import USTEPS_PER_DEG
from bioscara_gym.hardware.firmware import stall_threshold
from bioscara_gym.hardware.registers import FLAG_STALL

ENV = "Bioscara-Insert-v0"
SPEEDS_MM_S = (3, 4, 5, 6, 7, 8, 10, 15, 30)
SENSITIVITIES = (4, 6, 12)
#: How long the lift may press after contact before a jam counts as unnoticed, s.
PRESS_S = 1.5
DOWN = np.array([0.0, 0.0, -1.0, 0.0], dtype=np.float32)


def jam(
    speed: float, sensitivity: int, seed: int, config: Path | None = None
) -> tuple[float | None, float, float]:
    """One jam: s from contact to STALL (None: none within ``PRESS_S``), peak low-pass, peak force (N)."""
    steps = math.ceil((START_GAP_M[1] / speed + PRESS_S) / 0.04)
    kwargs = {"lift_speed": speed, "lift_sensitivity": sensitivity, "config": config}
    env = gym.make(ENV, max_episode_steps=steps, **kwargs)
    u = env.unwrapped
    env.reset(seed=seed)
    sim = u.sim
    m, d = sim.model, sim.data
    d.mocap_pos[m.body("fixture").mocapid[0], 0] += 0.005
    core = sim.cores["j2"]
    core.stall_log = []
    dof = int(m.jnt_dofadr[m.joint("j2").id])
    contact = tripped = None
    force = 0.0
    for _ in range(steps):
        _, _, terminated, truncated, _ = env.step(DOWN)
        tip = float(sim.joint_positions()[1]) + 0.005 - PEG_TIP_BELOW_TCP
        force = max(force, abs(float(d.qfrc_constraint[dof])))
        if contact is None and tip <= FIXTURE_TOP + 5e-5:
            contact = sim.time
        if core.flags & FLAG_STALL:
            tripped = sim.time
            break
        if terminated or truncated:
            break
    peak = max((row[3] for row in core.stall_log), default=0.0)
    env.close()
    if contact is None:  # landed within the last step
        contact = tripped if tripped is not None else sim.time
    return (None if tripped is None else tripped - contact), peak, force


def main() -> None:
    parser = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    parser.add_argument("--speeds", type=float, nargs="+", default=SPEEDS_MM_S, help="lift speeds, mm/s")
    parser.add_argument("--sensitivities", type=int, nargs="+", default=SENSITIVITIES)
    parser.add_argument("--episodes", type=int, default=16, help="seeded jams per setting")
    parser.add_argument("--config", type=Path, help="arm configuration YAML (default: the packaged one)")
    args = parser.parse_args()
    reduction = abs(gym.make(ENV, backend="mock", config=args.config).unwrapped.config.joint("j2").reduction)
    start = time.perf_counter()
    print(
        "| lift | motor | held error a pass | sensitivity (threshold at rest) | STALL | after contact | "
        "peak low-pass | peak force |"
    )
    print("|---|---|---|---|---|---|---|---|")
    for speed_mm in args.speeds:
        speed = speed_mm / 1000.0
        motor = speed * reduction
        per_pass = math.degrees(motor) * 1e-3 * USTEPS_PER_DEG
        for sensitivity in args.sensitivities:
            runs = [jam(speed, sensitivity, seed, args.config) for seed in range(args.episodes)]
            times = [t for t, _, _ in runs if t is not None]
            when = f"{min(times):.2f}-{max(times):.2f} s" if times else "-"
            peak = max(p for _, p, _ in runs)
            force = np.median([f for _, _, f in runs])
            print(
                f"| {speed_mm:g} mm/s | {motor:.1f} rad/s | {per_pass:.0f} | "
                f"{sensitivity} ({stall_threshold(0.0, sensitivity):.0f}) | "
                f"{len(times)}/{len(runs)} | {when} | {peak:.0f} | {force:.0f} N |",
                flush=True,
            )
    print(f"({time.perf_counter() - start:.0f} s)")


if __name__ == "__main__":
    main()
