"""The stepper drive behind the firmware: what the uStepper S32 does between the firmware and the rotor.

The firmware (:class:`~bioscara_gym.hardware.firmware.FirmwareCore`) calls the
uStepper S32 library; the library programs a TMC5130 driver chip and reads a
TLE5012B encoder. This module models that layer and the motor's torque
limits, in three parts (``docs/model.md``, "The drive model"):

* **The library and the chip** (facts from their public source,
  uStepper/uStepperS32): the limits the ramp generator really runs at
  (:func:`position_move_limits`, :func:`velocity_mode_acceleration`), the
  1 kHz closed-loop bookkeeping that produces the PID error the firmware's
  stall detection and homing read (:class:`ClosedLoop`), and the encoder's
  velocity estimator behind GETENCODERRPM (:class:`VelocityEstimator`).
* **The motor's torque** (:class:`DriveParams`): a hybrid stepper follows its
  field only while the torque the motion needs stays below the pull-out
  torque the current allows at that speed; beyond it the rotor slips, loses
  steps, and is driven only by a weak asynchronous torque until its speed
  comes back within the pull-in range of the field's. Every pole slip (four
  full steps of field against rotor) knocks the rotor back, which the
  encoder sees as a spike of PID error.
* **The PID error of a rotor that follows** (:class:`PidNoiseProfile`):
  jitter of rotor against field whose size depends on speed and on whether
  the joint speeds up or slows down (the real one rises between 15 and
  40 rad/s, ``high_speed_stall_test/README.md``); the sample is half-normal,
  as the real one is.

Units: motor side. Angles in motor degrees, speeds in rad/s or deg/s as
named, accelerations in motor rad/s² (a torque divided by the inertia the
motor sees, which is what the recordings identify), PID error in the
library's 1/256 microsteps (51,200 per revolution).
"""

from __future__ import annotations

import math
import struct
from bisect import bisect_right
from collections.abc import Sequence
from dataclasses import dataclass, fields, replace

__all__ = [
    "CONTROL_THRESHOLD_USTEPS",
    "ENCODER_COUNTS_PER_REV",
    "IDEAL_DRIVE",
    "USTEPS_PER_DEG",
    "ClosedLoop",
    "DriveParams",
    "PidNoiseProfile",
    "VelocityEstimator",
    "position_move_limits",
    "velocity_mode_acceleration",
    "velocity_mode_speed",
]

# ------------------------------------------------- the library and the chip
#: Microsteps per full step the library runs the TMC5130 at (``microSteps = 256``).
USTEPS_PER_FULL_STEP = 256
#: Full steps per revolution (``stepper.setup(CLOSEDLOOP, 200)`` in the firmware).
FULL_STEPS_PER_REV = 200
#: The PID error's unit per motor degree: 51,200 microsteps a turn.
USTEPS_PER_DEG = USTEPS_PER_FULL_STEP * FULL_STEPS_PER_REV / 360.0
#: Encoder counts per revolution (TLE5012B, 15 bit; ``CONVERTENCODERRAWTOANGLE``).
ENCODER_COUNTS_PER_REV = 32768
#: The closed loop rewrites the driver's position to the encoder's once the
#: two differ by this many microsteps (the firmware's ``setControlThreshold(15)``).
CONTROL_THRESHOLD_USTEPS = 15.0
#: The library's closed-loop and encoder-sampling timer: TIM4 at 84 MHz / 84,000.
CLOSED_LOOP_PERIOD_S = 0.001
#: The velocity estimator's gains (``velocityEstimator.h``: pulseFilterKP, pulseFilterKI).
ESTIMATOR_KP = 120.0
ESTIMATOR_KI = 1900.0

#: TMC5130 ramp units per motor deg/s² and deg/s, from the library's
#: conversions: steps/s² x 256 microsteps x ACCELERATIONCONVERSION 0.0220,
#: steps/s x 256 x VELOCITYCONVERSION 1.677; the firmware turns degrees into
#: steps with x 200/360 first. The chip runs the ramp in these units.
AMAX_PER_DPS2 = 200 / 360.0 * 256 * 0.0220
VMAX_PER_DPS = 200 / 360.0 * 256 * 1.677
#: Register limits the library checks (``TMC5130::setAcceleration``, ``setVelocity``): VMAX
#: saturates; AMAX is a 16-bit field, so a larger value has already wrapped.
AMAX_LIMIT = 0xFFFE
VMAX_LIMIT = 0x7FFE00
_U32_MAX = 0xFFFFFFFF


