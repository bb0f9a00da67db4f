"""The arm's field watch (``hardware/field_watch.py``): a rotor left behind its field, judged on the real arm.

The firmware's stall detection cannot see a rotor blocked while its field
turns faster than 100 microsteps a millisecond (docs/firmware.md, "the spike
filter's blind spot"); the watch compares what the host commanded, ramped as
the driver chip ramps it, with the encoder's speed.
"""

from __future__ import annotations

import math

import numpy as np
import pytest

from bioscara_gym.hardware.arm import Arm
from bioscara_gym.hardware.config import load_config
from bioscara_gym.hardware.drive import velocity_mode_acceleration
from bioscara_gym.hardware.errors import StalledError
from bioscara_gym.hardware.field_watch import (
    FIELD_LOST_MOTOR_RAD_S,
    FieldLostError,
    FieldWatch,
)
from bioscara_gym.hardware.registers import Flag
from bioscara_gym.hardware.transmission import rate_to_degrees
from bioscara_gym.validation.experiments import max_accel
from bioscara_gym.validation.recordings import find_recordings

CONFIG = load_config()

# ----------------------------------------------------------- the bound


def test_the_bound_is_where_the_firmwares_spike_filter_goes_blind() -> None:
    # A rise of 100 (1/256 microsteps, 51,200 a turn) in one 1 ms pass: 12.3 rad/s at the
    # motor; docs/firmware.md gives it per joint: j1 0.35 rad/s, j2 7.8 mm/s, j3 0.51, j4 1.0.
    assert pytest.approx(12.27, abs=0.01) == FIELD_LOST_MOTOR_RAD_S
    bounds = {j.name: FieldWatch(j.name, j.reduction, 1.0, 1.0).bound for j in CONFIG.joints}
    assert bounds["j1"] == pytest.approx(0.35, abs=0.005)
    assert bounds["j2"] == pytest.approx(0.0078, abs=0.0001)
    assert bounds["j3"] == pytest.approx(0.51, abs=0.005)
    assert bounds["j4"] == pytest.approx(1.02, abs=0.01)


# ------------------------------------------------- the rule, reading by reading


def _steady_watch() -> FieldWatch:
    """j1-like (reduction 35, 1 rad/s, 2 rad/s²) at its full 1 rad/s, the reading settled."""
    watch = FieldWatch("j1", 35.0, 1.0, 2.0)
    watch.velocity(0.0, 1.0, 1.0)
    for k in range(1, 51):
        watch.velocity(0.01 * k, 1.0, 1.0)
    return watch


def test_a_rotor_that_stands_while_its_field_turns_is_stopped_after_the_hold_and_not_before() -> None:
    watch = _steady_watch()
    start = 0.5
    for k in range(1, 10):  # behind from the first reading on: 0.09 s is not yet a loss
        watch.velocity(start + 0.01 * k, 1.0, 0.0)
    with pytest.raises(FieldLostError) as e:
        watch.velocity(start + 0.01 * 11, 1.0, 0.0)
    assert str(e.value) == (
        "j1: lost its field: the drive turned at +1 rad/s, where its encoder would read +1, and the rotor "
        "read +0 rad/s for 0.10 s, which the firmware's stall detection does not flag at that speed"
    )
    assert (e.value.joint, e.value.field, e.value.rotor) == ("j1", 1.0, 0.0)
    assert isinstance(e.value, StalledError)  # handled as a stall: the arm stops every joint


def test_one_reading_back_within_the_bound_starts_the_hold_over() -> None:
    watch = _steady_watch()
    t = 0.5
    for rotor in (0.0,) * 9 + (0.8,) + (0.0,) * 9:  # 0.8 rad/s: 0.2 behind, within 0.35
        t += 0.01
        watch.velocity(t, 1.0, rotor)
    assert watch.behind_since is not None  # the second stretch runs, 0.08 s long


def test_a_rotor_just_inside_the_bound_is_never_stopped() -> None:
    watch = _steady_watch()
    for k in range(1, 200):
        watch.velocity(0.5 + 0.01 * k, 1.0, 1.0 - 0.34)  # 0.34 rad/s behind, bound 0.35


def test_a_rotor_ahead_of_its_field_is_not_behind_it() -> None:
    watch = _steady_watch()
    for k in range(1, 100):
        watch.velocity(0.5 + 0.01 * k, 0.0, 1.0)  # told to stop: the field brakes, the rotor runs on


