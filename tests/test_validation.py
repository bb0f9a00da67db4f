"""The simulated arm against the real arm's recordings: one recording of each kind, and bad input.

The full validation (every recording) is ``bioscara validate`` and
``benchmarks/validate_real.py``; the fit is ``bioscara calibrate`` (slow, not here).
Expected values come from the recordings themselves (their files, their
READMEs) as literals.
"""

from __future__ import annotations

import dataclasses
import math
import os
import re
import shutil
import signal
import subprocess
import sys
import time
from pathlib import Path

import numpy as np
import pytest

from bioscara_gym.cli import main
from bioscara_gym.errors import RecordingError
from bioscara_gym.hardware import load_config
from bioscara_gym.hardware.arm import Arm
from bioscara_gym.hardware.drive import KICK_ACCEL, DriveParams, PidNoiseProfile
from bioscara_gym.hardware.firmware import FIRMWARE_STALL_RULE
from bioscara_gym.hardware.motor import KinematicStepper
from bioscara_gym.validation import validate
from bioscara_gym.validation.experiments import max_accel, rw, setting_max_val, stall, tracking
from bioscara_gym.validation.recordings import (
    DATA_DIR,
    StallSignal,
    find_recordings,
    read_max_accel,
    read_setting_max_val,
    read_stall_signal,
    read_tracking,
    read_transactions,
)

CONFIG = load_config()


# ------------------------------------------------------------------ readers
def test_max_accel_reader_takes_the_programs_header_and_samples() -> None:
    run = read_max_accel(DATA_DIR / "maxAccel" / "j1_3.csv")
    assert (run.joint, run.max_velocity, run.max_acceleration, run.current) == ("j1", 2.0, 3.0, 20.0)
    assert len(run.t) == 198
    assert run.t[0] == pytest.approx(0.0101075) and run.q[0] == pytest.approx(-4.72375)
    assert run.qd[-1] == pytest.approx(4.0971e-05)


def test_setting_max_val_reader_takes_the_limits() -> None:
    run = read_setting_max_val(DATA_DIR / "settingMaxVal" / "accel_test_5000_10000_online_change.csv")
    assert (run.max_acceleration, run.max_velocity, run.online_change) == (5000.0, 10000.0, True)
    assert run.position[-1] == pytest.approx(35999.746094)


def test_stall_reader_reads_gzipped_logs() -> None:
    sig = read_stall_signal(DATA_DIR / "high_speed_stall_test" / "j4_STALL_adaptive_stall_threshold.csv.gz")
    assert sig.joint == "j4" and len(sig.t) == 2908
    assert (sig.raw[-3], sig.raw[-2], sig.raw[-1]) == (420.0, 275.0, 236.0)
    assert sig.stalled[-1] == 1.0


def test_tracking_reader_finds_j1s_reference_and_feedback() -> None:
    run = read_tracking(DATA_DIR / "tracking_error" / "record_0p314_1p57_j1.csv.gz")
    assert (run.interface, run.ramp_speed, run.max_acceleration) == ("position", 0.314, 1.57)
    vel = read_tracking(DATA_DIR / "tracking_error" / "record_0p314_1p57_j1_vel_p0p5_i0p0_d0p0_kff1p0.csv.gz")
    assert vel.interface == "velocity" and vel.gains == {"p": 0.5, "i": 0.0, "d": 0.0, "kff": 1.0}


def test_transaction_reader_takes_the_bus_speed_from_the_name() -> None:
    tr = read_transactions(DATA_DIR / "RW_test" / "position_100kHz.csv.gz")
    assert (tr.what, tr.clock_hz) == ("position", 100_000.0)
    assert tr.read_us.mean() == pytest.approx(860.34, abs=0.01)  # RW_test/README.md, Table 3


# ----------------------------------------------- one recording of each kind
def test_j4_at_34_rad_per_s2_runs_at_the_16_bit_cut_acceleration() -> None:
    # The real j4 reached 1.89 rad/s in the 0.5 s of maxAccel/j4_4 (asked 10 rad/s at
    # 34 rad/s^2): not lost steps but SETUP's moveSteps(0) cutting AMAX to 16 bits
    # (408 rad/s^2 at the motor is 73,146 -> 7,610: 2.43 deg/s^2 x 1000, 3.5 rad/s^2).
    run = read_max_accel(DATA_DIR / "maxAccel" / "j4_4.csv")
    rows = {r.quantity: r for r in max_accel.compare(run, max_accel.replay(run, CONFIG), CONFIG)}
    assert rows["peak speed"].real == pytest.approx(1.891, abs=1e-3)
    assert rows["peak speed"].passed, rows["peak speed"]
    assert rows["lost steps"].real == "no" and rows["lost steps"].passed
    assert rows["position RMS"].passed


def test_j1_at_2_rad_per_s_loses_steps_as_the_real_one_did() -> None:
    # maxAccel/README.md: "at 3rad/s2 and 2rad/s joint doesnt reach max velocity".
    run = read_max_accel(DATA_DIR / "maxAccel" / "j1_3.csv")
    sim = max_accel.replay(run, CONFIG)
    rows = {r.quantity: r for r in max_accel.compare(run, sim, CONFIG)}
    assert rows["lost steps"].real == "yes" and rows["lost steps"].sim == "yes"
    assert sim.lost_sync >= 1
    assert max(abs(sim.qd)) < 1.0  # it never got near the 2 rad/s asked


def test_j1_gains_speed_after_its_first_slips_as_the_real_one_did() -> None:
    # maxAccel/j1_3.csv: the real j1 skipped from 0.1 s on and still reached
    # 0.809332 rad/s (at t = 0.42 s) before it fell away. A slipped rotor
    # pushed alike at every slip (the drive before slip_corner) peaked at
    # 0.713 (11.9 % short; bound 10 %).
    run = read_max_accel(DATA_DIR / "maxAccel" / "j1_3.csv")
    assert float(np.max(np.abs(run.qd))) == 0.809332  # the recording, as read
    rows = {r.quantity: r for r in max_accel.compare(run, max_accel.replay(run, CONFIG), CONFIG)}
    assert rows["peak speed"].sim == pytest.approx(0.809332, rel=0.10)
    assert rows["peak speed"].passed and rows["position RMS"].passed


def test_j1_after_losing_its_field_stops_where_the_real_one_stopped() -> None:
    # maxAccel/j1_3.csv: the real j1 slowed at a nearly constant rate and was
    # at rest 0.392 rad from its start from 0.81 s on (|qd| < 0.005 rad/s),
    # its field running on. The j1 fitted before the margin of its verdicts
    # let the slipped rotor creep on at 0.089 rad/s for ever.
    run = read_max_accel(DATA_DIR / "maxAccel" / "j1_3.csv")
    sim = max_accel.replay(run, CONFIG)
    rest = run.t > 1.0
    assert float(np.max(np.abs(run.qd[rest]))) < 0.005  # the recording, as read
    assert float(np.max(np.abs(sim.qd[rest]))) < 0.01
    assert sim.q[-1] - sim.q[0] == pytest.approx(-4.33145 - -4.72375, abs=0.02)  # first and last rows


