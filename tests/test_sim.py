"""The MuJoCo arm behind firmware-faithful joints (issue "MuJoCo model ... firmware-faithful joints").

The firmware rules of docs/firmware.md (the behaviour the emulator must
reproduce) act on MuJoCo physics here: homing pushes the link into its end
stop, stall detection trips on the lag of a link held by an obstacle or
starved of torque, the deadman stops a joint in simulated time. The joint
contract itself (refusals, flags, offsets) is ``test_conformance.py``'s, which
runs on the MuJoCo rigs too.

Time is simulated: ``backend.step(dt)`` and ``backend.clock.sleep(dt)`` step
firmware ticks and physics together. Fixtures are in ``conftest.py``
(``mujoco_arm``, ``homing_run``).
"""

from __future__ import annotations

import math
from collections.abc import Callable

import mujoco
import numpy as np
import pytest
from conftest import HomingRun, near_max_pose, ready_arm
from rigs import park_obstacle, place_obstacle

from bioscara_gym.assets import scene_path
from bioscara_gym.hardware.backends import Backend, make_backend
from bioscara_gym.hardware.config import load_config
from bioscara_gym.hardware.errors import StalledError
from bioscara_gym.hardware.registers import DEADMAN_S, HOMING_SETTLE_S, TICK_S, Flag
from bioscara_gym.hardware.sim import ArmSim
from bioscara_gym.hardware.transmission import rpm_to_velocity, velocity_to_rpm

#: Homing accuracy the issue asks for: 1 mm on the lift, 0.2 deg on the revolute joints.
HOMING_TOLERANCE = {"j1": math.radians(0.2), "j2": 0.001, "j3": math.radians(0.2), "j4": math.radians(0.2)}
#: Host control period while a test runs the arm, seconds (the firmware's tick).
PERIOD_S = 0.01
#: Duration of each velocity step: j3 reverses from -5 to +5 rad/s in 0.71 s at its SPEC 14 rad/s^2.
STEP_S = 0.8


# ----------------------------------------------------------------- helpers


def sim_of(backend: Backend) -> ArmSim:
    """The MuJoCo arm behind ``backend``."""
    assert isinstance(backend.sim, ArmSim)
    return backend.sim


def qpos(backend: Backend, name: str) -> float:
    """True position of joint ``name`` (rad or m), from MuJoCo."""
    sim = sim_of(backend)
    return float(sim.data.qpos[sim.model.joint(name).qposadr[0]])


def qvel(backend: Backend, name: str) -> float:
    """True velocity of joint ``name`` (rad/s or m/s), from MuJoCo."""
    sim = sim_of(backend)
    return float(sim.data.qvel[sim.model.joint(name).dofadr[0]])


def run(backend: Backend, seconds: float, poll: Callable[[], object] | None = None) -> None:
    """Let ``seconds`` of simulated time pass, talking to the arm every :data:`PERIOD_S` via ``poll``."""
    for _ in range(round(seconds / PERIOD_S)):
        backend.step(PERIOD_S)
        if poll is not None:
            poll()


def poll_all(backend: Backend) -> Callable[[], None]:
    """A poll that reads every joint's velocity (one transaction each, as the arm layer's read)."""

    def poll() -> None:
        for joint in backend.joints.values():
            joint.get_velocity()

    return poll


def home(backend: Backend, name: str) -> None:
    """Home joint ``name`` as the arm layer does: at its homing acceleration, then its max again."""
    j = backend.config.joint(name)
    joint = backend.joints[name]
    joint.set_max_acceleration(j.homing.acceleration)
    joint.home(j.homing.speed, j.homing.threshold, j.homing.current)
    joint.set_max_acceleration(j.max_acceleration)


def commanded_homing_speed(speed: float, reduction: float) -> float:
    """The joint speed (> 0) HOME actually carries: the motor RPM as one whole byte, truncated.

    j3 and j4 home at 11 RPM instead of 11.46, 4 % slower than configured.
    """
    return abs(rpm_to_velocity(int(abs(velocity_to_rpm(speed, reduction))), reduction))


