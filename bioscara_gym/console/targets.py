"""What a console command names: the common options, joints and groups, homing directions.

Everything here is checked against the configuration alone, before a
command locks its state file or opens the bus (:class:`~bioscara_gym.console.session.Session`'s
``check``): a request refused for its arguments sends nothing and writes nothing.
"""

from __future__ import annotations

import argparse
import dataclasses
import math
from collections.abc import Mapping
from dataclasses import dataclass, field
from pathlib import Path

from bioscara_gym.errors import ConsoleUsageError
from bioscara_gym.fsutil import output_clash
from bioscara_gym.hardware.arm import check_joint_targets
from bioscara_gym.hardware.backends import ALL_BACKENDS
from bioscara_gym.hardware.config import GRIPPER_NAME, ArmConfig, load_config
from bioscara_gym.hardware.errors import InvalidArgumentError
from bioscara_gym.hardware.recording import Recording
from bioscara_gym.hardware.registry import backend_names

#: Backends whose state ``--state`` can keep.
PERSISTENT_BACKENDS = backend_names("persistent")
#: Backends on an I2C bus whose number ``--bus`` sets (the emulated bus has no number).
BUS_BACKENDS = ("i2c",)
#: Backends driving the Bioscara's own joints, which have no REBOOT (only Dynamixel servos do).
REBOOTLESS_BACKENDS = backend_names("bioscara")
#: ``--direction`` to the Arm's homing direction: ``+`` to the max end stop, ``-`` to min.
HOMING_DIRECTIONS = {"+": 1, "-": -1}


@dataclass(frozen=True)
class ConsoleOptions:
    """The options every operator subcommand shares.

    Attributes:
        backend: Backend name (see :data:`~bioscara_gym.hardware.backends.ALL_BACKENDS`).
        config: Arm configuration YAML, ``None`` for the packaged default.
        bus: I2C bus number overriding the configuration's.
        state: State file for the simulated backends, ``None`` for none.
        record: ``--record``: the bus trace to append this command's session to.
        firmware: ``--firmware``: the joint firmware's folder for the ``sitl`` backend.
        backend_options: More options for the backend (a replay's bus and clock).
    """

    backend: str = "emulated"
    config: Path | None = None
    bus: int | None = None
    state: Path | None = None
    record: Recording | None = None
    firmware: Path | None = None
    backend_options: Mapping[str, object] = field(default_factory=dict)

    @classmethod
    def from_args(cls, args: argparse.Namespace) -> ConsoleOptions:
        """Take the common options from parsed arguments."""
        record = getattr(args, "record", None)
        _check_apart(args.state, record, args.config)  # before Recording reads the file as a trace
        return cls(
            backend=args.backend,
            config=args.config,
            bus=args.bus,
            state=args.state,
            record=None if record is None else Recording(record, getattr(args, "command", ""), args),
            firmware=getattr(args, "firmware", None),
            backend_options=getattr(args, "backend_options", None) or {},
        )

    def check(self) -> None:
        """Refuse an unknown backend, and ``--bus``, ``--firmware`` or ``--state`` on a backend without one.

        Raises:
            ConsoleUsageError: The options do not go together.
        """
        backend = self.backend
        if backend not in ALL_BACKENDS:
            raise ConsoleUsageError(f"unknown backend {backend!r}; expected one of {', '.join(ALL_BACKENDS)}")
        if self.bus is not None and backend not in BUS_BACKENDS:
            raise ConsoleUsageError(
                f"--bus {self.bus} needs --backend {' or '.join(BUS_BACKENDS)} (a numbered I2C bus); "
                f"{backend} has none"
            )
        if self.firmware is not None and backend != "sitl":
            raise ConsoleUsageError("--firmware needs --backend sitl (the firmware in the loop)")
        if self.state is not None and backend not in PERSISTENT_BACKENDS:
            reason = (
                "mock state does not persist" if backend == "mock" else "the real arm keeps its own state"
            )
            raise ConsoleUsageError(
                f"--state works with the {' and '.join(PERSISTENT_BACKENDS)} backends; {reason}"
            )
        if self.record is not None:
            trace = Path(self.record.path)
            _check_apart(self.state, trace, self.config)
            if trace.exists() and not trace.is_file():
                raise ConsoleUsageError(f"--record {trace} is not a regular file")

    def arm_config(self) -> ArmConfig:
        """The arm configuration the command uses: ``--config`` (or the packaged one), ``--bus`` applied.

        Raises:
            ConfigError: The file cannot be read or holds an invalid value.
        """
        config = load_config(self.config)
        if self.bus is not None:
            config = dataclasses.replace(config, bus=self.bus)
        return config


