"""Batch acquisition over designs and fidelities: which membranes to build or simulate next.

Score (uncertainty reduction per cost). A predictor gives, per fidelity ``f``, ``M`` paired
members ``F_m^f(x, h, p)`` (N): ensemble members or posterior draws, member ``m`` of every
fidelity being one hypothesis about the truth. On a height-pressure grid ``G`` (mm x Pa)
the deviation of member ``m`` at design ``x`` is the L2 norm over the grid

    d_m^f(x) = || F_m^f(x, G) - mean_k F_k^f(x, G) ||_2                      [N]

For a batch ``B = {(x_j, f_j)}_{j=1..q}`` the uncertainty reduction is

    U(B) = sum_m max_j d_m^{f_j}(x_j)                                        [N]

(each hypothesis is refuted by the batch member that best tells it from the consensus),
and the acquisition is ``A(B) = U(B) / sum_j c_{f_j}``. With one fidelity ``rig`` this is
the acquisition of Campbell et al. 2025 ("Active Learning Design: Modeling Force Output
for Axisymmetric Soft Pneumatic Actuators"): sum over ensemble members of the max over the
batch of the L2 deviation on a height-pressure grid; :attr:`Proposal.utility` is exactly
that number and the cost only rescales it. Fidelities: ``rig`` members carry the whole
predictive spread (discrepancy and parameters); ``sim`` members carry only the part a
simulator run informs (the simulator surrogate's spread), never the sim-to-real
discrepancy, so a sim run is worth its low cost only while that part dominates.

Optimisation: for every ring count and fidelity ("arm"), ``n_restarts`` random batches of
``q`` designs are scored in one forward pass (no gradient), and the best ``n_refine`` of
them are optimised jointly by L-BFGS (Liu & Nocedal 1989; ``optax.lbfgs`` with a
backtracking line search) on the unit-cube decoding of
:class:`~mfdesign.design.DesignSpace`. Screening raw samples before a multi-start local
search is BoTorch's initialisation heuristic (Balandat et al. 2020, "BoTorch: A Framework
for Efficient Monte-Carlo Bayesian Optimization"): one forward pass is a small fraction
of a restart's 20 L-BFGS iterations (each a forward pass, a backward pass and the line
search's passes), so L-BFGS is spent only where it starts well. On
``experiments/bench_acquire.py`` 1,000 screened + 32 refined batches took 5.6-7.8 s per
ring count, plain L-BFGS from 100 starts 18.7-20.1 s, for the same utility. The box
``[0, 1]`` is kept by the sine transform of MINUIT (James & Roos 1975):
``u = (1 + sin z) / 2`` with ``z`` unconstrained, so every iterate is a valid design.
Restarts and ring counts run together under ``jax.vmap`` in one ``jax.jit`` per fidelity
(the ring count is data, :meth:`~mfdesign.design.DesignSpace.decode_any`: three ring counts
cost one compilation, not three). The final batch is the
best of (a) each arm's best joint batch and (b) a cost-benefit greedy mix over the pool of
all optimised designs of all arms (Leskovec et al. 2007, "Cost-effective outbreak
detection in networks"; ``U`` is a facility-location function, hence submodular), which
lets one batch mix ring counts and fidelities. A batch never holds one membrane twice
(``MIN_SEPARATION``): when one design has the largest deviation for every member, no second
design adds to ``U``, and the next slot goes to the most uncertain distinct design per cost.
"""

from __future__ import annotations

import dataclasses
import math
import time
from typing import Mapping, Sequence

import equinox as eqx
import jax
import jax.numpy as jnp
import numpy as np
import optax

from mfdesign._x64 import enable_x64
from mfdesign.design import DesignError, DesignSpace, Membrane  # noqa: F401
from mfdesign.models.predictor import (  # noqa: F401  (re-exported: acquisition's inputs)
    AbstractPredictor,
    EnsemblePredictor,
    FunctionPredictor,
    Grid,
    SplitPredictor,
)

__all__ = [
    "FIDELITIES",
    "DEFAULT_COSTS",
    "Grid",
    "AbstractPredictor",
    "EnsemblePredictor",
    "SplitPredictor",
    "FunctionPredictor",
    "Proposal",
    "deviations",
    "batch_utility",
    "evaluate",
    "propose",
]

FIDELITIES = ("rig", "sim")
DEFAULT_COSTS = {"rig": 1.0, "sim": 0.01}  # a rig day vs a simulator plane (issue 7)


