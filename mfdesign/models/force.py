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
* ``standin`` (:class:`~mfdesign.models.standin.StandinForceModel`): a closed-form
  shape with no physics, for fast tests.

Sensitivities are autodiff (``jax.jacfwd``) through the implementation. One is chosen by
name with :func:`mfdesign.models.backends.force_model_for`.
"""

from __future__ import annotations

import abc
from typing import ClassVar

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

    def input_ranges(self) -> dict[str, tuple[float, float]]:
        """Plate heights [mm] and gauge pressures [Pa] the model vouches for."""
        return {"height_mm": (0.0, float("inf")), "pressure_pa": (0.0, float("inf"))}

    def covers(self, params: SimParams, margin: float = 0) -> bool:
        """Whether the model vouches for every constant in ``params`` (fields of any shape),
        ``margin`` lattice nodes inside its edge (for lattice-based models)."""
        return True

    def covering(
        self, params: SimParams, progress: bool = False, margin: int = 0, edge: float | None = None
    ) -> "ForceModel":
        """A model that holds every constant in ``params`` with ``margin`` lattice nodes to
        spare (with ``edge``: only on the sides where ``params`` come within ``edge`` nodes
        of the lattice's end); models valid everywhere (the emulator inside its ranges, the
        stand-in) return themselves, the exact model grows its lattice of simulator planes."""
        return self

    def reaching(self, params: "SimParams", p_max_pa: float, progress: bool = False) -> "ForceModel":
        """A model that answers for gauge pressures up to ``p_max_pa`` [Pa] under every
        simulator constant of ``params`` (fields of any shape). A thinner or softer membrane
        reads its force at the reduced pressure ``p / s`` (``s = (mu / mu0) tf`` < 1), above
        the data's pressures: models valid everywhere return themselves, the exact model's
        planes grow to it."""
        return self

    def outside_model(self, design, h_mm, p_pa, params: SimParams = SimParams()):
        """Rows [N] bool outside the physical model (force above ``p pi R^2``, the membrane
        below the clamp plane: ``Status.OUTSIDE_MODEL``); a model that cannot tell: none."""
        import jax.numpy as jnp

        return jnp.zeros(jnp.shape(h_mm), bool)

    def marking(self, mark: bool = True) -> "ForceModel":
        """The model whose rows outside the physical model read ``+inf`` (``mark``), the
        marker the likelihood and diagnosis' residuals drop such rows by (the measurement
        effects carry it through); a model that cannot tell returns itself."""
        return self

    def strict(self, strict: bool = True) -> "ForceModel":
        """The model for a sampler (``True``: NaN where it cannot vouch for a number) or for an
        optimiser (``False``: no NaN, values held at the edge of its validity)."""
        return self
