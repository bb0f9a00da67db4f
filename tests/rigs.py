"""Joint test rigs: one backend each, behind one small interface.

The conformance suite (``test_conformance.py``) runs every test against every
rig in :data:`RIG_FACTORIES`. A rig bundles a :class:`BaseJoint` that is not
yet ``init()``-ed with the handles a test needs to act on the world around it:
let time pass, hold the joint, cut its power, restart the host program.

Adding a backend is adding one factory (a function with no arguments that
returns a fresh :class:`JointRig`) to :data:`RIG_FACTORIES` and listing in its
``features`` which of :data:`FEATURES` it supports; tests that need a missing
feature are skipped with a reason.

Joint parameters are docs/model.md's (kinematics table and the arm's parameter
file), as :class:`~bioscara_gym.hardware.config.JointConfig` values.
"""

from __future__ import annotations

import contextlib
import errno
import functools
import io
import json
import math
import os
import re
import subprocess
import sys
import textwrap
from collections.abc import Callable, Iterator
from dataclasses import dataclass, field
from pathlib import Path
from typing import TYPE_CHECKING, Any

import mujoco
import numpy as np
import pytest

from bioscara_gym.hardware.arm import Arm
from bioscara_gym.hardware.backends import Backend, EmulatedBackend, make_backend
from bioscara_gym.hardware.base_joint import BaseJoint
from bioscara_gym.hardware.clock import Clock, ManualClock
from bioscara_gym.hardware.codec import pack_bytes
from bioscara_gym.hardware.config import ArmConfig, HomingConfig, JointConfig, load_config
from bioscara_gym.hardware.emulated_bus import EmulatedI2CBus, FaultPlan
from bioscara_gym.hardware.firmware import MICROSTEPS_PER_DEG, JointFirmware
from bioscara_gym.hardware.joint import Joint
from bioscara_gym.hardware.mock import MockJoint
from bioscara_gym.hardware.motor import KinematicStepper
from bioscara_gym.hardware.registers import BLOCKING_PICKUP_S, Flag, Reg
from bioscara_gym.hardware.sim import ArmSim, SimJoint

if TYPE_CHECKING:
    from bioscara_gym.hardware.sitl import SitlFirmware

#: Features a rig may have; tests that need one skip rigs without it.
FEATURES = frozenset(
    {
        "stall",  # stall detection trips when the joint is held (needs block/unblock)
        "deadman",  # the firmware's 50 ms deadman in velocity mode
        "power_cycle",  # the joint's power can be cut (HOMEOFFSET and homing lost)
        "host_restart",  # a second host object can talk to the same device
        "physics",  # end stops, ramps, lag: motion takes time and stops at real limits
    }
)

#: docs/model.md j1 (shoulder): kinematics table and parameter file.
J1 = JointConfig(
    name="j1",
    address=0x11,
    joint_type="revolute",
    reduction=35.0,
    min=-3.04647,
    max=3.04647,
    max_velocity=1.0,
    max_acceleration=2.0,
    stall_threshold=6,
    hold_current=20,
    drive_current=20,
    homing=HomingConfig(speed=0.03, threshold=30, current=15, acceleration=0.01),
)

#: docs/model.md j2 (lift): negative reduction, a positive motor turn moves it down.
J2 = JointConfig(
    name="j2",
    address=0x12,
    joint_type="prismatic",
    reduction=-2 * math.pi / 0.004,
    min=-0.0016,
    max=0.338,
    max_velocity=0.03,
    max_acceleration=0.2,
    stall_threshold=12,
    hold_current=40,
    drive_current=40,
    homing=HomingConfig(speed=0.003, threshold=50, current=30, acceleration=0.001),
)


def _unsupported(what: str) -> Callable[..., None]:
    def fail(*_: object) -> None:
        raise NotImplementedError(f"this rig does not support {what}; check rig.features first")

    return fail


@dataclass
class JointRig:
    """One joint backend under test, with handles on the world around it.

    Attributes:
        name: Rig id (used as the pytest parameter id).
        joint: The joint under test, created but not ``init()``-ed.
        params: The joint's parameters (limits, currents, homing, stall threshold).
        clock: The rig's clock (``now()``, ``sleep(dt)``): a manual clock, or
            the simulation's clock whose ``sleep`` steps physics; the joint
            waits on it.
        advance: ``advance(dt)`` lets ``dt`` seconds pass with no host
            traffic while the device keeps running its main loop.
        device_flags: The device's own flags, read without bus traffic.
        restart_host: Simulates the host program restarting: returns a new,
            not ``init()``-ed joint object on the same device. The old object
            is left as it was (the old process is gone, it sends nothing).
        features: Which of :data:`FEATURES` this rig supports.
        block: Hold the joint so it cannot move (feature ``"stall"``).
        unblock: Release it again (feature ``"stall"``).
        power_cycle: Cut and restore the joint's power (feature ``"power_cycle"``).
        power_up_at: Optional. Cut the power and restore it with the joint at
            ``q`` (rad or m): a fresh device at another pose. Rigs whose homing
            runs in simulated physics at the homing speed provide it, so a test
            that homes to ``min`` can start near ``min`` instead of spending
            minutes of simulated time travelling there.
    """

    name: str
    joint: BaseJoint
    params: JointConfig
    clock: Clock
    advance: Callable[[float], None]
    device_flags: Callable[[], Flag]
    restart_host: Callable[[], BaseJoint] = field(default=_unsupported("host_restart"))
    features: frozenset[str] = frozenset()
    block: Callable[[], None] = field(default=_unsupported("block"))
    unblock: Callable[[], None] = field(default=_unsupported("unblock"))
    power_cycle: Callable[[], None] = field(default=_unsupported("power_cycle"))
    power_up_at: Callable[[float], None] | None = None

    def __post_init__(self) -> None:
        """Reject unknown feature names (a typo would silently skip tests)."""
        unknown = self.features - FEATURES
        if unknown:
            raise ValueError(
                f"rig {self.name}: unknown features {sorted(unknown)}; known: {sorted(FEATURES)}"
            )

    def has(self, feature: str) -> bool:
        """Whether the rig supports ``feature`` (one of :data:`FEATURES`)."""
        if feature not in FEATURES:
            raise ValueError(f"unknown feature {feature!r}; known: {sorted(FEATURES)}")
        return feature in self.features