# ------------------------------------------------------------------ homing
#
# ``homing_run`` (conftest.py) homes each joint to each end stop from 2 % of its
# range inside it and records the true position at every 10 ms poll.


def _arrival(h: HomingRun) -> int:
    """Index of the first poll with the link at the end stop (within the homing tolerance)."""
    at_stop = np.abs(h.qpos - h.limit) <= HOMING_TOLERANCE[h.name]
    assert at_stop.any(), f"{h.name} never reached its end stop"
    return int(np.argmax(at_stop))


def test_homing_reports_the_end_stop_as_the_limit(homing_run: HomingRun) -> None:
    h = homing_run
    reported = h.backend.joints[h.name].get_position()
    assert reported == pytest.approx(h.limit, abs=HOMING_TOLERANCE[h.name])


def test_homing_leaves_the_link_at_the_end_stop(homing_run: HomingRun) -> None:
    h = homing_run
    assert qpos(h.backend, h.name) == pytest.approx(h.limit, abs=HOMING_TOLERANCE[h.name])


def test_homing_takes_the_travel_time_at_homing_speed_plus_settle(homing_run: HomingRun) -> None:
    h = homing_run
    speed = abs(h.backend.config.joint(h.name).homing.speed)
    least = abs(h.limit - h.start) / speed + HOMING_SETTLE_S
    assert least <= h.elapsed_s <= 3 * least, f"{h.name}: took {h.elapsed_s:.2f} s, least {least:.2f} s"


def test_homing_holds_still_while_it_settles(homing_run: HomingRun) -> None:
    h = homing_run
    j = h.backend.config.joint(h.name)
    settling = h.qpos[h.times < HOMING_SETTLE_S - TICK_S / 2]
    assert len(settling) >= 40  # polls start after the driver's pick-up wait (60 ms)
    # Held by the drive: only its compliance shows (the lift sags ~16 um under its weight).
    np.testing.assert_allclose(settling, h.start, atol=1e-4 * (j.max - j.min))


def test_homing_moves_monotonically_toward_the_end_stop(homing_run: HomingRun) -> None:
    h = homing_run
    settled = int(np.argmax(h.times >= HOMING_SETTLE_S - TICK_S / 2))
    steps = np.diff(h.qpos[settled : _arrival(h) + 1]) * h.direction
    # Up to 1e-6 (m or rad) back: the drive's compliance as the rotor starts (the lift
    # sinks 18 nm under its weight before its load angle builds), not a move.
    assert steps.min() >= -1e-6, f"{h.name} moved away from the end stop by {-steps.min():.3g}"


def test_homing_rebounds_from_the_end_stop_by_less_than_the_tolerance(homing_run: HomingRun) -> None:
    h = homing_run
    assert np.abs(h.qpos[_arrival(h) :] - h.limit).max() <= HOMING_TOLERANCE[h.name]


def test_homing_runs_at_the_homing_speed(homing_run: HomingRun) -> None:
    # The joint ramps up at its homing acceleration (the arm sets it before HOME, as the
    # seed does) to the homing speed: v(t) = min(speed, a t) after the settle. j1 and j2
    # cruise after 3 s; j3 (0.01 rad/s^2 to 0.05 rad/s) meets its stop still ramping.
    h = homing_run
    j = h.backend.config.joint(h.name)
    speed = commanded_homing_speed(j.homing.speed, j.reduction)
    t = h.times - HOMING_SETTLE_S
    expected = np.minimum(speed, j.homing.acceleration * np.clip(t, 0.0, None))
    # The middle of the run, between the settle and the end stop.
    arrive = t[_arrival(h)]
    middle = ((t > 0.2 * arrive) & (t < 0.8 * arrive))[1:]
    velocity = np.diff(h.qpos) / PERIOD_S * h.direction
    assert velocity[middle].mean() == pytest.approx(expected[1:][middle].mean(), rel=0.03)
    assert velocity.max() <= 1.1 * speed, "a jump: homing must drive the link, not teleport it"


