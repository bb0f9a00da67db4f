"""One simulated joint behind the real driver, on the emulated bus, as the test programs drove the real one.

The arm's test programs (``max_accel_test.cpp``, ``high_speed_stall_test.cpp``,
``comm_speed_test.cpp``) build one ``Joint`` of the original C++ driver and
call it; :class:`JointRig` gives the same calls on this package's
:class:`~bioscara_gym.hardware.joint.Joint` driver, whose bytes are the
original's, over an :class:`~bioscara_gym.hardware.emulated_bus.EmulatedI2CBus`
to the firmware emulator and the configured motor model, on simulated time:
the program's sleeps, every transaction's own duration (the configuration's
``bus_timing`` at its ``i2c_clock_hz``) and the program's loop overhead.
"""

from __future__ import annotations

import copy
import math

import numpy as np

from bioscara_gym.hardware.clock import ManualClock
from bioscara_gym.hardware.config import ArmConfig, JointConfig
from bioscara_gym.hardware.emulated_bus import EmulatedI2CBus
from bioscara_gym.hardware.errors import JointError
from bioscara_gym.hardware.firmware import FIRMWARE_STALL_RULE, JointFirmware, StallRule
from bioscara_gym.hardware.joint import Joint
from bioscara_gym.hardware.motor import POLE_PITCH_DEG, KinematicStepper
from bioscara_gym.hardware.registers import Flag

#: How far from its end stop the joint starts homing, motor degrees: enough
#: for the homing to run up to speed and show that the drive can home.
HOMING_RUN_DEG = 30.0
#: Simulated seconds a rig's homing may take (the slowest, j3's, needs about 3).
HOMING_TIMEOUT_S = 60.0
#: How close to its end stop homing must leave the rotor, motor degrees: the
#: first pole slip throws it back by up to a pole pitch (7.2 degrees).
HOMED_WITHIN_DEG = 2 * POLE_PITCH_DEG


#: Homed rigs kept for copying, by drive and bus (a calibration builds thousands
#: of rigs of a few hundred drives; homing is most of a rig's cost).
_HOMED: dict[tuple[object, ...], _Homed] = {}
_HOMED_KEPT = 64


class _Homed:
    """One joint homed against its configured end stop, as the programs require, for copying.

    Homed from :data:`HOMING_RUN_DEG` before the stop with the configured
    homing parameters; ``error`` says why not if the drive could not home
    (:class:`RigError`'s message), else ``parts`` are the clock, motor,
    firmware, bus and driver.
    """

    def __init__(self, config: ArmConfig, p: JointConfig, stall_rule: StallRule, clock_hz: float) -> None:
        clock = ManualClock()
        lo, hi = sorted(motor_deg(p, q) for q in (p.min, p.max))
        home_at = p.max if p.homing.speed > 0 else p.min
        stop = motor_deg(p, home_at)
        motor = KinematicStepper(
            stop - math.copysign(HOMING_RUN_DEG, stop - motor_deg(p, 0.0)), lo, hi, drive=p.drive
        )
        firmware = JointFirmware(motor, clock, stall_rule=stall_rule)
        bus = EmulatedI2CBus({p.address: firmware}, clock=clock, clock_hz=clock_hz, timing=config.bus_timing)
        joint = Joint(p.name, p.address, p.reduction, p.min, p.max, bus, clock=clock)
        self.parts = (clock, motor, firmware, bus, joint)
        self.error: str | None = None
        joint.init()
        joint.enable(p.drive_current, p.hold_current)
        joint.set_max_acceleration(p.homing.acceleration)
        try:
            joint.home(p.homing.speed, p.homing.threshold, p.homing.current, timeout_s=HOMING_TIMEOUT_S)
        except JointError as e:
            self.error = f"{p.name}: homing failed: {e}"
            return
        if not joint.is_homed():
            self.error = f"{p.name}: the rig's joint did not home"
        elif abs(motor.position_deg - stop) > HOMED_WITHIN_DEG:
            # The real arm homes with its configured speed, threshold and current: a
            # drive that trips its homing before the end stop is not the arm's.
            short = abs(motor.position_deg - stop)
            self.error = f"{p.name}: homing stopped {short:.1f} motor degrees short of the end stop"


class RigError(RuntimeError):
    """The configured drive cannot do what the real joint does before every test: home."""


def motor_deg(joint: JointConfig, q: float) -> float:
    """Motor degrees of joint position ``q`` (encoder zero at joint 0)."""
    return math.degrees(joint.reduction * q)


class JointRig:
    """A homed joint on the emulated bus with the configured drive model.

    The joint is homed against its configured end stop first (as the test
    programs require: ``if (!J.isHomed()) return``), then placed by hand at
    ``start_q``, disabled, as the operator did ("Move to center").

    Args:
        config: The arm configuration (drive models, bus timing, clock).
        joint: ``j1`` .. ``j4``.
        start_q: Where the operator leaves the joint (default: mid-range).
        stall_rule: The firmware build's stall detector.
        seed: Seed of the motor's PID-error jitter.
        clock_hz: Bus clock (default: the configuration's).
        end_stops: Whether the motor meets the joint's end stops (the
            validation takes them away for runs the arm's authors made off
            the arm, with more room than the joint has).
    """

    def __init__(
        self,
        config: ArmConfig,
        joint: str,
        start_q: float | None = None,
        *,
        stall_rule: StallRule = FIRMWARE_STALL_RULE,
        seed: int = 0,
        clock_hz: float | None = None,
        end_stops: bool = True,
    ) -> None:
        """Build, home and place the joint."""
        self.params = params = config.joint(joint)
        key = (params, config.bus_timing, clock_hz or config.i2c_clock_hz, stall_rule)
        homed = _HOMED.get(key)
        if homed is None:
            homed = _HOMED[key] = _Homed(config, params, stall_rule, clock_hz or config.i2c_clock_hz)
            if len(_HOMED) > _HOMED_KEPT:
                del _HOMED[next(iter(_HOMED))]
        if homed.error is not None:
            raise RigError(homed.error)
        # Every rig of one drive homes alike: a copy of the one homed rig, with its own jitter.
        self.clock, self.motor, self.firmware, self.bus, self.joint = copy.deepcopy(homed.parts)
        self.motor.rng = np.random.default_rng(seed)
        if not end_stops:
            self.motor.lower_stop_deg, self.motor.upper_stop_deg = -math.inf, math.inf
        q = 0.5 * (params.min + params.max) if start_q is None else start_q
        self.joint.disable()
        self.motor.place(self.firmware.core.encoder_zero + motor_deg(params, q) - self._offset_deg())
        self.sleep(0.05)

    def _offset_deg(self) -> float:
        return motor_deg(self.params, self.joint.offset or 0.0)

    def sleep(self, dt: float) -> None:
        """Let ``dt`` seconds pass (the firmware's loop runs)."""
        self.clock.sleep(dt)
        self.bus.update()

    @property
    def now(self) -> float:
        """Simulated time, s."""
        return self.clock.now()

    @property
    def flags(self) -> Flag:
        """The firmware's flags now."""
        return self.firmware.flags
