"""``settingMaxVal/``: a long move under SETMAXACCELERATION and SETMAXVELOCITY, at the motor.

Each file's header gives the limits (motor deg/s² and deg/s); the profile
is a move of the motor to 36,000° (100 turns) in four files and to about
29,230° in one. The program is not published, so the replay sends what the
header and the profile say: the limits, then MOVETOANGLE to where the
profile comes to rest (:func:`target`), and for the file with an online
change the two later commands the profile shows (:func:`online_change`). It is a test of the
firmware, the library and the driver chip rather than of a joint, so the
motor behind it is ideal (no joint is named; the moves are longer than any
joint's range).

The one number that a faithful emulation must get right here: a requested
10,000,000 deg/s² is cut to 16 bits by the library's ``moveSteps`` and the
real motor accelerated at about 9,000 deg/s².
"""

from __future__ import annotations

import math
from dataclasses import dataclass

import numpy as np

from bioscara_gym.hardware import codec
from bioscara_gym.hardware.clock import ManualClock
from bioscara_gym.hardware.emulated_bus import EmulatedI2CBus
from bioscara_gym.hardware.firmware import JointFirmware
from bioscara_gym.hardware.motor import KinematicStepper
from bioscara_gym.hardware.registers import Reg
from bioscara_gym.validation.recordings import SettingMaxValRun
from bioscara_gym.validation.report import Row

#: Bounds: peak speed and ramp acceleration within 10 %, position RMS at most 2 % of the move.
PEAK_BOUND_PCT = 10.0
ACCEL_BOUND_PCT = 10.0
POSITION_BOUND_PCT = 2.0
_ADDRESS = 0x11


@dataclass(frozen=True)
class OnlineChange:
    """The limits sent during the move: SETMAXACCELERATION (deg/s²), SETMAXVELOCITY (deg/s), when (s)."""

    accel_at_s: float
    accel_dps2: float
    velocity_at_s: float
    velocity_dps: float


def _slopes(run: SettingMaxValRun) -> np.ndarray:
    return np.gradient(run.velocity, run.t)


def target(run: SettingMaxValRun) -> float:
    """Where the move ends: the last position, plus the braking distance if the log stops early.

    Rounded to 10 degrees (36,000 in four of the packaged files).
    """
    v = float(run.velocity[-1])
    end = float(run.position[-1] - run.position[0])
    if abs(v) > 0.02 * float(np.max(np.abs(run.velocity))):
        tail = slice(max(0, len(run.t) - 10), len(run.t))
        decel = abs(float(np.polyfit(run.t[tail], run.velocity[tail], 1)[0])) or run.max_acceleration
        end += math.copysign(v * v / (2.0 * decel), v)
    return round(end, -1)


def ramp_acceleration(t: np.ndarray, v: np.ndarray) -> float:
    """Acceleration of the first ramp: a line through the speed while it rises from 10 to 60 % of its peak."""
    peak = float(np.max(v))
    sel = (v > 0.1 * peak) & (v < 0.6 * peak) & (np.arange(len(v)) < int(np.argmax(v)))
    if sel.sum() < 3:
        return math.nan
    return float(np.polyfit(t[sel], v[sel], 1)[0])


def online_change(run: SettingMaxValRun) -> OnlineChange | None:
    """The two commands of the online change, read off the profile (the program is not published).

    The acceleration changes where the speed's slope leaves the header's
    value for good (the new value is the slope after it, rounded to 100
    deg/s²); the velocity limit is the speed the profile settles at (rounded
    to 100 deg/s), sent when the speed stopped rising (the peak). ``None``
    where the profile shows no such change (its slope never leaves the
    header's value while the speed rises, or too few samples follow).
    """
    a0 = run.max_acceleration
    slope = _slopes(run)
    peak_i = int(np.argmax(run.velocity))
    rising = np.arange(len(slope)) < peak_i
    off = rising & (np.abs(slope - a0) > 0.25 * a0) & (run.velocity > 0.2 * run.velocity[peak_i])
    first = int(np.argmax(off))
    after_change = slope[first + 2 : max(first + 3, peak_i - 1)]
    if not off.any() or first == 0 or not len(after_change):
        return None
    a1 = float(np.median(after_change))
    after = run.velocity[peak_i:]
    flat = (
        after[np.abs(np.gradient(after)) < 0.02 * a0 * np.median(np.diff(run.t))] if len(after) > 1 else after
    )
    v1 = float(np.median(flat)) if len(flat) else float(run.velocity[-1])
    # the slope changed between the sample before ``first`` and ``first``; the speed peaked at ``peak_i``
    return OnlineChange(
        float(run.t[first - 1]),
        round(a1, -2),
        float(run.t[peak_i]) - 0.5 * (run.t[1] - run.t[0]),
        round(v1, -2),
    )


