"""Load cell offset: the load cell was tared with a different preload: every force reading is shifted."""

from __future__ import annotations

import jax.numpy as jnp

from mfdesign.physics.effects._base import MeasurementEffect, Parameter, register_effect
from mfdesign.physics.effects._priors import Normal

__all__ = ["LoadCellOffset"]


@register_effect
class LoadCellOffset(MeasurementEffect):
    """Force trials read ``F + offset`` [N]; a lift reads no load cell (its force is the weight)."""

    name = "load_cell_offset"
    story = "the load cell was tared with a different preload: every force reading is shifted"
    direct_check = "read the load cell with the plate off and no pressure"
    parameters = (Parameter("offset_n", "N", Normal(0.0, 1.0), 0.0, 0.8, "reading at zero force"),)

    def observed_force_fn(self, theta, force_fn, rows):
        return lambda h, p: force_fn(h, p) + jnp.where(rows.is_force, theta["offset_n"], 0.0)