def test_j1_comes_to_rest_at_its_target(make_arm_backend) -> None:
    # Its rotor lags its field by up to 0.75 motor degrees while it speeds up,
    # far more than the closed loop's 15 microsteps (0.105 deg). A rotor that
    # took up each new load angle at once hunted about its target for ever
    # (+-0.0007 rad); one with inertia on the field's spring settles.
    arm = Arm(make_arm_backend("sim"))
    arm.configure()
    arm.activate()
    arm.home()
    arm.move_to({"j1": 0.0}, timeout_s=8.0)  # there in 3.9 s from its max end stop


def test_j1_sits_as_still_as_the_real_one_after_a_ramp() -> None:
    # tracking_error/record_0p314_1p57_j1: from 0.5 s after the reference
    # stopped at 1.5707 rad, the real j1 read 1.570681-1.570725 rad (a spread
    # of 4.39e-5 rad). A j1 hunting about its target spreads 1.1e-3.
    run = read_tracking(DATA_DIR / "tracking_error" / "record_0p314_1p57_j1.csv.gz")
    rows = {r.quantity: r for r in tracking.compare(run, tracking.replay(run, CONFIG))}
    rest = rows["position spread at rest after the ramp"]
    assert rest.real == pytest.approx(4.39e-5, abs=0.01e-5)
    assert rest.sim < 1.05e-4 and rest.passed


#: The runs of maxAccel/ whose real motor lost steps (their qd falls away from
#: the command: maxAccel/README.md's "hearable skipping at 3 rad/s2", "doesnt
#: reach max velocity"; j2 at 0.05 m/s moved 19 mm where a joint that follows moves 102).
REAL_LOST = {"j1_2", "j1_3", "j2_2"}


@pytest.mark.parametrize(
    "name",
    [p.stem for p in sorted((DATA_DIR / "maxAccel").glob("*.csv"))],
)
def test_the_packaged_drive_keeps_a_margin_from_each_real_verdict(name: str) -> None:
    # A run the real motor held asks at most 0.9 of the simulated pull-out, one
    # where it lost steps at least 1.1: a task's command a little harder than
    # a recorded one meets what the real motor did (j1 held 1 rad/s with
    # 2 rad/s^2 and lost it with 3). The fit stops at the margin's edge, so
    # the bound holds to 0.005 (j4_5 asks 0.90002 of the packaged j4).
    run = read_max_accel(DATA_DIR / "maxAccel" / f"{name}.csv")
    sim = max_accel.replay(run, CONFIG)
    demand = max_accel.peak_demand(sim, max_accel.window(run, CONFIG))
    if name in REAL_LOST:
        assert demand > 1.095, f"{name} lost steps on the real arm; simulated demand {demand:.2f}"
    else:
        assert demand < 0.905, f"{name} held on the real arm; simulated demand {demand:.2f}"


def test_the_pid_noise_median_is_linear_between_knots_and_constant_beyond() -> None:
    # PidNoiseProfile's rule: the median at each knot, linear between knots,
    # constant beyond the last (and at the first below it); |speed| either way;
    # the falling medians while the set speed falls.
    profile = PidNoiseProfile((0.0, 10.0, 30.0), rising=(2.0, 12.0, 40.0), falling=(1.0, 5.0, 9.0))
    assert [profile.median(w, False) for w in (0.0, 5.0, 10.0, 20.0, 30.0, 100.0)] == [2, 7, 12, 26, 40, 40]
    assert profile.median(-20.0, False) == 26.0
    assert [profile.median(w, True) for w in (2.5, 10.0, 25.0, 31.0)] == [2.0, 5.0, 8.0, 9.0]
    assert PidNoiseProfile((5.0, 6.0), (3.0, 4.0), (3.0, 4.0)).median(1.0, False) == 3.0


def test_a_following_rotor_takes_up_a_new_load_angle_over_its_natural_period() -> None:
    # Pull-out 1000 rad/s^2 at 20 % current: 200, a stiffness of 200 x (pi/2)
    # per full step (pi/100 rad) = 10,000 /s^2: a natural frequency of 100 rad/s.
    # At 100 deg/s and no friction the rotor sits on its field; a load of
    # 100 rad/s^2 (half the pull-out) then asks a load angle of asin(0.5), a
    # third of a full step: 0.6 deg. Critically damped, the lag after t is
    # 0.6 x (1 - (1 + 100 t) e^(-100 t)): 0.0028 deg after 1 ms, 0.1585 after
    # 10 ms, 0.5757 after 50 ms, and it never overshoots.
    motor = KinematicStepper(0.0, drive=DriveParams(pullout_accel=1000.0))
    motor.command(100.0, 0.2)
    motor.advance(0.2)
    assert motor.field_deg - motor.position_deg == 0.0
    motor.load_accel = -100.0
    lags = []
    for _ in range(50):
        motor.advance(0.001)
        lags.append(motor.field_deg - motor.position_deg)
    assert lags[0] == pytest.approx(0.0028, abs=0.0002)
    assert lags[9] == pytest.approx(0.1585, abs=0.001)
    assert lags[49] == pytest.approx(0.5757, abs=0.001)
    assert max(lags) <= 0.6
    motor.advance(0.1)  # within a microstep of the load angle it is on it
    assert motor.field_deg - motor.position_deg == pytest.approx(0.6, abs=1e-9)


def _following_run(motor: KinematicStepper) -> list[tuple[float, float, float, float]]:
    """Ramps up, cruises, brakes, stops and turns back tick by tick; encoder, XACTUAL, PID error, speed."""
    out = []
    ticks = [*range(0, 400, 40), *[400] * 10, *range(400, -1, -50), *[0] * 10]
    for v in [*ticks, *range(40, -200, -80), *[-200] * 5, *range(-200, 1, 100)]:
        motor.command(float(v), 0.2)
        motor.advance(0.01)
        out.append((motor.position_deg, motor.setpoint_deg, motor.pid_error_deg, motor.velocity_dps))
    return out


def test_the_many_pass_shortcut_gives_what_the_1_ms_passes_give(monkeypatch: pytest.MonkeyPatch) -> None:
    # A drive whose load angle changes with every tick of the ramp (friction 20 %
    # of the pull-out, the ramp's 40 deg/s a tick 35 %; as it brakes, the rotor
    # waits on the field): the shortcut and the passes one by one must agree on
    # everything the firmware reads, to rounding.
    drive = DriveParams(pullout_accel=1000.0, friction_coulomb=40.0, friction_viscous=0.5)
    fast = _following_run(KinematicStepper(0.0, drive=drive))
    monkeypatch.setattr(KinematicStepper, "_follow_passes", lambda self, n, h: False)
    slow = _following_run(KinematicStepper(0.0, drive=drive))
    assert len(fast) == len(slow) == 50
    assert np.allclose(fast, slow, rtol=0, atol=1e-9)
    assert max(abs(f[2]) for f in fast) > 0.1  # the closed loop rewrote XACTUAL on the way