# ---------------------------------------------------------------- emulated


def motor_degrees(q: float, params: JointConfig) -> float:
    """Absolute motor degrees of joint position ``q`` (offset 0): ``rad2deg(reduction * q)``."""
    return math.degrees(params.reduction * q)


@dataclass
class EmulatedJoint:
    """The real :class:`Joint` driver over an emulated bus, with every layer exposed."""

    params: JointConfig
    clock: ManualClock
    motor: KinematicStepper
    firmware: JointFirmware
    bus: EmulatedI2CBus
    joint: Joint

    def new_joint(self, retries: int = 2) -> Joint:
        """A new driver object for the same device (as after a host restart)."""
        p = self.params
        return Joint(
            p.name, p.address, p.reduction, p.min, p.max, self.bus, retries=retries, clock=self.clock
        )

    def advance(self, dt: float) -> None:
        """Let ``dt`` seconds pass without traffic; the firmware's main loop runs."""
        self.clock.sleep(dt)
        self.bus.update()


def build_emulated(
    params: JointConfig,
    start_q: float,
    faults: FaultPlan | None = None,
    retries: int = 2,
) -> EmulatedJoint:
    """Build ``Joint`` -> ``EmulatedI2CBus`` -> ``JointFirmware`` -> ``KinematicStepper``.

    The stepper's end stops sit at the joint limits, converted to absolute
    motor degrees with the joint's signed reduction (so for j2 the joint's
    ``max`` is the motor's lower stop); the rotor starts at ``start_q``.

    Args:
        params: Joint parameters (address, reduction, limits).
        start_q: Initial joint position, rad or m, strictly inside the limits.
        faults: Fault plan of the bus (none by default).
        retries: The driver's retries.
    """
    if not params.min < start_q < params.max:
        raise ValueError(f"{params.name}: start {start_q} must lie inside {params.min}..{params.max}")
    stops = sorted((motor_degrees(params.min, params), motor_degrees(params.max, params)))
    clock = ManualClock()
    motor = KinematicStepper(motor_degrees(start_q, params), lower_stop_deg=stops[0], upper_stop_deg=stops[1])
    firmware = JointFirmware(motor, clock)
    bus = EmulatedI2CBus({params.address: firmware}, faults=faults, clock=clock)
    p = params
    joint = Joint(p.name, p.address, p.reduction, p.min, p.max, bus, retries=retries, clock=clock)
    return EmulatedJoint(params, clock, motor, firmware, bus, joint)


def home_and_enable(emu: EmulatedJoint, timeout_s: float = 60.0) -> EmulatedJoint:
    """Connect ``emu``'s joint, enable it, home it (configured parameters) and set its limits."""
    p, j = emu.params, emu.joint
    j.init()
    j.enable(p.drive_current, p.hold_current)
    j.home(p.homing.speed, p.homing.threshold, p.homing.current, timeout_s=timeout_s)
    j.set_max_velocity(p.max_velocity)
    j.set_max_acceleration(p.max_acceleration)
    return emu


def _emulated_rig(name: str, params: JointConfig, start_q: float) -> JointRig:
    emu = build_emulated(params, start_q)

    def block() -> None:
        emu.motor.blocked = True

    def unblock() -> None:
        emu.motor.blocked = False

    return JointRig(
        name=name,
        joint=emu.joint,
        params=params,
        clock=emu.clock,
        advance=emu.advance,
        device_flags=lambda: emu.firmware.flags,
        restart_host=emu.new_joint,
        features=frozenset({"stall", "deadman", "power_cycle", "host_restart", "physics"}),
        block=block,
        unblock=unblock,
        power_cycle=emu.firmware.power_cycle,
    )


def emulated_kinematic_j1() -> JointRig:
    """j1 (revolute, reduction 35) on the emulated bus, starting at q = 2.9 rad."""
    return _emulated_rig("emulated_kinematic_j1", J1, start_q=2.9)


def emulated_kinematic_j2() -> JointRig:
    """j2 (prismatic, reduction -1570.8) on the emulated bus, starting at q = 0.3 m."""
    return _emulated_rig("emulated_kinematic_j2", J2, start_q=0.3)


# -------------------------------------------------------------------- mock


def mock_j1() -> JointRig:
    """:class:`MockJoint` with j1's parameters and a manual clock.

    The mock is its own device, so a new object is a new device: no
    ``host_restart``. It has no stalls, no deadman and no physics.
    """
    clock = ManualClock()
    p = J1
    joint = MockJoint(p.name, p.reduction, p.min, p.max, clock=clock, homing_time_s=1.0)
    return JointRig(
        name="mock_j1",
        joint=joint,
        params=p,
        clock=clock,
        advance=clock.sleep,
        device_flags=lambda: Flag(joint.device_flags),
        features=frozenset({"power_cycle"}),
        power_cycle=joint.power_cycle,
    )


# ------------------------------------------------------------------ MuJoCo