@dataclass(frozen=True)
class SettingMaxValReplay:
    """The simulated profile at the recording's sample times (motor degrees, deg/s)."""

    t: np.ndarray
    position: np.ndarray
    velocity: np.ndarray
    change: OnlineChange | None


def replay(run: SettingMaxValRun) -> SettingMaxValReplay:
    """Set the header's limits, move to the profile's end, sample at the recording's times."""
    clock = ManualClock()
    motor = KinematicStepper(0.0)
    firmware = JointFirmware(motor, clock)
    bus = EmulatedI2CBus({_ADDRESS: firmware}, clock=clock)

    def send(reg: Reg, value: float | int) -> None:
        bus.transfer(_ADDRESS, bytes((reg,)) + codec.encode(reg, value), 1)

    def read(reg: Reg) -> float:
        reply = bus.transfer(_ADDRESS, bytes((reg,)), 5)
        return float(codec.decode(reg, reply[:4]))

    send(Reg.SETUP, codec.pack_bytes(50, 50))
    send(Reg.SETMAXACCELERATION, run.max_acceleration)
    send(Reg.SETMAXVELOCITY, run.max_velocity)
    start = motor.position_deg
    send(Reg.MOVETOANGLE, target(run))
    change = online_change(run) if run.online_change else None
    pending = (
        []
        if change is None
        else sorted(
            [
                (change.accel_at_s, Reg.SETMAXACCELERATION, change.accel_dps2),
                (change.velocity_at_s, Reg.SETMAXVELOCITY, change.velocity_dps),
            ]
        )
    )
    t0 = clock.now()
    pos, vel = [], []
    for ts in run.t:
        while pending and pending[0][0] <= ts:
            at, reg, value = pending.pop(0)
            clock.sleep(max(0.0, t0 + at - clock.now()))
            send(reg, value)
        clock.sleep(max(0.0, t0 + ts - clock.now()))
        pos.append(read(Reg.ANGLEMOVED) - start)
        vel.append(read(Reg.GETENCODERRPM) * 6.0)
    return SettingMaxValReplay(run.t, np.array(pos), np.array(vel), change)


def compare(run: SettingMaxValRun, sim: SettingMaxValReplay) -> list[Row]:
    """Peak speed, ramp acceleration and position RMS of one profile."""
    name = f"settingMaxVal/{run.name}"
    real_pos = run.position - run.position[0]
    note = "online change: none found in the profile" if run.online_change and sim.change is None else ""
    if sim.change is not None:
        c = sim.change
        note = (
            f"online change read off the profile: {c.accel_dps2:g} deg/s² at {c.accel_at_s:.2f} s, "
            f"{c.velocity_dps:g} deg/s at {c.velocity_at_s:.2f} s"
        )
    rows = [
        Row.compare(
            name,
            "peak speed",
            float(np.max(run.velocity)),
            float(np.max(sim.velocity)),
            PEAK_BOUND_PCT,
            unit="deg/s",
            note=note,
        ),
        Row.compare(
            name,
            "ramp acceleration",
            ramp_acceleration(run.t, run.velocity),
            ramp_acceleration(sim.t, sim.velocity),
            ACCEL_BOUND_PCT,
            unit="deg/s²",
            note=f"requested {run.max_acceleration:g} deg/s²",
        ),
    ]
    moved = float(np.max(np.abs(real_pos)))  # run_all leaves out a profile that did not move
    rms = float(np.sqrt(np.mean((sim.position - real_pos) ** 2)))
    error = 100 * rms / moved if moved > 0 else math.inf
    rows.append(
        Row(
            name,
            "position RMS",
            moved,
            rms,
            error,
            POSITION_BOUND_PCT,
            "deg",
            "% of move",
            bool(error <= POSITION_BOUND_PCT),
            "real: the move; sim: the RMS difference",
        )
    )
    return rows


def distance_moved(run: SettingMaxValRun) -> float:
    """How far the real motor moved from its first sample, degrees (0: it did not)."""
    return float(np.max(np.abs(run.position - run.position[0])))


def run_all(runs: list[SettingMaxValRun]) -> tuple[list[Row], dict[str, SettingMaxValReplay]]:
    """Replay and compare every profile; one failing row for a profile that did not move (no replay)."""
    rows, sims = [], {}
    for run in runs:
        if distance_moved(run) == 0.0:
            rows.append(
                Row.verdict(
                    f"settingMaxVal/{run.name}",
                    "the motor moved",
                    "no",
                    "-",
                    False,
                    "its position never changes: nothing to compare (not replayed)",
                )
            )
            continue
        sim = sims[run.name] = replay(run)
        rows += compare(run, sim)
    return rows, sims
