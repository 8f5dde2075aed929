"""Hysteresis: viscoelastic losses: the membrane pushes less on deflation than on inflation."""

from __future__ import annotations

import jax.numpy as jnp

from mfdesign.physics.effects._base import MeasurementEffect, Parameter, register_effect
from mfdesign.physics.effects._priors import Uniform

__all__ = ["Hysteresis"]


@register_effect
class Hysteresis(MeasurementEffect):
    """Viscoelastic loss: on deflation the rubber carries a fraction ``loss`` less force.

    A force trial's load cell reads ``(1 - loss) F``; a lifted plate settles where
    ``(1 - loss) F(h, p) = W``, i.e. lower (the virtual rig solves for that height).
    """

    name = "hysteresis"
    story = "viscoelastic losses: the membrane pushes less on deflation than on inflation"
    direct_check = "run one trial with a slow and one with a fast ramp, inflation and deflation, at one height"
    parameters = (Parameter("loss", "1", Uniform(0.0, 0.3), 0.0, 0.08, "fractional force deficit on deflation"),)

    def observed_force_fn(self, theta, force_fn, rows):
        scale = jnp.where(rows.is_deflate, 1.0 - theta["loss"], 1.0)
        return lambda h, p: scale * force_fn(h, p)
