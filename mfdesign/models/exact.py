"""The exact force model: the simulator itself, on the measured designs, at simulator accuracy.

``F = ExactForceModel(...)(design [N, 6] mm, h_mm [N], p_pa [N], SimParams) -> [N] N`` reads
simulator planes (:mod:`mfdesign.physics.planes`) of the designs it was built for:

    F = s max(0, G(h, p / s; c)),   s = (mu / mu0) tf

with ``G`` the signed reference plane interpolated by cubic convolution (Keys 1981: four
nodes per axis, C1, exact for quadratics) in height, reduced pressure and every lattice
coordinate ``c`` (``log J_m``, ``log rho`` for ringed membranes, and the mechanical
effects' coordinates). Two kinds of lattice axes:

* ``tensor`` axes form a full product lattice (calibration: ``jm`` and ``ring``, which
  interact strongly);
* ``additive`` axes each cross only the reference node: ``G = G_T + sum_d [G_d(c_d) -
  G_d(0)]``, exact for one such effect at a time and first order in their cross terms
  (diagnosis tests the effects one by one; a second-round pair is the one place this
  approximates, and ``experiments/bench_exact.py`` measures it).

Where an interpolation stencil meets an unconverged node the axis falls back to linear
interpolation between its two nearest nodes, and to NaN where those are missing too.
A plane node whose force is above ``P pi R^2`` (the simulator's ``Status.OUTSIDE_MODEL``:
the membrane leaves the clamp below the clamp plane; in reduced units the bound is the
same, ``s G <= p pi R^2`` iff ``G <= P pi R^2``) is kept in the signed plane (its
interpolation needs a smooth surface), but a row whose stencil holds such a node with a
nonzero weight is outside the physical model: NaN when strict (:meth:`ExactForceModel.outside_model`
says which rows; the likelihood and diagnosis' residuals leave them out and count them).
queries outside the lattice, above the grid's top, for a design the model was not built
for, or with a simulator constant the model does not vary are NaN (``outside="nan"``) or
held at the lattice edge (``outside="clamp"``, for optimisers that must not see NaN:
check the optimum with :meth:`ExactForceModel.covers`). It never extrapolates silently.

:func:`build_exact` makes one; :meth:`ExactForceModel.covering` returns one whose lattice
covers a box of coordinates (the planes it adds are solved and cached; the rest are reused).
"""

from __future__ import annotations

import dataclasses
import functools
import itertools
import logging
import math
from typing import Mapping, Sequence

import equinox as eqx
import jax
import jax.numpy as jnp
import numpy as np

from mfdesign._padding import bucketed_size, pad_last, padded_size
from mfdesign._x64 import enable_x64
from mfdesign.design import Membrane
from mfdesign.models.force import ForceModel
from mfdesign.physics import planes as pl
from mfdesign.physics.params import SimParams

# a growing lattice can solve planes for an hour: one line per growth says where it goes
log = logging.getLogger("mfdesign.models.exact")

__all__ = ["ExactForceModel", "LatticeAxis", "build_exact"]

_TOL = 1e-9


class LatticeAxis(eqx.Module):
    """One axis of the model's lattice: nodes ``k0 .. k0 + n - 1`` of :data:`~mfdesign.physics.planes.AXES`[name]."""

    name: str = eqx.field(static=True)
    k0: int = eqx.field(static=True)
    n: int = eqx.field(static=True)

    @property
    def axis(self) -> pl.Axis:
        return pl.AXES[self.name]

    @property
    def lo(self) -> float:
        return self.k0 * self.axis.step

    @property
    def hi(self) -> float:
        return (self.k0 + self.n - 1) * self.axis.step


def _keys_weights(t):
    """Cubic convolution weights (Keys 1981, a = -1/2) of nodes -1, 0, 1, 2 at ``t`` in [0, 1]."""
    t2, t3 = t * t, t * t * t
    return jnp.stack(
        [0.5 * (-t3 + 2 * t2 - t), 0.5 * (3 * t3 - 5 * t2 + 2), 0.5 * (-3 * t3 + 4 * t2 + t), 0.5 * (t3 - t2)], axis=-1
    )


def _contract(v, t, axis: int):
    """Interpolate the 4 nodes of ``v`` along ``axis`` at fraction ``t`` (broadcast against
    ``v`` without that axis): cubic where all four are finite, linear where the middle
    two are, NaN otherwise."""
    v = jnp.moveaxis(v, axis, -1)
    fin = jnp.isfinite(v)
    z = jnp.where(fin, v, 0.0)
    t = jnp.asarray(t)[..., None]
    w = _keys_weights(t[..., 0])
    cubic = jnp.sum(w * z, axis=-1)
    linear = (1.0 - t[..., 0]) * z[..., 1] + t[..., 0] * z[..., 2]
    return jnp.where(jnp.all(fin, -1), cubic, jnp.where(fin[..., 1] & fin[..., 2], linear, jnp.nan))


def _touch(v, t, axis: int):
    """Whether a node of the 4-node stencil of boolean ``v`` along ``axis`` that carries a
    nonzero cubic weight at fraction ``t`` is set (the mask counterpart of :func:`_contract`)."""
    v = jnp.moveaxis(v, axis, -1)
    w = _keys_weights(jnp.asarray(t))
    return jnp.any(v & (w != 0), axis=-1)


class _Weights(eqx.Module):
    """Full-axis weights of a D-axis lattice stencil, as outer products [L_1, ..., L_D]."""

    cubic: jax.Array  # Keys cubic weights on the 4^D stencil, 0 elsewhere
    linear: jax.Array  # multilinear weights on the 2^D middle nodes, 0 elsewhere


