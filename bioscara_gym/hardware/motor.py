"""Motor models behind the emulated firmware.

The firmware emits a set-point velocity once per 10 ms tick together with the
torque the driver current allows; the motor model plays the uStepper S32
between firmware and rotor (:mod:`~bioscara_gym.hardware.drive`): the chip
issues steps at that velocity, the rotor follows while the motor's torque
allows, the library's 1 kHz closed loop keeps the driver's position counter
and computes the PID error the firmware watches, and the encoder's velocity
estimator gives the speed it reports. :class:`KinematicStepper` is the model
of the driver tests and the validation against the real arm; the MuJoCo arm
provides another (``bioscara_gym.hardware.sim``).
"""

from __future__ import annotations

import math
from typing import Protocol, runtime_checkable

import numpy as np

from bioscara_gym.hardware.drive import (
    CLOSED_LOOP_PERIOD_S,
    CONTROL_THRESHOLD_USTEPS,
    ENCODER_COUNTS_PER_REV,
    HALF_NORMAL_MEDIAN,
    IDEAL_DRIVE,
    USTEPS_PER_DEG,
    VMAX_LIMIT,
    VMAX_PER_DPS,
    ClosedLoop,
    DriveParams,
    VelocityEstimator,
)

#: Motor degrees per full step: 200 full steps a turn, the unit of MOVESTEPS
#: (firmware; C++ API).
FULL_STEP_DEG = 1.8
#: One electrical period of a 200-step hybrid stepper: the field laps a
#: slipping rotor once every four full steps (a pole slip).
POLE_PITCH_DEG = 4 * FULL_STEP_DEG
#: The fastest the TMC5130 issues steps (VMAX 0x7FFE00 at the library's
#: conversion), motor deg/s: about 35,200 deg/s, 586 rev/s.
CHIP_MAX_SPEED_DPS = VMAX_LIMIT / VMAX_PER_DPS
_COUNTS_PER_DEG = ENCODER_COUNTS_PER_REV / 360.0


def _pole_slips(lead_deg: float) -> int:
    """Pole slips a field leading its rotor by ``lead_deg`` has made: the first at two full steps.

    The torque of a hybrid stepper reverses once the field leads the rotor
    by half an electrical period; from there the rotor is thrown back, and
    again every further period (four full steps).
    """
    return math.floor((abs(lead_deg) + 0.5 * POLE_PITCH_DEG) / POLE_PITCH_DEG)


#: How long one draw of a following rotor's PID-error jitter holds, s.
JITTER_HOLD_S = 0.01

_RAD = math.pi / 180.0
_DEG = 180.0 / math.pi


def _load_angle_deg(needed: float, pullout: float) -> float:
    """How far a following rotor lags its field, motor degrees (signed as ``needed``).

    The torque of a hybrid stepper is the pull-out torque times the sine of
    the load angle, which reaches a quarter electrical period at one full
    step: ``asin(needed / pullout)`` of it.
    """
    if not (math.isfinite(pullout) and pullout > 0.0) or not needed:
        return 0.0
    return math.copysign(math.asin(min(1.0, abs(needed) / pullout)) / (math.pi / 2) * FULL_STEP_DEG, needed)


