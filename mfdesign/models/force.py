"""The force-model interface: the simulator's plate force as a pure JAX function.

Every place where the model meets data or searches designs calls one of these::

    force_model(design [N, 6] mm, h_mm [N], p_pa [N], params: SimParams) -> F [N] N

with ``params`` fields scalar or ``[N]`` (row-wise effects). Three implementations:

* ``exact`` (:class:`~mfdesign.models.exact.ExactForceModel`): the simulator's planes of the
  measured designs, at simulator accuracy; the default wherever the model meets data;
* ``emulator`` (:class:`~mfdesign.models.emulator.Emulator`): a neural emulator of the
  simulator over the whole design space, for searches (acquisition, optimisation); its
  error (about 1 N RMS) is stated where it is used, and winners are checked by the
  simulator;
* ``standin`` (:class:`~mfdesign.calibration.standin.StandinForceModel`): a closed-form
  shape with no physics, for fast tests.

Sensitivities are autodiff (``jax.jacfwd``) through the implementation.
"""

from __future__ import annotations

import abc
from typing import ClassVar, Mapping

import equinox as eqx

from mfdesign.physics.params import SimParams

__all__ = ["FORCE_MODELS", "ForceModel"]

FORCE_MODELS = ("exact", "emulator", "standin")


class ForceModel(eqx.Module):
    """Abstract force model (module doc). Subclasses implement :meth:`__call__`."""

    name: ClassVar[str] = ""

    @abc.abstractmethod
    def __call__(self, design, h_mm, p_pa, params: SimParams = SimParams()):
        """Plate force [N] of every row (NaN where the model cannot vouch for a number)."""

    def support(self) -> dict[str, tuple[float, float]]:
        """Ranges of simulator constants where the model is valid (priors stay inside)."""
        return {}

    def covering(self, box: Mapping[str, tuple[float, float]], progress: bool = False) -> "ForceModel":
        """A model valid on ``box`` (lattice-axis name -> coordinate range); models valid
        everywhere return themselves."""
        return self

    def covers(self, box: Mapping[str, tuple[float, float]]) -> bool:
        return True