_FLOAT = struct.Struct("f")


def _f32(x: float) -> float:
    """Round to the nearest single-precision float (the library computes in float).

    Beyond float's range the result is infinite, as the C cast's is (IEEE 754):
    no warning, since a register value that large is the firmware's case too.
    (``struct`` rounds as ``np.float32`` does, at a twentieth of its cost: it
    is on every command's path.)
    """
    try:
        return _FLOAT.unpack(_FLOAT.pack(x))[0]
    except OverflowError:  # rounds to ±inf (struct refuses it)
        return math.copysign(math.inf, x)


def _to_u32(x: float) -> int:
    """C's ``(uint32_t)`` of a float on the Cortex-M4: saturating, NaN to 0 (VCVT)."""
    if math.isnan(x) or x <= 0.0:
        return 0
    return _U32_MAX if x >= _U32_MAX else int(x)


def _amax_library_units(max_acceleration_dps2: float) -> float:
    """The library's stored ``maxAcceleration``: ``|a x 200/360 x 256| x 0.0220`` in float."""
    steps = _f32(_f32(max_acceleration_dps2) * _f32(200 / 360.0))
    return _f32(abs(_f32(steps * USTEPS_PER_FULL_STEP)) * _f32(0.0220))


def _vmax_library_units(max_velocity_dps: float) -> float:
    """The library's stored ``maxVelocity``: ``|v x 200/360 x 256| x 1.677`` in float."""
    steps = _f32(_f32(max_velocity_dps) * _f32(200 / 360.0))
    return _f32(abs(_f32(steps * USTEPS_PER_FULL_STEP)) * _f32(1.677))


def velocity_mode_acceleration(max_acceleration_dps2: float) -> float:
    """Acceleration the chip ramps a SETRPM with after SETMAXACCELERATION, motor deg/s².

    ``setMaxAcceleration`` takes the magnitude and passes ``(uint32_t)`` of it
    to ``TMC5130::setAcceleration``, which stores it in a ``uint16_t`` field
    before its check against 0xFFFE: the value wraps at 16 bits (as a move's
    does), and only 0xFFFF becomes 0xFFFE.
    """
    amax = min(_to_u32(_amax_library_units(max_acceleration_dps2)) & 0xFFFF, AMAX_LIMIT)
    return amax / AMAX_PER_DPS2


def velocity_mode_speed(rpm: float) -> float:
    """Speed the chip runs a SETRPM at, motor deg/s (signed), whatever the max velocity.

    ``setRPM`` writes VMAX itself (the library's ``rpmToVelocity``, which
    agrees with VELOCITYCONVERSION to 0.04 %), saturated at 0x7FFE00; it
    does not clamp to the limit SETMAXVELOCITY set. The Cortex-M4's
    conversion makes a NaN 0 and ±inf the top speed (the firmware in the
    loop runs them so).
    """
    if math.isnan(rpm):
        return 0.0
    vmax = min(_to_u32(abs(rpm) * 6.0 * VMAX_PER_DPS), VMAX_LIMIT)
    return math.copysign(vmax / VMAX_PER_DPS, rpm)


def position_move_limits(max_velocity_dps: float, max_acceleration_dps2: float) -> tuple[float, float]:
    """Speed (deg/s) and acceleration (deg/s²) a MOVETOANGLE or MOVESTEPS ramps with.

    ``moveSteps`` writes ``(uint16_t)maxAcceleration`` to AMAX and DMAX: a
    16-bit cast, so a requested acceleration above about 20,900 deg/s²
    wraps around (10,000,000 deg/s² becomes 9,018 deg/s², as the real arm
    shows in ``settingMaxVal/accel_test_10000000_200000.csv``), and VMAX is
    ``(uint32_t)maxVelocity`` saturated at 0x7FFE00 (about 35,200 deg/s).
    """
    amax = _to_u32(_amax_library_units(max_acceleration_dps2)) & 0xFFFF
    vmax = min(_to_u32(_vmax_library_units(max_velocity_dps)), VMAX_LIMIT)
    return vmax / VMAX_PER_DPS, min(amax, AMAX_LIMIT) / AMAX_PER_DPS2


