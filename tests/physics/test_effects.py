"""The effects library: registry, priors, hooks, composition, and a user-written effect."""

from __future__ import annotations

import dataclasses
from dataclasses import dataclass

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
    Sample,
    Uniform,
    LogNormal,
    apply_observe,
    apply_sim_params,
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
    "contact_offset",
    "stress_softening",
    "pressure_sensor",
    "load_cell_offset",
    "rig_compliance",
    "hysteresis",
}


def _sample(n=5):
    return Sample(height_mm=np.full(n, 30.0), pressure_pa=np.linspace(0, 4000, n), force_n=np.linspace(0, 40, n))


def _ctx(n=5, **kw):
    base = dict(
        experiment="force",
        trial_index=np.zeros(n, int),
        phase=np.array(["inflate"] * n),
        time_s=np.arange(n) * 0.1,
        dF_dh=np.full(n, -1.5),
    )
    base.update(kw)
    return Context(**base)


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
    ctx = _ctx()
    assert apply_sim_params([e], neutral_theta([e]), base, ctx) == base
    s = _sample()
    out = apply_observe([e], neutral_theta([e]), s, ctx)
    for f in ("height_mm", "pressure_pa", "force_n"):
        np.testing.assert_array_equal(getattr(out, f), getattr(s, f))


@pytest.mark.parametrize("name", sorted(EXPECTED))
def test_typical_does_something(name):
    e = fx.effect(name)
    theta = typical_theta([e])
    n = 5
    ctx = _ctx(n, phase=np.array(["deflate"] * n))
    changed = apply_sim_params([e], theta, SimParams(), ctx) != SimParams()
    s = _sample(n)
    out = apply_observe([e], theta, s, ctx)
    changed |= any(not np.array_equal(getattr(out, f), getattr(s, f)) for f in ("height_mm", "pressure_pa", "force_n"))
    assert changed, f"{name} at its typical value changed nothing"


def test_mechanics_go_through_simparams():
    theta = {
        "thickness_deviation.relative": 0.1,
        "ring_softening.factor": 0.5,
        "contact_offset.offset_mm": 2.0,
        "clamp_prestretch.strain": 0.02,
        "thickness_gradient.gradient": -0.2,
    }
    p = apply_sim_params(
        ["thickness_deviation", "ring_softening", "contact_offset", "clamp_prestretch", "thickness_gradient"], theta
    )
    assert p.thickness_factor == pytest.approx(1.1)
    assert p.ring_mu_pa == pytest.approx(0.5e6)
    assert p.contact_offset_mm == pytest.approx(2.0)
    assert p.clamp_prestretch == pytest.approx(1.02)
    assert p.thickness_gradient == pytest.approx(-0.2)
    assert p.mu_pa == SimParams().mu_pa


def test_stress_softening_only_first_trial():
    th = {"stress_softening.stiffening": 0.2}
    first = apply_sim_params(["stress_softening"], th, SimParams(), Context(trial_index=0))
    later = apply_sim_params(["stress_softening"], th, SimParams(), Context(trial_index=3))
    assert first.mu_pa == pytest.approx(1.2 * SimParams().mu_pa)
    assert later == SimParams()


def test_pressure_sensor_and_load_cell():
    s = _sample()
    out = apply_observe(
        ["pressure_sensor", "load_cell_offset"],
        {"pressure_sensor.offset_pa": 100.0, "pressure_sensor.gain": 1.02, "load_cell_offset.offset_n": 0.5},
        s,
        _ctx(),
    )
    np.testing.assert_allclose(out.pressure_pa, 1.02 * s.pressure_pa + 100.0)
    np.testing.assert_allclose(out.force_n, s.force_n + 0.5)
    lift = apply_observe(["load_cell_offset"], {"load_cell_offset.offset_n": 0.5}, s, _ctx(experiment="lift"))
    np.testing.assert_array_equal(lift.force_n, s.force_n)  # weight of the mass, not a reading


def test_rig_compliance_sign_and_self_consistency():
    """Linear F(h) = F0 + s h: the exact fixed point F = F(h_set + F c) is F(h_set) / (1 - s c)."""
    c, slope = 0.05, -2.0
    f_stiff = np.array([10.0, 40.0])
    out = apply_observe(
        ["rig_compliance"],
        {"rig_compliance.compliance_mm_per_n": c},
        Sample(np.full(2, 20.0), np.full(2, 3000.0), f_stiff),
        _ctx(2, dF_dh=np.full(2, slope)),
    )
    assert np.all(out.force_n < f_stiff)  # the plate yields upwards: less force
    # self-consistency with a linear force law
    np.testing.assert_allclose(out.force_n, f_stiff + slope * out.force_n * c)
    with pytest.raises(ValueError, match="dF_dh"):
        apply_observe(["rig_compliance"], {"rig_compliance.compliance_mm_per_n": c}, _sample(), _ctx(dF_dh=None))


