"""The one predictor interface: abstract base, pointwise members, grid path, fidelity checks."""

import jax.numpy as jnp
import numpy as np
import pytest

from mfdesign.models.baselines import CurveFitConfig
from mfdesign.models.ensemble import EnsembleConfig
from mfdesign.models.predictor import (
    AbstractPredictor,
    EnsemblePredictor,
    FunctionPredictor,
    Grid,
    SplitPredictor,
)
from tiny_models import tiny_ensemble

GRID = Grid(h_mm=(0.0, 25.0), p_pa=(2000.0, 6000.0, 8000.0))
DESIGNS = jnp.asarray([[2.0, 26.0, 36.0, 6.0, np.nan, np.nan], [1.2, 30.0, np.nan, np.nan, np.nan, np.nan]])


def test_the_base_declares_members_and_fidelities():
    class NoMembers(AbstractPredictor):
        @property
        def fidelities(self):
            return ("rig",)

    class NoFidelities(AbstractPredictor):
        def members(self, fidelity, design, h_mm, p_pa):
            return h_mm[None]

    for cls in (NoMembers, NoFidelities):
        with pytest.raises(TypeError, match="abstract"):
            cls()


@pytest.mark.parametrize("fidelity", ["rig", "sim"])
def test_fast_ensemble_grid_equals_the_pointwise_grid(fidelity):
    """The ensembles' grid override and the base's grid (built on ``members``) agree."""
    ens = EnsemblePredictor(tiny_ensemble())
    split = SplitPredictor(tiny_ensemble(seed=0), tiny_ensemble(seed=1))
    for pred in (ens, split):
        if fidelity not in pred.fidelities:
            continue
        fast = np.asarray(pred.grid_members(fidelity, DESIGNS, GRID))
        pointwise = np.asarray(AbstractPredictor.grid_members(pred, fidelity, DESIGNS, GRID))
        assert fast.shape == (3, 2, GRID.size)
        np.testing.assert_allclose(fast, pointwise, rtol=1e-6, atol=1e-9)


def test_split_members_add_pointwise():
    sim, disc = tiny_ensemble(seed=0), tiny_ensemble(seed=1)
    pred = SplitPredictor(sim, disc)
    h, p = jnp.asarray([0.0, 30.0]), jnp.asarray([3000.0, 7000.0])
    np.testing.assert_allclose(pred.members("sim", DESIGNS, h, p), sim.predict(DESIGNS, h, p))
    np.testing.assert_allclose(
        pred.members("rig", DESIGNS, h, p), sim.predict(DESIGNS, h, p) + disc.predict(DESIGNS, h, p)
    )


def test_unknown_fidelity_names_the_allowed_ones():
    pred = FunctionPredictor({"rig": lambda d, h, p: h[None]})
    with pytest.raises(ValueError, match=r"'sim' not offered.*\['rig'\]"):
        pred.members("sim", DESIGNS, jnp.zeros(2), jnp.zeros(2))
    with pytest.raises(ValueError, match="not offered"):
        EnsemblePredictor(tiny_ensemble()).grid_members("sim", DESIGNS, GRID)


def test_fitted_specs_are_predictors():
    """``fit`` of every spec returns the one predictor type (what CV scores)."""
    rng = np.random.default_rng(0)
    two = [[2.0, 25.4, np.nan, np.nan, np.nan, np.nan], [1.5, 30.0, 45.0, 6.0, 60.0, 5.0]]
    d = np.repeat(np.asarray(two), 20, axis=0)
    h, p = rng.uniform(0, 40, 40), rng.uniform(1e3, 8e3, 40)
    f = 1e-3 * p - 0.1 * h
    ens = EnsembleConfig(n_members=2, steps=2, chunk=2, latent_width=4, latent_depth=1).fit(d, h, p, f, progress=False)
    curve = CurveFitConfig(degree=1).fit(d, h, p, f)
    assert isinstance(ens, EnsemblePredictor) and isinstance(curve, AbstractPredictor)
    np.testing.assert_array_equal(ens.members("rig", d, h, p), ens.ensemble.predict(d, h, p))
    assert curve.members("rig", d, h, p).shape == (1, 40)
