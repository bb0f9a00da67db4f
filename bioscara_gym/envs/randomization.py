"""Per-episode domain randomization: physics of the MuJoCo model, sensor noise, latency.

The settings (:class:`DomainRandomization`) and the draw of the model's
physics (:class:`PhysicsRandomizer`), which scales the arrays of a compiled
model in place: no MuJoCo import, and nothing to do where the backend has
no model (``mock``, ``i2c``). Sensor noise and latency are applied by the
env's loop (:class:`~bioscara_gym.envs.base.BioscaraEnv`).
"""

from __future__ import annotations

import math
import numbers
from dataclasses import dataclass, fields
from typing import Any

import numpy as np

#: Most control steps of command latency: a second at the default 25 Hz. A command reaches
#: the real joints within the cycle it is sent in (a transaction takes well under a millisecond,
#: docs/protocol.md), so a longer delay models no arm; it only leaves the policy without control.
MAX_LATENCY_STEPS = 25


@dataclass(frozen=True)
class DomainRandomization:
    """Per-episode randomization, all off (zero) by default; drawn from the env's seed.

    Attributes:
        mass: Relative spread of link masses (0.2: each scaled by U(0.8, 1.2)).
        friction: Relative spread of geom friction.
        damping: Relative spread of joint damping.
        sensor_noise: Std of Gaussian noise on measured joint positions (rad or m): what the
            policy observes and the cartesian controller acts on. The task draws its goals
            from, and its objects follow, the joints as the arm reports them.
        latency_steps: Maximum command latency in control steps (drawn 0..N), at most
            :data:`MAX_LATENCY_STEPS`.
    """

    mass: float = 0.0
    friction: float = 0.0
    damping: float = 0.0
    sensor_noise: float = 0.0
    latency_steps: int = 0

    def __post_init__(self) -> None:
        """Validate the types and ranges (one-line ``ValueError`` naming the field)."""
        for field in fields(self):
            value = getattr(self, field.name)
            wanted = numbers.Integral if field.name == "latency_steps" else numbers.Real
            if isinstance(value, bool) or not isinstance(value, wanted):
                kind = "an integer" if wanted is numbers.Integral else "a number"
                raise ValueError(f"randomization {field.name}={value!r} must be {kind}")
        for name in ("mass", "friction", "damping"):
            value = getattr(self, name)
            if not 0.0 <= value < 1.0:
                raise ValueError(f"randomization {name}={value} must be within [0, 1)")
        if not 0.0 <= self.sensor_noise < math.inf:
            raise ValueError(f"randomization sensor_noise={self.sensor_noise} must be >= 0 and finite")
        if not 0 <= self.latency_steps <= MAX_LATENCY_STEPS:  # seen: 10**6 taken, and the arm never moved
            raise ValueError(
                f"randomization latency_steps={self.latency_steps} must be from 0 to {MAX_LATENCY_STEPS}"
            )

    @property
    def physics(self) -> bool:
        """Whether any model parameter is randomized."""
        return bool(self.mass or self.friction or self.damping)

    @classmethod
    def default_on(cls) -> DomainRandomization:
        """A moderate setting for sim-to-real training."""
        return cls(mass=0.2, friction=0.3, damping=0.3, sensor_noise=0.0005, latency_steps=1)

    @classmethod
    def coerce(cls, value: DomainRandomization | dict | bool | None) -> DomainRandomization:
        """The settings the env's ``randomization`` argument stands for.

        Args:
            value: ``None`` or ``False``: all off; ``True``: :meth:`default_on`;
                a dict: its fields; a :class:`DomainRandomization`: itself.

        Raises:
            ValueError: ``value`` is none of these, names a field there is
                not, or a field is of the wrong type or out of range.
        """
        if value is None or value is False:
            return cls()
        if value is True:
            return cls.default_on()
        names = [field.name for field in fields(cls)]
        if isinstance(value, dict):
            unknown = [key for key in value if key not in names]
            if unknown:
                raise ValueError(f"randomization has {unknown[0]!r}; it takes {', '.join(names)}")
            return cls(**value)
        if isinstance(value, DomainRandomization):
            return value
        raise ValueError(
            f"randomization must be true, false, null or a mapping of {', '.join(names)}; got {value!r}"
        )


class PhysicsRandomizer:
    """Scales a MuJoCo model's masses, inertias, friction and damping around their nominal values.

    The nominal values are read from the model the first time it is
    randomized, so a model another part of the env changed before (Reach
    pins its unused block with a huge damping) keeps that change as nominal.

    Args:
        settings: The spreads to draw from.
    """

    def __init__(self, settings: DomainRandomization) -> None:
        """Remember ``settings``; nothing is read from a model yet."""
        self.settings = settings
        self._nominal: dict[str, np.ndarray] | None = None

    def randomize(self, model: Any, rng: np.random.Generator) -> None:
        """Draw new physics parameters for ``model`` (an ``MjModel``) from ``rng``, in place."""
        r = self.settings
        if not r.physics:
            return
        m = model
        if self._nominal is None:
            self._nominal = {
                "mass": m.body_mass.copy(),
                "inertia": m.body_inertia.copy(),
                "friction": m.geom_friction.copy(),
                "damping": m.dof_damping.copy(),
            }
        nom = self._nominal
        scale = rng.uniform(1 - r.mass, 1 + r.mass, size=m.nbody)
        m.body_mass[:] = nom["mass"] * scale
        m.body_inertia[:] = nom["inertia"] * scale[:, None]
        m.geom_friction[:] = nom["friction"] * rng.uniform(1 - r.friction, 1 + r.friction, size=(m.ngeom, 1))
        m.dof_damping[:] = nom["damping"] * rng.uniform(1 - r.damping, 1 + r.damping, size=m.nv)

    def nominal(self, model: Any) -> None:
        """Put ``model``'s nominal values back (nothing to do before the first :meth:`randomize`)."""
        if self._nominal is None:
            return
        nom, m = self._nominal, model
        m.body_mass[:] = nom["mass"]
        m.body_inertia[:] = nom["inertia"]
        m.geom_friction[:] = nom["friction"]
        m.dof_damping[:] = nom["damping"]
