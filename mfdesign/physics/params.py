"""Simulator inputs that calibration and physical effects vary: one immutable record.

Every field is a float (or a JAX scalar when batched / differentiated), so a
:class:`SimParams` can be ``vmap``-ed over, differentiated through and sampled by emcee.
Effects change the mechanics only through these fields, never by forking the code.
"""

from __future__ import annotations

import equinox as eqx
import jax

from mfdesign.materials import ECOFLEX_JM, ECOFLEX_MU_PA, Gent

Scalar = float | jax.Array


class SimParams(eqx.Module):
    """Physical constants of one simulation (units in the names).

    * ``mu_pa``, ``jm``: Gent constants of the rubber (the authors: 31.7 kPa, 39.6).
    * ``ring_mu_pa``, ``ring_jm``: Gent constants of the fabric rings, modelled as a
      much stiffer hyperelastic solid of the membrane's thickness (the authors' choice:
      1 MPa, 25); a modelling choice, not a measurement.
    * ``thickness_factor``: actual / nominal thickness (gravity moulding makes it != 1).
    * ``thickness_gradient``: relative thickness change from the disk edge to the clamp,
      ``t(r) = t_eff (1 + g ((r - r_mid) / (r_out - r0)))`` (zero mean over the annulus).
    * ``clamp_prestretch``: hoop stretch imposed by the clamp, ``R(r_out) = s * r_out``.
    * ``contact_offset_mm``: the rigid inner region has radius ``c + offset``: positive, the
      membrane stays stuck to the plate beyond the disk; negative, it is free over the disk's rim.
    * ``fabric_inset_mm``: every fabric edge bonded to rubber acts this far inside the
      fabric (the disk's radius shrinks by it; each ring's inner edge moves out and its outer
      edge in): the bond takes up the rubber's pull over a shear-lag length, so the rubber
      beside a fabric edge strains over a longer span than the nominal gap.
    * ``i2_share``: share of the rubber's small-strain shear modulus carried by a
      Mooney-Rivlin second-invariant term (:class:`~mfdesign.materials.Gent`; 0: plain Gent).
    """

    mu_pa: Scalar = ECOFLEX_MU_PA
    jm: Scalar = ECOFLEX_JM
    ring_mu_pa: Scalar = 1.0e6
    ring_jm: Scalar = 25.0
    thickness_factor: Scalar = 1.0
    thickness_gradient: Scalar = 0.0
    clamp_prestretch: Scalar = 1.0
    contact_offset_mm: Scalar = 0.0
    fabric_inset_mm: Scalar = 0.0
    i2_share: Scalar = 0.0

    @property
    def rubber(self) -> Gent:
        return Gent(mu_pa=self.mu_pa, jm=self.jm, i2_share=self.i2_share)

    @property
    def fabric(self) -> Gent:
        return Gent(mu_pa=self.ring_mu_pa, jm=self.ring_jm)
