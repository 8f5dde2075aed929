"""Differentiable forward model of diagnosis: a JAX force model + the effects.

:class:`ForwardModel` is what diagnosis calls (screen, refit, check, pipeline): the
force-model family's interface for the expected recorded force of a table's rows
(:class:`~mfdesign.models.force.RecordedForceModel`:
``expected_force(meas, effects, theta, rows) -> F [N] per row`` and its exact derivative
``jacobian``), with the batched refit ``fit``. It evaluates a pure JAX force model
(:class:`~mfdesign.models.force.ForceModel`: ``(design [N, 6] mm, h_mm [N], p_pa [N],
SimParams) -> F [N]``) at every row. Two back ends, built by name with :func:`forward_model`:

* :class:`ExactForwardModel`: simulator planes of the measured membranes
  (:mod:`mfdesign.models.exact`; the default of ``mfdesign diagnose``), whose lattice grows
  where the fits go (kept in a :class:`GrowingLattice`, the one state that changes while a
  diagnosis runs);
* :class:`EmulatorForwardModel`: a force model that holds every simulator constant by
  itself: the simulator's emulator (:func:`mfdesign.models.emulator.load_default`) or
  :class:`~mfdesign.models.standin.StandinForceModel` (the closed-form stand-in, for tests;
  the virtual rig's truth with ``simulator=standin_plane`` is the same formula).

The expected recorded force of a row recorded at ``(h, p)`` with effects ``theta`` is the
calibration's likelihood model (:mod:`mfdesign.physics.effects`, "the likelihood side"),
:func:`~mfdesign.models.force.recorded_force`, the one place that applies the effects::

    params = apply_row_sim_params(effects, theta, base, rows)           # mechanics, per row
    F      = apply_expected_force(effects, theta, force_model(., params), rows)   # measurement chain

with the query height of :func:`~mfdesign.diagnosis.expected.query_heights` (set-point in force
trials) and ``h``, ``p`` clipped to the force model's input range
(:class:`ClippedForceModel`).

Every registered effect with a likelihood hook is applied in one fixed order
(:func:`canonical_order`; effects not in the model sit at their neutral values, which are
exact identities), so one compiled function serves every candidate and every round: the screen's Jacobian is exact forward-mode
autodiff (``jax.jacfwd``) with respect to each parameter at the neutral point, and the full
check refits any subset of parameters by Levenberg-Marquardt (``optimistix``; More 1978)
with a Gaussian prior as extra residuals, for all candidates and folds in one compiled call.
"""

from __future__ import annotations

import abc
from dataclasses import dataclass
from typing import Any, Mapping, Sequence

import equinox as eqx
import jax
import jax.numpy as jnp
import numpy as np

from mfdesign._padding import pad_last, padded_size
from mfdesign.data.measurements import Measurements
from mfdesign.design import Membrane
from mfdesign.diagnosis.expected import query_heights, trial_order
from mfdesign.models.force import ForceModel, RecordedForceModel, recorded_force, row_sim_params
from mfdesign.physics import effects as fx
from mfdesign.physics.params import SimParams
from mfdesign.physics.solve import SimResult
from mfdesign.physics.status import Status
from mfdesign.physics._traces import stored_jit

__all__ = [
    "ClippedForceModel",
    "EmulatorForwardModel",
    "ExactForwardModel",
    "ForwardModel",
    "GrowingLattice",
    "RowTable",
    "canonical_order",
    "effect_order",
    "emulator_plane",
    "forward_model",
    "likelihood_effects",
    "parameter_names",
    "theta_vector",
]

LATTICE_ROUNDS = 4  # refits while the exact model's lattice grows around the optima
UNDEFINED_ROW_COST = 10.0  # residual, in noise floors, of a row whose force is NaN at the trial parameters
CHUNK = 4096  # rows per compiled call (bounds the memory of the emulator's activations)