def test_hysteresis_force_and_lift():
    n = 4
    phase = np.array(["inflate", "inflate", "deflate", "deflate"])
    s = Sample(np.full(n, 30.0), np.full(n, 3000.0), np.full(n, 20.0))
    out = apply_observe(["hysteresis"], {"hysteresis.loss": 0.1}, s, _ctx(n, phase=phase))
    np.testing.assert_allclose(out.force_n, [20, 20, 18, 18])
    lift = apply_observe(
        ["hysteresis"], {"hysteresis.loss": 0.1}, s, _ctx(n, phase=phase, experiment="lift", dF_dh=np.full(n, -2.0))
    )
    np.testing.assert_allclose(lift.height_mm, [30, 30, 29, 29])  # 0.1 * 20 N / -2 N/mm = -1 mm
    np.testing.assert_array_equal(lift.force_n, s.force_n)


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

    @dataclass(frozen=True)
    class MouldShrink(MechanicalEffect):
        name = "test_mould_shrink"
        story = "the cured rubber shrinks, so the clamp pre-stretches it"
        parameters = (Parameter("shrink", "1", Uniform(0.0, 0.05), 0.0, 0.01),)

        def sim_params(self, base, theta, context=None):
            return dataclasses.replace(base, clamp_prestretch=base.clamp_prestretch / (1 - theta["shrink"]))

    @dataclass(frozen=True)
    class HeightOffset(MeasurementEffect):
        name = "test_height_offset"
        story = "the time-of-flight sensors read the lifted plate a fixed distance high"
        parameters = (Parameter("offset_mm", "mm", Normal(0.0, 2.0), 0.0, 1.5),)

        def observe(self, theta, sample, context):
            if context.experiment != "lift":
                return sample
            return sample.replace(height_mm=sample.height_mm + theta["offset_mm"])

    try:
        register_effect(MouldShrink)
        register_effect(HeightOffset)
        assert EFFECTS["test_mould_shrink"] is MouldShrink
        effects = ["test_mould_shrink", "test_height_offset", "pressure_sensor"]
        theta = typical_theta(effects)
        p = apply_sim_params(effects, theta)
        assert p.clamp_prestretch == pytest.approx(1 / 0.99)
        s = apply_observe(effects, theta, _sample(), _ctx(experiment="lift"))
        np.testing.assert_allclose(s.height_mm, 31.5)
        with pytest.raises(ValueError, match="already registered"):

            @register_effect
            @dataclass(frozen=True)
            class Clash(MechanicalEffect):
                name = "pressure_sensor"
                story = "a clash"
                parameters = (Parameter("x", "1", Uniform(0, 1), 0.0, 0.5),)
    finally:
        EFFECTS.pop("test_mould_shrink", None)
        EFFECTS.pop("test_height_offset", None)


def test_user_effect_in_the_virtual_rig():
    """The virtual rig takes a user effect as hidden truth (with the analytic stand-in simulator)."""
    from mfdesign.design import Membrane
    from mfdesign.models.standin import standin_plane
    from mfdesign.rig.virtual import Noise, Protocol, VirtualRig

    @dataclass(frozen=True)
    class LiftHeightOffset(MeasurementEffect):
        name = "lift_height_offset"
        story = "the time-of-flight sensors read the lifted plate a fixed distance high"
        parameters = (Parameter("offset_mm", "mm", Normal(0.0, 2.0), 0.0, 1.5),)

        def observe(self, theta, sample, context):
            if context.experiment != "lift":
                return sample
            return sample.replace(height_mm=sample.height_mm + theta["offset_mm"])

    design = Membrane(2.0, 25.4)
    kw = dict(seed=3, noise=Noise.none(), protocol=Protocol(lift_trials=1), simulator=standin_plane)
    plain = VirtualRig(**kw).mass_lift(design, 1.5).df
    shifted = VirtualRig([LiftHeightOffset()], {"lift_height_offset.offset_mm": 5.0}, **kw).mass_lift(design, 1.5).df
    assert len(plain) == len(shifted)
    np.testing.assert_allclose(shifted["height_mm"], plain["height_mm"] + 5.0)
