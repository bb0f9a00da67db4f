"""Backends: joints, gripper and clock bundled, chosen by name.

=========== =================================================================
``sim``      :class:`SimJoint` on the MuJoCo arm (firmware rules, no bytes)
``mock``     :class:`MockJoint` mirrors, :class:`MockGripper`, manual clock
``emulated`` the real :class:`Joint` driver over :class:`EmulatedI2CBus`,
             whose :class:`JointFirmware` devices drive the MuJoCo arm
``i2c``      real :class:`Joint` s over :class:`SMBusI2C`, sysfs PWM gripper
``sitl``     as ``emulated``, each device the joint firmware's own source
             built for the host (``bioscara_gym.hardware.sitl``; needs a
             C++ compiler and ``firmware=DIR`` or ``BIOSCARA_FIRMWARE``)
``dynamixel`` :class:`DynamixelJoint` s on a serial port (``dynamixel-sdk``),
             and ``dynamixel-emulated``: the same over emulated XL430 servos
             (``bioscara_gym.hardware.dynamixel.backend``, docs/dynamixel.md)
=========== =================================================================

``step(dt)`` is one fixed-rate loop on every backend: a
:class:`~bioscara_gym.hardware.clock.DeadlineScheduler` on the backend's clock
returns ``dt`` after the previous step's deadline, so the cycle's own bus time
comes out of the period; an overrun restarts the schedule from now. On
hardware it sleeps on the wall clock; in simulation it advances physics and
firmware to the deadline, and every bus transaction (``emulated``) or driver
call (``sim``) has already advanced them by its wire time at the configured
``i2c_clock_hz`` (docs/protocol.md, "Wire time").
"""

from __future__ import annotations

import abc
import dataclasses
import importlib
import inspect
import os
from collections.abc import Mapping
from pathlib import Path

from bioscara_gym.hardware.base_joint import BaseJoint
from bioscara_gym.hardware.bus import I2CBus, SMBusI2C
from bioscara_gym.hardware.clock import Clock, DeadlineScheduler, ManualClock, WallClock
from bioscara_gym.hardware.config import ArmConfig, JointConfig, load_config
from bioscara_gym.hardware.emulated_bus import EmulatedI2CBus, FaultPlan
from bioscara_gym.hardware.errors import require_extra
from bioscara_gym.hardware.firmware import JointFirmware
from bioscara_gym.hardware.gripper import BaseGripper, Gripper, MockGripper
from bioscara_gym.hardware.joint import Joint
from bioscara_gym.hardware.mock import MockJoint
from bioscara_gym.hardware.recording import BusWrapper, Recording, recorder
from bioscara_gym.hardware.registers import Flag
from bioscara_gym.hardware.registry import BACKENDS as REGISTRY
from bioscara_gym.hardware.stats import CommStats

#: The backends of the Bioscara's own joints (:data:`~bioscara_gym.hardware.registry.BACKENDS`).
BACKENDS = tuple(n for n, spec in REGISTRY.items() if spec.bioscara)
#: Every backend name :func:`make_backend` accepts, optional subpackages' included.
ALL_BACKENDS = tuple(REGISTRY)


def with_i2c_clock(config: ArmConfig, i2c_clock_hz: float | None) -> ArmConfig:
    """``config`` with the bus clock option in place of its own (``None``: unchanged).

    Raises:
        ConfigError: The clock is not a number > 0 (a ``ValueError``, one line naming ``i2c_clock_hz``).
    """
    return config if i2c_clock_hz is None else dataclasses.replace(config, i2c_clock_hz=i2c_clock_hz)


def default_state_dir() -> Path:
    """Where the gripper's last width is kept by default (``$XDG_STATE_HOME/bioscara``)."""
    base = os.environ.get("XDG_STATE_HOME") or os.path.join(os.path.expanduser("~"), ".local", "state")
    return Path(base) / "bioscara"


def gripper_state_file(config: ArmConfig, option: str | Path | None, default: bool) -> Path | None:
    """Where the gripper keeps its last width: the option, else the config, else a default.

    The default (``default_state_dir()/gripper.json``) applies to the real arm
    only; simulated backends keep no state unless asked to.
    """
    if option is not None:
        return Path(option)
    if config.gripper.state_file:
        return Path(config.gripper.state_file).expanduser()
    return default_state_dir() / "gripper.json" if default else None


def mock_gripper(config: ArmConfig, state_file: str | Path | None = None) -> MockGripper:
    """A :class:`MockGripper` with the configured transmission and limits (no state file by default)."""
    g = config.gripper
    return MockGripper(
        g.reduction,
        g.offset,
        g.min,
        g.max,
        g.backup_init_pos,
        state_file=gripper_state_file(config, state_file, default=False),
    )


