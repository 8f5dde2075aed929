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
cost one compilation, not three), or one for every fidelity when the predictor takes the
fidelity as data (``fidelity_as_data``: :class:`~mfdesign.models.predictive.MultiFidelityPredictor`;
a budget's smaller counts are then padded to the largest with masked slots, while that
padding is cheap: :data:`SHARED_MAX_PADDING`). The final batch is the
best of (a) each arm's best joint batch and (b) a cost-benefit greedy mix over the pool of
all optimised designs of all arms (Leskovec et al. 2007, "Cost-effective outbreak
detection in networks"; ``U`` is a facility-location function, hence submodular), which
lets one batch mix ring counts and fidelities. A batch never holds one membrane twice
(``MIN_SEPARATION``): when one design has the largest deviation for every member, no second
design adds to ``U``, and the next slot goes to the most uncertain distinct design per cost.

A lab's round: ``budget={"rig": Q, "sim": S}`` fixes the runs per fidelity (``Q``
membranes to fabricate, ``S`` simulator planes the tool makes); ``pending`` membranes
(being built) count as measured, ``U(B | P) = sum_m max(max_j d_m(x_j), P_m) - sum_m P_m``
with ``P_m`` the largest deviation of member ``m`` over the pending membranes (BoTorch's
``X_pending``); :attr:`Proposal.runs` ranks the batch by marginal reduction, each run with
a reason computed from the grid (:func:`explain`). The acquisition
(:class:`BatchUncertainty`) is apart from the optimiser's start heuristic
(:func:`initial_batches`) and its L-BFGS, as BoTorch separates ``AcquisitionFunction``
from ``optim.initializers``.
"""

from __future__ import annotations

import dataclasses
import itertools
import math
import time
from typing import Mapping, Sequence

import equinox as eqx
import jax
import jax.numpy as jnp
import numpy as np
import optax

from mfdesign._x64 import enable_x64
from mfdesign.errors import InputError
from mfdesign.design import DesignError, DesignSpace, Membrane  # noqa: F401
from mfdesign.models.predictor import (  # noqa: F401  (re-exported: acquisition's inputs)
    AbstractPredictor,
    EnsemblePredictor,
    FunctionPredictor,
    Grid,
    SplitPredictor,
)
from mfdesign.physics._traces import stored_jit

__all__ = [
    "FIDELITIES",
    "DEFAULT_COSTS",
    "Grid",
    "AbstractPredictor",
    "EnsemblePredictor",
    "SplitPredictor",
    "FunctionPredictor",
    "BatchUncertainty",
    "Proposal",
    "Run",
    "deviations",
    "batch_utility",
    "pending_deviation",
    "initial_batches",
    "evaluate",
    "explain",
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


def batch_utility(dev, pending=None):
    """Paper's batch score ``sum_m max_j d[m, j]`` (N) from deviations ``[M, q]``.

    ``pending`` ``[M]`` (N): what designs already being built reach per member, ``max_p
    d_m(x_p)``; the score is then the batch's reduction beyond them, ``sum_m max(max_j
    d[m, j], pending_m) - sum_m pending_m`` (zero for a batch that only repeats them).
    """
    best = jnp.max(dev, axis=-1)  # [M, ...]
    if pending is None:
        return jnp.sum(best, axis=0)
    pending = jnp.reshape(pending, jnp.shape(pending) + (1,) * (best.ndim - 1))
    return jnp.sum(jnp.maximum(best, pending), axis=0) - jnp.sum(pending, axis=0)


class BatchUncertainty(eqx.Module):
    """The acquisition function, apart from any optimiser (BoTorch's split of
    ``AcquisitionFunction`` and ``optim.initializers``): the batch utility ``U(B | P)`` (N)
    of a batch of designs ``[q, 6]`` mm run at ``fidelity``, given the pending designs'
    per-member deviations ``pending`` ``[M]`` (N; zeros when nothing is pending, which
    gives the paper's ``U(B)`` exactly). Pending designs count as already measured (as
    BoTorch's ``X_pending``): a member they already tell from the consensus adds nothing
    when the batch tells it again. A pytree: one compilation serves any predictor of the
    same structure and any pending set of the same member count."""

    predictor: AbstractPredictor
    pending: jax.Array  # [M] N
    # a name (static: one compiled program per fidelity), or, for a predictor that takes
    # the fidelity as data (``fidelity_as_data``), an integer index into its fidelities
    # (:func:`_fidelity_arg`): one program serves every fidelity
    fidelity: str | jax.Array
    grid: Grid = eqx.field(static=True)

    def deviation(self, design):
        """Deviations ``[M, q]`` (N) of designs ``[q, 6]`` mm on the grid."""
        return deviations(self.predictor.grid_members(self.fidelity, design, self.grid))

    def __call__(self, design):
        """``U(B | P)`` (N) of designs ``[q, 6]`` mm."""
        return batch_utility(self.deviation(design), self.pending)


def _fidelity_arg(predictor: AbstractPredictor, fidelity: str):
    """``fidelity`` as the compiled kernels take it: an index array (data) for a predictor
    whose members take the fidelity as data (``fidelity_as_data``, e.g.
    :class:`~mfdesign.models.predictive.MultiFidelityPredictor`), so that every fidelity
    shares one compiled program; the name (static) otherwise."""
    if getattr(predictor, "fidelity_as_data", False):
        predictor.check_fidelity(fidelity)
        return jnp.asarray(predictor.fidelities.index(fidelity), jnp.int32)
    return fidelity


@stored_jit(fast_compile=True)
def _grid_members(predictor, fidelity, design, grid):
    return predictor.grid_members(fidelity, design, grid)


@eqx.filter_jit
def _deviation(predictor, fidelity, design, grid):
    return deviations(predictor.grid_members(fidelity, design, grid))


def _rows(designs) -> np.ndarray:
    """Membranes or ``[6]`` rows (mm) -> ``[n, 6]`` rows."""
    return np.stack([d.to_array() if isinstance(d, Membrane) else np.asarray(d, float) for d in designs])


def pending_deviation(predictor: AbstractPredictor, pending, grid: Grid = Grid()) -> np.ndarray:
    """``max_p d_m^rig(x_p)`` ``[M]`` (N) of the pending membranes (Membranes or ``[6]``
    rows, mm; being fabricated, so at the ``rig`` fidelity); ``[0.0]`` when none (it
    broadcasts over the members, and every deviation is > 0, so the score is unchanged)."""
    if len(pending) == 0:
        return np.zeros(1)
    fid = _fidelity_arg(predictor, _PENDING_FIDELITY)
    return np.asarray(_deviation(predictor, fid, jnp.asarray(_rows(pending)), grid)).max(axis=1)


# Pending designs are membranes being fabricated: their measurements will be rig data.
_PENDING_FIDELITY = "rig"


def evaluate(
    predictor: AbstractPredictor,
    designs,
    fidelities: Sequence[str],
    grid: Grid = Grid(),
    costs: Mapping[str, float] | None = None,
    pending: Sequence = (),
) -> dict:
    """Score a given batch: ``designs`` (Membranes or ``[q, 6]`` rows), one fidelity each.

    Returns ``utility`` (N, the paper's number for an all-rig batch; with ``pending``
    membranes, the reduction beyond theirs, ``U(B | P)``), ``cost``, ``score`` = utility /
    cost and ``deviation`` ``[q, M]``.
    """
    enable_x64()  # float64 physics: mfdesign._x64
    rows = _rows(designs)
    if len(fidelities) != len(rows):
        raise ValueError(f"one fidelity per design: {len(rows)} designs, {len(fidelities)} fidelities")
    costs = _check_costs(fidelities, costs)
    dev = [None] * len(rows)
    for f in dict.fromkeys(fidelities):  # one compiled call per fidelity
        idx = [j for j, g in enumerate(fidelities) if g == f]
        d = np.asarray(
            _deviation(predictor, _fidelity_arg(predictor, f), jnp.asarray(rows[idx]), grid)
        )  # [M, len(idx)]
        for k, j in enumerate(idx):
            dev[j] = d[:, k]
    dev = np.stack(dev, axis=0)  # [q, M]
    base = pending_deviation(predictor, pending, grid)
    utility = float(np.maximum(dev.max(axis=0), base).sum() - base.sum())
    cost = float(sum(costs[f] for f in fidelities))
    return {"utility": utility, "cost": cost, "score": utility / cost, "deviation": dev}


# --------------------------------------------------------------------------- optimiser
# Restarts screened per block: the ensemble's hidden activations for a block of restarts
# are [M, block, q, heights, width]; blocks keep them to tens of MB at 1,000+ restarts.
SCREEN_BLOCK = 128


def _masked(dev, mask):
    """Deviations ``[M, q]`` with the padding slots (``mask`` [q] False) at 0: every
    deviation is > 0, so a padding slot never wins a member's max (:func:`batch_utility`)
    and its coordinates get no gradient."""
    return dev if mask is None else jnp.where(mask, dev, 0.0)


@stored_jit(fast_compile=True)
def _screen(acq: BatchUncertainty, u0, n_rings, space):
    """Forward pass only: ``u0 [A, R, q, 6]`` (unit cube) -> deviations ``[A, R, q, M]``
    of every random batch (``jax.lax.map`` over blocks of ``SCREEN_BLOCK`` restarts)."""

    def one(u, n):
        return acq.deviation(space.decode_any(u, n)).T  # [q, M]

    def arm(u, n):
        return jax.lax.map(lambda ui: one(ui, n), u, batch_size=SCREEN_BLOCK)

    return jax.vmap(arm)(u0, n_rings)


def initial_batches(acq: BatchUncertainty, u0, n_rings, space: DesignSpace, n_best: int, mask=None):
    """The optimiser's start heuristic, apart from the acquisition (BoTorch's raw-sample
    screen, ``optim.initializers``): random batches ``u0 [A, R, q, 6]`` (unit cube) of ring
    counts ``n_rings [A]`` are scored by one forward pass of ``acq`` and the best ``n_best``
    per ring count kept, ``[A, n_best, q, 6]`` (all of them when ``n_best >= R``).
    ``mask`` [q]: the batch's slots (False: padding, left out of the score)."""
    if n_best >= u0.shape[1]:
        return u0
    dev0 = np.asarray(_screen(acq, u0, n_rings, space))  # [A, R, q, M]
    if mask is not None:
        dev0 = np.where(np.asarray(mask)[:, None], dev0, 0.0)
    util0 = np.asarray(batch_utility(np.moveaxis(dev0, -1, 0), acq.pending))  # [A, R]
    util0 = np.nan_to_num(util0, nan=-np.inf)
    order = np.argsort(-util0, axis=1, kind="stable")[:, :n_best]
    return jnp.take_along_axis(u0, jnp.asarray(order)[:, :, None, None], axis=1)


