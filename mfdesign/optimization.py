"""Membrane design for a lift task (Campbell et al. 2025, "Active Learning Design: Modeling
Force Output for Axisymmetric Soft Pneumatic Actuators", section on design optimisation).

Two problems over the unit-cube decoding of :class:`~mfdesign.design.DesignSpace` (every
point of ``[0, 1]^(2 + 2 n_rings)`` is a valid membrane), for 0, 1 and 2 rings:

**Height maximisation.** Targets ``(F_j, p_j)`` (N, Pa): a mass ``F_j`` lifted at chamber
pressure ``p_j``. The lift height ``h_j(x)`` of design ``x`` is the height where the
predicted mean force, falling with height, first drops to the load (quasi-static
inflation from ``h = 0``: the branch :func:`mfdesign.physics.solve.height_at` reports).
It is found on a height grid by the first crossing of the piecewise-linear interpolant,
which is differentiable in the forces, hence in ``x``. The loss (to minimise) is::

    L(x) = -k_h smin_tau(h(x)) / h_s + k_f mean_j (max(F_j - F(x, 0, p_j), 0) / F_s)^2

    smin_tau(h) = -tau log sum_j exp(-h_j / tau)      (LogSumExp smooth minimum, mm)

``smin_tau <= min_j h_j <= smin_tau + tau log K``, and it tends to the minimum as
``tau -> 0``. The constants are the authors' (``design_optimization.py`` and
``Membrane_Optimization.ipynb`` of gmcampbell/SPA_Design): ``k_h = 1``, ``k_f = k_p =
5000``, ``h_s = 70 mm``, ``F_s = 60 N``, LogSumExp scale ``h_s / 15`` on ``h / h_s``, i.e.
``tau = 15 mm``. The authors optimise the heights and pressures as free variables with
penalties on the force and pressure mismatch; here the heights are eliminated exactly by
the inversion and the pressures are the targets, so the pressure penalty is zero and the
force penalty acts only where a target cannot be lifted at all (``F(x, 0, p_j) < F_j``).

**Trajectory targeting.** Way-points ``(F_i, p_i, h_i)`` with weights ``w_i``: the model
pressure ``p^_i(x)`` at which the mean force at height ``h_i`` first reaches ``F_i`` (a
grid inversion in pressure, as in :func:`mfdesign.models.trajectory.model_pressure`)::

    L(x) = k_p sum_i w_i ((p^_i - p_i) / p_max)^2 / sum_i w_i
           + k_f mean_i (max(F_i - F(x, h_i, p_hi), 0) / F_t)^2

with ``p_max = 10 kPa`` (the paper's scaled trajectory error: ``sqrt`` of the first term
over ``k_p`` is :func:`mfdesign.models.trajectory.trajectory_errors`'s ``e_p``), ``F_t =
150 N`` (the authors' force scale for trajectories) and ``p_hi`` the top of the pressure
grid (an unreachable way-point gets ``p_hi`` and the force penalty).

**Optimiser.** ``n_starts`` points of a scrambled Sobol sequence in the unit cube (:func:`sobol_starts`), all scored at once;
the best ``n_refine`` (default: all) are refined by projected Adam (Kingma & Ba 2015;
``optax.adam`` followed by ``optax.projections.projection_box`` onto ``[0, 1]^d``), every
start under ``jax.vmap`` inside one ``lax.scan``, chunked by ``jax.lax.map(batch_size=)``
to bound memory. Each start keeps the best point it visited. :func:`optimize` searches
every ring count in the padded 6-d cube of :meth:`~mfdesign.design.DesignSpace.decode_any`
with the ring count as data, so the three ring counts share one compilation of the
screen and one of the refinement (they were three each). Measured once each, nothing else
running, height maximisation on the paper-design ensemble, 2,500 starts, best 64 refined,
rings 0-2: first call 61.8 s -> 55.3 s, second call 39.8 s -> 31.1 s.

The model is any :class:`~mfdesign.models.predictor.AbstractPredictor` offering the
``rig`` fidelity: ``members("rig", design [N, 6], h_mm [N], p_pa [N]) -> [M, N]`` forces
(N), traceable in all inputs. The optimiser uses the member mean; the member spread is
reported as the uncertainty of the winner's lift heights and trajectories.
"""

from __future__ import annotations

import abc
import dataclasses
import math
import time
from typing import Callable, Sequence

import equinox as eqx
import jax
import jax.numpy as jnp
import numpy as np
import optax

from mfdesign._x64 import enable_x64
from mfdesign.models.trajectory import first_crossing
from mfdesign.design import DesignSpace, Membrane
from mfdesign.models.predictor import RIG, AbstractPredictor
from mfdesign.models.trajectory import P_MAX_PA
from mfdesign.rig.config import RigConfig
from mfdesign.units import G_M_S2
from mfdesign.physics._traces import stored_jit

__all__ = [
    "MASSES_N",
    "TARGET_SETS",
    "Weights",
    "PAPER_WEIGHTS",
    "HeightTargets",
    "Waypoints",
    "smooth_min",
    "first_crossing",
    "lift_heights",
    "model_pressures",
    "DesignLoss",
    "HeightLoss",
    "height_loss",
    "TrajectoryLoss",
    "trajectory_loss",
    "multistart",
    "Result",
    "optimize",
    "lift_curves",
    "pressure_curves",
    "check_with_simulator",
    "limit_flags",
    "RIG_HEIGHT_MAX_MM",
    "RIG_PRESSURE_MAX_PA",
]

MASSES_N = (1.5 * G_M_S2, 2.5 * G_M_S2, 4.0 * G_M_S2)  # the paper's three masses: 14.715, 24.525, 39.24 N


# --------------------------------------------------------------------------- problems
@dataclasses.dataclass(frozen=True)
class Weights:
    """Penalty weights and scales (dimensionless weights; scales in N, mm, Pa).

    Defaults: the authors' values (module docstring). ``temperature_mm`` is the
    LogSumExp temperature ``tau`` of the smooth minimum of the lift heights.
    """

    k_force: float = 5000.0
    k_pressure: float = 5000.0
    k_height: float = 1.0
    force_scale_n: float = 60.0  # height maximisation (authors: f_max = 60)
    trajectory_force_scale_n: float = 150.0  # trajectory targeting (authors: f_max = 150)
    height_scale_mm: float = 70.0  # authors: h_max = 70
    pressure_scale_pa: float = P_MAX_PA  # the paper's p_max = 10 kPa
    temperature_mm: float = 15.0  # authors: scale h_max / 15 on h / h_max

    def __post_init__(self):
        for f in dataclasses.fields(self):
            v = getattr(self, f.name)
            if not (isinstance(v, (int, float)) and math.isfinite(v) and v >= 0):
                raise ValueError(f"Weights.{f.name} must be a finite number >= 0, got {v!r}")
        for name in (
            "force_scale_n",
            "trajectory_force_scale_n",
            "height_scale_mm",
            "pressure_scale_pa",
            "temperature_mm",
        ):
            if getattr(self, name) <= 0:
                raise ValueError(f"Weights.{name} must be > 0, got {getattr(self, name)!r}")