def _to_unit(z):
    """MINUIT sine transform: unconstrained ``z`` -> ``u = (1 + sin z) / 2`` in [0, 1]."""
    return 0.5 * (1.0 + jnp.sin(z))


# --------------------------------------------------------------------------- score
def deviations(members):
    """``d[m, b] = ||F[m, b, :] - mean_k F[k, b, :]||_2`` (N) from members ``[M, B, G]``."""
    dev = members - members.mean(axis=0, keepdims=True)
    return jnp.sqrt(jnp.sum(dev**2, axis=-1) + 1e-30)


def batch_utility(dev):
    """Paper's batch score ``sum_m max_j d[m, j]`` (N) from deviations ``[M, q]``."""
    return jnp.sum(jnp.max(dev, axis=-1), axis=0)


@eqx.filter_jit
def _deviation(predictor, fidelity, design, grid):
    return deviations(predictor.grid_members(fidelity, design, grid))


def evaluate(
    predictor: AbstractPredictor,
    designs,
    fidelities: Sequence[str],
    grid: Grid = Grid(),
    costs: Mapping[str, float] | None = None,
) -> dict:
    """Score a given batch: ``designs`` (Membranes or ``[q, 6]`` rows), one fidelity each.

    Returns ``utility`` (N, the paper's number for an all-rig batch), ``cost``, ``score``
    = utility / cost and ``deviation`` ``[q, M]``.
    """
    enable_x64()  # float64 physics: mfdesign._x64
    rows = np.stack([d.to_array() if isinstance(d, Membrane) else np.asarray(d, float) for d in designs])
    if len(fidelities) != len(rows):
        raise ValueError(f"one fidelity per design: {len(rows)} designs, {len(fidelities)} fidelities")
    costs = _check_costs(fidelities, costs)
    dev = [None] * len(rows)
    for f in dict.fromkeys(fidelities):  # one compiled call per fidelity
        idx = [j for j, g in enumerate(fidelities) if g == f]
        d = np.asarray(_deviation(predictor, f, jnp.asarray(rows[idx]), grid))  # [M, len(idx)]
        for k, j in enumerate(idx):
            dev[j] = d[:, k]
    dev = np.stack(dev, axis=0)  # [q, M]
    utility = float(dev.max(axis=0).sum())
    cost = float(sum(costs[f] for f in fidelities))
    return {"utility": utility, "cost": cost, "score": utility / cost, "deviation": dev}


# --------------------------------------------------------------------------- optimiser
# Restarts screened per block: the ensemble's hidden activations for a block of restarts
# are [M, block, q, heights, width]; blocks keep them to tens of MB at 1,000+ restarts.
SCREEN_BLOCK = 128


@eqx.filter_jit
def _screen_fidelity(predictor, u0, n_rings, fidelity, grid, space):
    """Forward pass only: ``u0 [A, R, q, 6]`` (unit cube) -> deviations ``[A, R, q, M]``
    of every random batch (``jax.lax.map`` over blocks of ``SCREEN_BLOCK`` restarts)."""

    def one(u, n):
        return deviations(predictor.grid_members(fidelity, space.decode_any(u, n), grid)).T  # [q, M]

    def arm(u, n):
        return jax.lax.map(lambda ui: one(ui, n), u, batch_size=SCREEN_BLOCK)

    return jax.vmap(arm)(u0, n_rings)


# Backtracking steps of L-BFGS's line search. Under vmap every restart waits for the one
# that backtracks most, so this caps the cost of each iteration: on the 2-core CPU, 100
# restarts x 20 iterations (q = 2, 32 members, 8 x 8 grid) took 20.3 s with 4 and 39.2 s
# with 10, with the same designs and utility (experiments/bench_acquire.py --restarts 100).
LINESEARCH_STEPS = 4


