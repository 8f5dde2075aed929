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

What a rig records is that force seen through the effects (:mod:`mfdesign.physics.effects`):
:func:`recorded_force` is the one place that applies them to a force model, row by row::

    params = row_sim_params(effects, theta, base, rows, thickness_rel)   # mechanics, per row
    F      = apply_expected_force(effects, theta, force_model(design, ., ., params), rows)  # measurement chain

The calibration's likelihood (:class:`~mfdesign.models.hierarchical.HierarchicalModel`) and
the diagnosis' forward model both call it. :class:`RecordedForceModel` is the interface of a
model of the expected recorded force of a measurement table's rows: a force model (its
``force_model``) and the plain model's constants (``base_params``) seen through the effects;
the diagnosis' back ends (:mod:`mfdesign.diagnosis.forward`) implement it.
"""

from __future__ import annotations

import abc
import dataclasses
from typing import TYPE_CHECKING, Any, ClassVar, Mapping, Sequence

import equinox as eqx
import jax
import numpy as np

from mfdesign.physics import effects as fx
from mfdesign.physics.params import SimParams

if TYPE_CHECKING:
    from mfdesign.data.measurements import Measurements

__all__ = ["FORCE_MODELS", "ForceModel", "RecordedForceModel", "recorded_force", "row_sim_params"]

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


# -- the force a rig records: the force model through the effects ---------------------------------
def row_sim_params(effects, theta, base: SimParams, rows: fx.Rows, thickness_rel=None) -> SimParams:
    """Row-wise simulator constants: every mechanical effect of ``effects`` at ``theta``
    (:func:`~mfdesign.physics.effects.apply_row_sim_params`), then, with ``thickness_rel``
    (scalar or [N]), the thickness factor times ``1 + thickness_rel`` (the calibration's
    per-membrane latent thickness; JAX)."""
    params = fx.apply_row_sim_params(effects, theta, base, rows)
    if thickness_rel is not None:
        params = dataclasses.replace(params, thickness_factor=params.thickness_factor * (1.0 + thickness_rel))
    return params


def recorded_force(
    force_model, design, rows: fx.Rows, effects, theta, base: SimParams, thickness_rel=None
) -> jax.Array:
    """Expected recorded force [N] of every row (JAX): ``force_model`` (``(design [N, 6] mm,
    h_mm [N], p_pa [N], SimParams) -> F [N]``) at the row-wise constants of
    :func:`row_sim_params` (mechanical effects on ``base``, then ``thickness_rel``), seen
    through the measurement effects at the rows' recorded ``(h, p)``
    (:func:`~mfdesign.physics.effects.apply_expected_force`).

    The one place that applies the effects to a force model: the likelihood's mean and the
    diagnosis' forward model. ``effects``: names or effects, applied in that order;
    ``theta``: ``{"effect.param": value}`` of every parameter of ``effects``."""
    params = row_sim_params(effects, theta, base, rows, thickness_rel)
    return fx.apply_expected_force(effects, theta, lambda h, p: force_model(design, h, p, params), rows)


class RecordedForceModel(eqx.Module):
    """Abstract model of the expected recorded force of a measurement table's rows (module doc).

    A :class:`ForceModel` answers for (design, h, p, simulator constants); a recorded-force
    model answers for the rows of a table through the effects (mechanics per row, then the
    measurement chain: :func:`recorded_force`), built on a force model (``force_model``)
    and the plain model's constants (``base_params``). The diagnosis' forward model
    (:class:`~mfdesign.diagnosis.forward.ForwardModel`: the exact planes, the emulator, the
    stand-in) implements it; its screen, refit and check call nothing else.
    """

    force_model: eqx.AbstractVar[ForceModel]
    base_params: eqx.AbstractVar[SimParams]

    @abc.abstractmethod
    def expected_force(
        self,
        meas: "Measurements",
        effects: Sequence[str | fx.Effect] = (),
        theta: Mapping[str, Any] | None = None,
        rows: np.ndarray | None = None,
    ) -> np.ndarray:
        """Expected recorded force [N] per row of ``meas`` (or of its rows ``rows``) with
        ``effects`` at ``theta`` (``{"effect.param": value}``; parameters not given neutral);
        NaN where the model has no number."""

    @abc.abstractmethod
    def outside_model(
        self,
        meas: "Measurements",
        effects: Sequence[str | fx.Effect] = (),
        theta: Mapping[str, Any] | None = None,
        rows: np.ndarray | None = None,
    ) -> np.ndarray:
        """Rows [N] bool of ``meas`` (or of its rows ``rows``) outside the physical model
        (``Status.OUTSIDE_MODEL``) with ``effects`` at ``theta``."""

    @abc.abstractmethod
    def jacobian(
        self,
        meas: "Measurements",
        free: Sequence[str],
        effects: Sequence[str | fx.Effect] = (),
        theta: Mapping[str, Any] | None = None,
        rows: np.ndarray | None = None,
        pad_cols: int = 0,
    ) -> np.ndarray:
        """``dF/dtheta`` [N per unit, rows x len(free)] of :meth:`expected_force` with respect
        to the parameters ``free`` (``"effect.param"``) at ``theta``."""

    def predict(self, meas: "Measurements") -> np.ndarray:
        """The plain model (no effects): ``expected_force(meas)`` [N] per row."""
        return self.expected_force(meas)
