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

import math

import numpy as np

from bioscara_gym.hardware.clock import ManualClock
from bioscara_gym.hardware.config import ArmConfig, JointConfig
from bioscara_gym.hardware.emulated_bus import EmulatedI2CBus
from bioscara_gym.hardware.firmware import FIRMWARE_STALL_RULE, JointFirmware, StallRule
from bioscara_gym.hardware.joint import Joint
from bioscara_gym.hardware.motor import POLE_PITCH_DEG, KinematicStepper
from bioscara_gym.hardware.registers import Flag

#: How far from its end stop the joint starts homing, motor degrees: enough
#: for the homing to run up to speed and show that the drive can home.
HOMING_RUN_DEG = 30.0
#: How close to its end stop homing must leave the rotor, motor degrees: the
#: first pole slip throws it back by up to a pole pitch (7.2 degrees).
HOMED_WITHIN_DEG = 2 * POLE_PITCH_DEG


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
        self.clock = ManualClock()
        lo, hi = sorted(motor_deg(params, q) for q in (params.min, params.max))
        home_at = params.max if params.homing.speed > 0 else params.min
        self.motor = KinematicStepper(
            motor_deg(params, home_at)
            - math.copysign(HOMING_RUN_DEG, motor_deg(params, home_at) - motor_deg(params, 0.0)),
            lo if end_stops else -math.inf,
            hi if end_stops else math.inf,
            drive=params.drive,
            rng=np.random.default_rng(seed),
        )
        if not end_stops:
            # Homing needs its stop: the motor meets it, then the stops go.
            self.motor.lower_stop_deg, self.motor.upper_stop_deg = lo, hi
        self.firmware = JointFirmware(self.motor, self.clock, stall_rule=stall_rule)
        self.bus = EmulatedI2CBus(
            {params.address: self.firmware},
            clock=self.clock,
            clock_hz=clock_hz or config.i2c_clock_hz,
            timing=config.bus_timing,
        )
        self.joint = Joint(
            params.name, params.address, params.reduction, params.min, params.max, self.bus, clock=self.clock
        )
        self._home()
        if not end_stops:
            self.motor.lower_stop_deg, self.motor.upper_stop_deg = -math.inf, math.inf
        q = 0.5 * (params.min + params.max) if start_q is None else start_q
        self.joint.disable()
        self.motor.place(self.firmware.core.encoder_zero + motor_deg(params, q) - self._offset_deg())
        self.sleep(0.05)

    def _offset_deg(self) -> float:
        return motor_deg(self.params, self.joint.offset or 0.0)

    def _home(self) -> None:
        p = self.params
        self.joint.init()
        self.joint.enable(p.drive_current, p.hold_current)
        self.joint.set_max_acceleration(p.homing.acceleration)
        stop = motor_deg(p, p.max if p.homing.speed > 0 else p.min)
        self.joint.home(p.homing.speed, p.homing.threshold, p.homing.current)
        if not self.joint.is_homed():
            raise RigError(f"{p.name}: the rig's joint did not home")
        # The real arm homes with its configured speed, threshold and current: a
        # drive that trips its homing before the end stop is not the arm's.
        if abs(self.motor.position_deg - stop) > HOMED_WITHIN_DEG:
            raise RigError(
                f"{p.name}: homing stopped {abs(self.motor.position_deg - stop):.1f} motor degrees "
                "short of the end stop"
            )

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