# Backtracking steps of L-BFGS's line search. Under vmap every restart waits for the one
# that backtracks most, so this caps the cost of each iteration: on the 2-core CPU, 100
# restarts x 20 iterations (q = 2, 32 members, 8 x 8 grid) took 20.3 s with 4 and 39.2 s
# with 10, with the same designs and utility (experiments/bench_acquire.py --restarts 100).
LINESEARCH_STEPS = 4


@stored_jit(fast_compile=True)
def _optimise(acq: BatchUncertainty, z0, n_rings, space, n_steps, mask=None):
    """``z0 [A, R, q, 6]``, ring counts ``n_rings [A]`` -> ``(u [A, R, q, 6], dev [A, R, q, M])``:
    every restart of every ring count runs ``n_steps`` L-BFGS iterations on ``-acq``
    (``jax.vmap`` over ring counts and restarts: one compiled call per fidelity, or one for
    all when the fidelity is data, reused for any predictor of the same structure, e.g. a
    refitted ensemble). The ring count is data
    (:meth:`~mfdesign.design.DesignSpace.decode_any`), so it costs no extra compilation.
    ``mask`` [q]: the batch's slots; False marks padding (:func:`_masked`: no score, no
    gradient, so its coordinates stay where they start and the others' L-BFGS steps are
    those of the unpadded batch)."""
    # The line search evaluates the utility only (no stored gradient): each step takes one
    # value-and-gradient at its start and forward passes at the line search's candidates.
    # optax's stored-gradient route (``store_grad=True`` + ``value_and_grad_from_state``)
    # traced the gradient twice, and under ``vmap`` its ``lax.cond`` runs both branches, so
    # every step paid a gradient at the start anyway (issue 40: XLA 13.3 s + tracing 6.9 s,
    # the cold demo's largest optimiser program).
    opt = optax.lbfgs(linesearch=optax.scale_by_backtracking_linesearch(max_backtracking_steps=LINESEARCH_STEPS))

    def one(z, n):
        def dev_of(z):
            if mask is not None:
                # a padding slot's coordinates carry no gradient, even where its forces are
                # NaN (a zero cotangent times a NaN derivative would be NaN)
                z = jnp.where(mask[:, None], z, jax.lax.stop_gradient(z))
            return acq.deviation(space.decode_any(_to_unit(z), n))  # [M, q]

        def loss(z):
            return -batch_utility(_masked(dev_of(z), mask), acq.pending)

        value_and_grad = jax.value_and_grad(loss)

        def step(carry, _):
            z, state = carry
            value, grad = value_and_grad(z)
            updates, state = opt.update(grad, state, z, value=value, grad=grad, value_fn=loss)
            return (optax.apply_updates(z, updates), state), None

        (z, _), _ = jax.lax.scan(step, (z, opt.init(z)), None, length=n_steps)
        return _to_unit(z), dev_of(z).T

    per_arm = jax.vmap(one, in_axes=(0, None))  # restarts
    return jax.vmap(per_arm, in_axes=(0, 0))(z0, n_rings)  # ring counts


