"""The paper's curve-fit baseline: polynomial features + ridge regression.

Campbell et al. 2025 compare their network with a curve fit: force as a polynomial in the
design numbers, the height and the pressure, fitted by least squares separately for
ringless and ringed membranes. Here, with ``x`` the standardised inputs of a group
(ringless: ``t, c, h, p``; ringed: ``t, c, r1, w1, r2, w2, h, p`` with an absent second
ring's numbers set to 0 after standardisation plus a 0/1 "two rings" indicator)::

    F(x) = sum_{|alpha| <= D} b_alpha x^alpha,
    b = argmin sum_i w_i (F_i - F(x_i))^2 + lam * ||b_{alpha != 0}||^2   (ridge)

solved in closed form. When a group has no training rows (e.g. a held-out ringless
membrane with no other ringless one), that group is predicted by a pooled fit over all
rows (ringed features, ring numbers 0 when absent): stated in ``CurveFit.fallback``.
"""

from __future__ import annotations

import dataclasses
import itertools

import equinox as eqx
import jax.numpy as jnp
import numpy as np

from mfdesign._x64 import enable_x64
from mfdesign.models.ensemble import check_inputs
from mfdesign.models.predictor import RIG, AbstractPredictor


def monomials(n_vars: int, degree: int) -> np.ndarray:
    """Exponent table ``[n_terms, n_vars]`` of all monomials of total degree <= ``degree``."""
    rows = [e for e in itertools.product(range(degree + 1), repeat=n_vars) if sum(e) <= degree]
    return np.asarray(sorted(rows, key=lambda e: (sum(e), tuple(-x for x in e))), dtype=np.int64)


def _raw_features(design, h, p, ringed: bool):
    """Input columns of a group (before standardisation); NaN marks absent rings."""
    if not ringed:
        return jnp.stack([design[:, 0], design[:, 1], h, p], axis=1)
    two = (~jnp.isnan(design[:, 4])).astype(h.dtype)
    return jnp.column_stack([design, h, p, two])


class _Poly(eqx.Module):
    """One fitted polynomial: standardisation, exponents, coefficients."""

    mu: np.ndarray
    sd: np.ndarray
    exps: np.ndarray
    coef: np.ndarray
    ringed: bool = eqx.field(static=True)

    def __call__(self, design, h, p):
        x = (_raw_features(design, h, p, self.ringed) - self.mu) / self.sd
        x = jnp.where(jnp.isnan(x), 0.0, x)
        phi = jnp.prod(x[:, None, :] ** self.exps[None, :, :], axis=-1)
        return phi @ self.coef


def fit_poly(design, h, p, f, w, degree: int, ridge: float, ringed: bool) -> _Poly:
    """Weighted ridge fit of one group (closed form, intercept not penalised)."""
    x = np.asarray(_raw_features(design, h, p, ringed))
    mu, sd = np.nanmean(x, 0), np.nanstd(x, 0)
    mu, sd = np.nan_to_num(mu), np.where((sd > 1e-12) & np.isfinite(sd), sd, 1.0)
    z = np.nan_to_num((x - mu) / sd)
    exps = monomials(z.shape[1], degree)
    phi = np.prod(z[:, None, :] ** exps[None, :, :], axis=-1)
    pen = np.full(len(exps), ridge)
    pen[0] = 0.0
    a = phi.T @ (w[:, None] * phi) + np.diag(pen)
    coef = np.linalg.lstsq(a, phi.T @ (w * f), rcond=None)[0]
    return _Poly(mu, sd, exps, coef, ringed)


@dataclasses.dataclass(frozen=True)
class CurveFitConfig:
    """The baseline's settings: polynomial ``degree`` and ridge strength ``ridge``."""

    degree: int = 3
    ridge: float = 1e-3

    def __post_init__(self):
        if self.degree not in range(1, 7):
            raise ValueError(f"CurveFitConfig.degree must be 1..6, got {self.degree!r}")
        if not (self.ridge >= 0 and np.isfinite(self.ridge)):
            raise ValueError(f"CurveFitConfig.ridge must be finite and >= 0, got {self.ridge!r}")

    def fit(self, design, h_mm, p_pa, force_n, weight=None, *, key=None, progress=False) -> "CurveFit":
        """:class:`~mfdesign.models.cv.ForceModelSpec` interface (``key``/``progress`` unused:
        the fit is exact)."""
        return fit_curve(self, design, h_mm, p_pa, force_n, weight)


class CurveFit(AbstractPredictor):
    """Fitted baseline, a predictor of the ``rig`` fidelity with one member (a curve fit has
    no spread)."""

    ringless: _Poly
    ringed: _Poly
    fallback: tuple[str, ...] = eqx.field(static=True)

    @property
    def fidelities(self):
        return (RIG,)

    def members(self, fidelity, design, h_mm, p_pa):
        """Force [1, n] N at design rows [n, 6] (mm), h [n] mm, p [n] Pa."""
        self.check_fidelity(fidelity)
        design = jnp.asarray(design)
        h, p = jnp.broadcast_arrays(jnp.asarray(h_mm, dtype=design.dtype), jnp.asarray(p_pa, dtype=design.dtype))
        has_ring = ~jnp.isnan(design[:, 2])
        return jnp.where(has_ring, self.ringed(design, h, p), self.ringless(design, h, p))[None, :]

    def mean_std(self, design, h_mm, p_pa):
        f = self.members(RIG, design, h_mm, p_pa)[0]
        return f, jnp.zeros_like(f)


def fit_curve(config: CurveFitConfig, design, h_mm, p_pa, force_n, weight=None) -> CurveFit:
    """Fit the ringless and the ringed polynomial (pooled fallback for an empty group)."""
    enable_x64()  # float64 physics: mfdesign._x64
    design, h, p, f, w = check_inputs(design, h_mm, p_pa, force_n, weight)
    w = np.ones_like(f) if w is None else w
    has_ring = ~np.isnan(design[:, 2])
    fits, fallback = {}, []
    pooled = None
    for ringed, mask in ((False, ~has_ring), (True, has_ring)):
        if mask.sum() > 0:
            fits[ringed] = fit_poly(
                design[mask], h[mask], p[mask], f[mask], w[mask], config.degree, config.ridge, ringed
            )
        else:
            if pooled is None:
                pooled = fit_poly(design, h, p, f, w, config.degree, config.ridge, True)
            fits[ringed] = pooled
            fallback.append("ringed" if ringed else "ringless")
    return CurveFit(fits[False], fits[True], tuple(fallback))
