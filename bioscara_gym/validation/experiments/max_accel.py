"""``maxAccel/``: how fast each joint accelerates and runs at the test's current, and where it loses steps.

``max_accel_test.cpp`` homes the joint (or refuses), disables it for the
operator to move it to mid-range, sets the max acceleration and velocity,
enables it at the test current, commands the max velocity and then, every
pass, sleeps 10 ms and reads the position and the velocity. Its logged time
``t`` adds up only the sleeps, so the replay runs each pass as the program
did: the logged sleep, the two transactions at their own duration on the
bus, and the program's print (``bus_timing.program_overhead_us``).
"""

from __future__ import annotations

import dataclasses
import math
from dataclasses import dataclass

import numpy as np

from bioscara_gym.hardware.config import ArmConfig
from bioscara_gym.hardware.drive import IDEAL_DRIVE
from bioscara_gym.validation.recordings import MaxAccelRun
from bioscara_gym.validation.report import Row
from bioscara_gym.validation.rig import JointRig

#: Bounds of the comparison (issue #23): peak speed within 10 %, position RMS
#: at most 5 % of the move, step loss where the real motor lost steps only.
PEAK_SPEED_BOUND_PCT = 10.0
POSITION_RMS_BOUND_PCT = 5.0


@dataclass(frozen=True)
class MaxAccelReplay:
    """The simulated run: one sample per recorded sample (joint units), and the motor's counters.

    The counters count from the velocity command on (not the homing before it).
    """

    t: np.ndarray  # simulated time of each sample, s from the velocity command
    q: np.ndarray
    qd: np.ndarray
    lost_sync: int
    pole_slips: int
    #: Per sample, the largest share of the pull-out torque the command had
    #: asked for since the velocity command (:attr:`KinematicStepper.peak_demand`).
    demand: np.ndarray | None = None


def replay(run: MaxAccelRun, config: ArmConfig, seed: int = 0) -> MaxAccelReplay:
    """Run ``max_accel_test.cpp`` with the run's settings on the simulated joint."""
    rig = JointRig(config, run.joint, seed=seed)
    joint = rig.joint
    joint.set_max_acceleration(run.max_acceleration)
    joint.set_max_velocity(run.max_velocity)
    current = round(run.current)
    joint.enable(current, current)
    start = rig.now
    motor = rig.motor
    motor.peak_demand = 0.0  # the homing's own is not the run's
    lost0, slips0 = motor.lost_sync, motor.pole_slips
    joint.set_velocity(run.max_velocity)
    overhead = config.bus_timing.program_overhead_s
    t, q, qd, demand = [], [], [], []
    last = 0.0
    for logged in run.t:
        rig.sleep(logged - last)
        last = logged
        q.append(joint.get_position())
        qd.append(joint.get_velocity())
        t.append(rig.now - start)
        demand.append(motor.peak_demand)
        rig.sleep(overhead)
    lost, slips = motor.lost_sync - lost0, motor.pole_slips - slips0
    return MaxAccelReplay(np.array(t), np.array(q), np.array(qd), lost, slips, np.array(demand))


def window(run: MaxAccelRun, config: ArmConfig) -> np.ndarray:
    """Samples to compare: while the real move stays within the simulated joint's room.

    The simulated joint starts at mid-range with half its range to go; a few
    real runs were made off the arm and went further (j3 4.8 rad of its
    ±2.63). Also ends where the real position jumps more than its speed allows
    (none in the packaged data).
    """
    params = config.joint(run.joint)
    room = 0.5 * (params.max - params.min)
    moved = np.abs(run.q - run.q[0])
    inside = moved <= room
    if inside.all():
        return np.ones(len(run.q), dtype=bool)
    end = int(np.argmin(inside))
    mask = np.zeros(len(run.q), dtype=bool)
    mask[:end] = True
    return mask


