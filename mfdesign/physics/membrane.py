"""Equilibrium equations of an axisymmetric hyperelastic membrane, one material segment.

Reference state: a flat annulus, radius ``r`` (mm). Deformed meridian ``(R(r), Z(r))``
with ``R' = lambda1 cos(phi)`` and ``Z' = lambda1 sin(phi)``: ``phi`` is the angle of
the meridian above the horizontal, going outward. Hoop stretch ``lambda2 = R / r``.
With ``W(lambda1, lambda2)`` the energy per reference volume and ``t(r)`` the reference
thickness, the meridional force per radian is ``Q = r t W1`` and force balance of a ring
element gives (derived in docs/physics.md)::

    d(r t W1 cos phi)/dr - t W2 - p R lambda1 sin phi = 0     (radial)
    d(r t W1 sin phi)/dr + p R lambda1 cos phi       = 0     (vertical)

hence, with ``lambda2' = (lambda1 cos phi - lambda2) / r``,

    Q'     = t W2 cos phi
    phi'   = -(t W2 sin phi + p R lambda1) / (r t W1)
    lambda1' = (t W2 cos phi - t W1 - r t' W1 - r t W12 lambda2') / (r t W11)

The vertical equation integrates exactly to the first integral used as a check:
``2 pi r t W1 sin(phi) + p pi R^2 = F`` for every ``r``, ``F`` the force on the plate.

At an interface between materials ``a`` and ``b``, ``R``, ``Z``, ``phi`` and ``Q`` are
continuous; ``lambda1`` jumps so that ``t W1_b(lambda1_b, lambda2) = t W1_a(lambda1_a,
lambda2)`` (:func:`jump_lambda1`).

Units inside the physics: mm, N, and N/mm^2 (= MPa) for stresses and pressure.
"""

from __future__ import annotations

import equinox as eqx
import jax
import jax.numpy as jnp
import optimistix as optx

from mfdesign.materials import Gent


class Segment(eqx.Module):
    """Material and thickness law on one radial interval (stresses in MPa, lengths mm)."""

    mu_mpa: jax.Array
    jm: jax.Array
    i2_share: jax.Array  # share of mu in a Mooney-Rivlin I2 term (mfdesign.materials.Gent)
    t_mm: jax.Array  # thickness at r_mid
    gradient: jax.Array  # relative thickness change across the whole annulus
    r_mid: jax.Array
    span: jax.Array

    def thickness(self, r):
        """Reference thickness ``t(r)`` [mm] and its derivative."""
        slope = self.t_mm * self.gradient / self.span
        return self.t_mm + slope * (r - self.r_mid), slope

    def energy(self, l1, l2):
        """Gent energy per reference volume [MPa]; NaN past the extension limit."""
        return Gent(mu_pa=self.mu_mpa, jm=self.jm, i2_share=self.i2_share).energy(l1, l2)

    def w1(self, l1, l2):
        return jax.grad(self.energy, argnums=0)(l1, l2)

    def w2(self, l1, l2):
        return jax.grad(self.energy, argnums=1)(l1, l2)

    def locking(self, l1, l2):
        """``(I1 - 3) / J_m``: reaches 1 at the extension limit."""
        return (l1**2 + l2**2 + 1.0 / (l1 * l2) ** 2 - 3.0) / self.jm


def rhs(r, y, args):
    """Right-hand side ``d(lambda1, lambda2, phi, Z)/dr`` of one segment."""
    seg, p = args
    l1, l2, phi, _z = y
    t, dt = seg.thickness(r)
    w1 = seg.w1(l1, l2)
    w2 = seg.w2(l1, l2)
    w11, w12 = jax.grad(seg.w1, argnums=(0, 1))(l1, l2)
    cos, sin = jnp.cos(phi), jnp.sin(phi)
    R = r * l2
    dl2 = (l1 * cos - l2) / r
    dphi = -(t * w2 * sin + p * R * l1) / (r * t * w1)
    dl1 = (t * w2 * cos - t * w1 - r * dt * w1 - r * t * w12 * dl2) / (r * t * w11)
    return jnp.stack([dl1, dl2, dphi, l1 * sin])


