"""Contact offset: the effective contact radius differs from the disk's.

Positive: the membrane sticks to the plate beyond the rigid disk. Negative: the rubber is
not held over the disk's rim (a rounded or chamfered edge, or a bond that peels under the
membrane's pull), so the free membrane starts inside the disk's radius. Either way the one
quantity the mechanics sees is the radius where the free membrane begins, so one signed
parameter carries both (the real mass lifts ask for a negative one: docs/real_data.md).
"""

from __future__ import annotations

from mfdesign.physics.effects._base import MechanicalEffect, Parameter, register_effect, _replace
from mfdesign.physics.effects._priors import Uniform

__all__ = ["ContactOffset"]


@register_effect
class ContactOffset(MechanicalEffect):
    name = "contact_offset"
    story = "the free membrane starts beyond the disk (it sticks to the plate) or inside it (it is not held over the disk's rim)"
    direct_check = "photograph the membrane at the disk's rim under pressure and measure where it leaves the plate"
    parameters = (Parameter("offset_mm", "mm", Uniform(-6.0, 6.0), 0.0, 2.0, "effective - nominal contact radius"),)

    def sim_params(self, base, theta, context=None):
        return _replace(base, contact_offset_mm=base.contact_offset_mm + theta["offset_mm"])
