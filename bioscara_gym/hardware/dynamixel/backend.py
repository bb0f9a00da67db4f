"""The ``dynamixel`` and ``dynamixel-emulated`` backends: an arm whose joints are servos.

=====================  ======================================================
``dynamixel``           :class:`DynamixelJoint` s on the configuration's
                        serial port (``dynamixel: {port, baudrate, rs485,
                        rates}``), wall clock, :class:`MockGripper`
``dynamixel-emulated``  the same driver and the official SDK over an
                        in-memory :class:`EmulatedRS485Bus` of XL430s, on a
                        manual clock
=====================  ======================================================

Each configured joint of ``type: dynamixel`` is the servo of its
``dynamixel.id``; a joint without a ``dynamixel`` block (the Bioscara's own
configuration) becomes the servo with ID = its index + 1 and offset 0, so
``bioscara status --backend dynamixel-emulated`` works with any
configuration. ``step(dt)`` runs the MH5's cycle: the writer loops, ``dt``
passes, the reader loops. The Gymnasium tasks stay the Bioscara's: no
MuJoCo model here, and the gripper is a mirror.
"""

from __future__ import annotations

from collections.abc import Mapping
from pathlib import Path

from bioscara_gym.hardware.backends import Backend, mock_gripper
from bioscara_gym.hardware.clock import Clock, ManualClock, WallClock
from bioscara_gym.hardware.config import ArmConfig, DynamixelBusConfig, JointConfig
from bioscara_gym.hardware.dynamixel.bus import DynamixelBus, LoopStats, load_sdk, port_module
from bioscara_gym.hardware.dynamixel.control_table import position_to_raw
from bioscara_gym.hardware.dynamixel.emulator import XL430, EmulatedRS485Bus
from bioscara_gym.hardware.dynamixel.joint import DynamixelJoint
from bioscara_gym.hardware.emulated_bus import FaultPlan
from bioscara_gym.hardware.registers import Flag
from bioscara_gym.hardware.stats import CommStats


def servo_id(config: ArmConfig, joint: JointConfig) -> int:
    """The joint's servo ID: its ``dynamixel.id``, else its index + 1."""
    if joint.dynamixel is not None:
        return joint.dynamixel.id
    return config.names.index(joint.name) + 1


def servo_offset(joint: JointConfig) -> float:
    """The joint's ``dynamixel.offset``, else 0."""
    return joint.dynamixel.offset if joint.dynamixel is not None else 0.0


def _servo_reduction(joint: JointConfig) -> float:
    """Servo turns per joint unit: the configured reduction of a Dynamixel joint, 1 for others.

    A Bioscara joint's reduction is its stepper's (35 for j1); a servo standing
    in for it in ``dynamixel-emulated`` turns with the joint.
    """
    return joint.reduction if joint.type == "dynamixel" else 1.0


class DynamixelBackend(Backend):
    """Dynamixel joints on one serial port (see the module docstring).

    Args:
        config: The arm configuration.
        port: An SDK port handler to use instead of the configuration's port (tests).
        clock: Time source (default: wall clock).
        retries: Extra attempts of a failed transaction.
        state_file: Gripper state file.
        synced: Run the MH5's sync loops in :meth:`step` (positions from
            ``pvl_reader``, commands through ``pv_writer``).
    """

    name = "dynamixel"

    def __init__(
        self,
        config: ArmConfig,
        port: object | None = None,
        clock: Clock | None = None,
        retries: int = 2,
        state_file: str | Path | None = None,
        synced: bool = True,
    ) -> None:
        """Build the bus and the drivers; nothing is sent yet."""
        load_sdk()
        bus_cfg = config.dynamixel or DynamixelBusConfig()
        clock = clock if clock is not None else WallClock()
        if port is None:
            port = port_module().RS485PortHandler(bus_cfg.port)
        self.bus = DynamixelBus(
            port, bus_cfg.baudrate, bus_cfg.rs485, clock, rates=dict(bus_cfg.rates), retries=retries
        )
        joints = {
            j.name: DynamixelJoint(
                j.name,
                servo_id(config, j),
                self.bus,
                _servo_reduction(j),
                j.min,
                j.max,
                servo_offset(j),
                clock,
            )
            for j in config.joints
        }
        super().__init__(config, joints, mock_gripper(config, state_file), clock)
        if synced:
            self.bus.start_loops()
        self.schedule.restart()  # starting the loops took time: the first period starts now

    def step(self, dt: float) -> None:
        """The writer loops, ``dt`` after the previous deadline (``schedule``), the reader loops."""
        self.bus.write_loops()
        self.schedule.wait(dt)
        self.bus.read_loops()

    def comm_stats(self) -> dict[str, CommStats | LoopStats]:  # type: ignore[override]
        """Per-joint transaction counters, then the sync loops' statistics (by loop name)."""
        stats: dict[str, CommStats | LoopStats] = {n: j.stats for n, j in self.joints.items()}  # type: ignore[attr-defined]
        stats.update(self.loop_stats())
        return stats

    def loop_stats(self) -> dict[str, LoopStats]:
        """The sync loops' statistics: ``pvl_reader``, ``tv_reader``, ``pv_writer``, ``t_writer``."""
        return self.bus.loop_stats()

    def close(self) -> None:
        """Close the port."""
        self.bus.close()


class EmulatedDynamixelBackend(DynamixelBackend):
    """The Dynamixel driver and the official SDK over emulated XL430s in memory.

    Args:
        config: The arm configuration.
        faults: Faults the emulated bus injects into status packets.
        initial_q: Joint name to power-up position (default: the middle of its limits).
        clock: Time source (default: a manual clock; ``step`` advances it).
        kwargs: Passed to :class:`DynamixelBackend`.
    """

    name = "dynamixel-emulated"
    options_to = "bioscara_gym.hardware.dynamixel.backend:DynamixelBackend"

    def __init__(
        self,
        config: ArmConfig,
        faults: FaultPlan | None = None,
        initial_q: Mapping[str, float] | None = None,
        clock: Clock | None = None,
        **kwargs: object,
    ) -> None:
        """Build one XL430 per joint, the bus, the in-memory port and the drivers."""
        load_sdk()
        clock = clock if clock is not None else ManualClock()
        servos = []
        for j in config.joints:
            q = (initial_q or {}).get(j.name, 0.5 * (j.min + j.max))
            raw = position_to_raw((q - servo_offset(j)) * _servo_reduction(j))
            servo = XL430(servo_id(config, j), clock, position=raw)
            servo.set("Min Position Limit", 0)
            servos.append(servo)
        self.emulated = EmulatedRS485Bus(servos, faults=faults, clock=clock)
        port = port_module().EmulatedPortHandler(self.emulated)
        super().__init__(config, port=port, clock=clock, **kwargs)  # type: ignore[arg-type]

    def device_flags(self, name: str) -> Flag | None:
        """The servo's own torque and hardware error as flags, read without a transaction."""
        servo = self.emulated.servos[self.joints[name].dxl_id]  # type: ignore[attr-defined]
        servo.update()
        flags = 0 if servo.torque else Flag.NOT_ENABLED
        if servo.hardware_error:
            flags |= Flag.STALL
        return Flag(flags)
