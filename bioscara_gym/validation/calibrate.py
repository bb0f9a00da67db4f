"""System identification: the model's free parameters fitted to the real arm's recordings.

``bioscara calibrate`` runs these fits and writes a configuration whose
``drive`` blocks, ``pid_noise`` profile and ``bus_timing`` come from the
recordings (every other value is the input configuration's):

* :func:`fit_bus_timing`: the host's overhead per transaction, the clock
  periods its controller adds and the handler times the profiling firmware
  did not measure, by non-negative least squares on ``RW_test/``.
* :func:`fit_program_overhead`: what ``max_accel_test.cpp`` spends per pass
  beyond its sleep and transactions, from the runs' constant-speed stretches
  (position step over the reported speed is the real period).
* :func:`fit_pid_noise`: the PID error of a following rotor, median by speed
  band while the set speed rises and while it falls, from the free-running
  rows of ``high_speed_stall_test/``.
* :func:`fit_drive`: per joint, the pull-out acceleration, its fall with
  speed, friction, the slipping rotor's torque and the pull-in range, by
  differential evolution (scipy) on the ``maxAccel/`` replays: position and
  peak speed of every run and whether it lost steps, plus the limits the
  arm's authors state in ``maxAccel/README.md`` for runs not published.
  Once per :data:`DRIVE_HYPOTHESES` (the slipping rotor's push free, and
  held at 0); the lower cost is kept.
* :func:`fit_pole_slip_swing`, last, on the fitted drives: how hard a pole
  slip throws the rotor back and how its swing dies away, shared by every
  drive, from the blocks in ``high_speed_stall_test/`` (the passes between
  the block and the trip).
"""

from __future__ import annotations

import dataclasses
import functools
import math
import multiprocessing
import signal
from collections.abc import Callable, Mapping, Sequence
from dataclasses import dataclass

import numpy as np

from bioscara_gym.hardware.config import ArmConfig
from bioscara_gym.hardware.drive import DriveParams, PidNoiseProfile
from bioscara_gym.hardware.i2c_timing import TransactionTiming, wire_time_s
from bioscara_gym.hardware.registers import Reg
from bioscara_gym.validation.experiments import max_accel
from bioscara_gym.validation.experiments.stall import BlockEvent, block_cost, block_events, replay_block
from bioscara_gym.validation.recordings import (
    HandlerTimes,
    MaxAccelRun,
    Recordings,
    StallSignal,
    Transactions,
)

__all__ = [
    "DRIVE_HYPOTHESES",
    "README_LIMITS",
    "Limit",
    "calibrate",
    "check_fittable",
    "fit_bus_timing",
    "fit_drive",
    "fit_pid_noise",
    "fit_pole_slip_swing",
    "fit_program_overhead",
]


# ----------------------------------------------------------------- bus timing
#: The functions of ``comm_speed_test.cpp`` by file: (read register, write register).
_RW_REGISTERS = {"position": (Reg.ANGLEMOVED, Reg.MOVETOANGLE), "velocity": (Reg.GETENCODERRPM, Reg.SETRPM)}
#: Bytes written and read by each (docs/protocol.md): a query writes the
#: register and reads value and flags, a command writes register and value and reads the flags.
_LENGTHS = {"read": (1, 5), "write": (5, 1)}


def fit_bus_timing(
    transactions: Sequence[Transactions], handlers: Sequence[HandlerTimes]
) -> TransactionTiming:
    """Host overhead, extra clock periods and unmeasured handler times from ``RW_test/``.

    The profiling firmware measured the handlers of the position functions
    (``baseline_joint_400kHz.csv``); those of GETENCODERRPM and SETRPM, the
    host's overhead and the periods its controller adds are fitted to the
    mean time of each function at each bus speed (non-negative least squares).

    Raises:
        ValueError: No position and velocity timings, or no handler times.
    """
    from scipy.optimize import lsq_linear

    measured: dict[int, float] = {}
    for h in handlers:
        for name, us in h.mean_us().items():
            if str(name) in Reg.__members__:
                measured[int(Reg[str(name)])] = us * 1e-6
    unknown = [int(Reg.GETENCODERRPM), int(Reg.SETRPM)]
    rows, y = [], []
    for tr in transactions:
        if tr.what not in _RW_REGISTERS:
            continue  # other host patterns: their program is not published
        for kind, mean_us in (("read", tr.read_us.mean()), ("write", tr.write_us.mean())):
            reg = int(_RW_REGISTERS[tr.what][0 if kind == "read" else 1])
            wire = wire_time_s(*_LENGTHS[kind], tr.clock_hz)
            row = [1.0, 1.0 / tr.clock_hz] + [1.0 if reg == u else 0.0 for u in unknown]
            known = measured.get(reg, 0.0) if reg not in unknown else 0.0
            rows.append(row)
            y.append(mean_us * 1e-6 - wire - known)
    if not rows or not measured:
        raise ValueError("RW_test needs position_/velocity_<speed>kHz.csv and baseline_joint_*.csv")
    sol = lsq_linear(np.array(rows), np.array(y), bounds=(0.0, np.inf)).x
    handler_s = dict(measured)
    handler_s.update({u: float(v) for u, v in zip(unknown, sol[2:], strict=True)})
    return TransactionTiming(float(sol[0]), float(sol[1]), handler_s)


