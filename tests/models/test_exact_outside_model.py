"""Points outside the physical model (issue 44, class 3): a plane node whose force is above
p pi R^2 (``Status.OUTSIDE_MODEL``) is never a number of the exact model (strict), never
enters a likelihood, and diagnosis' residuals drop and count it. Tiny synthetic planes (no
plane is solved): ``G(h, P) = P pi R^2 (1.05 - h / 25 mm)``, above the bound only at h = 0."""

from __future__ import annotations

import dataclasses

import jax.numpy as jnp
import numpy as np
import pandas as pd
import pytest

import mfdesign.models.exact as ex
from mfdesign.design import Membrane
from mfdesign.models.hierarchical import CalibrationData, HierarchicalModel
from mfdesign.physics import planes as pl
from mfdesign.physics.effects import Rows, Uniform
from mfdesign.physics.params import SimParams
from mfdesign.physics.status import force_bound_n

KEYS = ("[2.0, 25.4, nan, nan, nan, nan]",)
GRID = pl.PlaneGrid.covering(40.0, 5000.0)


def synthetic(h, p, r_mm=70.0):
    return force_bound_n(p, r_mm) * (1.05 - np.asarray(h) / 25.0)


@pytest.fixture(scope="module")
def model():
    """An exact model on the synthetic planes, lattice axis ``jm`` (two nodes)."""
    mp = pytest.MonkeyPatch()
    mp.setattr(
        pl,
        "solve_planes",
        lambda jobs, grid, **kw: [synthetic(*np.meshgrid(grid.h, grid.p, indexing="ij"))] * len(jobs),
    )
    try:
        yield ex._assemble(KEYS, SimParams(), {"jm": (0, 1)}, {}, GRID, "nan", False, False)
    finally:
        mp.undo()


def rows(h):
    h = np.asarray(h, float)
    design = np.repeat(Membrane.from_key(KEYS[0]).to_array()[None], h.size, axis=0)
    return jnp.asarray(design), jnp.asarray(h), jnp.full(h.size, 4000.0)


H = [0.0, 1.0, 3.0, 6.0, 10.0, 20.0]
NEAR = np.array([True, True, True, False, False, False])  # a stencil node at h = 0 (cubic: h < 5 mm)


def test_rows_interpolating_an_outside_node_are_nan_and_the_rest_unchanged(model):
    assert model.tensor_out is not None  # the planes say so: h = 0 nodes are outside
    blind = dataclasses.replace(model, tensor_out=None, additive_out=())  # the model before
    d, h, p = rows(H)
    for params in (SimParams(), SimParams(jm=jnp.full(len(H), SimParams().jm * 1.02))):  # scalar, per-row lattice
        f, f0 = np.asarray(model(d, h, p, params)), np.asarray(blind(d, h, p, params))
        assert np.isfinite(f0).all()  # the old model gave a number above p pi R^2 at h = 0
        assert f0[0] > force_bound_n(4000.0, 70.0)
        assert np.isnan(f[NEAR]).all() and np.array_equal(f[~NEAR], f0[~NEAR])
        assert np.array_equal(np.asarray(model.outside_model(d, h, p, params)), NEAR)
        # held at the lattice's edge (optimisers): no NaN, the number; marked: +inf
        assert np.array_equal(np.asarray(model.strict(False)(d, h, p, params)), f0)
        assert np.isposinf(np.asarray(model.marking()(d, h, p, params))[NEAR]).all()


def test_the_likelihood_drops_outside_rows_not_poisons_them(model):
    d, h, p = rows(H)
    n = len(H)
    rws = Rows(h, p, jnp.ones(n, bool), jnp.zeros(n, bool), jnp.ones(n, bool), jnp.zeros(n, jnp.int32))
    obs = jnp.asarray(np.asarray(model.strict(False)(d, h, p)))
    data = CalibrationData(d, rws, obs, jnp.ones(len(H)), KEYS)
    mu = SimParams().mu_pa
    hm = HierarchicalModel(
        force_model=model,
        effects=(),
        n_membranes=0,
        membrane_latents=False,
        mu_prior=Uniform(mu * 0.9, mu * 1.1),
        jm_prior=Uniform(SimParams().jm * 0.99, SimParams().jm * 1.05),
    )
    x = jnp.asarray([{"mu_pa": mu, "jm": SimParams().jm, "noise_n": 0.5}[name] for name in hm.names])
    ll = np.asarray(hm.pointwise_log_lik(x, data))
    assert np.array_equal(np.asarray(hm.outside_rows(x, data)), NEAR)
    typical = -0.5 - np.log(0.5) - 0.5 * np.log(2 * np.pi)  # E[log N(eps; 0, sigma)]
    np.testing.assert_allclose(ll[NEAR], typical)  # not -1e10, not the misfit of a number above p pi R^2
    np.testing.assert_allclose(ll[~NEAR], -np.log(0.5) - 0.5 * np.log(2 * np.pi))  # the data fit exactly
    assert np.isfinite(float(hm.log_posterior_u(hm.to_unconstrained(x), data)))


def test_diagnosis_residuals_drop_and_count_outside_rows(model):
    from mfdesign.data.measurements import Measurements
    from mfdesign.diagnosis.forward import EmulatorForwardModel
    from mfdesign.diagnosis.residuals import compute_residuals

    sim = EmulatorForwardModel(model)
    n = 8
    frame = pd.DataFrame(
        {
            "design_key": [KEYS[0]] * n,
            "trial": np.repeat([0, 1], n // 2),
            "experiment": ["force"] * n,
            "phase": ["inflate"] * n,
            "time_s": np.arange(n, dtype=float),
            "height_set_mm": np.repeat([0.0, 20.0], n // 2),
            "height_mm": np.repeat([0.0, 20.0], n // 2),
            "pressure_pa": np.tile([1000.0, 2000.0, 3000.0, 4000.0], 2),
            "force_n": np.tile([10.0, 20.0, 30.0, 40.0], 2),
            "weight": np.ones(n),
            "source": ["virtual"] * n,
        }
    )
    meas = Measurements(frame)
    out = sim.outside_model(meas)
    assert out[:4].all() and not out[4:].any()
    res = compute_residuals(meas, sim.expected_force(meas), out)
    assert res.dropped["outside_physical_model"] == 4 and len(res.frame) == 4
    assert np.isfinite(res.frame["predicted_n"]).all()
