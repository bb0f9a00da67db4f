"""The host's watch for a stepper whose rotor lost its field: what the firmware's stall detection misses.

The firmware's stall detection reads how much the rotor's lag grew in the
last millisecond and drops any rise of more than 100 in one pass
(docs/firmware.md, "Stall detection"). A rotor that loses its field at speed
rises past that at once: the field runs on while the rotor stands, and the
flag never comes. The simulated j1 did this in a PickPlace episode, 1,282
pole slips over 5.5 s with no STALL flag, and the real firmware has the same
filter (docs/firmware.md: j1 run into an obstacle at 0.8 or 1 rad/s is never
flagged).

The host knows what it sent and how the driver chip ramps it, so it knows how
fast the field turns; the encoder says how fast the rotor turns. The two
detectors split the speeds between them: the firmware's sees a blocked rotor
whose lag grows by less than 100 a pass, the field turning slower than
:data:`FIELD_LOST_MOTOR_RAD_S` (12.3 rad/s at the motor); a rotor behind its
field by more than that for :data:`FIELD_LOST_HOLD_S` is what it cannot see,
and :class:`FieldWatch` raises :class:`FieldLostError`. The arm then stops
every joint, as it does on a stall.

The field is predicted as the chip makes it (docs/firmware.md, "Motion"): a
SETRPM ramps the set speed to the command at the max acceleration; a
MOVETOANGLE runs a trapezoid to the target at the max velocity and
acceleration, braking so that it stops there. The configuration refuses
limits the chip would cut (``JointConfig``), so the configured limits are
the chip's.

Checked on the real arm's recordings (``tests/test_field_watch.py``): of
the 22 ``maxAccel/`` runs, it stops the two whose rotor lost its field for
good (``j1_3``, ``j2_2``: 25 and 69 rad/s behind at the motor when stopped)
and none of the others (at most 2.1 rad/s behind; ``j1_2``, which slipped
and locked on again, 3.5).
"""

from __future__ import annotations

import math

from bioscara_gym.hardware.drive import ESTIMATOR_KI, ESTIMATOR_KP
from bioscara_gym.hardware.errors import StalledError

#: A rotor behind its field by more than this, motor rad/s, is not following:
#: where the firmware's stall detection goes blind. Its spike filter drops a
#: rise of more than 100 (1/256 microsteps, 51,200 a turn) in one 1 ms pass
#: of the library's closed loop, and a blocked rotor's error rises by the
#: field's travel in that millisecond: 100 / 51,200 turns a millisecond is
#: 12.27 rad/s (j1 0.35 rad/s, j2 7.8 mm/s, j3 0.51 rad/s, j4 1.0 rad/s).
FIELD_LOST_MOTOR_RAD_S = 100 / 51_200 * 2 * math.pi / 0.001
#: ... for this long (10 firmware loop passes): one slow reading is not a loss.
FIELD_LOST_HOLD_S = 0.1
#: The chip ramps continuously; the watch steps its ramp at the firmware's loop
#: period, which is off by at most the max acceleration times this (j2: 2 mm/s).
RAMP_STEP_S = 0.01
#: Readings further apart than this say nothing of what the chip did between
#: them (every ramp of the arm's limits ends within 0.5 s): the prediction
#: starts over at the rotor's speed.
MAX_GAP_S = 1.0
#: The encoder's speed estimate (``getRPM()``, a PI tracking loop) trails a
#: speed that changes at a constant rate by KP/KI = 63 ms (``drive.VelocityEstimator``):
#: j3 accelerating at 14 rad/s² reads 0.88 rad/s slow, more than the bound.
ESTIMATE_LAG_S = ESTIMATOR_KP / ESTIMATOR_KI


class FieldLostError(StalledError):
    """The host's field watch: the rotor stayed behind what the driver chip commanded.

    A stall the firmware did not flag (its STALL flag is not set); handled as
    one: the arm stops every joint. Attributes as :class:`StalledError`, plus
    the predicted field speed and the measured rotor speed (joint units).
    """

    def __init__(self, message: str, *, joint: str, field: float, rotor: float) -> None:
        """Create the error for ``joint`` with the speeds that tripped it."""
        super().__init__(message, joint=joint)
        self.field = field
        self.rotor = rotor