def fit_program_overhead(runs: Sequence[MaxAccelRun], timing: TransactionTiming, clock_hz: float) -> float:
    """Seconds ``max_accel_test.cpp`` spends per pass beyond its sleep and two reads.

    On a stretch of constant speed (the reported speed within 1 % of the
    command for five samples), the position step over the speed is the
    real period; the mean over every such sample of every run, less the
    logged sleep and the two transactions, is the program's own time.
    """
    reads = timing.transaction_s(1, 5, clock_hz, int(Reg.ANGLEMOVED)) + timing.transaction_s(
        1, 5, clock_hz, int(Reg.GETENCODERRPM)
    )
    extra = []
    for run in runs:
        v = run.max_velocity
        steady = np.abs(run.qd - v) < 0.01 * v
        for i in range(5, len(run.t)):
            if steady[i - 4 : i + 1].all():
                real = (run.q[i] - run.q[i - 1]) / run.qd[i]
                extra.append(real - (run.t[i] - run.t[i - 1]) - reads)
    if not extra:
        names = ", ".join(f"maxAccel/{run.path.name}" for run in runs)
        raise ValueError(
            f"no maxAccel run reaches a constant speed (within 1 % of its Vel for 5 samples): the "
            f"program's overhead cannot be measured; looked at {names}"
        )
    return max(0.0, float(np.mean(extra)))


# ----------------------------------------------------------------- PID noise
#: Edges of the speed bands the PID-error jitter is fitted in, motor rad/s:
#: 1 rad/s wide up to 5 (where homing runs, and the jitter grows from almost
#: nothing at rest), then the validation's 5 rad/s bands.
NOISE_BAND_EDGES = (0.0, 1.0, 2.0, 3.0, 4.0, 5.0)


def fit_pid_noise(signals: Sequence[StallSignal]) -> PidNoiseProfile:
    """Median |PID error| per speed band while the set speed rises and while it falls.

    The bands are :data:`NOISE_BAND_EDGES`, then the validation's 5 rad/s
    bands (:func:`~.experiments.stall.band_medians`); pooled over every
    file's replayable passes (the old builds print the same raw error;
    passes within 0.3 s before a trip are left out, they belong to the
    stall); each band's median becomes a knot at its centre. A band with
    fewer than 5 passes takes its neighbour's value.

    Raises:
        ValueError: No free-running passes at all.
    """
    from bioscara_gym.validation.experiments.stall import BAND_RAD_S, _bands

    pools: dict[tuple[int, float], list[float]] = {}
    for sig in signals:
        keep = (sig.raw < 10_000) & ~((sig.set_speed == 0) & (np.abs(sig.speed) > 2.0))
        for i in np.nonzero(sig.stalled > 0)[0]:
            keep &= ~((sig.t > sig.t[i] - 0.3) & (sig.t <= sig.t[i]))
        _, direction = _bands(sig.speed, sig.set_speed)
        for w, d, v in zip(np.abs(sig.speed[keep]), direction[keep], sig.raw[keep], strict=True):
            pools.setdefault((1 if d >= 0 else -1, _noise_knot(float(w), BAND_RAD_S)), []).append(float(v))
    if not pools:
        raise ValueError("high_speed_stall_test holds no free-running passes to fit the PID-error profile on")
    knots = tuple(sorted({k for _, k in pools}))

    def medians(d: int) -> tuple[float, ...]:
        out: list[float | None] = [
            float(np.median(pools[(d, k)])) if len(pools.get((d, k), ())) >= 5 else None for k in knots
        ]
        known = [v for v in out if v is not None]
        last = known[0] if known else 0.0
        filled = []
        for v in out:
            last = v if v is not None else last
            filled.append(round(float(last), 1))
        return tuple(filled)

    return PidNoiseProfile(knots, medians(1), medians(-1))