def _into_the_stop(direction: float) -> list[tuple[float, float, float]]:
    """A following rotor run at 1000 deg/s toward its end stop 25 deg away: every tick's readings."""
    motor = KinematicStepper(0.0, lower_stop_deg=-25.0, upper_stop_deg=25.0)
    out = []
    for _ in range(10):
        motor.command(direction * 1000.0, 0.5)
        motor.advance(0.01)
        out.append((motor.position_deg, motor.setpoint_deg, motor.velocity_dps))
    return out


@pytest.mark.parametrize("direction", [1.0, -1.0])
def test_the_many_pass_shortcut_stops_at_the_end_stop_as_the_passes_do(
    monkeypatch: pytest.MonkeyPatch, direction: float
) -> None:
    # 100 deg asked of a rotor with 25 deg of room: the third tick, which reaches the
    # stop must not carry it past, whichever way it runs (the field runs on and
    # slips its poles; their kicks throw the rotor back from the stop).
    fast = _into_the_stop(direction)
    monkeypatch.setattr(KinematicStepper, "_follow_passes", lambda self, n, h: False)
    slow = _into_the_stop(direction)
    assert np.allclose(fast, slow, rtol=0, atol=1e-9)
    assert 20.0 < max(direction * p for p, _, _ in fast) <= 25.0  # at the stop, never past it


def test_the_largest_share_of_the_pull_out_torque_asked_for_is_kept() -> None:
    # Pull-out 1000 rad/s^2 at full current, no fall with speed, no friction: 500 at 50 %.
    # 0 -> 1 rad/s within one 10 ms tick asks 100 rad/s^2, a fifth of it.
    motor = KinematicStepper(0.0, drive=DriveParams(pullout_accel=1000.0))
    motor.command(math.degrees(1.0), 0.5)
    motor.advance(0.05)
    assert motor.peak_demand == pytest.approx(0.2) and motor.lost_sync == 0
    # 1 -> 11 rad/s within a tick asks 1000 rad/s^2: twice what it has; it loses its field
    motor.command(math.degrees(11.0), 0.5)
    motor.advance(0.05)
    assert motor.peak_demand == pytest.approx(2.0) and motor.lost_sync == 1


def _slipped_at(field_rad_s: float, slip_corner: float) -> tuple[KinematicStepper, float]:
    """A rotor at 20 rad/s whose field jumps to ``field_rad_s`` within one tick; where it is 2.5 s on."""
    drive = DriveParams(
        pullout_accel=1000.0,
        friction_coulomb=20.0,
        slip_fraction=0.5,
        slip_corner=slip_corner,
        pullin_speed=2.0,
    )
    motor = _at_20_rad_s(drive)
    motor.command(math.degrees(field_rad_s), 0.5)  # 2,000-8,000 rad/s^2: it loses its field
    motor.advance(2.5)
    return motor, motor.position_deg


def _at_20_rad_s(drive: DriveParams) -> KinematicStepper:
    """A rotor ramped to 20 rad/s at half current, following its field."""
    motor = KinematicStepper(0.0, drive=drive)
    for v in range(2, 21, 2):  # 200 rad/s^2: 0.42 of the 500 at half current
        motor.command(math.degrees(v), 0.5)
        motor.advance(0.01)
    assert motor.lost_sync == 0
    return motor


@pytest.mark.parametrize(("field_rad_s", "caught"), [(40.0, True), (60.0, False), (100.0, False)])
def test_a_slipping_rotor_is_dragged_along_only_while_its_field_barely_outruns_it(
    field_rad_s: float, caught: bool
) -> None:
    # Push 0.5 x 500 rad/s^2 at half current, halved at a slip of 10 rad/s
    # (1 / (1 + (slip / 10)^2)), against 20 rad/s^2 of dry friction: it wins
    # while the slip is under 10 x sqrt(11.5) = 34 rad/s. Slipped at 20 rad/s
    # under a field at 40 (a slip of some 18 once the tick's ramp is over)
    # the rotor catches up and locks on; under one at 60 (some 38, just past
    # the edge) or 100 (some 78) it coasts
    # to rest while the field runs on (maxAccel/j1_3: the real j1 gained speed
    # for 0.2 s after its first slips, then stopped dead).
    motor, before = _slipped_at(field_rad_s, slip_corner=10.0)
    assert motor.lost_sync >= 1
    motor.advance(0.5)
    moved = math.radians(motor.position_deg - before)
    if caught:
        assert motor.resyncs >= 1 and moved == pytest.approx(0.5 * field_rad_s, rel=0.01)
    else:
        assert motor.resyncs == 0 and abs(moved) < 0.05  # the pole slips' swing about a rotor at rest


def test_a_slipping_rotor_under_one_push_at_every_slip_catches_any_field() -> None:
    # slip_corner inf (the default): the 250 rad/s^2 push beats friction at any slip.
    motor, before = _slipped_at(100.0, slip_corner=math.inf)
    motor.advance(0.5)
    assert motor.resyncs >= 1
    assert math.radians(motor.position_deg - before) == pytest.approx(50.0, rel=0.01)


def _lost_at_20_rad_s(self_locking: bool) -> tuple[KinematicStepper, float]:
    """A rotor at 20 rad/s whose field jumps to 100 rad/s within one tick; where it is then."""
    drive = DriveParams(
        pullout_accel=1000.0, friction_coulomb=20.0, pullin_speed=2.0, self_locking=self_locking
    )
    motor = _at_20_rad_s(drive)
    before = motor.position_deg
    motor.command(math.degrees(100.0), 0.5)  # 8,000 rad/s^2 asked: it loses its field
    return motor, before


def test_a_self_locking_joint_stops_within_its_first_pole_slips() -> None:
    # Each pole slip's kick at half current: the reversed torque's mean,
    # 2.2e4 x 0.5 x 2/pi = 7,003 rad/s^2, over the time the lead takes to
    # cross two full steps (0.0628 rad) at the slip speed, some 80 rad/s
    # here: 7,003 x 0.0628 / 80 = 5.5 rad/s a slip, every 1.6 ms or sooner.
    # Behind a lead screw that comes off the joint's 20 rad/s: it stops
    # within 10 ms and stays, its field running on (maxAccel/j2_2: the real
    # j2 froze within one 10 ms sample).
    assert KICK_ACCEL == 2.2e4
    motor, before = _lost_at_20_rad_s(self_locking=True)
    motor.advance(0.01)
    assert motor.lost_sync == 1 and 2 <= motor.pole_slips <= 7  # a lap takes 1.57 ms at 80 rad/s of slip
    assert motor.rotor_velocity_dps == 0.0
    stopped = motor.position_deg - motor.swing_deg
    assert 0.0 < math.radians(stopped - before) < 20.0 * 0.01  # less than 10 ms at 20 rad/s
    motor.advance(1.0)
    assert motor.resyncs == 0 and motor.position_deg - motor.swing_deg == stopped