#: Power-up pose of the MuJoCo rigs. The joints under test (j1, j2) start a
#: short homing run inside their ``max`` end stop (j1 0.047 rad = 1.6 s at
#: 0.03 rad/s, j2 5 mm = 1.7 s at 3 mm/s); j3 and j4 are as in the model's
#: ``home`` keyframe, the elbow bent so that the forearm stays clear of where
#: :func:`place_obstacle` puts the obstacle for j1 and j2. With j1 near +-pi the
#: arm reaches over the empty back of the table, away from the block.
SIM_POSE = {"j1": 3.0, "j2": 0.333, "j3": 1.2, "j4": -0.6}

#: The geom :func:`place_obstacle` puts the obstacle against, per joint: a part
#: of the link that joint moves with nothing else of the arm beside it
#: (j1 swings the elbow sideways, j2 lowers the upper arm onto the obstacle).
OBSTACLE_TARGETS = {"j1": "elbow_housing", "j2": "upper_arm", "j3": "wrist_boss", "j4": "gripper_housing"}
#: Where the scene parks the obstacle (under the floor).
OBSTACLE_PARKED = (0.0, 0.0, -2.0)
#: Free gap left between the link and the obstacle, m.
OBSTACLE_GAP_M = 0.0005


def _support(geom_type: int, size: np.ndarray, xmat: np.ndarray, u: np.ndarray) -> float:
    """Half-extent of a box or cylinder along the unit vector ``u`` (its support function)."""
    local = xmat.reshape(3, 3).T @ u
    if geom_type == mujoco.mjtGeom.mjGEOM_BOX:
        return float(np.abs(local) @ size[:3])
    if geom_type == mujoco.mjtGeom.mjGEOM_CYLINDER:
        return float(size[0] * math.hypot(local[0], local[1]) + size[1] * abs(local[2]))
    raise ValueError(f"geom type {geom_type} has no support function here")


def place_obstacle(sim: ArmSim, joint: str, direction: int = -1, gap: float = OBSTACLE_GAP_M) -> None:
    """Move the scene's mocap obstacle into ``joint``'s way.

    The obstacle (a 0.06 x 0.06 x 0.2 m box that collides with the arm's
    links) is put ``gap`` ahead of the link in :data:`OBSTACLE_TARGETS`, in
    the direction that link moves when ``joint`` turns (or slides) with the
    sign of ``direction``, a face square to that motion. With the default
    gap a joint moving at a fraction of its max velocity touches it within
    tens of milliseconds and is then held by contact.

    Args:
        sim: The simulated arm.
        joint: Joint name.
        direction: +1 or -1, the sign of the joint velocity to block.
        gap: Free gap between link and obstacle, m.
    """
    m, d = sim.model, sim.data
    mujoco.mj_kinematics(m, d)
    geom = m.geom(OBSTACLE_TARGETS[joint])
    p = d.geom_xpos[geom.id].copy()
    jacp = np.zeros((3, m.nv))
    mujoco.mj_jac(m, d, jacp, None, p, int(geom.bodyid[0]))
    v = direction * jacp[:, m.joint(joint).dofadr[0]]
    u = v / np.linalg.norm(v)
    yaw = math.atan2(u[1], u[0]) if math.hypot(u[0], u[1]) > 1e-9 else 0.0
    quat = np.array([math.cos(yaw / 2), 0.0, 0.0, math.sin(yaw / 2)])
    obstacle_mat = np.zeros(9)
    mujoco.mju_quat2Mat(obstacle_mat, quat)
    obstacle = m.geom("obstacle")
    reach = _support(int(geom.type[0]), geom.size, d.geom_xmat[geom.id], u)
    reach += _support(int(obstacle.type[0]), obstacle.size, obstacle_mat, -u) + gap
    mocap = m.body("obstacle").mocapid[0]
    d.mocap_pos[mocap] = p + reach * u
    d.mocap_quat[mocap] = quat
    mujoco.mj_forward(m, d)


def park_obstacle(sim: ArmSim) -> None:
    """Move the obstacle back under the floor."""
    mocap = sim.model.body("obstacle").mocapid[0]
    sim.data.mocap_pos[mocap] = OBSTACLE_PARKED
    sim.data.mocap_quat[mocap] = (1.0, 0.0, 0.0, 0.0)
    mujoco.mj_forward(sim.model, sim.data)


@functools.cache
def _packaged_config() -> ArmConfig:
    """The packaged configuration (the numbers of docs/model.md), loaded once: it is frozen."""
    return load_config()


def _hold_other_joints(sim: ArmSim, joint_name: str, now: float) -> None:
    """Enable every joint but ``joint_name`` with its configured currents, so it holds its pose.

    As under the arm layer, the rest of the arm is powered: an unpowered
    elbow would swing when the shoulder accelerates, and its reaction would
    show in the shoulder's velocity.
    """
    for name, core in sim.cores.items():
        if name != joint_name:
            j = sim.config.joint(name)
            core.write(Reg.SETUP, pack_bytes(j.drive_current, j.hold_current), now)


