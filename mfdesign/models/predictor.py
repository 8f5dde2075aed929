"""The one predictor interface (:class:`AbstractPredictor`) that acquisition, design
optimisation and cross-validation consume, and its concrete predictors.

A predictor offers one or more fidelities (``rig``: the real rig, ``sim``: the simulator)
and, per fidelity, ``M`` paired members: member ``m`` of every fidelity is the same
hypothesis, so a fidelity's spread is what a run at that fidelity can inform. Everything
here is traceable (jit, vmap and grad in the design), because acquisition and design
optimisation differentiate through it.
"""

from __future__ import annotations

import abc
import dataclasses
from typing import Any, Callable, Mapping

import equinox as eqx
import jax
import jax.numpy as jnp
import numpy as np

__all__ = [
    "RIG",
    "AbstractPredictor",
    "EnsemblePredictor",
    "FunctionPredictor",
    "Grid",
    "SimulatorPredictor",
    "SplitPredictor",
]

# The real rig's fidelity: what measurements are, hence what cross-validation scores and
# what a membrane is designed for.
RIG = "rig"


# --------------------------------------------------------------------------- grid
@dataclasses.dataclass(frozen=True)
class Grid:
    """Height x pressure grid (mm, Pa) on which members are compared.

    Default: plate heights 0-70 mm every 10 mm (the rig's set heights) x pressures
    1-8 kPa every 1 kPa: 64 points.
    """

    h_mm: tuple[float, ...] = tuple(float(h) for h in range(0, 71, 10))
    p_pa: tuple[float, ...] = tuple(float(p) for p in range(1000, 8001, 1000))

    def __post_init__(self):
        for name in ("h_mm", "p_pa"):
            v = np.asarray(getattr(self, name), dtype=float)
            if v.ndim != 1 or v.size == 0:
                raise ValueError(f"Grid.{name} must be a non-empty list of numbers, got {getattr(self, name)!r}")
            if not np.all(np.isfinite(v)) or np.any(v < 0):
                raise ValueError(f"Grid.{name} must be finite and >= 0, got {v.tolist()}")
            object.__setattr__(self, name, tuple(float(x) for x in v))

    @property
    def size(self) -> int:
        return len(self.h_mm) * len(self.p_pa)

    def points(self) -> tuple[np.ndarray, np.ndarray]:
        """Flattened (h [G], p [G]), heights outer."""
        h, p = np.meshgrid(self.h_mm, self.p_pa, indexing="ij")
        return h.ravel(), p.ravel()


# --------------------------------------------------------------------------- predictors
class AbstractPredictor(eqx.Module):
    """Paired members per fidelity: what acquisition, design optimisation and CV consume.

    ``members(fidelity, design [N, 6], h_mm [N], p_pa [N]) -> [M, N]`` forces in N at
    points (design rows ``[t, c, r1, w1, r2, w2]`` mm, NaN for no ring; heights mm;
    pressures Pa). Must be traceable in every numeric input; member ``m`` of every
    fidelity is the same hypothesis. ``fidelities``: the fidelities offered (a property of
    the kind of predictor, not a constructor argument).

    :meth:`grid_members` (every design on a height x pressure grid) is built on
    :meth:`members`; a concrete predictor overrides it where a grid has a faster path.
    """

    @property
    @abc.abstractmethod
    def fidelities(self) -> tuple[str, ...]:
        """The fidelities offered, e.g. ``("rig", "sim")``."""

    @abc.abstractmethod
    def members(self, fidelity: str, design, h_mm, p_pa) -> jax.Array:
        """Members [M, N] (N) at design rows [N, 6] mm, heights [N] mm, pressures [N] Pa."""

    def grid_members(self, fidelity: str, design, grid: Grid) -> jax.Array:
        """Members [M, B, G] (N) of designs [B, 6] mm on ``grid`` (``G = grid.size``, heights outer)."""
        h, p = (jnp.asarray(a) for a in grid.points())
        b, g = design.shape[0], h.shape[0]
        rows = jnp.repeat(design, g, axis=0)
        out = self.members(fidelity, rows, jnp.tile(h, b), jnp.tile(p, b))
        return out.reshape(out.shape[0], b, g)

    def check_fidelity(self, fidelity: str) -> None:
        """``ValueError`` naming the offered fidelities when ``fidelity`` is not one of them."""
        if fidelity not in self.fidelities:
            raise ValueError(f"fidelity {fidelity!r} not offered by this predictor; allowed: {list(self.fidelities)}")