@pytest.mark.parametrize(
    ("self_locking", "rotor_after", "swing_after"), [(True, 0.0, -2.0), (False, 3.0, -5.0)]
)
def test_a_pole_slips_kick_comes_off_a_self_locking_joints_speed_and_only_the_rest_swings(
    self_locking: bool, rotor_after: float, swing_after: float
) -> None:
    # A kick of 5 rad/s on a rotor turning at 3 behind its field: a lead screw
    # stops it and swings it back by the 2 left; otherwise it swings by all 5.
    motor = KinematicStepper(0.0, drive=DriveParams(pullout_accel=1000.0, self_locking=self_locking))
    motor._rotor_dps, motor._slip_deg = math.degrees(3.0), 10.0
    motor._kick(math.degrees(5.0))
    assert math.radians(motor.rotor_velocity_dps) == pytest.approx(rotor_after)
    assert math.radians(motor._swing_dps) == pytest.approx(swing_after)


def test_a_joint_the_load_drives_back_coasts_on_after_its_pole_slips() -> None:
    # The same rotor without the lead screw: its kicks swing it about its
    # path, and it coasts from 20 rad/s against 20 rad/s^2 of friction:
    # 10 rad/s after 0.5 s, at rest after 1 s, 20^2 / (2 x 20) = 10 rad on.
    motor, before = _lost_at_20_rad_s(self_locking=False)
    motor.advance(0.5)
    assert motor.lost_sync == 1 and motor.pole_slips > 100
    assert math.radians(motor.rotor_velocity_dps) == pytest.approx(10.0, rel=0.02)
    motor.advance(1.0)
    assert motor.rotor_velocity_dps == 0.0 and motor.resyncs == 0
    assert math.radians(motor.position_deg - motor.swing_deg - before) == pytest.approx(10.0, rel=0.02)


def test_a_drive_without_self_locking_keeps_its_console_fingerprint() -> None:
    # Like slip_corner: False (the default) leaves the repr, so a console
    # state saved before the field keeps its fingerprint.
    assert "self_locking" not in repr(DriveParams(pullout_accel=1000.0))
    assert "self_locking=True" in repr(DriveParams(pullout_accel=1000.0, self_locking=True))


def test_a_drive_saves_the_fields_added_since_only_where_they_change_the_model() -> None:
    # A configuration or trace header written now loads in a version from
    # before slip_corner and self_locking, and means the same there.
    from bioscara_gym.hardware.drive import drive_from_dict, drive_to_dict

    plain = DriveParams(pullout_accel=1000.0)
    assert not {"slip_corner", "self_locking"} & set(drive_to_dict(plain))
    assert drive_from_dict(drive_to_dict(plain), None) == plain
    lead_screw = DriveParams(pullout_accel=1000.0, slip_corner=5.0, self_locking=True)
    saved = drive_to_dict(lead_screw)
    assert (saved["slip_corner"], saved["self_locking"]) == (5.0, True)
    assert drive_from_dict(saved, None) == lead_screw


def test_a_drive_without_slip_corner_keeps_its_console_fingerprint() -> None:
    # tests/traces/console_session.jsonl holds a state saved before slip_corner:
    # its default (inf) must not change the configuration's fingerprint; any
    # other value must.
    from bioscara_gym.console.state import config_fingerprint

    j1 = CONFIG.joint("j1")
    old = dataclasses.replace(j1, drive=dataclasses.replace(j1.drive, slip_corner=math.inf))
    joints = tuple(old if j.name == "j1" else j for j in CONFIG.joints)
    before = dataclasses.replace(CONFIG, joints=joints)
    assert "slip_corner" not in repr(old.drive)
    assert "slip_corner=5.388" in repr(j1.drive)
    assert config_fingerprint(before) != config_fingerprint(CONFIG)


def test_ten_million_deg_per_s2_is_cut_to_the_16_bit_register() -> None:
    # settingMaxVal/accel_test_10000000_200000.csv: the real motor accelerated at 9,021 deg/s^2.
    run = read_setting_max_val(DATA_DIR / "settingMaxVal" / "accel_test_10000000_200000.csv")
    rows = {r.quantity: r for r in setting_max_val.compare(run, setting_max_val.replay(run))}
    assert rows["ramp acceleration"].real == pytest.approx(9021, abs=5)
    assert rows["ramp acceleration"].sim == pytest.approx(9021, abs=0.01 * 9021)
    assert all(r.passed for r in rows.values())


def test_a_blocked_j4_trips_within_50_ms_of_the_real_one() -> None:
    sig = read_stall_signal(
        DATA_DIR / "high_speed_stall_test" / "j4_LOW_SPEED_STALL_adaptive_stall_threshold_two_levels.csv"
    )
    rule, sensitivity = stall.stall_rule_of(sig)
    assert sensitivity == 6 and rule.spike_limit > 243  # the build let a jump of 243 through
    rows = stall.compare(sig, stall.replay(sig, CONFIG))
    trips = [r for r in rows if r.quantity == "stall trip time"]
    assert len(trips) == 1 and trips[0].passed, rows
    assert not [r for r in rows if r.quantity == "false stall trips"]


def test_the_real_blocks_are_the_passes_between_block_and_trip() -> None:
    events = stall.block_events(find_recordings().stall_signal)
    assert [(e.name, round(e.set_speed, 2), len(e.speed)) for e in events] == [
        ("j4_LOW_SPEED_STALL_adaptive_stall_threshold_two_levels at 1.13 s", 5.7, 9),
        ("j4_STALL_adaptive_stall_threshold at 29.08 s", 25.8, 3),
    ]
    # the files' rows: measured speed 3.52 -0.59 ..., raw 196 20 ... 272 / 420 275 236
    assert events[0].speed[:2].tolist() == [3.52, -0.59] and events[0].raw[-1] == 272
    assert events[1].raw.tolist() == [420, 275, 236]
    # their builds' low-pass: filtered 19.19 -> 54.55 on 196 is a fifth of the
    # way (tau 0.05 s); 18.34 -> 58.5 on 420 a tenth (the packaged 0.1 s)
    assert [e.rule.tau_s for e in events] == [0.05, 0.1]


def _ramp(joint: str, raw_per_band: list[float], name: str) -> StallSignal:
    """A run up a ramp through 5 rad/s bands, 100 passes each, with the given raw error."""
    n = 100 * len(raw_per_band)
    speed = np.arange(n) * 0.05  # 100 passes per 5 rad/s band
    raw = np.repeat(raw_per_band, 100).astype(float)
    zeros = np.zeros(n)
    return StallSignal(Path(f"{name}.csv"), joint, speed / 100, raw, raw, raw, speed, speed, zeros, zeros)


def test_two_runs_are_compared_band_by_band_with_the_replays_bound() -> None:
    # 30 against 20 is 50 %, 25 against 20 is 25 % (bound 30); a 4 against 3 is
    # below the 10 floor: 10 %; a j3 run is not compared with j4's
    a = _ramp("j4", [20, 20, 20, 3], "a")
    b = _ramp("j4", [20, 30, 25, 4], "b")
    pairs = stall.run_to_run([a, b, _ramp("j3", [20, 20, 20, 20], "c")])
    assert pairs == [stall.RunToRun("a", "b", 3, 4, 50.0)]


