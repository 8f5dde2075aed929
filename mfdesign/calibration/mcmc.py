"""Bayesian calibration of the hierarchical model with emcee (Foreman-Mackey et al. 2013).

Steps of :func:`calibrate`:

1. rows: at most ``max_rows`` of the Measurements, evenly within each trial
   (:class:`~mfdesign.models.hierarchical.CalibrationData`);
2. MAP: ``optimistix.BFGS`` on the negative log posterior in the unconstrained
   parameterisation ``u`` (see :mod:`mfdesign.models.hierarchical`), from ``map_starts``
   starts at once (``jax.vmap``), the best kept; the Hessian ``H`` there by autodiff;
3. walkers: with the default moves' adaptation, draws of the Laplace approximation
   (``_laplace_start``); else a small Gaussian ball around the MAP, per-coordinate width
   ``ball * sqrt(diag H^-1)`` (Laplace widths; 1e-3 where H is not positive definite);
4. emcee's ensemble sampler with a jitted,
   vectorised log posterior (``vectorize=True``: one JAX call per step for all walkers; a
   ``pool`` splits that batch over its workers), ``emcee.backends.HDFBackend`` (``ChainFile``) so that a
   killed run resumes at the stored iteration (same file, same model: the chain goes on).
   Default moves (:func:`default_moves`, :func:`adapted_moves`): adaptation rounds
   (``ADAPT_ROUNDS``, ``ADAPT_STEPS`` in all) of independence proposals, first from the
   Laplace approximation, then refitted to the round before's draws, mixed with
   differential evolution (ter Braak 2006); after them the last refit, fixed;
5. convergence: integrated autocorrelation time tau per parameter (Sokal 1989, emcee's
   estimator), chain length >= 50 tau, mean acceptance fraction in [0.2, 0.9]; a
   :class:`ConvergenceWarning` when one fails; burn-in ``2 max tau``, thinning ``min tau / 2``;
6. a :class:`~mfdesign.calibration.posterior.Posterior` (physical units): samples (flat and
   per walker), summary table (median, 5 / 95 %), MAP, BIC and the Laplace log evidence; the
   report also holds ArviZ's R-hat and bulk / tail ESS of the physical chain (walkers as
   chains; :func:`~mfdesign.calibration.posterior.arviz_diagnostics`).
"""

from __future__ import annotations

import hashlib
import json
import math
import os
import warnings
from pathlib import Path
from typing import Any, Callable, Sequence

import equinox as eqx
import jax
import jax.numpy as jnp
import numpy as np

from mfdesign._padding import pad_last
from mfdesign._x64 import enable_x64
from mfdesign.calibration.posterior import Posterior
from mfdesign.models.hierarchical import CalibrationData, HierarchicalModel

__all__ = [
    "ConvergenceWarning",
    "LogPosterior",
    "MapResult",
    "OutsideModelWarning",
    "build_model",
    "calibrate",
    "convergence_report",
    "find_map",
]

# the convergence rule's numbers live beside its sentence (posterior.convergence_rule)
from mfdesign.calibration.posterior import ACCEPTANCE_RANGE, MIN_TAU_RATIO  # noqa: E402
from mfdesign.physics._traces import stored_jit
from mfdesign.physics.solve import in_batches


class ConvergenceWarning(UserWarning):
    """The chain is too short for its autocorrelation time, or the acceptance is off."""


class OutsideModelWarning(UserWarning):
    """Rows outside the physical model (force above p pi R^2) were left out of the likelihood."""


def build_model(force_model, data: CalibrationData, effects: Sequence[str] = (), **kwargs) -> HierarchicalModel:
    """A :class:`HierarchicalModel` with one thickness latent per membrane of ``data``."""
    enable_x64()  # float64 physics: mfdesign._x64
    return HierarchicalModel(
        force_model=force_model, effects=tuple(effects), n_membranes=len(data.design_keys), **kwargs
    )


@eqx.filter_jit
def _batch_log_post(model: HierarchicalModel, u, data: CalibrationData):
    """log p(u | D) for a batch ``u`` [W, dim]; module-level so that the compiled code is
    shared by every call with an equal model and data of the same shapes."""
    return jax.vmap(model.log_posterior_u, in_axes=(0, None))(u, data)


WALKER_CHUNK = 16  # points per log-posterior call (half the default 32 walkers: emcee's red-blue halves)


