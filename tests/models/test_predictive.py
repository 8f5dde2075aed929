"""The predictive distribution: posterior draws through the force model (+ discrepancy).

Uses the analytic stand-in force model (no emulator, no simulator) on a slice of the
bundled dataset, and hand-made posterior draws around the model's starting point.
"""

import numpy as np
import pytest

from mfdesign.calibration.mcmc import build_model
from mfdesign.calibration.posterior import Posterior
from mfdesign.models.standin import standin_force
from mfdesign.data.store import read_parquet
from mfdesign.workflows.demo import BUNDLED
from mfdesign.models.hierarchical import CalibrationData
from mfdesign.models.predictive import MultiFidelity, coverage


@pytest.fixture(scope="module")
def setup():
    meas = read_parquet(BUNDLED)
    meas = meas.subset(meas.design_keys[:3])
    data = CalibrationData.from_measurements(meas, max_rows=120, seed=0)
    model = build_model(standin_force, data)
    rng = np.random.default_rng(0)
    x0 = model.initial_physical()
    draws = x0 + 0.01 * np.abs(x0) * rng.standard_normal((12, x0.size))
    post = Posterior(
        model.names,
        tuple(s.unit for s in model.specs),
        draws,
        np.zeros(12),
        x0,
        0.0,
        float(len(data)),
        0.0,
        0.0,
        {},
        tuple(data.design_keys),
        (),
    )
    return meas, data, model, post


def test_sample_force_is_each_draws_expected_force(setup):
    _, data, model, post = setup
    t = model.thickness_for(post.samples, data)
    f = np.asarray(model.sample_force(post.samples, data))
    assert f.shape == (12, len(data))
    for s in (0, 5, 11):  # batched evaluation (lax.map) = one draw at a time
        np.testing.assert_allclose(f[s], np.asarray(model.expected_force(post.samples[s], data, t[s])), rtol=1e-12)


def test_interval_brackets_the_mean_and_widens_with_level(setup):
    meas, data, model, post = setup
    mf = MultiFidelity.from_posterior(model, post, delta=None, noise_n=0.5)
    m, lo50, hi50 = mf.interval(data, 0.5)
    _, lo90, hi90 = mf.interval(data, 0.9)
    assert np.all(lo90 <= lo50 + 1e-12) and np.all(hi50 <= hi90 + 1e-12)
    assert np.all((lo90 <= m) & (m <= hi90))
    cov = coverage(mf, meas, 0.9)
    assert 0.0 <= cov["coverage"] <= 1.0 and set(cov["per_membrane"]) == set(meas.design_keys)


def test_new_designs_draw_thickness_from_the_population(setup):
    _, data, model, post = setup
    mf = MultiFidelity.from_posterior(model, post, delta=None, noise_n=0.5)
    design = np.array([[1.7, 31.0, np.nan, np.nan, np.nan, np.nan]] * 4)
    f = np.asarray(mf.predict(design, np.full(4, 20.0), np.linspace(2000, 8000, 4)))
    assert f.shape == (12, 4) and np.all(np.isfinite(f))
    assert np.all(f.std(0) > 0)  # draws differ (theta and the new membrane's thickness)


def test_members_gives_a_calibrated_membrane_its_own_thickness(setup):
    """The traceable ``members`` (acquisition, design search, trajectories) must treat a
    calibrated membrane as ``predict`` does: with its own latent thickness, not a new draw."""
    import jax.numpy as jnp

    from mfdesign.design import Membrane

    _, data, model, post = setup
    mf = MultiFidelity.from_posterior(model, post, delta=None, noise_n=0.5)
    known = np.array([Membrane.from_key(k).to_array() for k in mf.design_keys])
    design = np.concatenate([known, [[1.7, 31.0, np.nan, np.nan, np.nan, np.nan]]])
    h, p = np.full(len(design), 20.0), np.full(len(design), 5000.0)
    got = np.asarray(mf.members(jnp.asarray(design), jnp.asarray(h), jnp.asarray(p)))
    want = np.asarray(mf.predict(design, h, p))
    np.testing.assert_allclose(got[:, :-1], want[:, :-1], rtol=1e-9)
    assert np.all(np.isfinite(got[:, -1])) and np.all(got.std(0)[-1:] > 0)