@dataclass(frozen=True)
class Target:
    """Devices a joint or group name stands for.

    Attributes:
        joints: Joint names, in configuration order.
        gripper: Whether the gripper is included.
    """

    joints: tuple[str, ...]
    gripper: bool

    @property
    def names(self) -> list[str]:
        """The joints, then ``gripper`` if included: the names the Arm's enable and disable take."""
        return [*self.joints, *([GRIPPER_NAME] if self.gripper else [])]


def resolve_target(config: ArmConfig, name: str | None) -> Target:
    """Resolve a joint, ``gripper`` or group name.

    Args:
        config: The arm configuration (joints and groups).
        name: A joint name, ``"gripper"``, a group name, or ``None`` for
            the group ``all`` (every joint and the gripper if not configured).

    Returns:
        The joints (configuration order) and whether the gripper is included.

    Raises:
        InvalidArgumentError: Unknown name; the message lists joints and groups.
    """
    if name is None:
        if "all" not in config.groups:
            return Target(config.names, True)
        name = "all"
    if name in config.names:
        return Target((name,), False)
    if name == GRIPPER_NAME:
        return Target((), True)
    members = config.groups.get(name)
    if members is None:
        raise InvalidArgumentError(
            f"unknown joint or group {name!r}; joints: {', '.join((*config.names, GRIPPER_NAME))}; "
            f"groups: {', '.join(config.groups) or 'none'}"
        )
    return Target(tuple(n for n in config.names if n in members), GRIPPER_NAME in members)


def resolve_joints(config: ArmConfig, name: str | None, gripper_has_no: str = "homing") -> tuple[str, ...]:
    """The joints of a joint or group name (as :func:`resolve_target`), for homing or a reboot.

    Args:
        config: The arm configuration (joints and groups).
        name: A joint or group name, ``None`` for the group ``all``.
        gripper_has_no: What the command does, for the refusal of the gripper alone.

    Raises:
        InvalidArgumentError: Unknown name, or the name stands for the gripper only.
    """
    target = resolve_target(config, name)
    if not target.joints:
        raise InvalidArgumentError(
            f"{name}: the gripper has no {gripper_has_no}; name a joint or a group of joints"
        )
    return target.joints


#: What ``reboot`` says of the gripper alone.
GRIPPER_NO_REBOOT = "REBOOT (only Dynamixel joints have one)"


def reboot_joints(config: ArmConfig, backend: str, name: str) -> tuple[str, ...]:
    """The joints ``reboot NAME`` sends REBOOT to, refusing a backend whose joints have none.

    Raises:
        InvalidArgumentError: Unknown name, the gripper alone, or joints without REBOOT.
    """
    names = resolve_joints(config, name, GRIPPER_NO_REBOOT)
    if backend in REBOOTLESS_BACKENDS:
        raise InvalidArgumentError(
            f"{names[0]}: the {backend} backend's joints have no REBOOT; only Dynamixel joints do "
            "(power-cycle a Bioscara joint instead)"
        )
    return names


def check_position(config: ArmConfig, name: str, value: float) -> None:
    """Refuse an unknown joint, or a position not finite or outside its limits (the Arm's check).

    Raises:
        InvalidArgumentError: Naming the joint, the value and the limits.
    """
    check_joint_targets(config, {name: value})


def check_gripper_width(config: ArmConfig, width_m: float) -> None:
    """Refuse a gripper width not finite or outside the gripper's limits.

    Raises:
        InvalidArgumentError: Naming the width and the limits.
    """
    g = config.gripper
    if not (math.isfinite(width_m) and g.min <= width_m <= g.max):
        raise InvalidArgumentError(
            f"gripper: width {width_m:g} m is outside the limits [{g.min:g}, {g.max:g}] m"
        )


def _check_apart(state: Path | None, record: Path | None, config: Path | None) -> None:
    """Refuse ``--state`` and ``--record`` on one file (each would spoil the other), or on ``--config``.

    Seen (a hostile test): ``--state`` naming the configuration was "cannot be read ...; delete it
    to start from a powered-up arm", advice to delete the configuration.

    Raises:
        ConsoleUsageError: Two of them name one file.
    """
    clash = output_clash({"--state": state, "--record": record}, {"--config": config})
    if clash is not None:
        raise ConsoleUsageError(clash)
