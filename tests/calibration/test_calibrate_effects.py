"""Likelihood side of the effects library: forward ``observe`` vs JAX ``expected_force``."""

from __future__ import annotations

import jax
import jax.numpy as jnp
import numpy as np
import pytest

import mfdesign  # noqa: F401  (float64)
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
    ctx = fx.Context(experiment=kind, trial_index=np.zeros(N, int), phase=phase, dF_dh=np.full(N, -0.3))
    return h, p, f, phase, ctx


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
def test_expected_force_inverts_observe(name, kind):
    """Record true samples through ``observe``; the expected recorded force at the recorded
    (h, p) must equal the recorded force (force rows) or the weight (lift rows)."""
    e = fx.effect(name)
    theta = e.typical() if name != "pressure_sensor" else {"offset_pa": 150.0, "gain": 1.04}
    h, p, f, phase, ctx = _setup(kind, deflate=True)
    weight = np.full(N, 30.0)
    if kind == "lift":
        # a lifted plate in equilibrium: the true force at the true (h, p) is the weight
        p = (np.sqrt(1 + 4 * (weight + 0.3 * h) / (0.004 * 2e4)) - 1) * 2e4 / 2
        f = weight
        assert np.allclose(true_force(h, p), weight)
    obs = e.observe(theta, fx.Sample(h, p, f), ctx)
    rows = _rows(obs.height_mm, obs.pressure_pa, kind, phase)
    got = np.asarray(e.expected_force(theta, true_force, rows))
    # exact for offsets/gains; first order in the effect for compliance and lift hysteresis
    tol = (
        0.02 * np.abs(obs.force_n).max()
        if name in ("rig_compliance", "hysteresis")
        else 1e-9 * np.abs(obs.force_n).max()
    )
    np.testing.assert_allclose(got, obs.force_n, atol=tol)
    # and the effect does something at its typical value
    neutral = np.asarray(e.expected_force(e.neutral(), true_force, rows))
    changed = not np.allclose(neutral, got) or not np.allclose(obs.force_n, f) or not np.allclose(obs.pressure_pa, p)
    assert changed or (kind == "lift" and name in ("load_cell_offset", "rig_compliance"))


@pytest.mark.parametrize("name", sorted(fx.EFFECTS))
def test_every_effect_traceable_with_traced_theta(name):
    """``row_sim_params`` and ``expected_force`` under jit and grad in theta."""
    e = fx.effect(name)
    h, p, f, phase, _ = _setup("force", deflate=True)
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
    class Bare(fx.MeasurementEffect):
        name, story = "bare_test_effect", "changes readings, no likelihood"
        parameters = (fx.Parameter("a", "N", fx.Normal(0, 1), 0.0, 1.0),)

        def observe(self, theta, sample, context):
            return sample.replace(force_n=sample.force_n + theta["a"])

    assert not Bare().has_likelihood
    rows = _rows(np.ones(2), np.ones(2), "force", np.array(["inflate"] * 2))
    with pytest.raises(NotImplementedError, match="bare_test_effect"):
        fx.apply_expected_force([Bare()], {"bare_test_effect.a": 1.0}, true_force, rows)


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
def test_jax_logpdf_matches_numpy(prior):
    x = np.linspace(-1.5, 4.0, 57)
    np.testing.assert_allclose(np.asarray(prior.logpdf_jax(jnp.asarray(x))), prior.logpdf(x), rtol=1e-10)