@dataclass(frozen=True)
class emulator_plane:  # noqa: N801 -- used like a function: VirtualRig(simulator=emulator_plane(emu))
    """A ``VirtualRig(simulator=...)`` adapter: ``force_model`` on the rig's h x p grid.

    Locking is reported as 0 (no bursts) and the membrane's rise as ``p / 250 - h / 2`` mm
    (as :func:`~mfdesign.models.standin.standin_plane`; it ends ringless force trials at the
    rig's contact limit). With it the virtual rig's truth and :class:`EmulatorForwardModel` share
    the same physics, so a sweep tests the diagnosis logic alone.
    """

    force_model: Any
    name: str = "emulator"

    def __repr__(self) -> str:
        return f"emulator_plane({self.name})"

    def __call__(self, design: Membrane, h_grid, p_grid, params: SimParams = SimParams()):
        H, P = np.meshgrid(np.asarray(h_grid, float), np.asarray(p_grid, float), indexing="ij")
        d = np.broadcast_to(np.asarray(design.to_array(), float), (H.size, 6))
        params = jax.tree.map(lambda a: jnp.asarray(a, float), params)
        f = np.asarray(
            _plane_force(self.force_model, jnp.asarray(d), jnp.asarray(H.ravel()), jnp.asarray(P.ravel()), params)
        ).reshape(H.shape)
        return SimResult(
            force_n=f,
            status=np.full(H.shape, int(Status.OK), np.int8),
            max_locking=np.zeros(H.shape),
            max_rise_mm=P / 250.0 - H / 2.0,
            wrinkled=np.zeros(H.shape, bool),
        )


@eqx.filter_jit
def _plane_force(force_model, d, h, p, params):
    return force_model(d, h, p, params)


def likelihood_effects(names: Sequence[str] | None = None) -> list[str]:
    """Registered effects (or ``names``, checked): every effect has its JAX likelihood hook
    (a measurement effect without ``observed_force_fn`` cannot be registered)."""
    return [fx.effect(n).name for n in (sorted(fx.EFFECTS) if names is None else names)]


CHAIN = ("pressure_sensor", "hysteresis", "rig_compliance", "load_cell_offset")


def canonical_order() -> tuple[str, ...]:
    """Effects with a likelihood hook: mechanical ones by name, then ``CHAIN``, then the rest by name."""
    names = likelihood_effects()
    mech = sorted(n for n in names if not fx.effect(n).acts_on_measurement)
    chain = [n for n in CHAIN if n in names]
    return tuple(mech + chain + sorted(n for n in names if n not in mech and n not in chain))


# -- layout: which parameters, in which order ------------------------------------------------------
def effect_order(effects: Sequence[str | fx.Effect] = ()) -> tuple[str, ...]:
    """The canonical order (:func:`canonical_order`): every effect with a likelihood hook, the
    mechanical ones first, then the measurement chain from the inputs outwards (pressure
    sensor, losses, frame, load-cell tare), others by name. ``effects`` are only validated: a
    neutral effect is an exact identity, so one order (and one compiled function) serves every
    model."""
    likelihood_effects([fx.effect(e).name for e in effects])
    return canonical_order()


def parameter_names(order: Sequence[str]) -> tuple[str, ...]:
    """Qualified parameter names (``"effect.param"``) of the effects of ``order``, in order."""
    return tuple(fx.neutral_theta(order))


def theta_vector(order: Sequence[str], theta: Mapping[str, Any] | None) -> np.ndarray:
    """``theta`` (``{"effect.param": value}``, others neutral) as a vector over :func:`parameter_names`."""
    names = parameter_names(order)
    per = fx.split_theta(order, theta)  # validates the names
    flat = {f"{k}.{p}": v for k, d in per.items() for p, v in d.items()}
    return np.array([float(flat[n]) for n in names])