def _noise_knot(speed: float, width: float) -> float:
    """The centre of the jitter band ``speed`` (motor rad/s) falls in."""
    edges = NOISE_BAND_EDGES
    if speed < edges[-1]:
        i = int(np.searchsorted(edges, speed, side="right")) - 1
        return 0.5 * (edges[i] + edges[i + 1])
    band = math.floor(speed / width)
    return width * (band + 0.5)


# ------------------------------------------------------------ pole-slip swing
#: Where the swing's fit starts: (kick_accel rad/s², kick_time_s, kick_period_s).
#: Two starts, a short sharp swing and a slow one (the cost has both valleys).
SWING_STARTS = ((1.5e5, 0.01, 0.04), (5e4, 0.05, 0.1))
#: Seeds of the PID-error jitter each candidate is replayed with (the cost is
#: their mean): whether a slow block trips at its first pole slip can hang on
#: the jitter of one pass, and a fit on one seed finds that knife's edge.
SWING_SEEDS = (0, 1, 2)


def fit_pole_slip_swing(
    config: ArmConfig, events: Sequence[BlockEvent], maxfev: int = 150
) -> tuple[float, float, float]:
    """Fit the swing of a pole slip (``kick_accel``, ``kick_time_s``, ``kick_period_s``) to the real blocks.

    Each :class:`~.experiments.stall.BlockEvent` is replayed
    (:func:`~.experiments.stall.replay_block`) with one candidate on every
    drive and each of :data:`SWING_SEEDS`; the cost is the mean over the
    seeds of :func:`~.experiments.stall.block_cost` summed over the blocks
    (measured speed RMS, the raw error's median and largest value, and
    whether the trip came within 50 ms of the real one).
    Nelder-Mead in log space from each of :data:`SWING_STARTS`; the best.

    Raises:
        ValueError: No block to fit to.
    """
    from scipy.optimize import minimize

    if not events:
        raise ValueError("high_speed_stall_test holds no block that ended in a trip to fit the swing to")

    def cost(x: np.ndarray) -> float:
        accel, tau, period = (float(10**v) for v in x)
        c = config.with_drives(kick_accel=accel, kick_time_s=tau, kick_period_s=period)
        return sum(
            sum(block_cost(e, replay_block(e, c, seed=seed))) for e in events for seed in SWING_SEEDS
        ) / len(SWING_SEEDS)

    best = min(
        (
            minimize(cost, np.log10(start), method="Nelder-Mead", options={"maxfev": maxfev, "xatol": 0.01})
            for start in SWING_STARTS
        ),
        key=lambda r: r.fun,
    )
    accel, tau, period = (float(10**v) for v in best.x)
    return accel, tau, period


# --------------------------------------------------------------------- drive
@dataclass(frozen=True)
class Limit:
    """A limit the arm's authors state for a run they did not publish: lost steps or not.

    Attributes:
        joint: The joint.
        max_velocity: Velocity commanded (joint units).
        max_acceleration: Acceleration set (joint units).
        current: Percent.
        lost: Whether the motor lost steps.
        source: Where it is stated.
    """

    joint: str
    max_velocity: float
    max_acceleration: float
    current: float
    lost: bool
    source: str

    def as_run(self) -> MaxAccelRun:
        """A run of ``max_accel_test.cpp`` of these settings, 2 s long (no samples to compare)."""
        t = 0.01012 * np.arange(1, 201)
        from pathlib import Path

        nan = np.full(len(t), np.nan)
        return MaxAccelRun(
            Path(f"README:{self.joint}_{self.max_velocity:g}_{self.max_acceleration:g}"),
            self.joint,
            self.max_velocity,
            self.max_acceleration,
            self.current,
            t,
            nan,
            nan,
        )