def test_the_encoders_lag_while_accelerating_is_not_a_loss() -> None:
    # j3 ramped at its 14 rad/s² reads KP/KI = 63 ms late: 0.88 rad/s slow, above its bound
    # of 0.51. The uStepper's estimator (drive.VelocityEstimator) read at 20 Hz, fed the
    # encoder of a rotor that follows a 0 -> 5 rad/s ramp exactly.
    from bioscara_gym.hardware.drive import ENCODER_COUNTS_PER_REV, VelocityEstimator

    j3 = CONFIG.joint("j3")
    estimator = VelocityEstimator()
    watch = FieldWatch("j3", j3.reduction, j3.max_velocity, j3.max_acceleration)
    counts_per_joint_rad = abs(j3.reduction) * ENCODER_COUNTS_PER_REV / (2 * math.pi)
    position, speed = 0.0, 0.0
    watch.velocity(0.0, 5.0, 0.0)
    worst = 0.0
    for ms in range(1, 1001):
        speed = min(5.0, speed + j3.max_acceleration * 0.001)
        position += speed * 0.001
        estimator.update(position * counts_per_joint_rad)
        if ms % 50 == 0:
            read = estimator.counts_per_s / counts_per_joint_rad
            worst = max(worst, min(5.0, j3.max_acceleration * ms * 0.001) - read)
            watch.velocity(ms * 0.001, 5.0, read)
    assert worst > watch.bound  # the lag alone would have stopped it


@pytest.mark.parametrize(
    ("reduction", "speed", "accel", "move"),
    [pytest.param(35.0, 1.0, 2.0, 1.0, id="j1-1rad"), pytest.param(-1570.8, 0.03, 0.2, 0.02, id="j2-20mm")],
)
def test_a_position_move_is_predicted_as_the_chip_brakes_it(
    reduction: float, speed: float, accel: float, move: float
) -> None:
    # A move read at 20 Hz: the field's place within each 50 ms decides when it brakes (j2's
    # bound, 7.8 mm/s, is less than a cycle of its 0.2 m/s²). A rotor on the trapezoid (the
    # chip's own 1 ms steps) is never behind; one that stands 40 % into the move is.
    watch = FieldWatch("j", reduction, speed, accel)
    watch.start(0.0, 0.0, 0.0, 0.0)
    q, v, t = 0.0, 0.0, 0.0
    for ms in range(1, 4001):
        v = min(v + accel * 0.001, speed, math.sqrt(2 * accel * max(move - q, 0.0)))
        q += v * 0.001
        if ms % 50 == 0:
            t = ms * 0.001
            watch.position(t, move, q, v)  # the encoder's lag left out: the rotor ahead, if anything
    standing = FieldWatch("j", reduction, speed, accel)
    standing.start(0.0, 0.0, 0.0, 0.0)
    with pytest.raises(FieldLostError):
        for k in range(1, 80):
            q = min(0.05 * k * speed, 0.4 * move)
            standing.position(0.05 * k, move, q, speed if q < 0.4 * move else 0.0)


def test_a_position_reading_brakes_the_field_from_where_the_joint_was_at_the_last_one() -> None:
    # j2 cruising at 0.03 m/s, the target 3 mm ahead; the next reading 50 ms later. The chip,
    # in 10 ms steps: 0.03 m/s while the target is further than v²/2a = 2.25 mm (three steps,
    # 0.9 mm), then braking at 0.2 m/s²: 0.0290, then 0.0270 (sqrt(2 x 0.2 x 1.805 mm) = 0.0269
    # asks for more than one step can take). From the reading's own place (1.5 mm on) it
    # would have braked from the first step, to 0.020.
    watch = FieldWatch("j2", -1570.8, 0.03, 0.2, "m/s")
    watch.start(0.0, 0.03, 0.03, 0.0)
    watch.position(0.05, 0.003, 0.0015, 0.03)
    assert watch.field == pytest.approx(0.0270, abs=0.0002)


def test_stopped_the_next_reading_starts_over_from_the_rotors_speed() -> None:
    watch = _steady_watch()
    watch.stop()
    for k in range(1, 200):  # at rest now, commanded to rest: nothing left of the 1 rad/s field
        watch.velocity(1.0 + 0.01 * k, 0.0, 0.0)


@pytest.mark.parametrize("gap", [1.1, 3600.0])
def test_a_reading_long_after_the_last_starts_over_instead_of_replaying_the_gap(gap: float) -> None:
    # More than 1 s, up to an hour between readings (a position interface left idle, no deadman
    # in position mode): not 360,000 ramp steps, and the field is taken from the rotor (at rest
    # here), not from the old command (1 rad/s).
    watch = _steady_watch()
    now = 0.5 + gap
    watch.velocity(now, 1.0, 0.0)
    assert (watch.field, watch.time) == (0.0, now)
    for k in range(1, 200):  # commanded to rest from there: nothing left of the old field
        watch.velocity(now + 0.01 * k, 0.0, 0.0)