class LogPosterior:
    """``u [W, dim] -> log p(u | D) [W]`` (NumPy in, NumPy out) for emcee, jitted and vmapped.

    Picklable (for a multiprocessing / MPI ``pool``). With ``pool``, a batch is split into
    one chunk per worker (``pool.map``), each chunk one JAX call.
    """

    def __init__(self, model: HierarchicalModel, data: CalibrationData, pool=None, chunks: int | None = None):
        self.model, self.data, self.pool = model, data, pool
        self.chunks = chunks or getattr(pool, "size", None) or getattr(pool, "_processes", None) or os.cpu_count() or 1

    def __getstate__(self):
        return {"model": self.model, "data": self.data, "pool": None, "chunks": self.chunks}

    def batch(self, u: np.ndarray) -> np.ndarray:
        # chunks of WALKER_CHUNK points, the last padded: one compiled program for every batch
        # (emcee asks for the whole ensemble, its halves and smaller sets: three programs of
        # ~1 s XLA each in a cold demo, issue 40)
        u = np.atleast_2d(np.asarray(u, float))
        n = len(u)
        if not n:
            return np.zeros(0)
        padded = pad_last(u, WALKER_CHUNK * -(-n // WALKER_CHUNK))  # in_batches never meets a short batch
        out = in_batches(
            lambda b: _batch_log_post(self.model, jnp.asarray(b), self.data), padded, size=WALKER_CHUNK, lanes=1
        )
        return out[:n]

    def __call__(self, u) -> np.ndarray:
        u = np.atleast_2d(np.asarray(u, float))
        if self.pool is None:
            return self.batch(u)
        parts = [p for p in np.array_split(u, min(self.chunks, len(u))) if len(p)]
        return np.concatenate(list(self.pool.map(self.batch, parts)))


class MapResult(eqx.Module):
    """MAP in ``u`` (unconstrained) and ``x`` (physical), log posterior, Hessian of -log p in u."""

    u: jax.Array
    x: jax.Array
    log_post: jax.Array
    hessian: jax.Array
    converged: jax.Array


def _neg_log_post(u, args):
    model, data = args
    return -model.log_posterior_u(u, data)


def _neg_log_post_per_row(u, args):
    # BFGS starts from the identity as its inverse Hessian: on the unscaled sum over
    # ~1,000 rows its first step is thousands of units of u long, far off the force
    # model's lattice, and the backtracking search then stalls at the start (seen with the
    # Student-t likelihood: "converged" at the start point). Per row the first step is O(1).
    model, data = args
    return _neg_log_post(u, args) / jnp.maximum(jnp.sum(data.weight), 1.0)


@stored_jit(fast_compile=True)
def _map_kernel(model: HierarchicalModel, inits, data: CalibrationData, max_steps: int):
    """BFGS from every start at once, and the Hessian at every end point (one compile)."""
    import optimistix as optx

    solver = optx.BFGS(rtol=1e-9, atol=1e-9)

    def one(u):
        sol = optx.minimise(_neg_log_post_per_row, solver, u, args=(model, data), max_steps=max_steps, throw=False)
        u = sol.value
        hess = jax.hessian(_neg_log_post)(u, (model, data))
        return u, sol.result == optx.RESULTS.successful, -_neg_log_post(u, (model, data)), hess

    return jax.vmap(one)(inits)


def find_map(
    model: HierarchicalModel, data: CalibrationData, starts: int = 4, seed: int = 0, max_steps: int = 1000, u0=None
) -> MapResult:
    """MAP by ``optimistix.BFGS`` from ``starts`` points at once (``jax.vmap``): ``u0``
    (default: the prior-median start) and Gaussian perturbations of it (sd 0.3 in u); the
    best is kept."""
    enable_x64()  # float64 physics: mfdesign._x64
    u0 = model.to_unconstrained(model.initial_physical()) if u0 is None else np.asarray(u0, float)
    rng = np.random.default_rng(seed)
    inits = u0 + np.vstack([np.zeros(model.dim), 0.3 * rng.standard_normal((max(starts, 1) - 1, model.dim))])
    us, ok, vals, hess = _map_kernel(model, jnp.asarray(inits), data, max_steps)
    vals = jnp.where(jnp.isfinite(vals), vals, -jnp.inf)
    best = int(jnp.argmax(vals))
    return MapResult(us[best], model.to_physical(us[best]), vals[best], hess[best], ok[best])


LATTICE_SD = 5.0  # the force model must hold the MAP +- this many Laplace sd in every parameter
LATTICE_ROUNDS = 8
EDGE_STEP = 2  # lattice nodes added past a MAP that sits on the lattice's edge
# "On the edge": closer to it than this many nodes. A MAP searched with the model clamped
# at the edge stops there; one inside the last cell is a real optimum (a full node of
# margin here grew the demo's plain lattice from 3 x 3 to 8 x 8 nodes: 162 planes, 7 min).
EDGE_MARGIN = 0.25


# Eigenvalues of the Hessian below this share of the largest are flat: the data (and priors)
# leave that direction undetermined at the MAP.
FLAT_EIG = 1e-10
# A parameter with more than this squared weight on a flat direction has no Laplace width.
FLAT_WEIGHT = 1e-6


def _lattice_steps(model: HierarchicalModel, data: CalibrationData, res: MapResult) -> np.ndarray:
    """Half-widths [dim] in ``u`` of the box the lattice must hold around the MAP, one per
    parameter: ``LATTICE_SD`` marginal sd (capped at 0.5 a parameter) from the Hessian's
    positive-definite part, where the Hessian determines that parameter. A parameter that
    loads on a flat or concave direction (the hierarchy's funnel, a prior-free effect) has
    no width the data give; it gets the u step that moves the lattice axis it moves fastest
    by ``EDGE_STEP`` nodes, and 0 where it moves no axis (noise, the thickness spread): its
    own axes grow, not every axis (issue 40). With a positive-definite Hessian this is
    exactly ``LATTICE_SD * min(sd, 0.5)``, the Laplace box."""
    from mfdesign.physics import planes as pl

    h = np.asarray(res.hessian, float)
    h = 0.5 * (h + h.T)
    u = np.asarray(res.u, float)
    if not np.all(np.isfinite(h)):
        lam, vec = np.zeros(len(u)), np.eye(len(u))
    else:
        lam, vec = np.linalg.eigh(h)
    good = lam > FLAT_EIG * max(float(np.max(np.abs(lam))), 1e-300)
    var = (vec[:, good] ** 2) @ (1.0 / lam[good]) if good.any() else np.zeros(len(u))
    flat = (vec[:, ~good] ** 2).sum(axis=1) > FLAT_WEIGHT
    steps = LATTICE_SD * np.minimum(np.sqrt(var), 0.5)
    if flat.any():
        # d(coordinate)/du per parameter and axis, by central differences of 1e-4 in u
        eps = 1e-4
        pts = np.vstack([u + eps * np.eye(len(u)), u - eps * np.eye(len(u))])
        prm = _params_at(model, data, pts)
        base = getattr(model.force_model, "base", None)
        ringed = bool(np.any(np.asarray(getattr(model.force_model, "ringed", True))))
        axes = [a for a in pl.AXES.values() if base is not None and (ringed or not a.ringed_only)]
        for i in np.flatnonzero(flat):
            nodes_per_u = 0.0
            for axis in axes:
                c = np.asarray(axis.coord(prm, base), float)  # [2 dim, rows]
                d = np.nanmax(np.abs(c[i] - c[len(u) + i])) / (2 * eps) if np.isfinite(c[i]).any() else 0.0
                nodes_per_u = max(nodes_per_u, float(d) / axis.step if np.isfinite(d) else 0.0)
            edge = min(EDGE_STEP / nodes_per_u, LATTICE_SD * 0.5) if nodes_per_u > 1e-9 else 0.0
            steps[i] = max(steps[i], edge)  # never narrower than what the curvature that exists says
    return steps


def _params_at(model: HierarchicalModel, data: CalibrationData, u: np.ndarray):
    """SimParams (fields ``[K, N]``) of the rows at unconstrained points ``u`` [K, dim]."""
    return _params_program(model, data, np.asarray(np.atleast_2d(u), float))


@eqx.filter_jit
def _params_program(model: HierarchicalModel, data: CalibrationData, u):
    # one program per point count: run eagerly, the vmapped transforms compiled ~40 small
    # XLA programs in a cold demo (issue 40)
    return jax.vmap(lambda xx: model.sim_params(xx, data))(model.to_physical(u))


def fit_force_model(
    model: HierarchicalModel,
    data: CalibrationData,
    res: MapResult,
    *,
    starts: int = 4,
    seed: int = 0,
    progress: bool = False,
) -> tuple[HierarchicalModel, MapResult]:
    """Grow the force model until it holds the MAP +- ``LATTICE_SD`` Laplace sd.

    The exact force model holds simulator planes only where fits need them. The MAP is
    searched with the model held at its lattice's edge (no NaN for the optimiser); while
    the MAP sits within ``EDGE_MARGIN`` nodes of an edge, the lattice grows ``EDGE_STEP`` nodes past it
    and the MAP is searched again from there; once it is inside, the lattice grows to
    the MAP +- ``LATTICE_SD`` Laplace sd (a Hessian taken at an edge would measure the
    lattice, not the data), per parameter: a parameter the Hessian leaves undetermined
    grows only the axes it moves, ``EDGE_STEP`` nodes (:func:`_lattice_steps`). An axis
    grows only where the MAP or the posterior's box reaches past it, never as a default.
    At most ``LATTICE_ROUNDS`` rounds; models valid everywhere return at once. Returns the
    model for sampling (strict: NaN outside the lattice) and the MAP."""
    enable_x64()  # float64 physics: mfdesign._x64
    from mfdesign.models.force import ForceModel

    fm = model.force_model
    if not isinstance(fm, ForceModel):
        return model, res
    for _ in range(LATTICE_ROUNDS):
        at_map = _params_at(model, data, np.asarray(res.u)[None])
        if not fm.covers(at_map, margin=EDGE_MARGIN):  # past the edge it sits on, only
            grown = fm.covering(at_map, progress=progress, margin=EDGE_STEP, edge=EDGE_MARGIN)
        else:
            # The box the posterior needs, per parameter (``_lattice_steps``): its Laplace
            # width where the Hessian gives one; where it does not, only the axes that
            # parameter moves grow (once ``EDGE_STEP`` nodes on both sides of every axis:
            # a default, not what the data asked for).
            u = np.asarray(res.u)
            steps = np.diag(_lattice_steps(model, data, res))
            grown = fm.covering(_params_at(model, data, np.vstack([u, u + steps, u - steps])), progress=progress)
        if grown is fm:
            break
        fm = grown
        model = eqx.tree_at(lambda m: m.force_model, model, fm)
        res = find_map(model, data, starts=starts, seed=seed, u0=res.u)
    return eqx.tree_at(lambda m: m.force_model, model, fm.strict(True)), res


def _cover_starts(model: HierarchicalModel, data: CalibrationData, progress: bool) -> HierarchicalModel:
    """The force model grown to hold the MAP search's start (prior median): the cell around it on every
    axis the parameters move (the MAP search then grows it where it goes)."""
    from mfdesign.models.force import ForceModel

    if not isinstance(model.force_model, ForceModel):
        return model
    u0 = model.to_unconstrained(model.initial_physical())
    # Small steps of every parameter: each constant the parameters move gets its axis.
    pts = np.vstack([u0, u0 + 0.01 * np.eye(model.dim), u0 - 0.01 * np.eye(model.dim)])
    fm = model.force_model.covering(_params_at(model, data, pts), progress=progress, margin=0)
    return eqx.tree_at(lambda m: m.force_model, model, fm)


def map_on_lattice(
    model: HierarchicalModel, data: CalibrationData, *, starts: int = 4, seed: int = 0, progress: bool = False
) -> tuple[HierarchicalModel, MapResult]:
    """The MAP as :func:`calibrate` finds it before sampling: the force model grown to hold
    the search's start, :func:`find_map`, then :func:`fit_force_model` (the lattice grown
    around the MAP). Returns the model for sampling and the MAP."""
    model = _cover_starts(model, data, progress)
    res = find_map(model, data, starts=starts, seed=seed)
    return fit_force_model(model, data, res, starts=starts, seed=seed, progress=progress)


def _strict(fm, strict: bool):
    from mfdesign.models.force import ForceModel

    return fm.strict(strict) if isinstance(fm, ForceModel) else fm


def _reaches_edge(model: HierarchicalModel, data: CalibrationData, u_s: np.ndarray) -> str:
    """A problem line when posterior samples leave the force model's lattice (else '')."""
    from mfdesign.models.force import ForceModel

    fm = model.force_model
    if not isinstance(fm, ForceModel) or len(u_s) == 0:
        return ""
    pick = np.linspace(0, len(u_s) - 1, min(len(u_s), 256)).astype(int)
    if fm.covers(_params_at(model, data, u_s[pick])):
        return ""
    return (
        "posterior samples reach the edge of the exact force model's lattice of simulator planes: the "
        "posterior is truncated there; rerun (the lattice grows around the new MAP) or widen the priors' support"
    )


def _ball(result: MapResult, n_walkers: int, scale: float, rng: np.random.Generator) -> np.ndarray:
    h = np.asarray(result.hessian)
    width = np.full(h.shape[0], 1e-3)
    try:
        cov = np.linalg.inv(0.5 * (h + h.T))
        d = np.diag(cov)
        if np.all(np.isfinite(d)) and np.all(d > 0):
            width = np.clip(scale * np.sqrt(d), 1e-5, 0.5)
    except np.linalg.LinAlgError:
        pass
    return np.asarray(result.u)[None, :] + width[None, :] * rng.standard_normal((n_walkers, h.shape[0]))


LAPLACE_SHARE = 0.6  # of the first round's steps: independence proposals from the Laplace approximation
# Ends of the adaptation rounds (burn-in): round 1 uses the Laplace approximation at the MAP,
# every later round the independence proposal refitted to the draws of the round before.
# With 28 parameters (22 membranes' latents) the Laplace widths were up to 2.5x the
# posterior's and one refit on 100 correlated steps left the chain at acceptance 0.09 and
# tau ~25-40 (14 tau in 2000 steps, not converged); an independence proposal's acceptance
# falls fast with the error of its covariance in many dimensions, and every round's draws
# come from a better proposal, so the estimate improves round by round
# (experiments/bench_chain_latents.py).
ADAPT_ROUNDS = (50, 100, 200, 300)
ADAPT_STEPS = ADAPT_ROUNDS[-1]  # burn-in of the default moves (see calibrate)
ADAPTED_SHARE = 0.8  # of the later rounds' steps: independence proposals fitted to the walkers
ADAPTED_INFLATE = 1.1  # scale factor s of the fitted proposal (log weights' variance ~ d (1 - 1/s^2)^2 / 2)
LAPLACE_DF = 5.0  # Student-t dof of the first round (the Laplace approximation may fit badly)


def adapted_df(dim: int) -> float:
    """Student-t dof of the fitted proposal: ``2 dim`` (at least ``LAPLACE_DF``). A t with few
    dof spreads its draws' radius far wider than a near-Gaussian posterior's in many
    dimensions (the exact posterior covariance and 5 dof accept ~0.4 of the proposals in
    28 dimensions, 2 dim dof ~0.6); 2 dim keeps the t's polynomial tails."""
    return max(LAPLACE_DF, 2.0 * dim)


def _mixture(mean, cov, share: float, inflate: float, df: float = LAPLACE_DF) -> list:
    """``share`` of the steps independence proposals (Student-t with ``df`` dof at ``mean``
    with scale ``cov``), the rest differential evolution and its snooker update (ter Braak
    2006; ter Braak & Vrugt 2008); DE alone where ``cov`` is not positive definite or ``share`` <= 0."""
    import emcee

    from mfdesign.calibration.laplace_move import LaplaceMove

    de = [(emcee.moves.DEMove(), 0.8), (emcee.moves.DESnookerMove(), 0.2)]
    if share <= 0:
        return de
    try:
        lap = LaplaceMove(mean, cov, df=df, inflate=inflate)
    except np.linalg.LinAlgError:
        return de
    if not np.all(np.isfinite(lap.chol)):
        return de
    return [(lap, share)] + [(m, (1 - share) * w) for m, w in de]


def adapted_moves(draws: np.ndarray) -> list:
    """The moves of an adaptation round after the first, and of the chain after them: the
    independence proposal with the mean and covariance of ``draws`` [K, dim] (the round
    before's), ``adapted_df(dim)`` dof, scale ``ADAPTED_INFLATE``, for ``ADAPTED_SHARE`` of
    the steps, differential evolution for the rest (it keeps exploring where the Student-t
    fits badly)."""
    draws = np.asarray(draws, float)
    return _mixture(
        np.mean(draws, 0), np.cov(draws.T), ADAPTED_SHARE, inflate=ADAPTED_INFLATE, df=adapted_df(draws.shape[1])
    )


def default_moves(result: MapResult, laplace_share: float | None = None) -> list:
    """emcee moves of the first adaptation round: independence proposals from the Laplace
    approximation at the MAP (:class:`~mfdesign.calibration.laplace_move.LaplaceMove`) for
    ``laplace_share`` of the steps, differential evolution for the rest."""
    share = LAPLACE_SHARE if laplace_share is None else float(laplace_share)
    h = np.asarray(result.hessian)
    try:
        cov = np.linalg.inv(0.5 * (h + h.T))
    except np.linalg.LinAlgError:
        return _mixture(None, None, 0.0, 1.0)
    return _mixture(np.asarray(result.u), cov, share, inflate=1.3, df=LAPLACE_DF)


def _laplace_start(result: MapResult, n_walkers: int, rng: np.random.Generator) -> np.ndarray | None:
    """Walkers drawn from the Laplace approximation at the MAP (Gaussian, the inverse
    Hessian as covariance), each coordinate's offsets shrunk to at most 0.5 in ``u`` a
    standard deviation (as :func:`_ball` caps its widths: the exact force model's lattice
    holds ``LATTICE_SD`` of them); None where the Hessian is not positive definite. The
    start of the default moves: a tight ball grows to the posterior's spread only through
    differential evolution (tens of steps in 28 dimensions), and an independence proposal
    fitted to an ensemble narrower than the posterior stays too narrow (on a 30-dimensional
    Gaussian like tests/calibration/test_default_moves.py's, Laplace widths 2x too wide:
    from a 0.1-sd ball the rounds ended at 0.86 of its spread, tau 19 after them; from the
    Laplace draws at 1.0, tau 6)."""
    h = np.asarray(result.hessian, float)
    try:
        chol = np.linalg.cholesky(np.linalg.inv(0.5 * (h + h.T)))
    except np.linalg.LinAlgError:
        return None
    if not np.all(np.isfinite(chol)):
        return None
    sd = np.sqrt(np.sum(chol**2, axis=1))
    z = (rng.standard_normal((n_walkers, h.shape[0])) @ chol.T) * np.minimum(1.0, 0.5 / np.maximum(sd, 1e-300))
    return np.asarray(result.u)[None, :] + z


def convergence_report(
    sampler, names: Sequence[str], min_ratio: float = MIN_TAU_RATIO, warn: bool = True, discard: int = 0
) -> dict[str, Any]:
    """Integrated autocorrelation times, chain length / tau, mean acceptance, over the
    chain after its first ``discard`` steps (the adaptation stage); warns when that chain
    is shorter than ``min_ratio`` tau or the acceptance is outside ``ACCEPTANCE_RANGE``."""
    import emcee

    chain = sampler.get_chain(discard=discard)
    n_after = int(chain.shape[0])  # the steps the autocorrelation time is measured on
    n_steps = n_after + int(discard)
    tau = np.asarray(emcee.autocorr.integrated_time(chain, tol=0, quiet=True), float)
    acc = float(np.mean(sampler.acceptance_fraction))
    ratio = float(n_after / np.max(tau)) if np.all(np.isfinite(tau)) else 0.0
    report = {
        "n_steps": n_steps,
        "n_steps_after_adapt": n_after,
        "n_walkers": int(chain.shape[1]),
        "tau": {n: float(t) for n, t in zip(names, tau)},
        "tau_max": float(np.max(tau)),
        "steps_over_tau": ratio,
        "min_steps_over_tau": min_ratio,
        "acceptance": acc,
        "acceptance_range": list(ACCEPTANCE_RANGE),
        "adapt_steps": int(discard),
    }
    problems = []
    if not np.all(np.isfinite(tau)):
        # a chain too short (or too stuck) for emcee to estimate tau at all: a NaN here
        # crashed the report (math.ceil) of a 40-step campaign smoke run
        bad = [n for n, t in zip(names, tau) if not np.isfinite(t)]
        problems.append(
            f"chain of {n_after} steps (after {discard} adaptation steps) is too short to estimate the "
            f"autocorrelation time of {', '.join(bad[:3])}{' ...' if len(bad) > 3 else ''}; want >= {min_ratio:g} tau"
        )
    elif ratio < min_ratio:
        worst = names[int(np.argmax(tau))]
        problems.append(
            f"chain of {n_after} steps (after {discard} adaptation steps) is {ratio:.1f} tau long (tau_max {np.max(tau):.1f} for "
            f"{worst}); want >= {min_ratio:g} tau, i.e. >= {math.ceil(min_ratio * np.max(tau))} steps"
        )
    if not ACCEPTANCE_RANGE[0] <= acc <= ACCEPTANCE_RANGE[1]:
        problems.append(f"mean acceptance fraction {acc:.2f} outside {list(ACCEPTANCE_RANGE)}")
    report["converged"] = not problems
    report["problems"] = problems
    if problems and warn:
        warnings.warn("; ".join(problems), ConvergenceWarning, stacklevel=2)
    return report


def _fingerprint(model: HierarchicalModel, data: CalibrationData) -> str:
    h = hashlib.sha256()
    h.update(json.dumps({"names": model.names, "effects": model.effects, "lik": model.likelihood}).encode())
    for a in (data.force_n, data.rows.h_mm, data.rows.p_pa):
        h.update(np.asarray(a).tobytes())
    return h.hexdigest()[:20]


def _stored_map(path: Path, fingerprint: str):
    import h5py

    if not path.exists():
        return None
    with h5py.File(path, "r") as f:
        if "mfdesign" not in f:
            return None
        g = f["mfdesign"]
        if g.attrs.get("fingerprint") != fingerprint:
            raise ValueError(
                f"{path} holds a chain of another model or data set (fingerprint {g.attrs.get('fingerprint')} "
                f"!= {fingerprint}); use a new file or resume=False to overwrite it"
            )
        return {k: np.asarray(g[k]) for k in ("u", "x", "hessian")} | {
            "log_post": float(g.attrs["log_post"]),
            "converged": bool(g.attrs["converged"]),
        }


def _store_map(path: Path, fingerprint: str, res: MapResult, names) -> None:
    import h5py

    with h5py.File(path, "a") as f:
        if "mfdesign" in f:
            del f["mfdesign"]
        g = f.create_group("mfdesign")
        g.attrs["fingerprint"] = fingerprint
        g.attrs["names"] = json.dumps(list(names))
        g.attrs["log_post"] = float(res.log_post)
        g.attrs["converged"] = bool(res.converged)
        for k in ("u", "x", "hessian"):
            g.create_dataset(k, data=np.asarray(getattr(res, k)))


def calibrate(
    data,
    model: HierarchicalModel,
    *,
    n_walkers: int | None = None,
    n_steps: int = 3000,
    chain_path: str | os.PathLike | None = None,
    resume: bool = True,
    pool=None,
    seed: int = 0,
    progress: bool = True,
    max_rows: int | None = 3000,
    map_starts: int = 4,
    ball: float = 0.1,
    callback: Callable[[int], None] | None = None,
    warn: bool = True,
    moves=None,
    stop_when_converged: bool = False,
    check_every: int = 50,
) -> Posterior:
    """Sample the posterior of ``model`` given ``data`` with emcee; stop when converged.

    The MAP (optimistix BFGS from ``map_starts`` starts) seeds a Gaussian ball of walkers;
    the default moves are differential evolution mixed with its snooker update (ter Braak
    2006; ter Braak & Vrugt 2008), which mix faster than the stretch move on these
    posteriors. With ``stop_when_converged`` the chain stops once it is ``MIN_TAU_RATIO``
    times the longest autocorrelation time and that estimate moved < 5 % since the last
    check (emcee's documented monitoring recipe).

    **Arguments:**

    - `data`: the measurements (:class:`~mfdesign.data.measurements.Measurements`, or a
      prepared :class:`~mfdesign.models.hierarchical.CalibrationData`).
    - `model`: the :class:`~mfdesign.models.hierarchical.HierarchicalModel` (force model,
      effects, priors, likelihood).
    - `n_walkers`: emcee walkers (default `max(32, 2 dim + 2)`).
    - `n_steps`: total chain length (the most steps with `stop_when_converged`); a resumed
      run samples only the missing steps.
    - `chain_path`: HDF5 file of the chain (`emcee.backends.HDFBackend`, group `"mcmc"`; the
      MAP is stored beside it, group `"mfdesign"`); `None`: in memory.
    - `resume`: continue the chain in `chain_path` (`False` starts over).
    - `pool`: anything with `map` (multiprocessing, an MPI pool from schwimmbad).
    - `seed`: random seed of the starts and walkers.
    - `progress`: progress bars.
    - `max_rows`: rows the likelihood uses (evenly within trials; `None`: all).
    - `map_starts`: optimiser starts of the MAP search.
    - `ball`: width of the walkers' start ball in Laplace standard deviations (when the
      default moves adapt, the walkers start from the Laplace approximation instead).
    - `callback`: called with the iteration after every step.
    - `warn`: emit a `ConvergenceWarning` when the chain has not converged.
    - `moves`: emcee moves (default above).
    - `stop_when_converged`: stop early once converged (above).
    - `check_every`: steps between convergence checks.

    **Returns:**

    A :class:`~mfdesign.calibration.posterior.Posterior`: constrained samples, the MAP, the
    convergence report (R-hat, ESS, tau; `converged` says whether to trust it) and
    `to_inference_data()` for ArviZ.
    """
    enable_x64()  # float64 physics: mfdesign._x64
    import emcee

    if not isinstance(data, CalibrationData):
        data = CalibrationData.from_measurements(data, max_rows=max_rows, seed=seed)
    if model.uses_latents and model.n_membranes != len(data.design_keys):
        raise ValueError(
            f"model has {model.n_membranes} membrane latents but the data hold "
            f"{len(data.design_keys)} membranes; build it with build_model(force_model, data)"
        )
    dim = model.dim
    n_walkers = int(n_walkers or max(32, 2 * dim + 2))
    if n_walkers < 2 * dim:
        raise ValueError(f"emcee needs n_walkers >= 2 * dim = {2 * dim}, got {n_walkers}")
    if n_steps < 1:
        raise ValueError(f"n_steps must be >= 1, got {n_steps}")
    fp = _fingerprint(model, data)

    backend, stored = None, None
    if chain_path is not None:
        chain_path = Path(chain_path)
        chain_path.parent.mkdir(parents=True, exist_ok=True)
        if not resume and chain_path.exists():
            chain_path.unlink()
        stored = _stored_map(chain_path, fp) if resume else None
        from mfdesign.calibration.chain_file import ChainFile

        backend = ChainFile(str(chain_path), name="mcmc")
    model = eqx.tree_at(lambda m: m.force_model, model, _strict(model.force_model, False))
    if stored is not None:
        res = MapResult(*(jnp.asarray(stored[k]) for k in ("u", "x", "log_post", "hessian", "converged")))
        model, _ = fit_force_model(model, data, res, starts=map_starts, seed=seed, progress=progress)
    else:
        model, res = map_on_lattice(model, data, starts=map_starts, seed=seed, progress=progress)
        if backend is not None:
            backend.reset(n_walkers, dim)
            _store_map(chain_path, fp, res, model.names)
    if not bool(res.converged):
        warnings.warn(
            "the MAP search (BFGS) did not report convergence; walkers start at its best point",
            ConvergenceWarning,
            stacklevel=2,
        )

    # Adaptation rounds when the moves are ours (ADAPT_ROUNDS): the first with the Laplace
    # approximation at the MAP, each later one with the independence proposal refitted to
    # the draws of the round before (the MAP's Hessian misjudges the hierarchy's spread:
    # there tau stayed ~20 steps, on the walkers' own covariance it is a few). The rounds
    # are burn-in; the chain after the last is sampled with a fixed kernel (the proposal
    # fitted to the last round), so it is an ordinary MCMC chain. Each round's moves
    # follow from the stored chain alone, so a resumed run rebuilds them.
    adapt = ADAPT_STEPS if moves is None and n_steps >= 3 * ADAPT_STEPS else 0
    first = default_moves(res) if moves is None else moves
    logp = LogPosterior(model, data, pool=pool)  # the model as the lattice fit left it
    if backend is None:
        backend = emcee.backends.Backend()  # in memory, shared by every round's sampler
        backend.reset(n_walkers, dim)
    done = int(backend.iteration)
    if done and backend.shape != (n_walkers, dim):
        raise ValueError(f"{chain_path} holds {backend.shape} walkers x dim, asked for {(n_walkers, dim)}")

    def sampler_with(mv):
        return emcee.EnsembleSampler(n_walkers, dim, logp, vectorize=True, backend=backend, moves=mv)

    def run(sampler, upto: int, start) -> bool:
        """Sample up to iteration ``upto``; True when stopped as converged."""
        old_tau = np.inf
        for _ in sampler.sample(start, iterations=max(upto - int(backend.iteration), 0), progress=progress):
            it = int(sampler.iteration)
            if callback is not None:
                callback(it)
            if stop_when_converged and it > adapt and (it - adapt) % max(int(check_every), 1) == 0:
                tau = np.asarray(sampler.get_autocorr_time(discard=adapt, tol=0, quiet=True), float)
                if (
                    np.all(np.isfinite(tau))
                    and it - adapt >= MIN_TAU_RATIO * np.max(tau)
                    and np.all(np.abs(old_tau - tau) < 0.05 * tau)
                ):
                    return True
                old_tau = tau
        return False

    sampler = sampler_with(first)
    if done == 0:
        sampler.random_state = np.random.RandomState(seed).get_state()
        rng = np.random.default_rng(seed)
        start = _laplace_start(res, n_walkers, rng) if adapt else None  # over-dispersed, not a ball
        start = _ball(res, n_walkers, ball, rng) if start is None else start
    else:
        start = sampler.get_last_sample()  # continue from the stored walkers (and random state)
    begin = 0
    for end in ADAPT_ROUNDS if adapt else ():
        if done < end:
            run(sampler, end, start)
            start = sampler.get_last_sample()
        sampler = sampler_with(adapted_moves(backend.get_chain(discard=begin, flat=True)[: (end - begin) * n_walkers]))
        start = sampler.get_last_sample()
        begin = end
    run(sampler, n_steps, start)

    report = convergence_report(sampler, model.names, warn=warn, discard=adapt)
    tau_max = report["tau_max"] if np.isfinite(report["tau_max"]) else 1.0
    burn = adapt + int(min(max(2 * tau_max, 1), (sampler.iteration - adapt) // 2))
    # a chain too short for an autocorrelation estimate has NaN taus: no thinning then
    # (int(NaN) raised "cannot convert float NaN to integer" on --mcmc-steps 1)
    taus = [t for t in report["tau"].values() if np.isfinite(t)] if report["tau"] else []
    thin = max(1, int(min(taus) / 2)) if taus else 1
    report.update(burn=burn, thin=thin, map_converged=bool(res.converged), resumed_from=done)
    u_s = sampler.get_chain(discard=burn, thin=thin, flat=True)
    lp_s = sampler.get_log_prob(discard=burn, thin=thin, flat=True)
    x_s = np.asarray(model.to_physical(u_s))
    # the same draws per walker [draw, walker, dim] (physical) for ArviZ: chain x draw
    x_chain = np.asarray(model.to_physical(sampler.get_chain(discard=burn, thin=thin)))
    lp_chain = np.asarray(sampler.get_log_prob(discard=burn, thin=thin))
    from mfdesign.calibration.posterior import arviz_diagnostics

    report.update(arviz_diagnostics(x_chain, model.names))
    # The sampler saw NaN (rejected) outside the force model's lattice: a chain that
    # presses on its edge is truncated there, not converged.
    edge = _reaches_edge(model, data, u_s)
    if edge:
        report["problems"].append(edge)
        report["converged"] = False
        if warn:
            warnings.warn(edge, ConvergenceWarning, stacklevel=2)

    x_map = np.asarray(res.x)
    # Rows outside the physical model at the MAP (a force above p pi R^2: the membrane
    # below the clamp plane) are not data of this fit: counted, said, and left out of the
    # MAP's log-likelihood and the rows BIC counts.
    w = np.asarray(data.weight, float)
    outside = np.asarray(model.outside_rows(res.x, data), bool)
    ll_map = float(np.sum(np.where(outside, 0.0, w * np.asarray(model.pointwise_log_lik(res.x, data)))))
    n_rows = float(np.sum(w[~outside]))
    report["outside_model_rows"] = int(outside.sum())
    if outside.any() and warn:
        warnings.warn(
            f"{int(outside.sum())} of {outside.size} rows are outside the physical model at the MAP (the force "
            "model's force there is above p pi R^2: the membrane would leave the clamp below the clamp plane); "
            "they are left out of the likelihood",
            OutsideModelWarning,
            stacklevel=2,
        )
    sign, logdet = np.linalg.slogdet(np.asarray(res.hessian))
    laplace = float(res.log_post) + 0.5 * dim * math.log(2 * math.pi) - 0.5 * logdet if sign > 0 else float("nan")
    bic = dim * math.log(n_rows) - 2.0 * ll_map
    units = tuple(s.unit for s in model.specs)
    return Posterior(
        model.names,
        units,
        x_s,
        lp_s,
        x_map,
        ll_map,
        n_rows,
        bic,
        laplace,
        report,
        tuple(data.design_keys),
        tuple(model.effects),
        x_chain,
        lp_chain,
        force_model=model.force_model,
    )
