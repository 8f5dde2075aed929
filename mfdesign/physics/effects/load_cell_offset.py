"""Load cell offset: the load cell was tared with a different preload: every force reading is shifted."""

from __future__ import annotations

from dataclasses import dataclass

import jax.numpy as jnp

from mfdesign.physics.effects._base import MeasurementEffect, Parameter, register_effect
from mfdesign.physics.effects._priors import Normal

__all__ = ["LoadCellOffset"]


@register_effect
@dataclass(frozen=True)
class LoadCellOffset(MeasurementEffect):
    name = "load_cell_offset"
    story = "the load cell was tared with a different preload: every force reading is shifted"
    parameters = (Parameter("offset_n", "N", Normal(0.0, 1.0), 0.0, 0.8, "reading at zero force"),)

    def observe(self, theta, sample, context):
        if context.experiment != "force":
            return sample  # in a mass lift the force column is the known weight
        return sample.replace(force_n=sample.force_n + theta["offset_n"])

    def observed_force_fn(self, theta, force_fn, rows):
        return lambda h, p: force_fn(h, p) + jnp.where(rows.is_force, theta["offset_n"], 0.0)
