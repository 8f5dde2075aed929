"""The effects library: registry, priors, hooks, composition, and a user-written effect."""

from __future__ import annotations

import dataclasses

import equinox as eqx
import jax.numpy as jnp
import numpy as np
import pytest

from mfdesign.physics import effects as fx
from mfdesign.physics.effects import (
    EFFECTS,
    Context,
    MeasurementEffect,
    MechanicalEffect,
    Normal,
    Parameter,
    Rows,
    Uniform,
    LogNormal,
    apply_expected_force,
    apply_sim_params,
    recorded_lift_height,
    neutral_theta,
    register_effect,
    split_theta,
    typical_theta,
)
from mfdesign.physics.params import SimParams

EXPECTED = {
    "thickness_deviation",
    "thickness_gradient",
    "clamp_prestretch",
    "ring_softening",
    "ring_stiffening",
    "contact_offset",
    "fabric_inset",
    "rubber_i2",
    "stress_softening",
    "lift_preload",
    "pressure_sensor",
    "load_cell_offset",
    "rig_compliance",
    "hysteresis",
}


def _rows(n=5, experiment="force", deflate=False, h=30.0, p=None):
    """Recorded rows: plate at ``h`` mm, pressures 0..4 kPa (or ``p``), one kind and phase."""
    p = np.linspace(0, 4000, n) if p is None else p
    return Rows(
        h_mm=jnp.full(n, h),
        p_pa=jnp.asarray(p, float),
        is_force=jnp.full(n, experiment == "force"),
        is_deflate=jnp.broadcast_to(jnp.asarray(deflate), (n,)),
        is_first_trial=jnp.ones(n, bool),
        membrane=jnp.zeros(n, jnp.int32),
    )


def _law(h, p):
    """A force law [N]: rises with pressure, falls with height (slope -1.5 N/mm)."""
    return 0.01 * p - 1.5 * (h - 30.0)


def _ctx(**kw):
    return Context(**{"experiment": "force", "trial_index": np.zeros(5, int), **kw})


def test_registry_has_the_candidates():
    assert EXPECTED <= set(EFFECTS)
    for name, cls in EFFECTS.items():
        e = cls()
        assert e.name == name and e.story and e.parameters
        assert e.acts_on_mechanics or e.acts_on_measurement
        for p in e.parameters:
            lo, hi = p.prior.bounds
            assert lo <= p.typical <= hi
            assert np.isfinite(p.prior.logpdf(p.typical))


@pytest.mark.parametrize("name", sorted(EXPECTED))
def test_neutral_does_nothing(name):
    e = fx.effect(name)
    base = SimParams()
    assert apply_sim_params([e], neutral_theta([e]), base, _ctx()) == base
    for kind in ("force", "lift"):
        rows = _rows(experiment=kind, deflate=True)
        out = apply_expected_force([e], neutral_theta([e]), _law, rows)
        np.testing.assert_array_equal(out, _law(rows.h_mm, rows.p_pa))


@pytest.mark.parametrize("name", sorted(EXPECTED))
def test_typical_does_something(name):
    e = fx.effect(name)
    theta = typical_theta([e])
    changed = apply_sim_params([e], theta, SimParams(), _ctx()) != SimParams()
    for kind in ("force", "lift"):  # a lift-only effect acts on lift rows alone
        rows = _rows(experiment=kind, deflate=True)
        out = apply_expected_force([e], theta, _law, rows)
        changed |= not np.array_equal(out, _law(rows.h_mm, rows.p_pa))
    assert changed, f"{name} at its typical value changed nothing"


