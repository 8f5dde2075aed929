"""A new effect in one file: the lift's height sensors read the plate a fixed distance high.

Load it with ``mfdesign diagnose DATA --effects-module docs/examples/lift_height_offset.py``
(or import it): from then on ``"lift_height_offset"`` works wherever an effect name does.
"""

import jax.numpy as jnp

from mfdesign.physics.effects import MeasurementEffect, Normal, Parameter, register_effect


@register_effect
class LiftHeightOffset(MeasurementEffect):
    name = "lift_height_offset"
    story = "the time-of-flight sensors read the lifted plate a fixed distance high"
    parameters = (Parameter("offset_mm", "mm", Normal(0.0, 2.0), 0.0, 1.5, "reading - true height in lifts"),)

    def observed_force_fn(self, theta, force_fn, rows):
        """Expected recorded force at recorded (h, p): a lift's plate is ``offset_mm`` below
        the height its sensors record (the likelihood evaluates this at the recorded rows;
        the virtual rig records a lift where it equals the weight)."""
        return lambda h, p: force_fn(jnp.where(rows.is_force, h, h - theta["offset_mm"]), p)