def _mujoco_rig(name: str, backend_name: str, joint_name: str) -> JointRig:
    """One joint of the MuJoCo arm under test, powered up at :data:`SIM_POSE`.

    ``advance`` steps physics and every firmware core; ``block`` puts the
    scene's obstacle in the way of the joint's link (:func:`place_obstacle`),
    ``unblock`` parks it again. The other joints are enabled and hold their
    pose; ``power_cycle`` cuts only the joint under test.
    """
    backend: Backend = make_backend(backend_name, _packaged_config(), initial_qpos=SIM_POSE)
    sim: ArmSim = backend.sim  # type: ignore[assignment]
    core = sim.cores[joint_name]
    params = backend.config.joint(joint_name)
    clock = backend.clock
    _hold_other_joints(sim, joint_name, clock.now())

    def new_joint() -> BaseJoint:
        if isinstance(backend, EmulatedBackend):
            p = params
            return Joint(p.name, p.address, p.reduction, p.min, p.max, backend.bus, clock=clock)
        return SimJoint(params, core, clock)

    def block() -> None:
        qvel = sim.data.qvel[sim.model.joint(joint_name).dofadr[0]]
        place_obstacle(sim, joint_name, direction=1 if qvel > 0 else -1)

    def power_up_at(q: float) -> None:
        sim.reset({**SIM_POSE, joint_name: q})
        _hold_other_joints(sim, joint_name, clock.now())

    return JointRig(
        name=name,
        joint=backend.joints[joint_name],
        params=params,
        clock=clock,
        # Let the time pass (backend.step would count it from the last deadline,
        # and the first step after a homing is an overrun that waits for nothing).
        advance=backend.clock.sleep,
        device_flags=lambda: Flag(core.flags),
        restart_host=new_joint,
        features=frozenset({"stall", "deadman", "power_cycle", "host_restart", "physics"}),
        block=block,
        unblock=lambda: park_obstacle(sim),
        power_cycle=lambda: core.power_cycle(clock.now()),
        power_up_at=power_up_at,
    )


def sim_j1() -> JointRig:
    """j1 as a :class:`SimJoint` of the MuJoCo arm (firmware core, no bytes)."""
    return _mujoco_rig("sim_j1", "sim", "j1")


def sim_j2() -> JointRig:
    """j2, the lift, as a :class:`SimJoint` of the MuJoCo arm."""
    return _mujoco_rig("sim_j2", "sim", "j2")


def emulated_mujoco_j1() -> JointRig:
    """j1: the real :class:`Joint` over the ``emulated`` backend's bus, MuJoCo behind."""
    return _mujoco_rig("emulated_mujoco_j1", "emulated", "j1")


def emulated_mujoco_j2() -> JointRig:
    """j2: the real :class:`Joint` over the ``emulated`` backend's bus, MuJoCo behind."""
    return _mujoco_rig("emulated_mujoco_j2", "emulated", "j2")


# -------------------------------------------------------- firmware in the loop

#: Why the SITL tests skip, and how to run them.
SITL_SKIP_REASON = (
    "firmware in the loop: set BIOSCARA_FIRMWARE to the joint firmware's folder "
    "(Arduino/joint/ of a checkout of DALSA-Lab/bioscara); .ci/run sets it when CI has that folder"
)


def sitl_source() -> str:
    """The firmware's folder (``BIOSCARA_FIRMWARE``), else skip the test with :data:`SITL_SKIP_REASON`."""
    from bioscara_gym.hardware.sitl.build import FIRMWARE_ENV

    source = os.environ.get(FIRMWARE_ENV)
    if not source:
        pytest.skip(SITL_SKIP_REASON)
    return source


@dataclass
class SitlJoint:
    """The real :class:`Joint` driver over an emulated bus into the joint firmware built for the host."""

    params: JointConfig
    clock: ManualClock
    motor: KinematicStepper
    firmware: SitlFirmware
    bus: EmulatedI2CBus
    joint: Joint

    def new_joint(self) -> Joint:
        """A new driver object for the same device (as after a host restart)."""
        p = self.params
        return Joint(p.name, p.address, p.reduction, p.min, p.max, self.bus, clock=self.clock)

    def advance(self, dt: float) -> None:
        """Let ``dt`` seconds pass without traffic; the firmware runs."""
        self.clock.sleep(dt)
        self.bus.update()


def build_sitl(params: JointConfig, start_q: float, source: str | None = None) -> SitlJoint:
    """``Joint`` -> ``EmulatedI2CBus`` -> ``SitlFirmware`` -> ``KinematicStepper``, stops at the limits."""
    from bioscara_gym.hardware.sitl import SitlFirmware

    source = source or sitl_source()
    stops = sorted((motor_degrees(params.min, params), motor_degrees(params.max, params)))
    clock = ManualClock()
    motor = KinematicStepper(motor_degrees(start_q, params), lower_stop_deg=stops[0], upper_stop_deg=stops[1])
    firmware = SitlFirmware(source, params.name, motor, clock)
    bus = EmulatedI2CBus({firmware.address: firmware}, clock=clock)
    p = params
    joint = Joint(p.name, p.address, p.reduction, p.min, p.max, bus, clock=clock)
    return SitlJoint(params, clock, motor, firmware, bus, joint)


def _sitl_rig(name: str, params: JointConfig, start_q: float) -> JointRig:
    sitl = build_sitl(params, start_q)

    def block() -> None:
        sitl.motor.blocked = True

    def unblock() -> None:
        sitl.motor.blocked = False

    return JointRig(
        name=name,
        joint=sitl.joint,
        params=params,
        clock=sitl.clock,
        advance=sitl.advance,
        device_flags=lambda: sitl.firmware.flags,
        restart_host=sitl.new_joint,
        features=frozenset({"stall", "deadman", "power_cycle", "host_restart", "physics"}),
        block=block,
        unblock=unblock,
        power_cycle=sitl.firmware.power_cycle,
    )


def sitl_kinematic_j1() -> JointRig:
    """j1 on the real firmware (SITL) behind the emulated bus, kinematic motor, at q = 2.9 rad."""
    return _sitl_rig("sitl_kinematic_j1", J1, start_q=2.9)