PAPER_WEIGHTS = Weights()


def _vector(name: str, values, n: int | None = None, positive: bool = False) -> tuple[float, ...]:
    try:
        arr = np.asarray(values, dtype=float).reshape(-1)
    except (TypeError, ValueError):
        raise ValueError(f"{name} must be a list of numbers, got {values!r}") from None
    if arr.size == 0 or (n is not None and arr.size != n):
        raise ValueError(f"{name} needs {n if n else 'at least one'} value(s), got {arr.size}")
    if not np.all(np.isfinite(arr)) or np.any(arr < 0) or (positive and np.any(arr <= 0)):
        raise ValueError(f"{name} must be finite and {'> 0' if positive else '>= 0'}, got {arr.tolist()}")
    return tuple(float(v) for v in arr)


@dataclasses.dataclass(frozen=True)
class HeightTargets:
    """Height maximisation targets: lift ``force_n[j]`` (N, > 0) at ``p_pa[j]`` (Pa, > 0)."""

    force_n: tuple[float, ...]
    p_pa: tuple[float, ...]

    def __post_init__(self):
        f = _vector("force_n", self.force_n, positive=True)
        object.__setattr__(self, "force_n", f)
        object.__setattr__(self, "p_pa", _vector("p_pa", self.p_pa, len(f), positive=True))


@dataclasses.dataclass(frozen=True)
class Waypoints:
    """Trajectory way-points: at load ``force_n[i]`` (N) the plate is at ``h_mm[i]`` (mm)
    when the pressure is ``p_pa[i]`` (Pa); ``weight[i] >= 0`` (default 1)."""

    force_n: tuple[float, ...]
    p_pa: tuple[float, ...]
    h_mm: tuple[float, ...]
    weight: tuple[float, ...] | None = None

    def __post_init__(self):
        f = _vector("force_n", self.force_n, positive=True)
        object.__setattr__(self, "force_n", f)
        object.__setattr__(self, "p_pa", _vector("p_pa", self.p_pa, len(f)))
        object.__setattr__(self, "h_mm", _vector("h_mm", self.h_mm, len(f)))
        w = (1.0,) * len(f) if self.weight is None else _vector("weight", self.weight, len(f))
        if sum(w) <= 0:
            raise ValueError("Waypoints.weight sums to zero: nothing to target")
        object.__setattr__(self, "weight", w)


# The paper's height-maximisation target sets: the three masses at one pressure each
# (set A 6.9 kPa = 1.0 psi, set B 8.3 kPa = 1.2 psi; the authors' notebook uses 6895 and 8273 Pa).
TARGET_SETS = {
    "A": HeightTargets(MASSES_N, (6895.0,) * 3),
    "B": HeightTargets(MASSES_N, (8273.0,) * 3),
}


# --------------------------------------------------------------------------- predictor
def _members_at(predictor: AbstractPredictor, design, h, p):
    """Rig members [M] (N) at one point (design [6] mm, scalars h mm, p Pa): a membrane is
    designed for the rig. vmap it over grids so that work not depending on the mapped input
    (e.g. the ensemble's latent net over a p grid) runs once."""
    return predictor.members(RIG, design[None], jnp.reshape(h, (1,)), jnp.reshape(p, (1,)))[:, 0]


# --------------------------------------------------------------------------- building blocks
def smooth_min(x, temperature, axis: int = -1):
    """LogSumExp smooth minimum ``-T log sum exp(-x / T)`` (same units as ``x``).

    Lower-bounds ``min(x)``, within ``T log n`` of it; tends to ``min(x)`` as ``T -> 0``.
    """
    return -temperature * jax.nn.logsumexp(-jnp.asarray(x) / temperature, axis=axis)


def lift_heights(predictor, design, force_n, p_pa, h_grid, members: bool = False):
    """Lift heights (mm) of one design ``[6]`` at loads ``force_n`` [K] and pressures ``p_pa`` [K].

    The first height on ``h_grid`` [G] (from 0) where the predicted force falls to the load,
    linearly interpolated; 0 when the force at ``h_grid[0]`` is already below the load (not
    lifted), ``h_grid[-1]`` when it never falls (saturated). Mean force by default; per
    member with ``members=True`` (leading axis M). Returns ``(h, force at h_grid[0])``.
    """
    h_grid = jnp.asarray(h_grid)
    f = jax.vmap(jax.vmap(lambda h, p: _members_at(predictor, design, h, p), (0, None)), (None, 0))(
        h_grid, jnp.asarray(p_pa)
    )  # [K, G, M]
    f = jnp.moveaxis(f, -1, 0)  # [M, K, G]
    if not members:
        f = f.mean(0)
    h, _ = first_crossing(h_grid, -f, -jnp.asarray(force_n))
    return h, f[..., 0]


def model_pressures(predictor, design, force_n, h_mm, p_grid, members: bool = False):
    """Pressures (Pa) at which the predicted force at height ``h_mm`` [K] first reaches
    ``force_n`` [K], on ``p_grid`` [G] (``p_grid[-1]`` when never). Returns ``(p, force at
    p_grid[-1])``; per member with ``members=True``."""
    p_grid = jnp.asarray(p_grid)
    f = jax.vmap(jax.vmap(lambda h, p: _members_at(predictor, design, h, p), (None, 0)), (0, None))(
        jnp.asarray(h_mm), p_grid
    )  # [K, G, M]
    f = jnp.moveaxis(f, -1, 0)
    if not members:
        f = f.mean(0)
    p, _ = first_crossing(p_grid, f, jnp.asarray(force_n))
    return p, f[..., -1]


def _mean_force(predictor, design, h, p):
    """Member-mean force (N) at heights ``h`` [K] and pressures ``p`` [K] of one design."""
    return jax.vmap(lambda hh, pp: _members_at(predictor, design, hh, pp).mean())(h, p)


def _invert(force_of, design, x, level, decreasing: bool):
    """First crossing of ``force_of(x_k, design) = level_k`` along the grid ``x`` [G], per
    target k.

    Same value as :func:`first_crossing` on the mean force, but the grid pass carries no
    gradient (the design enters it through ``stop_gradient``, so neither a backward pass
    nor forward-mode tangents run through it): the two bracketing points are evaluated
    again with gradient, which is all the linear interpolation depends on (2 points per
    target instead of G). Returns ``(x*, force at the lower bracket)``: the force at
    ``x[0]`` when the level is already crossed there, at ``x[-1]`` when it is never reached.
    """
    fixed = jax.lax.stop_gradient(design)
    fg = jax.lax.stop_gradient(
        jax.vmap(lambda xx: force_of(xx, fixed), out_axes=-1)(jnp.broadcast_to(x[:, None], (x.shape[0],) + level.shape))
    )
    sign = -1.0 if decreasing else 1.0
    above = sign * fg >= sign * level[:, None]
    reached = above.any(-1)
    j = jnp.argmax(above, axis=-1)
    g = x.shape[0] - 1
    j = jnp.where(reached, j, g)
    jm = jnp.where(reached, jnp.maximum(j - 1, 0), g)
    f0, f1 = force_of(x[jm], design), force_of(x[j], design)
    y0, y1, lv = sign * f0, sign * f1, sign * level
    dy = y1 - y0
    frac = jnp.where(dy != 0, jnp.clip((lv - y0) / jnp.where(dy != 0, dy, 1.0), 0.0, 1.0), 0.0)
    out = jnp.where(reached, jnp.where(j == 0, x[0], x[jm] + frac * (x[j] - x[jm])), x[-1])
    return out, f0