#: ``maxAccel/README.md``: runs named there but not published (j3_15, j3_17, j3_18).
README_LIMITS = (
    Limit("j3", 5.0, 14.0, 20, False, "maxAccel/README.md: max acceleration at 14 rad/s2 (run j3_17)"),
    Limit(
        "j3", 5.0, 15.0, 20, True, "maxAccel/README.md: acc 15 rad/s2 and vel 5rad/s didnt work (run j3_18)"
    ),
    Limit("j3", 5.0, 10.0, 20, False, "maxAccel/README.md: max velocity 5 rad/s at 20% current (run j3_15)"),
)

#: What the fit may choose per joint: (field, low, high, searched on a log scale).
#: Accelerations in motor rad/s² at 100 % current (pull-out) or as
#: decelerations (friction): a lead screw's friction over its small inertia
#: is thousands of rad/s², an arm's tens.
DRIVE_BOUNDS = (
    ("pullout_accel", 300.0, 100_000.0, True),
    ("corner_speed", 20.0, 3000.0, True),
    ("corner_exponent", 1.0, 12.0, False),
    ("friction_coulomb", 1.0, 20_000.0, True),
    ("friction_viscous", 0.0, 50.0, False),
    ("slip_fraction", 0.0, 1.0, False),
    ("slip_corner", 0.5, 1000.0, True),
    ("pullin_speed", 0.5, 30.0, False),
)


#: The drive fit's starting assumptions, each searched in full; the lower
#: cost is kept. With the slipping rotor's push free, the search settled for
#: j1 in a valley where a slipped rotor creeps on at 0.089 rad/s (drive cost
#: 0.0131); the real j1 in ``j1_3`` slows at a nearly constant rate and stops
#: dead, which the search found with that push held at 0 (0.0043, before
#: :data:`DEMAND_MARGIN`; docs/validation.md).
DRIVE_HYPOTHESES: tuple[Mapping[str, float], ...] = ({}, {"slip_fraction": 0.0})


def _with_drive(config: ArmConfig, joint: str, drive: DriveParams) -> ArmConfig:
    joints = tuple(dataclasses.replace(j, drive=drive) if j.name == joint else j for j in config.joints)
    return dataclasses.replace(config, joints=joints)


#: How far from the edge of its pull-out a run must stay before the fit
#: pays for it: a run the real motor held should ask at most ``1 - m`` of
#: the pull-out torque, one where it lost steps at least ``1 + m``. The real
#: verdicts bracket the edge (j1 held at 1 rad/s with 2 rad/s², lost with
#: 3); without a margin a least-cost fit puts the edge on the held run
#: (``j1_1`` asked 0.96 of its pull-out), where a command a hair faster in
#: a task loses steps the real motor kept.
DEMAND_MARGIN = 0.1


def _margin_cost(demand: float, lost: bool) -> float:
    """(How far inside :data:`DEMAND_MARGIN` of the edge ``demand`` is, over the margin)²."""
    inside = (1.0 + DEMAND_MARGIN - demand) if lost else (demand - (1.0 - DEMAND_MARGIN))
    return max(0.0, inside / DEMAND_MARGIN) ** 2


def drive_cost(
    config: ArmConfig, runs: Sequence[MaxAccelRun], limits: Sequence[Limit], step_loss_weight: float = 1.0
) -> float:
    """What the drive fit minimises: position and peak-speed errors, step-loss verdicts and their margin.

    Per published run: (position RMS / move)² + (peak speed error / peak)²
    over the compared window, plus ``step_loss_weight`` if the simulated run
    disagrees with the real one on lost steps and ``step_loss_weight`` times
    the margin cost (:data:`DEMAND_MARGIN`) of the largest share of the
    pull-out torque it asked for; per stated limit, the same verdict and margin terms.
    """
    total = 0.0
    for run in runs:
        sim = max_accel.replay(run, config)
        commanded = max_accel.replay(run, max_accel.ideal(config, run.joint))
        mask = max_accel.window(run, config)
        real = run.q[mask] - run.q[0]
        move = max(float(np.max(np.abs(real))), 1e-9)
        rms = float(np.sqrt(np.mean((sim.q[mask] - sim.q[0] - real) ** 2))) / move
        peak = float(np.max(np.abs(run.qd[mask])))
        peak_err = abs(float(np.max(np.abs(sim.qd[mask]))) - peak) / peak
        lost_real = max_accel.lost_steps(run.qd[mask], commanded.qd[mask], run)
        lost_sim = max_accel.lost_steps(sim.qd[mask], commanded.qd[mask], run)
        demand = max_accel.peak_demand(sim, mask) or 0.0
        total += rms**2 + peak_err**2
        total += step_loss_weight * ((lost_real != lost_sim) + _margin_cost(demand, lost_real))
    for limit in limits:
        run = limit.as_run()
        sim = max_accel.replay(run, config)
        commanded = max_accel.replay(run, max_accel.ideal(config, run.joint))
        demand = max_accel.peak_demand(sim, np.ones(len(sim.t), bool)) or 0.0
        lost_sim = max_accel.lost_steps(sim.qd, commanded.qd, run)
        total += step_loss_weight * ((lost_sim != limit.lost) + _margin_cost(demand, limit.lost))
    return total


