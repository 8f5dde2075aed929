"""Likelihood side of the effects library: what the virtual rig records is what ``expected_force`` expects."""

from __future__ import annotations

import jax
import jax.numpy as jnp
import numpy as np
import pytest

from mfdesign.physics import effects as fx
from mfdesign.physics.params import SimParams

N = 40


def true_force(h, p):
    """A smooth force plane [N] (falls with h, rises with p), NumPy or JAX."""
    return 0.004 * p * (1.0 + p / 2e4) - 0.3 * h


def _setup(kind: str, deflate: bool):
    rng = np.random.default_rng(3)
    h = rng.uniform(15, 60, N)  # a lifted plate sinking by hysteresis stays above 0
    p = rng.uniform(2000, 9000, N)
    f = true_force(h, p)
    phase = np.where(np.arange(N) % 2 == 0 if deflate else np.zeros(N, bool), "deflate", "inflate")
    return h, p, f, phase


def _rows(h, p, kind, phase):
    n = len(h)
    return fx.Rows(
        jnp.asarray(h),
        jnp.asarray(p),
        jnp.full(n, kind == "force"),
        jnp.asarray(phase == "deflate"),
        jnp.zeros(n, bool),
        jnp.zeros(n, jnp.int32),
    )


@pytest.mark.parametrize("kind", ["force", "lift"])
@pytest.mark.parametrize("name", sorted(n for n, c in fx.EFFECTS.items() if c().acts_on_measurement))
def test_recorded_rows_are_what_the_likelihood_expects(name, kind):
    """Record rows as the virtual rig does (force trials: the hook at the set-points; lifts:
    the height where the hook equals the weight); the expected recorded force at the
    recorded (h, p) must equal the recorded force (force rows) or the weight (lift rows)."""
    e = fx.effect(name)
    theta = e.typical() if name != "pressure_sensor" else {"offset_pa": 150.0, "gain": 1.04}
    h, p, f, phase = _setup(kind, deflate=True)
    weight = np.full(N, 30.0)
    if kind == "lift":
        # a lifted plate in equilibrium: the true force at the true (h, p) is the weight
        p = (np.sqrt(1 + 4 * (weight + 0.3 * h) / (0.004 * 2e4)) - 1) * 2e4 / 2
        assert np.allclose(true_force(h, p), weight)
        h = np.asarray(fx.recorded_lift_height([e], {e.name: theta}, true_force, _rows(h, p, kind, phase), weight, h))
        recorded = weight
    else:
        recorded = np.asarray(e.expected_force(theta, true_force, _rows(h, p, kind, phase)))
    rows = _rows(h, p, kind, phase)
    got = np.asarray(e.expected_force(theta, true_force, rows))
    np.testing.assert_allclose(got, recorded, atol=1e-9 * np.abs(recorded).max())
    # and the effect does something at its typical value
    neutral = np.asarray(e.expected_force(e.neutral(), true_force, rows))
    force_only, lift_only = ("load_cell_offset", "rig_compliance"), ("lift_preload",)
    assert (
        not np.allclose(neutral, got)
        or (kind == "lift" and name in force_only)
        or (kind == "force" and name in lift_only)
    )


@pytest.mark.parametrize("name", sorted(fx.EFFECTS))
def test_every_effect_traceable_with_traced_theta(name):
    """``row_sim_params`` and ``expected_force`` under jit and grad in theta."""
    e = fx.effect(name)
    h, p, f, phase = _setup("force", deflate=True)
    rows = _rows(h, p, "force", phase)
    names = e.parameter_names

    def total(vals):
        theta = dict(zip(names, vals))
        params = e.row_sim_params(SimParams(), theta, rows)
        scale = params.mu_pa / 31.7e3 * params.thickness_factor * params.ring_mu_pa / 1e6
        return jnp.sum(e.expected_force(theta, lambda hh, pp: scale * true_force(hh, pp), rows))

    vals = jnp.asarray([e.typical()[n] for n in names])
    g = jax.jit(jax.grad(total))(vals)
    assert g.shape == vals.shape and bool(jnp.all(jnp.isfinite(g)))


