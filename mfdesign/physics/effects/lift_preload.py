"""Lift preload: the membrane lifts the plate, its guide and bearing friction as well as the mass."""

from __future__ import annotations

import jax.numpy as jnp

from mfdesign.physics.effects._base import MeasurementEffect, Parameter, register_effect
from mfdesign.physics.effects._priors import Normal

__all__ = ["LiftPreload"]


@register_effect
class LiftPreload(MeasurementEffect):
    """In a mass lift the force column is the mass's weight ``W``; the membrane carries
    ``W + preload_n`` (the plate and its guide) ``+ friction_n`` on inflation and
    ``- friction_n`` on deflation (bearing friction opposes the motion). So the expected
    recorded weight at the recorded (h, p) is ``F(h, p) - preload_n -+ friction_n``.

    A negative preload is allowed: a counterweighted plate, or the rows' motion opposite to
    their phase label, read as an upward load. Force trials are untouched (the load cell
    sits between plate and rig)."""

    name = "lift_preload"
    story = "a lift also carries the plate, its guide and bearing friction; the force column records only the mass"
    direct_check = "weigh the plate with its guide and measure the bearing's friction force"
    parameters = (
        Parameter("preload_n", "N", Normal(0.0, 5.0, -20.0, 20.0), 0.0, 3.0, "plate + guide weight [N]"),
        Parameter("friction_n", "N", Normal(0.0, 2.0, 0.0, 10.0), 0.0, 1.0, "bearing friction [N], opposes motion"),
    )

    def observed_force_fn(self, theta, force_fn, rows):
        load = theta["preload_n"] + jnp.where(rows.is_deflate, -theta["friction_n"], theta["friction_n"])
        return lambda h, p: force_fn(h, p) - jnp.where(rows.is_force, 0.0, load)