def _settled(
    offset_deg: float, rate_dps: float, pullout: float, h: float, n: int = 1
) -> tuple[list[float], float]:
    """A following rotor's way onto its load angle over ``n`` passes of ``h`` s.

    Returns each pass's offset from the load angle (deg) and the last rate (deg/s).

    The field holds the rotor like a spring whose stiffness at small load
    angles is the pull-out torque over a full step times π/2 (the slope of
    :func:`_load_angle_deg`'s sine at 0). Over the rotor's inertia that is a
    natural frequency of ``sqrt(pullout x π/2 / full step)``: 96 rad/s for
    j1 at 20 % current. The motion is taken as critically damped, solved
    exactly: the recordings do not resolve the rotor's own ringing, and a
    real j1 at rest after a move sits still to a few microsteps
    (``tracking_error/``, docs/model.md). Under a microstep it ends.
    """
    if not (math.isfinite(pullout) and pullout > 0.0):
        return [0.0] * n, 0.0
    a = math.sqrt(pullout * (math.pi / 2) / (FULL_STEP_DEG * _RAD))
    decay = math.exp(-a * h)
    x, v = offset_deg, rate_dps
    offsets = []
    for _ in range(n):
        if x or v:
            b = v + a * x
            y = x + b * h
            x, v = decay * y, decay * (b - a * y)
            if (abs(x) + abs(v) / a) * USTEPS_PER_DEG < 1.0:
                x = v = 0.0
        offsets.append(x)
    return offsets, v


@runtime_checkable
class Motor(Protocol):
    """What the firmware needs from a motor, in motor degrees.

    Positions are absolute motor degrees (the firmware keeps its own encoder
    zero); velocities are deg/s.
    """

    @property
    def setpoint_deg(self) -> float:
        """The driver's position counter (XACTUAL): where moves count from.

        The chip advances it with every step it issues; the library's closed
        loop rewrites it to the encoder whenever the two differ by 15
        microsteps or more.
        """
        ...

    @property
    def position_deg(self) -> float:
        """Encoder reading."""
        ...

    @property
    def velocity_dps(self) -> float:
        """The encoder's speed estimate (what GETENCODERRPM reports, x 6)."""
        ...

    @property
    def pid_error_deg(self) -> float:
        """The library's last PID error (``getPidError()``), in motor degrees."""
        ...

    @property
    def pid_jitter_usteps(self) -> float:
        """The following rotor's jitter as the stall detector sees it, 1/256 microsteps (0: none)."""
        ...

    def command(self, velocity_dps: float, torque_fraction: float) -> None:
        """Set the step rate (deg/s) and the available torque (0-1 of full current)."""
        ...

    def hold_here(self) -> None:
        """Stop issuing steps where the rotor is (hard stop, zero PID error)."""
        ...

    def advance(self, dt: float) -> None:
        """Advance the model by ``dt`` seconds (no-op where physics runs elsewhere)."""
        ...