def test_mechanics_go_through_simparams():
    theta = {
        "thickness_deviation.relative": 0.1,
        "ring_softening.factor": 0.5,
        "contact_offset.offset_mm": 2.0,
        "clamp_prestretch.strain": 0.02,
        "thickness_gradient.gradient": -0.2,
        "fabric_inset.inset_mm": 0.75,
        "rubber_i2.share": 0.2,
    }
    p = apply_sim_params(
        [
            "thickness_deviation",
            "ring_softening",
            "contact_offset",
            "clamp_prestretch",
            "thickness_gradient",
            "fabric_inset",
            "rubber_i2",
        ],
        theta,
    )
    assert p.thickness_factor == pytest.approx(1.1)
    assert p.ring_mu_pa == pytest.approx(0.5e6)
    assert p.contact_offset_mm == pytest.approx(2.0)
    assert p.clamp_prestretch == pytest.approx(1.02)
    assert p.thickness_gradient == pytest.approx(-0.2)
    assert p.fabric_inset_mm == pytest.approx(0.75)
    assert p.i2_share == pytest.approx(0.2)
    assert p.mu_pa == SimParams().mu_pa


def test_stress_softening_only_first_trial():
    th = {"stress_softening.stiffening": 0.2}
    first = apply_sim_params(["stress_softening"], th, SimParams(), Context(trial_index=0))
    later = apply_sim_params(["stress_softening"], th, SimParams(), Context(trial_index=3))
    assert first.mu_pa == pytest.approx(1.2 * SimParams().mu_pa)
    assert later == SimParams()


def test_pressure_sensor_and_load_cell():
    """A sample at true pressure p is recorded at 1.02 p + 100 Pa with the force + 0.5 N."""
    p_true = np.linspace(0, 4000, 5)
    theta = {"pressure_sensor.offset_pa": 100.0, "pressure_sensor.gain": 1.02, "load_cell_offset.offset_n": 0.5}
    effects = ["pressure_sensor", "load_cell_offset"]
    rows = _rows(p=1.02 * p_true + 100.0)
    out = apply_expected_force(effects, theta, _law, rows)
    np.testing.assert_allclose(out, _law(30.0, p_true) + 0.5)
    lift = apply_expected_force(
        ["load_cell_offset"], {"load_cell_offset.offset_n": 0.5}, _law, _rows(experiment="lift", p=p_true)
    )
    np.testing.assert_array_equal(lift, _law(30.0, p_true))  # weight of the mass, not a reading


def test_lift_preload_acts_on_lifts_only_and_friction_opposes_motion():
    """The membrane carries W + preload + friction on inflation, W + preload - friction on
    deflation, so the expected recorded weight is F - preload -+ friction; force rows untouched."""
    theta = {"lift_preload.preload_n": 3.0, "lift_preload.friction_n": 1.0}
    up = apply_expected_force(["lift_preload"], theta, _law, _rows(experiment="lift"))
    down = apply_expected_force(["lift_preload"], theta, _law, _rows(experiment="lift", deflate=True))
    force = apply_expected_force(["lift_preload"], theta, _law, _rows())
    base = _law(30.0, np.linspace(0, 4000, 5))
    np.testing.assert_allclose(up, base - 4.0)
    np.testing.assert_allclose(down, base - 2.0)
    np.testing.assert_array_equal(force, base)
    # the virtual rig records a preloaded lift where F(h, p) = W + preload + friction
    rows = _rows(n=1, experiment="lift", p=[3000.0])
    h = np.asarray(recorded_lift_height(["lift_preload"], theta, _law, rows, 20.0, 30.0))
    np.testing.assert_allclose(_law(h, 3000.0), 20.0 + 4.0, atol=1e-8)


def test_rig_compliance_sign_and_self_consistency():
    """Linear F(h) = F0 + s h: the exact fixed point F = F(h_set + F c) is F(h_set) / (1 - s c)."""
    c, slope = 0.05, -2.0
    f_stiff = np.array([10.0, 40.0])
    law = lambda h, p: f_stiff + slope * (h - 20.0)  # noqa: E731
    out = np.asarray(
        apply_expected_force(["rig_compliance"], {"rig_compliance.compliance_mm_per_n": c}, law, _rows(2, h=20.0))
    )
    assert np.all(out < f_stiff)  # the plate yields upwards: less force
    # self-consistency with a linear force law
    np.testing.assert_allclose(out, f_stiff + slope * out * c)
    # a force rising with height is never amplified more than 5x; a lift's frame is not loaded
    rising = lambda h, p: 10.0 + 100.0 * h  # noqa: E731
    theta = {"rig_compliance.compliance_mm_per_n": c}
    np.testing.assert_allclose(apply_expected_force(["rig_compliance"], theta, rising, _rows(2, h=0.0)), 50.0)
    lift = apply_expected_force(["rig_compliance"], theta, law, _rows(2, experiment="lift", h=20.0))
    np.testing.assert_array_equal(lift, f_stiff)