# ------------------------------------------------------------------- stall


#: j1's speed into the obstacle: 0.3 rad/s is 10.5 rad/s at the motor, so the
#: blocked rotor shows 601 deg/s x 1 ms x 51,200/360 = 85 microsteps a pass:
#: above the threshold (60) and within the firmware's spike limit (a jump of
#: more than 100 is dropped, docs/firmware.md "Stall detection").
INTO_OBSTACLE = -0.3


@pytest.fixture
def j1_driven_into_obstacle(mujoco_arm: Backend) -> Backend:
    """j1 homed, stall detection on, running at -0.3 rad/s into the obstacle 2 cm ahead of the elbow."""
    backend = mujoco_arm
    joint, j = backend.joints["j1"], backend.config.joint("j1")
    home(backend, "j1")
    joint.enable_stallguard(j.stall_threshold)
    place_obstacle(sim_of(backend), "j1", direction=-1, gap=0.02)
    joint.set_velocity(INTO_OBSTACLE)
    for _ in range(round(1.0 / PERIOD_S)):
        backend.step(PERIOD_S)
        if joint.get_flags() & Flag.STALL:
            return backend
    pytest.fail(f"j1 never stalled against the obstacle; at {qpos(backend, 'j1'):.4f} rad")


def test_joint_driven_into_obstacle_stalls(j1_driven_into_obstacle: Backend) -> None:
    backend = j1_driven_into_obstacle
    assert backend.joints["j1"].is_stalled()
    assert sim_of(backend).cores["j1"].flags & Flag.STALL


def test_joint_stalls_at_the_obstacle_not_before(j1_driven_into_obstacle: Backend) -> None:
    backend = j1_driven_into_obstacle
    sim = sim_of(backend)
    obstacle = sim.model.geom("obstacle").id
    touching = [c for c in sim.data.contact[: sim.data.ncon] if obstacle in (c.geom1, c.geom2)]
    assert touching, "stalled with the arm clear of the obstacle"


def test_set_velocity_after_stall_raises_stalled_error(j1_driven_into_obstacle: Backend) -> None:
    with pytest.raises(StalledError):
        j1_driven_into_obstacle.joints["j1"].set_velocity(-0.5)


def test_stalled_joint_comes_to_rest(j1_driven_into_obstacle: Backend) -> None:
    backend = j1_driven_into_obstacle
    run(backend, 0.2, poll_all(backend))
    assert abs(qvel(backend, "j1")) < 1e-3
    before = qpos(backend, "j1")
    run(backend, 0.5, poll_all(backend))
    assert qpos(backend, "j1") == pytest.approx(before, abs=1e-4)


def test_stalled_joint_refuses_motion_after_the_obstacle_is_removed(j1_driven_into_obstacle: Backend) -> None:
    backend = j1_driven_into_obstacle
    joint = backend.joints["j1"]
    park_obstacle(sim_of(backend))
    before = qpos(backend, "j1")
    for _ in range(10):
        with pytest.raises(StalledError):
            joint.set_velocity(-0.5)
        run(backend, 0.05)
    assert qpos(backend, "j1") == pytest.approx(before, abs=1e-4)


def test_reenabled_joint_moves_again_once_the_obstacle_is_removed(j1_driven_into_obstacle: Backend) -> None:
    backend = j1_driven_into_obstacle
    joint, j = backend.joints["j1"], backend.config.joint("j1")
    park_obstacle(sim_of(backend))
    joint.enable(j.drive_current, j.hold_current)
    joint.enable_stallguard(j.stall_threshold)
    before = qpos(backend, "j1")
    joint.set_velocity(-0.5)
    run(backend, 0.5, poll_all(backend))
    assert not joint.get_flags() & Flag.STALL
    assert qvel(backend, "j1") == pytest.approx(-0.5, rel=1e-3)
    assert qpos(backend, "j1") < before - 0.15