# With the fidelity as data (``fidelity_as_data``) one compiled screen and L-BFGS serve
# every fidelity, each fidelity's batch padded to the largest count (a budget's 2 rig +
# 1 sim: the sim batch gets one masked slot). That saves a compilation (~7 s of a cold
# demo, issue 40) but the padding slots cost L-BFGS steps: with the campaign's defaults (32
# refined restarts x 20 steps x 3 ring counts) the sim arm of a 2 rig + 1 sim budget took
# 168 s instead of 85 s, warm (emulator physics, 16 draws, 100 screened restarts). So
# fidelities share a program only while the padding is at most this many slot-steps
# (:func:`_padding_work`; ~45 ms each on the 2-core CPU with the emulator's physics and
# 16 draws: ~4.5 s, less than the compilation it saves); the demo's 2 restarts x 5 steps
# are 30. Above it every fidelity has its own program, by name, unpadded.
SHARED_MAX_PADDING = 100


def _padding_work(counts, q_pad: int, n_arms: int, n_restarts: int, top: int, n_steps: int) -> int:
    """Slot-steps the padding of ``counts`` (runs per fidelity) to ``q_pad`` adds: L-BFGS
    steps of the refined restarts, and the screen's forward passes (a quarter of a step
    each: no gradient, no line search) when it runs."""
    screened = n_restarts // 4 if top < n_restarts else 0
    return sum((q_pad - q) * n_arms * (top * max(n_steps, 1) + screened) for q in counts)


