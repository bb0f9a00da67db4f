"""The backends and joint types by name: the one place every reader of a name looks.

Data only, as Gymnasium keeps its registrations: names and ``module:Class``
strings, imported when one is built. :func:`~bioscara_gym.hardware.backends.make_backend`
builds a backend from :data:`BACKENDS`; the configuration loader checks a
joint's ``type`` against :data:`DRIVERS`; the envs (``backend=``), the
console (``--backend``, ``--state``), ``--record`` and deploy take their
choices from the flags below. A new backend or joint type is its module and
one entry here (docs/extending.md).
"""

from __future__ import annotations

from dataclasses import dataclass


@dataclass(frozen=True)
class BackendSpec:
    """One backend.

    Attributes:
        name: The name ``make_backend``, ``backend=`` and ``--backend`` take.
        entry_point: Its :class:`~bioscara_gym.hardware.backends.Backend` subclass, ``module:Class``.
        description: A few words for messages and docs.
        needs: The module it needs and the extra that installs it
            (``("mujoco", "sim")``), checked before it is imported.
        bioscara: Whether it drives the Bioscara's own joints (the core
            backends) rather than an optional subpackage's (Dynamixel servos).
        records: Whether it has an I2C bus ``--record`` can trace.
        deployable: Whether ``bioscara deploy`` drives it.
        persistent: Whether the console's ``--state`` keeps it between commands.
    """

    name: str
    entry_point: str
    description: str
    needs: tuple[str, str] | None = None
    bioscara: bool = True
    records: bool = False
    deployable: bool = False
    persistent: bool = False


@dataclass(frozen=True)
class DriverSpec:
    """One joint type: a configuration ``type`` and its driver.

    Attributes:
        name: The configuration's ``type:`` value.
        entry_point: Its :class:`~bioscara_gym.hardware.base_joint.BaseJoint` subclass, ``module:Class``.
        description: A few words for messages and docs.
    """

    name: str
    entry_point: str
    description: str


_MUJOCO = ("mujoco", "sim")

#: Every backend, by name, in the order messages list them.
BACKENDS: dict[str, BackendSpec] = {
    spec.name: spec
    for spec in (
        BackendSpec(
            "sim",
            "bioscara_gym.hardware.backends:SimBackend",
            "the MuJoCo arm, firmware rules without bytes",
            needs=_MUJOCO,
            persistent=True,
        ),
        BackendSpec(
            "mock", "bioscara_gym.hardware.backends:MockBackend", "mirrors on a manual clock", deployable=True
        ),
        BackendSpec(
            "emulated",
            "bioscara_gym.hardware.backends:EmulatedBackend",
            "the real driver over the emulated bus into the MuJoCo arm",
            needs=_MUJOCO,
            records=True,
            deployable=True,
            persistent=True,
        ),
        BackendSpec(
            "i2c",
            "bioscara_gym.hardware.backends:I2CBackend",
            "the real arm on /dev/i2c-N",
            records=True,
            deployable=True,
        ),
        BackendSpec(
            "sitl",
            "bioscara_gym.hardware.sitl.arm:SitlBackend",
            "as emulated, each device the joint firmware's own source",
            needs=_MUJOCO,
            deployable=True,
        ),
        BackendSpec(
            "dynamixel",
            "bioscara_gym.hardware.dynamixel.backend:DynamixelBackend",
            "Dynamixel XL430 joints on a serial port",
            bioscara=False,
        ),
        BackendSpec(
            "dynamixel-emulated",
            "bioscara_gym.hardware.dynamixel.backend:EmulatedDynamixelBackend",
            "the same over emulated XL430 servos",
            bioscara=False,
        ),
    )
}

#: Every joint type, by the configuration's ``type:`` value.
DRIVERS: dict[str, DriverSpec] = {
    spec.name: spec
    for spec in (
        DriverSpec("i2c", "bioscara_gym.hardware.joint:Joint", "the Bioscara's I2C stepper joint"),
        DriverSpec(
            "dynamixel", "bioscara_gym.hardware.dynamixel.joint:DynamixelJoint", "a Dynamixel XL430 servo"
        ),
    )
}


def backend_names(flag: str | None = None) -> tuple[str, ...]:
    """The names of the backends, or of those whose ``flag`` (``deployable``, ``records``...) is set."""
    return tuple(n for n, spec in BACKENDS.items() if flag is None or getattr(spec, flag))