@pytest.mark.parametrize(
    ("pushes", "held"),
    [
        ((0.0, 0.0, 0.0, 0.0, -4.0), False),  # one 2 ms step at 4x its force: a rattling block
        ((-1.0, -1.0, -1.0, -1.0, -1.0), True),  # the drive's force for the whole tick: an obstacle
        ((-1.0, -1.0, -1.0, -1.0, -0.6), True),  # a mean of 0.92 of it, the last step under 0.9
        ((-0.8, -0.8, -0.8, -0.8, -1.2), False),  # a mean of 0.88 of it, the last step over 0.9
    ],
)
def test_a_contact_holds_the_rotor_by_its_mean_force_over_the_tick(
    mujoco_arm: Backend, pushes: tuple[float, ...], held: bool
) -> None:
    # A rotor is held once the constraints push against its drive with more than
    # CONTACT_FRACTION (0.9) of the drive's force at its current, over the tick's
    # five 2 ms physics steps: the grasped block that rattles between the fingers
    # kicks j1 for one step with 3-5 N m, about j1's 3.5 N m at 20 % current or
    # more (seed 0 of PickPlace-v1, velocity mode), and the real stepper rides it out.
    backend = mujoco_arm
    home(backend, "j1")
    backend.joints["j1"].set_velocity(-0.2)  # away from the end stop it homed at
    run(backend, 0.3, poll_all(backend))
    motor = sim_of(backend).motors["j1"]
    data, model = motor._data, motor._model
    force = model.actuator_forcerange[motor._act_id, 1]  # the drive's force at this current
    assert force == pytest.approx(17.5 * 0.2)
    forces = sim_of(backend)._forces
    for push in pushes:
        data.actuator_force[motor._act_id] = -force
        data.qfrc_constraint[motor._dadr] = -push * force
        forces.sample()
    motor.end_physics()
    assert motor.stepper.held is held


# ------------------------------------------- acceleration beyond the torque


def _velocity_steps(backend: Backend, name: str, acceleration: float) -> tuple[float | None, list[float]]:
    """Run ``name`` through velocity steps at a ramp of ``acceleration`` (rad/s^2).

    The joint is homed and stall detection is on with its configured
    threshold. The steps, v the SPEC max velocity: -v, 0, +v, 0, each for
    :data:`STEP_S`: from rest, as the real arm's max-acceleration runs went
    (j3 reached 5 rad/s at 14 rad/s^2, run j3_17, not at 15, j3_18). A full
    reversal at 14 is beyond what the recordings show: the calibrated j3
    drive, at its edge there, reaches 4.5 rad/s of 5.

    Returns:
        When it stalled (s after the first step; None if it did not), and
        the joint's true velocity at the end of each step it completed.
    """
    joint, j = backend.joints[name], backend.config.joint(name)
    home(backend, name)
    joint.enable_stallguard(j.stall_threshold)
    joint.set_max_acceleration(acceleration)
    poll = poll_all(backend)
    t0, reached = backend.clock.now(), []
    for v in (-j.max_velocity, 0.0, j.max_velocity, 0.0):
        try:
            joint.set_velocity(v)
        except StalledError:
            return backend.clock.now() - t0, reached
        for _ in range(round(STEP_S / PERIOD_S)):
            backend.step(PERIOD_S)
            poll()
            if joint.is_stalled():
                return backend.clock.now() - t0, reached
        reached.append(qvel(backend, name))
    return None, reached


def test_spec_max_acceleration_follows_velocity_steps_without_stalling(mujoco_arm: Backend) -> None:
    j3 = mujoco_arm.config.joint("j3")
    stalled, reached = _velocity_steps(mujoco_arm, "j3", j3.max_acceleration)
    assert stalled is None, f"j3 stalled at {stalled:.2f} s with its SPEC acceleration"
    v = j3.max_velocity
    np.testing.assert_allclose(reached, [-v, 0.0, v, 0.0], atol=1e-2 * v)