#: The fields that decide what a slipped rotor does: searched again on their
#: own once the rest is fitted (:func:`fit_drive`).
SLIP_FIELDS = ("slip_fraction", "slip_corner", "pullin_speed")

Bound = tuple[str, float, float, bool]


def fit_drive(
    config: ArmConfig,
    joint: str,
    runs: Sequence[MaxAccelRun],
    limits: Sequence[Limit] = (),
    *,
    held: Mapping[str, float] | None = None,
    seed: int = 0,
    maxiter: int = 40,
    popsize: int = 16,
    progress: Callable[[str], None] | None = None,
) -> DriveParams:
    """Fit one joint's drive to its ``maxAccel/`` runs and stated limits (differential evolution).

    ``held`` names fields of :data:`DRIVE_BOUNDS` kept at a value instead of
    searched (one of :data:`DRIVE_HYPOTHESES`). Three stages: every field
    at once, from the configuration's drive; the slipped rotor's fields
    (:data:`SLIP_FIELDS`) on their own, the rest held where the first stage
    put them; a local polish of every field. The first stage settles where
    each run loses steps (pull-out, friction); what the rotor does after
    that acts only in the runs that lost steps, and a search of all eight
    fields at once, where a verdict flipping is a step in the cost, rarely
    finds it (j1: 0.0155 after forty generations; 0.0086 after the second
    stage, 0.0076 after the polish).

    Raises:
        ValueError: No run or limit of this joint, or a held field that is
            not one of the fit's.
    """
    from scipy.optimize import minimize

    held = dict(held or {})
    unknown = sorted(set(held) - {b[0] for b in DRIVE_BOUNDS})
    if unknown:
        raise ValueError(f"{joint}: cannot hold {', '.join(unknown)}: not a field the drive fit searches")
    runs = [r for r in runs if r.joint == joint]
    limits = [lim for lim in limits if lim.joint == joint]
    if not runs and not limits:
        raise ValueError(f"{joint}: no maxAccel run or stated limit to fit its drive to")

    def cost(drive: DriveParams) -> float:
        try:
            return drive_cost(_with_drive(config, joint, drive), runs, limits)
        except Exception:  # a drive the rig cannot even home with
            return 1e3

    def say(stage: str, value: float) -> None:
        if progress:
            progress(f"{joint} ({_hypothesis(held)}): {stage}, cost {value:.4f}")

    searched = [b for b in DRIVE_BOUNDS if b[0] not in held]
    first = _evolve(
        cost, config.joint(joint).drive.with_values(**held), searched, seed, maxiter, popsize, say
    )
    slip = [b for b in searched if b[0] in SLIP_FIELDS]
    second = _evolve(cost, first, slip, seed, maxiter, popsize, say) if slip else first
    # A local polish of every field (the cost steps where a run starts to lose steps).
    bounds = _bounds(searched)
    polished = minimize(
        lambda x: cost(_drive_at(second, searched, x)),
        _start(second, searched),
        method="Nelder-Mead",
        bounds=bounds,
        options={"maxfev": 40 * len(bounds), "xatol": 1e-4},
    )
    found = cost(second)
    best = _drive_at(second, searched, polished.x) if polished.fun <= found else second
    say("polished", min(polished.fun, found))
    return best


def _bounds(searched: Sequence[Bound]) -> list[tuple[float, float]]:
    """The search's box: log10 of the bounds of the fields searched on a log scale."""
    return [(math.log10(lo), math.log10(hi)) if log else (lo, hi) for _, lo, hi, log in searched]