# The height loss's grid tops out here [mm]: a lift beyond it scores as this height
HEIGHT_GRID_TOP_MM = 80.0


# --------------------------------------------------------------------------- losses
def _decode(space: DesignSpace, u, n_rings):
    """A loss's point -> design ``[6]`` mm: ``u`` has ``2 + 2 n`` cube coordinates
    (:meth:`~DesignSpace.decode_unit`, ``n`` read from its length), or 6 in the padded
    layout of :meth:`~DesignSpace.decode_any` with the loss's ``n_rings`` (data, so one
    compiled search serves every ring count)."""
    if u.shape[-1] == 6:
        return space.decode_any(u, n_rings)
    if u.shape[-1] not in (2, 4):
        raise ValueError(f"a design point has 2, 4 or 6 unit-cube coordinates, got {u.shape[-1]}")
    n = (u.shape[-1] - 2) // 2
    # n_rings is traced (not static), so the mismatch can only be caught at run time.
    return eqx.error_if(
        space.decode_unit(u, n),
        jnp.asarray(n_rings) != n,
        f"this loss is for another ring count than {n} ({u.shape[-1]} cube coordinates)",
    )


class DesignLoss(eqx.Module):
    """What the two losses share: ``u [dim] -> (loss, aux)`` decodes the unit-cube point
    (:func:`_decode`, ring count ``n_rings``) and scores the design ``[6]`` mm
    (:meth:`of_design`) for loads ``force_n`` [K] N at pressures ``p_pa`` [K] Pa. A pytree
    (the predictor's arrays are leaves), so compiled multi-starts are reused across models."""

    predictor: AbstractPredictor
    force_n: jax.Array
    p_pa: jax.Array
    n_rings: jax.Array  # data, not static: one compilation for every ring count
    space: DesignSpace = eqx.field(static=True)
    weights: Weights = eqx.field(static=True)

    def __call__(self, u):
        return self.of_design(_decode(self.space, u, self.n_rings))

    @abc.abstractmethod
    def of_design(self, design) -> tuple[jax.Array, dict]:
        """``(loss, aux)`` of one design ``[6]`` mm."""


class HeightLoss(DesignLoss):
    """Height maximisation (module docstring) on the height grid ``h_grid`` [G] mm; aux:
    heights [K] mm, smooth minimum (the score, mm) and the force-deficit penalty."""

    h_grid: jax.Array

    def of_design(self, design):
        w = self.weights
        h, f0 = _invert(
            lambda hh, d: _mean_force(self.predictor, d, hh, self.p_pa),
            design,
            self.h_grid,
            self.force_n,
            decreasing=True,
        )
        f0 = jnp.where(h <= self.h_grid[0], f0, jnp.inf)  # the deficit counts only where not lifted
        score = smooth_min(h, w.temperature_mm)
        penalty = w.k_force * jnp.mean((jnp.maximum(self.force_n - f0, 0.0) / w.force_scale_n) ** 2)
        return -w.k_height * score / w.height_scale_mm + penalty, dict(heights_mm=h, score_mm=score, penalty=penalty)


def _shared_fields(predictor, problem: HeightTargets | Waypoints, space: DesignSpace, n_rings: int, weights) -> dict:
    """The :class:`DesignLoss` fields of ``problem`` (raises on a ring count ``space`` lacks)."""
    space.dim(n_rings)
    return dict(
        predictor=predictor,
        force_n=jnp.asarray(problem.force_n),
        p_pa=jnp.asarray(problem.p_pa),
        n_rings=jnp.asarray(int(n_rings)),
        space=space,
        weights=weights,
    )


def height_loss(
    predictor, targets: HeightTargets, space: DesignSpace, n_rings: int, weights: Weights = PAPER_WEIGHTS, h_grid=None
) -> HeightLoss:
    """The height-maximisation loss of ``predictor`` (an :class:`AbstractPredictor`);
    ``h_grid`` default 0-80 mm in 5 mm steps."""
    h_grid = jnp.linspace(0.0, HEIGHT_GRID_TOP_MM, 17) if h_grid is None else jnp.asarray(h_grid, float)
    return HeightLoss(**_shared_fields(predictor, targets, space, n_rings, weights), h_grid=h_grid)


class TrajectoryLoss(DesignLoss):
    """Trajectory targeting (module docstring): way-points at heights ``h_mm`` [K] mm with
    normalised weights ``weight`` [K], inverted on the pressure grid ``p_grid`` [G] Pa; aux:
    model pressures [K] Pa, the scaled trajectory RMSE ``e_p`` and the unreachable penalty."""

    h_mm: jax.Array
    weight: jax.Array
    p_grid: jax.Array

    def of_design(self, design):
        w = self.weights
        p_hat, f_lo = _invert(
            lambda pp, d: _mean_force(self.predictor, d, self.h_mm, pp),
            design,
            self.p_grid,
            self.force_n,
            decreasing=False,
        )
        f_hi = jnp.where(p_hat >= self.p_grid[-1], f_lo, jnp.inf)  # the deficit counts only where unreached
        e2 = jnp.sum(self.weight * ((p_hat - self.p_pa) / w.pressure_scale_pa) ** 2)
        penalty = w.k_force * jnp.mean((jnp.maximum(self.force_n - f_hi, 0.0) / w.trajectory_force_scale_n) ** 2)
        return w.k_pressure * e2 + penalty, dict(pressures_pa=p_hat, traj_rmse=jnp.sqrt(e2), penalty=penalty)


def trajectory_loss(
    predictor, waypoints: Waypoints, space: DesignSpace, n_rings: int, weights: Weights = PAPER_WEIGHTS, p_grid=None
) -> TrajectoryLoss:
    """The trajectory-targeting loss of ``predictor`` (an :class:`AbstractPredictor`);
    ``p_grid`` default 0-20 kPa in 250 Pa steps."""
    p_grid = jnp.linspace(0.0, 2.0 * P_MAX_PA, 81) if p_grid is None else jnp.asarray(p_grid, float)
    wt = np.asarray(waypoints.weight) / sum(waypoints.weight)
    return TrajectoryLoss(
        **_shared_fields(predictor, waypoints, space, n_rings, weights),
        h_mm=jnp.asarray(waypoints.h_mm),
        weight=jnp.asarray(wt),
        p_grid=p_grid,
    )


