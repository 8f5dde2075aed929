"""Property tests of the RPN ensemble (mfdesign.models.ensemble)."""

import equinox as eqx
import jax
import jax.numpy as jnp
import numpy as np
import pytest

from mfdesign.models.ensemble import Ensemble, EnsembleConfig, fit_ensemble

NAN = np.nan
SMALL = dict(
    n_members=3, steps=40, batch=16, ring_embed_dim=3, latent_depth=1, latent_width=8, chunk=20, monotone=True
)  # one config throughout: the training step compiles once


def toy_data(n=90, seed=0):
    rng = np.random.default_rng(seed)
    designs = np.array(
        [[2.0, 25.4, NAN, NAN, NAN, NAN], [2.0, 30.0, 40.0, 5.0, NAN, NAN], [1.5, 28.0, 38.0, 5.0, 55.0, 6.0]]
    )
    d = designs[rng.integers(0, 3, n)]
    h = rng.uniform(0, 50, n)
    p = rng.uniform(0, 10_000, n)
    f = 3e-3 * p * d[:, 0] - 0.2 * h + 5 * (~np.isnan(d[:, 2]))
    return d, h, p, f, rng.uniform(0.5, 1.5, n)


@pytest.fixture(scope="module")
def fitted():
    d, h, p, f, w = toy_data()
    return fit_ensemble(EnsembleConfig(**SMALL), d, h, p, f, w, key=1, progress=False)


def test_predict_shape_and_finite(fitted):
    d, h, p, *_ = toy_data(20, seed=3)
    out = fitted.predict(d, h, p)
    assert out.shape == (3, 20)
    assert np.all(np.isfinite(out))
    mu, sd = fitted.mean_std(d, h, p)
    np.testing.assert_allclose(mu, out.mean(0))
    assert np.all(sd >= 0)


def test_swapping_rings_gives_identical_predictions(fitted):
    a = np.array([[1.5, 28.0, 38.0, 5.0, 55.0, 6.0]] * 4)
    b = a[:, [0, 1, 4, 5, 2, 3]]
    h, p = np.linspace(5, 45, 4), np.linspace(1e3, 9e3, 4)
    np.testing.assert_array_equal(fitted.predict(a, h, p), fitted.predict(b, h, p))


def test_absent_rings_no_nan_in_values_or_gradients(fitted):
    design = jnp.array([2.0, 25.4, NAN, NAN, NAN, NAN])

    def f(design, h, p):
        return fitted.predict(design[None], h[None], p[None]).sum()

    val = f(design, jnp.array(20.0), jnp.array(4e3))
    grads = jax.grad(f, argnums=(0, 1, 2))(design, jnp.array(20.0), jnp.array(4e3))
    assert np.isfinite(val)
    for g in grads:
        assert np.all(np.isfinite(g))
    np.testing.assert_array_equal(grads[0][2:], 0.0)  # absent rings carry no gradient
    # gradients with respect to all trainable parameters are finite too
    pgrads = eqx.filter_grad(lambda m: m.predict(design[None], jnp.array([20.0]), jnp.array([4e3])).sum())(fitted)
    leaves = [x for x in jax.tree.leaves(pgrads) if hasattr(x, "dtype")]
    assert leaves and all(np.all(np.isfinite(x)) for x in leaves)


def test_monotone_option_is_monotone_in_pressure(fitted):
    p = np.linspace(0, 12_000, 200)
    for design in toy_data()[0][:3]:
        f = np.asarray(fitted.predict(np.tile(design, (200, 1)), np.full(200, 30.0), p))
        assert np.all(np.diff(f, axis=1) >= -1e-9)


def test_prior_members_unchanged_by_training():
    d, h, p, f, w = toy_data()
    cfg0 = EnsembleConfig(**{**SMALL, "steps": 0})
    cfg1 = EnsembleConfig(**SMALL)
    m0 = fit_ensemble(cfg0, d, h, p, f, w, key=4, progress=False)
    m1 = fit_ensemble(cfg1, d, h, p, f, w, key=4, progress=False)
    for a, b in zip(jax.tree.leaves(m0.prior), jax.tree.leaves(m1.prior)):
        np.testing.assert_array_equal(a, b)
    moved = [not np.array_equal(a, b) for a, b in zip(jax.tree.leaves(m0.trainable), jax.tree.leaves(m1.trainable))]
    assert any(moved)