def meridional_force(seg: Segment, r, l1, l2):
    """``Q = r t W1`` [N/mm... per radian: N]: continuous across interfaces."""
    t, _ = seg.thickness(r)
    return r * t * seg.w1(l1, l2)


def admissible_stretch(seg: Segment, l2, fraction=0.999):
    """Range ``(lo, hi)`` of ``lambda1`` with ``(I1 - 3) / J_m <= fraction`` at ``l2``.

    ``I1 = x^2 + l2^2 + 1/(x l2)^2 <= 3 + fraction J_m`` is a quadratic in ``x^2``.
    """
    c = 3.0 + fraction * seg.jm - l2**2
    disc = jnp.sqrt(jnp.maximum(c**2 - 4.0 / l2**2, 0.0))
    return jnp.sqrt(0.5 * jnp.maximum(c - disc, 1e-12)), jnp.sqrt(0.5 * (c + disc))


_JUMP_SOLVER = optx.Newton(rtol=1e-12, atol=1e-12)


@jax.custom_jvp
def _jump_root(seg_a: Segment, seg_b: Segment, r, l1_a, l2):
    """Root of ``G(x) = Q_b(x, l2) - Q_a(l1_a, l2)`` in the admissible range of ``b``."""
    target = meridional_force(seg_a, r, l1_a, l2)
    scale = r * seg_a.t_mm * seg_a.mu_mpa
    lo, hi = admissible_stretch(seg_b, l2)

    def residual(x, _):
        return (meridional_force(seg_b, r, x, l2) - target) / scale

    guess = jnp.clip(1.0 + (l1_a - 1.0) * seg_a.mu_mpa / seg_b.mu_mpa, lo, hi)
    sol = optx.root_find(residual, _JUMP_SOLVER, guess, options=dict(lower=lo, upper=hi), max_steps=60, throw=False)
    return jnp.clip(sol.value, lo, hi)


@_jump_root.defjvp
def _jump_root_jvp(primals, tangents):
    # Implicit function theorem for the scalar G(x, inputs) = 0:
    # dx = -(dG/d inputs . d inputs) / (dG/dx). A scalar division, so no linear solve
    # (whose tangent solves lineax always checks, aborting a batch on one bad point).
    seg_a, seg_b, r, l1_a, l2 = primals
    x = _jump_root(*primals)

    def G(sa, sb, rr, la, ll):
        return meridional_force(sb, rr, x, ll) - meridional_force(sa, rr, la, ll)

    _, dG = jax.jvp(G, primals, tangents)
    dGdx = jax.grad(lambda xx: meridional_force(seg_b, r, xx, l2))(x)
    dx = -dG / dGdx
    return x, jnp.where(jnp.isfinite(dx), dx, 0.0)


def jump_lambda1(seg_a: Segment, seg_b: Segment, r, l1_a, l2, valid=True):
    """``lambda1`` on side ``b`` of an interface at ``r`` that carries the same ``Q``.

    Newton (optimistix) from the small-strain guess ``1 + (lambda1_a - 1) mu_a / mu_b``,
    iterates kept inside the material's admissible range. ``W1`` is increasing in
    ``lambda1`` over that whole range (numerator and ``1 / (J_m - I1 + 3)`` both help),
    so the root is unique. Returns ``(lambda1_b, ok)``.
    """
    lo_a, hi_a = admissible_stretch(seg_a, l2)
    finite = valid & jnp.isfinite(l1_a) & jnp.isfinite(l2) & (l2 > 0.05) & (l2 < 20.0)
    finite = finite & (l1_a > lo_a) & (l1_a < hi_a)
    l1_safe = jnp.where(finite, l1_a, 1.5)
    l2_safe = jnp.where(finite, l2, 1.0)
    value = _jump_root(seg_a, seg_b, r, l1_safe, l2_safe)
    scale = r * seg_a.t_mm * seg_a.mu_mpa
    mismatch = meridional_force(seg_b, r, value, l2_safe) - meridional_force(seg_a, r, l1_safe, l2_safe)
    ok = finite & (jnp.abs(mismatch) < 1e-9 * scale)
    return value, ok