def test_coverage_leaves_out_rows_without_a_value_and_counts_them(setup, monkeypatch):
    """A row the model has no number for (outside the physical model: NaN) must not turn the
    RMSE into NaN nor count as outside the interval (a round's train RMSE read NaN)."""
    meas, data, model, post = setup
    mf = MultiFidelity.from_posterior(model, post, delta=None, noise_n=0.5)
    whole = coverage(mf, meas, 0.9)
    real = MultiFidelity.interval

    def with_holes(self, data, level=0.9, n_noise=8, key=0):
        m, lo, hi = real(self, data, level, n_noise, key)
        m = np.array(m, float)
        m[::10] = np.nan
        return m, lo, hi

    monkeypatch.setattr(MultiFidelity, "interval", with_holes)
    holed = coverage(mf, meas, 0.9)
    assert np.isfinite(holed["rmse_n"]) and holed["rows_without_value"] > 1000  # every 10th of ~20k rows
    assert holed["rmse_n"] == pytest.approx(whole["rmse_n"], rel=0.2) and whole["rows_without_value"] == 0


def test_the_predictor_takes_the_fidelity_by_name_or_as_data(setup):
    """``rig`` = physics + discrepancy, ``sim`` = physics alone, whether the fidelity comes
    as a name or as a traced index (one compiled program for both, issue 40); and the
    ``sim`` members carry no gradient through the discrepancy (finite on a training
    membrane, where the gate's sqrt(1 - g^2) has an infinite slope)."""
    import jax
    import jax.numpy as jnp

    from mfdesign.design import Membrane
    from mfdesign.models.discrepancy import Discrepancy
    from mfdesign.models.predictive import MultiFidelityPredictor
    from tiny_models import tiny_ensemble

    _, data, model, post = setup
    anchors = jnp.asarray(np.array([Membrane.from_key(k).to_array() for k in data.design_keys]))
    delta = Discrepancy(tiny_ensemble(4), anchors, 0.3, 1.5)
    mf = MultiFidelity.from_posterior(model, post, delta=delta, noise_n=0.5)
    pred = mf.predictor(8)
    assert isinstance(pred, MultiFidelityPredictor) and pred.fidelities == ("rig", "sim")
    design = jnp.concatenate([anchors[:1], jnp.asarray([[1.7, 31.0, np.nan, np.nan, np.nan, np.nan]])])
    h, p = jnp.array([20.0, 30.0]), jnp.array([5000.0, 6000.0])
    thin = mf.thinned(8)
    physics = MultiFidelity(thin.model, thin.theta, None, thin.noise_n, thin.design_keys)
    want = {"rig": np.asarray(thin.members(design, h, p)), "sim": np.asarray(physics.members(design, h, p))}
    assert not np.allclose(want["rig"], want["sim"])
    by_index = jax.jit(lambda i, d: pred.members(i, d, h, p))
    for i, f in enumerate(pred.fidelities):
        # eagerly the rows are padded to 256 (one compiled shape for every table): the
        # same numbers but for the last bit (the vectorised loops differ)
        np.testing.assert_allclose(np.asarray(pred.members(f, design, h, p)), want[f], rtol=1e-13, atol=1e-12)
        np.testing.assert_allclose(np.asarray(by_index(jnp.asarray(i), design)), want[f], rtol=1e-13, atol=1e-12)
    g = jax.grad(lambda d: by_index(jnp.asarray(1), d).sum())(design)
    assert np.all(np.isfinite(np.asarray(g)[:, :2]))
    with pytest.raises(ValueError, match="not offered"):
        pred.members("lab", design, h, p)