def sitl_kinematic_j2() -> JointRig:
    """j2 on the real firmware (SITL) behind the emulated bus, kinematic motor, at q = 0.3 m."""
    return _sitl_rig("sitl_kinematic_j2", J2, start_q=0.3)


#: Every rig the conformance suite runs on, by id.
RIG_FACTORIES: dict[str, Callable[[], JointRig]] = {
    "mock_j1": mock_j1,
    "emulated_kinematic_j1": emulated_kinematic_j1,
    "emulated_kinematic_j2": emulated_kinematic_j2,
    "sim_j1": sim_j1,
    "sim_j2": sim_j2,
    "emulated_mujoco_j1": emulated_mujoco_j1,
    "emulated_mujoco_j2": emulated_mujoco_j2,
    "sitl_kinematic_j1": sitl_kinematic_j1,
    "sitl_kinematic_j2": sitl_kinematic_j2,
}


# ------------------------------------------------------------- arm tests (test_arm_*.py)

MakeBackend = Callable[..., Backend]
NAMES = ("j1", "j2", "j3", "j4")
CONFIG = load_config()
KNOWN_JOINTS = r"known joints: j1, j2, j3, j4"
#: Control period of the tests' cycles, s (25 Hz, as the envs run).
DT = 0.04


#: Power-up pose of the simulated arms: 0.3 % of each range inside the end stop
#: homing drives to, so homing takes about a simulated second.
NEAR_END_STOPS = ArmSim.parked_pose(CONFIG, margin=0.003)


@dataclass
class Traffic:
    """Register transactions of every joint, in order: ``(joint, register, value)``.

    ``value`` is the command's payload, or ``None`` for a read.
    """

    log: list[tuple[str, Reg, float | int | None]] = field(default_factory=list)

    def regs(self, name: str) -> list[Reg]:
        """Registers joint ``name`` was sent, in order."""
        return [reg for joint, reg, _ in self.log if joint == name]

    def values(self, name: str, reg: Reg) -> list[float | int | None]:
        """Payloads of ``reg`` commands to joint ``name``."""
        return [value for joint, r, value in self.log if joint == name and r == reg and value is not None]

    def clear(self) -> None:
        """Forget the transactions so far."""
        self.log.clear()


def spy(monkeypatch: pytest.MonkeyPatch, arm: Arm) -> Traffic:
    """Record every joint's register traffic from now on."""
    traffic = Traffic()
    for name, joint in arm.joints.items():
        command, query = joint._command, joint._query

        def recording_command(reg: Reg, value: float | int, _n: str = name, _f: Callable = command) -> int:
            traffic.log.append((_n, Reg(reg), value))
            return _f(reg, value)

        def recording_query(reg: Reg, _n: str = name, _f: Callable = query) -> tuple[float | int, int]:
            traffic.log.append((_n, Reg(reg), None))
            return _f(reg)

        monkeypatch.setattr(joint, "_command", recording_command)
        monkeypatch.setattr(joint, "_query", recording_query)
    return traffic


def cycle_until(arm: Arm, done: Callable[[], bool], max_s: float = 20.0) -> float:
    """Run control cycles of :data:`DT` until ``done()``; return the time it took."""
    start = arm.backend.clock.now()
    while not done():
        assert arm.backend.clock.now() - start < max_s, f"not done after {max_s} s"
        arm.cycle(DT)
    return arm.backend.clock.now() - start


def start_homing(arm: Arm, name: str, speed: float) -> None:
    """Claim the home interface of ``name``, send a home command of ``speed``, read the state."""
    arm.claim(name, "home")
    arm.set_command(name, speed)
    arm.write()
    arm.read()


def motor_rate_deg(name: str, value: float) -> float:
    """A joint-side velocity or acceleration as sent to the joint, deg/s or deg/s^2."""
    return abs(math.degrees(CONFIG.joint(name).reduction * value))


def enable_and_home_elsewhere(arm: Arm, name: str, speed: float) -> None:
    """Leave ``name`` as an earlier process would have: enabled and homing at ``speed``.

    The homing is started through the joint's register primitive, so this
    process's driver knows nothing of it (no blocking command, no offset);
    the earlier process then ended, which takes longer than the firmware's
    pick-up of a blocking command (any transaction before it would cancel
    the homing: docs/firmware.md); then the arm reads the state, as
    :meth:`Arm.configure` would.
    """
    cfg = CONFIG.joint(name)
    joint = arm.joints[name]
    joint.enable(cfg.drive_current, cfg.hold_current)
    rpm = joint.homing_rpm(speed)
    joint._command(
        Reg.HOME, pack_bytes(int(rpm > 0), int(abs(rpm)), cfg.homing.threshold, cfg.homing.current)
    )
    arm.backend.step(BLOCKING_PICKUP_S)
    arm.read()


# --------------------------------------------------------------- Dynamixel

from bioscara_gym.hardware.config import DynamixelJointConfig  # noqa: E402

#: Features only Dynamixel rigs have; each exempts the rig from the Bioscara-specific
#: tests that contradict it (``test_conformance.py`` skips those with the reason).
FEATURES = FEATURES | {
    "absolute_encoder",  # never NOT_HOMED: homing is motionless, positions survive power cycles
    "reboot_clears_faults",  # a hardware error (the stall) clears only with REBOOT, not with enable()
}