# -- the compiled core ------------------------------------------------------------------------------
class ClippedForceModel(ForceModel):
    """A force model asked at plate heights clipped to ``[0, h_max_mm]`` mm and pressures
    clipped to ``[0, p_max_pa]`` Pa (its input range: effects may push a row's query past
    it, and diagnosis must not ask the model where it does not vouch for a number)."""

    force_model: ForceModel
    h_max_mm: float = eqx.field(static=True)
    p_max_pa: float = eqx.field(static=True)
    name = "clipped"

    def __call__(self, design, h_mm, p_pa, params: SimParams = SimParams()):
        h = jnp.clip(h_mm, 0.0, self.h_max_mm)
        return self.force_model(design, h, jnp.clip(p_pa, 0.0, self.p_max_pa), params)

    def marking(self, mark: bool = True) -> "ClippedForceModel":
        return ClippedForceModel(self.force_model.marking(mark), self.h_max_mm, self.p_max_pa)


@stored_jit(fast_compile=True)
def _forward(force_model: ClippedForceModel, order: tuple, names: tuple, base: SimParams, t0, P, x, design, rows):
    """Expected recorded force [N] of ``rows`` at ``theta = t0 + P @ x`` (all effects of ``order``)."""
    th = t0 + P @ x
    return recorded_force(force_model, design, rows, order, {n: th[i] for i, n in enumerate(names)}, base)


@stored_jit(fast_compile=True)
def _jacobian(force_model, order, names, base, t0, P, x, design, rows):
    return jax.jacfwd(lambda xx: _forward(force_model, order, names, base, t0, P, xx, design, rows))(x)


@stored_jit(fast_compile=True)
def _fit_batch(force_model, order, names, base, design, rows, obs, sigma, t0, P, w, tau, x0, max_steps: int):
    """Levenberg-Marquardt (optimistix) for a batch of problems (leading axis of t0, P, w, tau, x0), in turn:
    residuals ``[sqrt(w) (obs - F(t0 + P x)) / sigma, x / tau]`` (Gaussian-prior MAP)."""
    import optimistix as optx

    def resid(x, args):
        t0_, P_, w_, tau_ = args
        f = _forward(force_model, order, names, base, t0_, P_, x, design, rows)
        # A row the model has no number for costs a fixed miss, not nothing: with a zero
        # residual there, a fit would be drawn to parameters that leave the hard rows
        # undefined (a thinner membrane past the Gent limit "fits" every row it blanks).
        r = jnp.sqrt(w_) * jnp.where(jnp.isfinite(f), (obs - f) / sigma, UNDEFINED_ROW_COST)
        return jnp.concatenate([r, x / tau_])

    solver = optx.LevenbergMarquardt(rtol=1e-6, atol=1e-6)

    def one(t0_, P_, w_, tau_, x0_):
        sol = optx.least_squares(resid, solver, x0_, args=(t0_, P_, w_, tau_), max_steps=max_steps, throw=False)
        return sol.value, sol.result == optx.RESULTS.successful

    # one problem after the other (lax.map): memory of one fit, not of the whole batch
    return jax.lax.map(lambda a: one(*a), (t0, P, w, tau, x0))


@eqx.filter_jit
def _take(design, rows: fx.Rows, idx) -> tuple[jax.Array, fx.Rows]:
    # one program per shape pair: op by op, the design and each of the six row fields
    # compiled a gather of their own (~90 small programs a demo, issue 40)
    return design[idx], rows.take(idx)


def _row_params(order, names, base: SimParams, rows: fx.Rows, thetas) -> SimParams:
    """Simulator constants of every row at each parameter vector of ``thetas`` [B, n]
    (NumPy leaves, leading axis B). One compiled call, the vectors padded to a power of
    two by repeating the last (the lattice covers their box, which a repeat leaves as it
    is): op by op under vmap every (B, rows) pair compiled ~25 small programs (issue 40)."""
    thetas = np.atleast_2d(np.asarray(thetas, float))
    b = len(thetas)
    out = _row_params_of(order, names, base, rows, jnp.asarray(pad_last(thetas, padded_size(b))))
    return jax.tree.map(lambda a: np.asarray(a)[:b], out)