def test_the_real_j4_runs_do_not_meet_the_band_bound_against_each_other() -> None:
    # the packaged high_speed_stall_test/ files, raw |PID error|, both ramps
    runs = [s for s in find_recordings().stall_signal if "LOW_SPEED" not in s.name]
    pairs = {(p.first, p.second): (p.within, p.bands, round(p.worst)) for p in stall.run_to_run(runs)}
    assert pairs == {
        ("j4_STALL_adaptive_stall_threshold", "j4_adaptive_stall_threshold"): (40, 48, 80),
        ("j4_STALL_adaptive_stall_threshold", "j4_adaptive_stall_threshold_two_levels"): (44, 48, 58),
        ("j4_adaptive_stall_threshold", "j4_adaptive_stall_threshold_two_levels"): (40, 48, 473),
    }


def test_the_packaged_firmware_would_not_have_flagged_the_real_blocks() -> None:
    # The older builds that recorded them tripped at the last logged pass; the
    # packaged source's spike filter (a rise of over 100 keeps the last value)
    # drops the pole slips' spikes, and what is left stays under 60.
    for event in stall.block_events(find_recordings().stall_signal):
        for rule, trips in ((event.rule, True), (FIRMWARE_STALL_RULE, False)):
            last, x = 20.0, 20.0  # a free-running j4's filtered error before the block (~19-25)
            tripped = False
            for raw in event.raw:
                last, x = rule.filter(float(raw), last, x)
                tripped |= x > 10 * event.sensitivity
            assert tripped is trips, (event.name, rule)


def test_the_swing_after_a_block_is_judged_against_the_real_one() -> None:
    event = stall.block_events(find_recordings().stall_signal)[1]  # j4 at 25.8 rad/s
    rows = stall.compare_block(event, stall.replay_block(event, CONFIG))
    assert [r.quantity for r in rows] == [
        "measured speed after the block: RMS error",
        "raw |PID error| after the block: median",
        "raw |PID error| after the block: largest",
        "stall trip after the block",
    ]
    assert all(r.passed for r in rows), rows
    # A rotor thrown back a tenth as hard: its speed falls too slowly and its largest raw
    # error stays under the real 420; ten times as hard: it stops at once (20.8, 6.7
    # against the real 22.2, 14.7, 8.7). Each fails a row the fitted swing passes.
    for kick in (KICK_ACCEL / 10, KICK_ACCEL * 10):
        other = stall.compare_block(event, stall.replay_block(event, CONFIG.with_drives(kick_accel=kick)))
        assert not all(r.passed for r in other), (kick, other)


def test_a_drive_that_cannot_home_is_one_failing_row_not_a_crash(tmp_path: Path) -> None:
    # j4 homes at 10 % current: friction of 5000 rad/s^2 against a pull-out of
    # 2000 x 10 % = 200 leaves it standing; its recordings are not replayed.
    stuck = CONFIG.joint("j4").drive.with_values(pullout_accel=2000.0, friction_coulomb=5000.0)
    joints = tuple(dataclasses.replace(j, drive=stuck) if j.name == "j4" else j for j in CONFIG.joints)
    root = tmp_path / "test"
    (root / "maxAccel").mkdir(parents=True)
    for name in ("j3_1.csv", "j4_1.csv"):
        shutil.copy(DATA_DIR / "maxAccel" / name, root / "maxAccel" / name)
    result = validate(root, dataclasses.replace(CONFIG, joints=joints))
    homing = [r for r in result.rows if r.experiment == "homing/j4"]
    assert len(homing) == 1 and not homing[0].passed
    assert "short of the end stop" in str(homing[0].sim)
    assert {r.experiment for r in result.rows if r.experiment.startswith("maxAccel/")} == {"maxAccel/j3_1"}


def test_the_position_controller_lags_as_the_readme_says() -> None:
    # tracking_error/README.md, Test 1: ~0.12 s at 0.314 rad/s and 1.57 rad/s^2.
    run = read_tracking(DATA_DIR / "tracking_error" / "record_0p314_1p57_j1.csv.gz")
    rows = {r.quantity: r for r in tracking.compare(run, tracking.replay(run, CONFIG))}
    assert rows["steady-state error vs README"].real == 0.12
    assert rows["steady-state error vs README"].passed


def test_the_velocity_follower_catches_up_from_the_ramps_start_as_the_real_one_did() -> None:
    # tracking_error/record_0p314_0p157_j1_vel_p0p5_...: the file starts 1.18 s into a
    # ramp from -1.5707 rad (its reference -1.200 at 0.314 rad/s). The real error
    # (r - q) still rose, 0.262 rad at the first row and 0.307 a second later, then
    # decayed as P = 0.5 pulled it in: 0.0459 at 5 s, a mean over the ramp of 0.297 s.
    # The README's "zero for kp > 0" is not reached within the ramp, so no row
    # holds the replay to it.
    name = "record_0p314_0p157_j1_vel_p0p5_i0p0_d0p0_kff1p0.csv.gz"
    run = read_tracking(DATA_DIR / "tracking_error" / name)
    sim = tracking.replay(run, CONFIG)
    err = sim.reference - sim.feedback
    at = {t: int(np.searchsorted(sim.t, t)) for t in (0.0, 1.0, 5.0)}
    assert err[at[0.0]] == pytest.approx(0.262, abs=0.03)
    assert err[at[1.0]] == pytest.approx(0.307, abs=0.03)
    assert err[at[5.0]] == pytest.approx(0.0459, abs=0.02)
    rows = {r.quantity: r for r in tracking.compare(run, sim)}
    assert set(rows) == {"steady-state error vs recording"}
    assert rows["steady-state error vs recording"].real == pytest.approx(0.297, abs=0.001)
    assert rows["steady-state error vs recording"].passed
    assert "not settled within the ramp" in rows["steady-state error vs recording"].note


def test_transactions_take_the_measured_time_at_400_khz() -> None:
    tr = read_transactions(DATA_DIR / "RW_test" / "position_400kHz.csv.gz")
    rows = rw.compare(tr, rw.replay(tr, CONFIG))
    assert [r.real for r in rows] == [pytest.approx(270.70, abs=0.01), pytest.approx(624.66, abs=0.01)]
    assert all(r.passed for r in rows), rows


# ---------------------------------------------------------------- bad input
def test_a_folder_without_recordings_is_one_error_naming_it(tmp_path: Path) -> None:
    with pytest.raises(RecordingError, match=f"^{tmp_path}: holds no recordings"):
        find_recordings(tmp_path)


def test_a_malformed_csv_names_the_file_and_line(tmp_path: Path) -> None:
    (tmp_path / "maxAccel").mkdir()
    lines = (DATA_DIR / "maxAccel" / "j1_1.csv").read_text().splitlines()
    lines[12] = "0.03, oops, 0.1, 0.2"
    bad = tmp_path / "maxAccel" / "j1_1.csv"
    bad.write_text("\n".join(lines))
    with pytest.raises(RecordingError, match=r"j1_1\.csv: line 13: not a number"):
        find_recordings(tmp_path)