def _drive_at(base: DriveParams, searched: Sequence[Bound], x: np.ndarray) -> DriveParams:
    """``base`` with the searched fields at the point ``x`` of the search."""
    values = {name: float(10**v if log else v) for (name, _, _, log), v in zip(searched, x, strict=True)}
    return base.with_values(**values)


def _evolve(
    cost: Callable[[DriveParams], float],
    base: DriveParams,
    searched: Sequence[Bound],
    seed: int,
    maxiter: int,
    popsize: int,
    say: Callable[[str, float], None],
) -> DriveParams:
    """Differential evolution over the ``searched`` fields of ``base``, the others held."""
    from scipy.optimize import differential_evolution

    def at(x: np.ndarray) -> float:
        return cost(_drive_at(base, searched, x))

    generation = 0

    def report(xk: np.ndarray, convergence: float = 0.0) -> None:
        nonlocal generation
        generation += 1
        say(f"{len(searched)} fields, generation {generation}", at(xk))

    result = differential_evolution(
        at,
        _bounds(searched),
        x0=_start(base, searched),
        seed=seed,
        maxiter=maxiter,
        popsize=popsize,
        tol=1e-6,
        polish=False,
        updating="deferred",
        callback=report,
    )
    return _drive_at(base, searched, result.x)


def _start(drive: DriveParams, searched: Sequence[Bound]) -> np.ndarray:
    """The configuration's drive as a point of the search, each value brought inside its bounds.

    Seeded into the first generation, so the fit ends no worse than the
    drive it starts from (an unbounded value such as an ideal drive's
    ``inf`` goes to its bound).
    """
    point = []
    for name, lo, hi, log in searched:
        value = min(max(float(getattr(drive, name)), lo), hi)
        point.append(math.log10(value) if log else value)
    return np.array(point)


def _hypothesis(held: Mapping[str, float]) -> str:
    """``slip_fraction held at 0``, or ``all searched`` when nothing is held."""
    return ", ".join(f"{k} held at {v:g}" for k, v in held.items()) or "all searched"


def hypotheses_line(costs: Sequence[float]) -> str:
    """Each hypothesis's drive cost, the kept one marked.

    For example ``all searched 0.0131, slip_fraction held at 0 0.0021 (kept)``.
    """
    kept = list(costs).index(min(costs))
    parts = [
        f"{_hypothesis(h)} {c:.4f}" + (" (kept)" if i == kept else "")
        for i, (h, c) in enumerate(zip(DRIVE_HYPOTHESES, costs, strict=True))
    ]
    return ", ".join(parts)


# ------------------------------------------------------------------ it all
_FORKED_FIT: Callable[[tuple[str, int]], DriveParams] | None = None


def _worker_signals() -> None:
    """In a fit's worker: Ctrl-C is the parent's; SIGTERM (the parent's terminate) and SIGHUP end it.

    A forked worker starts with the parent's handlers, so its SIGHUP (the
    terminal closed: the whole job gets one) would raise the parent's
    interrupt inside the worker.
    """
    signal.signal(signal.SIGINT, signal.SIG_IGN)
    signal.signal(signal.SIGTERM, signal.SIG_DFL)
    if signal.getsignal(signal.SIGHUP) != signal.SIG_IGN:  # nohup's stays
        signal.signal(signal.SIGHUP, signal.SIG_DFL)


def _forked_fit(task: tuple[str, int]) -> DriveParams:
    assert _FORKED_FIT is not None, "set by calibrate() before the pool forks"
    return _FORKED_FIT(task)


@dataclass
class Calibration:
    """What :func:`calibrate` produced, with the costs before and after."""

    config: ArmConfig
    timing: TransactionTiming
    noise: PidNoiseProfile | None
    drive_cost_before: dict[str, float]
    drive_cost_after: dict[str, float]
    #: Per joint, the cost of the drive fitted under each of :data:`DRIVE_HYPOTHESES`, in order.
    drive_cost_by_hypothesis: dict[str, tuple[float, ...]] = dataclasses.field(default_factory=dict)


