"""Clamp prestretch: clamping the membrane stretches it radially before inflation."""

from __future__ import annotations

from mfdesign.physics.effects._base import MechanicalEffect, Parameter, register_effect, _replace
from mfdesign.physics.effects._priors import Uniform

__all__ = ["ClampPrestretch"]


@register_effect
class ClampPrestretch(MechanicalEffect):
    name = "clamp_prestretch"
    story = "clamping the membrane stretches it radially before inflation"
    direct_check = "mark radial lines on the membrane and measure their spacing before and after clamping"
    parameters = (Parameter("strain", "1", Uniform(0.0, 0.08), 0.0, 0.02, "hoop stretch at the clamp - 1"),)

    def sim_params(self, base, theta, context=None):
        return _replace(base, clamp_prestretch=base.clamp_prestretch * (1.0 + theta["strain"]))