@pytest.mark.parametrize(
    ("folder", "name", "row", "cell"),
    [("maxAccel", "j1_1.csv", 12, "nan"), ("settingMaxVal", "accel_test_5000_200000.csv", 10, "1e400")],
)
def test_a_value_that_is_not_finite_names_the_file_and_line(
    tmp_path: Path, folder: str, name: str, row: int, cell: str
) -> None:
    # Seen (a hostile test): NaN rows gave "zero-size array to reduction operation maximum",
    # naming nothing, or were compared and failed as "nan deg/s"; 1e400 a numpy warning.
    (tmp_path / folder).mkdir()
    lines = (DATA_DIR / folder / name).read_text().splitlines()
    fields = lines[row].split(",")
    lines[row] = ",".join([fields[0], cell, *fields[2:]])
    (tmp_path / folder / name).write_text("\n".join(lines))
    with pytest.raises(
        RecordingError, match=rf"{re.escape(name)}: line {row + 1}: '{cell}' is not a finite number$"
    ):
        find_recordings(tmp_path)


def test_a_gzip_that_unpacks_beyond_the_limit_is_refused(
    tmp_path: Path, monkeypatch: pytest.MonkeyPatch
) -> None:
    # Seen (a hostile test): 26 MB of gzipped zeros unpacked to 6 GB: a MemoryError traceback.
    import gzip

    from bioscara_gym.validation import recordings

    monkeypatch.setattr(recordings, "MAX_RECORDING_BYTES", 1000)
    (tmp_path / "maxAccel").mkdir()
    (tmp_path / "maxAccel" / "j1_1.csv.gz").write_bytes(gzip.compress(b"0" * 1001))
    with pytest.raises(RecordingError, match=r"j1_1\.csv\.gz: unpacks to more than 1000 bytes$"):
        find_recordings(tmp_path)


@pytest.mark.parametrize("kind", ["fifo", "folder"])
def test_a_recording_name_on_what_is_no_file_is_refused_not_skipped(tmp_path: Path, kind: str) -> None:
    # Seen (a hostile test): a FIFO named like a recording was skipped without a word.
    (tmp_path / "maxAccel").mkdir()
    shutil.copy(DATA_DIR / "maxAccel" / "j3_6.csv", tmp_path / "maxAccel")
    odd = tmp_path / "maxAccel" / "j1_1.csv"
    if kind == "fifo":
        os.mkfifo(odd)
    else:
        odd.mkdir()
    with pytest.raises(RecordingError, match=r"j1_1\.csv: cannot be read \(not a regular file\)$"):
        find_recordings(tmp_path)


def test_a_recording_of_an_unknown_joint_is_refused(tmp_path: Path) -> None:
    (tmp_path / "maxAccel").mkdir()
    text = (DATA_DIR / "maxAccel" / "j1_1.csv").read_text().replace("joint: j1", "joint: j9")
    (tmp_path / "maxAccel" / "j9_1.csv").write_text(text)
    with pytest.raises(RecordingError, match=r"j9_1\.csv: unknown joint 'j9'"):
        find_recordings(tmp_path)


def test_a_users_folder_of_their_own_recordings_is_validated(tmp_path: Path) -> None:
    (tmp_path / "maxAccel").mkdir()
    shutil.copy(DATA_DIR / "maxAccel" / "j3_6.csv", tmp_path / "maxAccel")
    result = validate(tmp_path, CONFIG)
    assert [r.experiment for r in result.rows] == ["maxAccel/j3_6"] * 3
    assert result.passed


def test_validate_on_an_empty_folder_is_one_line_and_exit_2(tmp_path: Path) -> None:
    proc = subprocess.run(
        [sys.executable, "-m", "bioscara_gym", "validate", str(tmp_path)],
        capture_output=True,
        text=True,
        check=False,
    )
    assert proc.returncode == 2
    assert proc.stderr.strip().splitlines() == [
        f"bioscara validate: error: {tmp_path}: holds no recordings: expected "
        "maxAccel/, settingMaxVal/, high_speed_stall_test/, "
        "stall_detection_test/, tracking_error/ or RW_test/ with .csv files "
        "(the arm repository's test/ layout)"
    ]


def test_calibrate_refuses_a_missing_output_folder_before_fitting(tmp_path: Path) -> None:
    out = tmp_path / "nowhere" / "arm.yaml"
    proc = subprocess.run(
        [sys.executable, "-m", "bioscara_gym", "calibrate", "--out", str(out)],
        capture_output=True,
        text=True,
        check=False,
    )
    assert proc.returncode == 2
    assert (
        proc.stderr.strip() == f"bioscara calibrate: error: --out {out}: folder {out.parent} does not exist"
    )


def test_calibrate_refuses_an_output_under_a_file_naming_it_a_file(tmp_path: Path) -> None:
    # Seen (a hostile test): "folder ... does not exist" for a folder that was a file.
    (tmp_path / "notes").write_text("x")
    out = tmp_path / "notes" / "arm.yaml"
    proc = subprocess.run(
        [sys.executable, "-m", "bioscara_gym", "calibrate", "--out", str(out)],
        capture_output=True,
        text=True,
        check=False,
    )
    assert proc.returncode == 2
    expected = f"bioscara calibrate: error: --out {out}: {out.parent} is a file, not a folder"
    assert proc.stderr.strip() == expected


@pytest.mark.parametrize(
    ("command", "option", "path", "problem"),
    [
        ("calibrate", "--out", "/proc/arm.yaml", "cannot write in /proc: "),
        ("validate", "--json", "/proc/rows.json", "cannot write in /proc: "),
        ("validate", "--plots", "/proc/plots", "cannot write in /proc: "),
        ("validate", "--json", "/dev/null", "is not a regular file"),
    ],
)
def test_an_output_that_cannot_be_written_is_refused_before_the_work(
    command: str, option: str, path: str, problem: str, capsys: pytest.CaptureFixture[str]
) -> None:
    # Seen (a hostile test): calibrate --out /proc/c.yaml fitted on both CPUs for 10 minutes
    # and more; validate --json /proc/... replayed everything, then named a temporary file.
    if not Path("/proc").is_dir():
        pytest.skip("no /proc: a folder that refuses files")
    assert main([command, option, path]) == 2
    err = capsys.readouterr().err.strip()  # after "cannot write in": the system's own words
    assert "\n" not in err and err.startswith(f"bioscara {command}: error: {option} {path}: {problem}")


def test_calibrate_refuses_zero_workers_in_one_line(tmp_path: Path) -> None:
    proc = subprocess.run(
        [sys.executable, "-m", "bioscara_gym", "calibrate", "--out", str(tmp_path / "a.yml"), "--workers=0"],
        capture_output=True,
        text=True,
        check=False,
    )
    assert proc.returncode == 2
    assert proc.stderr.strip() == "bioscara calibrate: error: --workers must be >= 1, got 0"


def _children(pid: int) -> set[int]:
    path = Path(f"/proc/{pid}/task/{pid}/children")
    return {int(c) for c in path.read_text().split()} if path.exists() else set()


