"""The joint firmware in the loop (SITL): the firmware's own source, built for the host.

``joint.ino`` is compiled unchanged against the project's stand-ins for
``Arduino.h``, ``Wire.h`` and ``UstepperS32.h`` (``native/``) and run behind
the emulated bus as :class:`SitlFirmware`, a device like
:class:`~bioscara_gym.hardware.firmware.JointFirmware`, in front of the
project's motor models. Nothing above ``hardware/`` knows which device
answers. Importing this package needs no compiler: the firmware is built
(and cached) the first time a device is made. docs/firmware.md, "Firmware
in the loop", describes the stand-ins and what they cannot model.
"""

from bioscara_gym.hardware.sitl.build import FIRMWARE_ENV, build_firmware, cache_root, firmware_dir
from bioscara_gym.hardware.sitl.device import MotorBridge, SitlFirmware, SitlState

__all__ = [
    "FIRMWARE_ENV",
    "MotorBridge",
    "SitlFirmware",
    "SitlState",
    "build_firmware",
    "cache_root",
    "firmware_dir",
]