class VelocityEstimator:
    """The encoder's speed estimate behind ``getRPM()`` (uStepper S32 ``VelocityEstimator``).

    A tracking loop run at every 1 kHz encoder sample: it predicts the
    position from its speed, and a PI correction (KP 120, KI 1900) of the
    position error updates it; ``getRPM`` returns the integrator. It lags a
    speed change by about 50 ms and a constant acceleration by KP/KI = 63 ms,
    which is why the real arm's logged speed trails its position.
    """

    __slots__ = ("_pos_est", "_vel_est", "_vel_int")

    def __init__(self) -> None:
        """Start at rest at count 0."""
        self.reset()

    def reset(self, counts: float = 0.0) -> None:
        """Zero the estimate at ``counts`` (``encoder.setHome()`` resets it too)."""
        self._pos_est = counts
        self._vel_est = 0.0
        self._vel_int = 0.0

    def update(self, counts: float) -> None:
        """One 1 kHz iteration with the encoder's count."""
        self.update_many((counts,))

    def update_many(self, counts: Sequence[float]) -> None:
        """One 1 kHz iteration per count, in order."""
        t = CLOSED_LOOP_PERIOD_S
        pos, vel, integral = self._pos_est, self._vel_est, self._vel_int
        for count in counts:
            pos += vel * t
            error = count - pos
            integral += error * ESTIMATOR_KI * t
            vel = error * ESTIMATOR_KP + integral
        self._pos_est, self._vel_est, self._vel_int = pos, vel, integral

    def shift(self, counts: float) -> None:
        """Move the estimate's position by ``counts`` (the encoder was re-zeroed)."""
        self._pos_est += counts

    @property
    def counts_per_s(self) -> float:
        """The estimate in encoder counts per second."""
        return self._vel_int

    @property
    def velocity_dps(self) -> float:
        """The estimate in motor deg/s (``getRPM() x 6``)."""
        return self._vel_int * 360.0 / ENCODER_COUNTS_PER_REV


class ClosedLoop:
    """The library's 1 kHz closed loop: the driver's position counter and the PID error.

    Each pass computes ``error = XACTUAL - encoder`` (microsteps) and, once
    ``|error| >= 15``, rewrites XACTUAL to the encoder so a position move ends
    where the encoder says (``closedLoopCallback``). ``getPidError()``
    returns the last pass's error: the change of the rotor's lag since the
    last rewrite, not the lag itself. XACTUAL is what the firmware's moves
    count from (:attr:`xactual_deg`); the field keeps the steps the chip
    issued, the rewrite does not move it.
    """

    __slots__ = ("error", "xactual_deg")

    def __init__(self, position_deg: float) -> None:
        """Start with the counter on the rotor."""
        self.xactual_deg = position_deg
        self.error = 0.0

    def step(self, advance_deg: float, encoder_deg: float) -> float:
        """One pass: the chip issued ``advance_deg`` since the last; returns the error (microsteps)."""
        self.xactual_deg += advance_deg
        error = (self.xactual_deg - encoder_deg) * USTEPS_PER_DEG
        if abs(error) >= CONTROL_THRESHOLD_USTEPS:
            self.xactual_deg = encoder_deg
        self.error = error
        return error