@pytest.mark.skipif(not Path(f"/proc/{os.getpid()}/task").is_dir(), reason="needs Linux's /proc")
def test_calibrate_stopped_by_sigterm_stops_its_fitting_workers(tmp_path: Path) -> None:
    # Seen (a hostile test): SIGTERM ended the main process at once; its two forked workers
    # went on fitting on both CPUs for minutes, until each was killed by hand.
    proc = subprocess.Popen(
        [
            sys.executable,
            "-m",
            "bioscara_gym",
            "calibrate",
            "--out",
            str(tmp_path / "a.yml"),
            "--workers",
            "2",
        ],
        stdout=subprocess.DEVNULL,
        stderr=subprocess.PIPE,
        text=True,
    )
    try:
        deadline = time.monotonic() + 120
        while len(_children(proc.pid)) < 2 and proc.poll() is None and time.monotonic() < deadline:
            time.sleep(0.2)
        workers = _children(proc.pid)
        assert len(workers) == 2, "the fit's workers never started"
        proc.send_signal(signal.SIGTERM)
        _, err = proc.communicate(timeout=30)
    finally:
        proc.kill()
    assert proc.returncode == 143
    assert err.strip() == "bioscara calibrate: interrupted by SIGTERM"
    assert not [w for w in workers if Path(f"/proc/{w}").exists()]
    assert not (tmp_path / "a.yml").exists()


def test_calibrate_fits_joints_in_worker_processes_with_the_same_result(
    tmp_path: Path, monkeypatch: pytest.MonkeyPatch
) -> None:
    # The drive fit itself is slow; a stand-in marks which process fitted which joint.
    import os

    from bioscara_gym.validation import calibrate as cal

    def fake_fit(config, joint, runs, limits=(), *, held, seed, maxiter, progress=None):
        (tmp_path / f"{joint}.{os.getpid()}").touch()
        pullout = 1000.0 * int(joint[1]) + seed + maxiter
        fitted = {"pullout_accel": pullout, "slip_fraction": 0.25, **held}
        return config.joint(joint).drive.with_values(**fitted)

    def fake_cost(config, runs, limits):
        # j1 and j3 fit better with the slipping rotor's push held at 0, j2 and j4 with it free.
        (joint,) = {r.joint for r in runs}
        slip = config.joint(joint).drive.slip_fraction
        return abs(slip - (0.0 if joint in ("j1", "j3") else 0.25)) + int(joint[1])

    monkeypatch.setattr(cal, "fit_drive", fake_fit)
    monkeypatch.setattr(cal, "drive_cost", fake_cost)
    monkeypatch.setattr(cal, "block_events", lambda signals: [])  # no swing fit
    rec = find_recordings(None)
    serial = cal.calibrate(CONFIG, rec, seed=3, maxiter=5, workers=1)
    forked = cal.calibrate(CONFIG, rec, seed=3, maxiter=5, workers=2)
    assert forked.config == serial.config
    assert forked.drive_cost_by_hypothesis == serial.drive_cost_by_hypothesis
    drives = [forked.config.joint(j).drive for j in ("j1", "j2", "j3", "j4")]
    assert [d.pullout_accel for d in drives] == [1008.0, 2008.0, 3008.0, 4008.0]
    assert [d.slip_fraction for d in drives] == [0.0, 0.25, 0.0, 0.25]
    assert forked.drive_cost_by_hypothesis == {
        "j1": (1.25, 1.0),
        "j2": (2.0, 2.25),
        "j3": (3.25, 3.0),
        "j4": (4.0, 4.25),
    }
    assert forked.drive_cost_after == {"j1": 1.0, "j2": 2.0, "j3": 3.0, "j4": 4.0}
    pids = {p.suffix for p in tmp_path.iterdir()}
    assert f".{os.getpid()}" in pids and len(pids) >= 2  # the serial fit here, the forked ones elsewhere


def _bowl(pullout: float, slip_fraction: float):
    """A drive cost whose floor (0) is j1 at this pull-out and push: it stands in for the slow replays."""

    def cost(config, runs, limits):
        d = config.joint("j1").drive
        return math.log10(d.pullout_accel / pullout) ** 2 + (d.slip_fraction - slip_fraction) ** 2

    return cost


def test_the_drive_fit_holds_what_a_hypothesis_holds_and_searches_the_rest(
    monkeypatch: pytest.MonkeyPatch,
) -> None:
    # The replays are slow; a bowl in the drive's fields stands in for them.
    # Its floor: pull-out 3000 rad/s², the slipping rotor pushed at 0.3 of it.
    from bioscara_gym.validation import calibrate as cal

    monkeypatch.setattr(cal, "drive_cost", _bowl(3000.0, 0.3))
    runs = [r for r in find_recordings(None).max_accel if r.joint == "j1"]
    free = cal.fit_drive(CONFIG, "j1", runs, maxiter=30, popsize=6)
    held = cal.fit_drive(CONFIG, "j1", runs, held={"slip_fraction": 0.0}, maxiter=30, popsize=6)
    assert free.pullout_accel == pytest.approx(3000.0, rel=0.02)
    assert free.slip_fraction == pytest.approx(0.3, abs=0.01)
    assert held.slip_fraction == 0.0
    assert held.pullout_accel == pytest.approx(3000.0, rel=0.02)
    with pytest.raises(ValueError, match=r"^j1: cannot hold noise: not a field the drive fit searches$"):
        cal.fit_drive(CONFIG, "j1", runs, held={"noise": 0.0})


def test_the_drive_fit_starts_from_the_configurations_drive_and_ends_no_worse() -> None:
    # A bowl whose floor is the packaged j1 (pull-out 919.7 rad/s^2, push 0.4367
    # of it): one generation of five points can only keep it, or find a point as good.
    from bioscara_gym.validation import calibrate as cal

    start = CONFIG.joint("j1").drive
    assert (start.pullout_accel, start.slip_fraction) == (919.7, 0.4367)
    bowl = _bowl(919.7, 0.4367)

    def cost(drive: DriveParams) -> float:
        return bowl(cal._with_drive(CONFIG, "j1", drive), (), ())

    fitted = cal._evolve(cost, start, cal.DRIVE_BOUNDS, 0, 1, 5, lambda stage, value: None)
    assert cost(fitted) < 1e-12
    # An ideal drive's unbounded fields start at their bounds, log-scaled ones as log10.
    ideal = cal._start(DriveParams(), cal.DRIVE_BOUNDS)
    assert ideal.tolist() == [5.0, math.log10(3000.0), 1.0, 0.0, 0.0, 0.0, 3.0, 30.0]


def test_the_drive_fit_keeps_a_self_locking_transmission_as_the_configuration_says() -> None:
    # self_locking is the joint's build (a lead screw), not a number the fit searches.
    from bioscara_gym.validation import calibrate as cal

    assert "self_locking" not in [name for name, *_ in cal.DRIVE_BOUNDS]
    x = cal._start(DriveParams(pullout_accel=1000.0), cal.DRIVE_BOUNDS)
    assert cal._drive_at(DriveParams(self_locking=True), cal.DRIVE_BOUNDS, x).self_locking is True
    assert cal._drive_at(DriveParams(), cal.DRIVE_BOUNDS, x).self_locking is False