@eqx.filter_jit
def _optimise_fidelity(predictor, z0, n_rings, fidelity, grid, space, n_steps):
    """``z0 [A, R, q, 6]``, ring counts ``n_rings [A]`` -> ``(u [A, R, q, 6], dev [A, R, q, M])``:
    every restart of every ring count runs ``n_steps`` L-BFGS iterations on ``-U``
    (``jax.vmap`` over ring counts and restarts: one compiled call per fidelity, reused for
    any predictor of the same structure, e.g. a refitted ensemble). The ring count is data
    (:meth:`~mfdesign.design.DesignSpace.decode_any`), so it costs no extra compilation."""
    opt = optax.lbfgs(
        linesearch=optax.scale_by_backtracking_linesearch(max_backtracking_steps=LINESEARCH_STEPS, store_grad=True)
    )

    def one(z, n):
        def dev_of(z):
            design = space.decode_any(_to_unit(z), n)  # [q, 6]
            return deviations(predictor.grid_members(fidelity, design, grid))  # [M, q]

        def loss(z):
            return -batch_utility(dev_of(z))

        value_and_grad = optax.value_and_grad_from_state(loss)

        def step(carry, _):
            z, state = carry
            value, grad = value_and_grad(z, state=state)
            updates, state = opt.update(grad, state, z, value=value, grad=grad, value_fn=loss)
            return (optax.apply_updates(z, updates), state), None

        (z, _), _ = jax.lax.scan(step, (z, opt.init(z)), None, length=n_steps)
        return _to_unit(z), dev_of(z).T

    per_arm = jax.vmap(one, in_axes=(0, None))  # restarts
    return jax.vmap(per_arm, in_axes=(0, 0))(z0, n_rings)  # ring counts


# --------------------------------------------------------------------------- proposal
@dataclasses.dataclass(frozen=True)
class Proposal:
    """The chosen batch: ``designs[j]`` to run at ``fidelities[j]``.

    ``scores[j]``: design j alone, ``sum_m d_m(x_j) / c_j`` (N per cost unit);
    ``utility``: ``U(B)`` in N (the paper's score for an all-rig batch); ``cost``; ``score`` =
    utility / cost; ``deviation`` ``[q, M]``; ``arms``: per (ring count, fidelity) the best
    joint batch found and its restarts' utilities; ``wall_s``.
    """

    designs: tuple[Membrane, ...]
    fidelities: tuple[str, ...]
    scores: tuple[float, ...]
    utility: float
    cost: float
    score: float
    deviation: np.ndarray
    arms: tuple[dict, ...]
    wall_s: float

    def to_json(self) -> dict:
        return {
            "designs": [d.key() for d in self.designs],
            "fidelities": list(self.fidelities),
            "scores": list(self.scores),
            "utility_n": self.utility,
            "cost": self.cost,
            "score": self.score,
            "wall_s": self.wall_s,
            "arms": [
                {k: v for k, v in a.items() if k not in ("u", "dev", "restart_utility")}
                | {"restart_utility_quantiles": np.quantile(a["restart_utility"], [0, 0.5, 0.9, 1]).tolist()}
                for a in self.arms
            ],
        }

    def save(self, path) -> None:
        from pathlib import Path

        from mfdesign import outputs

        outputs.write_json(Path(path), self.to_json())


def _check_costs(fidelities, costs):
    costs = dict(DEFAULT_COSTS if costs is None else costs)
    for f in fidelities:
        c = costs.get(f)
        if c is None:
            raise ValueError(f"no cost given for fidelity {f!r}; give costs={{{f!r}: positive number}}")
        if not (isinstance(c, (int, float)) and math.isfinite(c) and c > 0):
            raise ValueError(f"cost of fidelity {f!r} must be a positive finite number, got {c!r}")
    return costs


# Two designs of the same ring count closer than this in every unit-cube coordinate are
# one membrane to the lab (0.1 mm of thickness, 0.6 mm of contact radius): a batch never
# holds both. Without it, when one design has the largest deviation for every member, the
# paper's score gains ~1e-5 relative from a near-copy and the greedy took it as the cheap
# second slot (seen in the demo: two sim runs 0.001 mm apart).
MIN_SEPARATION = 0.05


def _near(units, j: int) -> np.ndarray:
    """Mask over ``units`` ``[(n_rings, unit-cube coordinates)]``: which are one membrane
    with ``units[j]`` (same ring count, within ``MIN_SEPARATION`` in every coordinate)."""
    n, x = units
    return (n == n[j]) & (np.max(np.abs(x - x[j]), axis=1) < MIN_SEPARATION)


def _unit_array(units) -> tuple[np.ndarray, np.ndarray]:
    """``[(n_rings, coordinates)]`` -> ring counts ``[K]`` and coordinates zero-padded to
    ``[K, 6]`` (only equal ring counts are compared, so the padding never matters)."""
    x = np.zeros((len(units), 6))
    for i, (_, u) in enumerate(units):
        x[i, : len(u)] = u
    return np.array([n for n, _ in units]), x