class KinematicStepper:
    """A stepper motor and its uStepper S32 drive, without a rigid-body simulation.

    The rotor follows the field while the acceleration asked of it (plus
    friction and load) stays within the pull-out acceleration the current
    allows at its speed (:class:`~bioscara_gym.hardware.drive.DriveParams`);
    it then lags the field by its load angle. Beyond that it slips: it loses
    steps, the asynchronous torque and friction decide its speed, every pole
    slip knocks it back (a spike of PID error), and it locks back onto the
    field once their speeds come within the pull-in range. End stops and a
    blocked rotor hold it where it is while the field runs on, which is how
    homing finds the end stop. The default drive is ideal: it never slips
    and its PID error has no jitter.

    Args:
        position_deg: Initial rotor position, absolute motor degrees.
        lower_stop_deg: Lower end stop (motor degrees), ``-inf`` for none.
        upper_stop_deg: Upper end stop (motor degrees), ``inf`` for none.
        drive: The motor's torque and jitter (default: ideal).
        load_accel: Constant external load (e.g. gravity through the
            transmission) as an acceleration of the rotor, motor rad/s², signed.
        max_speed_dps: Steps are never issued faster than this (default: the
            chip's own limit, about 35,200 deg/s).
        rng: Random numbers for the PID error's jitter (seeded by the caller;
            default seed 0).
    """

    def __init__(
        self,
        position_deg: float = 0.0,
        lower_stop_deg: float = -math.inf,
        upper_stop_deg: float = math.inf,
        drive: DriveParams = IDEAL_DRIVE,
        load_accel: float = 0.0,
        max_speed_dps: float = CHIP_MAX_SPEED_DPS,
        rng: np.random.Generator | None = None,
    ) -> None:
        """Create the motor at rest at ``position_deg``."""
        if lower_stop_deg >= upper_stop_deg:
            raise ValueError(f"end stops: lower {lower_stop_deg} must be below upper {upper_stop_deg}")
        if not max_speed_dps > 0:
            raise ValueError(f"max_speed_dps={max_speed_dps!r} must be > 0")
        self.lower_stop_deg = lower_stop_deg
        self.upper_stop_deg = upper_stop_deg
        self.drive = drive
        self.load_accel = float(load_accel)
        self.max_speed_dps = max_speed_dps
        self.rng = rng if rng is not None else np.random.default_rng(0)
        self.blocked = False  # tests set it to hold the rotor (an obstacle)
        self._held = False  # a physics engine holds it (hold_rotor)
        #: Counters of what the motor did (never reset by the model): times it
        #: lost its field, pole slips, times it locked back on.
        self.lost_sync = 0
        self.pole_slips = 0
        self.resyncs = 0
        #: The largest share of the pull-out torque the field's motion has asked
        #: for so far (acceleration, friction and load over the pull-out at the
        #: field's speed; above 1 the rotor cannot follow): how close a run came
        #: to losing steps, or how far past it (never reset by the model; a
        #: caller may set it to 0 to start a new count).
        self.peak_demand = 0.0
        self._position = float(position_deg)
        self._field = float(position_deg)
        self._rotor_dps = 0.0
        self._command_dps = 0.0
        self._torque_fraction = 0.0
        self._accel_rad_s2 = 0.0  # the field's acceleration over the current tick
        self._accel_left_s = 0.0
        self._falling = False  # the step rate came down on the last change (the jitter differs)
        self._lag_deg = 0.0
        # The following rotor's way onto its load angle (its inertia on the
        # field's spring, critically damped): its place minus field-minus-lag,
        # deg, and that offset's rate, deg/s.
        self._settle_deg = 0.0
        self._settle_dps = 0.0
        self._synced = True
        self._slip_deg = 0.0  # field minus rotor while slipping
        # The rotor's swing about its mean path after a pole slip (a damped
        # oscillation the encoder sees): offset, deg, and its rate, deg/s.
        self._swing_deg = 0.0
        self._swing_dps = 0.0
        self._loop = ClosedLoop(self._position)
        self._estimator = VelocityEstimator()
        self._estimator.reset(self._position * _COUNTS_PER_DEG)
        self._pid_error = 0.0
        self._jitter_z = 0.0  # the jitter's current draw (standard normal) and its age, s
        self._jitter_age = JITTER_HOLD_S
        self._jitter = 0.0

    # ---------------------------------------------------------------- readings
    @property
    def setpoint_deg(self) -> float:
        """The driver's position counter (XACTUAL), absolute motor degrees."""
        return self._loop.xactual_deg

    @property
    def field_deg(self) -> float:
        """Where the field is: every step the chip issued, absolute motor degrees."""
        return self._field

    @property
    def position_deg(self) -> float:
        """Encoder (rotor, its swing after a pole slip included), absolute motor degrees."""
        return self._position + self._swing_deg

    @property
    def swing_deg(self) -> float:
        """The rotor's swing after a pole slip, deg: how far the encoder reads from its mean place."""
        return self._swing_deg

    @property
    def field_velocity_dps(self) -> float:
        """The chip's step rate, deg/s."""
        return self._command_dps

    @property
    def rotor_velocity_dps(self) -> float:
        """The rotor's true speed, deg/s."""
        return self._rotor_dps

    @property
    def velocity_dps(self) -> float:
        """The encoder's speed estimate, deg/s (lags the rotor by about 50 ms)."""
        return self._estimator.velocity_dps

    @property
    def pid_error_deg(self) -> float:
        """The library's last PID error, motor degrees."""
        return self._pid_error / USTEPS_PER_DEG

    @property
    def pid_jitter_usteps(self) -> float:
        """The following rotor's PID-error jitter as the stall detector reads it, 1/256 microsteps.

        Fitted to the stall detector's own samples (``high_speed_stall_test/``:
        10 ms passes, 20 % current, j3 and j4 ramping); the firmware's stall
        detector reads the larger of it and :attr:`pid_error_deg`. Not part
        of the error itself: the homing's polls do not see it. At homing
        speeds those samples reach 5.5 times their median (33-45 microsteps)
        once in a thousand, above the arm's homing thresholds (25-50), yet the
        real arm homes with them: a slowly turning rotor at homing current
        jitters less than the recordings show, by an amount they do not tell.
        """
        return self._jitter

    @property
    def synced(self) -> bool:
        """Whether the rotor follows its field (False: it slips, losing steps)."""
        return self._synced

    @property
    def torque_fraction(self) -> float:
        """Available torque as a fraction of full current."""
        return self._torque_fraction

    @property
    def held(self) -> bool:
        """Whether something outside holds the rotor (:meth:`hold_rotor`)."""
        return self._held

    def hold_rotor(self, position_deg: float) -> None:
        """Something outside (an end stop, an obstacle in a physics engine) holds the rotor here.

        A rotor that followed its field loses it; until :meth:`release_rotor`,
        the rotor stays where it is put while the field runs on (pole slips).
        """
        self._position = float(position_deg)
        self._rotor_dps = 0.0
        self._settle_deg = self._settle_dps = 0.0
        if self._synced:
            self.lost_sync += 1
            self._synced = False
            self._slip_deg = self._field - self._position
        self._held = True

    def release_rotor(self) -> None:
        """Nothing holds the rotor any more: it moves under its own torque (and may lock on again)."""
        self._held = False

    #: State added to the model since state files were first saved, with the
    #: value that means what such a file meant (a rotor on its load angle):
    #: a file without them restores as that.
    LATER_STATE: dict[str, float] = {"_settle_deg": 0.0, "_settle_dps": 0.0}

    def snapshot(self) -> dict[str, object]:
        """The model's state, the random generator's included (not the drive's parameters: configuration)."""
        # peak_demand is a reading for the caller (validation), not the motor's state:
        # state files saved before it existed still restore.
        skip = ("rng", "drive", "_loop", "_estimator", "peak_demand")
        state = {k: v for k, v in vars(self).items() if k not in skip}
        state["_loop"] = (self._loop.xactual_deg, self._loop.error)
        est = self._estimator
        state["_estimator"] = (est._pos_est, est._vel_est, est._vel_int)
        state["rng"] = self.rng.bit_generator.state
        return state

    def restore(self, state: dict[str, object]) -> None:
        """Return to a :meth:`snapshot`."""
        for key, value in state.items():
            if key == "_loop":
                self._loop.xactual_deg, self._loop.error = value  # type: ignore[misc]
            elif key == "_estimator":
                est = self._estimator
                est._pos_est, est._vel_est, est._vel_int = value  # type: ignore[misc]
            elif key == "rng":
                self.rng.bit_generator.state = value  # type: ignore[assignment]
            else:
                setattr(self, key, value)

    # ---------------------------------------------------------------- commands
    def command(self, velocity_dps: float, torque_fraction: float) -> None:
        """Set the step rate (deg/s) and available torque (0-1) from the next step on."""
        velocity_dps = max(-self.max_speed_dps, min(self.max_speed_dps, velocity_dps))
        if velocity_dps != self._command_dps:
            # The firmware's ramp changes the rate once a 10 ms tick.
            self._accel_rad_s2 = (velocity_dps - self._command_dps) * _RAD / 0.01
            self._accel_left_s = 0.01
            self._falling = abs(velocity_dps) < abs(self._command_dps)
        elif self._accel_left_s <= 0.0:
            self._falling = False
        self._command_dps = velocity_dps
        self._torque_fraction = torque_fraction

    def hold_here(self) -> None:
        """Stop hard: the field, the counter and the step rate onto the rotor (released, following).

        The field at its full strength holds the rotor where the encoder
        reads it: a swing after a pole slip ends there.
        """
        self._position = self._clamp(self._position + self._swing_deg)
        self._swing_deg = self._swing_dps = 0.0
        self._field = self._position
        self._loop.xactual_deg = self._position
        self._command_dps = 0.0
        self._accel_rad_s2 = 0.0
        self._accel_left_s = 0.0
        self._lag_deg = self._settle_deg = self._settle_dps = 0.0
        self._rotor_dps = 0.0
        self._synced = True
        self._held = False
        self._slip_deg = 0.0
        self._pid_error = 0.0

    def turn_to(self, position_deg: float, dt: float) -> None:
        """Unpowered, the load turned the rotor to ``position_deg`` over ``dt`` s (momentum, a hand).

        No field holds it, so it goes where the link takes it, and the
        encoder's speed estimate sees it pass by pass (the closed loop's 1 ms
        period): a coasting joint reads its speed, as the real encoder does.
        """
        target = self._clamp(float(position_deg))
        start = self._position + self._swing_deg
        n = max(1, round(dt / CLOSED_LOOP_PERIOD_S)) if dt > 0.0 else 0
        for k in range(1, n + 1):
            self._estimator.update((start + (target - start) * k / n) * _COUNTS_PER_DEG)
        self._rotor_dps = (target - start) / dt if n else 0.0
        self._position = self._field = self._loop.xactual_deg = target
        self._swing_deg = self._swing_dps = 0.0
        self._lag_deg = self._settle_deg = self._settle_dps = 0.0
        self._synced = True
        self._pid_error = 0.0

    def place(self, position_deg: float) -> None:
        """Put the rotor at ``position_deg`` by hand, at rest (the operator moves a disabled joint)."""
        self._swing_deg = self._swing_dps = 0.0
        self._position = self._clamp(float(position_deg))
        self.hold_here()
        self._estimator.reset(self._position * _COUNTS_PER_DEG)

    def advance(self, dt: float) -> None:
        """Run the drive and the rotor for ``dt`` seconds in 1 ms closed-loop passes."""
        n = max(1, round(dt / CLOSED_LOOP_PERIOD_S))
        h = dt / n
        if not self._follow_passes(n, h):
            for _ in range(n):
                self._pass(h)
        self._sample_jitter(dt)

    def _follow_passes(self, n: int, h: float) -> bool:
        """``n`` passes at once, if the rotor follows throughout (the common case; the same result).

        At a constant step rate the load angle is constant; the rotor takes
        up a change of it over its settling (:func:`_settled`, pass by pass
        here), and the closed loop sees each pass's place. A rotor whose
        settling would take it back against the field waits, as in
        :meth:`_follow`. Returns False (nothing done) when anything else may
        happen: a slip, a stop, a pole slip's swing, an acceleration that
        ends mid-way.
        """
        if not self._synced or self._swing_deg or self._swing_dps or self.blocked or self._held:
            return False
        if self._torque_fraction <= 0.0:
            return False
        dt = n * h
        left = self._accel_left_s
        if left <= 0.0:
            accel = 0.0
        elif left >= dt - 1e-12:
            accel = self._accel_rad_s2
        else:
            return False
        v = self._command_dps
        needed = self._needed(v, accel)
        pullout = self.drive.pullout(self._torque_fraction, v * _RAD)
        if abs(needed) > pullout or self._at_stop(v):
            return False
        lag = _load_angle_deg(needed, pullout)
        x, xd = self._settle_deg + lag - self._lag_deg, self._settle_dps
        # The settling's constants, as _settled has them (none: no settling).
        a = math.sqrt(pullout * (math.pi / 2) / (FULL_STEP_DEG * _RAD)) if math.isfinite(pullout) else 0.0
        decay = math.exp(-a * h)
        step = v * h
        field = self._field
        before = self._position
        lower, upper = self.lower_stop_deg, self.upper_stop_deg
        # The closed loop over the passes, kept local until every place is
        # known to be a following rotor's.
        loop = self._loop
        xactual = loop.xactual_deg
        error = loop.error
        counts = []
        for _ in range(n):
            if not a:
                x = xd = 0.0
            elif x or xd:
                b = xd + a * x
                y = x + b * h
                x, xd = decay * y, decay * (b - a * y)
                if (abs(x) + abs(xd) / a) * USTEPS_PER_DEG < 1.0:
                    x = xd = 0.0
            field += step
            place = field - lag + x
            if place < lower or place > upper:
                return False  # at a stop: the passes one by one hold it there
            if v * (place - before) < 0.0:
                # It waits (stiction) until the field has pulled that far ahead.
                x, xd = before - (field - lag), 0.0
                place = before
            before = place
            xactual += step
            error = (xactual - place) * USTEPS_PER_DEG
            if abs(error) >= CONTROL_THRESHOLD_USTEPS:
                xactual = place
            counts.append(place * _COUNTS_PER_DEG)
        self._demand(needed, pullout)
        self._estimator.update_many(counts)
        loop.xactual_deg = xactual
        loop.error = self._pid_error = error
        self._field = field
        self._position = before
        self._settle_deg, self._settle_dps = x, xd
        self._rotor_dps = v
        self._lag_deg = lag
        if left > 0.0:
            self._accel_left_s = left - dt
        return True

    # ---------------------------------------------------------------- internals
    def _pass(self, h: float) -> None:
        """One closed-loop period: field, rotor, PID error, speed estimate."""
        if self._torque_fraction <= 0.0:
            # Unpowered: the rotor stays where it is; the chip's steps go nowhere.
            self._position = self._clamp(self._position + self._swing_deg)
            self._swing_deg = self._swing_dps = 0.0
            self._field = self._loop.xactual_deg = self._position
            self._lag_deg = self._settle_deg = self._settle_dps = 0.0
            self._rotor_dps = 0.0
            self._synced = True
            self._pid_error = 0.0
            self._estimator.update(self._position * _COUNTS_PER_DEG)
            return
        accel = 0.0
        if self._accel_left_s > 0.0:
            accel = self._accel_rad_s2
            self._accel_left_s -= h
        v_field = self._command_dps
        advance = v_field * h
        self._field += advance
        if not (self.blocked or self._held):
            pullout = self.drive.pullout(self._torque_fraction, v_field * _RAD)
            self._demand(self._needed(v_field, accel), pullout)
        if self._synced:
            self._follow(v_field, accel, h)
        else:
            self._slip(v_field, accel, h)
        if self._swing_deg or self._swing_dps:
            self._swing(h)
        encoder = self.position_deg
        self._pid_error = self._loop.step(advance, encoder)
        self._estimator.update(encoder * _COUNTS_PER_DEG)

    def _swing(self, h: float) -> None:
        """Advance the swing after a pole slip by ``h`` s: a damped oscillation, solved exactly.

        It decays with ``kick_time_s`` at period ``kick_period_s``; once it
        is under a microstep it ends (the mean path is the rotor's place).
        """
        drive = self.drive
        x, v = self._swing_deg, self._swing_dps
        if drive.kick_time_s <= 0.0:
            self._swing_deg = self._swing_dps = 0.0
            return
        a = 1.0 / drive.kick_time_s
        w = 2.0 * math.pi / drive.kick_period_s if drive.kick_period_s > 0 else 0.0
        decay = math.exp(-a * h)
        if w > 0.0:
            c, s = math.cos(w * h), math.sin(w * h)
            b = (v + a * x) / w
            x_new = decay * (x * c + b * s)
            v_new = decay * ((-a * x + w * b) * c - (a * b + w * x) * s)
            amplitude = math.hypot(x_new, (v_new + a * x_new) / w)
        else:  # critically damped: x(t) = (x + (v + a x) t) e^{-at}
            b = v + a * x
            x_new = decay * (x + b * h)
            v_new = decay * (b - a * (x + b * h))
            amplitude = abs(x_new) + abs(v_new) * drive.kick_time_s
        if amplitude * USTEPS_PER_DEG < 1.0:
            x_new = v_new = 0.0
        self._swing_deg, self._swing_dps = x_new, v_new

    def _demand(self, needed: float, pullout: float) -> None:
        """Keep the largest share of the pull-out torque asked for (:attr:`peak_demand`)."""
        if math.isfinite(pullout) and pullout > 0.0:
            self.peak_demand = max(self.peak_demand, abs(needed) / pullout)

    def _needed(self, v_dps: float, accel: float) -> float:
        """Acceleration the motor must supply to move the rotor so, rad/s²."""
        return accel + self.drive.friction(v_dps * _RAD) - self.load_accel

    def _follow(self, v_field: float, accel: float, h: float) -> None:
        drive = self.drive
        omega = v_field * _RAD
        needed = self._needed(v_field, accel)
        pullout = drive.pullout(self._torque_fraction, omega)
        held = (v_field != 0.0 and (self.blocked or self._held)) or self._at_stop(v_field)
        if held or abs(needed) > pullout:
            self.lost_sync += 1
            self._synced = False
            self._settle_deg = self._settle_dps = 0.0
            self._slip_deg = self._field - self._position
            if held:
                self._rotor_dps = 0.0
            self._slip(v_field, accel, h)
            return
        lag = _load_angle_deg(needed, pullout)
        # The rotor does not jump to a new load angle: its inertia on the
        # field's spring takes it there (critically damped), so a short move
        # ends before the full lag builds up.
        x = self._settle_deg + lag - self._lag_deg
        (self._settle_deg,), self._settle_dps = _settled(x, self._settle_dps, pullout, h)
        self._lag_deg = lag
        place = self._field - lag
        # A rotor that starts against friction does not jump back by its load
        # angle: it waits (stiction) until the field has pulled that far ahead.
        target = self._clamp(place + self._settle_deg)
        if v_field * (target - self._position) < 0.0:
            target = self._position
        if target != place + self._settle_deg:
            self._settle_deg, self._settle_dps = target - place, 0.0
        self._position = target
        self._rotor_dps = v_field

    def _slip(self, v_field: float, accel: float, h: float) -> None:
        drive = self.drive
        omega = self._rotor_dps * _RAD
        if not (self.blocked or self._held):
            direction = v_field - self._rotor_dps
            push = drive.slip_push(self._torque_fraction, omega, direction * _RAD)
            drive_acc = math.copysign(push, direction) if direction and math.isfinite(push) else 0.0
            outer = drive_acc + self.load_accel
            if omega == 0.0:
                # Stiction: it starts only once the push beats dry friction.
                acc = (
                    0.0
                    if abs(outer) <= drive.friction_coulomb
                    else outer - math.copysign(drive.friction_coulomb, outer)
                )
                new = acc * h
            else:
                new = omega + (outer - drive.friction(omega)) * h
                if (new > 0.0) != (omega > 0.0) and abs(outer) <= drive.friction_coulomb:
                    new = 0.0  # friction stops it; it does not reverse it
            self._position = self._clamp(self._position + 0.5 * (omega + new) * _DEG * h)
            self._rotor_dps = new * _DEG
            if self._position in (self.lower_stop_deg, self.upper_stop_deg):
                self._rotor_dps = 0.0
        else:
            self._rotor_dps = 0.0
        before = self._slip_deg
        self._slip_deg = self._field - self._position
        laps = _pole_slips(self._slip_deg) - _pole_slips(before)
        if laps > 0:
            # The field passed a pole the rotor did not: it throws the rotor
            # back, away from the field (kick_accel).
            self.pole_slips += laps
            self._kick(self._kick_dps(v_field))
        if self._can_lock(v_field, accel):
            self.resyncs += 1
            self._synced = True
            self._field = self._position
            self._rotor_dps = v_field
            self._slip_deg = 0.0
            self._lag_deg = 0.0  # on the field: it takes up its load angle from here

    def _kick(self, kick_dps: float) -> None:
        """Throw the rotor back from the field by ``kick_dps``.

        Behind a self-locking transmission, free to move, the kick first
        comes off the joint's speed towards the field (it does not reverse
        it: the screw's friction holds); whatever is left, and every kick
        elsewhere, swings the rotor about its path.
        """
        away = -math.copysign(1.0, self._slip_deg)
        if self.drive.self_locking and not (self.blocked or self._held) and self._rotor_dps * away < 0.0:
            taken = min(kick_dps, abs(self._rotor_dps))
            self._rotor_dps += away * taken
            kick_dps -= taken
        self._swing_dps += away * kick_dps

    def _kick_dps(self, v_field: float) -> float:
        """The speed one pole slip throws the rotor back with, deg/s (``DriveParams.kick_accel``).

        The reversed torque acts while the lead crosses half an electrical
        period (two full steps) at the slip speed: its mean, 2/π of the
        peak, over that time; at most the speed gained falling through the
        two steps under it.
        """
        accel = self.drive.kick_accel * self._torque_fraction * (2.0 / math.pi)  # mean, rad/s²
        half_period = 0.5 * POLE_PITCH_DEG * _RAD
        slip = abs(v_field - self._rotor_dps) * _RAD
        falling = math.sqrt(2.0 * accel * half_period)
        kick = falling if slip * falling <= accel * half_period else accel * half_period / slip
        return kick * _DEG

    def _can_lock(self, v_field: float, accel: float) -> bool:
        """Whether the slipping rotor locks back onto the field now.

        Its speed must be within the pull-in range of the field's, and the
        field must not ask more of it than the pull-out torque allows.
        """
        if self.blocked or self._held or self._at_stop(v_field):
            return False
        drive = self.drive
        if abs(v_field - self._rotor_dps) * _RAD > drive.pullin_speed and not (
            v_field == 0.0 and self._rotor_dps == 0.0
        ):
            return False
        return abs(self._needed(v_field, accel)) <= drive.pullout(self._torque_fraction, v_field * _RAD)

    def _at_stop(self, v_field: float) -> bool:
        """Whether an end stop holds the rotor against the field's direction."""
        return (v_field > 0 and self._position >= self.upper_stop_deg) or (
            v_field < 0 and self._position <= self.lower_stop_deg
        )

    def _clamp(self, position: float) -> float:
        return min(max(position, self.lower_stop_deg), self.upper_stop_deg)

    def _sample_jitter(self, dt: float) -> None:
        """Draw the following rotor's jitter (:attr:`pid_jitter_usteps`).

        A new draw every :data:`JITTER_HOLD_S` (the recordings' sample time:
        nothing faster is known), scaled by the median at the current speed.
        """
        noise = self.drive.noise
        self._jitter = 0.0
        if noise is None or not self._synced or self._torque_fraction <= 0.0:
            return
        self._jitter_age += dt
        if self._jitter_age >= JITTER_HOLD_S - 1e-9:
            self._jitter_age = 0.0
            self._jitter_z = float(self.rng.standard_normal())
        speed = self._command_dps * _RAD
        median = noise.median(speed, self._falling) * self.drive.noise_scale
        self._jitter = float(round(abs(median / HALF_NORMAL_MEDIAN * self._jitter_z)))