# ------------------------------------------------------- the motor's torque
@dataclass(frozen=True)
class PidNoiseProfile:
    """Size of the PID error of a rotor that follows its field, by speed (motor side).

    The median |PID error| (1/256 microsteps) at each speed knot, while the
    set speed rises and while it falls; linear between knots, constant
    beyond the last. A sample is half-normal with that median (the real
    error's quantiles: 10 % at 0.24x the median, 90 % at 2.5x, 99 % at 3.2x;
    a half-normal has 0.19x, 2.4x and 3.8x).

    Attributes:
        speeds_rad_s: Knots, motor rad/s, increasing from 0.
        rising: Median at each knot while the speed set point rises (or holds).
        falling: Median at each knot while it falls.
    """

    speeds_rad_s: tuple[float, ...]
    rising: tuple[float, ...]
    falling: tuple[float, ...]

    def __post_init__(self) -> None:
        """Check the knots."""
        n = len(self.speeds_rad_s)
        if n < 1 or len(self.rising) != n or len(self.falling) != n:
            raise ValueError(
                f"pid noise profile: {n} speeds, {len(self.rising)} rising and "
                f"{len(self.falling)} falling medians; the three lists must have one value a knot"
            )
        if any(b <= a for a, b in zip(self.speeds_rad_s, self.speeds_rad_s[1:], strict=False)):
            raise ValueError(f"pid noise profile: speeds {self.speeds_rad_s} must increase")
        if any(not math.isfinite(m) or m < 0 for m in (*self.rising, *self.falling)):
            raise ValueError("pid noise profile: medians must be finite and >= 0")

    def median(self, speed_rad_s: float, falling: bool) -> float:
        """Median |PID error| at motor speed ``|speed_rad_s|``.

        ``np.interp``'s rule and arithmetic, without its array set-up (it is
        asked once a tick per joint).
        """
        values = self.falling if falling else self.rising
        knots = self.speeds_rad_s
        speed = abs(speed_rad_s)
        j = bisect_right(knots, speed)
        if j == 0:
            return float(values[0])
        if j == len(knots):
            return float(values[-1])
        slope = (values[j] - values[j - 1]) / (knots[j] - knots[j - 1])
        return slope * (speed - knots[j - 1]) + values[j - 1]


#: The largest finite drive value. The fitted ones are at most some 10^4 (motor rad/s^2,
#: rad/s, 1/s); 10^308 overflowed the motor model to NaN, where ``inf`` (no limit) works.
DRIVE_VALUE_MAX = 1e9


#: Half-normal median: |N(0, sigma)| has median 0.6745 sigma.
HALF_NORMAL_MEDIAN = 0.6744897501960817


#: The pole-slip swing fitted to the real blocks (``bioscara calibrate``, last,
#: on the fitted drives; ``high_speed_stall_test/``: j4 at 20 % current held
#: at 5.7 and 25.8 motor rad/s; docs/validation.md): every drive's default.
KICK_ACCEL = 2.2e4
KICK_TIME_S = 0.042
KICK_PERIOD_S = 0.086


#: Fields of :class:`DriveParams` added after configurations were saved
#: (their default keeps the model as it was).
_ADDED_LATER = frozenset({"slip_corner", "self_locking"})