@eqx.filter_jit
def _row_params_of(order, names, base: SimParams, rows: fx.Rows, thetas) -> SimParams:
    return jax.vmap(lambda th: row_sim_params(order, {n: th[i] for i, n in enumerate(names)}, base, rows))(thetas)


def _rows_of(meas: Measurements) -> tuple[jax.Array, fx.Rows]:
    df = meas._df
    keys = df["design_key"].to_numpy(object).astype(str)
    uniq, inv = np.unique(keys, return_inverse=True)
    design = np.stack([Membrane.from_key(k).to_array() for k in uniq])[inv]
    rows = fx.Rows(
        h_mm=jnp.asarray(query_heights(meas)),
        p_pa=jnp.asarray(df["pressure_pa"].to_numpy(float)),
        is_force=jnp.asarray((df["experiment"] == "force").to_numpy()),
        is_deflate=jnp.asarray((df["phase"] == "deflate").to_numpy()),
        is_first_trial=jnp.asarray(trial_order(meas) == 0),
        membrane=jnp.asarray(inv.astype(np.int32)),
    )
    return jnp.asarray(design), rows


# -- caches: the state that changes while a diagnosis runs, kept out of the (immutable) models ------
class RowTable:
    """``(design [N, 6] mm, Rows)`` of measurement tables, memoised per table object (a table
    is not modified once read). An explicit cache: the forward model holding it stays immutable."""

    def __init__(self) -> None:
        self._memo: dict[int, tuple[Measurements, tuple[jax.Array, fx.Rows]]] = {}

    def __call__(self, meas: Measurements) -> tuple[jax.Array, fx.Rows]:
        memo = self._memo.get(id(meas))
        if memo is None or memo[0] is not meas:  # an id reused by a new table
            memo = (meas, _rows_of(meas))
            self._memo[id(meas)] = memo
        return memo[1]


class GrowingLattice:
    """The exact force model as diagnosis grows it. Fits go where the lattice has no planes
    yet; the planes solved for them must stay for every later call of the diagnosis (the
    screen, each candidate's refit, the BIC, the next round), so the grown model is kept
    here, in an explicit cache object, and the forward model holding it stays immutable."""

    def __init__(self, model: ForceModel, progress: bool = False) -> None:
        self.model = model
        self.progress = progress

    def cover(self, params: SimParams, p_max_pa: float | None = None) -> bool:
        """Grow the model to hold every constant of ``params`` (fields of any shape) and, for
        gauge pressures up to ``p_max_pa`` [Pa], every reduced pressure ``p / s`` they need
        (``s = (mu / mu0) tf``: a thinner membrane reads planes above the data's pressures);
        whether it grew."""
        grown = self.model.covering(params, progress=self.progress)
        if p_max_pa is not None:
            grown = grown.reaching(params, p_max_pa, progress=self.progress)
        changed = grown is not self.model
        self.model = grown
        return changed


def _float_params(params: SimParams) -> SimParams:
    return jax.tree.map(lambda a: jnp.asarray(a, float), params)


def _input_max(force_model: ForceModel) -> tuple[float, float]:
    """Highest plate height [mm] and gauge pressure [Pa] ``force_model`` vouches for."""
    rng = force_model.input_ranges()
    return float(rng["height_mm"][1]), float(rng["pressure_pa"][1])