def test_stress_softening_rows_match_trial_context():
    e = fx.effect("stress_softening")
    rows = fx.Rows(
        jnp.zeros(3),
        jnp.zeros(3),
        jnp.ones(3, bool),
        jnp.zeros(3, bool),
        jnp.asarray([True, False, True]),
        jnp.zeros(3, jnp.int32),
    )
    got = np.asarray(e.row_sim_params(SimParams(), {"stiffening": 0.2}, rows).mu_pa)
    first = e.sim_params(SimParams(), {"stiffening": 0.2}, fx.Context(trial_index=0)).mu_pa
    later = e.sim_params(SimParams(), {"stiffening": 0.2}, fx.Context(trial_index=3)).mu_pa
    np.testing.assert_allclose(got, [first, later, first])


def test_measurement_effect_without_likelihood_is_refused():
    """The hook is abstract: an effect without it cannot be made, registered or calibrated."""

    class Bare(fx.MeasurementEffect):
        name, story = "bare_test_effect", "changes readings, no likelihood"
        parameters = (fx.Parameter("a", "N", fx.Normal(0, 1), 0.0, 1.0),)

    with pytest.raises(TypeError, match="observed_force_fn"):
        Bare()
    with pytest.raises(TypeError, match="no likelihood hook"):
        fx.register_effect(Bare)
    assert "bare_test_effect" not in fx.EFFECTS


@pytest.mark.parametrize(
    "prior",
    [
        fx.Uniform(-1.0, 2.0),
        fx.Normal(0.5, 0.3, 0.0, 1.5),
        fx.Normal(1.0, 2.0),
        fx.LogNormal(0.5, 1.0, 0.01, 1.0),
        fx.LogNormal(3.0, 0.4),
    ],
)
def test_logpdf_matches_scipy(prior):
    """The one (JAX) log-density against scipy's truncated distributions."""
    from scipy import stats

    x = np.linspace(-1.5, 4.0, 57)
    lo, hi = prior.bounds
    if isinstance(prior, fx.Uniform):
        ref = stats.uniform(lo, hi - lo).logpdf(x)
    elif isinstance(prior, fx.Normal):
        ref = stats.truncnorm((lo - prior.mean) / prior.sd, (hi - prior.mean) / prior.sd, prior.mean, prior.sd).logpdf(
            x
        )
    else:
        law = stats.lognorm(prior.sigma, scale=prior.median)
        with np.errstate(divide="ignore"):
            ref = np.where((x >= lo) & (x <= hi), law.logpdf(x) - np.log(law.cdf(hi) - law.cdf(lo)), -np.inf)
    got = np.asarray(jax.jit(prior.logpdf)(jnp.asarray(x)))
    np.testing.assert_allclose(got, ref, rtol=1e-10)
    assert isinstance(float(prior.logpdf(prior.center)), float)  # a NumPy caller converts


@pytest.mark.parametrize("bounds", [(-1.0, 2.0), (0.5, np.inf), (-np.inf, 3.0), (-np.inf, np.inf)])
def test_bijection_round_trip_and_jacobian(bounds):
    b = fx.bijection(bounds)
    u = jnp.linspace(-3.0, 3.0, 13)
    x = b.to_physical(u)
    assert np.all((np.asarray(x) > bounds[0]) & (np.asarray(x) < bounds[1]))
    np.testing.assert_allclose(np.asarray(b.to_unconstrained(x)), np.asarray(u), atol=1e-9)
    slope = jax.vmap(jax.grad(b.to_physical))(u)
    np.testing.assert_allclose(np.asarray(b.log_jacobian(u)), np.log(np.abs(np.asarray(slope))), atol=1e-12)
