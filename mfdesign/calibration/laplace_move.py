"""An independence Metropolis-Hastings move drawn from the Laplace approximation.

Tierney (1994), "Markov chains for exploring posterior distributions", Ann. Statist. 22,
1701-1762, section 2.3.3: proposals ``x' ~ q`` independent of the current point, accepted
with ``min(1, p(x') q(x) / (p(x) q(x')))``. With ``q`` a heavy-tailed Student-t centred at
the MAP with the inverse Hessian as its scale, a near-Gaussian posterior (many rows, a
dozen parameters) is crossed in one accepted step instead of the tens of ensemble steps
an affine-invariant move needs per autocorrelation time; the heavier tails keep the
chain correct (``q`` must cover ``p``'s tails). Mixed with differential evolution in
:func:`mfdesign.calibration.mcmc.calibrate`, which keeps exploring where ``q`` fits badly.

In many dimensions the acceptance falls fast with the mismatch of ``q``: a Student-t with
few dof spreads the radius of its draws far wider than a near-Gaussian posterior's, and the
inflation costs ~ ``d (1 - 1/inflate^2)^2 / 2`` in the log weights' variance (for the exact
covariance in 28 dimensions, 5 dof and inflation 1.2 accept ~0.38, 56 dof and 1.1 ~0.63);
so the fitted proposals of :func:`~mfdesign.calibration.mcmc.adapted_moves` take ``2 d``
dof and a smaller inflation than the first round's Laplace approximation.
"""

from __future__ import annotations

import emcee
import numpy as np

__all__ = ["LaplaceMove"]


class LaplaceMove(emcee.moves.MHMove):
    """``mean`` [d] (the MAP in the sampler's coordinates), ``cov`` [d, d] (the inverse
    Hessian there), ``df`` the Student-t degrees of freedom, ``inflate`` the factor on its
    scale (> 1: wider than the posterior, so that ``q`` covers it)."""

    def __init__(self, mean, cov, df: float = 5.0, inflate: float = 1.3):
        self.mean = np.asarray(mean, float)
        self.chol = np.linalg.cholesky(inflate**2 * np.asarray(cov, float))  # LinAlgError: not PD
        self.df = float(df)
        super().__init__(self._propose, ndim=self.mean.size)

    def _log_q(self, x: np.ndarray) -> np.ndarray:
        r = np.linalg.solve(self.chol, (x - self.mean).T)  # [d, K] standardised offsets
        return -0.5 * (self.df + self.mean.size) * np.log1p(np.sum(r**2, 0) / self.df)

    def _propose(self, coords: np.ndarray, random) -> tuple[np.ndarray, np.ndarray]:
        k, d = coords.shape
        w = np.sqrt(random.chisquare(self.df, k) / self.df)
        q = self.mean + (random.standard_normal((k, d)) @ self.chol.T) / w[:, None]
        # ln q(x) - ln q(x'): the Hastings factor of an independence proposal
        return q, self._log_q(coords) - self._log_q(q)