def test_hysteresis_force_and_lift():
    n = 4
    deflate = np.array([False, False, True, True])
    flat = lambda h, p: jnp.full(jnp.shape(h), 20.0)  # noqa: E731
    out = apply_expected_force(["hysteresis"], {"hysteresis.loss": 0.1}, flat, _rows(n, deflate=deflate))
    np.testing.assert_allclose(out, [20, 20, 18, 18])
    # a lift: the plate of F = 80 - 2 h N carries W = 20 N at 30 mm; on deflation it sinks to
    # where 0.9 F = W (exactly: 28.89 mm; the first-order step gave 29 = 30 + 0.1 W / dF_dh)
    law = lambda h, p: 80.0 - 2.0 * h  # noqa: E731
    rows = _rows(n, experiment="lift", deflate=deflate)
    h = np.asarray(recorded_lift_height(["hysteresis"], {"hysteresis.loss": 0.1}, law, rows, 20.0, 30.0))
    np.testing.assert_allclose(h[:2], 30.0)
    np.testing.assert_allclose(0.9 * law(h[2:], 0.0), 20.0)
    np.testing.assert_allclose(h[2:], 30.0 + 0.1 * 20.0 / -2.0, atol=0.12)  # first order: within 0.12 mm


def test_theta_forms_and_typos():
    nested = split_theta(["pressure_sensor"], {"pressure_sensor": {"offset_pa": 50.0}})
    flat = split_theta(["pressure_sensor"], {"pressure_sensor.offset_pa": 50.0})
    assert nested == flat == {"pressure_sensor": {"offset_pa": 50.0, "gain": 1.0}}
    with pytest.raises(KeyError, match="offset_pa"):
        split_theta(["pressure_sensor"], {"pressure_sensor.ofset_pa": 1.0})
    with pytest.raises(KeyError):
        split_theta(["pressure_sensor"], {"hysteresis.loss": 0.1})
    with pytest.raises(KeyError, match="registered"):
        fx.effect("no_such_effect")
    with pytest.raises(ValueError, match="twice"):
        apply_sim_params(["hysteresis", "hysteresis"], {})


def test_priors():
    rng = np.random.default_rng(0)
    for prior in (Uniform(-1.0, 2.0), Normal(0.0, 1.0, -0.5, 3.0), LogNormal(0.5, 1.0, 0.01, 1.0)):
        x = prior.sample(rng, size=2000)
        lo, hi = prior.bounds
        assert np.all((x >= lo) & (x <= hi))
        assert np.all(np.isfinite(prior.logpdf(x)))
        assert prior.logpdf(hi + 1.0) == -np.inf
        assert isinstance(prior.sample(rng), float)
    # normalisation of the truncated normal (crude quadrature)
    g = np.linspace(-0.5, 3.0, 20001)
    assert np.trapezoid(np.exp(Normal(0.0, 1.0, -0.5, 3.0).logpdf(g)), g) == pytest.approx(1.0, rel=1e-4)
    e = fx.effect("pressure_sensor")
    th = e.sample_prior(rng)
    assert set(th) == {"offset_pa", "gain"} and np.isfinite(e.log_prior(th))