def _i2c_joint(j: JointConfig, bus: I2CBus, retries: int, clock: Clock) -> Joint:
    """The I2C driver of joint ``j``, knowing its configured limits (for its position check)."""
    return Joint(
        j.name,
        j.address,
        j.reduction,
        j.min,
        j.max,
        bus,
        retries,
        clock,
        max_velocity=j.max_velocity,
        max_acceleration=j.max_acceleration,
    )


class Backend(abc.ABC):
    """Joints, gripper and clock of one arm: what the :class:`~bioscara_gym.hardware.arm.Arm` drives.

    The contract every backend keeps (the Arm, the envs, the console and
    deploy rely on nothing else):

    - :attr:`joints` holds one :class:`~bioscara_gym.hardware.base_joint.BaseJoint`
      per configured joint, by name, in configuration order; :attr:`gripper`
      one :class:`~bioscara_gym.hardware.gripper.BaseGripper`. Nothing is
      sent to a device before the Arm calls ``init()``.
    - :attr:`clock` is the one time source of the joints, the gripper and
      :meth:`step`: simulated (``sim``, ``mock``, ``emulated``, ``sitl``) or
      the wall clock (the arm), in seconds.
    - :meth:`step` lets one control period pass, on that clock, without drift.
    - :meth:`device_flags` and :meth:`device_currents` look into a device
      without a transaction where the backend can (a simulation, a mirror),
      else return ``None``; :meth:`comm_stats` and :meth:`loop_stats` are empty
      without a bus or sync loops.
    - :meth:`close` releases what the backend holds (bus handles, ports,
      loaded firmware); the Arm calls it once, on ``shutdown()``. A backend
      is a context manager that closes on leaving the ``with`` block.

    Attributes:
        name: Backend name, as :func:`make_backend` takes it.
        config: The arm configuration.
        joints: Joint name to joint, in configuration order.
        gripper: The gripper.
        clock: The backend's time source, s.
        sim: The MuJoCo arm where there is one, else ``None``.
        schedule: The control loop's deadlines on ``clock`` (:meth:`step`).
        options_to: ``module:Class`` whose ``__init__`` takes the options this
            backend's ``**kwargs`` passes on (:func:`make_backend` checks them).
    """

    name = ""
    options_to = ""

    def __init__(
        self,
        config: ArmConfig,
        joints: Mapping[str, BaseJoint],
        gripper: BaseGripper,
        clock: Clock,
        sim: object | None = None,
        schedule: DeadlineScheduler | None = None,
    ) -> None:
        """Bundle the parts; the schedule starts now unless one is given."""
        self.config = config
        self.joints = dict(joints)
        self.gripper = gripper
        self.clock = clock
        self.sim = sim
        self.schedule = schedule if schedule is not None else DeadlineScheduler(clock)

    def step(self, dt: float) -> None:
        """Wait (on hardware) or advance (in simulation) until ``dt`` after the previous step's deadline.

        The time since that deadline (bus transactions, the policy) is part
        of the period, so the loop keeps its rate without drift. A cycle
        that already took longer is an overrun: no wait, and the schedule
        restarts from now (:attr:`schedule` counts them).
        """
        self.schedule.wait(dt)

    def device_flags(self, name: str) -> Flag | None:
        """The flags joint ``name``'s device holds now, read without a bus transaction.

        Only a simulated or mock device can be looked into; on hardware this
        is ``None`` and the flags of the joint's last reply are what is known.
        """
        sim = self.sim
        if sim is not None:
            return Flag(sim.cores[name].flags)  # type: ignore[attr-defined]
        return None

    def device_currents(self, name: str) -> tuple[int, int] | None:
        """Joint ``name``'s drive and hold current (percent) as its device holds them, or ``None``.

        Only the firmware emulator behind a simulated arm can be looked
        into; on hardware and on ``mock`` this is ``None``.
        """
        sim = self.sim
        if sim is not None:
            core = sim.cores[name]  # type: ignore[attr-defined]
            return int(core.drive_current), int(core.hold_current)
        return None

    def comm_stats(self) -> dict[str, CommStats]:
        """Bus statistics per joint (empty where there is no bus)."""
        return {n: j.stats for n, j in self.joints.items() if isinstance(j, Joint)}

    def loop_stats(self) -> dict[str, object]:
        """Statistics of the bus's sync loops by loop name (the ``dynamixel`` backends; else empty).

        Each value has ``as_dict()`` (packets, errors, timeouts, achieved
        rate, since reset and in total) for logs, and ``reset()``.
        """
        return {}

    @abc.abstractmethod
    def close(self) -> None:
        """Release what the backend holds (bus handles, ports, loaded firmware); sends nothing."""

    def __enter__(self) -> Backend:
        """Use as a context manager."""
        return self

    def __exit__(self, *exc: object) -> None:
        """Close on leaving the ``with`` block."""
        self.close()


