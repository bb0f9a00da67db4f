"""The MuJoCo arm with the real joint firmware (SITL) behind every joint, and the ``sitl`` backend.

:class:`SitlArmSim` is :class:`~bioscara_gym.hardware.sim.ArmSim` with a
:class:`~bioscara_gym.hardware.sitl.SitlFirmware` per joint in place of a
``FirmwareCore``: every millisecond each joint's driver turns its coils
(the ``MujocoMotor``'s set point), physics steps 1 ms (the model's 2 ms step
halved, so the encoders are sampled at the library's 1 kHz), then each
joint's encoder, closed loop and firmware run. :class:`SitlBackend` puts the
real :class:`~bioscara_gym.hardware.joint.Joint` driver and the emulated bus
in front, as the ``emulated`` backend does, so the Arm, the envs, the deploy
rehearsal and the console run on the firmware's own source.
"""

from __future__ import annotations

import math
import os
from collections.abc import Mapping
from pathlib import Path

import mujoco
import numpy as np

from bioscara_gym.hardware.backends import Backend, gripper_state_file, with_i2c_clock
from bioscara_gym.hardware.bus import I2CBus
from bioscara_gym.hardware.config import ArmConfig
from bioscara_gym.hardware.emulated_bus import EmulatedI2CBus, FaultPlan
from bioscara_gym.hardware.errors import SitlError
from bioscara_gym.hardware.joint import Joint
from bioscara_gym.hardware.recording import BusWrapper
from bioscara_gym.hardware.sim import ArmSim, SimGripper
from bioscara_gym.hardware.sitl.build import JOINTS, firmware_dir
from bioscara_gym.hardware.sitl.device import STEP_S, SitlFirmware

__all__ = ["SitlArmSim", "SitlBackend"]


class SitlArmSim(ArmSim):
    """The MuJoCo arm, each joint run by the joint firmware built for the host.

    Args:
        config: Arm configuration; its joints must be named j1..j4 (the
            firmware is built with ``-D J1`` ... ``-D J4``).
        firmware: The firmware's folder; ``None``: ``$BIOSCARA_FIRMWARE``.
        initial_qpos: Joint positions at power-up (see :class:`ArmSim`).
        model_path: MJCF scene to load.
        serial: Keep each firmware's serial output.

    ``cores`` maps each joint to its :class:`SitlFirmware` (they have the
    ``flags`` the backends look at). Physics runs at 1 ms; a
    :meth:`reset` powers every joint up again (its ``setup()``).

    Raises:
        SitlError: No firmware, a build error, or a joint not named j1..j4.
    """

    def __init__(
        self,
        config: ArmConfig,
        firmware: str | os.PathLike[str] | None = None,
        initial_qpos: Mapping[str, float] | None = None,
        model_path: str | Path | None = None,
        serial: bool = False,
    ) -> None:
        """Load the model, build (or load) the firmware and power every joint up."""
        source = firmware_dir(firmware)
        for j in config.joints:
            if j.name not in JOINTS:
                raise SitlError(f"joint {j.name!r}: the firmware is built for {', '.join(JOINTS)} only")
        self.devices: dict[str, SitlFirmware] = {}
        super().__init__(config, initial_qpos, model_path)
        self.model.opt.timestep = STEP_S
        self.substeps_per_tick = round(0.01 / STEP_S)
        self.devices = {
            name: SitlFirmware(source, name, motor, self.clock, serial=serial, owns_ticks=False)
            for name, motor in self.motors.items()
        }
        self.cores = self.devices  # type: ignore[assignment]
        self._deg_per_unit = {j.name: math.degrees(j.reduction) for j in config.joints}
        self.reset()

    def reset(self, qpos: Mapping[str, float] | None = None) -> None:
        """Power-cycle the arm at ``qpos`` (default ``initial_qpos``), at rest: every firmware boots."""
        if not self.devices:
            super().reset(qpos)
            return
        mujoco.mj_resetData(self.model, self.data)
        for name, q in (qpos or self.initial_qpos).items():
            self.data.qpos[self._qadr[name]] = q
        for motor in self.motors.values():
            motor.hold_here()
        mujoco.mj_forward(self.model, self.data)
        self._pending = 0.0
        for device in self.devices.values():
            device.power_cycle()
        self.schedule.restart()

    def snapshot(self) -> tuple[np.ndarray, dict[str, object]]:  # type: ignore[override]
        """Physics and every joint's firmware image, for :meth:`restore`."""
        spec = mujoco.mjtState.mjSTATE_INTEGRATION
        state = np.empty(mujoco.mj_stateSize(self.model, spec))
        mujoco.mj_getState(self.model, self.data, state, spec)
        return state, {name: device.snapshot() for name, device in self.devices.items()}

    def restore(self, snapshot: tuple[np.ndarray, dict[str, object]]) -> None:  # type: ignore[override]
        """Return physics and every firmware to a :meth:`snapshot`."""
        state, images = snapshot
        mujoco.mj_setState(self.model, self.data, state, mujoco.mjtState.mjSTATE_INTEGRATION)
        for name, device in self.devices.items():
            device.restore(images[name])  # type: ignore[arg-type]
        self._pending = 0.0
        mujoco.mj_forward(self.model, self.data)
        self.schedule.restart()

    def set_joint_state(self, qpos: Mapping[str, float]) -> None:
        """Teleport joints; each encoder and driver follows without a jump in its firmware's view."""
        for name, q in qpos.items():
            adr = self._qadr[name]
            self.devices[name].teleport(self._deg_per_unit[name] * (q - float(self.data.qpos[adr])))
            self.data.qpos[adr] = q
            self.motors[name].hold_here()
        mujoco.mj_forward(self.model, self.data)

    def step(self, dt: float) -> None:
        """Advance by ``dt`` seconds in 1 ms steps: drivers, physics, encoders and firmware.

        A remainder below 1 ms is carried to the next call.
        """
        self._pending += dt
        m, d = self.model, self.data
        devices = list(self.devices.values())
        motors = list(self.motors.values())
        while self._pending >= STEP_S - 1e-9:
            self._pending -= STEP_S
            for device in devices:
                device.tick_begin()  # the coils' motion over this ms to the drive
            for motor in motors:
                motor.advance(STEP_S)  # the drive runs ahead of physics
                motor.begin_physics()
            mujoco.mj_step(m, d)
            for motor in motors:
                motor.end_physics()
            for device in devices:
                device.tick_end()

    def read_serial(self) -> dict[str, str]:
        """Each joint's serial output since the last call (``serial=True``)."""
        return {name: device.read_serial() for name, device in self.devices.items()}


