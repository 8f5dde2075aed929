"""What acquisition and design optimisation consume: paired members per fidelity on a
height x pressure grid (:class:`Predictor`), and the concrete predictors.

Member ``m`` of every fidelity is the same hypothesis, so a fidelity's spread is what a
run at that fidelity can inform. Everything here is traceable (jit, vmap and grad in the
design), because acquisition differentiates through it.
"""

from __future__ import annotations

import dataclasses
from typing import Any, Callable, Mapping, Protocol, runtime_checkable

import mfdesign._x64  # noqa: F401  (float64 before any JAX array)
import equinox as eqx
import jax
import jax.numpy as jnp
import numpy as np

__all__ = ["EnsemblePredictor", "FunctionPredictor", "Grid", "Predictor", "SplitPredictor"]


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
@runtime_checkable
class Predictor(Protocol):
    """What acquisition consumes: paired members per fidelity on a grid.

    ``grid_members(fidelity, design [B, 6], grid) -> [M, B, G]`` forces in N (design rows
    ``[t, c, r1, w1, r2, w2]`` mm, NaN for no ring; ``G = grid.size``, heights outer).
    Must be traceable (jit/vmap/grad in ``design``); member ``m`` of every fidelity is the
    same hypothesis.
    """

    fidelities: tuple[str, ...]

    def grid_members(self, fidelity: str, design, grid: Grid) -> jax.Array: ...


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


class EnsemblePredictor(eqx.Module):
    """The rig-only paper case: the members of one RPN :class:`~mfdesign.models.ensemble.Ensemble`."""

    ensemble: Any
    fidelities: tuple[str, ...] = eqx.field(static=True, default=("rig",))

    def grid_members(self, fidelity, design, grid):
        _check_fidelity(self, fidelity)
        return _ensemble_grid(self.ensemble, design, grid)


class SplitPredictor(eqx.Module):
    """Simulator surrogate + discrepancy: ``rig_m = sim_m + disc_m``, ``sim_m = sim_m``.

    ``sim``: an ensemble fitted to simulator output (its spread is what simulator runs
    inform); ``discrepancy``: an ensemble fitted to rig minus simulator surrogate (only rig
    runs inform it). Both need the same number of members (member m pairs with member m).
    """

    sim: Any
    discrepancy: Any
    fidelities: tuple[str, ...] = eqx.field(static=True, default=("rig", "sim"))

    def __check_init__(self):
        if self.sim.n_members != self.discrepancy.n_members:
            raise ValueError(
                f"sim ({self.sim.n_members}) and discrepancy ({self.discrepancy.n_members}) "
                "ensembles need the same number of members"
            )

    def grid_members(self, fidelity, design, grid):
        _check_fidelity(self, fidelity)
        s = _ensemble_grid(self.sim, design, grid)
        return s if fidelity == "sim" else s + _ensemble_grid(self.discrepancy, design, grid)


class FunctionPredictor(eqx.Module):
    """Any pointwise model: ``functions[fidelity](design [N, 6], h_mm [N], p_pa [N]) -> [M, N]``."""

    functions: tuple[tuple[str, Callable], ...] = eqx.field(static=True)
    fidelities: tuple[str, ...] = eqx.field(static=True)

    def __init__(self, functions: Mapping[str, Callable]):
        if not functions:
            raise ValueError("FunctionPredictor needs at least one fidelity")
        self.functions = tuple(dict(functions).items())  # hashable: jit caches on it
        self.fidelities = tuple(dict(functions))

    def grid_members(self, fidelity, design, grid):
        _check_fidelity(self, fidelity)
        h, p = (jnp.asarray(a) for a in grid.points())
        b, g = design.shape[0], h.shape[0]
        rows = jnp.repeat(design, g, axis=0)
        out = dict(self.functions)[fidelity](rows, jnp.tile(h, b), jnp.tile(p, b))
        return out.reshape(out.shape[0], b, g)


def _check_fidelity(predictor, fidelity):
    if fidelity not in predictor.fidelities:
        raise ValueError(f"fidelity {fidelity!r} not offered by this predictor; allowed: {list(predictor.fidelities)}")