class SimBackend(Backend):
    """:class:`SimJoint` s and :class:`SimGripper` on the MuJoCo arm.

    There is no bus, but every driver call takes the wire time its
    transaction would take at ``i2c_clock_hz`` (the same the emulated bus
    charges), so readings are as old as on the arm.

    Args:
        config: Arm configuration.
        state_file: Gripper state file.
        i2c_clock_hz: Bus clock whose wire time each call takes, Hz;
            default the configuration's ``i2c_clock_hz``.
        sim_kwargs: Passed to :class:`ArmSim`.
    """

    name = "sim"
    options_to = "bioscara_gym.hardware.sim:ArmSim"

    def __init__(
        self,
        config: ArmConfig,
        state_file: str | Path | None = None,
        i2c_clock_hz: float | None = None,
        **sim_kwargs: object,
    ) -> None:
        """Build the simulated arm (kwargs go to :class:`ArmSim`)."""
        require_extra("mujoco", "the sim backend", "sim")
        from bioscara_gym.hardware.sim import ArmSim, SimGripper, make_sim_joints

        config = with_i2c_clock(config, i2c_clock_hz)
        sim = ArmSim(config, **sim_kwargs)  # type: ignore[arg-type]
        super().__init__(
            config,
            make_sim_joints(sim, i2c_clock_hz=config.i2c_clock_hz),
            SimGripper(config.gripper, sim, gripper_state_file(config, state_file, default=False)),
            sim.clock,
            sim,
            sim.schedule,
        )

    def close(self) -> None:
        """Nothing to release: the MuJoCo arm holds no handle."""


class EmulatedBackend(Backend):
    """The real :class:`Joint` driver over an :class:`EmulatedI2CBus` into the MuJoCo arm.

    Args:
        config: Arm configuration (addresses, reductions, limits).
        faults: Faults the bus injects; its ``drift_ppm`` scales the loop's
            periods (:attr:`FaultPlan.period_scale`).
        retries: Driver retries per transaction.
        state_file: Gripper state file.
        i2c_clock_hz: Bus clock, Hz, whose wire time every transaction
            takes; default the configuration's ``i2c_clock_hz``.
        wrap_bus: Puts the bus behind another before the joints get it
            (``record=`` of :func:`make_backend`; a replay's bus).
        sim_kwargs: Passed to :class:`ArmSim`.
    """

    name = "emulated"
    options_to = "bioscara_gym.hardware.sim:ArmSim"

    def __init__(
        self,
        config: ArmConfig,
        faults: FaultPlan | None = None,
        retries: int = 2,
        state_file: str | Path | None = None,
        wrap_bus: BusWrapper | None = None,
        i2c_clock_hz: float | None = None,
        **sim_kwargs: object,
    ) -> None:
        """Build the arm, one firmware per joint address, the bus and the drivers."""
        require_extra("mujoco", "the emulated backend", "sim")
        from bioscara_gym.hardware.sim import ArmSim, SimGripper

        config = with_i2c_clock(config, i2c_clock_hz)
        faults = faults or FaultPlan()
        sim = ArmSim(config, **sim_kwargs)  # type: ignore[arg-type]
        sim.schedule.scale = faults.period_scale
        self.devices = {
            j.address: JointFirmware(None, sim.clock, core=sim.cores[j.name]) for j in config.joints
        }
        self.bus: I2CBus = EmulatedI2CBus(
            self.devices, faults, clock=sim.clock, clock_hz=config.i2c_clock_hz, timing=config.bus_timing
        )
        if wrap_bus is not None:
            self.bus = wrap_bus(self.bus, sim.clock)
        joints = {j.name: _i2c_joint(j, self.bus, retries, sim.clock) for j in config.joints}
        gripper = SimGripper(config.gripper, sim, gripper_state_file(config, state_file, default=False))
        super().__init__(config, joints, gripper, sim.clock, sim, sim.schedule)

    def close(self) -> None:
        """Close the emulated bus."""
        self.bus.close()


class MockBackend(Backend):
    """:class:`MockJoint` s and a :class:`MockGripper` on a manual clock."""

    name = "mock"

    def __init__(
        self,
        config: ArmConfig,
        homing_time_s: float = 1.0,
        state_file: str | Path | None = None,
        clock: Clock | None = None,
    ) -> None:
        """Build mirrors of every configured joint."""
        clock = clock or ManualClock()
        joints = {
            j.name: MockJoint(j.name, j.reduction, j.min, j.max, clock, homing_time_s) for j in config.joints
        }
        super().__init__(config, joints, mock_gripper(config, state_file), clock)

    def close(self) -> None:
        """Nothing to release: the mirrors hold no handle."""

    def device_flags(self, name: str) -> Flag | None:
        """The mirror's own flags (see :meth:`Backend.device_flags`)."""
        return Flag(self.joints[name].device_flags)  # type: ignore[attr-defined]