@dataclass(frozen=True)
class DriveParams:
    """A joint's motor and drive as the recordings identify them (motor side).

    Accelerations are torques divided by the inertia the motor sees (rotor
    plus load through the transmission), in motor rad/s². ``math.inf``
    pull-out means a motor that never loses a step unless it is blocked;
    ``noise=None`` a PID error without jitter (the ideal drive of the unit
    tests).

    Attributes:
        pullout_accel: Largest acceleration the motor holds its field with at
            100 % current and standstill (it scales with the current).
        corner_speed: Motor speed at which the pull-out torque has halved,
            rad/s: ``pullout / (1 + (|w| / corner_speed) ** corner_exponent)``.
        corner_exponent: How sharply the pull-out torque falls around the
            corner speed (1: the back-EMF's gentle fall; larger: a motor
            that holds its torque and then gives up within a few rad/s, as
            the real j1 and j2 do).
        friction_coulomb: Dry friction as a deceleration.
        friction_viscous: Viscous friction, 1/s (deceleration per rad/s).
        slip_fraction: The asynchronous torque of a slipping rotor, as a
            fraction of the pull-out torque at its speed, while the field
            barely outruns it.
        slip_corner: Slip speed (field minus rotor, motor rad/s) at which
            that torque has halved: ``1 / (1 + (slip / slip_corner)²)`` of
            it. A rotor the field only just laps is still dragged along; one
            it laps fast feels the torque's sign flip too often to follow
            and coasts on friction alone (``maxAccel/j1_3``: the real j1
            gained speed for 0.2 s after its first slips, then stopped
            dead while its field ran on). ``inf``: the same torque at every slip.
        pullin_speed: A slipping rotor locks back onto the field once their
            speeds differ by less than this, rad/s (ideal: at once).
        kick_accel: The field's torque over the rotor's own inertia at full
            current, rad/s²: a slipping rotor is thrown back at each pole
            slip, the load staying behind the transmission's give. The
            field's torque reverses for the half electrical period the lead
            takes to cross its last two full steps, so the kick is that
            torque's mean (2/π of it) over that time, and at most the speed
            it gains falling through those two steps: slow slips kick hard
            (a blocked rotor trips homing at its first pole slip), fast ones
            barely (the torque averages out).
        kick_time_s: The thrown-back rotor swings about its mean path; the
            swing decays with this time constant, s.
        kick_period_s: Period of the swing, s. The encoder sees the swing
            (ANGLEMOVED, the speed estimate, the PID error): the firmware's
            10 ms samples of a blocked rotor's error range from a few
            microsteps to hundreds, and its measured speed drops faster
            than the rotor's mean, as the real ones do.
        self_locking: A transmission the load cannot drive back (j2's lead
            screw): a pole slip's reversed torque takes the kick off the
            joint's own speed, since the load's momentum goes into the
            screw's friction instead of carrying the rotor on, so the joint
            stops within a few pole slips (``maxAccel/j2_2``: the real j2
            froze within one 10 ms sample at 0.049 m/s while its field ran
            on). Only a kick beyond the joint's speed swings the rotor. False
            (the default): the load carries the rotor on; every kick swings.
        noise: PID error jitter of a following rotor, or None.
        noise_scale: Factor on the profile's medians (per joint).
    """

    pullout_accel: float = math.inf
    corner_speed: float = math.inf
    corner_exponent: float = 1.0
    friction_coulomb: float = 0.0
    friction_viscous: float = 0.0
    slip_fraction: float = 0.0
    slip_corner: float = math.inf
    pullin_speed: float = math.inf
    kick_accel: float = KICK_ACCEL
    kick_time_s: float = KICK_TIME_S
    kick_period_s: float = KICK_PERIOD_S
    self_locking: bool = False
    noise: PidNoiseProfile | None = None
    noise_scale: float = 1.0

    def __post_init__(self) -> None:
        """Check every value (one line naming the field)."""
        if not isinstance(self.self_locking, bool):
            raise ValueError(f"drive: self_locking={self.self_locking!r} must be true or false")
        for f in fields(self):
            if f.name in ("noise", "self_locking"):
                continue
            v = getattr(self, f.name)
            if isinstance(v, bool) or not isinstance(v, int | float) or math.isnan(v) or v < 0:
                raise ValueError(f"drive: {f.name}={v!r} must be a number >= 0")
            if DRIVE_VALUE_MAX < v < math.inf:
                raise ValueError(f"drive: {f.name}={v!r} is beyond {DRIVE_VALUE_MAX:g}; inf is no limit")
        for name in ("pullout_accel", "corner_speed", "corner_exponent", "slip_corner"):
            if getattr(self, name) == 0:
                raise ValueError(f"drive: {name}=0 must be > 0")
        if self.slip_fraction > 1:
            raise ValueError(f"drive: slip_fraction={self.slip_fraction} must be within 0-1")

    def __repr__(self) -> str:
        """The dataclass's repr, less the fields added since that still keep the model as it was.

        A console state names the configuration it was saved with by a hash of
        this text (``console.state.config_fingerprint``): a field added at the
        value that reproduces the older model leaves that hash as it was.
        """
        shown = [f"{name}={getattr(self, name)!r}" for name in self.stated_fields()]
        return f"{type(self).__name__}({', '.join(shown)})"

    def stated_fields(self) -> list[str]:
        """The fields, less those added since configurations were first saved that keep their default."""
        return [
            f.name
            for f in fields(self)
            if not (f.name in _ADDED_LATER and getattr(self, f.name) == f.default)
        ]

    def pullout(self, torque_fraction: float, speed_rad_s: float) -> float:
        """Pull-out acceleration at ``torque_fraction`` of full current and motor speed, rad/s²."""
        if math.isinf(self.pullout_accel):
            return math.inf
        ratio = abs(speed_rad_s) / self.corner_speed
        return self.pullout_accel * torque_fraction / (1.0 + ratio**self.corner_exponent)

    def slip_push(self, torque_fraction: float, speed_rad_s: float, slip_rad_s: float) -> float:
        """Torque on a slipping rotor at a motor speed and slip speed (field minus rotor), rad/s² (>= 0)."""
        ratio = abs(slip_rad_s) / self.slip_corner
        return self.slip_fraction * self.pullout(torque_fraction, speed_rad_s) / (1.0 + ratio * ratio)

    def friction(self, speed_rad_s: float) -> float:
        """Friction deceleration at a motor speed (signed against the motion), rad/s²."""
        if speed_rad_s == 0.0:
            return 0.0
        return math.copysign(self.friction_coulomb, speed_rad_s) + self.friction_viscous * speed_rad_s

    def with_values(self, **values: float) -> DriveParams:
        """A copy with some fields replaced (the calibration's step)."""
        return replace(self, **values)