# --------------------------------------------------------------------------- multi-start
@stored_jit(fast_compile=True)
def _screen(loss, u0, batch_size: int):
    return jax.lax.map(lambda u: loss(u)[0], u0, batch_size=batch_size)


@stored_jit(fast_compile=True)
def _refine(loss, u0, steps: int, lr: float, batch_size: int):
    """Projected Adam from every row of ``u0`` [R, d] (vmapped, chunked); best visited point."""
    opt = optax.adam(lr)

    def one(u):
        def step(carry, _):
            u, state, best_u, best_l = carry
            (val, _), g = jax.value_and_grad(loss, has_aux=True)(u)
            g = jnp.where(jnp.isfinite(g), g, 0.0)
            better = val < best_l
            best_u, best_l = jnp.where(better, u, best_u), jnp.where(better, val, best_l)
            upd, state = opt.update(g, state, u)
            u = optax.projections.projection_box(optax.apply_updates(u, upd), 0.0, 1.0)
            return (u, state, best_u, best_l), val

        init = (u, opt.init(u), u, jnp.asarray(jnp.inf, u.dtype))
        (u, _, best_u, best_l), _ = jax.lax.scan(step, init, None, length=steps)
        last = loss(u)[0]
        better = last < best_l
        return jnp.where(better, u, best_u), jnp.where(better, last, best_l)

    return jax.lax.map(one, u0, batch_size=batch_size)


@eqx.filter_jit
def _decode_any(space: DesignSpace, u, n_rings):
    # one program for every ring count (data): op by op, each decode compiled ~20 small ones
    return space.decode_any(u, n_rings)


@stored_jit(fast_compile=True)
def _winner(loss: DesignLoss, u, design, grid):
    """The winner's ``aux`` and its per-member lift heights [M, K] mm on the height grid
    ``grid`` (a :class:`HeightLoss`) or model pressures [M, K] Pa on the pressure grid (a
    :class:`TrajectoryLoss`), in one compiled call: op by op under vmap, the members' draws
    compiled once per grid shape (6 programs, ~9 s of a cold demo, issue 40)."""
    _, aux = loss(u)
    if isinstance(loss, HeightLoss):
        per_member, _ = lift_heights(loss.predictor, design, loss.force_n, loss.p_pa, grid, members=True)
    else:
        assert isinstance(loss, TrajectoryLoss)
        per_member, _ = model_pressures(loss.predictor, design, loss.force_n, loss.h_mm, grid, members=True)
    return aux, per_member


@eqx.filter_jit
def _forward_value_and_grad(loss, u):
    """``(gradient, (loss, aux))`` of ``loss`` at ``u`` in forward mode (``jax.jacfwd``: one
    tangent per coordinate), for a loss through ODE solves that carry tangents forward
    only (the simulator's). Not vmapped: under vmap, even of one row, every ``cond`` in the
    simulator's solvers runs both branches (a step took 26 s against 3 s)."""
    return jax.jacfwd(lambda v: (lambda out: (out[0], out))(loss(v)), has_aux=True)(u)


def sobol_starts(n: int, dim: int, seed: int = 0) -> np.ndarray:
    """``n`` start points in ``[0, 1]^dim``: the first ``n`` of a scrambled Sobol sequence
    (``scipy.stats.qmc``; Owen scrambling, seeded). Why not uniform random draws: a
    low-discrepancy sequence leaves no large empty region of the design cube at the same
    count (lower centred L2 discrepancy; ``tests/test_optimize.py``), so fewer starts miss a
    basin. The sequence is drawn to the next power of two and cut, as SciPy recommends,
    which keeps its balance properties for the leading points."""
    from scipy.stats import qmc

    m = max(0, math.ceil(math.log2(max(n, 1))))
    return qmc.Sobol(d=dim, scramble=True, seed=seed).random_base2(m)[:n]


def multistart(
    loss: Callable,
    dim: int,
    n_starts: int = 2500,
    steps: int = 100,
    lr: float = 0.03,
    n_refine: int | None = None,
    seed: int = 0,
    batch_size: int = 250,
) -> dict:
    """Minimise ``loss(u)[0]`` over ``[0, 1]^dim`` from ``n_starts`` Sobol starts (:func:`sobol_starts`).

    All starts are scored; the best ``n_refine`` (all if None) run ``steps`` projected Adam
    steps. Returns u (best), loss, per-refined-start final losses and points
    (``points`` [n_refine, dim]) and wall times (s; the first call of a shape includes
    compilation).
    """
    enable_x64()  # float64 physics: mfdesign._x64
    for name, v, low in (
        ("n_starts", n_starts, 1),
        ("steps", steps, 0),
        ("batch_size", batch_size, 1),
        ("dim", dim, 1),
    ):
        if not isinstance(v, (int, np.integer)) or isinstance(v, bool) or v < low:
            raise ValueError(f"{name} must be an integer >= {low}, got {v!r}")
    n_refine = n_starts if n_refine is None else int(n_refine)
    if not 1 <= n_refine <= n_starts:
        raise ValueError(f"n_refine must be between 1 and n_starts={n_starts}, got {n_refine}")
    if not (math.isfinite(lr) and lr > 0):
        raise ValueError(f"lr must be a positive number, got {lr!r}")
    u0 = jnp.asarray(sobol_starts(n_starts, dim, seed), dtype=jnp.float64)
    t0 = time.perf_counter()
    if n_refine < n_starts:
        first = np.asarray(_screen(loss, u0, min(batch_size, n_starts)))
        first = np.where(np.isfinite(first), first, np.inf)
        u0 = u0[np.argsort(first)[:n_refine]]
    t1 = time.perf_counter()
    u, final = _refine(loss, u0, steps, lr, min(batch_size, n_refine))
    final = np.asarray(final)
    t2 = time.perf_counter()
    k = int(np.nanargmin(np.where(np.isfinite(final), final, np.nan))) if np.isfinite(final).any() else 0
    u = np.asarray(u)
    return dict(u=u[k], loss=float(final[k]), losses=final, points=u, screen_s=t1 - t0, refine_s=t2 - t1)