# -- the interface ----------------------------------------------------------------------------------
class ForwardModel(RecordedForceModel):
    """Expected recorded force per row of a measurement table from a JAX force model and the
    effects (module doc): what the screen, the refit, the check and the pipeline call.

    The diagnosis' :class:`~mfdesign.models.force.RecordedForceModel`: a force model
    answers for (design, h, p, simulator constants); this answers for the rows of a
    measurement table through the effects (mechanics per row, then the measurement chain:
    :func:`~mfdesign.models.force.recorded_force`), and is built on a force model.

    A back end provides the force model, the plain model's constants ``base_params``
    (authors'), the force model's input range (``h_max_mm`` mm, ``p_max_pa`` Pa: queries are
    clipped to it), a :class:`RowTable`, and :meth:`cover`: how its force model comes to
    hold the simulator constants a call needs. Evaluation, derivatives and fits are here, once.
    """

    h_max_mm: eqx.AbstractVar[float]
    p_max_pa: eqx.AbstractVar[float]
    tables: eqx.AbstractVar[RowTable]

    @abc.abstractmethod
    def cover(self, meas: Measurements, order: tuple, thetas: np.ndarray, rows: np.ndarray | None = None) -> bool:
        """Make the force model hold the simulator constants of the rows ``rows`` of ``meas``
        (default: all) at each parameter vector of ``thetas`` [B, n_params] (over
        :func:`parameter_names` of ``order``); returns whether the force model changed.
        Called before every evaluation and after every fit."""

    # -- data -----------------------------------------------------------------------------------
    @property
    def clipped(self) -> ClippedForceModel:
        """The current force model with its inputs clipped to its range (what every row is
        asked); rows outside the physical model read ``+inf`` (``ForceModel.marking``: a fit
        treats them as undefined rows, :meth:`expected_force` as NaN, :meth:`outside_model` counts them)."""
        return ClippedForceModel(self.force_model, self.h_max_mm, self.p_max_pa).marking(True)

    def table(self, meas: Measurements, rows: np.ndarray | None = None) -> tuple[jax.Array, fx.Rows]:
        """``(design [N, 6] mm, Rows)`` of ``meas`` (or of its rows ``rows``)."""
        design, rws = self.tables(meas)
        if rows is None:
            return design, rws
        return _take(design, rws, jnp.asarray(rows))

    # -- evaluation -----------------------------------------------------------------------------
    def _eval(self, fn, meas, rows, order, t0, P, x) -> np.ndarray:
        """``fn`` (:func:`_forward` or :func:`_jacobian`) on the rows ``rows`` of ``meas``
        (None: all), in chunks of :data:`CHUNK` rows gathered from the whole table: one
        gather program whatever the subset (a subset taken first compiled a gather per
        subset size, ~30 small programs a cold diagnosis, issue 40)."""
        design, table = self.tables(meas)
        idx_all = np.arange(int(design.shape[0])) if rows is None else np.asarray(rows, np.int64)
        n = len(idx_all)
        names = parameter_names(order)
        fm = self.clipped
        args = tuple(jnp.asarray(np.asarray(a, float)) for a in (t0, P, x))
        out = []
        for a in range(0, n, CHUNK):
            b = min(a + CHUNK, n)
            # the last chunk repeats its last row up to CHUNK: every chunk shares one compile
            idx = jnp.asarray(idx_all[np.minimum(np.arange(a, a + CHUNK), n - 1)])
            d, r = (design, table) if rows is None and n == CHUNK else _take(design, table, idx)
            out.append(np.asarray(fn(fm, order, names, self.base_params, *args, d, r))[: b - a])
        return np.concatenate(out, axis=0)

    def expected_force(
        self,
        meas: Measurements,
        effects: Sequence[str | fx.Effect] = (),
        theta: Mapping[str, Any] | None = None,
        rows: np.ndarray | None = None,
    ) -> np.ndarray:
        """Expected observed force [N] per row of ``meas`` (or of its rows ``rows``) with
        ``effects`` at ``theta`` (``{"effect.param": value}``; parameters not given neutral);
        NaN where the model has no number (rows outside the physical model among them)."""
        f = self._marked_force(meas, effects, theta, rows)
        return np.where(np.isposinf(f), np.nan, f)

    def outside_model(
        self,
        meas: Measurements,
        effects: Sequence[str | fx.Effect] = (),
        theta: Mapping[str, Any] | None = None,
        rows: np.ndarray | None = None,
    ) -> np.ndarray:
        """Rows [N] bool of ``meas`` (or of its rows ``rows``) outside the physical model with
        ``effects`` at ``theta``: the force model's force there is above ``p pi R^2``
        (``Status.OUTSIDE_MODEL``); :meth:`expected_force` has NaN there."""
        return np.isposinf(self._marked_force(meas, effects, theta, rows))

    def _marked_force(self, meas, effects, theta, rows) -> np.ndarray:
        order = effect_order(effects)
        fx.split_theta([fx.effect(e) for e in effects], theta)  # a name outside ``effects`` is an error
        t = theta_vector(order, theta)
        self.cover(meas, order, t[None], rows)
        return self._eval(_forward, meas, rows, order, t, np.zeros((len(t), 1)), np.zeros(1))

    def jacobian(
        self,
        meas: Measurements,
        free: Sequence[str],
        effects: Sequence[str | fx.Effect] = (),
        theta: Mapping[str, Any] | None = None,
        rows: np.ndarray | None = None,
        pad_cols: int = 0,
    ) -> np.ndarray:
        """Exact ``dF/dtheta`` [N per unit, rows x len(free)] (``jax.jacfwd``) of the expected force
        with respect to the parameters ``free`` (``"effect.param"``) at ``theta`` (others neutral).
        Every call computes one column per parameter of the order (at least ``pad_cols``),
        zeros beyond ``free``: one compiled shape serves any ``free``."""
        order = effect_order(effects)
        names = parameter_names(order)
        missing = [f for f in free if f not in names]
        if missing:
            raise KeyError(f"no parameter(s) {missing}; known: {list(names)}")
        t = theta_vector(order, theta)
        # One column per parameter of the order, whatever ``free`` holds: the screen's rounds
        # ask for 16, then 14 (the found effect's out), the refit for KMAX = 4, and each
        # count was its own compile (~5 s each on the exact model, issue 40). The padding
        # costs less: on 1,000 rows of the exact model a call took 0.18 s with 16 columns
        # against 0.08 s with 4 (the bundled data, compiled).
        k = max(len(names), pad_cols, 1)
        P = np.zeros((len(names), k))
        for j, f in enumerate(free):
            P[names.index(f), j] = 1.0
        # Beside theta, not only at it: a mechanical effect at its neutral value moves no
        # constant, so covering theta alone adds no lattice axis for it, and its derivative
        # came out 0 (a hidden clamp pre-stretch was ranked 7th by the screen). One side
        # suffices (a one-node axis differentiates as a forward difference) and halves the
        # planes a cold screen solves; a fit that goes the other way grows the axis there.
        steps = JACOBIAN_COVER_STEP * P[:, : len(free)].T
        self.cover(meas, order, np.vstack([t[None], t + steps]), rows)
        return self._eval(_jacobian, meas, rows, order, t, P, np.zeros(k))[:, : len(free)]

    def fit(
        self,
        meas: Measurements,
        rows: np.ndarray,
        target: np.ndarray,
        order: tuple,
        t0: np.ndarray,
        P: np.ndarray,
        w: np.ndarray,
        tau: np.ndarray,
        x0: np.ndarray,
        sigma: float,
        max_steps: int = 60,
        pad_rows: int | None = None,
    ) -> tuple[np.ndarray, np.ndarray]:
        """Batch of Gaussian-prior MAP fits ``x [B, k]`` (see :func:`_fit_batch`) on ``rows`` of ``meas``
        against ``target`` [N] (one per row of ``rows``); returns ``(x, converged [B])``. ``pad_rows``: pad the rows
        (weight 0) to this many, so that data sets of other sizes reuse the compiled fit."""
        n, pad = len(rows), max(pad_rows or 0, len(rows))
        rows = np.concatenate([rows, np.full(pad - n, rows[0])])  # weight 0: equal shapes share one compile
        target = np.concatenate([np.asarray(target, float), np.zeros(pad - n)])
        w = np.concatenate([np.asarray(w, float), np.zeros((len(w), pad - n))], axis=1)
        design, rws = self.table(meas, rows)
        t0, P = np.asarray(t0, float), np.asarray(P, float)
        names = parameter_names(order)
        # The exact model's lattice grows where the fits go: fit with the model held at the
        # lattice's edge, grow it around the optima (and the start), refit from there.
        x = np.asarray(x0, float)
        self.cover(meas, order, t0 + np.einsum("bij,bj->bi", P, x), rows)
        for _ in range(LATTICE_ROUNDS):
            x, ok = self._fit_chunks(design, rws, target, order, names, sigma, t0, P, w, tau, x, max_steps)
            if not self.cover(meas, order, t0 + np.einsum("bij,bj->bi", P, x), rows):
                break
        return x, ok

    def _fit_chunks(self, design, rws, target, order, names, sigma, t0, P, w, tau, x, max_steps):
        """:func:`_fit_batch` on chunks of :data:`FIT_CHUNK` problems: a batch of any size
        runs one compiled program (its size was in the shapes: 8 and 12 problems were two
        compiles of ~10 s, issue 40). The fits run one after the other anyway (``lax.map``),
        so chunks cost no speed; the last one is filled with inert problems (weight 0, start
        0, no free direction: their residuals are 0 at the start, so they stop at once)."""
        b = len(x)
        m = -(-b // FIT_CHUNK) * FIT_CHUNK
        fill = lambda a, v: np.concatenate([a, np.full((m - b,) + a.shape[1:], v, float)])  # noqa: E731
        args = (
            np.concatenate([t0, np.broadcast_to(t0[:1], (m - b,) + t0.shape[1:])]),
            fill(P, 0.0),
            fill(np.asarray(w, float), 0.0),
            fill(np.asarray(tau, float), 1.0),
            fill(x, 0.0),
        )
        xs, oks = [], []
        for a in range(0, m, FIT_CHUNK):
            xc, okc = _fit_batch(
                self.clipped,
                order,
                names,
                self.base_params,
                design,
                rws,
                jnp.asarray(target, float),
                float(sigma),
                *(jnp.asarray(v[a : a + FIT_CHUNK], float) for v in args),
                int(max_steps),
            )
            xs.append(np.asarray(xc))
            oks.append(np.asarray(okc))
        return np.concatenate(xs)[:b], np.concatenate(oks)[:b]


JACOBIAN_COVER_STEP = 1e-3  # parameter units: a step that reaches the first lattice node of its axis
# Problems per compiled fit call: a full check's batch is candidate sets x (1 + 3 folds)
FIT_CHUNK = 4


# -- the back ends ----------------------------------------------------------------------------------
class EmulatorForwardModel(ForwardModel):
    """A force model that holds every simulator constant by itself (its ``covering`` returns
    it unchanged): the emulator inside its training ranges, the stand-in. Nothing grows.

    ``force_model``: e.g. :func:`~mfdesign.models.emulator.load_default` or
    :class:`~mfdesign.models.standin.StandinForceModel`; ``base_params``: the simulator
    constants of the plain model (default: authors').
    """

    force_model: ForceModel
    base_params: SimParams
    h_max_mm: float = eqx.field(static=True)
    p_max_pa: float = eqx.field(static=True)
    tables: RowTable = eqx.field(static=True, repr=False)

    def __init__(self, force_model: ForceModel, base_params: SimParams = SimParams()):
        self.force_model = force_model
        self.base_params = _float_params(base_params)
        self.h_max_mm, self.p_max_pa = _input_max(force_model)
        self.tables = RowTable()

    def cover(self, meas: Measurements, order: tuple, thetas: np.ndarray, rows: np.ndarray | None = None) -> bool:
        return False  # the force model holds every constant already


class ExactForwardModel(ForwardModel):
    """Simulator planes of the measured membranes (:class:`~mfdesign.models.exact.ExactForceModel`,
    mechanical effects on additive lattice axes): the lattice grows where the calls and fits
    go (:class:`GrowingLattice`; planes are solved once, then come from memory or disk).

    ``force_model``: the starting model (:func:`forward_model` builds it); ``base_params``:
    the simulator constants of the plain model (the planes' reference); ``progress``:
    progress bars while planes are solved.
    """

    lattice: GrowingLattice = eqx.field(static=True, repr=False)
    base_params: SimParams
    h_max_mm: float = eqx.field(static=True)
    p_max_pa: float = eqx.field(static=True)
    tables: RowTable = eqx.field(static=True, repr=False)

    def __init__(self, force_model: ForceModel, base_params: SimParams = SimParams(), progress: bool = False):
        self.lattice = GrowingLattice(force_model, progress)
        self.base_params = _float_params(base_params)
        self.h_max_mm, self.p_max_pa = _input_max(force_model)  # the grid, which growth keeps
        self.tables = RowTable()

    @property
    def force_model(self) -> ForceModel:
        """The lattice as grown so far."""
        return self.lattice.model

    def cover(self, meas: Measurements, order: tuple, thetas: np.ndarray, rows: np.ndarray | None = None) -> bool:
        # a subset padded to a power of two by its last row (its constants are among the
        # others'): one program per size class, not per subset size (issue 40)
        _, rws = self.table(meas, None if rows is None else pad_last(rows, padded_size(len(rows))))
        params = _row_params(order, parameter_names(order), self.base_params, rws, thetas)
        # the rows' highest gauge pressure: at s it reads the planes at p / s (the planes
        # start at twice the data's top, room for the pressure chain's gain)
        return self.lattice.cover(params, p_max_pa=float(np.nanmax(np.asarray(rws.p_pa, float), initial=0.0)))


def forward_model(physics: str, meas: Measurements, *, cache=None, progress: bool = False) -> ForwardModel:
    """Diagnosis' forward model on ``physics`` (:data:`~mfdesign.models.force.FORCE_MODELS`).

    Arguments:
        physics: ``"exact"`` (simulator planes of the measured membranes, at simulator
            accuracy; mechanical effects on additive lattice axes that grow where the
            fits go), ``"emulator"`` (the bundled neural emulator; about 1 N RMS off the
            simulator) or ``"standin"`` (the analytic stand-in; tests).
        meas: the measurements (the exact model needs their designs and ranges).
        cache: plane cache folder (exact; default ``$MFDESIGN_CACHE_DIR/planes``).
        progress: progress bars while planes are solved.
    """
    from mfdesign.models.backends import force_model_for

    if physics != "exact":
        return EmulatorForwardModel(force_model_for(physics))
    df = meas._df
    if len(df) == 0:
        raise ValueError("no rows to diagnose")
    # The screen differentiates every candidate at neutral (a step of each parameter,
    # :meth:`ForwardModel.jacobian`): its planes are solved with the reference ones.
    order = canonical_order()
    names = parameter_names(order)
    t0 = np.array([fx.neutral_theta(order)[n] for n in names], float)
    steps = t0 + JACOBIAN_COVER_STEP * np.eye(len(names))
    base = SimParams()
    _, rows = _rows_of(meas)
    some = np.unique(np.linspace(0, len(df) - 1, min(len(df), 256)).astype(int))  # per-row effects vary
    fm = force_model_for(
        "exact",
        tuple(dict.fromkeys(df["design_key"])),
        h_max_mm=float(np.nanmax(query_heights(meas))),
        p_max_pa=float(df["pressure_pa"].max()),
        base=base,
        progress=progress,
        cache=cache,
        grow="additive",
        also=_row_params(order, names, base, rows.take(jnp.asarray(some)), steps),
    )
    return ExactForwardModel(fm, base_params=base, progress=progress)
