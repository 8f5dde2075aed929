"""Hencky's solution of the Föppl membrane problem, computed independently with SciPy.

A clamped circular membrane (radius ``a``, thickness ``h``, Young's modulus ``E``,
Poisson's ratio ``nu``) under a uniform pressure ``q``, in the small-strain, moderate-
rotation (Föppl) theory. References: H. Hencky, "Über den Spannungszustand in kreisrunden
Platten mit verschwindender Biegungssteifigkeit", Z. Math. Phys. 63 (1915) 311-317;
S. Timoshenko & S. Woinowsky-Krieger, *Theory of Plates and Shells*, 2nd ed. (1959),
§ 98 "Large deflections of membranes" (eqs. (h)-(j): w0 = 0.662 a (q a / E h)^(1/3) and
sigma_0 = 0.423 (E q^2 a^2 / h^2)^(1/3) at the centre for nu = 0.3).

Equations (``N_r``, ``N_t`` stress resultants, ``u`` radial and ``w`` vertical
displacement):

* radial equilibrium ``d(r N_r)/dr = N_t``;
* vertical equilibrium ``N_r w' = -q r / 2``;
* strains ``e_r = u' + w'^2 / 2``, ``e_t = u / r`` with plane-stress Hooke's law;
* clamp ``u(a) = 0``, i.e. ``N_t(a) = nu N_r(a)``; regularity at the centre.

With ``S = r N_r`` compatibility ``(r e_t)' = e_r - w'^2/2`` becomes
``r S'' + S' - S / r = -E h w'^2 / 2 = -E h q^2 r^4 / (8 S^2)``.
Scaling ``rho = r / a``, ``Q = q a / (E h)``, ``S = a E h Q^(2/3) s(rho)`` removes every
constant: ``rho s'' + s' - s / rho = -rho^4 / (8 s^2)``, ``s ~ n0 rho`` at the centre,
``s'(1) = nu s(1)`` at the clamp. Then

* ``N_r(0) = n0 E h Q^(2/3)``, so ``sigma_0 = n0 (E q^2 a^2 / h^2)^(1/3)``: S(nu) = n0;
* ``w' = -Q^(1/3) rho^2 / (2 s)``, so ``w0 = K a Q^(1/3)`` with
  ``K(nu) = int_0^1 rho^2 / (2 s) d rho``.

The one unknown ``n0`` is found by shooting (``solve_ivp`` + ``brentq``).
"""

from __future__ import annotations

from dataclasses import dataclass

import numpy as np
from scipy.integrate import solve_ivp
from scipy.optimize import brentq

_RHO0 = 1e-4  # start of the integration; the series below is exact to O(rho^5) there


def _rhs(rho, y):
    s, ds, k = y
    d2s = (-(rho**4) / (8.0 * s * s) - ds + s / rho) / rho
    return [ds, d2s, rho * rho / (2.0 * s)]


def _shoot(n0: float):
    # Series at the centre: s = n0 rho + b rho^3 with b = -1 / (64 n0^2).
    b = -1.0 / (64.0 * n0 * n0)
    rho = _RHO0
    y0 = [n0 * rho + b * rho**3, n0 + 3 * b * rho**2, rho**3 / (6.0 * n0)]
    return solve_ivp(_rhs, (rho, 1.0), y0, method="DOP853", rtol=1e-12, atol=1e-14)


def _clamp_residual(n0: float, nu: float) -> float:
    sol = _shoot(n0)
    s, ds, _ = sol.y[:, -1]
    return ds - nu * s  # u(a) = 0  <=>  N_t(a) = nu N_r(a)


@dataclass(frozen=True)
class HenckySolution:
    nu: float
    stress_coefficient: float  # S(nu): sigma_0 = S (E q^2 a^2 / h^2)^(1/3)
    deflection_coefficient: float  # K(nu): w0 = K a (q a / (E h))^(1/3)

    def centre_deflection(self, a, h, E, q):
        return self.deflection_coefficient * a * (q * a / (E * h)) ** (1.0 / 3.0)

    def centre_stress(self, a, h, E, q):
        return self.stress_coefficient * (E * q * q * a * a / (h * h)) ** (1.0 / 3.0)


def hencky(nu: float) -> HenckySolution:
    """Hencky's constants for Poisson's ratio ``nu`` (by shooting on the centre stress)."""
    n0 = brentq(_clamp_residual, 0.05, 5.0, args=(nu,), xtol=1e-14, rtol=1e-13)
    k = _shoot(n0).y[2, -1]
    return HenckySolution(nu=nu, stress_coefficient=float(n0), deflection_coefficient=float(k))


def hencky_profile(nu: float, rho=None):
    """Normalised deflection ``w(rho) / (a Q^(1/3))`` on ``rho`` in [0, 1] (w(1) = 0)."""
    n0 = hencky(nu).stress_coefficient
    b = -1.0 / (64.0 * n0 * n0)
    y0 = [n0 * _RHO0 + b * _RHO0**3, n0 + 3 * b * _RHO0**2, _RHO0**3 / (6.0 * n0)]
    rho = np.linspace(_RHO0, 1.0, 201) if rho is None else np.asarray(rho)
    sol = solve_ivp(_rhs, (_RHO0, 1.0), y0, method="DOP853", rtol=1e-12, atol=1e-14, dense_output=True)
    k_end = sol.y[2, -1]
    return rho, k_end - sol.sol(np.clip(rho, _RHO0, 1.0))[2]


if __name__ == "__main__":
    for nu in (0.3, 0.5):
        sol = hencky(nu)
        print(
            f"nu={nu}: w0 = {sol.deflection_coefficient:.5f} a (qa/Eh)^1/3, "
            f"sigma0 = {sol.stress_coefficient:.5f} (E q^2 a^2/h^2)^1/3"
        )