def test_ten_times_spec_max_acceleration_wraps_to_a_gentle_ramp(mujoco_arm: Backend) -> None:
    # 140 rad/s^2 at j3 is 192,514 deg/s^2 at the motor, AMAX 602,355: the library's
    # 16-bit AMAX keeps 602,355 mod 65,536 = 12,530, 4,005 deg/s^2 = 2.91 rad/s^2
    # at the joint (docs/model.md, limits). The first step (-5 rad/s) is still
    # ramping after 0.8 s: 2.33 rad/s.
    j3 = mujoco_arm.config.joint("j3")
    stalled, reached = _velocity_steps(mujoco_arm, "j3", 10 * j3.max_acceleration)
    assert stalled is None
    assert reached[0] == pytest.approx(-2.91 * STEP_S, rel=0.02)


def test_fifty_times_spec_max_acceleration_is_not_flagged(mujoco_arm: Backend) -> None:
    # 700 rad/s^2 wraps to 62,652 AMAX units, 14.56 rad/s^2 at the joint: the 16-bit
    # register brings it back to about the SPEC acceleration, which j3 follows.
    j3 = mujoco_arm.config.joint("j3")
    stalled, _ = _velocity_steps(mujoco_arm, "j3", 50 * j3.max_acceleration)
    assert stalled is None


# ----------------------------------------------------------------- deadman


@pytest.fixture
def j1_in_velocity_mode(mujoco_arm: Backend) -> Backend:
    """j1 homed and running at -0.5 rad/s for 0.5 s, the host polling every 10 ms."""
    home(mujoco_arm, "j1")
    mujoco_arm.joints["j1"].set_velocity(-0.5)
    run(mujoco_arm, 0.5, poll_all(mujoco_arm))
    assert qvel(mujoco_arm, "j1") == pytest.approx(-0.5, rel=1e-3)
    return mujoco_arm


def test_an_unpowered_joints_encoder_reads_the_speed_its_link_coasts_at(j1_in_velocity_mode: Backend) -> None:
    # Seen: with its current cut while turning, j1 coasted on in MuJoCo and
    # GETENCODERRPM read 0; the real encoder is on the shaft the link turns.
    # Its speed estimate lags the shaft by about 50 ms, so while the link slows
    # down the reading lies between its speed now and 80 ms ago.
    backend = j1_in_velocity_mode
    joint = backend.joints["j1"]
    speeds = [qvel(backend, "j1")] * 8
    joint.set_drive_current(0)
    for _ in range(20):
        backend.step(0.01)
        speeds.append(qvel(backend, "j1"))
        read = joint.get_velocity()
        assert speeds[-9] <= read <= speeds[-1]  # negative speeds, slowing down
    assert speeds[-1] > -0.4  # it did slow down: nothing drives it
    assert speeds[-1] < -0.3  # and it still turns


def test_deadman_tolerates_40ms_of_simulated_silence(j1_in_velocity_mode: Backend) -> None:
    backend = j1_in_velocity_mode
    backend.step(0.04)
    assert not sim_of(backend).cores["j1"].flags & Flag.NOT_ENABLED
    assert qvel(backend, "j1") == pytest.approx(-0.5, rel=1e-3)


def test_deadman_trips_after_50ms_of_simulated_silence(j1_in_velocity_mode: Backend) -> None:
    backend = j1_in_velocity_mode
    backend.step(DEADMAN_S + 2 * TICK_S)
    assert sim_of(backend).cores["j1"].flags & Flag.NOT_ENABLED
    assert backend.joints["j1"].get_flags() & Flag.NOT_ENABLED


