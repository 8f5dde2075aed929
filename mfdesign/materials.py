"""Incompressible hyperelastic materials for thin membranes.

For a membrane in plane stress with principal stretches ``lambda1`` (meridional) and
``lambda2`` (hoop), incompressibility gives ``lambda3 = 1 / (lambda1 lambda2)`` and the
first invariant ``I1 = lambda1^2 + lambda2^2 + lambda1^-2 lambda2^-2``.

* Gent (Gent 1996, Rubber Chem. Technol. 69:59):
  ``W = -(mu J_m / 2) ln(1 - (I1 - 3) / J_m)``; the chains lock at ``I1 - 3 = J_m``.
  With ``i2_share = b > 0`` a Mooney-Rivlin second-invariant term (Mooney 1940, J. Appl.
  Phys. 11:582; Rivlin & Saunders 1951, Phil. Trans. A 243:251) takes the share ``b`` of the
  small-strain shear modulus: ``W = (1 - b) W_Gent + (b mu / 2)(I2 - 3)``, so ``mu`` stays
  the small-strain shear modulus. Uniaxial coupons barely separate the two invariants;
  equibiaxial stretch (an inflated membrane) does: the I2 term stiffens it at large stretch
  and removes the inflation's softening towards a limit point.
* neo-Hookean (Treloar 1943): ``W = (mu / 2)(I1 - 3)``, the limit ``J_m -> inf``.

``W`` is per unit reference volume, in the units of ``mu`` (pascals in the public API).
Derivatives ``W1 = dW/dlambda1``, ``W2 = dW/dlambda2`` and the second derivatives come
from autodiff. Beyond the extension limit the Gent energy is NaN (never clipped): the
simulator turns that into the status "extension limit".
"""

from __future__ import annotations

import equinox as eqx
import jax
import jax.numpy as jnp


def first_invariant(l1, l2):
    """``I1`` of the incompressible plane-stress state."""
    return l1**2 + l2**2 + 1.0 / (l1 * l2) ** 2


def second_invariant(l1, l2):
    """``I2`` of the incompressible plane-stress state."""
    return 1.0 / l1**2 + 1.0 / l2**2 + (l1 * l2) ** 2


class Material(eqx.Module):
    """Base class: subclasses implement :meth:`energy` (per reference volume)."""

    def energy(self, l1, l2):
        raise NotImplementedError

    def dW(self, l1, l2):
        """``(W1, W2)``: the energy's derivatives with respect to the two stretches."""
        return jax.grad(self.energy, argnums=(0, 1))(l1, l2)

    def d2W(self, l1, l2):
        """``(W11, W12)``: the derivatives of ``W1`` with respect to ``lambda1`` and ``lambda2``."""
        w1 = lambda a, b: jax.grad(self.energy, argnums=0)(a, b)  # noqa: E731
        return jax.grad(w1, argnums=(0, 1))(l1, l2)

    def locking_fraction(self, l1, l2):
        """``(I1 - 3) / J_m``: 1 at the extension limit, 0 for materials that do not lock."""
        return jnp.zeros_like(l1 + l2)


# The authors' fit of Ecoflex 00-30 (the paper's constants; calibration starts from them).
ECOFLEX_MU_PA = 31.7e3  # Pa
ECOFLEX_JM = 39.6


class NeoHookean(Material):
    """``W = (mu / 2)(I1 - 3)`` with shear modulus ``mu_pa`` [Pa]."""

    mu_pa: float | jax.Array = ECOFLEX_MU_PA

    def energy(self, l1, l2):
        return 0.5 * self.mu_pa * (first_invariant(l1, l2) - 3.0)


class Gent(Material):
    """Gent: small-strain shear modulus ``mu_pa`` [Pa], locking parameter ``jm``
    (dimensionless) and the share ``i2_share`` (0 <= b < 1) of the modulus carried by a
    Mooney-Rivlin ``I2`` term (module doc; 0: plain Gent)."""

    mu_pa: float | jax.Array = ECOFLEX_MU_PA
    jm: float | jax.Array = ECOFLEX_JM
    i2_share: float | jax.Array = 0.0

    def energy(self, l1, l2):
        x = (first_invariant(l1, l2) - 3.0) / self.jm
        # NaN beyond the limit on purpose: a state past locking does not exist.
        x = jnp.where(x < 1.0, x, jnp.nan)
        b = self.i2_share
        gent = -0.5 * self.mu_pa * self.jm * jnp.log1p(-x)
        return (1.0 - b) * gent + 0.5 * b * self.mu_pa * (second_invariant(l1, l2) - 3.0)

    def locking_fraction(self, l1, l2):
        return (first_invariant(l1, l2) - 3.0) / self.jm


# The authors' choices, kept as named defaults (ARCHITECTURE.md, the data README).
FABRIC_RING = Gent(mu_pa=1.0e6, jm=25.0)  # the stiff ring material: a modelling choice