def _lattice_weights(pos, lengths) -> _Weights:
    """Weights over whole ghost-padded lattice axes of lengths ``lengths`` for the stencil
    cells ``pos`` (:func:`_position` per axis: start ``i``, fraction ``t``). Per axis the
    same rule as :func:`_contract`; over several axes a tensor product (cubic where every
    node of the 4^D stencil is finite, else multilinear where the 2^D middle nodes are:
    :meth:`ExactForceModel._contract_planes`; the two agree with :func:`_contract` applied
    axis by axis wherever the stencil is complete; near an unconverged node this rule does
    not depend on the order of the axes)."""
    vecs = []
    for (i, t, _), n in zip(pos, lengths):
        k = jnp.arange(n) - i  # stencil slot of each node
        inside = (k >= 0) & (k < 4)
        wc = jnp.where(inside, _keys_weights(t)[jnp.clip(k, 0, 3)], 0.0)
        wl = jnp.where(k == 1, 1.0 - t, jnp.where(k == 2, t, 0.0))
        vecs.append((wc, wl))

    def outer(j):
        out = vecs[0][j]
        for v in vecs[1:]:
            out = out[..., None] * v[j]
        return out

    return _Weights(outer(0), outer(1))


class _Tables(eqx.Module):
    """A lattice array ``[M, L_1, ..., L_D, nh, np]`` (ghost-padded) laid out for contracting
    whole planes at scalar lattice coordinates (:meth:`ExactForceModel._contract_planes`: a
    sampler's walkers, vmapped): the values lattice-first (one matrix product per walker),
    and summed-area tables (Crow 1984) of the unsolved nodes and of the nodes outside the
    physical model, so that whether a walker's stencil holds one is 2^D lookups of a plane
    each instead of a product over the whole lattice. Three such products, each after a
    transpose of the whole array, took 5 of the ~8 ms a 16-walker log-posterior call spent
    in the demo's planes (issue 40). Made once per lattice (:func:`_assemble`)."""

    values: jax.Array  # [prod(L), M * nh * np]: unsolved nodes 0
    unsolved: jax.Array  # [L_1 + 1, ..., L_D + 1, M * nh * np] int32: summed-area table
    # whether any node is unsolved: only then does a contraction need the multilinear
    # fallback and the stencil checks (a second product as large as the first: 3 of the
    # ~11 ms a 16-walker log-posterior call spent on a round of 22 membranes, issue 40)
    holed: jax.Array  # [] bool
    outside: jax.Array | None  # the same of the outside-model nodes; None: no node is outside
    plane: tuple = eqx.field(static=True)  # (M, nh, np)


def _summed_area(mask, D: int):
    """Counts of set nodes of ``mask`` [L_1, ..., L_D, P] over every box [0, i_1) x ... x [0, i_D): [L_1 + 1, ..., P]."""
    s = jnp.asarray(mask).astype(jnp.int32)
    for k in range(D):
        s = jnp.pad(jnp.cumsum(s, axis=k), [(1, 0) if i == k else (0, 0) for i in range(s.ndim)])
    return s


@functools.partial(jax.jit, static_argnums=2)
def _tables(arr, out, D: int) -> _Tables:
    """:class:`_Tables` of a lattice array ``arr`` and its outside-model mask ``out`` (or None)
    (one program per lattice shape: op by op, each shape compiled a dozen small ones)."""
    lat = jnp.moveaxis(jnp.asarray(arr), 0, D)  # [L_1, ..., L_D, M, nh, np]
    plane = tuple(int(n) for n in lat.shape[D:])
    flat = lat.reshape(lat.shape[:D] + (-1,))
    fin = jnp.isfinite(flat)
    return _Tables(
        values=jnp.where(fin, flat, 0.0).reshape(-1, flat.shape[-1]),
        unsolved=_summed_area(~fin, D),
        holed=~jnp.all(fin),
        outside=None if out is None else _summed_area(jnp.moveaxis(jnp.asarray(out), 0, D).reshape(flat.shape), D),
        plane=plane,
    )


def _box_count(table, lo, hi):
    """Set nodes in the box ``lo[k] <= i_k <= hi[k]`` (per lattice axis) of a summed-area
    table (:func:`_summed_area`): inclusion-exclusion over the box's 2^D corners."""
    total = 0
    for corner in itertools.product((0, 1), repeat=len(lo)):
        idx = tuple(b + 1 if c else a for c, a, b in zip(corner, lo, hi))
        total = total + (-1) ** (len(lo) - sum(corner)) * table[idx]
    return total


def _outside_nodes(planes: np.ndarray, grid: pl.PlaneGrid, radii_mm: np.ndarray) -> np.ndarray:
    """Nodes of signed planes ``[M, ..., n_h, n_p]`` above the force bound ``P pi R^2`` of
    their membrane (``radii_mm`` [M], the clamp radius), as the simulator marks
    ``Status.OUTSIDE_MODEL``. The column P = 0 is extrapolated (never solved): never outside."""
    from mfdesign.physics.solve import FORCE_BOUND_RTOL
    from mfdesign.physics.status import force_bound_n

    r = np.asarray(radii_mm, float).reshape((-1,) + (1,) * (planes.ndim - 1))
    bound = force_bound_n(grid.p, 1.0) * r**2
    out = np.asarray(planes, float) > bound * (1 + FORCE_BOUND_RTOL)
    out[..., 0] = False
    return out


def _pad_edge(a: np.ndarray, axes: Sequence[int]) -> np.ndarray:
    """A ghost node at both ends of each of ``axes``, a copy of the edge node (the mask of
    :func:`_pad_ghosts`' extrapolated ghosts: the stencil holds the node next to it too)."""
    return np.pad(a, [(1, 1) if i in set(axes) else (0, 0) for i in range(a.ndim)], mode="edge")