# --------------------------------------------------------------------------- proposal
@dataclasses.dataclass(frozen=True)
class Run:
    """One run of a proposal, ranked: ``design`` (mm) at ``fidelity``.

    ``rank``: 1 = the largest reduction; ``reduction_n``: what it adds to the batch's
    utility after the runs ranked above it and the pending membranes (N; the runs' sum is
    :attr:`Proposal.utility`); ``alone_n``: its reduction on its own beyond the pending
    membranes (N); ``cost``; ``reason``: one sentence computed from the members on the grid;
    ``reduction_rms_n``: ``reduction_n`` as a spread, N RMS per member and grid point
    (:func:`per_point`).
    """

    rank: int
    design: Membrane
    fidelity: str
    reduction_n: float
    alone_n: float
    cost: float
    reason: str
    reduction_rms_n: float | None = None

    def to_json(self) -> dict:
        return {
            "rank": self.rank,
            "design": self.design.key(),
            "fidelity": self.fidelity,
            "reduction_n": self.reduction_n,
            "reduction_rms_n": self.reduction_rms_n,
            "alone_n": self.alone_n,
            "cost": self.cost,
            "reason": self.reason,
        }


@dataclasses.dataclass(frozen=True)
class Proposal:
    """The chosen batch: ``designs[j]`` to run at ``fidelities[j]``.

    ``scores[j]``: design j alone, ``sum_m d_m(x_j) / c_j`` (N per cost unit);
    ``utility``: ``U(B | P)`` in N (the paper's score ``U(B)`` for an all-rig batch with
    nothing pending); ``cost``; ``score`` = utility / cost; ``deviation`` ``[q, M]``;
    ``arms``: per (ring count, fidelity) the best joint batch found and its restarts'
    utilities; ``wall_s``; ``runs``: the batch ranked (:class:`Run`); ``pending``: the
    membranes being built that the batch counted as measured; ``budget``: runs per
    fidelity when the batch was chosen for a fixed budget (None: a free mix of ``q``).
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
    runs: tuple[Run, ...] = ()
    pending: tuple[Membrane, ...] = ()
    budget: dict | None = None

    @property
    def fabricate(self) -> tuple[Run, ...]:
        """The membranes to fabricate and measure on the rig, ranked."""
        return tuple(r for r in self.runs if r.fidelity == _PENDING_FIDELITY)

    @property
    def simulate(self) -> tuple[Run, ...]:
        """The runs the tool makes itself (simulator planes), ranked."""
        return tuple(r for r in self.runs if r.fidelity != _PENDING_FIDELITY)

    def to_json(self, made: Mapping[int, dict] | None = None) -> dict:
        """JSON-ready dict; ``made``: per simulator run's rank, what making it gave
        (:meth:`mfdesign.sim_runs.MadeRun.to_json`); a run not in it is listed as not made."""
        made = {} if made is None else made
        return {
            "designs": [d.key() for d in self.designs],
            "fidelities": list(self.fidelities),
            "scores": list(self.scores),
            "utility_n": self.utility,
            "cost": self.cost,
            "score": self.score,
            "wall_s": self.wall_s,
            "budget": self.budget,
            "pending": [d.key() for d in self.pending],
            "fabricate": [r.to_json() for r in self.fabricate],
            "simulate": [
                r.to_json() | {"made_by": "the tool (a simulator plane)"} | made.get(r.rank, {"made": False})
                for r in self.simulate
            ],
            "arms": [
                {k: v for k, v in a.items() if k not in ("u", "dev", "restart_utility")}
                | {"restart_utility_quantiles": np.quantile(a["restart_utility"], [0, 0.5, 0.9, 1]).tolist()}
                for a in self.arms
            ],
        }

    def save(self, path, made: Mapping[int, dict] | None = None) -> None:
        from pathlib import Path

        from mfdesign import outputs

        outputs.write_json(Path(path), self.to_json(made))


# The most a call may ask (the CLI's bounds, mfdesign.cli._contract.OPTION_MAX): beyond
# them the arrays of restarts x batch do not fit a machine.
MAX_Q = 256
MAX_RESTARTS = 1_000_000
MAX_REFINE = 100_000
MAX_STEPS = 1_000_000


def _count(name: str, v, low: int, high: int) -> int:
    if not isinstance(v, (int, np.integer)) or isinstance(v, bool) or not low <= v <= high:
        raise InputError(f"{name} must be an integer from {low} to {high:,}, got {v!r}")
    return int(v)


def _checked_arguments(
    predictor, q, fidelities, costs, n_restarts, n_rings, grid, key, space, n_steps, n_refine, budget, pending
):
    """:func:`propose`'s arguments checked (``InputError``, one line, for each bad one):
    ``(fidelities, sizes, costs, n_rings, pending, key)``."""
    if not isinstance(predictor, AbstractPredictor):
        raise InputError(
            f"predictor: a {type(predictor).__name__}; allowed: an AbstractPredictor (EnsemblePredictor(ensemble), "
            "SplitPredictor, FunctionPredictor, or MFFit.load(folder).predictor())"
        )
    if isinstance(fidelities, str) or not isinstance(fidelities, Sequence):
        raise InputError(f"fidelities: {fidelities!r}; allowed: a sequence of names from {list(predictor.fidelities)}")
    if budget is None:
        if not isinstance(q, (int, np.integer)) or isinstance(q, bool) or q < 1:
            raise InputError(f"q (batch size) must be an integer >= 1, got {q!r}")
        _count("q (batch size)", q, 1, MAX_Q)
        fidelities = tuple(dict.fromkeys(fidelities))
        sizes = {f: int(q) for f in fidelities}
    else:
        if q is not None:
            raise InputError("give q (a free mix of fidelities) or budget (runs per fidelity), not both")
        if not isinstance(budget, Mapping):
            raise InputError(f"budget: {budget!r}; allowed: a mapping of fidelity to runs, e.g. {{'rig': 2}}")
        budget = dict(budget)
        for f, k in budget.items():
            if not isinstance(k, (int, np.integer)) or isinstance(k, bool) or k < 0:
                raise InputError(f"budget[{f!r}] (runs at fidelity {f!r}) must be an integer >= 0, got {k!r}")
        sizes = {f: int(k) for f, k in budget.items() if k > 0}
        if not sizes:
            raise InputError(f"the budget holds no run: {budget}")
        _count("the budget's runs", sum(sizes.values()), 1, MAX_Q)
        fidelities = tuple(sizes)
    _count("n_restarts", n_restarts, 1, MAX_RESTARTS)
    _count("n_refine", n_refine, 1, MAX_REFINE)
    _count("n_steps", n_steps, 0, MAX_STEPS)
    if not fidelities:
        raise InputError(f"give at least one fidelity; allowed: {list(predictor.fidelities)}")
    for f in fidelities:
        if f not in predictor.fidelities:
            raise InputError(f"fidelity {f!r} not offered by this model; allowed: {list(predictor.fidelities)}")
    try:
        costs = _check_costs(fidelities, costs)
        n_rings = tuple(dict.fromkeys(n_rings))
    except (ValueError, TypeError) as err:
        raise InputError(str(err) if isinstance(err, InputError) else f"costs or n_rings: {err}") from None
    if not n_rings or any(n not in (0, 1, 2) for n in n_rings):
        raise InputError(f"n_rings must be a non-empty subset of (0, 1, 2), got {n_rings!r}")
    if not isinstance(grid, Grid):
        raise InputError(f"grid: a {type(grid).__name__}; allowed: mfdesign.acquire.Grid")
    if not isinstance(space, DesignSpace):
        raise InputError(f"space: a {type(space).__name__}; allowed: mfdesign.design.DesignSpace")
    try:
        pending = tuple(d if isinstance(d, Membrane) else Membrane.from_array(d) for d in pending)
    except InputError:
        raise
    except (ValueError, TypeError) as err:
        raise InputError(f"pending: {err}; allowed: Membranes or arrays [t, c, r1, w1, r2, w2] mm") from None
    if isinstance(key, (int, np.integer)) and not isinstance(key, bool):
        key = jax.random.PRNGKey(int(key))
    elif not (isinstance(key, jax.Array) and jnp.shape(key) in ((2,), ())):
        raise InputError(f"key: {key!r}; allowed: an int seed or a jax.random key")
    return fidelities, sizes, costs, n_rings, pending, key


def _check_costs(fidelities, costs):
    costs = dict(DEFAULT_COSTS if costs is None else costs)
    for f in fidelities:
        c = costs.get(f)
        if c is None:
            raise InputError(f"no cost given for fidelity {f!r}; give costs={{{f!r}: positive number}}")
        if not (isinstance(c, (int, float)) and math.isfinite(c) and c > 0):
            raise InputError(f"cost of fidelity {f!r} must be a positive finite number, got {c!r}")
    return costs


# Two designs of the same ring count closer than this in every unit-cube coordinate are
# one membrane to the lab (0.1 mm of thickness, 0.6 mm of contact radius): a batch never
# holds both, nor a design near a pending one. Without it, when one design has the largest
# deviation for every member, the paper's score gains ~1e-5 relative from a near-copy and
# the greedy took it as the cheap second slot (seen in the demo: two sim runs 0.001 mm apart).
MIN_SEPARATION = 0.05


def _near_to(units, others) -> np.ndarray:
    """Mask over ``units`` (``_unit_array`` form): which are one membrane with any of
    ``others`` (same ring count, within ``MIN_SEPARATION`` in every coordinate)."""
    (n, x), (m, y) = units, others
    if len(m) == 0:
        return np.zeros(len(n), bool)
    close = (n[:, None] == m[None, :]) & (np.max(np.abs(x[:, None, :] - y[None, :, :]), axis=2) < MIN_SEPARATION)
    return close.any(axis=1)


def _near(units, j: int) -> np.ndarray:
    """Mask over ``units`` ``[(n_rings, unit-cube coordinates)]``: which are one membrane
    with ``units[j]``."""
    n, x = units
    return _near_to(units, (n[j : j + 1], x[j : j + 1]))


def _unit_array(units) -> tuple[np.ndarray, np.ndarray]:
    """``[(n_rings, coordinates)]`` -> ring counts ``[K]`` and coordinates zero-padded to
    ``[K, 6]`` (only equal ring counts are compared, so the padding never matters)."""
    x = np.zeros((len(units), 6))
    for i, (_, u) in enumerate(units):
        x[i, : len(u)] = u
    return np.array([n for n, _ in units], dtype=int), x


def _greedy(dev, cost, q, units, base, blocked=None, fids=None, quota=None):
    """Cost-benefit greedy (Leskovec et al. 2007): add the candidate that maximises the
    batch's ``U(B | P) / cost`` among those that add to ``U``; ``dev`` [K, M] deviations,
    ``cost`` [K], ``units`` [K] ``(n_rings, cube coordinates)``, ``base`` [M] (or [1]) the
    pending membranes' deviations. Candidates near a chosen one or a ``blocked`` one (the
    pending membranes; ``MIN_SEPARATION``) are out. With ``quota`` (runs per fidelity) and
    ``fids`` [K], each fidelity gets exactly its number of slots. When no candidate left
    adds to ``U``, the slot goes to the most uncertain one per cost (``sum_m d_m / c``).
    Returns indices [q]."""
    chosen = []
    best = np.broadcast_to(np.asarray(base, float), dev.shape[1:]).copy()
    base_sum = best.sum()
    spent = 0.0
    own = dev.sum(1) / cost
    units = _unit_array(units)
    allowed = np.ones(len(dev), bool) if blocked is None else ~_near_to(units, _unit_array(blocked))
    left = None if quota is None else dict(quota)
    for _ in range(q):
        quota_ok = np.ones(len(dev), bool) if left is None else np.isin(fids, [f for f, k in left.items() if k > 0])
        now = allowed & quota_ok
        total = np.maximum(dev, best[None, :]).sum(1)
        ratio = (total - base_sum) / (spent + cost)
        # A slot must add uncertainty reduction: with q fixed, a cheap candidate that adds
        # nothing would otherwise win as a filler (it lowers U / cost the least).
        useful = now & (total - best.sum() > 1e-9 * max(best.sum(), 1e-300))
        if useful.any():
            score = np.where(useful, ratio, -np.inf)
        else:
            score = np.where(now, own, -np.inf) if now.any() else np.where(quota_ok, ratio, -np.inf)
        j = int(np.argmax(score))
        chosen.append(j)
        best = np.maximum(best, dev[j])
        spent += cost[j]
        allowed &= ~_near(units, j)
        allowed[chosen] = False
        if left is not None:
            left[fids[j]] -= 1
    return chosen


def _rank(dev, base) -> tuple[list[int], list[float], list[float]]:
    """Order a batch by marginal reduction: the run that adds most to ``U(B | P)`` first,
    then the one that adds most after it, ... ``dev`` [q, M], ``base`` [M] or [1]. Returns
    the order, each run's marginal reduction in it (N, summing to ``U(B | P)``) and each
    run's reduction alone (N)."""
    best = np.broadcast_to(np.asarray(base, float), dev.shape[1:]).copy()
    alone = [float(np.maximum(d, best).sum() - best.sum()) for d in dev]
    order, gains, left = [], [], list(range(len(dev)))
    while left:
        g = [np.maximum(dev[j], best).sum() - best.sum() for j in left]
        k = int(np.argmax(g))
        order.append(left.pop(k))
        gains.append(float(g[k]))
        best = np.maximum(best, dev[order[-1]])
    return order, gains, alone


