"""Simulator emulator: interface, physics invariances, gradients, ranges, persistence."""

from __future__ import annotations

import jax
import jax.numpy as jnp
import numpy as np
import pytest

from mfdesign.models.emulator import (
    PARAM_FIELDS,
    Emulator,
    EmulatorConfig,
    default_ranges,
    evaluate,
    fit_emulator,
    init_emulator,
    load_default,
)
from mfdesign.physics.params import SimParams

DESIGNS = np.array(
    [
        [2.0, 30.0, np.nan, np.nan, np.nan, np.nan],
        [1.5, 27.0, 45.0, 6.0, np.nan, np.nan],
        [2.5, 26.0, 40.0, 5.5, 56.0, 6.0],
    ]
)


def _random_emulator(seed=0):
    cfg = EmulatorConfig(n_members=3, width=16, depth=2, seed=seed)
    mean = np.zeros(14)
    std = np.ones(14)
    return init_emulator(cfg, mean, std, default_ranges())


@pytest.fixture(scope="module")
def emu():
    return _random_emulator()


def _queries(n=6, seed=1):
    rng = np.random.default_rng(seed)
    d = DESIGNS[rng.integers(0, 3, n)]
    return d, rng.uniform(0, 70, n), rng.uniform(500, 9000, n)


def test_shapes_broadcasting_and_positivity(emu):
    d, h, p = _queries()
    f = emu(d, h, p, SimParams())
    assert f.shape == (6,) and np.all(np.isfinite(f)) and np.all(f >= 0)
    # array-valued params equal to the scalars give the same answer
    arr = SimParams(**{k: jnp.full(6, getattr(SimParams(), k)) for k in PARAM_FIELDS})
    np.testing.assert_allclose(emu(d, h, p, arr), f, rtol=1e-12)
    # one design broadcast over points
    f1 = emu(d[0], h, p)
    np.testing.assert_allclose(f1, emu(np.tile(d[0], (6, 1)), h, p), rtol=1e-12)
    assert emu.members_force(d, h, p).shape == (3, 6)
    m, s = emu.mean_std(d, h, p)
    assert m.shape == s.shape == (6,) and np.all(s >= 0)
    # no pressure, no force
    assert np.all(emu(d, h, np.zeros(6)) == 0.0)


def test_rejects_bad_design_shape(emu):
    with pytest.raises(ValueError, match=r"\[N, 6\]"):
        emu(np.ones((3, 5)), np.ones(3), np.ones(3))


def test_exact_similarity_mu_times_thickness(emu):
    """F depends on mu, t and thickness_factor only through mu * t * thickness_factor, and
    on ring_mu only through ring_mu / mu (exact for the simulator's equations)."""
    d, h, p = _queries()
    a = emu(d, h, p, SimParams(mu_pa=30e3, thickness_factor=1.0, ring_mu_pa=6e5))
    b = emu(d, h, p, SimParams(mu_pa=20e3, thickness_factor=1.5, ring_mu_pa=4e5))
    np.testing.assert_allclose(a, b, rtol=1e-10)
    c = emu(d, h, p, SimParams(mu_pa=20e3, thickness_factor=1.0, ring_mu_pa=4e5))
    assert np.max(np.abs(np.asarray(c) - np.asarray(a))) > 1e-6


def test_gradients_match_finite_differences(emu):
    """grad in h, p and every SimParams field (one jitted call) against central differences."""
    d, h, p = _queries(n=1, seed=3)
    x0 = {"h": float(h[0]), "p": float(p[0])}
    x0.update(
        {
            f: float(
                getattr(SimParams(mu_pa=25e3, thickness_gradient=0.1, clamp_prestretch=1.03, contact_offset_mm=1.0), f)
            )
            for f in PARAM_FIELDS
        }
    )

    @jax.jit
    def f(x):
        par = SimParams(**{k: x[k] for k in PARAM_FIELDS})
        return emu(d, x["h"][None], x["p"][None], par)[0]

    xs = {k: jnp.asarray(v) for k, v in x0.items()}
    g = jax.jit(jax.grad(f))(xs)
    for k, v in x0.items():
        if k == "ring_jm":
            continue
        eps = 1e-5 * max(abs(v), 1.0)
        up = dict(xs, **{k: jnp.asarray(v + eps)})
        dn = dict(xs, **{k: jnp.asarray(v - eps)})
        fd = (f(up) - f(dn)) / (2 * eps)
        assert np.isfinite(g[k]), k
        np.testing.assert_allclose(g[k], fd, rtol=1e-5, atol=1e-9, err_msg=k)


def test_vmap_over_params(emu):
    d, h, p = _queries()
    mus = jnp.array([20e3, 30e3, 40e3])
    out = jax.vmap(lambda m: emu(d, h, p, SimParams(mu_pa=m)))(mus)
    assert out.shape == (3, 6)
    np.testing.assert_allclose(out[1], emu(d, h, p, SimParams(mu_pa=30e3)), rtol=1e-12)