#: A joint on an XL430-W250 (docs/dynamixel.md): limits +-2000 position units
#: around the centre, so that the conformance suite's targets (10 % inside a
#: limit) fall on whole position units, and a max velocity of 100 velocity
#: units, so that its 20 % test velocity is a whole unit. Homing, currents and
#: stall threshold are checked but unused by a servo.
DXL_J1 = JointConfig(
    name="j1",
    address=None,  # type: ignore[arg-type]
    joint_type="revolute",
    reduction=1.0,
    min=-2000 * 0.001533980787886,
    max=2000 * 0.001533980787886,
    max_velocity=100 * 0.023980823922402,
    max_acceleration=10.0,
    stall_threshold=6,
    hold_current=20,
    drive_current=20,
    homing=HomingConfig(speed=0.5, threshold=30, current=15, acceleration=1.0),
    type="dynamixel",
    dynamixel=DynamixelJointConfig(id=1),
)


def dynamixel_emulated_j1() -> JointRig:
    """:class:`DynamixelJoint` through the official SDK to an emulated XL430 (in memory), at q = 2.9 rad."""
    pytest.importorskip("dynamixel_sdk", reason="the [dynamixel] extra is not installed")
    from bioscara_gym.hardware.dynamixel.bus import DynamixelBus
    from bioscara_gym.hardware.dynamixel.control_table import position_to_raw
    from bioscara_gym.hardware.dynamixel.emulator import XL430, EmulatedRS485Bus
    from bioscara_gym.hardware.dynamixel.joint import DynamixelJoint
    from bioscara_gym.hardware.dynamixel.port import EmulatedPortHandler

    p = DXL_J1
    clock = ManualClock()
    servo = XL430(1, clock, position=position_to_raw(2.9))
    emulated = EmulatedRS485Bus([servo], clock=clock)
    bus = DynamixelBus(EmulatedPortHandler(emulated), clock=clock)

    def new_joint() -> DynamixelJoint:
        return DynamixelJoint(p.name, 1, bus, p.reduction, p.min, p.max, 0.0, clock)

    def device_flags() -> Flag:
        servo.update()
        flags = Flag(0) if servo.torque else Flag.NOT_ENABLED
        return flags | Flag.STALL if servo.hardware_error else flags

    def advance(dt: float) -> None:
        clock.sleep(dt)
        servo.update()

    def block() -> None:
        servo.blocked = True

    def unblock() -> None:
        servo.blocked = False

    return JointRig(
        name="dynamixel_emulated_j1",
        joint=new_joint(),
        params=p,
        clock=clock,
        advance=advance,
        device_flags=device_flags,
        restart_host=new_joint,
        features=frozenset(
            {"stall", "power_cycle", "host_restart", "absolute_encoder", "reboot_clears_faults"}
        ),
        block=block,
        unblock=unblock,
        power_cycle=servo.power_cycle,
    )


RIG_FACTORIES["dynamixel_emulated_j1"] = dynamixel_emulated_j1


# ------------------------------------------------------- blocked imports
def run_blocked(
    code: str, blocked: tuple[str, ...] = (), env: dict[str, str] | None = None, cwd: Path | None = None
) -> subprocess.CompletedProcess[str]:
    """Run ``code`` in a fresh interpreter in which importing any of ``blocked`` fails (in ``cwd``)."""
    prelude = textwrap.dedent(
        f"""
        import sys

        class _Blocked:
            def find_spec(self, name, path=None, target=None):
                if name.split(".")[0] in {blocked!r}:
                    raise ModuleNotFoundError(f"No module named {{name!r}} (blocked)", name=name)
                return None

        sys.meta_path.insert(0, _Blocked())
        """
    )
    return subprocess.run(
        [sys.executable, "-c", prelude + textwrap.dedent(code)],
        capture_output=True,
        text=True,
        timeout=120,
        cwd=cwd or Path(__file__).resolve().parents[1],
        env=env,
    )


def wait_for_homing_end(arm: Arm, name: str) -> None:
    """Let time pass, without the arm's read, until the firmware ends ``name``'s homing (BUSY clear)."""
    joint = arm.joints[name]
    while joint.is_busy():
        arm.backend.step(DT)
        joint.get_flags()


# ------------------------------------------------------------ a trained policy
#: A bus trace's header (format version 2) and one PING transaction, for the trace readers' tests.
TRACE_HEADER: dict[str, Any] = {
    "type": "header",
    "format": "bioscara-bus-trace",
    "version": 2,
    "backend": "emulated",
    "command": "ping",
    "config": {},
    "args": {},
}
TRACE_TX: dict[str, Any] = {
    "type": "tx",
    "i": 0,
    "t": 0.5,
    "dur": 0.25,
    "addr": "0x11",
    "write": "0f",
    "read_len": 2,
    "read": "4f0c",
}


#: A tiny SAC + HER entry on Reach (as tests/test_training.py's), valid as it stands: 300 steps.
TINY_SAC_ENTRY: dict[str, Any] = {
    "n_timesteps": 300,
    "policy": "MultiInputPolicy",
    "buffer_size": 1000,
    "batch_size": 32,
    "learning_starts": 100,
    "replay_buffer_class": "HerReplayBuffer",
    "policy_kwargs": "dict(net_arch=[16, 16])",
    "env_kwargs": {"control_mode": "cartesian", "reward_type": "dense"},
    "eval_freq": 200,
    "eval_episodes": 2,
}


def train_tiny_sac(out: Path, env_id: str = "Bioscara-Reach-v0") -> Path:
    """A SAC + HER policy (as the Reach config trains) after 200 steps, saved with its metadata."""
    import gymnasium as gym
    import torch
    from stable_baselines3 import SAC, HerReplayBuffer

    from bioscara_gym.training.features import GoalErrorExtractor
    from bioscara_gym.training.metadata import build_metadata, save_policy

    torch.set_num_threads(1)
    env_kwargs = {"control_mode": "cartesian", "reward_type": "log"}
    env = gym.make(env_id, **env_kwargs)
    model = SAC(
        "MultiInputPolicy",
        env,
        learning_starts=100,
        batch_size=32,
        buffer_size=1000,
        replay_buffer_class=HerReplayBuffer,
        policy_kwargs={"net_arch": [32, 32], "features_extractor_class": GoalErrorExtractor},
        seed=0,
        device="cpu",
    )
    model.learn(200)
    model_path, _ = save_policy(model, out, build_metadata(env, env_id, env_kwargs, algo="sac"))
    env.close()
    return model_path


