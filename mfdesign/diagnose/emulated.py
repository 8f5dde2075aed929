"""Differentiable forward model of diagnosis: a JAX force model + the effects.

:class:`EmulatorModel` (``expected_force(meas, effects, theta) -> F [N] per row``, ``predict``,
``jacobian``, ``fit``) evaluates a pure JAX ``force_model(design [N, 6] mm, h_mm [N], p_pa [N],
SimParams) -> F [N]`` at every row: the exact model (simulator planes of the measured
membranes, :mod:`mfdesign.models.exact`; the default of ``mfdesign diagnose``), the
simulator's emulator (:func:`mfdesign.models.emulator.load_default`), or
:class:`~mfdesign.models.standin.StandinForceModel` (the closed-form stand-in, for tests;
the virtual rig's truth with ``simulator=standin_plane`` is the same formula).
:func:`forward_model` builds one.

The expected recorded force of a row recorded at ``(h, p)`` with effects ``theta`` is the
calibration's likelihood model (:mod:`mfdesign.physics.effects`, "the likelihood side")::

    params = apply_row_sim_params(effects, theta, base, rows)           # mechanics, per row
    F      = apply_expected_force(effects, theta, force_model(., params), rows)   # measurement chain

with the query height of :func:`~mfdesign.diagnose.expected.query_heights` (set-point in force
trials) and ``h``, ``p`` clipped to the force model's range (``h_range_mm``, ``p_range_pa``).

Every registered effect with a likelihood hook is applied in one fixed order
(:func:`canonical_order`; effects not in the model sit at their neutral values, which are
exact identities), so one compiled function serves every candidate and every round: the screen's Jacobian is exact forward-mode
autodiff (``jax.jacfwd``) with respect to each parameter at the neutral point, and the full
check refits any subset of parameters by Levenberg-Marquardt (``optimistix``; More 1978)
with a Gaussian prior as extra residuals, for all candidates and folds in one compiled call.
"""

from __future__ import annotations

from dataclasses import dataclass, field
from typing import Any, Mapping, Sequence

import equinox as eqx
import jax
import jax.numpy as jnp
import numpy as np

from mfdesign.data.measurements import Measurements
from mfdesign.design import Membrane
from mfdesign.diagnose.expected import query_heights, trial_order
from mfdesign.physics import effects as fx
from mfdesign.physics.params import SimParams
from mfdesign.physics.solve import SimResult
from mfdesign.physics.status import Status

__all__ = ["EmulatorModel", "emulator_plane", "forward_model", "likelihood_effects"]

LATTICE_ROUNDS = 4  # refits while the exact model's lattice grows around the optima
CHUNK = 4096  # rows per compiled call (bounds the memory of the emulator's activations)


