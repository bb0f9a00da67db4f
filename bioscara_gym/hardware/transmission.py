"""Joint <-> actuator transmission and unit conversions (``docs/model.md``).

Joint side: rad, rad/s, rad/s^2 (revolute) or m, m/s, m/s^2 (prismatic).
Actuator side, what goes over the bus: degrees, RPM, deg/s, deg/s^2.
``actuator = reduction * (joint - offset)``; velocities and accelerations use
the reduction and never the offset.
"""

from __future__ import annotations

import math

from bioscara_gym.hardware.motor import FULL_STEP_DEG


def joint_to_actuator(value: float, reduction: float, offset: float = 0.0) -> float:
    """Joint value to actuator value (rad or m -> motor rad)."""
    return reduction * (value - offset)


def actuator_to_joint(value: float, reduction: float, offset: float = 0.0) -> float:
    """Actuator value to joint value (motor rad -> rad or m)."""
    return value / reduction + offset


def position_to_degrees(q: float, reduction: float, offset: float) -> float:
    """Joint position (rad or m) to the MOVETOANGLE payload in motor degrees."""
    return math.degrees(joint_to_actuator(q, reduction, offset))


def degrees_to_position(deg: float, reduction: float, offset: float) -> float:
    """ANGLEMOVED motor degrees to joint position (rad or m)."""
    return actuator_to_joint(math.radians(deg), reduction, offset)


def velocity_to_rpm(qd: float, reduction: float) -> float:
    """Joint velocity (rad/s or m/s) to motor RPM, as the SETRPM payload."""
    return math.degrees(reduction * qd) / 6.0


def rpm_to_velocity(rpm: float, reduction: float) -> float:
    """Motor RPM (GETENCODERRPM) to joint velocity (rad/s or m/s)."""
    return math.radians(rpm) / reduction * 6.0


def rate_to_degrees(value: float, reduction: float) -> float:
    """Joint max velocity or acceleration to motor deg/s or deg/s^2."""
    return math.degrees(reduction * value)


#: MOVESTEPS counts microsteps: the firmware passes its int32 to the uStepper
#: library's ``moveSteps(microsteps)``, which adds it to the driver's position
#: (1/256 of a full step, 51,200 a turn; UstepperS32.cpp, TMC5130 XACTUAL).
MICROSTEPS_PER_FULL_STEP = 256


def steps_to_degrees(steps: float) -> float:
    """MOVESTEPS microsteps to motor degrees (1/256 of a 1.8-degree full step, 51,200 a turn)."""
    return steps * FULL_STEP_DEG / MICROSTEPS_PER_FULL_STEP