def test_the_drive_fit_searches_the_slipped_rotors_fields_again_on_their_own(
    monkeypatch: pytest.MonkeyPatch,
) -> None:
    # Stage one: all eight fields from the configuration's drive; stage two:
    # push, its corner and the pull-in, the rest where stage one put them.
    from bioscara_gym.validation import calibrate as cal

    calls = []

    def evolve(cost, base, searched, seed, maxiter, popsize, say):
        calls.append((base, [b[0] for b in searched]))
        return base.with_values(pullout_accel=base.pullout_accel + 1.0)

    monkeypatch.setattr(cal, "_evolve", evolve)
    monkeypatch.setattr(cal, "drive_cost", lambda config, runs, limits: 0.0)
    runs = [r for r in find_recordings(None).max_accel if r.joint == "j1"]
    fitted = cal.fit_drive(CONFIG, "j1", runs)
    start = CONFIG.joint("j1").drive
    assert [c[1] for c in calls] == [
        [
            "pullout_accel",
            "corner_speed",
            "corner_exponent",
            "friction_coulomb",
            "friction_viscous",
            "slip_fraction",
            "slip_corner",
            "pullin_speed",
        ],
        ["slip_fraction", "slip_corner", "pullin_speed"],
    ]
    assert calls[0][0] == start
    assert calls[1][0].pullout_accel == start.pullout_accel + 1.0
    assert fitted.pullout_accel == pytest.approx(start.pullout_accel + 2.0, rel=1e-9)  # then the polish
    calls.clear()
    cal.fit_drive(CONFIG, "j1", runs, held={"slip_fraction": 0.0})
    assert [c[1][-2:] for c in calls] == [["slip_corner", "pullin_speed"]] * 2
    assert calls[0][0].slip_fraction == 0.0


def test_the_drive_fit_keeps_the_second_stage_when_the_polish_ends_worse(
    monkeypatch: pytest.MonkeyPatch,
) -> None:
    # Nelder-Mead may end on a point that costs more than its start (bounds
    # clip it): then the second stage's drive is the fit.
    import scipy.optimize

    from bioscara_gym.validation import calibrate as cal

    monkeypatch.setattr(cal, "_evolve", lambda cost, base, *rest: base.with_values(pullout_accel=1234.0))
    monkeypatch.setattr(cal, "drive_cost", lambda config, runs, limits: 0.0)
    worse = scipy.optimize.OptimizeResult(x=np.full(8, 0.5), fun=1.0)
    monkeypatch.setattr(scipy.optimize, "minimize", lambda *args, **kwargs: worse)
    runs = [r for r in find_recordings(None).max_accel if r.joint == "j1"]
    assert cal.fit_drive(CONFIG, "j1", runs).pullout_accel == 1234.0


def test_calibrate_names_each_hypothesis_cost_and_the_one_kept() -> None:
    from bioscara_gym.validation.calibrate import DRIVE_HYPOTHESES, hypotheses_line

    assert DRIVE_HYPOTHESES == ({}, {"slip_fraction": 0.0})
    assert hypotheses_line((0.0131, 0.0021)) == "all searched 0.0131, slip_fraction held at 0 0.0021 (kept)"
    assert hypotheses_line((0.0021, 0.0021)) == "all searched 0.0021 (kept), slip_fraction held at 0 0.0021"


def test_a_run_near_the_edge_of_its_pull_out_costs_the_fit_by_its_side() -> None:
    # The real verdicts bracket the edge: a held run should ask at most 0.9 of
    # the pull-out, a lost one at least 1.1; inside, the cost grows with the
    # square of the way in, one margin's width costing as much as a wrong verdict.
    from bioscara_gym.validation.calibrate import DEMAND_MARGIN, _margin_cost

    assert DEMAND_MARGIN == 0.1
    assert _margin_cost(0.9, lost=False) == 0.0
    assert _margin_cost(0.5, lost=False) == 0.0
    assert _margin_cost(0.96, lost=False) == pytest.approx(0.36)  # j1_1 on the fit without a margin
    assert _margin_cost(1.0, lost=False) == pytest.approx(1.0)
    assert _margin_cost(1.1, lost=True) == 0.0
    assert _margin_cost(394.0, lost=True) == 0.0
    assert _margin_cost(1.0, lost=True) == pytest.approx(1.0)
    assert _margin_cost(0.9, lost=True) == pytest.approx(4.0)


def test_the_drive_cost_charges_the_margin_of_every_run_and_stated_limit(
    monkeypatch: pytest.MonkeyPatch,
) -> None:
    from bioscara_gym.validation import calibrate as cal

    seen: list[tuple[float, bool]] = []

    def charged(demand: float, lost: bool) -> float:
        seen.append((demand, lost))
        return 1000.0

    monkeypatch.setattr(cal, "_margin_cost", charged)
    rec = find_recordings(None)
    j1 = sorted((r for r in rec.max_accel if r.joint == "j1"), key=lambda r: r.path.name)
    assert cal.drive_cost(CONFIG, j1, ()) > 3000.0
    # maxAccel/README.md: j1 held at 1 rad/s and 2 rad/s², lost steps at 3 rad/s² and at 2 rad/s.
    assert [lost for _, lost in seen] == [False, True, True]
    assert all(d > 0.0 for d, _ in seen)
    seen.clear()
    j3_limits = [lim for lim in cal.README_LIMITS if lim.joint == "j3"]
    assert cal.drive_cost(CONFIG, (), j3_limits) == 3000.0  # every verdict as stated
    assert [lost for _, lost in seen] == [False, True, False]
    assert all(d > 0.0 for d, _ in seen)


def test_plots_are_written_all_or_none(tmp_path: Path, monkeypatch: pytest.MonkeyPatch) -> None:
    # Seen (a hostile test): SIGTERM during validate --plots left 4 to 37 of the 41 PNGs.
    pytest.importorskip("matplotlib")
    from bioscara_gym.validation import plots

    (tmp_path / "maxAccel").mkdir()
    shutil.copy(DATA_DIR / "maxAccel" / "j3_6.csv", tmp_path / "maxAccel")
    (tmp_path / "RW_test").mkdir()
    shutil.copy(DATA_DIR / "RW_test" / "position_100kHz.csv.gz", tmp_path / "RW_test")
    result = validate(tmp_path, CONFIG)
    out = tmp_path / "plots"
    names = sorted(p.name for p in plots.write_plots(result, out))
    assert names and sorted(p.name for p in out.iterdir()) == names  # nothing hidden left
    assert all(p.suffix == ".png" for p in out.iterdir())

    def interrupted(v: object, folder: Path) -> list[Path]:
        raise KeyboardInterrupt  # after maxAccel's pictures were drawn

    monkeypatch.setattr(plots, "_transactions", interrupted)
    with pytest.raises(KeyboardInterrupt):
        plots.write_plots(result, tmp_path / "new")
    assert not (tmp_path / "new").exists()
    (out / "mine.txt").write_text("kept", encoding="utf-8")
    before = {p.name: p.stat().st_mtime_ns for p in out.iterdir()}
    with pytest.raises(KeyboardInterrupt):
        plots.write_plots(result, out)
    assert {p.name: p.stat().st_mtime_ns for p in out.iterdir()} == before