@dataclass(frozen=True)
class emulator_plane:  # noqa: N801 -- used like a function: VirtualRig(simulator=emulator_plane(emu))
    """A ``VirtualRig(simulator=...)`` adapter: ``force_model`` on the rig's h x p grid.

    Locking is reported as 0 (no bursts) and the membrane's rise as ``p / 250 - h / 2`` mm
    (as :func:`~mfdesign.models.standin.standin_plane`; it ends ringless force trials at the
    rig's contact limit). With it the virtual rig's truth and :class:`EmulatorModel` share
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


# -- the compiled core ------------------------------------------------------------------------------
@eqx.filter_jit
def _forward(
    force_model,
    order: tuple,
    names: tuple,
    base: SimParams,
    t0,
    P,
    x,
    design,
    rows: fx.Rows,
    h_max: float,
    p_max: float,
):
    """Expected recorded force [N] of ``rows`` at ``theta = t0 + P @ x`` (all effects of ``order``)."""
    th = t0 + P @ x
    theta = {n: th[i] for i, n in enumerate(names)}
    params = fx.apply_row_sim_params(order, theta, base, rows)
    fn = lambda h, p: force_model(design, jnp.clip(h, 0.0, h_max), jnp.clip(p, 0.0, p_max), params)  # noqa: E731
    return fx.apply_expected_force(order, theta, fn, rows)


@eqx.filter_jit
def _jacobian(force_model, order, names, base, t0, P, x, design, rows, h_max, p_max):
    return jax.jacfwd(lambda xx: _forward(force_model, order, names, base, t0, P, xx, design, rows, h_max, p_max))(x)


@eqx.filter_jit
def _fit_batch(
    force_model, order, names, base, h_max, p_max, design, rows, obs, sigma, t0, P, w, tau, x0, max_steps: int
):
    """Levenberg-Marquardt (optimistix) for a batch of problems (leading axis of t0, P, w, tau, x0), in turn:
    residuals ``[sqrt(w) (obs - F(t0 + P x)) / sigma, x / tau]`` (Gaussian-prior MAP)."""
    import optimistix as optx

    def resid(x, args):
        t0_, P_, w_, tau_ = args
        f = _forward(force_model, order, names, base, t0_, P_, x, design, rows, h_max, p_max)
        r = jnp.sqrt(w_) * jnp.nan_to_num(obs - f) / sigma
        return jnp.concatenate([r, x / tau_])

    solver = optx.LevenbergMarquardt(rtol=1e-6, atol=1e-6)

    def one(t0_, P_, w_, tau_, x0_):
        sol = optx.least_squares(resid, solver, x0_, args=(t0_, P_, w_, tau_), max_steps=max_steps, throw=False)
        return sol.value, sol.result == optx.RESULTS.successful

    # one problem after the other (lax.map): memory of one fit, not of the whole batch
    return jax.lax.map(lambda a: one(*a), (t0, P, w, tau, x0))


def _row_params(order, names, base: SimParams, rows: fx.Rows, thetas) -> SimParams:
    """Simulator constants of every row at each parameter vector of ``thetas`` [B, n]."""
    thetas = jnp.atleast_2d(jnp.asarray(thetas, float))
    return jax.vmap(lambda th: fx.apply_row_sim_params(order, {n: th[i] for i, n in enumerate(names)}, base, rows))(
        thetas
    )


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


def _take(design, rows, idx):
    idx = jnp.asarray(idx)
    return design[idx], rows.take(idx)


@dataclass
class EmulatorModel:
    """Expected observed force per row from a JAX force model and the effects (module doc).

    ``force_model``: ``(design, h_mm, p_pa, SimParams) -> F [N]`` (default: the bundled
    emulator, :func:`~mfdesign.models.emulator.load_default`); ``base_params``: the simulator
    constants of the plain model (authors'); ``h_range_mm`` / ``p_range_pa``: inputs are
    clipped to these (default: the emulator's training ranges, else 0-80 mm, 0-10 kPa).
    """

    force_model: Any = None
    base_params: SimParams = field(default_factory=SimParams)
    h_range_mm: tuple[float, float] | None = None
    p_range_pa: tuple[float, float] | None = None
    progress: bool = False
    _memo: dict = field(default_factory=dict, repr=False)

    def __post_init__(self):
        if self.force_model is None:
            from mfdesign.models.emulator import load_default

            self.force_model = load_default()
        from mfdesign.models.force import ForceModel

        rng = self.force_model.input_ranges() if isinstance(self.force_model, ForceModel) else {}
        self.h_range_mm = self.h_range_mm or tuple(rng.get("height_mm", (0.0, 80.0)))
        self.p_range_pa = self.p_range_pa or tuple(rng.get("pressure_pa", (0.0, 1.0e4)))
        self.base_params = jax.tree.map(lambda a: jnp.asarray(a, float), self.base_params)

    @property
    def name(self) -> str:
        return getattr(self.force_model, "name", "") or type(self.force_model).__name__.lower()

    def _cover(self, meas: Measurements, order, thetas: np.ndarray, rows=None) -> None:
        """Grow the force model to hold the constants of every row at each of ``thetas``
        [B, n_params] (the exact model solves the simulator planes it lacks; others hold
        everything already). Called before every evaluation and after every fit."""
        from mfdesign.models.force import ForceModel

        if not isinstance(self.force_model, ForceModel):
            return
        _, rws = self.data(meas)
        if rows is not None:
            rws = rws.take(jnp.asarray(rows))
        params = _row_params(order, self.names(order), self.base_params, rws, thetas)
        self.force_model = self.force_model.covering(params, progress=self.progress)

    # -- layout ---------------------------------------------------------------------------------
    def order(self, effects: Sequence[str | fx.Effect] = ()) -> tuple[str, ...]:
        """The canonical order: every effect with a likelihood hook, the mechanical ones first,
        then the measurement chain from the inputs outwards (pressure sensor, losses, frame,
        load-cell tare), others by name. ``effects`` are only validated: a neutral effect is an
        exact identity, so one order (and one compiled function) serves every model."""
        likelihood_effects([fx.effect(e).name for e in effects])
        return canonical_order()

    @staticmethod
    def names(order: Sequence[str]) -> tuple[str, ...]:
        return tuple(fx.neutral_theta(order))

    def theta_vector(self, order, theta: Mapping[str, Any] | None) -> np.ndarray:
        names = self.names(order)
        per = fx.split_theta(order, theta)  # validates the names
        flat = {f"{k}.{p}": v for k, d in per.items() for p, v in d.items()}
        return np.array([float(flat[n]) for n in names])

    def data(self, meas: Measurements):
        """``(design [N, 6], Rows)`` of a table (memoised per table object)."""
        memo = self._memo.get(id(meas))
        if memo is None or memo[0] is not meas:
            memo = (meas, _rows_of(meas))
            self._memo[id(meas)] = memo
        return memo[1]

    # -- evaluation -----------------------------------------------------------------------------
    def _chunks(self, n: int):
        for a in range(0, n, CHUNK):
            idx = np.arange(a, a + CHUNK)
            yield a, min(a + CHUNK, n), np.minimum(idx, n - 1)

    def _eval(self, fn, design, rows, order, t0, P, x) -> np.ndarray:
        n = int(design.shape[0])
        names = self.names(order)
        out = []
        args = (np.asarray(t0, float), np.asarray(P, float), np.asarray(x, float))
        for a, b, idx in self._chunks(n):
            d, r = (design, rows) if n == CHUNK else _take(design, rows, idx)
            val = fn(
                self.force_model,
                order,
                names,
                self.base_params,
                *map(jnp.asarray, args),
                d,
                r,
                float(self.h_range_mm[1]),
                float(self.p_range_pa[1]),
            )
            out.append(np.asarray(val)[: b - a])
        return np.concatenate(out, axis=0)

    def expected_force(
        self,
        meas: Measurements,
        effects: Sequence[str | fx.Effect] = (),
        theta: Mapping[str, Any] | None = None,
        rows: np.ndarray | None = None,
    ) -> np.ndarray:
        """Expected observed force [N] per row of ``meas`` (or of its rows ``rows``)."""
        order = self.order(effects)
        fx.split_theta([fx.effect(e) for e in effects], theta)  # a name outside ``effects`` is an error
        t = self.theta_vector(order, theta)
        self._cover(meas, order, t[None], rows)
        design, rws = self.data(meas)
        if rows is not None:
            design, rws = _take(design, rws, rows)
        return self._eval(_forward, design, rws, order, t, np.zeros((len(t), 1)), np.zeros(1))

    def predict(self, meas: Measurements) -> np.ndarray:
        """The plain model (no effects): ``expected_force(meas)``."""
        return self.expected_force(meas)

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
        ``pad_cols``: compute at least this many columns (zeros beyond ``free``; equal shapes
        share one compile)."""
        order = self.order(effects)
        names = self.names(order)
        missing = [f for f in free if f not in names]
        if missing:
            raise KeyError(f"no parameter(s) {missing}; known: {list(names)}")
        t = self.theta_vector(order, theta)
        k = max(len(free), pad_cols)
        P = np.zeros((len(names), k))
        for j, f in enumerate(free):
            P[names.index(f), j] = 1.0
        # Beside theta, not only at it: a mechanical effect at its neutral value moves no
        # constant, so covering theta alone adds no lattice axis for it, and its derivative
        # came out 0 (a hidden clamp pre-stretch was ranked 7th by the screen). One side
        # suffices (a one-node axis differentiates as a forward difference) and halves the
        # planes a cold screen solves; a fit that goes the other way grows the axis there.
        steps = JACOBIAN_COVER_STEP * P[:, : len(free)].T
        self._cover(meas, order, np.vstack([t[None], t + steps]), rows)
        design, rws = self.data(meas)
        if rows is not None:
            design, rws = _take(design, rws, rows)
        return self._eval(_jacobian, design, rws, order, t, P, np.zeros(k))[:, : len(free)]

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
        against ``target`` [len(rows)]; returns ``(x, converged [B])``. ``pad_rows``: pad the rows
        (weight 0) to this many, so that data sets of other sizes reuse the compiled fit."""
        n, pad = len(rows), max(pad_rows or 0, len(rows))
        rows = np.concatenate([rows, np.full(pad - n, rows[0])])  # weight 0: equal shapes share one compile
        target = np.concatenate([np.asarray(target, float), np.zeros(pad - n)])
        w = np.concatenate([np.asarray(w, float), np.zeros((len(w), pad - n))], axis=1)
        design, rws = _take(*self.data(meas), rows)
        t0, P = np.asarray(t0, float), np.asarray(P, float)
        # The exact model's lattice grows where the fits go: fit with the model held at the
        # lattice's edge, grow it around the optima (and the start), refit from there.
        x = np.asarray(x0, float)
        self._cover(meas, order, t0 + np.einsum("bij,bj->bi", P, x), rows)
        for _ in range(LATTICE_ROUNDS):
            x, ok = _fit_batch(
                self.force_model,
                order,
                self.names(order),
                self.base_params,
                float(self.h_range_mm[1]),
                float(self.p_range_pa[1]),
                design,
                rws,
                jnp.asarray(target, float),
                float(sigma),
                *(jnp.asarray(a, float) for a in (t0, P, w, tau, x)),
                int(max_steps),
            )
            x, ok = np.asarray(x), np.asarray(ok)
            before = self.force_model
            self._cover(meas, order, t0 + np.einsum("bij,bj->bi", P, x), rows)
            if self.force_model is before:
                break
        return x, ok


JACOBIAN_COVER_STEP = 1e-3  # parameter units: a step that reaches the first lattice node of its axis


def forward_model(physics: str, meas: Measurements, *, cache=None, progress: bool = False) -> EmulatorModel:
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
    from mfdesign.models.force import FORCE_MODELS

    if physics == "exact":
        from mfdesign.models.exact import build_exact

        df = meas._df
        if len(df) == 0:
            raise ValueError("no rows to diagnose")
        h = query_heights(meas)
        # The screen differentiates every candidate at neutral (a step of each parameter,
        # :meth:`EmulatorModel.jacobian`): its planes are solved with the reference ones.
        order = canonical_order()
        names = EmulatorModel.names(order)
        t0 = np.array([fx.neutral_theta(order)[n] for n in names], float)
        steps = t0 + JACOBIAN_COVER_STEP * np.eye(len(names))
        base = SimParams()
        _, rows = _rows_of(meas)
        some = np.unique(np.linspace(0, len(df) - 1, min(len(df), 256)).astype(int))  # per-row effects vary
        also = _row_params(order, names, base, rows.take(jnp.asarray(some)), steps)
        fm = build_exact(
            tuple(dict.fromkeys(df["design_key"])),
            h_max_mm=float(np.nanmax(h)),
            p_max_pa=float(df["pressure_pa"].max()),
            outside="clamp",
            grow="additive",
            cache=cache,
            progress=progress,
            base=base,
            also=also,
        )
        return EmulatorModel(fm, base_params=base, progress=progress)
    if physics == "emulator":
        return EmulatorModel(None, progress=progress)
    if physics == "standin":
        from mfdesign.models.standin import StandinForceModel

        return EmulatorModel(StandinForceModel(), progress=progress)
    raise ValueError(f"--physics must be one of {list(FORCE_MODELS)}, got {physics!r}")