# --------------------------------------------------------------------------- result
@dataclasses.dataclass(frozen=True)
class Result:
    """The optimised design and its predicted behaviour (JSON-able via :meth:`to_json`).

    ``problem``: "height" or "trajectory"; ``per_rings``: best loss, design and timings per
    ring count; ``prediction``: the winner's targets with mean and member spread;
    ``curves``: predicted trajectories (per force: mean and 5/95 % member band);
    ``simulator``: the winner checked by the simulator (None if not run); ``limits``: why
    the winner may not be what it seems, in words (a height at the grid's top or above the
    rig's travel, a pressure at the grid's top or above the rig's limit, a design-space
    bound or minimum gap reached; :func:`limit_flags`); ``alternatives``: other designs
    (other starts or ring counts) whose loss is within ``tie_tol`` of the winner's;
    ``simulator_refined``: where the check disagreed with the model, the few projected-Adam
    steps taken on the simulator itself from the winner, and that design's own check
    (:func:`simulator_refine`; None when not run).
    """

    problem: str
    design_key: str
    n_rings: int
    loss: float
    per_rings: dict
    prediction: dict
    curves: dict
    simulator: dict | None = None
    settings: dict = dataclasses.field(default_factory=dict)
    limits: list = dataclasses.field(default_factory=list)
    alternatives: list = dataclasses.field(default_factory=list)
    simulator_refined: dict | None = None

    def to_json(self) -> dict:
        return dataclasses.asdict(self)


def _member_curves(fn, forces, grid, x_key: str, y: str, unit: str) -> dict:
    """Per force ``F``: the members' curves ``fn(F, grid) -> [M, X]`` over ``grid`` [X] as
    ``{x_key: grid, y_mean_unit, y_lo_unit, y_hi_unit}`` (member mean and 5/95 % band)."""
    out = {}
    for F in forces:
        v = np.asarray(fn(F, jnp.asarray(grid)))  # [M, X]
        out[f"{F:.3f}"] = {
            x_key: np.asarray(grid).tolist(),
            f"{y}_mean_{unit}": v.mean(0).tolist(),
            f"{y}_lo_{unit}": np.percentile(v, 5, 0).tolist(),
            f"{y}_hi_{unit}": np.percentile(v, 95, 0).tolist(),
        }
    return out


def lift_curves(predictor, design, forces, p_grid, h_grid) -> dict:
    """Per force: lift height (mm) vs pressure ``p_grid`` (Pa), member mean and 5/95 % band."""
    d = jnp.asarray(design)
    fn = jax.jit(lambda F, pp: lift_heights(predictor, d, jnp.full_like(pp, F), pp, h_grid, members=True)[0])
    return _member_curves(fn, forces, p_grid, "p_pa", "h", "mm")


def pressure_curves(predictor, design, forces, h_grid, p_grid) -> dict:
    """Per force: pressure (Pa) to hold the load at heights ``h_grid`` (mm), mean and 5/95 % band."""
    d = jnp.asarray(design)
    fn = jax.jit(lambda F, hh: model_pressures(predictor, d, jnp.full_like(hh, F), hh, p_grid, members=True)[0])
    return _member_curves(fn, forces, h_grid, "h_mm", "p", "pa")


# The check's height grid reaches past the model's 80 mm: an optimum the model puts at the
# top of its grid gets a number from the simulator (paper_design's optimum was
# BEYOND_GRID at 80 mm, so its check said nothing), flagged above the rig's travel.
CHECK_H_MAX_MM = 120.0
# 6 mm brackets (the crossing is then solved at fixed force): 3 loads x 21 heights = 63
# points fit force_at's 64-point batch; 25 heights (5 mm) made 75, padded to 128, and the
# demo's check took 36 s instead of ~15 (bench_demo on 821563c)
CHECK_N_HEIGHTS = 21


def check_with_simulator(
    design: Membrane,
    force_n,
    p_pa,
    predicted_h_mm,
    params=None,
    h_max_mm: float = CHECK_H_MAX_MM,
    n_heights: int = CHECK_N_HEIGHTS,
) -> dict:
    """Simulated lift heights (``mfdesign.physics.solve.height_at``, on ``n_heights``
    heights 0 .. ``h_max_mm`` mm) at the targets vs the model's; ``params``: calibrated
    :class:`SimParams` or the paper's defaults."""
    enable_x64()  # float64 physics: mfdesign._x64
    from mfdesign.physics.params import SimParams
    from mfdesign.physics.solve import height_at
    from mfdesign.physics.status import Status

    params = SimParams() if params is None else params
    t0 = time.perf_counter()
    h, status = height_at(
        design, np.asarray(force_n, float), np.asarray(p_pa, float), params, h_max_mm=h_max_mm, n_heights=n_heights
    )
    h = np.asarray(h, float)
    diff = h - np.asarray(predicted_h_mm, float)
    return dict(
        force_n=list(map(float, force_n)),
        p_pa=list(map(float, p_pa)),
        h_sim_mm=[None if not np.isfinite(v) else float(v) for v in h],
        status=[Status(int(s)).name for s in np.asarray(status)],
        h_model_mm=list(map(float, predicted_h_mm)),
        diff_mm=[None if not np.isfinite(v) else float(v) for v in diff],
        mae_mm=float(np.nanmean(np.abs(diff))) if np.isfinite(diff).any() else None,
        params=_param_dict(params),
        h_max_mm=float(h_max_mm),
        seconds=time.perf_counter() - t0,
    )


def simulator_refine(
    problem: "HeightTargets | Waypoints",
    space: DesignSpace,
    n_rings: int,
    u,
    params=None,
    weights: "Weights | None" = None,
    steps: int = 6,
    lr: float = 0.02,
) -> dict:
    """A few projected-Adam steps on the simulator itself from the cube point ``u`` (a
    model's optimum): the same loss as the search, with the model's forces replaced by the
    simulator's (:class:`~mfdesign.models.predictor.SimulatorPredictor` at ``params``,
    gradients in forward mode). Used where the simulator's check disagrees with the model:
    a search on the model finds the model's optimum, and near it the simulator knows
    better (issue 43). The best visited point is kept (the start included, so the
    simulator's loss never rises), and checked by :func:`check_with_simulator`.

    Returns a JSON-able dict: the start and end designs, the simulator's loss at both,
    steps, learning rate, the refined design's check and wall seconds (the first call
    compiles the simulator's forward-mode search: about a minute on 2 cores)."""
    from mfdesign.models.predictor import SimulatorPredictor

    weights = PAPER_WEIGHTS if weights is None else weights
    t0 = time.perf_counter()
    make = height_loss if isinstance(problem, HeightTargets) else trajectory_loss
    loss = make(SimulatorPredictor(params), problem, space, n_rings, weights)
    # A Python loop over the steps (optax's own idiom): one compiled program, the forward
    # gradient with the loss and its aux; a scan would compile the final loss beside it
    # (~130 s against ~45 s on 2 cores). The last evaluation scores the last step.
    opt = optax.adam(lr)
    u0 = jnp.asarray(u, float)
    uk, state = u0, opt.init(u0)
    start, best = None, (np.inf, u0, None)
    for k in range(int(steps) + 1):
        g, (val, aux) = _forward_value_and_grad(loss, uk)
        val = float(val)
        start = val if start is None else start
        if val < best[0]:
            best = (val, uk, aux)
        if k == int(steps):
            break
        upd, state = opt.update(jnp.where(jnp.isfinite(g), g, 0.0), state, uk)
        uk = optax.projections.projection_box(optax.apply_updates(uk, upd), 0.0, 1.0)
    l_best, u_best, aux = best
    if aux is None:  # no finite loss anywhere: report the start
        u_best, aux = u0, _forward_value_and_grad(loss, u0)[1][1]
    u_best = np.asarray(u_best)
    design0 = Membrane.from_array(np.asarray(space.decode_any(u0, n_rings)))
    design = Membrane.from_array(np.asarray(space.decode_any(jnp.asarray(u_best), n_rings)))
    if isinstance(problem, HeightTargets):
        model_h = np.asarray(aux["heights_mm"])
    else:
        model_h = np.asarray(problem.h_mm, float)
    check = check_with_simulator(design, problem.force_n, problem.p_pa, model_h, params)
    return dict(
        start_design_key=design0.key(),
        design_key=design.key(),
        n_rings=int(n_rings),
        u=space.cube_of(u_best, n_rings).tolist(),
        loss_sim_start=start if start is not None and np.isfinite(start) else None,
        loss_sim=l_best if np.isfinite(l_best) else None,
        steps=int(steps),
        lr=float(lr),
        check=check,
        seconds=time.perf_counter() - t0,
    )


