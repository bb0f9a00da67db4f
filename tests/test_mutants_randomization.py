"""Tests that kill mutants of bioscara_gym/envs/randomization.py (issue #24 item 11, docs/mutation.md).

Expected values are literals from ``DomainRandomization``'s docstring (all
off by default; 0.2 spreads masses over U(0.8, 1.2); noise a std, latency a
count of steps), its validation messages and ``PhysicsRandomizer``'s
(masses and inertias, friction and damping scaled around the nominal values
read the first time). The model is a stand-in with the ``MjModel`` arrays
the randomizer touches: plain numpy, no MuJoCo.
"""

from __future__ import annotations

import re
from types import SimpleNamespace

import numpy as np
import pytest

from bioscara_gym.envs.randomization import DomainRandomization, PhysicsRandomizer


def test_all_off_by_default() -> None:
    r = DomainRandomization()
    assert (r.mass, r.friction, r.damping, r.sensor_noise, r.latency_steps) == (0.0, 0.0, 0.0, 0.0, 0)
    assert r.physics is False


@pytest.mark.parametrize("field", ["mass", "friction", "damping"])
def test_any_spread_alone_randomizes_physics(field: str) -> None:
    assert DomainRandomization(**{field: 0.1}).physics is True


@pytest.mark.parametrize("field", ["sensor_noise", "latency_steps"])
def test_noise_and_latency_are_not_physics(field: str) -> None:
    assert DomainRandomization(**{field: 1}).physics is False


@pytest.mark.parametrize("field", ["mass", "friction", "damping"])
@pytest.mark.parametrize("value", [0.0, 0.5, 0.999])
def test_a_spread_within_0_and_1_is_accepted(field: str, value: float) -> None:
    assert getattr(DomainRandomization(**{field: value}), field) == value


@pytest.mark.parametrize("field", ["mass", "friction", "damping"])
@pytest.mark.parametrize("value", [1.0, -0.01, 2.0])
def test_a_spread_outside_0_to_1_is_refused_naming_it(field: str, value: float) -> None:
    with pytest.raises(ValueError, match=rf"^randomization {field}={value} must be within \[0, 1\)$"):
        DomainRandomization(**{field: value})


def test_negative_sensor_noise_is_refused_and_zero_accepted() -> None:
    assert DomainRandomization(sensor_noise=0.0).sensor_noise == 0.0
    with pytest.raises(ValueError, match=r"^randomization sensor_noise=-0.001 must be >= 0 and finite$"):
        DomainRandomization(sensor_noise=-0.001)


def test_negative_latency_is_refused_and_zero_accepted() -> None:
    assert DomainRandomization(latency_steps=0).latency_steps == 0
    assert DomainRandomization(latency_steps=25).latency_steps == 25  # a second at 25 Hz
    for steps in (-1, 26, 10**6):  # seen: 10**6 taken, and the arm never moved
        with pytest.raises(ValueError, match=f"^randomization latency_steps={steps} must be from 0 to 25$"):
            DomainRandomization(latency_steps=steps)


def test_default_on_is_the_moderate_setting() -> None:
    on = DomainRandomization.default_on()
    assert on == DomainRandomization(
        mass=0.2, friction=0.3, damping=0.3, sensor_noise=0.0005, latency_steps=1
    )


@pytest.mark.parametrize("off", [None, False])
def test_coerce_none_and_false_are_all_off(off: object) -> None:
    assert DomainRandomization.coerce(off) == DomainRandomization()


def test_coerce_true_is_default_on_a_dict_its_fields_an_instance_itself() -> None:
    assert DomainRandomization.coerce(True) == DomainRandomization.default_on()
    assert DomainRandomization.coerce({"mass": 0.1, "latency_steps": 2}) == DomainRandomization(
        mass=0.1, latency_steps=2
    )
    r = DomainRandomization(friction=0.4)
    assert DomainRandomization.coerce(r) is r


@pytest.mark.parametrize("bad", [1, 0.2, "on", [0.2]])
def test_coerce_refuses_anything_else_naming_it(bad: object) -> None:
    # A ValueError, as every other bad env setting: the CLI says it in one line.
    message = (
        "randomization must be true, false, null or a mapping of "
        f"mass, friction, damping, sensor_noise, latency_steps; got {bad!r}"
    )
    with pytest.raises(ValueError, match=f"^{re.escape(message)}$"):
        DomainRandomization.coerce(bad)


def test_coerce_refuses_a_field_there_is_not_listing_those_there_are() -> None:
    message = "randomization has 'bogus'; it takes mass, friction, damping, sensor_noise, latency_steps"
    with pytest.raises(ValueError, match=f"^{re.escape(message)}$"):
        DomainRandomization.coerce({"mass": 0.1, "bogus": 1})


@pytest.mark.parametrize(
    ("field", "value", "kind"),
    [
        ("mass", "0.2", "a number"),
        ("friction", None, "a number"),
        ("damping", True, "a number"),
        ("sensor_noise", [0.1], "a number"),
        ("latency_steps", 1.5, "an integer"),
        ("latency_steps", "2", "an integer"),
        ("latency_steps", False, "an integer"),
    ],
)
def test_a_field_of_the_wrong_type_is_refused_naming_it(field: str, value: object, kind: str) -> None:
    message = f"randomization {field}={value!r} must be {kind}"
    with pytest.raises(ValueError, match=f"^{re.escape(message)}$"):
        DomainRandomization.coerce({field: value})