# ------------------------------------------------------- a motor the test sets
class FakeMotor:
    """A motor whose set point, encoder and speed the test sets directly."""

    def __init__(self) -> None:
        self.setpoint_deg = 0.0
        self.position_deg = 0.0
        self.velocity_dps = 0.0

    @property
    def pid_error_deg(self) -> float:
        return self.setpoint_deg - self.position_deg

    @property
    def pid_jitter_usteps(self) -> float:
        return 0.0

    def set_error(self, microsteps: float) -> None:
        """Make the PID error (set point - encoder) ``microsteps``."""
        self.setpoint_deg = self.position_deg + microsteps / MICROSTEPS_PER_DEG

    def command(self, velocity_dps: float, torque_fraction: float) -> None:
        pass

    def hold_here(self) -> None:
        self.setpoint_deg = self.position_deg

    def advance(self, dt: float) -> None:
        pass


# ------------------------------------------- faults the deploy tests inject
class ConstantPolicy:
    """Returns ``action`` every call; ``bad_from`` on it returns NaN instead."""

    def __init__(self, action: list[float], bad_from: int | None = None) -> None:
        self.action = np.asarray(action, dtype=np.float32)
        self.bad_from = bad_from
        self.calls = 0

    def __call__(self, obs: dict[str, np.ndarray]) -> np.ndarray:
        self.calls += 1
        if self.bad_from is not None and self.calls > self.bad_from:
            return np.array([np.nan, 0.0, 0.0, 0.0], dtype=np.float32)
        return self.action


class AnswersFF:
    """A joint that has stopped sending: every byte read is 0xFF (the bus left high).

    Its firmware keeps running (its main loop, its deadman); only the replies are lost.
    """

    def __init__(self, firmware: Any) -> None:
        self.firmware = firmware

    def transfer(self, data: bytes, read_len: int) -> bytes:
        return b"\xff" * read_len

    def update(self) -> None:
        self.firmware.update()


def lose_joint_at(cycle: int, name: str, address: int, nacks: bool) -> Callable[[int, Any], None]:
    """An ``on_cycle`` hook: from ``cycle`` on the joint NACKs (``nacks``) or answers 0xFF.

    Its last delivered exchange is made 60 ms old (its replies were lost that
    long), so its deadman trips at the next pass, as seen on the arm.
    """

    def lose(at: int, env: Any) -> None:
        if at == cycle:
            backend = env.unwrapped.backend
            devices = backend.bus.devices
            if nacks:
                del devices[address]
            else:
                devices[address] = AnswersFF(devices[address])
            backend.sim.cores[name].last_rx -= 0.06

    return lose