def _disagrees(check: dict, tol_mm: float, top_mm: float | None = HEIGHT_GRID_TOP_MM) -> bool:
    """Whether a simulator check contradicts the model as far as the search's loss can
    tell: a target with no simulated height, or a mean absolute difference above
    ``tol_mm`` once both heights are capped at ``top_mm`` (the loss's grid top: above it
    every height scores the same, so a simulator that lifts higher than the model's
    saturated grid agrees with it; None: no cap, for way-points)."""
    beyond = [st == "BEYOND_GRID" for st in check.get("status", [""] * len(check["h_sim_mm"]))]
    top = float(check.get("h_max_mm", np.inf))
    # past the check's grid: at least its top (above the loss's grid, so capped alike)
    sim = np.array([top if b else np.nan if v is None else v for v, b in zip(check["h_sim_mm"], beyond)], float)
    model = np.asarray(check["h_model_mm"], float)
    if not np.isfinite(sim).all():
        return True
    if top_mm is not None:
        sim, model = np.minimum(sim, top_mm), np.minimum(model, top_mm)
    return bool(np.mean(np.abs(sim - model)) > tol_mm)


def _param_dict(params) -> dict:
    out = {}
    for f in dataclasses.fields(params):
        try:
            out[f.name] = float(getattr(params, f.name))
        except (TypeError, ValueError):
            out[f.name] = repr(getattr(params, f.name))
    return out


# The rig's limits (mfdesign.rig.config defaults): the plate's travel and the pressure at
# which the controller goes to its safe state.
RIG_HEIGHT_MAX_MM = RigConfig().height_max_mm
RIG_PRESSURE_MAX_PA = RigConfig().hard_pressure_limit_pa
# How close (mm) a height, pressure (Pa / 1000) or design number must be to a limit to sit on it.
_AT_LIMIT = 1e-6


def _bound_flags(design: Membrane, space: DesignSpace) -> list[str]:
    """Design-space bounds and minimum gaps the design sits on (a fixed feature, low ==
    high, is the caller's choice and not flagged)."""
    out = []
    tol = 1e-6
    for name, value, (lo, hi) in (
        ("thickness", design.thickness_mm, space.thickness_mm),
        ("contact radius", design.contact_radius_mm, space.contact_radius_mm),
        *((f"ring {k} half-width", r.half_width_mm, space.half_width_mm) for k, r in enumerate(design.rings, 1)),
    ):
        if hi - lo <= tol:
            continue
        if value <= lo + tol * max(1.0, lo):
            out.append(f"{name} {value:g} mm is at the design space's lower bound {lo:g} mm")
        elif value >= hi - tol * max(1.0, hi):
            out.append(f"{name} {value:g} mm is at the design space's upper bound {hi:g} mm")
    edges = [("the contact disk", design.contact_radius_mm)]
    for k, r in enumerate(design.rings, 1):
        if r.inner_mm - edges[-1][1] <= space.gap_mm + tol:
            out.append(f"ring {k} sits at the {space.gap_mm:g} mm minimum gap from {edges[-1][0]}")
        edges.append((f"ring {k}", r.outer_mm))
    if design.rings and space.outer_radius_mm - edges[-1][1] <= space.gap_mm + tol:
        out.append(f"ring {design.n_rings} sits at the {space.gap_mm:g} mm minimum gap from the clamp")
    return out


def limit_flags(
    problem: HeightTargets | Waypoints,
    prediction: dict,
    design: Membrane,
    space: DesignSpace,
    h_grid_top_mm: float = HEIGHT_GRID_TOP_MM,
    p_grid_top_pa: float = 2.0 * P_MAX_PA,
) -> list[str]:
    """Why an optimum may be an artefact of a limit, one sentence each: a lift height at the
    top of the height grid (``h_grid_top_mm``: the force never fell to the load, the true
    height may be higher) or above the rig's travel (75 mm: cannot be measured); a load not
    lifted at all; a pressure at the top of the pressure grid (``p_grid_top_pa``: never
    reached) or above the rig's hard limit (12 kPa); a design-space bound or minimum gap
    (:func:`_bound_flags`). ``prediction`` is :attr:`Result.prediction`."""
    out = []
    F, p = prediction["force_n"], prediction["p_pa"]
    if isinstance(problem, HeightTargets):
        for f, pp, h in zip(F, p, prediction["h_mean_force_mm"]):
            what = f"lift height of {f:.3g} N at {pp / 1e3:.3g} kPa"
            if h >= h_grid_top_mm - _AT_LIMIT:
                # both limits when the grid's top is above the rig's travel (80 vs 75 mm)
                travel = (
                    f", and above the rig's {RIG_HEIGHT_MAX_MM:g} mm travel (cannot be measured)"
                    if h > RIG_HEIGHT_MAX_MM
                    else ""
                )
                out.append(
                    f"{what} is at the {h_grid_top_mm:g} mm top of the height grid "
                    f"(the force never falls to the load there: the true height may be higher){travel}"
                )
            elif h > RIG_HEIGHT_MAX_MM:
                out.append(
                    f"{what} is {h:.3g} mm, above the rig's {RIG_HEIGHT_MAX_MM:g} mm travel (cannot be measured)"
                )
            elif h <= _AT_LIMIT:
                out.append(f"{what} is 0 mm: the load is not lifted at all")
    else:
        for f, pp, h, pm in zip(F, p, problem.h_mm, prediction["p_model_pa"]):
            what = f"way-point {f:.3g} N at {h:g} mm (target {pp / 1e3:.3g} kPa)"
            if pm >= p_grid_top_pa - 1e3 * _AT_LIMIT:
                out.append(f"{what} is never reached below {p_grid_top_pa / 1e3:g} kPa (the top of the pressure grid)")
            elif pm > RIG_PRESSURE_MAX_PA:
                out.append(
                    f"{what} needs {pm / 1e3:.3g} kPa, above the rig's {RIG_PRESSURE_MAX_PA / 1e3:g} kPa pressure limit"
                )
            if h > RIG_HEIGHT_MAX_MM:
                out.append(f"{what} is above the rig's {RIG_HEIGHT_MAX_MM:g} mm travel (cannot be measured)")
    for pp in sorted(set(p)):
        if pp > RIG_PRESSURE_MAX_PA:
            out.append(f"target pressure {pp / 1e3:.3g} kPa is above the rig's {RIG_PRESSURE_MAX_PA / 1e3:g} kPa limit")
    return out + _bound_flags(design, space)


