"""A chain too short or too stuck for emcee to estimate tau is reported as not converged,
in words, instead of crashing the report (a 40-step campaign smoke run met a NaN tau)."""

import warnings

import numpy as np

from mfdesign.calibration.mcmc import convergence_report


class _Stuck:
    """A sampler stub whose walkers never moved (zero variance: emcee's tau is NaN)."""

    acceptance_fraction = np.zeros(8)

    def get_chain(self, discard=0):
        return np.ones((40 - discard, 8, 2))


def test_a_nan_autocorrelation_time_is_a_stated_problem_not_a_crash():
    with warnings.catch_warnings():
        warnings.simplefilter("ignore")
        report = convergence_report(_Stuck(), ["mu_pa", "jm"], warn=False)
    assert report["converged"] is False
    assert any("too short to estimate the autocorrelation time of mu_pa, jm" in p for p in report["problems"])