def test_a_velocity_reading_after_a_start_in_position_is_a_ramp_not_a_move() -> None:
    # Seen (a hostile test): a claim stores the joint's position; the first velocity reading
    # then ran the position trapezoid toward the command, a speed read as a target.
    watch = FieldWatch("j2", -1570.8, 0.03, 0.2, "m/s")
    watch.start(0.0, 0.0, 0.0, position=0.17)
    watch.velocity(0.05, 0.03, 0.0)
    assert watch.field == pytest.approx(0.01)  # 0.2 m/s² for 50 ms


def test_a_start_at_the_encoders_reading_allows_for_its_lag_at_full_acceleration() -> None:
    j3 = CONFIG.joint("j3")
    watch = FieldWatch("j3", j3.reduction, j3.max_velocity, j3.max_acceleration)
    watch.start(0.0, 2.0, 2.0, exact=False)
    assert watch.slack == pytest.approx(14.0 * 0.063, rel=0.01)  # 0.88 rad/s, above the bound of 0.51
    watch.start(0.0, 0.0, 0.0)
    assert watch.slack == 0.0
    fresh = FieldWatch("j3", j3.reduction, j3.max_velocity, j3.max_acceleration)
    fresh.velocity(0.0, 5.0, 2.0)  # no start: the first reading starts it, at the reading
    assert (fresh.field, fresh.slack) == (2.0, pytest.approx(14.0 * 0.063, rel=0.01))


def test_each_turn_of_the_ramp_adds_a_10_ms_step_until_the_field_has_held_its_speed_long_enough() -> None:
    # j1 (2 rad/s²) from rest to 1 rad/s: two turns (it starts, then stops accelerating),
    # 0.02 rad/s each; cleared once 1 rad/s has held for 0.04 / 2 + 0.01 = 0.03 s.
    watch = FieldWatch("j1", 35.0, 1.0, 2.0)
    watch.start(0.0, 0.0, 0.0)
    watch.velocity(0.25, 1.0, 1.0)  # the rotor ahead: never behind
    assert watch.slack == pytest.approx(0.02)  # accelerating
    watch.velocity(0.51, 1.0, 1.0)
    assert watch.slack == pytest.approx(0.04)  # at 1 rad/s since 0.50 s: held 0.01 s
    watch.velocity(0.525, 1.0, 1.0)
    assert watch.slack == pytest.approx(0.04)  # held 0.025 s
    watch.velocity(0.535, 1.0, 1.0)
    assert watch.slack == 0.0  # held 0.035 s
    watch.velocity(0.6, -1.0, 1.0)  # a reversal: one turn
    assert watch.slack == pytest.approx(0.02)


def test_a_ramp_that_keeps_turning_widens_the_bound_until_the_field_holds_its_speed() -> None:
    # j1 switched between ±1 rad/s every 0.1 s: 10 reversals, 0.2 rad/s; 0.2 s at 1 rad/s,
    # once it gets there, clears it.
    watch = FieldWatch("j1", 35.0, 1.0, 2.0)
    watch.start(0.0, 0.0, 0.0)
    t = 0.0
    for k in range(10):
        for _ in range(5):
            t += 0.02
            watch.velocity(t, 1.0 if k % 2 == 0 else -1.0, watch.reading)
    assert watch.slack == pytest.approx(0.2)
    for _ in range(60):
        t += 0.02
        watch.velocity(t, 1.0, watch.reading)
    assert watch.slack == 0.0


@pytest.mark.parametrize(
    ("args", "message"),
    [
        (("j1", 0.0, 1.0, 2.0), "j1: the field watch needs a finite, non-zero reduction, got 0.0"),
        (("j1", 35.0, 1.0, -2.0), "j1: the field watch needs a max_acceleration > 0, got -2.0"),
        (("j1", 35.0, 1.0, 0.0), "j1: the field watch needs a max_acceleration > 0, got 0.0"),
        (("j2", 35.0, math.nan, 2.0), "j2: the field watch needs a max_velocity > 0, got nan"),
    ],
)
def test_a_watch_without_a_ramp_to_predict_is_refused_naming_the_joint(args: tuple, message: str) -> None:
    with pytest.raises(ValueError, match=f"^{message}$"):
        FieldWatch(*args)


