"""One calibrated row the force model has no value for must not make every interval NaN."""

from __future__ import annotations

import warnings

import jax.numpy as jnp
import numpy as np

from mfdesign.models.force import ForceModel
from mfdesign.models.standin import standin_force
from mfdesign.physics.params import SimParams


class _HoleAt60mm(ForceModel):
    """The stand-in with no value above 60 mm (like the simulator's NOT_CONVERGED points)."""

    name = "standin-with-a-hole"

    def __call__(self, design, h_mm, p_pa, params: SimParams = SimParams()):
        f = standin_force(design, h_mm, p_pa, params)
        return jnp.where(jnp.asarray(h_mm) > 60.0, jnp.nan, f)


def test_predictive_noise_and_intervals_stay_finite_beside_a_row_without_value():
    from test_calibrate import virtual_data

    from mfdesign.calibration.workflow import fit_multi_fidelity
    from mfdesign.models.ensemble import EnsembleConfig

    table, _ = virtual_data()
    assert (table.df["height_mm"] > 60.0).any()  # the hole is hit by some calibrated rows
    with warnings.catch_warnings():
        warnings.simplefilter("ignore")
        fit = fit_multi_fidelity(
            table,
            _HoleAt60mm(),
            ("pressure_sensor",),
            n_steps=60,
            max_rows=200,
            ensemble_config=EnsembleConfig(n_members=2, steps=20, monotone=False),
            progress=False,
        )
    assert np.isfinite(fit.noise_n) and fit.noise_n > 0
    mf = fit.mf.thinned(4)
    data = mf.data_for(None, None, None, table=table)
    mean, lo, hi = (np.asarray(a) for a in mf.interval(data, 0.9, key=0))
    low = np.asarray(data.rows.h_mm) <= 60.0
    assert np.isfinite(mean[low]).all() and np.isfinite(lo[low]).all() and np.isfinite(hi[low]).all()


def _tiny_fit(**kwargs):
    """A quick ``fit_multi_fidelity`` on the virtual rig's data (stand-in physics): (fit, table)."""
    from test_calibrate import virtual_data

    from mfdesign.calibration.workflow import fit_multi_fidelity
    from mfdesign.models.ensemble import EnsembleConfig
    from mfdesign.models.standin import StandinForceModel

    table, _ = virtual_data()
    with warnings.catch_warnings():
        warnings.simplefilter("ignore")
        fit = fit_multi_fidelity(
            table,
            StandinForceModel(),
            n_steps=60,
            max_rows=200,
            ensemble_config=EnsembleConfig(n_members=2, steps=20, monotone=False),
            progress=False,
            **kwargs,
        )
    return fit, table


def test_given_priors_hold_the_material():
    """``fit_multi_fidelity(jm_prior=..., mu_prior=...)``: narrow priors (the coupons' J_m
    and modulus, held) bound every posterior draw of J_m and mu, where the default priors
    let the data move them."""
    from mfdesign.physics.effects import Uniform

    fit, _ = _tiny_fit(jm_prior=Uniform(30.0, 31.0), mu_prior=Uniform(28.0e3, 28.5e3))
    names = list(fit.posterior.names)
    jm = np.asarray(fit.posterior.samples[:, names.index("jm")])
    mu = np.asarray(fit.posterior.samples[:, names.index("mu_pa")])
    assert jm.min() >= 30.0 and jm.max() <= 31.0
    assert mu.min() >= 28.0e3 and mu.max() <= 28.5e3


def test_without_membrane_latents_every_membrane_is_nominal():
    """``fit_multi_fidelity(membrane_latents=False)``: no thickness latents, no population
    spread (what the membranes share is not traded against each one's own scale), and the
    predictive still gives finite intervals."""
    fit, table = _tiny_fit(membrane_latents=False)
    names = list(fit.posterior.names)
    assert not any(n.startswith("thickness") for n in names), names
    data = fit.mf.data_for(None, None, None, table=table)
    mean, lo, hi = (np.asarray(a) for a in fit.mf.interval(data, 0.9, key=0))
    assert np.isfinite(mean).all() and (lo <= mean).all() and (mean <= hi).all()