# Grid points whose member spread is at least this fraction of the largest make up the
# region a run's reason names (where the members disagree most).
REASON_FRACTION = 0.8


def _span(values, unit: str, scale: float = 1.0) -> str:
    lo, hi = min(values) / scale, max(values) / scale
    return f"{lo:g} {unit}" if lo == hi else f"{lo:g}-{hi:g} {unit}"


def explain(predictor: AbstractPredictor, design, fidelity: str, grid: Grid = Grid()) -> tuple[str, dict]:
    """Where on the grid the members disagree most for ``design`` (Membrane or ``[6]`` mm)
    at ``fidelity``: the heights (mm) and pressures (Pa) whose member standard deviation
    is within ``REASON_FRACTION`` of its largest value, and that value (N). Returns the
    phrase "at 40-60 mm, 4-6 kPa where the members disagree most (member std up to 3.1 N)"
    and its numbers."""
    row = _rows([design])
    f = np.asarray(_grid_members(predictor, _fidelity_arg(predictor, fidelity), jnp.asarray(row), grid))[:, 0]  # [M, G]
    spread = f.std(axis=0).reshape(len(grid.h_mm), len(grid.p_pa))  # heights outer
    top = float(np.nanmax(spread)) if np.isfinite(spread).any() else float("nan")
    hot = spread >= REASON_FRACTION * top if np.isfinite(top) else np.ones_like(spread, bool)
    hs = [h for h, row_hot in zip(grid.h_mm, hot) if row_hot.any()]
    ps = [p for p, col_hot in zip(grid.p_pa, hot.T) if col_hot.any()]
    phrase = (
        f"at {_span(hs, 'mm')}, {_span(ps, 'kPa', 1e3)} where the members disagree most (member std up to {top:.2g} N)"
    )
    return phrase, {"h_mm": hs, "p_pa": ps, "std_n": top}