class FieldWatch:
    """One joint's watch: the field's speed predicted from the commands, against the encoder's.

    :meth:`start` it where the chip's field is known, feed it every reading
    while the joint is commanded (:meth:`velocity` or :meth:`position`), and
    :meth:`stop` it while it is not.

    The prediction runs open loop, so it carries a slack: what it may be off
    by. A start at the encoder's reading may be off by the estimate's lag at
    full acceleration; each turn of the ramp (the field starts or stops
    accelerating, or reverses) by one 10 ms step of the acceleration, since
    a command reaches the chip's ramp up to a firmware pass later than the
    watch assumes (the emulated firmware ramps in 10 ms passes). So commands
    that keep the ramp turning widen the watch's bound turn by turn (a
    policy switching j4 every 5 cycles at 100 Hz drifted 2.4 rad/s from the
    emulated chip in 1.5 s). Once the field has held its speed longer than
    the slack takes to ramp away, the chip holds the same speed and the
    slack is 0 again.

    Args:
        joint: The joint's name (for the error).
        reduction: Motor rad per joint unit (signed, not 0; the magnitude counts).
        max_velocity: The joint's max velocity, rad/s or m/s (a position move's top speed), > 0.
        max_acceleration: The joint's max acceleration, rad/s² or m/s² (the chip's ramp), > 0.
        unit: The speed unit, for the message.

    Attributes:
        bound: The shortfall that counts as behind, joint units
            (:data:`FIELD_LOST_MOTOR_RAD_S` at the motor).
        slack: What the prediction may be off by now, added to the bound.

    Raises:
        ValueError: A reduction of 0 or a limit that is not positive and finite, naming the joint.
    """

    def __init__(
        self, joint: str, reduction: float, max_velocity: float, max_acceleration: float, unit: str = "rad/s"
    ) -> None:
        """Watch ``joint``; the first reading starts the prediction."""
        for name, value in (("max_velocity", max_velocity), ("max_acceleration", max_acceleration)):
            if not (math.isfinite(value) and value > 0):
                raise ValueError(f"{joint}: the field watch needs a {name} > 0, got {value!r}")
        if not (math.isfinite(reduction) and reduction != 0):
            raise ValueError(
                f"{joint}: the field watch needs a finite, non-zero reduction, got {reduction!r}"
            )
        self.joint = joint
        self.max_velocity = float(max_velocity)
        self.max_acceleration = float(max_acceleration)
        self.unit = unit
        self.bound = FIELD_LOST_MOTOR_RAD_S / abs(reduction)
        # The state (start() sets all of it): the field's speed now, joint units (None: not
        # predicting), what the encoder of a rotor on it reads, the position at the last
        # reading (position mode), the ramp's direction at the last step (+1, -1, 0 holding
        # its speed), how long it has held its speed, and when the rotor fell behind.
        self.field: float | None
        self._measured: float | None
        self.behind_since: float | None
        self.start(0.0, 0.0, 0.0)
        self.stop()

    def start(
        self, now: float, field: float, reading: float, position: float | None = None, *, exact: bool = True
    ) -> None:
        """Start predicting at ``now``: the field turns at ``field``, the encoder reads ``reading``.

        ``position``: where the joint is (position mode; None: taken from the
        next reading). ``exact``: the field is known (at rest after a stall,
        while disabled, or when a simulation placed the joints); otherwise it
        is the encoder's reading, which trails a ramping field by up to the
        max acceleration times :data:`ESTIMATE_LAG_S` (the slack starts there).
        The arm starts a watch when a joint is claimed (at the measured speed,
        not exact) and at rest in the other cases.
        """
        self.field, self.reading, self.time, self._measured = field, reading, now, position
        self.slack = 0.0 if exact else self.max_acceleration * ESTIMATE_LAG_S
        self._turn, self._held_s = 0, 0.0
        self.behind_since = None

    def stop(self) -> None:
        """Stop predicting until :meth:`start` (or a reading, which starts at the rotor's speed)."""
        self.field = None

    def velocity(self, now: float, command: float, rotor: float) -> None:
        """A reading in velocity mode: ``command`` was sent (SETRPM), the encoder reads ``rotor``.

        Raises:
            FieldLostError: The rotor has been behind the field too long.
            ValueError: ``command`` is not finite.
        """
        self._reading(now, None, command, rotor)

    def position(self, now: float, target: float, position: float, rotor: float) -> None:
        """A reading in position mode: ``target`` was sent (MOVETOANGLE), the joint is at ``position``.

        Raises:
            FieldLostError: The rotor has been behind the field too long.
            ValueError: ``target`` is not finite.
        """
        self._reading(now, position, target, rotor)

    def _reading(self, now: float, position: float | None, command: float, rotor: float) -> None:
        """Run the chip's ramp from the last reading to ``now``, then compare the rotor with it.

        In :data:`RAMP_STEP_S` steps: the field's speed moves toward its
        target at the max acceleration (never faster: a move that must stop
        sooner overshoots, as the chip's does). Velocity mode (``position``
        None): the target is ``command``. Position mode: the speed that
        still stops at ``command`` from the field's own position, which
        starts at where the rotor was measured at the last reading.
        """
        if not math.isfinite(command):
            raise ValueError(f"{self.joint}: the field watch was given a command of {command!r}")
        if self.field is not None and now == self.time:
            return  # no time has passed: nothing to predict
        if self.field is None or not 0.0 < now - self.time <= MAX_GAP_S:
            self.start(now, rotor, rotor, position, exact=False)
            return
        start, self._measured = self._measured, position
        if position is not None and start is not None:
            position = start
        steps = max(1, math.ceil((now - self.time) / RAMP_STEP_S - 1e-9))
        h = (now - self.time) / steps
        accel_step = self.max_acceleration * h
        decay = math.exp(-h / ESTIMATE_LAG_S)
        field, reading = self.field, self.reading
        for _ in range(steps):
            if position is None:
                target = command
            else:
                remaining = command - position
                brake = math.sqrt(2.0 * self.max_acceleration * abs(remaining))
                target = math.copysign(min(self.max_velocity, brake), remaining)
            new = min(max(target, field - accel_step), field + accel_step)
            self._account(new - field, accel_step, h)
            # The encoder's estimate of a rotor on that field: a lag of ESTIMATE_LAG_S, taken
            # exactly over the step with the field's speed changing at a constant rate.
            slope_lag = (new - field) / h * ESTIMATE_LAG_S
            reading = new - slope_lag + (reading - field + slope_lag) * decay
            if position is not None:
                position += 0.5 * (field + new) * h
            field = new
        self.field, self.reading, self.time = field, reading, now
        along = math.copysign(1.0, self.reading) * rotor  # the rotor's speed in the expected direction
        shortfall = abs(self.reading) - along
        if shortfall <= self.bound + self.slack:
            self.behind_since = None
            return
        if self.behind_since is None:
            self.behind_since = now
        elif now - self.behind_since >= FIELD_LOST_HOLD_S - 1e-9:
            held = now - self.behind_since
            raise FieldLostError(
                f"lost its field: the drive turned at {self.field:+.3g} {self.unit}, where its encoder "
                f"would read {self.reading:+.3g}, and the rotor read {rotor:+.3g} {self.unit} for "
                f"{held:.2f} s, which the firmware's stall detection does not flag at that speed",
                joint=self.joint,
                field=self.field,
                rotor=rotor,
            )

    def _account(self, change: float, accel_step: float, h: float) -> None:
        """The slack after one ramp step that changed the field's speed by ``change``."""
        turn = 0 if abs(change) < accel_step * (1.0 - 1e-9) else (1 if change > 0 else -1)
        if turn != self._turn:
            self._turn = turn
            self.slack += self.max_acceleration * RAMP_STEP_S
        if turn:
            self._held_s = 0.0
            return
        self._held_s += h
        if self._held_s >= self.slack / self.max_acceleration + RAMP_STEP_S:
            self.slack = 0.0
