"""Joint test rigs: one backend each, behind one small interface.

The conformance suite (``test_conformance.py``) runs every test against every
rig in :data:`RIG_FACTORIES`. A rig bundles a :class:`BaseJoint` that is not
yet ``init()``-ed with the handles a test needs to act on the world around it:
let time pass, hold the joint, cut its power, restart the host program.

Adding a backend is adding one factory (a function with no arguments that
returns a fresh :class:`JointRig`) to :data:`RIG_FACTORIES` and listing in its
``features`` which of :data:`FEATURES` it supports; tests that need a missing
feature are skipped with a reason.

Joint parameters are SPEC.md's (kinematics table and the arm's parameter
file), as :class:`~bioscara_gym.hardware.config.JointConfig` values.
"""

from __future__ import annotations

import math
from collections.abc import Callable
from dataclasses import dataclass, field

from bioscara_gym.hardware.base_joint import BaseJoint
from bioscara_gym.hardware.clock import ManualClock
from bioscara_gym.hardware.config import HomingConfig, JointConfig
from bioscara_gym.hardware.emulated_bus import EmulatedI2CBus, FaultPlan
from bioscara_gym.hardware.firmware import JointFirmware
from bioscara_gym.hardware.joint import Joint
from bioscara_gym.hardware.mock import MockJoint
from bioscara_gym.hardware.motor import KinematicStepper
from bioscara_gym.hardware.registers import Flag

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

#: SPEC.md j1 (shoulder): kinematics table and parameter file.
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

#: SPEC.md j2 (lift): negative reduction, a positive motor turn moves it down.
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
        clock: The rig's manual clock (``now()``, ``sleep(dt)``); the joint
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
    """

    name: str
    joint: BaseJoint
    params: JointConfig
    clock: ManualClock
    advance: Callable[[float], None]
    device_flags: Callable[[], Flag]
    restart_host: Callable[[], BaseJoint] = field(default=_unsupported("host_restart"))
    features: frozenset[str] = frozenset()
    block: Callable[[], None] = field(default=_unsupported("block"))
    unblock: Callable[[], None] = field(default=_unsupported("unblock"))
    power_cycle: Callable[[], None] = field(default=_unsupported("power_cycle"))

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


#: Every rig the conformance suite runs on, by id.
RIG_FACTORIES: dict[str, Callable[[], JointRig]] = {
    "mock_j1": mock_j1,
    "emulated_kinematic_j1": emulated_kinematic_j1,
    "emulated_kinematic_j2": emulated_kinematic_j2,
}