def test_in_range_flags(emu):
    d = np.tile(DESIGNS[1], (10, 1))
    h = np.full(10, 20.0)
    p = np.full(10, 5000.0)
    base = SimParams()
    assert np.all(emu.in_range(d, h, p, base))
    h2 = h.copy()
    h2[0] = 90.0
    h2[1] = np.nan
    p2 = p.copy()
    p2[2] = -10.0
    p2[3] = 12_000.0
    mu = np.full(10, 31.7e3)
    mu[4] = 80e3
    jm = np.full(10, 39.6)
    jm[5] = 5.0
    off = np.zeros(10)
    off[6] = 15.0  # effective disk runs into the ring
    d2 = d.copy()
    d2[7, 0] = 4.0  # too thick
    d2[8, 3] = np.nan  # radius without width
    d2[9, 3] = 20.0  # ring far too wide
    flags = np.asarray(emu.in_range(d2, h2, p2, SimParams(mu_pa=mu, jm=jm, contact_offset_mm=off)))
    assert not flags.any(), flags
    assert not np.asarray(emu.in_range(DESIGNS[0], 10.0, 100.0, SimParams(ring_jm=30.0))).item()


def test_a_constant_it_never_saw_is_nan_not_ignored(emu):
    """The emulator was trained without a fabric inset: with one it says NaN (and out of
    range), never the force of the membrane without it."""
    d, h, p = _queries()
    inset = SimParams(fabric_inset_mm=np.where(np.arange(len(h)) % 2 == 0, 0.5, 0.0))
    f = np.asarray(emu(d, h, p, inset))
    assert np.all(np.isnan(f[::2])) and np.all(np.isfinite(f[1::2]))
    assert not np.asarray(emu.in_range(d, h, p, inset))[::2].any()
    assert emu.support()["fabric_inset_mm"] == (0.0, 0.0)
    # the rule is general: every SimParams field has a support, pinned where untrained
    import dataclasses

    assert set(emu.support()) >= {f.name for f in dataclasses.fields(SimParams)}
    assert emu.untrained_fields() == {"fabric_inset_mm": 0.0, "i2_share": 0.0}


def test_save_load_bit_identical(emu, tmp_path):
    d, h, p = _queries()
    emu.save(tmp_path / "e", extra={"note": "test"})
    back = Emulator.load(tmp_path / "e")
    assert np.array_equal(np.asarray(back(d, h, p)), np.asarray(emu(d, h, p)))
    assert back.range_dict == emu.range_dict
    assert back.config == emu.config
    meta = (tmp_path / "e" / "emulator.json").read_text()
    (tmp_path / "e" / "emulator.json").write_text(meta.replace('"format_version": 1', '"format_version": 99'))
    with pytest.raises(ValueError, match="format_version"):
        Emulator.load(tmp_path / "e")
    with pytest.raises(FileNotFoundError):
        Emulator.load(tmp_path / "nothing")


def test_fit_learns_a_smooth_target():
    """Training drives the held-out error of a known smooth y(q, h) well below its spread."""
    rng = np.random.default_rng(0)
    n = 3000
    d = DESIGNS[rng.integers(0, 3, n)]
    h = rng.uniform(0, 60, n)
    p = rng.uniform(100, 9000, n)
    par = {f: np.full(n, getattr(SimParams(), f)) for f in PARAM_FIELDS}
    par["mu_pa"] = rng.uniform(20e3, 40e3, n)
    r0 = d[:, 1]
    q = p / (par["mu_pa"] * d[:, 0])
    y = np.exp(-h / 30.0) * (1.0 + q)  # a dimensionless force ratio
    F = p * 1e-6 * np.pi * r0**2 * y
    arrays = {"design": d, "h": h, "p": p, "F": F, **par}
    cfg = EmulatorConfig(n_members=2, width=32, depth=2, steps=500, batch=256, lr=1e-2)
    train = {k: v[:2500] for k, v in arrays.items()}
    test = {k: v[2500:] for k, v in arrays.items()}
    emu, hist = fit_emulator(train, cfg, progress=False)
    assert np.all(np.isfinite(hist["loss"]))
    acc = evaluate(emu, test)
    assert acc["all"]["rmse_n"] < 0.05 * np.std(test["F"]), acc["all"]


def test_default_artifact_loads_and_is_sane():
    emu = load_default()
    d, h, p = _queries()
    f = np.asarray(emu(d, h, p))
    assert np.all(np.isfinite(f)) and np.all(f >= 0)
    # force rises with pressure at a height where the membrane touches the plate
    f_p = np.asarray(emu(DESIGNS[0], np.full(3, 5.0), np.array([3000.0, 6000.0, 9000.0])))
    assert np.all(np.diff(f_p) > 0)


@pytest.mark.slow
def test_default_artifact_agrees_with_simulator():
    from mfdesign.design import Membrane
    from mfdesign.physics.solve import force_at
    from mfdesign.physics.status import Status

    emu = load_default()
    m = Membrane.from_array(DESIGNS[0])
    h = np.array([5.0, 15.0, 30.0])
    p = np.array([4000.0, 6000.0, 8000.0])
    res = force_at(m, h, p, SimParams())
    ok = res.status == Status.OK
    assert ok.sum() >= 2
    pred = np.asarray(emu(DESIGNS[0], h, p))
    frange = 185.0  # N: the force range of the training data
    assert np.all(np.abs(pred[ok] - res.force_n[ok]) < 0.05 * frange), (pred, res.force_n)
