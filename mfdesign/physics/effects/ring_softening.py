"""Ring softening: the fabric rings partly delaminate from the rubber, so they are less stiff than assumed."""

from __future__ import annotations

from mfdesign.physics.effects._base import MechanicalEffect, Parameter, register_effect, _replace
from mfdesign.physics.effects._priors import LogNormal

__all__ = ["RingSoftening"]


@register_effect
class RingSoftening(MechanicalEffect):
    name = "ring_softening"
    story = "the fabric rings partly delaminate from the rubber, so they are less stiff than assumed"
    direct_check = "a hoop or uniaxial test of a ring cut from a bonded membrane"
    parameters = (
        Parameter("factor", "1", LogNormal(0.5, 1.0, 0.01, 1.0), 1.0, 0.3, "effective / assumed ring shear modulus"),
    )

    def sim_params(self, base, theta, context=None):
        return _replace(base, ring_mu_pa=base.ring_mu_pa * theta["factor"])
