"""Dynamixel servos (XL430-W250, protocol 2.0) as joints of the arm.

* :mod:`.control_table`: the servo's control table and the protocol's numbers, as data.
* :mod:`.protocol`: CRC-16, byte stuffing, instruction and status packets.
* :mod:`.emulator`: byte-exact emulated servos on an emulated RS-485 bus, with faults.
* :mod:`.pty_server`: the emulated bus behind a pseudo-terminal (``bioscara emulate dynamixel``).
* :mod:`.bus`: the host side: transactions with retries, the MH5's sync loops and their statistics.
* :mod:`.joint`: :class:`DynamixelJoint`, the ``BaseJoint`` API on a servo.
* :mod:`.port`: the SDK's port with RS-485 set-up, and an in-memory port (imports the SDK).
* :mod:`.backend`: the ``dynamixel`` and ``dynamixel-emulated`` backends.

Importing this package needs no ``dynamixel-sdk``: the modules that talk
through the SDK import it when a bus is built, and a missing SDK is one
:class:`~bioscara_gym.hardware.errors.MissingExtraError` naming the
``[dynamixel]`` extra. See ``docs/dynamixel.md``.
"""

from bioscara_gym.hardware.dynamixel.bus import DynamixelBus, LoopStats, SyncLoop, load_sdk
from bioscara_gym.hardware.dynamixel.emulator import XL430, EmulatedRS485Bus
from bioscara_gym.hardware.dynamixel.joint import DynamixelJoint

__all__ = [
    "XL430",
    "DynamixelBus",
    "DynamixelJoint",
    "EmulatedRS485Bus",
    "LoopStats",
    "SyncLoop",
    "load_sdk",
]