def test_a_command_that_is_not_a_number_is_refused_and_the_prediction_kept() -> None:
    watch = _steady_watch()
    with pytest.raises(ValueError, match=r"^j1: the field watch was given a command of nan$"):
        watch.velocity(0.51, math.nan, 1.0)
    assert watch.field == 1.0


def test_a_second_reading_at_the_same_time_changes_nothing() -> None:
    watch = _steady_watch()
    for k in range(1, 10):
        watch.velocity(0.5 + 0.01 * k, 1.0, 0.0)
    since = watch.behind_since
    watch.velocity(0.59, 1.0, 0.0)
    assert watch.behind_since == since and watch.time == 0.59


def _ramp_from(watch: FieldWatch) -> None:
    """j1 commanded 1 rad/s at 2 rad/s², read 20 times a second as the estimator's 63 ms late."""
    for k in range(1, 30):
        t = 0.05 * k
        watch.velocity(t, 1.0, min(1.0, max(0.0, 2.0 * (t - 0.063))))


def test_started_at_rest_the_field_ramps_from_zero_whatever_the_encoder_reads() -> None:
    # After a simulation placed the joint the encoder's estimate reads the jump (0.5 rad/s
    # here) while the chip stands: the field starts at 0.
    watch = FieldWatch("j1", 35.0, 1.0, 2.0)
    watch.start(0.0, 0.0, 0.5)
    _ramp_from(watch)
    misled = FieldWatch("j1", 35.0, 1.0, 2.0)
    misled.start(0.0, 0.5, 0.5)  # the field taken from the reading: 0.5 rad/s ahead all the ramp
    with pytest.raises(FieldLostError):
        _ramp_from(misled)


# ------------------------------------------------- the real arm's recordings


def _chip_acceleration(joint: str, acceleration: float) -> float:
    """What the chip ramps a SETRPM with (the real runs' j2_5 and j4_4 limits wrap)."""
    dps2 = abs(rate_to_degrees(acceleration, CONFIG.joint(joint).reduction))
    return acceleration * velocity_mode_acceleration(dps2) / dps2


def _watch_trips(run: max_accel.MaxAccelRun) -> bool:
    """The watch fed the real run's readings on the replayed program's own time base."""
    commanded = max_accel.replay(run, max_accel.ideal(CONFIG, run.joint))
    mask = max_accel.window(run, CONFIG)
    watch = FieldWatch(
        run.joint,
        CONFIG.joint(run.joint).reduction,
        run.max_velocity,
        _chip_acceleration(run.joint, run.max_acceleration),
    )
    watch.start(0.0, 0.0, 0.0)  # at rest when the program sends its velocity
    try:
        for t, qd in zip(commanded.t[mask], run.qd[mask], strict=True):
            watch.velocity(float(t), run.max_velocity, float(qd))
    except FieldLostError:
        return True
    return False


def test_on_the_real_max_accel_runs_it_stops_the_two_that_lost_their_field_for_good_and_no_other() -> None:
    # maxAccel/: j1 at 2 rad/s and 3 rad/s² peaked at 0.81 rad/s and stood (j1_3); j2 at
    # 0.05 m/s moved 19 mm (j2_2). j1_2 slipped and locked on again; the 19 others held.
    runs = find_recordings().max_accel
    assert len(runs) == 22
    tripped = {run.name for run in runs if _watch_trips(run)}
    assert tripped == {"j1_3", "j2_2"}


def test_on_the_real_free_ramps_of_the_stall_test_it_never_trips() -> None:
    # high_speed_stall_test/: the host ramps the set speed (motor rad/s) every pass; the
    # three files without a block ran free to 120 rad/s (J3: 5 rad/s) and back.
    free = [s for s in find_recordings().stall_signal if "STALL" not in s.name]
    assert len(free) == 3
    for signal in free:
        watch = FieldWatch(signal.joint, 1.0, 1000.0, 30.0 * 12.0)  # motor units; MAXACCEL 30 (j4)
        for t, set_speed, speed in zip(signal.t, signal.set_speed, signal.speed, strict=True):
            watch.velocity(float(t), float(set_speed), float(speed))


# ------------------------------------------------------------ in the arm


@pytest.fixture
def arm(make_arm_backend) -> Arm:
    """The simulated arm, active and homed (every joint at its max end stop)."""
    arm = Arm(make_arm_backend("sim"))
    arm.configure()
    arm.activate()
    arm.home()
    return arm


