"""The gated discrepancy: shrinks to zero and widens away from its membranes; the gate's
length comes from leave-one-membrane-out and picks transfer only when it helps."""

import json
import math

import jax
import jax.numpy as jnp
import numpy as np
import pytest

from mfdesign.design import membrane_features
from mfdesign.models.discrepancy import Discrepancy, fit_gated
from mfdesign.models.ensemble import EnsembleConfig

CFG = EnsembleConfig(n_members=2, steps=600, batch=64, latent_width=16, latent_depth=2, monotone=False, chunk=300)
NAN = np.nan
DESIGNS = np.array(
    [
        [2.0, 25.4, NAN, NAN, NAN, NAN],
        [1.5, 30.0, NAN, NAN, NAN, NAN],
        [2.0, 25.4, 49.0, 5.0, NAN, NAN],
        [2.33, 29.63, 37.63, 5.0, 62.0, 5.0],
        [1.2, 36.0, 50.0, 6.0, NAN, NAN],
    ]
)


def _rows(designs, n=60, seed=0):
    rng = np.random.default_rng(seed)
    d = np.repeat(designs, n, axis=0)
    h = rng.uniform(0, 60, len(d))
    p = rng.uniform(0, 8000, len(d))
    return d, h, p, np.repeat(np.arange(len(designs)), n)


def test_membrane_features_measure_a_ring_as_one_unit():
    f = np.asarray(membrane_features(DESIGNS[:3]))
    assert f.shape == (3, 8) and np.all(np.isfinite(f))
    assert np.linalg.norm(f[2] - f[0]) == pytest.approx(math.sqrt(1 + (49 / 44.6) ** 2 + (5 / 8) ** 2))
    assert np.linalg.norm(f[1] - f[0]) == pytest.approx(math.hypot(0.5 / 2.0, 4.6 / 12.7))


def test_the_gate_is_one_on_its_membranes_and_the_draws_widen_to_sigma_far_away():
    d, h, p, m = _rows(DESIGNS[:2], n=40)
    from mfdesign.models.ensemble import fit_ensemble

    ens = fit_ensemble(CFG, d, h, p, 3.0 + 0.0 * h, key=0, progress=False)
    delta = Discrepancy(ens, jnp.asarray(DESIGNS[:2]), 0.2, 2.0)
    far = DESIGNS[3:4]
    g = np.asarray(delta.gate(np.concatenate([DESIGNS[:2], far])))
    np.testing.assert_allclose(g[:2], 1.0)
    assert g[2] < 1e-6
    x = np.repeat(np.concatenate([DESIGNS[:1], far]), 1, axis=0)
    draws = np.asarray(delta.draws(x, np.array([20.0, 20.0]), np.array([4000.0, 4000.0]), 512, jax.random.PRNGKey(3)))
    members = np.asarray(ens.predict(x[:1], np.array([20.0]), np.array([4000.0])))[:, 0]
    assert set(np.round(draws[:, 0], 9)) == set(np.round(members, 9))  # on its membrane: the members
    assert abs(draws[:, 1].mean()) < 1e-9 and draws[:, 1].std() == pytest.approx(
        2.0, rel=0.15
    )  # far: N(0, sigma), antithetic
    assert np.allclose(np.asarray(Discrepancy(ens, jnp.asarray(DESIGNS[:2]), math.inf, 0.0).gate(far)), 1.0)


def test_fit_gated_keeps_a_shared_discrepancy_and_gates_a_per_membrane_one():
    d, h, p, m = _rows(DESIGNS)
    w = np.ones(len(h))
    rng = np.random.default_rng(1)
    shared = 4.0 * np.sin(h / 20.0)  # the same discrepancy on every membrane: it transfers
    fit = fit_gated(CFG, d, h, p, shared + 0.1 * rng.standard_normal(len(h)), w, m, key=0)
    table = {r["length"]: r["heldout_rmse_n"] for r in fit.selection()}
    assert fit.length >= 0.75, fit.selection()
    assert table[fit.length if math.isfinite(fit.length) else None] < 0.5 * table[0.0]
    offsets = np.array([3.0, -4.0, 5.0, -3.0, 4.0])  # one offset per membrane: no transfer
    own = offsets[m] + 0.1 * rng.standard_normal(len(h))
    fit = fit_gated(CFG, d, h, p, own, w, m, key=0)
    assert fit.length <= 0.2, fit.selection()
    assert 2.0 < fit.sigma_n < 6.0  # the spread of the membranes' offsets (RMS 3.9 N)
    assert np.asarray(fit.mean(d[:1], h[:1], p[:1]))[0] == pytest.approx(3.0, abs=0.6)  # its own membrane kept


def test_save_load_round_trip_and_an_old_folder_loads_ungated(tmp_path):
    d, h, p, m = _rows(DESIGNS[:3], n=20)
    fit = fit_gated(CFG, d, h, p, np.sin(h / 10), np.ones(len(h)), m, key=0)
    fit.save(tmp_path / "delta")
    back = Discrepancy.load(tmp_path / "delta")
    assert back.length == fit.length and back.sigma_n == pytest.approx(fit.sigma_n)
    assert fit.p_ref_pa > 0 and back.p_ref_pa == pytest.approx(fit.p_ref_pa)
    key = jax.random.PRNGKey(0)
    np.testing.assert_allclose(
        np.asarray(back.draws(d[:5], h[:5], p[:5], 4, key)), np.asarray(fit.draws(d[:5], h[:5], p[:5], 4, key))
    )
    (tmp_path / "delta" / "gate.json").unlink()
    old = Discrepancy.load(tmp_path / "delta")
    assert math.isinf(old.length) and old.sigma_n == 0.0
    (tmp_path / "delta" / "gate.json").write_text(json.dumps({"anchors_mm": [], "length": -1, "sigma_n": 1}))
    from mfdesign.errors import InputError

    with pytest.raises(InputError, match="allowed"):
        Discrepancy.load(tmp_path / "delta")


def test_no_pressure_no_discrepancy_near_or_far():
    """At p = 0 neither the rubber nor the simulator pushes: the gated discrepancy's mean and
    every draw are exactly 0 there (no constant term, the prior term grows as p / p_ref),
    while at a typical pressure far away the spread is sigma."""
    d, h, p, m = _rows(DESIGNS[:3], n=30)
    fit = fit_gated(CFG, d, h, p, 2.0 + np.sin(h / 10), np.ones(len(h)), m, key=0)
    assert fit.p_ref_pa == pytest.approx(float(np.sqrt(np.mean(p**2))))
    x = np.concatenate([DESIGNS[:1], DESIGNS[4:5]])  # a training membrane and a far one
    zero = np.zeros(2)
    assert np.all(np.asarray(fit.mean(x, np.array([10.0, 40.0]), zero)) == 0.0)
    assert np.all(np.asarray(fit.draws(x, np.array([10.0, 40.0]), zero, 8, jax.random.PRNGKey(0))) == 0.0)
    far = Discrepancy(fit.ensemble, fit.anchors, 0.05, 2.0, (), 4000.0)
    at_ref = np.asarray(far.draws(DESIGNS[4:5], np.array([20.0]), np.array([4000.0]), 512, jax.random.PRNGKey(1)))
    at_half = np.asarray(far.draws(DESIGNS[4:5], np.array([20.0]), np.array([2000.0]), 512, jax.random.PRNGKey(1)))
    assert at_ref.std() == pytest.approx(2.0, rel=0.15)
    np.testing.assert_allclose(at_half, 0.5 * at_ref, atol=1e-9)
