"""Contact offset: the membrane sticks to the plate beyond the rigid disk, so the effective contact radius is larger."""

from __future__ import annotations

from mfdesign.physics.effects._base import MechanicalEffect, Parameter, register_effect, _replace
from mfdesign.physics.effects._priors import Uniform

__all__ = ["ContactOffset"]


@register_effect
class ContactOffset(MechanicalEffect):
    name = "contact_offset"
    story = "the membrane sticks to the plate beyond the rigid disk, so the effective contact radius is larger"
    parameters = (Parameter("offset_mm", "mm", Uniform(0.0, 6.0), 0.0, 2.0, "effective - nominal contact radius"),)

    def sim_params(self, base, theta, context=None):
        return _replace(base, contact_offset_mm=base.contact_offset_mm + theta["offset_mm"])