def _ensemble_grid(ens, design, grid: Grid):
    """RPN ensemble members [M, B, G] on a grid. ``vmap`` over pressure is innermost and
    the latent network does not depend on p, so it runs once per (member, design, height):
    the head is polynomial in p."""
    h = jnp.asarray(grid.h_mm)
    p = jnp.asarray(grid.p_pa)
    one = lambda net, pri, x, hh, pp: ens._member(net, pri, x, hh, pp)  # noqa: E731
    f = jax.vmap(one, in_axes=(None, None, None, None, 0))  # p
    f = jax.vmap(f, in_axes=(None, None, None, 0, None))  # h
    f = jax.vmap(f, in_axes=(None, None, 0, None, None))  # designs
    f = eqx.filter_vmap(f, in_axes=(eqx.if_array(0), eqx.if_array(0), None, None, None))  # members
    out = f(ens.trainable, ens.prior, design, h, p)
    return out.reshape(out.shape[0], out.shape[1], -1).astype(jnp.result_type(float))


class EnsemblePredictor(AbstractPredictor):
    """The rig-only paper case: the members of one RPN :class:`~mfdesign.models.ensemble.Ensemble`
    (what :meth:`~mfdesign.models.ensemble.EnsembleConfig.fit` returns)."""

    ensemble: Any

    @property
    def fidelities(self):
        return (RIG,)

    def members(self, fidelity, design, h_mm, p_pa):
        self.check_fidelity(fidelity)
        return self.ensemble.predict(design, h_mm, p_pa)

    def grid_members(self, fidelity, design, grid):
        self.check_fidelity(fidelity)
        return _ensemble_grid(self.ensemble, design, grid)


class SplitPredictor(AbstractPredictor):
    """Simulator surrogate + discrepancy: ``rig_m = sim_m + disc_m``, ``sim_m = sim_m``.

    ``sim``: an ensemble fitted to simulator output (its spread is what simulator runs
    inform); ``discrepancy``: an ensemble fitted to rig minus simulator surrogate (only rig
    runs inform it). Both need the same number of members (member m pairs with member m).
    """

    sim: Any
    discrepancy: Any

    @property
    def fidelities(self):
        return (RIG, "sim")

    def __check_init__(self):
        if self.sim.n_members != self.discrepancy.n_members:
            raise ValueError(
                f"sim ({self.sim.n_members}) and discrepancy ({self.discrepancy.n_members}) "
                "ensembles need the same number of members"
            )

    def members(self, fidelity, design, h_mm, p_pa):
        self.check_fidelity(fidelity)
        s = self.sim.predict(design, h_mm, p_pa)
        return s if fidelity == "sim" else s + self.discrepancy.predict(design, h_mm, p_pa)

    def grid_members(self, fidelity, design, grid):
        self.check_fidelity(fidelity)
        s = _ensemble_grid(self.sim, design, grid)
        return s if fidelity == "sim" else s + _ensemble_grid(self.discrepancy, design, grid)


class FunctionPredictor(AbstractPredictor):
    """Any pointwise model: ``functions[fidelity](design [N, 6], h_mm [N], p_pa [N]) -> [M, N]``."""

    functions: tuple[tuple[str, Callable], ...] = eqx.field(static=True)

    def __init__(self, functions: Mapping[str, Callable]):
        if not functions:
            raise ValueError("FunctionPredictor needs at least one fidelity")
        self.functions = tuple(dict(functions).items())  # hashable: jit caches on it

    @property
    def fidelities(self):
        return tuple(name for name, _ in self.functions)

    def members(self, fidelity, design, h_mm, p_pa):
        self.check_fidelity(fidelity)
        return dict(self.functions)[fidelity](design, h_mm, p_pa)


class SimulatorPredictor(AbstractPredictor):
    """The simulator itself at constants ``params``, one member, for both fidelities (the
    simulator at calibrated constants standing for the rig): for a few search steps on the
    simulator near a model's optimum (:func:`mfdesign.optimization.simulator_refine`).

    Each point is solved by its own continuation
    (:func:`~mfdesign.physics.solve.point_force`): seconds per batch, so it is for local
    refinement, not for a global search. Traceable in the design; differentiate it in
    forward mode (``jax.jacfwd``: the ODE solves carry tangents forward, not backward)."""

    params: Any  # SimParams with array fields (physics.solve.traced_params)
    path_steps: int = eqx.field(static=True)

    def __init__(self, params=None):
        from mfdesign.physics.params import SimParams
        from mfdesign.physics.solve import PATH_STEPS, STIFF_RING_PATH_REFINE, fine_path, traced_params

        params = SimParams() if params is None else params
        self.path_steps = PATH_STEPS * (STIFF_RING_PATH_REFINE if fine_path(params) else 1)
        self.params = traced_params(params)

    @property
    def fidelities(self):
        return (RIG, "sim")

    def members(self, fidelity, design, h_mm, p_pa):
        from mfdesign.physics.solve import point_force

        self.check_fidelity(fidelity)
        one = lambda d, h, p: point_force(d, h, p, self.params, self.path_steps)  # noqa: E731
        return jax.vmap(one)(design, h_mm, p_pa)[None]