def _check_flags(check: dict | None) -> list[str]:
    """The simulator check's heights above the rig's travel, one sentence each."""
    if not check:
        return []
    top = check.get("h_max_mm", CHECK_H_MAX_MM)
    out = []
    for f, pp, h, st in zip(check["force_n"], check["p_pa"], check["h_sim_mm"], check["status"]):
        if h is not None and h > RIG_HEIGHT_MAX_MM:
            where = f"to {h:.3g} mm"
        elif h is None and st == "BEYOND_GRID":
            where = f"past {top:g} mm (the top of its height grid)"
        else:
            continue
        out.append(
            f"the simulator lifts {f:.3g} N at {pp / 1e3:.3g} kPa {where}, above the rig's "
            f"{RIG_HEIGHT_MAX_MM:g} mm travel (cannot be measured)"
        )
    return out


# Two designs of one ring count closer than this in every unit-cube coordinate are one
# membrane (as acquisition's MIN_SEPARATION): an alternative must differ from the winner.
ALTERNATIVE_SEPARATION = 0.05


def _alternatives(found, best_loss: float, winner, tie_tol: float, limit: int) -> list[dict]:
    """Other designs within ``tie_tol`` (relative) of the best loss, best first, each a
    different membrane from the winner and from each other. ``found``: ``(loss, n_rings,
    cube point, Membrane)`` of every refined start; ``winner``: ``(n_rings, cube point)``."""
    tol = tie_tol * max(abs(best_loss), 1e-12)
    kept = [winner]
    out = []
    for loss, n, u, design in sorted(found, key=lambda c: c[0]):
        if not np.isfinite(loss) or loss - best_loss > tol or len(out) >= limit:
            continue
        if any(m == n and np.max(np.abs(u - v)) < ALTERNATIVE_SEPARATION for m, v in kept):
            continue
        kept.append((n, u))
        gap = (loss - best_loss) / max(abs(best_loss), 1e-300)
        out.append(dict(design_key=design.key(), n_rings=int(n), loss=float(loss), gap_pct=100.0 * float(gap)))
    return out