def per_point(score_n: float, n_members: int, n_points: int) -> float:
    """A score of :func:`batch_utility` (N: a sum over ``n_members`` of L2 norms over
    ``n_points`` grid points) as a spread in newtons: the members' RMS deviation from their
    mean per grid point, averaged over the members, ``score / (M sqrt(G))``."""
    return float(score_n) / (max(n_members, 1) * math.sqrt(max(n_points, 1)))


def _reason(phrase: str, gain: float, alone: float, rank: int, n_members: int = 1, n_points: int = 1) -> str:
    """One sentence for a ranked run (numbers from :func:`explain` and :func:`_rank`). The
    paper's score is a sum over members of grid norms, not a spread anyone can read off a
    plot: the sentence gives it per member and grid point (:func:`per_point`) and says what
    the sum is."""
    if gain <= 1e-9 * max(alone, 1e-300) or gain <= 0.0:
        return (
            f"adds no reduction beyond the runs ranked above and the pending membranes (alone "
            f"{per_point(alone, n_members, n_points):.3g} N per member and grid point); "
            f"the most uncertain distinct design left, {phrase}"
        )
    after = "" if rank == 1 else " beyond the runs ranked above"
    return (
        f"reduces the spread by {per_point(gain, n_members, n_points):.3g} N RMS per member and grid point{after} "
        f"(the paper's score {gain:.3g} N is that summed over {n_members} members' L2 norms on the "
        f"{n_points}-point grid), most {phrase}"
    )


