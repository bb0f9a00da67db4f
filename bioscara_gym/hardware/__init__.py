"""Joint and gripper drivers of the Bioscara arm, real and emulated.

This package imports no Gymnasium: it is the driver layer every backend and
the deployment code stand on.
"""

from bioscara_gym.hardware.base_joint import BaseJoint
from bioscara_gym.hardware.bus import I2CBus, SMBusI2C
from bioscara_gym.hardware.clock import Clock, ManualClock, WallClock
from bioscara_gym.hardware.config import ArmConfig, GripperConfig, HomingConfig, JointConfig, load_config
from bioscara_gym.hardware.emulated_bus import EmulatedI2CBus, Fault, FaultPlan
from bioscara_gym.hardware.errors import (
    AlreadyInitializedError,
    CommError,
    ConfigError,
    ErrType,
    IncorrectStateError,
    InvalidArgumentError,
    JointError,
    NotEnabledError,
    NotHomedError,
    NotInitError,
    StalledError,
    UnknownJointError,
    error_to_string,
)
from bioscara_gym.hardware.firmware import FirmwareCore, JointFirmware
from bioscara_gym.hardware.gripper import BaseGripper, Gripper, MockGripper
from bioscara_gym.hardware.joint import Joint
from bioscara_gym.hardware.mock import MockJoint
from bioscara_gym.hardware.motor import KinematicStepper, Motor
from bioscara_gym.hardware.registers import BrakeMode, Flag, Reg
from bioscara_gym.hardware.stats import CommStats

__all__ = [
    "AlreadyInitializedError",
    "ArmConfig",
    "BaseGripper",
    "BaseJoint",
    "BrakeMode",
    "Clock",
    "CommError",
    "CommStats",
    "ConfigError",
    "EmulatedI2CBus",
    "ErrType",
    "Fault",
    "FaultPlan",
    "FirmwareCore",
    "Flag",
    "Gripper",
    "GripperConfig",
    "HomingConfig",
    "I2CBus",
    "IncorrectStateError",
    "InvalidArgumentError",
    "Joint",
    "JointConfig",
    "JointError",
    "JointFirmware",
    "KinematicStepper",
    "ManualClock",
    "MockGripper",
    "MockJoint",
    "Motor",
    "NotEnabledError",
    "NotHomedError",
    "NotInitError",
    "Reg",
    "SMBusI2C",
    "StalledError",
    "UnknownJointError",
    "WallClock",
    "error_to_string",
    "load_config",
]