def _position(c, lo_node: float, step: float, n: int, clamp: bool):
    """Cell index ``i`` (stencil start in the ghost-padded axis), fraction ``t`` and
    validity of coordinate ``c`` on nodes ``lo_node + k step``, k = 0 .. n - 1."""
    u = (c - lo_node) / step
    valid = (u >= -_TOL) & (u <= n - 1 + _TOL)
    u = jnp.clip(u, 0.0, n - 1.0)
    i = jnp.clip(jnp.floor(u), 0, n - 2).astype(jnp.int32)
    return i, u - i, valid | clamp


def _pad_ghosts(a: np.ndarray, axes: Sequence[int]) -> np.ndarray:
    """One ghost node at both ends of each of ``axes``, by linear extrapolation (the
    stencil of an edge cell; the interpolant is then quadratic-exact up to the edge)."""
    for ax in axes:
        a = np.moveaxis(a, ax, 0)
        a = np.concatenate([2 * a[:1] - a[1:2], a, 2 * a[-1:] - a[-2:-1]], axis=0)
        a = np.moveaxis(a, 0, ax)
    return a


def _eager_forces(model: "ExactForceModel", design, h_mm, p_pa, params: SimParams) -> jax.Array:
    """:meth:`ExactForceModel.__call__` outside a trace: one compiled program per padded row
    count (rows repeated up to :func:`~mfdesign._padding.bucketed_size`, the result sliced back; a repeated row
    changes no other row's number). Run op by op, each call compiled ~20 small XLA programs
    per new row count: 642 of a cold quick demo's 1,228 compilations (28.9 of its 190.9 s
    of XLA, issue 40; the figures, the diagnosis' residual tables, the prediction of each
    membrane). Arrays whose leading axis is not the rows' (one design for all rows, scalar
    constants) pass as they are; Python numbers become arrays, so a new value of a constant
    is data, not a new program."""
    h = np.asarray(h_mm, float)
    if h.ndim != 1:
        return _compiled_forces(model, design, h_mm, p_pa, params)
    n = h.shape[0]
    size = bucketed_size(n, minimum=8)

    def pad(a, rows_axis_ndim: int = 1):
        a = np.asarray(a, float)
        return pad_last(a, size) if n and a.ndim == rows_axis_ndim and a.shape[0] == n else a

    out = _compiled_forces(model, pad(design, 2), pad(h), pad(p_pa), jax.tree.map(pad, params))
    return out[:n] if n and out.ndim and out.shape[0] == size else out


@eqx.filter_jit
def _compiled_forces(model: "ExactForceModel", design, h_mm, p_pa, params: SimParams) -> jax.Array:
    return model._forces(design, h_mm, p_pa, params)


def _nan_match(a, b):
    """|a - b| summed over the design's 6 numbers, NaN-aware (both NaN: equal)."""
    both = jnp.isnan(a) & jnp.isnan(b)
    one = jnp.isnan(a) ^ jnp.isnan(b)
    d = jnp.where(both, 0.0, jnp.where(one, jnp.inf, jnp.abs(jnp.nan_to_num(a) - jnp.nan_to_num(b))))
    return jnp.sum(d, axis=-1)