def test_infinite_sensor_noise_is_refused() -> None:
    with pytest.raises(ValueError, match=r"^randomization sensor_noise=inf must be >= 0 and finite$"):
        DomainRandomization(sensor_noise=float("inf"))
    assert DomainRandomization(sensor_noise=1e6).sensor_noise == 1e6


# ------------------------------------------------------------ PhysicsRandomizer


def _model(nbody: int = 400, ngeom: int = 400, nv: int = 400) -> SimpleNamespace:
    """The arrays of an ``MjModel`` the randomizer scales, with distinct nominal values."""
    return SimpleNamespace(
        nbody=nbody,
        ngeom=ngeom,
        nv=nv,
        body_mass=np.linspace(0.5, 2.0, nbody),
        body_inertia=np.outer(np.linspace(1.0, 3.0, nbody), [1.0, 2.0, 3.0]),
        geom_friction=np.outer(np.linspace(0.5, 1.5, ngeom), [1.0, 0.005, 0.0001]),
        dof_damping=np.linspace(0.1, 4.0, nv),
    )


def _assert_spread(ratio: np.ndarray, spread: float) -> None:
    """``ratio`` drawn from U(1 - spread, 1 + spread): inside it, and over most of it."""
    assert np.all(ratio >= 1.0 - spread) and np.all(ratio <= 1.0 + spread)
    assert ratio.min() < 1.0 - 0.9 * spread and ratio.max() > 1.0 + 0.9 * spread


def test_physics_off_leaves_the_model_alone() -> None:
    m = _model()
    nominal = _model()
    PhysicsRandomizer(DomainRandomization(sensor_noise=0.1, latency_steps=2)).randomize(
        m, np.random.default_rng(0)
    )
    for name in ("body_mass", "body_inertia", "geom_friction", "dof_damping"):
        np.testing.assert_array_equal(getattr(m, name), getattr(nominal, name))


def test_nominal_puts_back_every_array_the_draw_scaled() -> None:
    m, nominal = _model(), _model()
    physics = PhysicsRandomizer(DomainRandomization(mass=0.2, friction=0.3, damping=0.3))
    physics.nominal(m)  # before any draw: nothing read, nothing changed
    physics.randomize(m, np.random.default_rng(3))
    assert not np.array_equal(m.body_mass, nominal.body_mass)
    physics.nominal(m)
    for name in ("body_mass", "body_inertia", "geom_friction", "dof_damping"):
        np.testing.assert_array_equal(getattr(m, name), getattr(nominal, name))


def test_masses_and_inertias_scale_together_per_body() -> None:
    m, nominal = _model(), _model()
    PhysicsRandomizer(DomainRandomization(mass=0.2)).randomize(m, np.random.default_rng(1))
    ratio = m.body_mass / nominal.body_mass
    _assert_spread(ratio, 0.2)
    np.testing.assert_allclose(
        m.body_inertia / nominal.body_inertia, np.outer(ratio, [1.0, 1.0, 1.0]), rtol=1e-12
    )
    np.testing.assert_array_equal(m.geom_friction, nominal.geom_friction)  # friction 0: scaled by exactly 1
    np.testing.assert_array_equal(m.dof_damping, nominal.dof_damping)


def test_friction_scales_per_geom_all_three_coefficients_alike() -> None:
    m, nominal = _model(), _model()
    PhysicsRandomizer(DomainRandomization(friction=0.3)).randomize(m, np.random.default_rng(2))
    ratio = m.geom_friction / nominal.geom_friction
    _assert_spread(ratio[:, 0], 0.3)
    np.testing.assert_allclose(ratio, np.outer(ratio[:, 0], [1.0, 1.0, 1.0]), rtol=1e-12)
    np.testing.assert_array_equal(m.body_mass, nominal.body_mass)


def test_damping_scales_per_dof() -> None:
    m, nominal = _model(), _model()
    PhysicsRandomizer(DomainRandomization(damping=0.3)).randomize(m, np.random.default_rng(3))
    _assert_spread(m.dof_damping / nominal.dof_damping, 0.3)
    np.testing.assert_array_equal(m.body_inertia, nominal.body_inertia)


def test_each_draw_scales_the_nominal_values_read_the_first_time() -> None:
    m = _model()
    m.dof_damping[0] = 1e9  # changed before the first draw (Reach pins its block): nominal
    first = _model()
    first.dof_damping[0] = 1e9
    r = PhysicsRandomizer(DomainRandomization(mass=0.2, friction=0.3, damping=0.3))
    rng = np.random.default_rng(4)
    for _ in range(5):  # scaled from the nominal each time, never from the last draw
        r.randomize(m, rng)
        _assert_spread(m.body_mass / first.body_mass, 0.2)
        _assert_spread(m.geom_friction[:, 0] / first.geom_friction[:, 0], 0.3)
        _assert_spread(m.dof_damping / first.dof_damping, 0.3)
    assert 0.7e9 <= m.dof_damping[0] <= 1.3e9


def test_the_settings_are_kept() -> None:
    s = DomainRandomization(mass=0.1)
    assert PhysicsRandomizer(s).settings is s
