"""Stress softening: Mullins effect: the virgin rubber of the first inflation is stiffer than in every later trial."""

from __future__ import annotations

import numpy as np

from mfdesign.physics.effects._base import MechanicalEffect, Parameter, register_effect, _replace
from mfdesign.physics.effects._priors import Uniform

__all__ = ["StressSoftening"]


@register_effect
class StressSoftening(MechanicalEffect):
    name = "stress_softening"
    story = "Mullins effect: the virgin rubber of the first inflation is stiffer than in every later trial"
    direct_check = "compare the first and the third inflation of a fresh membrane at one height"
    parameters = (
        Parameter(
            "stiffening",
            "1",
            Uniform(0.0, 0.5),
            0.0,
            0.15,
            "relative increase of the rubber's shear modulus on the membrane's first trial",
        ),
    )

    def sim_params(self, base, theta, context=None):
        first = context is not None and int(np.min(context.trial_index)) == 0
        return self._stiffen(base, theta, float(first))

    def row_sim_params(self, base, theta, rows):
        return self._stiffen(base, theta, rows.is_first_trial.astype(float))

    @staticmethod
    def _stiffen(base, theta, first):
        """mu times ``1 + stiffening`` where ``first`` is 1 (the first trial), unchanged where 0."""
        return _replace(base, mu_pa=base.mu_pa * (1.0 + theta["stiffening"] * first))