def optimize(
    predictor: AbstractPredictor,
    problem: HeightTargets | Waypoints,
    rings: Sequence[int] = (0, 1, 2),
    space: DesignSpace = DesignSpace(),
    weights: Weights = PAPER_WEIGHTS,
    n_starts: int = 2500,
    steps: int = 100,
    lr: float = 0.03,
    n_refine: int | None = None,
    seed: int = 0,
    batch_size: int = 250,
    check: bool = False,
    sim_params=None,
    sim_constants: dict | None = None,
    progress: bool = True,
    tie_tol: float = 0.02,
    n_alternatives: int = 5,
    sim_refine_steps: int = 6,
    sim_refine_tol_mm: float = 2.0,
) -> Result:
    """Optimise a membrane design for a lift task (the paper's design study).

    One :func:`multistart` per ring count in ``rings``; the lowest loss wins. The winner's
    per-member predictions and trajectories are reported, and with ``check`` its lift
    heights are recomputed by the simulator (slow: minutes on 2 CPU cores).

    **Arguments:**

    - `predictor`: the model, offering the `rig` fidelity
      (:class:`~mfdesign.models.predictor.AbstractPredictor`; a fitted RPN ensemble through
      :class:`~mfdesign.models.predictor.EnsemblePredictor`).
    - `problem`: :class:`HeightTargets` (maximise the lifted heights of given loads [N] at
      given pressures [Pa]) or :class:`Waypoints` (reach heights [mm] at loads with least
      pressure error).
    - `rings`: ring counts to search.
    - `space`: the design space (bounds, gaps).
    - `weights`: the loss's weights and scales (:class:`Weights`; default the paper's).
    - `n_starts`: Sobol starts per ring count (all scored).
    - `steps`: projected-Adam steps of each refined start.
    - `lr`: Adam's learning rate (unit-cube coordinates).
    - `n_refine`: best starts refined (`None`: all).
    - `seed`: random seed.
    - `batch_size`: starts per `jax.lax.map` chunk (bounds memory).
    - `check`: recompute the winner's lift heights with the simulator.
    - `sim_params`: simulator constants of the check (default the authors'; a fit-mf
      model's are its calibrated ones, :func:`~mfdesign.calibration.workflow.calibrated_sim_params`).
    - `sim_constants`: what `sim_params` are, recorded with the check as ``constants``
      (default ``{"constants": "authors"}`` without `sim_params`, else ``"given"``).
    - `progress`: progress bars.
    - `tie_tol`: relative gap to the best loss within which other designs (other starts,
      other ring counts) are reported as alternatives (default 2 %).
    - `n_alternatives`: at most this many alternatives.
    - `sim_refine_steps`: with `check`, where the check disagrees with the model (no
      comparable height, or a mean absolute difference above `sim_refine_tol_mm` [mm]), this
      many projected-Adam steps on the simulator itself from the winner
      (:func:`simulator_refine`; 0: never).
    - `sim_refine_tol_mm`: the disagreement that starts them [mm].

    **Returns:**

    A :class:`Result`: the winning design (mm), its loss and predictions with the members'
    spread, the runner-up per ring count, the limits it sits on (:func:`limit_flags`), the
    near-ties, and the simulator check when asked.
    """
    enable_x64()  # float64 physics: mfdesign._x64
    from tqdm.auto import tqdm

    rings = tuple(int(r) for r in rings)
    if not rings or any(r not in (0, 1, 2) for r in rings):
        raise ValueError(f"rings must be a non-empty subset of (0, 1, 2), got {rings}")
    height = isinstance(problem, HeightTargets)
    if not height and not isinstance(problem, Waypoints):
        raise TypeError(f"problem must be HeightTargets or Waypoints, got {type(problem).__name__}")
    if not (isinstance(tie_tol, (int, float)) and math.isfinite(tie_tol) and tie_tol >= 0):
        raise ValueError(f"tie_tol must be a finite number >= 0, got {tie_tol!r}")
    make = height_loss if height else trajectory_loss
    per, best, found = {}, None, []
    for r in tqdm(rings, desc="optimise (ring counts)", disable=not progress):
        loss = make(predictor, problem, space, r, weights)
        res = multistart(loss, 6, n_starts, steps, lr, n_refine, seed, batch_size)  # padded cube
        design = Membrane.from_array(np.asarray(_decode_any(space, jnp.asarray(res["u"]), jnp.asarray(r))))
        per[str(r)] = dict(
            loss=res["loss"],
            design_key=design.key(),
            u=space.cube_of(res["u"], r).tolist(),
            screen_s=res["screen_s"],
            refine_s=res["refine_s"],
            n_finite=int(np.isfinite(res["losses"]).sum()),
        )
        for loss_k, u_k in zip(res["losses"], res["points"]):
            found.append((float(loss_k), r, space.cube_of(u_k, r), None if not np.isfinite(loss_k) else u_k))
        if best is None or res["loss"] < best[0]:
            best = (res["loss"], r, design, res["u"])
    loss_val, r, design, u = best
    ties = [
        (loss_k, n, cube, Membrane.from_array(np.asarray(_decode_any(space, jnp.asarray(u6), jnp.asarray(n)))))
        for loss_k, n, cube, u6 in found
        if u6 is not None and loss_k - loss_val <= tie_tol * max(abs(loss_val), 1e-12)
    ]
    alternatives = _alternatives(ties, float(loss_val), (r, space.cube_of(u, r)), tie_tol, n_alternatives)
    d = jnp.asarray(design.to_array())
    F = np.asarray(problem.force_n)
    p = np.asarray(problem.p_pa)
    pred = {"force_n": F.tolist(), "p_pa": p.tolist()}
    hg = jnp.linspace(0.0, HEIGHT_GRID_TOP_MM, 17)
    pg = jnp.linspace(0.0, 2.0 * P_MAX_PA, 81)
    aux, per_member = _winner(make(predictor, problem, space, r, weights), jnp.asarray(u), d, hg if height else pg)
    if height:
        hm = np.asarray(per_member)
        pred.update(
            h_mean_force_mm=np.asarray(aux["heights_mm"]).tolist(),
            score_mm=float(aux["score_mm"]),
            min_h_mm=float(np.min(aux["heights_mm"])),
            h_member_mean_mm=hm.mean(0).tolist(),
            h_member_std_mm=hm.std(0).tolist(),
            penalty=float(aux["penalty"]),
        )
        curves = lift_curves(predictor, d, sorted(set(F.tolist())), np.linspace(0, 1.2e4, 49), hg)
    else:
        pm = np.asarray(per_member)
        pred.update(
            h_mm=list(problem.h_mm),
            p_model_pa=np.asarray(aux["pressures_pa"]).tolist(),
            p_member_std_pa=pm.std(0).tolist(),
            traj_rmse=float(aux["traj_rmse"]),
            penalty=float(aux["penalty"]),
        )
        curves = pressure_curves(predictor, d, sorted(set(F.tolist())), np.linspace(0, 60, 31), pg)
    sim = None
    if check:
        model_h = pred["h_mean_force_mm"] if height else list(problem.h_mm)
        sim = check_with_simulator(design, F, p, model_h, sim_params)
        sim["constants"] = dict(
            sim_constants or {"constants": "authors" if sim_params is None else "given"}
        )  # the check's heights depend on them by mm: say which
    refined = None
    if check and sim_refine_steps > 0 and _disagrees(sim, sim_refine_tol_mm, HEIGHT_GRID_TOP_MM if height else None):
        refined = simulator_refine(problem, space, r, u, sim_params, weights, steps=sim_refine_steps)
        refined["check"]["constants"] = sim["constants"]
        refined["why"] = (
            f"the simulator's check disagrees with the model (mean |difference| {sim['mae_mm']:.1f} mm > "
            f"{sim_refine_tol_mm:g} mm)"
            if sim.get("mae_mm") is not None
            else "the simulator's check has no height to compare with the model's"
        )
    settings = dict(
        n_starts=n_starts,
        steps=steps,
        lr=lr,
        n_refine=n_refine,
        seed=seed,
        weights=dataclasses.asdict(weights),
        rings=list(rings),
        tie_tol=tie_tol,
        sim_refine_steps=sim_refine_steps,
        sim_refine_tol_mm=sim_refine_tol_mm,
    )
    limits = limit_flags(problem, pred, design, space) + _check_flags(sim)
    return Result(
        "height" if height else "trajectory",
        design.key(),
        r,
        float(loss_val),
        per,
        pred,
        curves,
        sim,
        settings,
        limits,
        alternatives,
        refined,
    )


def plot(result: Result, path, title: str = "") -> None:
    """Predicted trajectories of the winner with the member band; targets as markers."""
    import matplotlib

    matplotlib.use("Agg")
    import matplotlib.pyplot as plt

    fig, ax = plt.subplots(figsize=(6.5, 4.5))
    pred = result.prediction
    for k, (F, c) in enumerate(result.curves.items()):
        col = f"C{k}"
        if result.problem == "height":
            x = np.asarray(c["p_pa"]) / 1e3
            ax.plot(x, c["h_mean_mm"], color=col, label=f"{float(F):.1f} N")
            ax.fill_between(x, c["h_lo_mm"], c["h_hi_mm"], color=col, alpha=0.2)
        else:
            y = np.asarray(c["h_mm"])
            ax.plot(np.asarray(c["p_mean_pa"]) / 1e3, y, color=col, label=f"{float(F):.1f} N")
            ax.fill_betweenx(y, np.asarray(c["p_lo_pa"]) / 1e3, np.asarray(c["p_hi_pa"]) / 1e3, color=col, alpha=0.2)
    keys = list(result.curves)
    for i, F in enumerate(pred["force_n"]):
        col = f"C{min(range(len(keys)), key=lambda k: abs(float(keys[k]) - F))}"
        h = pred["h_mean_force_mm"][i] if result.problem == "height" else pred["h_mm"][i]
        ax.plot(pred["p_pa"][i] / 1e3, h, "o", color=col, mec="k")
    if result.simulator:
        s = result.simulator
        hs = [np.nan if v is None else v for v in s["h_sim_mm"]]
        which = s.get("constants", {}).get("constants", "authors")
        ax.plot(np.asarray(s["p_pa"]) / 1e3, hs, "kx", ms=9, label=f"simulator check ({which} constants)")
    if result.simulator_refined:
        s = result.simulator_refined["check"]
        hs = [np.nan if v is None else v for v in s["h_sim_mm"]]
        ax.plot(np.asarray(s["p_pa"]) / 1e3, hs, "k+", ms=11, label="simulator, after its own search near it")
    ax.set_xlabel("pressure [kPa]")
    ax.set_ylabel("lift height [mm]")
    ax.set_title(title or f"{result.problem}: {result.design_key}", fontsize=9)
    ax.legend(fontsize=8)
    fig.tight_layout()
    from mfdesign import outputs

    outputs.savefig(fig, path, dpi=120)
    plt.close(fig)
