"""Rig compliance: the rig's frame yields under the membrane's push: the plate sits higher than its set-point."""

from __future__ import annotations

import jax
import jax.numpy as jnp

from mfdesign.physics.effects._base import MeasurementEffect, Parameter, register_effect
from mfdesign.physics.effects._priors import Uniform

__all__ = ["RigCompliance"]


@register_effect
class RigCompliance(MeasurementEffect):
    """The frame that holds the plate at its set height is a spring of stiffness ``k``.

    The membrane pushes the plate up with the force ``F_obs`` the load cell reads; the
    frame yields by ``F_obs / k``, so the true plate height is ``h_set + F_obs / k`` while
    the height sensors, mounted on the same frame, still read ``h_set``. Self-consistency:
    ``F_obs = F(h_set + F_obs / k)``; to first order ``F_obs = F + dF_dh F_obs / k``, so
    ``F_obs = F / (1 - dF_dh / k)``. With ``dF_dh < 0`` (force falls with height) the rig
    reads less than the stiff-rig force. Parameterised by the compliance ``1 / k`` so that
    0 is the neutral value. A lift's free plate does not load the frame.
    """

    name = "rig_compliance"
    story = "the rig's frame yields under the membrane's push: the plate sits higher than its set-point"
    direct_check = "measure the plate's displacement under a known load with the membrane removed"
    parameters = (
        Parameter("compliance_mm_per_n", "mm/N", Uniform(0.0, 0.1), 0.0, 0.02, "1 / k, plate displacement per newton"),
    )

    def observed_force_fn(self, theta, force_fn, rows):
        c = theta["compliance_mm_per_n"]

        def fn(h, p):
            f, slope = jax.jvp(lambda hh: force_fn(hh, p), (h,), (jnp.ones_like(h),))
            slope = jnp.nan_to_num(slope, nan=0.0)  # unknown slope (next to an unsolved cell): no correction
            denom = jnp.maximum(1.0 - slope * c, 0.2)  # guard a rising F(h): never amplify > 5x
            return jnp.where(rows.is_force, f / denom, f)

        return fn
