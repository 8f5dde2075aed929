"""Hysteresis: viscoelastic losses: the membrane pushes less on deflation than on inflation."""

from __future__ import annotations

from dataclasses import dataclass

import jax.numpy as jnp
import numpy as np

from mfdesign.physics.effects._base import MeasurementEffect, Parameter, register_effect
from mfdesign.physics.effects._priors import Uniform

__all__ = ["Hysteresis"]


@register_effect
@dataclass(frozen=True)
class Hysteresis(MeasurementEffect):
    """Viscoelastic loss: on deflation the rubber carries a fraction ``loss`` less force.

    In a force trial the load cell reads ``(1 - loss) F``. In a mass lift the plate then
    sinks until ``(1 - loss) F(h) = W``: to first order ``dh = loss W / dF_dh`` (< 0).
    """

    name = "hysteresis"
    story = "viscoelastic losses: the membrane pushes less on deflation than on inflation"
    parameters = (Parameter("loss", "1", Uniform(0.0, 0.3), 0.0, 0.08, "fractional force deficit on deflation"),)

    def observe(self, theta, sample, context):
        loss = theta["loss"]
        down = context.is_deflate
        if loss == 0.0 or not np.any(down):
            return sample
        if context.experiment == "force":
            return sample.replace(force_n=np.where(down, (1.0 - loss) * sample.force_n, sample.force_n))
        if context.dF_dh is None:
            raise ValueError("hysteresis in a mass lift needs context.dF_dh (N/mm)")
        slope = np.asarray(context.dF_dh, float)
        ok = np.isfinite(slope) & (slope < -1e-6)
        dh = np.where(ok, loss * sample.force_n / np.where(ok, slope, -1.0), 0.0)
        return sample.replace(height_mm=np.where(down, np.maximum(sample.height_mm + dh, 0.0), sample.height_mm))

    def observed_force_fn(self, theta, force_fn, rows):
        # Force rows: the load cell reads (1 - loss) F. Lift rows: the plate settles where
        # (1 - loss) F(h, p) = W at the recorded h, so the expected "force" sample is the same
        # (1 - loss) F (the forward model moves the height to first order instead).
        loss = theta["loss"]
        return lambda h, p: jnp.where(rows.is_deflate, (1.0 - loss) * force_fn(h, p), force_fn(h, p))