def test_save_load_predicts_identical_bits(fitted, tmp_path):
    fitted.save(tmp_path / "m")
    loaded = Ensemble.load(tmp_path / "m")
    d, h, p, *_ = toy_data(30, seed=5)
    np.testing.assert_array_equal(fitted.predict(d, h, p), loaded.predict(d, h, p))
    assert loaded.config == fitted.config


def test_load_rejects_wrong_format(fitted, tmp_path):
    fitted.save(tmp_path / "m")
    meta = tmp_path / "m" / "ensemble.json"
    meta.write_text(meta.read_text().replace('"format_version": 1', '"format_version": 99'))
    with pytest.raises(ValueError, match="format_version"):
        Ensemble.load(tmp_path / "m")


def test_seeded_fit_is_reproducible():
    d, h, p, f, w = toy_data()
    cfg = EnsembleConfig(**SMALL)
    a = fit_ensemble(cfg, d, h, p, f, w, key=7, progress=False)
    b = fit_ensemble(cfg, d, h, p, f, w, key=7, progress=False)
    np.testing.assert_array_equal(a.predict(d, h, p), b.predict(d, h, p))


@pytest.mark.parametrize(
    "kwargs, match",
    [
        (dict(design=np.ones((3, 5))), r"\[n, 6\]"),
        (dict(h=np.ones(2)), "h_mm must have 3"),
        (dict(design=np.array([[2.0, 25.4, 40.0, NAN, NAN, NAN]] * 3)), "both radius and half-width"),
        (dict(w=-np.ones(3)), "weight must be >= 0"),
        (dict(p=-np.ones(3)), "monotone head needs"),
    ],
)
def test_invalid_inputs_raise_clear_errors(kwargs, match):
    args = dict(
        design=np.array([[2.0, 25.4, NAN, NAN, NAN, NAN]] * 3), h=np.ones(3), p=np.ones(3), f=np.ones(3), w=np.ones(3)
    )
    args.update(kwargs)
    with pytest.raises(ValueError, match=match):
        fit_ensemble(
            EnsembleConfig(**SMALL), args["design"], args["h"], args["p"], args["f"], args["w"], progress=False
        )


def test_config_validation():
    with pytest.raises(ValueError, match="intercept must be true or false"):
        EnsembleConfig.from_dict({"intercept": "no"})
    assert EnsembleConfig.from_dict(EnsembleConfig(intercept=False).to_dict()).intercept is False
    with pytest.raises(ValueError, match="degree"):
        EnsembleConfig(degree=4)
    with pytest.raises(ValueError, match="n_members"):
        EnsembleConfig(n_members=0)


def test_predict_in_row_passes_equals_one_pass(fitted):
    """Many rows go through the members ROW_CHUNK at a time (issue 40: the discrepancy's 48
    members on 150k rows at once peaked at 7.5 GB); every row keeps its value, the padding
    of the last pass is cut, and gradients still flow."""
    import mfdesign.models.ensemble as ens

    d, h, p, *_ = toy_data(ens.ROW_CHUNK + 37, seed=5)
    chunked = np.asarray(fitted.predict(d, h, p))
    points = eqx.filter_vmap(fitted._member, in_axes=(None, None, 0, 0, 0))
    members = eqx.filter_vmap(points, in_axes=(eqx.if_array(0), eqx.if_array(0), None, None, None))
    whole = np.asarray(members(fitted.trainable, fitted.prior, jnp.asarray(d), jnp.asarray(h), jnp.asarray(p)))
    assert chunked.shape == whole.shape == (3, len(h))
    np.testing.assert_allclose(chunked, whole, rtol=1e-6, atol=1e-6)
    grad = jax.grad(lambda pp: fitted.predict(d, h, pp).sum())(jnp.asarray(p))
    assert grad.shape == p.shape and np.all(np.isfinite(grad))


def test_subset_is_the_members_it_names(fitted):
    """A training run of several ensembles' members splits into ensembles of their own
    (the discrepancy trains its full and leave-one-out members at once, issue 40)."""
    d, h, p, *_ = toy_data(20, seed=3)
    part = fitted.subset(1, 3)
    assert part.n_members == 2 and part.config.n_members == 2
    np.testing.assert_array_equal(np.asarray(part.predict(d, h, p)), np.asarray(fitted.predict(d, h, p))[1:3])
    with pytest.raises(ValueError, match="allowed"):
        fitted.subset(2, 5)