def test_deadman_decelerates_the_joint_to_rest(j1_in_velocity_mode: Backend) -> None:
    backend = j1_in_velocity_mode
    a = backend.config.joint("j1").max_acceleration
    backend.step(DEADMAN_S + 2 * TICK_S)
    velocities = []
    for _ in range(round(0.6 / TICK_S)):
        backend.step(TICK_S)  # still silent: the host is gone
        velocities.append(qvel(backend, "j1"))
    speeds = np.abs(velocities)
    # The firmware ramps the set point to 0 at max acceleration; the link follows it
    # (no hard brake, overshoot past 0 of ~1 % of the speed).
    t = np.arange(len(speeds)) * TICK_S
    ramp = np.maximum(speeds[0] - a * t, 0.0)
    assert speeds[0] > 0.4
    np.testing.assert_allclose(speeds, ramp, atol=0.02)
    rest = round((speeds[0] / a + 0.2) / TICK_S)
    assert np.all(speeds[rest:] < 1e-3), f"still moving at {speeds[rest:].max():.2g} rad/s"


# ------------------------------------------------------------- determinism


def _scripted_trajectory(backend_name: str) -> np.ndarray:
    """Home every joint at once, then run velocity and position commands; qpos every 10 ms."""
    with make_backend(backend_name, initial_qpos=near_max_pose(load_config())) as backend:
        ready_arm(backend)
        sim = sim_of(backend)
        joints = backend.joints
        trajectory = [sim.data.qpos.copy()]

        def tick(poll: Callable[[], object]) -> None:
            backend.step(PERIOD_S)
            poll()
            trajectory.append(sim.data.qpos.copy())

        for name, joint in joints.items():
            h = backend.config.joint(name).homing
            joint.set_max_acceleration(h.acceleration)
            joint.start_homing(h.speed, h.threshold, h.current)
        while any([joint.get_flags() & Flag.BUSY for joint in joints.values()]):  # poll every joint
            tick(lambda: None)
        for name, joint in joints.items():
            joint.post_homing()
            joint.set_max_acceleration(backend.config.joint(name).max_acceleration)  # as the arm does
        joints["j1"].set_velocity(-0.5)
        joints["j4"].set_velocity(3.0)
        joints["j2"].set_position(0.25)
        joints["j3"].set_position(0.8)
        for _ in range(100):
            tick(poll_all(backend))
        joints["j1"].set_velocity(0.2)
        joints["j4"].stop()
        for _ in range(50):
            tick(poll_all(backend))
        return np.array(trajectory)


@pytest.fixture(scope="module")
def scripted() -> dict[str, np.ndarray]:
    """:func:`_scripted_trajectory` on each MuJoCo backend, run once per module."""
    return {name: _scripted_trajectory(name) for name in ("sim", "emulated")}


def test_scripted_trajectory_moves_every_joint(scripted: dict[str, np.ndarray]) -> None:
    model = mujoco.MjModel.from_xml_path(str(scene_path()))
    for name in ("j1", "j2", "j3", "j4"):
        adr = model.joint(name).qposadr[0]
        assert np.ptp(scripted["sim"][:, adr]) > 0.01, f"{name} did not move: the comparisons prove nothing"


@pytest.mark.parametrize("backend_name", ["sim", "emulated"])
def test_same_commands_give_identical_trajectories(
    backend_name: str, scripted: dict[str, np.ndarray]
) -> None:
    again = _scripted_trajectory(backend_name)
    assert np.array_equal(again, scripted[backend_name])


def test_sim_and_emulated_give_the_same_trajectory(scripted: dict[str, np.ndarray]) -> None:
    sim, emulated = scripted["sim"], scripted["emulated"]
    assert sim.shape == emulated.shape
    # Not bit-identical: the bus carries float32 payloads (limits, set points), SimJoint
    # Python floats. A float32 of ~1000 motor degrees rounds by ~1e-4 deg, i.e. < 1e-7
    # rad at the joint (7e-8 rad measured on j3).
    np.testing.assert_allclose(emulated, sim, rtol=0, atol=1e-6)
