"""Thickness gradient: the uncured rubber flows outwards in the mould: the membrane thins (or thickens) towards the clamp."""

from __future__ import annotations

from mfdesign.physics.effects._base import MechanicalEffect, Parameter, register_effect, _replace
from mfdesign.physics.effects._priors import Normal

__all__ = ["ThicknessGradient"]


@register_effect
class ThicknessGradient(MechanicalEffect):
    name = "thickness_gradient"
    story = "the uncured rubber flows outwards in the mould: the membrane thins (or thickens) towards the clamp"
    direct_check = "measure each membrane's thickness near the disk and near the clamp"
    parameters = (
        Parameter(
            "gradient",
            "1",
            Normal(0.0, 0.15, -0.6, 0.6),
            0.0,
            -0.15,
            "relative thickness change from the disk edge to the clamp (zero-mean)",
        ),
    )

    def sim_params(self, base, theta, context=None):
        return _replace(base, thickness_gradient=base.thickness_gradient + theta["gradient"])