#: A drive that never loses a step and shows no jitter (a blocked rotor still slips poles).
IDEAL_DRIVE = DriveParams()


# ------------------------------------------------------- configuration file
#: The fields of a joint's ``drive:`` block (everything but the shared noise profile).
DRIVE_FIELDS = tuple(f.name for f in fields(DriveParams) if f.name != "noise")


def noise_from_dict(data: object) -> PidNoiseProfile:
    """The top-level ``pid_noise:`` block of a configuration file.

    Raises:
        ValueError: Not a mapping of ``speeds_rad_s``, ``rising`` and ``falling`` lists.
    """
    if not isinstance(data, dict) or set(data) != {"speeds_rad_s", "rising", "falling"}:
        raise ValueError("pid_noise must be a mapping of exactly speeds_rad_s, rising and falling (lists)")
    try:
        values = {k: tuple(float(x) for x in data[k]) for k in data}
    except (TypeError, ValueError) as e:
        raise ValueError(f"pid_noise: every value must be a number ({e})") from e
    return PidNoiseProfile(**values)


def noise_to_dict(noise: PidNoiseProfile) -> dict[str, list[float]]:
    """Plain data of a profile (see :func:`noise_from_dict`)."""
    return {
        "speeds_rad_s": list(noise.speeds_rad_s),
        "rising": list(noise.rising),
        "falling": list(noise.falling),
    }


def drive_from_dict(data: object, noise: PidNoiseProfile | None) -> DriveParams:
    """A joint's ``drive:`` block, with the arm's shared PID-error profile.

    Raises:
        ValueError: Not a mapping, an unknown or non-numeric field (one line naming it).
    """
    if not isinstance(data, dict):
        raise ValueError(f"drive must be a mapping of {', '.join(DRIVE_FIELDS)}")
    for key in data:
        if key not in DRIVE_FIELDS:
            raise ValueError(f"drive: unknown field {key!r}; allowed: {', '.join(DRIVE_FIELDS)}")
    values: dict[str, float] = {}
    for key, value in data.items():
        if value == ".inf" or (isinstance(value, str) and value.strip().lower() in ("inf", ".inf")):
            value = math.inf
        values[key] = value
    return DriveParams(**values, noise=noise)


def drive_to_dict(drive: DriveParams) -> dict[str, float | bool]:
    """Plain data of a joint's drive (the shared noise profile left out).

    A field added since configurations were first saved is left out while
    it keeps its default, as in ``repr``: a file written here then loads in
    a version without that field, and means the same there.
    """
    return {k: getattr(drive, k) for k in drive.stated_fields() if k in DRIVE_FIELDS}