def propose(
    predictor: AbstractPredictor,
    q: int | None = None,
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
    *,
    budget: Mapping[str, int] | None = None,
    pending: Sequence = (),
) -> Proposal:
    """Choose ``q`` (design, fidelity) pairs maximising expected uncertainty reduction per cost.

    The batch utility is the paper's (module docstring) over the height-pressure grid;
    ``n_restarts`` random joint batches per (ring count, fidelity) are scored, the best
    ``n_refine`` refined by ``n_steps`` L-BFGS iterations, all ring counts and restarts in
    one vmapped, jitted call per fidelity. The acquisition (:class:`BatchUncertainty`) is
    apart from the optimiser's start heuristic (:func:`initial_batches`), as in BoTorch.

    **Arguments:**

    - `predictor`: members per fidelity (:class:`~mfdesign.models.predictor.AbstractPredictor`).
    - `q`: designs in the batch, a free mix of `fidelities` (give `q` or `budget`).
    - `fidelities`: fidelities to choose from (`"rig"`, `"sim"`).
    - `costs`: cost per fidelity (default :data:`DEFAULT_COSTS`).
    - `n_restarts`: random batches scored per (ring count, fidelity).
    - `n_rings`: ring counts to search.
    - `grid`: the height [mm] x pressure [Pa] grid the uncertainty is measured on.
    - `key`: int seed or `jax.random` key.
    - `space`: the design space (bounds; `low == high` fixes a feature).
    - `n_steps`: L-BFGS iterations of each refined batch.
    - `progress`: progress output.
    - `n_refine`: batches refined per (ring count, fidelity).
    - `budget`: runs per fidelity, e.g. `{"rig": 2, "sim": 4}` (2 membranes to fabricate,
      4 simulator planes): the batch holds exactly that many of each.
    - `pending`: membranes already being built (Membranes or `[6]` rows, mm): counted as
      measured on the rig (their members' deviations as if already reduced), so the batch
      adds what they do not and never repeats one of them.

    **Returns:**

    A :class:`Proposal`: the designs (mm), their fidelities, utilities and costs, and the
    runs ranked with a reason each. Raises `InputError` (a `ValueError`) on bad arguments.
    """
    enable_x64()  # float64 physics: mfdesign._x64
    t0 = time.perf_counter()
    fidelities, sizes, costs, n_rings, pending, key = _checked_arguments(
        predictor, q, fidelities, costs, n_restarts, n_rings, grid, key, space, n_steps, n_refine, budget, pending
    )
    q = sum(sizes.values()) if budget is not None else q
    base = pending_deviation(predictor, pending, grid)  # [M], or [1] zeros when none
    blocked = [(d.n_rings, space.encode(d)) for d in pending]

    from tqdm.auto import tqdm

    arms, pool_u, pool_dev, pool_cost, pool_arm = [], [], [], [], []
    n_arr = jnp.asarray(n_rings)
    top = min(int(n_refine), n_restarts)
    q_pad = max(sizes[f] for f in fidelities)
    shared = (
        getattr(predictor, "fidelity_as_data", False)
        and _padding_work([sizes[f] for f in fidelities], q_pad, len(n_rings), n_restarts, top, int(n_steps))
        <= SHARED_MAX_PADDING
    )
    for f, k in zip(
        tqdm(fidelities, desc="acquisition (fidelities)", disable=not progress), jax.random.split(key, len(fidelities))
    ):
        qf = sizes[f]
        acq = BatchUncertainty(predictor, jnp.asarray(base), _fidelity_arg(predictor, f) if shared else f, grid)
        u0 = jax.random.uniform(k, (len(n_rings), n_restarts, qf, 6), minval=0.0, maxval=1.0)
        mask = None
        if shared:
            # padding slots at the cube's centre (z = 0); the real slots' draws are unchanged
            u0 = jnp.concatenate([u0, jnp.full(u0.shape[:2] + (q_pad - qf, 6), 0.5)], axis=2)
            mask = jnp.arange(q_pad) < qf
        ta = time.perf_counter()
        u0 = initial_batches(acq, u0, n_arr, space, top, mask)  # screen, then refine the best starts
        u_all, dev_all = _optimise(acq, jnp.arcsin(2.0 * u0 - 1.0), n_arr, space, int(n_steps), mask)
        # [A, top, q, 6], [A, top, q, M] without the padding slots
        u_all, dev_all = np.asarray(u_all)[:, :, :qf], np.asarray(dev_all)[:, :, :qf]
        wall = time.perf_counter() - ta
        for i, n in enumerate(n_rings):
            u, dev = space.cube_of(u_all[i], n), dev_all[i]  # [top, q, dim], [top, q, M]
            util = np.asarray(batch_utility(np.moveaxis(dev, -1, 0), base))  # [top]
            util = np.where(np.isfinite(util), util, -np.inf)
            r = int(np.argmax(util))
            arms.append(
                {
                    "n_rings": n,
                    "fidelity": f,
                    "best_utility_n": float(util[r]),
                    "best_score": float(util[r] / (qf * costs[f])),
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
            pool_cost.append(np.full(top * qf, costs[f]))
            pool_arm += [f] * (top * qf)

    # (a) best joint batches of the arms (one arm per fidelity: with a budget, every
    # combination of one arm per fidelity), (b) cost-benefit greedy mix over the pool. A
    # joint batch holding one membrane twice, or a pending one (MIN_SEPARATION), is out.
    cands = []
    by_fidelity = [[a for a in arms if a["fidelity"] == f] for f in fidelities]
    combos = [(a,) for a in arms] if budget is None else itertools.product(*by_fidelity)
    pending_units = _unit_array(blocked)
    for combo in combos:
        units = [(a["n_rings"], x) for a in combo for x in a["u"]]
        arr = _unit_array(units)
        if not any(_near(arr, j)[:j].any() for j in range(q)) and not _near_to(arr, pending_units).any():
            fids = [a["fidelity"] for a in combo for _ in a["u"]]
            cands.append((units, fids, np.concatenate([a["dev"] for a in combo])))
    dev_all = np.concatenate(pool_dev)
    dev_all = np.where(np.isfinite(dev_all), dev_all, 0.0)
    idx = _greedy(
        dev_all,
        np.concatenate(pool_cost),
        q,
        pool_u,
        base,
        blocked,
        np.asarray(pool_arm),
        None if budget is None else sizes,
    )
    cands.append(([pool_u[i] for i in idx], [pool_arm[i] for i in idx], dev_all[idx]))

    def utility_of(dev):
        return float(batch_utility(dev.T, base))

    best = max(cands, key=lambda c: utility_of(c[2]) / sum(costs[f] for f in c[1]))
    units, fids, dev = best
    designs = tuple(space.decode(np.asarray(x), n) for n, x in units)
    utility = utility_of(dev)
    cost = float(sum(costs[f] for f in fids))
    scores = tuple(float(dev[j].sum() / costs[fids[j]]) for j in range(q))
    order, gains, alone = _rank(np.where(np.isfinite(dev), dev, 0.0), base)
    n_points = len(grid.h_mm) * len(grid.p_pa)
    runs = []
    for rank, (j, gain) in enumerate(zip(order, gains), start=1):
        phrase, _ = explain(predictor, designs[j], fids[j], grid)
        runs.append(
            Run(
                rank,
                designs[j],
                fids[j],
                gain,
                alone[j],
                float(costs[fids[j]]),
                _reason(phrase, gain, alone[j], rank, dev.shape[1], n_points),
                per_point(gain, dev.shape[1], n_points),
            )
        )
    return Proposal(
        designs,
        tuple(fids),
        scores,
        utility,
        cost,
        utility / cost,
        dev,
        tuple(arms),
        time.perf_counter() - t0,
        tuple(runs),
        pending,
        None if budget is None else sizes,
    )