def test_user_defined_effect_in_a_few_lines():
    """A user writes a new effect in one short file and the whole machinery takes it."""

    class MouldShrink(MechanicalEffect):
        name = "test_mould_shrink"
        story = "the cured rubber shrinks, so the clamp pre-stretches it"
        parameters = (Parameter("shrink", "1", Uniform(0.0, 0.05), 0.0, 0.01),)

        def sim_params(self, base, theta, context=None):
            return dataclasses.replace(base, clamp_prestretch=base.clamp_prestretch / (1 - theta["shrink"]))

    class HeightOffset(MeasurementEffect):
        name = "test_height_offset"
        story = "the time-of-flight sensors read the lifted plate a fixed distance high"
        parameters = (Parameter("offset_mm", "mm", Normal(0.0, 2.0), 0.0, 1.5),)

        def observed_force_fn(self, theta, force_fn, rows):
            return lambda h, p: force_fn(jnp.where(rows.is_force, h, h - theta["offset_mm"]), p)

    try:
        register_effect(MouldShrink)
        register_effect(HeightOffset)
        assert EFFECTS["test_mould_shrink"] is MouldShrink
        effects = ["test_mould_shrink", "test_height_offset", "pressure_sensor"]
        theta = typical_theta(effects)
        p = apply_sim_params(effects, theta)
        assert p.clamp_prestretch == pytest.approx(1 / 0.99)
        # a plate lifted to 30 mm (F = 100 - h N, W = 70 N, any pressure) is recorded at 31.5 mm
        law = lambda h, p: 100.0 - h  # noqa: E731
        h = recorded_lift_height(effects, theta, law, _rows(experiment="lift"), 70.0, 30.0)
        np.testing.assert_allclose(h, 31.5)
        with pytest.raises(ValueError, match="already registered"):

            @register_effect
            class Clash(MechanicalEffect):
                name = "pressure_sensor"
                story = "a clash"
                parameters = (Parameter("x", "1", Uniform(0, 1), 0.0, 0.5),)

                def sim_params(self, base, theta, context=None):
                    return base

        with pytest.raises(TypeError, match="no likelihood hook"):

            @register_effect
            class NoHook(MeasurementEffect):
                name = "test_no_hook"
                story = "changes readings, says not how"
                parameters = (Parameter("x", "1", Uniform(0, 1), 0.0, 0.5),)

        assert "test_no_hook" not in EFFECTS
    finally:
        EFFECTS.pop("test_mould_shrink", None)
        EFFECTS.pop("test_height_offset", None)


def test_effects_are_frozen_modules():
    e = fx.effect("pressure_sensor")
    assert (
        isinstance(e, eqx.Module)
        and e == fx.effect("pressure_sensor")
        and hash(e) == hash(fx.effect("pressure_sensor"))
    )
    with pytest.raises(dataclasses.FrozenInstanceError):
        e.x = 1.0
    with pytest.raises(TypeError):
        fx.MeasurementEffect()


def test_user_effect_in_the_virtual_rig():
    """The virtual rig takes a user effect as hidden truth (with the analytic stand-in simulator)."""
    from mfdesign.design import Membrane
    from mfdesign.models.standin import standin_plane
    from mfdesign.rig.virtual import Noise, Protocol, VirtualRig

    class LiftHeightOffset(MeasurementEffect):
        name = "lift_height_offset"
        story = "the time-of-flight sensors read the lifted plate a fixed distance high"
        parameters = (Parameter("offset_mm", "mm", Normal(0.0, 2.0), 0.0, 1.5),)

        def observed_force_fn(self, theta, force_fn, rows):
            return lambda h, p: force_fn(jnp.where(rows.is_force, h, h - theta["offset_mm"]), p)

    design = Membrane(2.0, 25.4)
    kw = dict(seed=3, noise=Noise.none(), protocol=Protocol(lift_trials=1), simulator=standin_plane)
    plain = VirtualRig(**kw).mass_lift(design, 1.5).df
    shifted = VirtualRig([LiftHeightOffset()], {"lift_height_offset.offset_mm": 5.0}, **kw).mass_lift(design, 1.5).df
    assert len(plain) == len(shifted)
    np.testing.assert_allclose(shifted["height_mm"], plain["height_mm"] + 5.0)