def lost_steps(qd: np.ndarray, commanded: np.ndarray, run: MaxAccelRun) -> bool:
    """Whether a speed trace fell behind what the driver chip commanded: lost steps.

    ``commanded`` is the same program replayed on a motor that never loses a
    step (the firmware, the library and the chip as they are, so it includes
    what the chip makes of the limits: the 16-bit cut of the acceleration
    that ``moveSteps(0)`` in SETUP leaves behind, for one). Read through the
    same encoder estimate, a motor that keeps its field stays within 10 % of
    the command of it; one that lost steps falls further behind.
    """
    if len(qd) == 0:
        return False
    shortfall = np.abs(commanded) - np.abs(qd)
    return bool(np.max(shortfall) > 0.1 * abs(run.max_velocity))


def peak_demand(sim: MaxAccelReplay, mask: np.ndarray) -> float | None:
    """The largest share of the pull-out torque the command asked for within the compared samples."""
    if sim.demand is None or not mask.any():
        return None
    return float(sim.demand[np.nonzero(mask)[0][-1]])


def _demand_note(sim: MaxAccelReplay, mask: np.ndarray) -> str:
    demand = peak_demand(sim, mask)
    return "" if demand is None else f"; the command asked up to {demand:.3g}x its pull-out torque"


def ideal(config: ArmConfig, joint: str) -> ArmConfig:
    """``config`` with ``joint``'s motor made ideal: the chip's command, followed exactly."""
    joints = tuple(dataclasses.replace(j, drive=IDEAL_DRIVE) if j.name == joint else j for j in config.joints)
    return dataclasses.replace(config, joints=joints)


def compare(
    run: MaxAccelRun, sim: MaxAccelReplay, config: ArmConfig, commanded: MaxAccelReplay | None = None
) -> list[Row]:
    """Peak speed, step loss and position RMS of one run (``commanded``: the ideal replay)."""
    if commanded is None:
        commanded = replay(run, ideal(config, run.joint))
    name = f"maxAccel/{run.name}"
    unit = "m/s" if config.joint(run.joint).joint_type == "prismatic" else "rad/s"
    pos_unit = unit.removesuffix("/s")
    mask = window(run, config)
    note = "" if mask.all() else f"first {int(mask.sum())} of {len(mask)} samples (end of the joint's room)"
    real_qd, sim_qd = run.qd[mask], sim.qd[mask]
    rows = [
        Row.compare(
            name,
            "peak speed",
            float(np.max(np.abs(real_qd))),
            float(np.max(np.abs(sim_qd))),
            PEAK_SPEED_BOUND_PCT,
            unit=unit,
            note=note,
        )
    ]
    real_lost = lost_steps(real_qd, commanded.qd[mask], run)
    sim_lost = lost_steps(sim_qd, commanded.qd[mask], run)
    rows.append(
        Row.verdict(
            name,
            "lost steps",
            "yes" if real_lost else "no",
            "yes" if sim_lost else "no",
            real_lost == sim_lost,
            note=f"motor lost its field {sim.lost_sync}x, {sim.pole_slips} pole slips"
            + _demand_note(sim, mask),
        )
    )
    real_move = run.q[mask] - run.q[0]
    sim_move = sim.q[mask] - sim.q[0]
    moved = float(np.max(np.abs(real_move)))
    rms = float(np.sqrt(np.mean((sim_move - real_move) ** 2)))
    rows.append(
        Row(
            name,
            "position RMS",
            moved,
            rms,
            100.0 * rms / moved if moved > 0 else math.inf,
            POSITION_RMS_BOUND_PCT,
            pos_unit,
            "% of move",
            bool(moved > 0 and 100.0 * rms / moved <= POSITION_RMS_BOUND_PCT),
            "real: the move; sim: the RMS difference",
        )
    )
    return rows


def run_all(runs: list[MaxAccelRun], config: ArmConfig) -> tuple[list[Row], dict[str, MaxAccelReplay]]:
    """Replay and compare every run."""
    rows, sims = [], {}
    for run in runs:
        sim = sims[run.name] = replay(run, config)
        rows += compare(run, sim, config)
    return rows, sims