class FlipsNextReply:
    """A joint whose next reply to ``reg`` (a read or a command) comes back with bit ``bit`` flipped.

    Bits count from the reply's first byte, least significant first: in
    ANGLEMOVED's 5-byte reply bit 30 is the float's top exponent bit and bit
    33 the flags byte's BUSY.
    """

    def __init__(self, firmware: Any, bit: int, reg: Reg = Reg.ANGLEMOVED) -> None:
        self.firmware, self.bit, self.reg = firmware, bit, reg

    def transfer(self, data: bytes, read_len: int) -> bytes:
        reply = bytearray(self.firmware.transfer(data, read_len))
        if data[:1] == bytes((self.reg,)) and self.bit is not None:
            reply[self.bit // 8] ^= 1 << (self.bit % 8)
            self.bit = None
        return bytes(reply)

    def update(self) -> None:
        self.firmware.update()


class FillingDisk:
    """``os.write`` of the run log on a disk that fills: while ``full``, half of the bytes land, then ENOSPC.

    ``full_for`` writes later space returns (``None``: never), as when another
    process frees some.
    """

    def __init__(self, full_for: int | None) -> None:
        self.full_for = full_for
        self.full = False
        self.fd: int | None = None

    def __call__(self, fd: int, data: Any) -> int:
        if not self.full or fd != self.fd:
            return os.write(fd, data)
        if self.full_for is not None:
            self.full_for -= 1
            self.full = self.full_for > 0
        os.write(fd, bytes(data)[: len(data) // 2])  # what a full disk takes before it refuses
        raise OSError(errno.ENOSPC, os.strerror(errno.ENOSPC))


@contextlib.contextmanager
def run_log_disk_filling(at_cycle: int, full_for: int | None) -> Iterator[Callable[[int, Any], None]]:
    """The disk under a deploy's run log fills at ``at_cycle`` (:class:`FillingDisk`); yields the hook.

    While it is active, every :class:`~bioscara_gym.training.deploy.Deployment`
    made is watched, so the hook finds the run log's file descriptor at cycle 0.
    """
    from unittest import mock

    from bioscara_gym.training.deploy import Deployment

    made: list[Any] = []
    disk = FillingDisk(full_for)
    original_init = Deployment.__init__

    def init(self: Any, *args: Any, **kwargs: Any) -> None:
        original_init(self, *args, **kwargs)
        made.append(self)

    def hook(cycle: int, env: Any) -> None:
        if cycle == 0:
            disk.fd = made[-1]._log._fd
        if cycle == at_cycle:
            disk.full = True

    with (
        mock.patch.object(Deployment, "__init__", init),
        mock.patch("bioscara_gym.training.deploy_log._os_write", disk),
    ):
        yield hook


def nan_actor_weights(run: Path) -> list[str]:
    """The actor's output layer full of NaN, model and metadata otherwise intact."""
    import torch
    from stable_baselines3 import SAC

    from bioscara_gym.training.metadata import save_policy

    act_only = {"replay_buffer_class": None, "replay_buffer_kwargs": {}, "buffer_size": 1}
    sac = SAC.load(run / "model.zip", device="cpu", custom_objects=act_only)
    with torch.no_grad():
        sac.policy.actor.mu.weight.fill_(float("nan"))
    save_policy(sac, run, json.loads((run / "metadata.json").read_text()))
    return ["--model", str(run / "model.zip")]


# ------------------------------------------------------ scripted random draws
class ScriptedRng:
    """Stands in for an env's ``np_random``: each draw takes the next fraction ``f`` in [0, 1) of a script.

    ``uniform(low, high)`` gives ``low + f * (high - low)`` (``size`` of them as
    an array), ``random()`` gives ``f``. Running out fails the test: a redraw
    the script did not expect.
    """

    def __init__(self, fractions: list[float]) -> None:
        self._fractions = list(fractions)

    def _next(self) -> float:
        if not self._fractions:
            raise AssertionError("more draws than scripted (a redraw)")
        return self._fractions.pop(0)

    def uniform(self, low: float = 0.0, high: float = 1.0, size: int | None = None) -> float | np.ndarray:
        if size is None:
            return low + self._next() * (high - low)
        return np.array([low + self._next() * (high - low) for _ in range(size)])

    def random(self) -> float:
        return self._next()

    @property
    def left(self) -> int:
        """Draws left in the script."""
        return len(self._fractions)


# ---------------------------------------------------------- command outputs
def files_under(root: Path) -> dict[str, bytes]:
    """Every file under ``root`` and its contents (to show a refusal wrote nothing)."""
    return {str(p.relative_to(root)): p.read_bytes() for p in sorted(root.rglob("*")) if p.is_file()}


def train_refusal(root: Path, capsys: pytest.CaptureFixture[str], argv: list[str], message: str) -> str:
    """``bioscara train ...``: one line matching ``message``, exit 2, nothing written; the line."""
    from bioscara_gym.cli import main

    before = files_under(root)
    rc = main(argv)
    err = capsys.readouterr().err
    assert "Traceback" not in err
    lines = err.strip().splitlines()
    assert len(lines) == 1, f"expected one line, got {len(lines)}:\n{err}"
    assert lines[0].startswith("bioscara train: error: "), lines[0]
    assert re.search(message, lines[0]), lines[0]
    assert rc == 2
    assert files_under(root) == before  # nothing trained, nothing written
    assert not (root / "run" / "tb").exists()
    return lines[0]


def one_line_error(capsys: pytest.CaptureFixture[str], command: str, kind: str = "error: ") -> str:
    """The single line on stderr after ``bioscara COMMAND: KIND`` (``kind=""``: an interruption too)."""
    lines = capsys.readouterr().err.strip().splitlines()
    assert len(lines) == 1, lines
    prefix = f"bioscara {command}: {kind}"
    assert lines[0].startswith(prefix), lines[0]
    return lines[0].removeprefix(prefix)


def drive_currents(state_file: Path) -> dict[str, int]:
    """Each joint's drive current in a console ``--state`` file, as its firmware emulator holds it."""
    firmware = json.loads(state_file.read_text(encoding="utf-8"))["firmware"]
    return {joint: state["drive_current"] for joint, state in firmware.items()}


# ---------------------------------------------------- in-process deployments
def read_log(path: Path) -> list[dict[str, Any]]:
    """Every line of a run log, parsed (fails on a torn line)."""
    return [json.loads(line) for line in path.read_text(encoding="utf-8").splitlines()]


class DeployRun:
    """A finished in-process deployment: its object, what it printed, what it raised, its log."""

    def __init__(self, deployment: Any, output: str, error: BaseException | None, log: Path) -> None:
        self.deployment, self.output, self.error, self.log = deployment, output, error, log

    @property
    def summary(self) -> dict[str, Any]:
        return self.deployment.summary

    @property
    def backend(self) -> Any:
        return self.deployment.env.unwrapped.backend

    @property
    def lines(self) -> list[str]:
        return self.output.splitlines()

    @property
    def records(self) -> list[dict[str, Any]]:
        return read_log(self.log)


def run_deployment(
    fields: dict[str, Any],
    policy: Any = None,
    metadata: dict[str, Any] | None = None,
    on_cycle: Callable[[int, Any], None] | None = None,
    catch: tuple[type[BaseException], ...] = (),
) -> DeployRun:
    """Run a :class:`~bioscara_gym.training.deploy.Deployment` of ``DeployArgs(**fields)`` in-process.

    A :class:`~bioscara_gym.errors.DeployError`, or one of ``catch``, is kept
    in the result instead of raised.
    """
    from rich.console import Console

    from bioscara_gym.errors import DeployError
    from bioscara_gym.training.deploy import DeployArgs, Deployment

    out = io.StringIO()
    deployment = Deployment(
        DeployArgs(**fields),
        policy=policy,
        metadata=metadata,
        console=Console(file=out, width=200),
        on_cycle=on_cycle,
    )
    error = None
    try:
        deployment.run()
    except (DeployError, *catch) as e:
        error = e
    return DeployRun(deployment, out.getvalue(), error, Path(fields["log"]))
