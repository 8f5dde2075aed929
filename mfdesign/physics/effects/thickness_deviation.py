"""Thickness deviation: gravity moulding leaves a membrane thicker or thinner than its nominal thickness."""

from __future__ import annotations

from mfdesign.physics.effects._base import MechanicalEffect, Parameter, register_effect, _replace
from mfdesign.physics.effects._priors import Normal

__all__ = ["ThicknessDeviation"]


@register_effect
class ThicknessDeviation(MechanicalEffect):
    name = "thickness_deviation"
    story = "gravity moulding leaves a membrane thicker or thinner than its nominal thickness"
    direct_check = "measure each membrane's thickness with calipers or a micrometer at several radii"
    parameters = (Parameter("relative", "1", Normal(0.0, 0.1, -0.5, 0.5), 0.0, 0.08, "actual / nominal thickness - 1"),)

    def sim_params(self, base, theta, context=None):
        return _replace(base, thickness_factor=base.thickness_factor * (1.0 + theta["relative"]))
