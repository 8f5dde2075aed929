"""A new effect in one file: the lift's height sensors read the plate a fixed distance high.

Load it with ``mfdesign diagnose DATA --effects-module docs/examples/lift_height_offset.py``
(or import it): from then on ``"lift_height_offset"`` works wherever an effect name does.
"""

from dataclasses import dataclass

import jax.numpy as jnp

from mfdesign.physics.effects import MeasurementEffect, Normal, Parameter, register_effect


@register_effect
@dataclass(frozen=True)
class LiftHeightOffset(MeasurementEffect):
    name = "lift_height_offset"
    story = "the time-of-flight sensors read the lifted plate a fixed distance high"
    parameters = (Parameter("offset_mm", "mm", Normal(0.0, 2.0), 0.0, 1.5, "reading - true height in lifts"),)

    def observe(self, theta, sample, context):
        """The virtual rig: true values -> what the rig records."""
        if context.experiment != "lift":
            return sample
        return sample.replace(height_mm=sample.height_mm + theta["offset_mm"])

    def observed_force_fn(self, theta, force_fn, rows):
        """The likelihood: in a lift the plate sits ``offset_mm`` below the recorded height."""
        return lambda h, p: force_fn(jnp.where(rows.is_force, h, h - theta["offset_mm"]), p)