class SitlBackend(Backend):
    """The real :class:`Joint` driver over an :class:`EmulatedI2CBus` into the firmware in the loop.

    As :class:`~bioscara_gym.hardware.backends.EmulatedBackend`, with each
    joint's device the firmware's own source built for the host
    (:class:`SitlArmSim`). Each device answers at the address its
    ``configuration.h`` gives; the arm configuration must agree.

    Args:
        config: Arm configuration.
        firmware: The firmware's folder (``--firmware``); ``None``:
            ``$BIOSCARA_FIRMWARE``.
        faults: Faults the bus injects (as ``emulated``).
        retries: Driver retries per transaction.
        state_file: Gripper state file.
        wrap_bus: Puts the bus behind another (``record=``).
        i2c_clock_hz: Bus clock, Hz; default the configuration's.
        serial: Keep the firmware's serial output (``backend.sim.read_serial()``).
        sim_kwargs: Passed to :class:`SitlArmSim` (``initial_qpos``, ``model_path``).

    Raises:
        SitlError: No firmware, a build error, or an address the firmware does not answer at.
    """

    name = "sitl"
    options_to = "bioscara_gym.hardware.sitl.arm:SitlArmSim"

    def __init__(
        self,
        config: ArmConfig,
        firmware: str | os.PathLike[str] | None = None,
        faults: FaultPlan | None = None,
        retries: int = 2,
        state_file: str | Path | None = None,
        wrap_bus: BusWrapper | None = None,
        i2c_clock_hz: float | None = None,
        serial: bool = False,
        **sim_kwargs: object,
    ) -> None:
        """Build the arm, one firmware per joint, the bus and the drivers."""
        config = with_i2c_clock(config, i2c_clock_hz)
        faults = faults or FaultPlan()
        sim = SitlArmSim(config, firmware, serial=serial, **sim_kwargs)  # type: ignore[arg-type]
        sim.schedule.scale = faults.period_scale
        for j in config.joints:
            answers = sim.devices[j.name].address
            if answers != j.address:
                raise SitlError(
                    f"{j.name}: the configuration's address {j.address:#04x} is not the firmware's "
                    f"{answers:#04x} (configuration.h ADR)"
                )
        self.devices = {j.address: sim.devices[j.name] for j in config.joints}
        bus = EmulatedI2CBus(self.devices, faults, clock=sim.clock, clock_hz=config.i2c_clock_hz)  # type: ignore[arg-type]
        self.bus: I2CBus = bus
        if wrap_bus is not None:
            self.bus = wrap_bus(self.bus, sim.clock)
        joints = {
            j.name: Joint(j.name, j.address, j.reduction, j.min, j.max, self.bus, retries, sim.clock)
            for j in config.joints
        }
        gripper = SimGripper(config.gripper, sim, gripper_state_file(config, state_file, default=False))
        super().__init__(config, joints, gripper, sim.clock, sim, sim.schedule)

    def device_currents(self, name: str) -> tuple[int, int] | None:
        """``None``: the firmware keeps its currents in variables no register reads back.

        (:meth:`Backend.device_currents` reads the emulator's; the stand-in
        chip's run and hold currents are in 31ths, not the percent sent.)
        """
        return None

    def close(self) -> None:
        """Close the emulated bus and unload the firmware copies."""
        self.bus.close()
        for device in self.devices.values():
            device.close()
