"""Pressure sensor: the pressure transducer has a zero offset and a gain error."""

from __future__ import annotations

from dataclasses import dataclass

from mfdesign.physics.effects._base import MeasurementEffect, Parameter, register_effect
from mfdesign.physics.effects._priors import Normal

__all__ = ["PressureSensor"]


@register_effect
@dataclass(frozen=True)
class PressureSensor(MeasurementEffect):
    name = "pressure_sensor"
    story = "the pressure transducer has a zero offset and a gain error"
    parameters = (
        Parameter("offset_pa", "Pa", Normal(0.0, 150.0), 0.0, 150.0, "reading at zero gauge pressure"),
        Parameter("gain", "1", Normal(1.0, 0.03, 0.8, 1.2), 1.0, 1.0, "reading / true pressure"),
    )

    def observe(self, theta, sample, context):
        return sample.replace(pressure_pa=theta["gain"] * sample.pressure_pa + theta["offset_pa"])

    def observed_force_fn(self, theta, force_fn, rows):
        # recorded p = gain * p_true + offset  =>  p_true = (p - offset) / gain
        return lambda h, p: force_fn(h, (p - theta["offset_pa"]) / theta["gain"])