def _greedy(dev, cost, q, units):
    """Cost-benefit greedy (Leskovec et al. 2007): add the candidate that maximises the
    batch's ``U / cost`` among those that add to ``U``; ``dev`` [K, M] deviations, ``cost``
    [K], ``units`` [K] ``(n_rings, cube coordinates)``. Candidates near a chosen one
    (``MIN_SEPARATION``) are out. When no candidate left adds to ``U``, the slot goes to the
    most uncertain one per cost (``sum_m d_m / c``). Returns indices [q]."""
    chosen, best = [], np.zeros(dev.shape[1])
    spent = 0.0
    own = dev.sum(1) / cost
    allowed = np.ones(len(dev), bool)
    units = _unit_array(units)
    for _ in range(q):
        total = np.maximum(dev, best[None, :]).sum(1)
        ratio = total / (spent + cost)
        # A slot must add uncertainty reduction: with q fixed, a cheap candidate that adds
        # nothing would otherwise win as a filler (it lowers U / cost the least).
        useful = allowed & (total - best.sum() > 1e-9 * max(best.sum(), 1e-300))
        if useful.any():
            score = np.where(useful, ratio, -np.inf)
        else:
            score = np.where(allowed, own, -np.inf) if allowed.any() else ratio
        j = int(np.argmax(score))
        chosen.append(j)
        best = np.maximum(best, dev[j])
        spent += cost[j]
        allowed &= ~_near(units, j)
        allowed[chosen] = False
    return chosen


