"""Pressure sensor: the pressure transducer has a zero offset and a gain error."""

from __future__ import annotations

from mfdesign.physics.effects._base import MeasurementEffect, Parameter, register_effect
from mfdesign.physics.effects._priors import Normal

__all__ = ["PressureSensor"]


@register_effect
class PressureSensor(MeasurementEffect):
    """The transducer reads ``p_rec = gain p_true + offset`` [Pa], in force trials and lifts alike."""

    name = "pressure_sensor"
    story = "the pressure transducer has a zero offset and a gain error"
    direct_check = "check the pressure transducer against a reference gauge at two pressures"
    parameters = (
        Parameter("offset_pa", "Pa", Normal(0.0, 150.0), 0.0, 150.0, "reading at zero gauge pressure"),
        Parameter("gain", "1", Normal(1.0, 0.03, 0.8, 1.2), 1.0, 1.0, "reading / true pressure"),
    )

    def observed_force_fn(self, theta, force_fn, rows):
        # a row recorded at p was at the true pressure (p - offset) / gain
        return lambda h, p: force_fn(h, (p - theta["offset_pa"]) / theta["gain"])
