"""Fabric inset: every fabric edge bonded to rubber acts inside the fabric.

The disk and the rings are fabric cast into the rubber. At a fabric edge the bond takes
up the rubber's pull over a shear-lag length (and a cut edge frays), so the last
millimetres of fabric stretch with the rubber: the rubber beside each fabric edge strains
over a longer span than the nominal gap. One length serves every edge: the disk's radius
shrinks by it, and each ring's inner edge moves out and its outer edge in. Unlike a
contact offset, which moves the disk's edge alone, it weighs most on a membrane with
short rubber gaps (a 3 mm gap gains twice the inset).
"""

from __future__ import annotations

from mfdesign.physics.effects._base import MechanicalEffect, Parameter, register_effect, _replace
from mfdesign.physics.effects._priors import Uniform

__all__ = ["FabricInset"]


@register_effect
class FabricInset(MechanicalEffect):
    name = "fabric_inset"
    story = "each fabric edge bonded to rubber acts inside the fabric (shear lag at the bond, fray), so short rubber gaps strain over a longer span"
    direct_check = (
        "section a bonded ring and measure where the fabric starts to carry load (or a hoop test of a bonded ring)"
    )
    parameters = (Parameter("inset_mm", "mm", Uniform(0.0, 2.0), 0.0, 0.5, "fabric edge's effective inset [mm]"),)

    def sim_params(self, base, theta, context=None):
        return _replace(base, fabric_inset_mm=base.fabric_inset_mm + theta["inset_mm"])