def propose(
    predictor: AbstractPredictor,
    q: int,
    fidelities: Sequence[str] = ("rig",),
    costs: Mapping[str, float] | None = None,
    n_restarts: int = 1000,
    n_rings: Sequence[int] = (0, 1, 2),
    grid: Grid = Grid(),
    key=0,
    space: DesignSpace = DesignSpace(),
    n_steps: int = 20,
    progress: bool = False,
    n_refine: int = 32,
) -> Proposal:
    """Choose ``q`` (design, fidelity) pairs maximising expected uncertainty reduction per cost.

    The batch utility is the paper's (module docstring) over the height-pressure grid;
    ``n_restarts`` random joint batches per (ring count, fidelity) are scored, the best
    ``n_refine`` refined by ``n_steps`` L-BFGS iterations, all ring counts and restarts in
    one vmapped, jitted call per fidelity (start heuristics apart from the utility, as in
    BoTorch).

    **Arguments:**

    - `predictor`: members per fidelity (:class:`~mfdesign.models.predictor.AbstractPredictor`).
    - `q`: designs in the batch.
    - `fidelities`: fidelities to choose from (`"rig"`, `"sim"`).
    - `costs`: cost per fidelity (default :data:`DEFAULT_COSTS`).
    - `n_restarts`: random batches scored per (ring count, fidelity).
    - `n_rings`: ring counts to search.
    - `grid`: the height [mm] x pressure [Pa] grid the uncertainty is measured on.
    - `key`: int seed or `jax.random` key.
    - `space`: the design space (bounds, gaps).
    - `n_steps`: L-BFGS iterations of each refined batch.
    - `progress`: progress output.
    - `n_refine`: batches refined per (ring count, fidelity).

    **Returns:**

    A :class:`Proposal`: the designs (mm), their fidelities, utilities and costs. Raises
    `ValueError` on bad arguments.
    """
    enable_x64()  # float64 physics: mfdesign._x64
    t0 = time.perf_counter()
    if not isinstance(q, (int, np.integer)) or isinstance(q, bool) or q < 1:
        raise ValueError(f"q (batch size) must be an integer >= 1, got {q!r}")
    if not isinstance(n_restarts, (int, np.integer)) or n_restarts < 1:
        raise ValueError(f"n_restarts must be an integer >= 1, got {n_restarts!r}")
    if not isinstance(n_refine, (int, np.integer)) or isinstance(n_refine, bool) or n_refine < 1:
        raise ValueError(f"n_refine must be an integer >= 1, got {n_refine!r}")
    if not isinstance(n_steps, (int, np.integer)) or n_steps < 0:
        raise ValueError(f"n_steps must be an integer >= 0, got {n_steps!r}")
    fidelities = tuple(dict.fromkeys(fidelities))
    if not fidelities:
        raise ValueError(f"give at least one fidelity; allowed: {list(predictor.fidelities)}")
    for f in fidelities:
        if f not in predictor.fidelities:
            raise ValueError(f"fidelity {f!r} not offered by this model; allowed: {list(predictor.fidelities)}")
    costs = _check_costs(fidelities, costs)
    n_rings = tuple(dict.fromkeys(n_rings))
    if not n_rings or any(n not in (0, 1, 2) for n in n_rings):
        raise ValueError(f"n_rings must be a non-empty subset of (0, 1, 2), got {n_rings!r}")
    key = jax.random.PRNGKey(key) if isinstance(key, (int, np.integer)) else key

    from tqdm.auto import tqdm

    arms, pool_u, pool_dev, pool_cost, pool_arm = [], [], [], [], []
    n_arr = jnp.asarray(n_rings)
    for f, k in zip(
        tqdm(fidelities, desc="acquisition (fidelities)", disable=not progress), jax.random.split(key, len(fidelities))
    ):
        u0 = jax.random.uniform(k, (len(n_rings), n_restarts, q, 6), minval=0.0, maxval=1.0)
        ta = time.perf_counter()
        top = min(int(n_refine), n_restarts)
        if top < n_restarts:  # screen, then refine the best starts
            dev0 = np.asarray(_screen_fidelity(predictor, u0, n_arr, f, grid, space))  # [A, R, q, M]
            util0 = np.nan_to_num(dev0.max(axis=2).sum(axis=2), nan=-np.inf)  # [A, R]
            order = np.argsort(-util0, axis=1, kind="stable")[:, :top]
            u0 = jnp.take_along_axis(u0, jnp.asarray(order)[:, :, None, None], axis=1)
        u_all, dev_all = _optimise_fidelity(predictor, jnp.arcsin(2.0 * u0 - 1.0), n_arr, f, grid, space, int(n_steps))
        u_all, dev_all = np.asarray(u_all), np.asarray(dev_all)  # [A, top, q, 6], [A, top, q, M]
        wall = time.perf_counter() - ta
        for i, n in enumerate(n_rings):
            u, dev = space.cube_of(u_all[i], n), dev_all[i]  # [top, q, dim], [top, q, M]
            util = dev.max(axis=1).sum(axis=1)  # [top]
            util = np.where(np.isfinite(util), util, -np.inf)
            r = int(np.argmax(util))
            arms.append(
                {
                    "n_rings": n,
                    "fidelity": f,
                    "best_utility_n": float(util[r]),
                    "best_score": float(util[r] / (q * costs[f])),
                    "wall_s": wall / len(n_rings),
                    "screened": n_restarts,
                    "refined": top,
                    "u": u[r],
                    "dev": dev[r],
                    "restart_utility": util,
                }
            )
            pool_u += [(n, x) for x in u.reshape(-1, u.shape[-1])]
            pool_dev.append(dev.reshape(-1, dev.shape[-1]))
            pool_cost.append(np.full(top * q, costs[f]))
            pool_arm += [f] * (top * q)

    # (a) best joint batch of one arm, (b) cost-benefit greedy mix over the pool.
    # An arm's joint batch whose designs coincide (MIN_SEPARATION) is one membrane twice: out.
    cands = []
    for a in arms:
        units = [(a["n_rings"], x) for x in a["u"]]
        arr = _unit_array(units)
        if not any(_near(arr, j)[:j].any() for j in range(q)):
            cands.append((units, [a["fidelity"]] * q, a["dev"]))
    dev_all = np.concatenate(pool_dev)
    dev_all = np.where(np.isfinite(dev_all), dev_all, 0.0)
    idx = _greedy(dev_all, np.concatenate(pool_cost), q, pool_u)
    cands.append(([pool_u[i] for i in idx], [pool_arm[i] for i in idx], dev_all[idx]))
    best = max(cands, key=lambda c: c[2].max(axis=0).sum() / sum(costs[f] for f in c[1]))
    units, fids, dev = best
    designs = tuple(space.decode(np.asarray(x), n) for n, x in units)
    utility = float(dev.max(axis=0).sum())
    cost = float(sum(costs[f] for f in fids))
    scores = tuple(float(dev[j].sum() / costs[fids[j]]) for j in range(q))
    return Proposal(
        designs, tuple(fids), scores, utility, cost, utility / cost, dev, tuple(arms), time.perf_counter() - t0
    )