def check_fittable(config: ArmConfig, rec: Recordings) -> None:
    """Refuse recordings the fit cannot use, before any replay: the quick fits :func:`calibrate` runs first.

    Raises:
        ValueError: What :func:`fit_bus_timing`, :func:`fit_program_overhead`
            or :func:`fit_pid_noise` cannot fit, naming the files.
    """
    timing = config.bus_timing
    if rec.transactions and rec.handler_times:
        timing = fit_bus_timing(rec.transactions, rec.handler_times)
    if rec.max_accel:
        fit_program_overhead(rec.max_accel, timing, config.i2c_clock_hz)
    if rec.stall_signal:
        fit_pid_noise(rec.stall_signal)


def calibrate(
    config: ArmConfig,
    rec: Recordings,
    *,
    seed: int = 0,
    maxiter: int = 40,
    workers: int = 1,
    progress: Callable[[str], None] | None = None,
) -> Calibration:
    """Fit every parameter the recordings identify; return the calibrated configuration.

    ``workers`` above 1 fits the joints' drives, one joint and hypothesis
    each, in that many processes (the result does not depend on it).
    """
    timing = config.bus_timing
    if rec.transactions and rec.handler_times:
        timing = fit_bus_timing(rec.transactions, rec.handler_times)
    if rec.max_accel:
        overhead = fit_program_overhead(rec.max_accel, timing, config.i2c_clock_hz)
        timing = dataclasses.replace(timing, program_overhead_s=overhead)
    config = dataclasses.replace(config, bus_timing=timing)
    noise = fit_pid_noise(rec.stall_signal) if rec.stall_signal else None
    if noise is not None:
        config = config.with_drives(noise=noise)
    limits = README_LIMITS if rec.root.resolve() == _packaged_root() else ()
    named = {r.joint for r in rec.max_accel} | {lim.joint for lim in limits}
    joints = [j for j in sorted(named) if j in config.names]

    def own(joint: str) -> tuple[list[MaxAccelRun], list[Limit]]:
        return [r for r in rec.max_accel if r.joint == joint], [lim for lim in limits if lim.joint == joint]

    before = {joint: drive_cost(config, *own(joint)) for joint in joints}
    # Each run moves one joint, so the joints' fits are independent: one
    # process per joint and hypothesis.
    tasks = [(joint, h) for joint in joints for h in range(len(DRIVE_HYPOTHESES))]

    def fit(task: tuple[str, int], progress: Callable[[str], None] | None) -> DriveParams:
        joint, h = task
        return fit_drive(
            config,
            joint,
            rec.max_accel,
            limits,
            held=DRIVE_HYPOTHESES[h],
            seed=seed,
            maxiter=maxiter,
            progress=progress,
        )

    if workers > 1 and len(tasks) > 1:
        # Forked workers inherit the fit (the configuration does not pickle) and
        # print plain lines: they cannot reach the caller's console.
        global _FORKED_FIT
        plain = functools.partial(print, flush=True) if progress else None
        _FORKED_FIT = functools.partial(fit, progress=plain)
        fork = multiprocessing.get_context("fork")
        try:
            # A Pool, not an executor: leaving the block on an interrupt terminates the
            # workers, where an executor waits for their fits (minutes each) to end.
            with fork.Pool(min(workers, len(tasks)), initializer=_worker_signals) as pool:
                fitted = pool.map(_forked_fit, tasks)
        finally:
            _FORKED_FIT = None
    else:
        fitted = [fit(task, progress) for task in tasks]
    by_hypothesis: dict[str, tuple[float, ...]] = {}
    for joint in joints:
        candidates = [d for (j, _), d in zip(tasks, fitted, strict=True) if j == joint]
        costs = tuple(drive_cost(_with_drive(config, joint, d), *own(joint)) for d in candidates)
        by_hypothesis[joint] = costs
        config = _with_drive(config, joint, candidates[costs.index(min(costs))])
    after = {joint: drive_cost(config, *own(joint)) for joint in joints}
    # Last: the blocks are replayed on the joint's fitted drive.
    events = block_events(rec.stall_signal) if rec.stall_signal else []
    if events:
        accel, tau, period = fit_pole_slip_swing(config, events)
        config = config.with_drives(kick_accel=accel, kick_time_s=tau, kick_period_s=period)
    return Calibration(config, timing, noise, before, after, by_hypothesis)


def _packaged_root() -> object:
    from bioscara_gym.validation.recordings import DATA_DIR

    return DATA_DIR.resolve()


def finite_or_none(x: float) -> float | None:
    """``x`` if finite (for JSON)."""
    return x if math.isfinite(x) else None