def test_the_arm_stops_j1_blocked_at_full_speed_which_the_firmware_does_not_flag(arm: Arm) -> None:
    # j1 blocked at 1 rad/s (35 rad/s at the motor, 285 a pass) rises past the spike filter at
    # once: the firmware alone presses on (benchmarks/collision_speeds.py).
    from rigs import place_obstacle

    arm.claim("j1", "velocity")
    arm.set_command("j1", -1.0)
    for _ in range(40):
        arm.cycle(0.01)
    place_obstacle(arm.backend.sim, "j1", direction=-1, gap=0.005)
    core = arm.backend.sim.cores["j1"]
    cycles = 0
    with pytest.raises(FieldLostError, match=r"^j1: lost its field: the drive turned at -1 rad/s"):
        for cycles in range(1, 100):  # noqa: B007 - counted for after the loop
            arm.cycle(0.01)
    assert cycles <= 20  # within 0.2 s of the obstacle's placing (measured: 0.17 s)
    assert not core.flags & Flag.STALL  # the firmware had not seen it
    assert core.flags & Flag.NOT_ENABLED  # its field cut


@pytest.mark.parametrize("joint", ["j1", "j2", "j3", "j4"])
def test_a_joint_sent_a_new_target_every_cycle_is_never_stopped(arm: Arm, joint: str) -> None:
    # Position mode at 20 Hz, a random target around mid-range each cycle (as a cartesian
    # policy sends): the chip brakes, overshoots and turns back, and the watch must know where
    # its field is. A field braked one cycle early (anchored at the wrong reading) is off by
    # the max acceleration times a cycle: for j2, 0.01 m/s against a bound of 0.0078.
    cfg = CONFIG.joint(joint)
    mid = 0.5 * (cfg.min + cfg.max)
    arm.claim(joint, "position")
    arm.move_to({joint: mid}, period_s=0.05)
    span = 0.01 if joint == "j2" else 0.3
    rng = np.random.default_rng(0)
    for _ in range(200):
        arm.set_command(joint, mid + rng.uniform(-span, span))
        arm.cycle(0.05)


def test_a_joint_claimed_for_velocity_while_braking_a_position_move_is_not_stopped(arm: Arm) -> None:
    # Seen (a hostile test): j4 switched from a position move, 0.5 s in and braking, to
    # velocity 0. The encoder trails the braking field by 30 rad/s² x 63 ms = 1.9 rad/s.
    arm.claim("j4", "position")
    arm.move_to({"j4": -2.0})
    arm.set_command("j4", 2.0)
    for _ in range(25):
        arm.cycle(0.02)
    arm.release("j4")
    arm.claim("j4", "velocity")
    arm.set_command("j4", 0.0)
    for _ in range(50):
        arm.cycle(0.02)
    assert arm.joint_states["j4"].velocity == pytest.approx(0.0, abs=0.05)


@pytest.mark.parametrize(("mode", "every"), [("velocity", 5), ("cartesian", 3)])
def test_push_at_100_hz_switching_every_few_steps_is_never_stopped(mode: str, every: int) -> None:
    # Seen (a hostile test): the emulated chip ramps in 10 ms passes, the watch continuously;
    # with the ramp turning every few 11.7 ms cycles the two drifted 2.4 rad/s apart (j4).
    import gymnasium as gym

    env = gym.make("Bioscara-Push-v0", control_mode=mode, control_freq=100.0)
    env.reset(seed=0)
    for k in range(200):
        sign = 1.0 if (k // every) % 2 == 0 else -1.0
        *_, terminated, truncated, info = env.step(np.full(env.action_space.shape, sign, dtype=np.float32))
        assert not info["field_lost"], f"step {k}: {info.get('stalled_joint')}"
        if terminated or truncated:
            break
    env.close()


def test_a_mock_joint_mirrors_its_commands_and_is_not_watched(homed_mock_arm: Arm) -> None:
    assert homed_mock_arm.watches == {}


def test_an_arm_driving_every_joint_at_its_limits_is_never_stopped_by_the_watch(arm: Arm) -> None:
    # To mid-range in position mode, then every joint reversed between its max velocities at
    # its max acceleration, all at once (around mid-range: no end stop in reach).
    arm.move_to({j.name: 0.5 * (j.min + j.max) for j in CONFIG.joints}, period_s=0.02)
    for name in arm.names:
        arm.release(name)
        arm.claim(name, "velocity")
    for sign, seconds in ((-1.0, 0.25), (1.0, 0.5), (-1.0, 0.5), (1.0, 0.25)):
        for name in arm.names:
            arm.set_command(name, sign * CONFIG.joint(name).max_velocity)
        for _ in range(round(seconds / 0.02)):
            arm.cycle(0.02)
    assert all(arm.watches[n].field is not None for n in arm.names)  # it was watching throughout