class I2CBackend(Backend):
    """The real arm: :class:`Joint` s over ``/dev/i2c-N``, the sysfs PWM gripper.

    ``step(dt)`` waits on the wall clock until ``dt`` has passed since the
    previous step's deadline (a fixed-rate loop), not ``dt`` from now. ``bus``,
    ``clock`` and ``gripper`` replace ``/dev/i2c-N``, the wall clock and the
    sysfs gripper (a replay's); ``wrap_bus`` as for :class:`EmulatedBackend`.
    """

    name = "i2c"

    def __init__(
        self,
        config: ArmConfig,
        bus: I2CBus | None = None,
        retries: int = 2,
        state_file: str | Path | None = None,
        sysfs_root: str | Path = "/sys/class/pwm",
        clock: Clock | None = None,
        gripper: BaseGripper | None = None,
        wrap_bus: BusWrapper | None = None,
    ) -> None:
        """Open the bus and build the drivers (nothing is sent yet)."""
        clock = clock if clock is not None else WallClock()
        self.bus = bus if bus is not None else SMBusI2C(config.bus)
        if wrap_bus is not None:
            self.bus = wrap_bus(self.bus, clock)
        joints = {j.name: _i2c_joint(j, self.bus, retries, clock) for j in config.joints}
        g = config.gripper
        gripper = gripper or Gripper(
            g.reduction,
            g.offset,
            g.min,
            g.max,
            g.backup_init_pos,
            state_file=gripper_state_file(config, state_file, default=True),
            pwm_chip=g.pwm_chip,
            pwm_channel=g.pwm_channel,
            sysfs_root=sysfs_root,
        )
        super().__init__(config, joints, gripper, clock)

    def close(self) -> None:
        """Close the bus."""
        self.bus.close()


def make_backend(
    name: str = "sim", config: ArmConfig | str | os.PathLike[str] | None = None, **options: object
) -> Backend:
    """Build a backend by name.

    Args:
        name: One of :data:`ALL_BACKENDS`.
        config: An :class:`ArmConfig`, a YAML path, or ``None`` for the
            packaged default.
        **options: Backend-specific options (e.g. ``faults`` for ``emulated``
            and ``sitl``, ``firmware`` for ``sitl``, ``initial_qpos`` for the
            simulated ones, ``state_file``), and
            ``record``: a :class:`~.recording.Recording` (or a path) to write
            every bus transaction to (``i2c`` and ``emulated``; docs/traces.md).

    Raises:
        ValueError: Unknown backend name; ``record`` on a backend without a bus.
    """
    if not isinstance(config, ArmConfig):
        config = load_config(config)
    spec = REGISTRY.get(name)
    if spec is None:
        raise ValueError(f"unknown backend {name!r}; expected one of {', '.join(ALL_BACKENDS)}")
    if spec.needs is not None:
        require_extra(spec.needs[0], f"the {name} backend", spec.needs[1])
    module, _, cls_name = spec.entry_point.partition(":")
    cls: type[Backend] = getattr(importlib.import_module(module), cls_name)
    takes = _options_of(cls)
    unknown = sorted(set(options) - takes - {"record"}) if takes is not None else []
    if unknown:  # seen: a raw TypeError from the class's __init__
        offered = ", ".join(sorted(takes - {"wrap_bus"} | ({"record"} if spec.records else set())))
        raise ValueError(f"the {name} backend takes no option {', '.join(unknown)}; its options: {offered}")
    record = options.pop("record", None)
    if record is not None:
        if not spec.records:
            raise ValueError(f"--record needs a backend with an I2C bus (i2c, emulated); {name} has none")
        if not isinstance(record, Recording):
            record = Recording(Path(record), "")  # type: ignore[arg-type]
        options["wrap_bus"] = recorder(record, name, config)
    return cls(config, **options)  # type: ignore[arg-type]


def _options_of(cls: type) -> set[str] | None:
    """The keyword options ``cls`` takes after its configuration, with those its ``**kwargs`` passes on.

    ``None``: it takes any (``**kwargs`` that goes to no class named in ``options_to``).
    """
    params = list(inspect.signature(cls.__init__).parameters.values())[2:]  # self, config
    names = {p.name for p in params if p.kind is p.KEYWORD_ONLY or p.kind is p.POSITIONAL_OR_KEYWORD}
    if any(p.kind is p.VAR_KEYWORD for p in params):
        module, _, target = getattr(cls, "options_to", "").partition(":")
        if not target:
            return None
        more = _options_of(getattr(importlib.import_module(module), target))
        return None if more is None else names | more
    return names