class ExactForceModel(ForceModel):
    """Simulator planes of a set of designs behind the force-model interface (module doc)."""

    designs: jax.Array  # [M, 6] mm
    ringed: jax.Array  # [M] bool
    tensor: jax.Array  # [M, n_1 + 2, ..., n_T + 2, n_h + 2, n_p + 2]: ghost-padded planes
    additive: tuple  # per additive axis: [M, n_d + 2, n_h + 2, n_p + 2]
    base: SimParams  # reference constants of the planes (mu0, J_m0, ring, ...)
    tensor_axes: tuple = eqx.field(static=True)
    additive_axes: tuple = eqx.field(static=True)
    grid: pl.PlaneGrid = eqx.field(static=True)
    design_keys: tuple = eqx.field(static=True)
    outside: str = eqx.field(static=True, default="nan")
    cache: object = eqx.field(static=True, default=None)
    grow: str = eqx.field(static=True, default="tensor")  # where :meth:`covering` puts a new axis
    # Nodes outside the physical model (``_outside_nodes``), ghost-padded like ``tensor`` /
    # ``additive``; None / () where no node of the lattice is outside (nothing to check).
    tensor_out: object = None
    additive_out: tuple = ()
    # rows outside the physical model read +inf (whatever ``outside`` says): the likelihood's
    # and diagnosis' marker, carried through the measurement effects (:meth:`marking`)
    mark_outside: bool = eqx.field(static=True, default=False)
    # :class:`_Tables` of ``tensor`` and each ``additive`` array, made with them by
    # :func:`_assemble`; () for a model made by hand (derived on each call instead)
    tables: tuple = ()
    name = "exact"

    def __check_init__(self):
        # the tables are derived from the planes: they must be those planes' (a replaced
        # tensor_out=None is fine: no outside check reads them then)
        if self.tables:
            arrays = (self.tensor, *self.additive)
            lattice = lambda a, D: math.prod(a.shape[1 : 1 + D])  # noqa: E731
            dims = (len(self.tensor_axes),) + (1,) * len(self.additive)
            if len(self.tables) != len(arrays) or any(
                t.values.shape != (lattice(a, D), a.size // lattice(a, D)) for t, a, D in zip(self.tables, arrays, dims)
            ):
                raise ValueError("ExactForceModel: tables do not match the planes (made by _assemble only)")

    # -- interface ------------------------------------------------------------------------------
    def __call__(self, design, h_mm, p_pa, params: SimParams = SimParams()):
        if any(isinstance(leaf, jax.core.Tracer) for leaf in jax.tree.leaves((design, h_mm, p_pa, params))):
            # Under a transformation: inside a jit the program is inlined; under an eager
            # vmap or grad it is one compiled program instead of op-by-op batched primitives
            # (the diagnosis' BIC and refits vmapped the clipped model: 205 small XLA programs).
            return _compiled_forces(self, design, h_mm, p_pa, params)
        return _eager_forces(self, design, h_mm, p_pa, params)

    def _forces(self, design, h_mm, p_pa, params: SimParams):
        design = jnp.atleast_2d(jnp.asarray(design, float))
        h = jnp.asarray(h_mm, float)
        p = jnp.asarray(p_pa, float)
        n = h.shape[0]
        dist = _nan_match(design[:, None, :], self.designs[None, :, :])  # [N, M]
        m = jnp.argmin(dist, axis=1).astype(jnp.int32)
        ok = jnp.min(dist, axis=1) < 1e-6
        ringed = self.ringed[m]
        prm = jax.tree.map(lambda a: jnp.asarray(a, float), params)
        s = (prm.mu_pa / self.base.mu_pa) * prm.thickness_factor * jnp.ones(n)
        ok = ok & (s > 0) & (prm.ring_jm == self.base.ring_jm)
        P = jnp.maximum(p, 0.0) / s
        # Constants the lattice does not vary must sit at the reference (never extrapolate).
        used = {a.name for a in self.tensor_axes + self.additive_axes}
        for name, axis in pl.AXES.items():
            if name in used:
                continue
            c = axis.coord(prm, self.base) * jnp.ones(n)
            off = jnp.abs(c) > 1e-9
            ok = ok & ~(off & ringed if axis.ringed_only else off)

        # Lattice axes: a per-axis coordinate (scalar: contract whole planes once; [N]: per row).
        def coords(axes):
            out = []
            for a in axes:
                c = a.axis.coord(prm, self.base)
                if a.axis.ringed_only:
                    c = jnp.where(ringed, c, a.lo) if jnp.ndim(c) else c
                out.append(c)
            return out

        grid_part = jnp.zeros(self.tensor.shape[:1] + self.tensor.shape[-2:])
        row_parts = jnp.zeros(n)
        c_t = coords(self.tensor_axes)
        if all(jnp.ndim(c) == 0 for c in c_t):
            g, _ = self._contract_planes(0, self.tensor_axes, c_t)
            grid_part = grid_part + g
            ok = ok & self._valid_scalar(self.tensor_axes, c_t, ringed)
        else:
            row_parts = row_parts + self._rows_lattice(self.tensor, self.tensor_axes, c_t, m, h, P)
            ok = ok & self._valid_rows(self.tensor_axes, c_t, ringed)
        for d, (a, arr) in enumerate(zip(self.additive_axes, self.additive)):
            c = coords((a,))[0]
            zero = jnp.zeros_like(c)
            if jnp.ndim(c) == 0:
                g1, _ = self._contract_planes(1 + d, (a,), [c])
                g0, _ = self._contract_planes(1 + d, (a,), [zero])
                grid_part = grid_part + (g1 - g0)
            else:
                row_parts = row_parts + (
                    self._rows_lattice(arr, (a,), [c], m, h, P) - self._rows_lattice(arr, (a,), [zero], m, h, P)
                )
            ok = ok & self._valid_rows((a,), [c * jnp.ones(n)], ringed)
        g_rows = self._rows_plane(grid_part, m, h, P)
        # Beyond the grid's top there is no plane: NaN whatever ``outside`` says.
        ok = ok & (P <= self.grid.p_top_pa + _TOL) & (h <= self.grid.h_top_mm + _TOL)
        f = s * jnp.maximum(g_rows + row_parts, 0.0)
        f = jnp.where(ok, f, jnp.nan)
        if self.tensor_out is None and not self.additive_out:
            return f
        out = ok & self._outside_rows(c_t, coords, m, h, P)
        if self.mark_outside:
            return jnp.where(out, jnp.inf, f)
        return jnp.where(out, jnp.nan, f) if self.outside == "nan" else f

    def _outside_rows(self, c_t, coords, m, h, P):
        """Rows whose interpolation stencil holds a node outside the physical model (module doc)."""
        n = h.shape[0]
        grid_out = jnp.zeros(self.tensor.shape[:1] + self.tensor.shape[-2:], bool)
        row_out = jnp.zeros(n, bool)
        if self.tensor_out is not None:
            if all(jnp.ndim(c) == 0 for c in c_t):
                grid_out = grid_out | self._contract_planes(0, self.tensor_axes, c_t, touch=True)[0]
            else:
                row_out = row_out | self._rows_lattice(self.tensor_out, self.tensor_axes, c_t, m, h, P, _touch)
        for d, (a, arr) in enumerate(zip(self.additive_axes, self.additive_out)):
            c = coords((a,))[0]
            for cc in (c, jnp.zeros_like(c)):
                if jnp.ndim(cc) == 0:
                    grid_out = grid_out | self._contract_planes(1 + d, (a,), [cc], touch=True)[0]
                else:
                    row_out = row_out | self._rows_lattice(arr, (a,), [cc], m, h, P, _touch)
        return row_out | self._rows_plane(grid_out, m, h, P, _touch)

    def outside_model(self, design, h_mm, p_pa, params: SimParams = SimParams()):
        """Rows [N] bool outside the physical model (a plane node their interpolation uses
        has a force above ``p pi R^2``: ``Status.OUTSIDE_MODEL``); False where the model has
        no number for another reason (off the lattice, an unsolved node)."""
        return jnp.isposinf(self.marking(True)(design, h_mm, p_pa, params))

    def marking(self, mark: bool = True) -> "ExactForceModel":
        """The model whose rows outside the physical model read ``+inf`` (``mark``; the
        likelihood's and diagnosis' marker, which the measurement effects carry through)
        instead of NaN (strict) or the plane's number (clamp)."""
        return self if self.mark_outside == mark else dataclasses.replace(self, mark_outside=mark)

    def support(self) -> dict[str, tuple[float, float]]:
        """Hard ranges of the constants the planes can reach (for priors): J_m [1] from the
        lattice's limits, ``mu_pa`` [Pa] x thickness factor from the grid's top in reduced
        pressure (a softer or thinner membrane needs planes to higher ``p / s``)."""
        a = pl.AXES["jm"]
        s_min = 1.0 / pl.PlaneGrid.P_MARGIN
        return {
            "jm": (float(self.base.jm * math.exp(a.lo)), float(self.base.jm * math.exp(a.hi))),
            "mu_pa": (float(self.base.mu_pa * s_min / 0.7), float(self.base.mu_pa * 2.0)),
            "thickness_factor": (0.7, 1.3),
        }

    def _box(self, params: SimParams) -> dict[str, tuple[float, float]]:
        return _box_of(params, self.base, bool(np.any(np.asarray(self.ringed))), self._axis_names())

    def _axis_names(self) -> set[str]:
        return {a.name for a in self.tensor_axes + self.additive_axes}

    def covers(self, params: SimParams, margin: float = 0) -> bool:
        """Whether the lattice holds every constant in ``params`` (fields of any shape) with
        ``margin`` nodes to spare on each side (short of an axis' hard limit)."""
        box = self._box(params)
        axes = {a.name: a for a in self.tensor_axes + self.additive_axes}
        for name, (lo, hi) in box.items():
            a = axes.get(name)
            if a is None:
                return False
            step = a.axis.step
            need_lo = max(lo - margin * step, a.axis.lo)
            need_hi = min(hi + margin * step, a.axis.hi)
            if need_lo < a.lo - _TOL or need_hi > a.hi + _TOL:
                return False
        return True

    def covering(
        self, params: SimParams, progress: bool = False, margin: int = 0, edge: float | None = None
    ) -> "ExactForceModel":
        """The model grown to hold every constant in ``params`` (fields of any shape) with
        ``margin`` nodes to spare: each axis' node range is widened (never shrunk), and a
        constant the model did not vary yet becomes a new axis (:attr:`grow`). With
        ``edge``, the ``margin`` is added only on the sides where ``params`` come within
        ``edge`` nodes of the lattice's end (and on every side of a new axis): a fit that
        ran into the lattice's edge on one axis grows that axis, not every axis (a held
        constant, J_m within +-0.2 say, grew like the rest and doubled the planes). Planes
        already solved come from memory or disk. Returns ``self`` when nothing is missing."""
        if self.covers(params, margin if edge is None else edge):
            return self
        have = {a.name: (a.lo, a.hi) for a in self.tensor_axes + self.additive_axes}

        def sides(k, lo, hi):  # nodes to add below and above the box of axis k
            if edge is None or k not in have:
                return margin, margin
            st = pl.AXES[k].step
            return (
                margin if lo - edge * st < have[k][0] - _TOL else 0,
                margin if hi + edge * st > have[k][1] + _TOL else 0,
            )

        box = {}
        for k, (lo, hi) in self._box(params).items():
            below, above = sides(k, lo, hi)
            box[k] = (lo - below * pl.AXES[k].step, hi + above * pl.AXES[k].step)
        t_nodes, a_nodes = _widen(
            {a.name: (a.k0, a.k0 + a.n - 1) for a in self.tensor_axes},
            {a.name: (a.k0, a.k0 + a.n - 1) for a in self.additive_axes},
            box,
            self.grow,
        )
        # an upper bound: a ringless membrane needs no nodes of a ringed-only axis (the ring ratio)
        n_planes = len(self.design_keys) * (
            math.prod(hi - lo + 1 for lo, hi in t_nodes.values())
            + sum(max(hi, 0) - min(lo, 0) + 1 for lo, hi in a_nodes.values())
        )
        log.info(
            "exact planes: lattice grows to %s (at most %d planes of %d membranes, cached ones read)",
            ", ".join(f"{k} {lo}..{hi}" for k, (lo, hi) in {**t_nodes, **a_nodes}.items()),
            n_planes,
            len(self.design_keys),
        )
        return _assemble(
            self.design_keys, self.base, t_nodes, a_nodes, self.grid, self.outside, self.cache, progress, self.grow
        )

    def reaching(self, params: SimParams, p_max_pa: float, progress: bool = False) -> "ExactForceModel":
        """The model with its planes reaching the highest reduced pressure ``p_max_pa / s``
        [Pa] that ``params`` need (``s = (mu / mu0) tf``; returns ``self`` when they already
        do). A thinner or softer membrane (``s < 1``) needs planes above the data's
        pressures; where a fit goes there, the planes grow rather than the candidate being
        dropped as NaN. Every plane is solved again on the taller grid (a plane is one
        continuation path from 0 Pa; cached ones are reused), so the top is raised with a
        quarter to spare: one growth, not one per fit."""
        mu, tf = np.asarray(params.mu_pa, float), np.asarray(params.thickness_factor, float)
        nd = max(mu.ndim, tf.ndim)  # fields per draw [B] and per draw and row [B, N] align on the left
        mu, tf = (a.reshape(a.shape + (1,) * (nd - a.ndim)) for a in (mu, tf))
        s = (mu / float(self.base.mu_pa) * tf).ravel()
        s = s[np.isfinite(s) & (s > 0)]
        if not s.size:
            return self
        p_reduced_pa = float(p_max_pa) / float(np.min(s))
        if p_reduced_pa <= self.grid.p_top_pa + _TOL:
            return self
        grid = pl.PlaneGrid.covering(self.grid.h_top_mm, 1.25 * p_reduced_pa, p_margin=1.0)
        log.info(
            "exact planes: reduced pressure %.0f Pa is above the planes' top %.0f Pa; they grow to %.0f Pa",
            p_reduced_pa,
            self.grid.p_top_pa,
            grid.p_top_pa,
        )
        nodes = lambda axes: {a.name: (a.k0, a.k0 + a.n - 1) for a in axes}  # noqa: E731
        return _assemble(
            self.design_keys,
            self.base,
            nodes(self.tensor_axes),
            nodes(self.additive_axes),
            grid,
            self.outside,
            self.cache,
            progress,
            self.grow,
        )

    def input_ranges(self) -> dict[str, tuple[float, float]]:
        return {"height_mm": (0.0, self.grid.h_top_mm), "pressure_pa": (0.0, float("inf"))}

    def strict(self, strict: bool = True) -> "ExactForceModel":
        """``outside="nan"`` (strict: samplers reject what the lattice does not hold) or
        ``"clamp"`` (optimisers see no NaN; check the optimum with :meth:`covers`)."""
        return dataclasses.replace(self, outside="nan" if strict else "clamp")

    # -- internals ------------------------------------------------------------------------------
    def _valid_scalar(self, axes, cs, ringed):
        ok = jnp.asarray(True)
        for a, c in zip(axes, cs):
            _, _, v = _position(c, a.lo, a.axis.step, a.n, self.outside == "clamp")
            ok = ok & (v | (~ringed if a.axis.ringed_only else False))
        return ok

    def _valid_rows(self, axes, cs, ringed):
        ok = jnp.ones(ringed.shape, bool)
        for a, c in zip(axes, cs):
            _, _, v = _position(c, a.lo, a.axis.step, a.n, self.outside == "clamp")
            ok = ok & (v | (~ringed if a.axis.ringed_only else False))
        return ok

    def _contract_planes(self, k: int, axes, cs, touch: bool = False):
        """Contract the lattice axes of lattice array ``k`` (0: :attr:`tensor`, ``1 + d``: the
        additive axis ``d``) at scalar coordinates: [M, nh+2, np+2] forces, or with ``touch``
        whether a node outside the physical model carries a nonzero weight (the mask rule of
        :func:`_touch`).

        The tensor-product rule of :func:`_lattice_weights`: cubic where all ``4^D`` stencil
        nodes are finite, multilinear where the ``2^D`` middle ones are, NaN otherwise. As
        one product with full-axis weight vectors over the unbatched planes
        (:class:`_Tables`): a sampler's walkers (vmapped) then cost one [walkers, lattice
        nodes] x [lattice nodes, plane nodes] product, where slicing a 4^D stencil block per
        walker and contracting it axis by axis moved 24 MB a walker (issue 40: 773 MB a
        32-walker log-posterior call on the demo's 6 x 5 x 5 x 34 x 85 lattice, memory-bound
        at 111 ms). Which stencils hold an unsolved or outside node are box counts."""
        pos = [_position(c, a.lo, a.axis.step, a.n, self.outside == "clamp") for a, c in zip(axes, cs)]
        valid = jnp.asarray(True)
        for _, _, v in pos:
            valid = valid & v
        arr = self.tensor if k == 0 else self.additive[k - 1]
        if not pos:
            if touch:
                return self.tensor_out if k == 0 else self.additive_out[k - 1], valid
            return arr, valid
        D = len(pos)
        tab = self.tables[k] if self.tables else self._tables_of(k)
        i = [p_[0] for p_ in pos]
        if touch:
            # the nodes whose Keys weight is nonzero form a run of stencil slots per axis
            # (all four; one at a node; three or two where a weight rounds to 0 near one)
            slot = jnp.arange(4)
            nz = [_keys_weights(t) != 0 for _, t, _ in pos]
            lo = [ii + jnp.min(jnp.where(z, slot, 4)) for ii, z in zip(i, nz)]
            hi = [ii + jnp.max(jnp.where(z, slot, -1)) for ii, z in zip(i, nz)]
            return (_box_count(tab.outside, lo, hi) > 0).reshape(tab.plane), valid
        w = _lattice_weights(pos, arr.shape[1 : 1 + D])

        def holed(_):
            cubic, linear = jnp.stack([w.cubic.reshape(-1), w.linear.reshape(-1)]) @ tab.values
            stencil_solved = _box_count(tab.unsolved, i, [ii + 3 for ii in i]) == 0
            middle_solved = _box_count(tab.unsolved, [ii + 1 for ii in i], [ii + 2 for ii in i]) == 0
            return jnp.where(stencil_solved, cubic, jnp.where(middle_solved, linear, jnp.nan))

        # every node solved: the cubic product is the answer (the predicate is the planes',
        # not a walker's: under vmap the cond stays a branch, not a select of both)
        g = jax.lax.cond(tab.holed, holed, lambda _: w.cubic.reshape(-1) @ tab.values, None)
        return g.reshape(tab.plane), valid

    def _tables_of(self, k: int) -> _Tables:
        """:class:`_Tables` of lattice array ``k`` (:func:`_assemble` makes them once; a model
        made by hand has none, and they are derived on each call)."""
        if k == 0:
            return _tables(self.tensor, self.tensor_out, len(self.tensor_axes))
        out = self.additive_out[k - 1] if self.additive_out else None
        return _tables(self.additive[k - 1], out, 1)

    def _rows_plane(self, g, m, h, P, contract=_contract):
        """2-D cubic convolution of planes ``g`` [M, nh+2, np+2] at each row's (h, P)."""
        ih, th, _ = _position(jnp.maximum(h, 0.0), 0.0, pl.H_STEP_MM, g.shape[1] - 2, True)
        ip, tp, _ = _position(P, 0.0, pl.P_STEP_PA, g.shape[2] - 2, True)

        def one(mm, i, j, a, b):
            block = jax.lax.dynamic_slice(g, (mm, i, j), (1, 4, 4))[0]
            return contract(contract(block, b, axis=1), a, axis=0)

        return jax.vmap(one)(m, ih, ip, th, tp)

    def _rows_lattice(self, arr, axes, cs, m, h, P, contract=_contract):
        """Per-row interpolation over lattice axes and (h, P) (coordinates [N])."""
        n = h.shape[0]
        pos = [_position(c * jnp.ones(n), a.lo, a.axis.step, a.n, True) for a, c in zip(axes, cs)]
        ih, th, _ = _position(jnp.maximum(h, 0.0), 0.0, pl.H_STEP_MM, arr.shape[-2] - 2, True)
        ip, tp, _ = _position(P, 0.0, pl.P_STEP_PA, arr.shape[-1] - 2, True)
        D = len(axes)

        def one(mm, ii, tt, i, j, a, b):
            block = jax.lax.dynamic_slice(arr, (mm, *ii, i, j), (1,) + (4,) * (D + 2))[0]
            block = contract(contract(block, b, axis=D + 1), a, axis=D)
            for k in reversed(range(D)):
                block = contract(block, tt[k], axis=k)
            return block

        ii = [p_[0] for p_ in pos]
        tt = [p_[1] for p_ in pos]
        return jax.vmap(one)(m, ii, tt, ih, ip, th, tp)


@jax.jit
def _coords(prm: SimParams, base: SimParams) -> dict:
    """Every lattice axis' coordinate [n] at constants ``prm`` (fields [n]) around ``base``
    (scalar fields): one program per ``n``, where the axes' jnp ops on NumPy arrays ran
    eagerly and compiled one small program per op and shape (~30 a demo, issue 40)."""
    return {name: axis.coord(prm, base) for name, axis in pl.AXES.items()}


def _box_of(params: SimParams, base: SimParams, any_ringed: bool, axis_names=frozenset()) -> dict:
    """Coordinate range per axis of ``params`` (fields of any shape); axes whose coordinate
    never leaves 0 are omitted (unless in ``axis_names``), and ``ring`` without ringed designs."""
    leaves, tree = jax.tree.flatten(jax.tree.map(lambda a: np.asarray(a, float), params))
    # Fields batched as [K] (per draw) and [K, N] (per draw and row) align on the left.
    nd = max(a.ndim for a in leaves)
    flat = [a.ravel() for a in np.broadcast_arrays(*(a.reshape(a.shape + (1,) * (nd - a.ndim)) for a in leaves))]
    if not flat[0].size:
        return {}
    # padded to a power of two by repeating the last entry (ranges unchanged): few shapes
    size = padded_size(flat[0].size)
    prm = jax.tree.unflatten(tree, [pad_last(a, size) for a in flat])
    coords = _coords(prm, jax.tree.map(lambda a: np.asarray(a, float), base))
    box = {}
    for name, axis in pl.AXES.items():
        if axis.ringed_only and not any_ringed:
            continue
        c = np.asarray(coords[name], float)
        c = c[np.isfinite(c)]
        if c.size and (np.max(np.abs(c)) > 1e-9 or name in axis_names):
            box[name] = (float(np.min(c)), float(np.max(c)))
    return box


def _widen(t_nodes: dict, a_nodes: dict, box: dict, grow: str) -> tuple[dict, dict]:
    """Node ranges (axis -> (k0, k1)) widened, never shrunk, to hold ``box`` (axis ->
    coordinate range); an axis in neither becomes a new one where ``grow`` says."""
    t_nodes, a_nodes = dict(t_nodes), dict(a_nodes)
    for name, (lo, hi) in box.items():
        nodes = (
            t_nodes if name in t_nodes else a_nodes if name in a_nodes else (t_nodes if grow == "tensor" else a_nodes)
        )
        k0, k1 = pl.node_range(pl.AXES[name], lo, hi)
        old = nodes.get(name, (k0, k1))
        nodes[name] = (min(old[0], k0), max(old[1], k1))
    return t_nodes, a_nodes


def _ensure_two(axis: pl.Axis, k0: int, k1: int) -> tuple[int, int]:
    """At least two nodes (an interpolation cell), growing towards the allowed side."""
    if k1 > k0:
        return k0, k1
    if (k1 + 1) * axis.step <= axis.hi + _TOL:
        return k0, k1 + 1
    return k0 - 1, k1


def _assemble(design_keys, base, t_nodes, a_nodes, grid, outside, cache, progress, grow="tensor") -> ExactForceModel:
    designs = [Membrane.from_key(k) for k in design_keys]
    t_nodes = {k: _ensure_two(pl.AXES[k], *v) for k, v in t_nodes.items()}
    # An additive axis is a difference from its reference node, which it must hold.
    a_nodes = {k: _ensure_two(pl.AXES[k], min(v[0], 0), max(v[1], 0)) for k, v in a_nodes.items()}
    # Every plane the lattice lacks in one solve (one pool over all cores, no tail per axis).
    parts = [pl.lattice_jobs(designs, base, t_nodes)] + [
        pl.lattice_jobs(designs, base, {name: rng}) for name, rng in a_nodes.items()
    ]
    planes = pl.solve_planes([j for jobs, _ in parts for j in jobs], grid, cache=cache, progress=progress)
    stacked, at = [], 0
    for jobs, stack in parts:
        stacked.append(stack(planes[at : at + len(jobs)]))
        at += len(jobs)
    lat = len(t_nodes)
    tensor = _pad_ghosts(stacked[0], range(1, lat + 3))
    additive = [jnp.asarray(_pad_ghosts(arr, range(1, 4))) for arr in stacked[1:]]
    # nodes outside the physical model: kept only where the lattice has one (else no check)
    radii = np.array([d.outer_radius_mm for d in designs], float)
    outs = [_outside_nodes(arr, grid, radii) for arr in stacked]
    if any(o.any() for o in outs):
        log.info(
            "exact planes: %d of %d plane nodes are outside the physical model (force above p pi R^2); "
            "rows that interpolate them have no value",
            sum(int(o.sum()) for o in outs),
            sum(o.size for o in outs),
        )
        t_out = jnp.asarray(_pad_edge(outs[0], range(1, lat + 3)))
        a_out = tuple(jnp.asarray(_pad_edge(o, range(1, 4))) for o in outs[1:])
    else:
        t_out, a_out = None, ()
    tables = (_tables(tensor, t_out, lat),) + tuple(
        _tables(arr, a_out[d] if a_out else None, 1) for d, arr in enumerate(additive)
    )
    return ExactForceModel(
        designs=jnp.asarray(np.stack([d.to_array() for d in designs])),
        ringed=jnp.asarray([d.n_rings > 0 for d in designs]),
        tensor=jnp.asarray(tensor),
        additive=tuple(additive),
        base=jax.tree.map(float, base),
        tensor_axes=tuple(LatticeAxis(k, v[0], v[1] - v[0] + 1) for k, v in t_nodes.items()),
        additive_axes=tuple(LatticeAxis(k, v[0], v[1] - v[0] + 1) for k, v in a_nodes.items()),
        grid=grid,
        design_keys=tuple(design_keys),
        outside=outside,
        cache=cache,
        grow=grow,
        tensor_out=t_out,
        additive_out=a_out,
        tables=tables,
    )


def build_exact(
    design_keys: Sequence[str],
    *,
    h_max_mm: float = 80.0,
    p_max_pa: float = 10_000.0,
    tensor: Mapping[str, tuple[float, float]] | None = None,
    additive: Mapping[str, tuple[float, float]] | None = None,
    base: SimParams = SimParams(),
    outside: str = "nan",
    cache=None,
    progress: bool = False,
    grow: str = "tensor",
    also: SimParams | None = None,
) -> ExactForceModel:
    """An :class:`ExactForceModel` of the membranes ``design_keys``.

    Arguments:
        design_keys: the measured designs (``"[t, c, r1, w1, r2, w2]"`` keys).
        h_max_mm: the highest plate height [mm] the rows need.
        p_max_pa: the highest gauge pressure [Pa] the rows need (the planes reach 1.35 x it
            in reduced pressure, room for softer or thinner membranes).
        tensor: lattice axes of the full product (axis name -> coordinate range), e.g.
            ``{"jm": (-0.1, 0.1), "ring": (-0.2, 0.2)}`` for calibration.
        additive: lattice axes that each cross only the reference node (diagnosis' effects).
        base: the reference constants (mu0, J_m0, ring constants); ``tf`` is ignored.
        outside: ``"nan"`` (default) or ``"clamp"`` for queries outside the lattice.
        cache: plane cache folder (default :func:`mfdesign.physics.planes.cache_dir`), or False.
        progress: a progress bar over the planes to solve.
        grow: where :meth:`ExactForceModel.covering` puts an axis the model did not vary yet:
            ``"tensor"`` (calibration: exact cross terms) or ``"additive"`` (diagnosis: one
            effect at a time, few planes).
        also: constants (fields of any shape) to hold from the start, on new axes placed as
            ``grow`` says: their planes are solved in one pool with the reference planes
            (a later :meth:`ExactForceModel.covering` would solve them after, one more wait).

    Axes: see :data:`mfdesign.physics.planes.AXES` (``jm``, ``ring``, ``gradient``,
    ``prestretch``, ``offset``). Coordinate 0 is the reference.
    """
    enable_x64()  # float64 physics: mfdesign._x64
    if outside not in ("nan", "clamp"):
        raise ValueError(f"outside must be 'nan' or 'clamp', got {outside!r}")
    bad = [k for k in list(tensor or {}) + list(additive or {}) if k not in pl.AXES]
    if bad:
        raise ValueError(f"unknown lattice axes {bad}; known: {list(pl.AXES)}")
    grid = pl.PlaneGrid.covering(h_max_mm, p_max_pa)
    t_nodes = {k: pl.node_range(pl.AXES[k], *v) for k, v in (tensor or {}).items()}
    a_nodes = {k: pl.node_range(pl.AXES[k], *v) for k, v in (additive or {}).items()}
    if grow not in ("tensor", "additive"):
        raise ValueError(f"grow must be 'tensor' or 'additive', got {grow!r}")
    if also is not None:
        ringed = any(Membrane.from_key(k).n_rings > 0 for k in design_keys)
        t_nodes, a_nodes = _widen(t_nodes, a_nodes, _box_of(also, base, ringed), grow)
    return _assemble(tuple(design_keys), base, t_nodes, a_nodes, grid, outside, cache, progress, grow)
