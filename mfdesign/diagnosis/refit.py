"""Full check on the forward model (:class:`~mfdesign.diagnosis.forward.ForwardModel`): nonlinear refit,
held-out error, calibration's BIC.

For each candidate set of effects (the effects already in the model plus one candidate):

1. rows: at most ``max_rows`` usable rows, evenly spaced within each trial (neighbouring
   samples of a 10 Hz ramp carry little new information);
2. fit: every parameter of the set, ``theta = neutral + step x``, by Levenberg-Marquardt
   (``optimistix.LevenbergMarquardt``; More 1978) on the residuals
   ``[(F_obs - F(theta)) / s, x / tau]`` (noise floor ``s``; the effects' priors as Gaussian
   ridge terms of scale ``tau``, Bishop 2006 sec. 3.3), from the screen's estimate;
   results outside a prior's bounds are clipped to them;
3. held-out: leave-membranes-out folds (weight 0 on the test membranes) fitted in the same
   compiled call as the full fit, then the test membranes predicted;
4. ``delta BIC = BIC(set) - BIC(model without the candidate)`` with the calibration's
   likelihood (:meth:`~mfdesign.models.hierarchical.HierarchicalModel.log_lik`, Gaussian,
   noise at its maximum-likelihood value) and the formula of
   :func:`mfdesign.calibration.mcmc.calibrate` (``k ln n - 2 ln L``), so that diagnosis and
   calibration rank models alike;
5. standard errors from the exact Jacobian at the optimum, inflated for the serial
   correlation of the residuals within trials (AR(1) factor ``(1 + rho) / (1 - rho)``).
"""

from __future__ import annotations

import math
from dataclasses import dataclass, field
from typing import Mapping, Sequence

import jax.numpy as jnp
import numpy as np

from mfdesign._padding import pad_last, padded_size
from mfdesign.data.measurements import Measurements
from mfdesign.diagnosis.forward import ForwardModel, effect_order, parameter_names, theta_vector
from mfdesign.diagnosis.residuals import Residuals, noise_floor, subsample
from mfdesign.diagnosis.screen import lag1_autocorrelation, parameter_scale, parameter_step
from mfdesign.physics import effects as fx
from mfdesign.physics._traces import stored_jit

__all__ = ["CheckResult", "calibrate_effects", "full_check"]

MAX_ROWS = (
    1000  # rows per refit, evenly within trials (the bundled data ranks alike and fits the same offset as with 2,500)
)
KMAX = 4  # parameters per fit are padded to this (and rows to max_rows): one compiled fit serves all


@dataclass(frozen=True)
class CheckResult:
    effects: tuple[str, ...]
    theta: dict
    stderr: dict
    rmse_n: float
    heldout_rmse_n: float
    heldout_rmse_base_n: float
    delta_bic: float
    n_eff: float
    noise_floor_n: float
    folds: list = field(default_factory=list)
    # Laplace approximation of the joint posterior (the exact Jacobian at the optimum,
    # inflated for serial correlation): the parameters' correlation matrix, in theta's order.
    # Near +-1 the data cannot tell the parameters (or the effects behind them) apart.
    correlation: list = field(default_factory=list)
    # rows without a model value under this candidate, in words ("" when every row has one)
    undefined: str = ""

    @property
    def heldout_over_noise(self) -> float:
        return self.heldout_rmse_n / self.noise_floor_n if self.noise_floor_n > 0 else float("nan")

    def to_json(self) -> dict:
        d = dict(self.__dict__)
        d["effects"] = list(self.effects)
        d["heldout_over_noise"] = self.heldout_over_noise
        return d


MAX_UNDEFINED = 0.02  # rows without a model value a candidate may leave out (a larger share: not evaluated)


def _undefined_words(frame, bad: np.ndarray) -> str:
    """Where the model has no number: count, and per membrane its heights and pressures."""
    f = frame.loc[bad]
    parts = []
    for key, g in f.groupby("design_key", sort=False):
        h, p = g["height_mm"].to_numpy(float), g["pressure_pa"].to_numpy(float) / 1000.0
        parts.append(f"{key} at {np.nanmin(h):.0f}-{np.nanmax(h):.0f} mm, {np.nanmin(p):.1f}-{np.nanmax(p):.1f} kPa")
    return f"{int(bad.sum())} of {bad.size} rows (" + "; ".join(parts) + ")"


def _not_evaluated(effects, theta, floor: float, undefined: str) -> "CheckResult":
    nan = float("nan")
    return CheckResult(
        effects=tuple(effects),
        theta=theta,
        stderr={},
        rmse_n=nan,
        heldout_rmse_n=nan,
        heldout_rmse_base_n=nan,
        delta_bic=nan,
        n_eff=nan,
        noise_floor_n=floor,
        undefined=undefined,
    )


def _bic(sim: ForwardModel, meas, rows, target, effects, theta, resid) -> float:
    """``k ln n - 2 ln L`` at ``theta`` with the calibration's likelihood (mu, J_m fixed; k =
    effect parameters + noise)."""
    from mfdesign.models.hierarchical import CalibrationData, HierarchicalModel

    n = len(rows)
    # padded to a power of two by the last row at weight 0 (its sum unchanged): the check's
    # BICs on rows[keep] of other sizes share one program (1.9 s of XLA alone, 11.0 s beside
    # the demo's compile-ahead thread; issue 40)
    size = padded_size(n)
    design, rws = sim.table(meas, pad_last(np.asarray(rows), size))
    weight = np.concatenate([np.ones(n), np.zeros(size - n)])
    data = CalibrationData(
        design, rws, jnp.asarray(pad_last(np.asarray(target, float), size)), jnp.asarray(weight), ("all",)
    )
    base = sim.base_params
    mu, jm = float(base.mu_pa), float(base.jm)
    # Every likelihood effect in the canonical order, those outside the set at their neutral
    # values (exact identities): one compiled log-likelihood serves every candidate set.
    order = effect_order(effects)
    model = HierarchicalModel(
        force_model=sim.clipped,
        effects=tuple(order),
        n_membranes=0,
        membrane_latents=False,
        mu_prior=fx.Uniform(mu * (1 - 1e-9), mu * (1 + 1e-9)),
        jm_prior=fx.Uniform(jm * (1 - 1e-9), jm * (1 + 1e-9)),
        base=base,
    )
    noise = max(float(np.sqrt(np.mean(np.square(resid)))), 1e-9)
    v = {
        "mu_pa": mu,
        "jm": jm,
        "noise_n": noise,
        **fx.neutral_theta(order),
        **{k: float(theta[k]) for k in fx.neutral_theta(effects)},
    }
    x = jnp.asarray([v[nm] for nm in model.names])
    ll = float(_log_lik(model, x, data))
    k = sum(len(fx.effect(e).parameters) for e in effects) + 1
    return k * math.log(n) - 2.0 * ll


@stored_jit(fast_compile=True)
def _log_lik(model, x, data):
    """The model's log likelihood as one program per row count (run eagerly, each BIC compiled
    ~25 small XLA programs in a cold demo, issue 40). Stored: a cold demo's plan compiles it
    ahead (in the diagnosis it waited 11.0 s behind the kernels compiling ahead, session 43)."""
    return model.log_lik(x, data)


def _layout(order, sets, theta0, starts=None):
    """Per set: its parameters, the map ``P`` from fit coordinates to theta, the prior
    scales and the start (``starts[i]``, else ``theta0``, else neutral; in prior bounds)."""
    names = parameter_names(order)
    kmax = max(KMAX, *(sum(len(fx.effect(e).parameters) for e in s) for s in sets))
    t0 = theta_vector(order, {})
    out = []
    for i, s in enumerate(sets):
        start = {**(theta0 or {}), **((starts[i] or {}) if starts is not None else {})}
        pars = [(fx.effect(e), p) for e in s for p in fx.effect(e).parameters]
        P = np.zeros((len(names), kmax))
        tau = np.ones(kmax)
        x0 = np.zeros(kmax)
        for j, (e, p) in enumerate(pars):
            q = e.qualified(p.name)
            step = parameter_step(p)
            P[names.index(q), j] = step
            tau[j] = parameter_scale(p) / abs(step)
            lo, hi = p.prior.bounds
            x0[j] = (float(np.clip(start.get(q, p.neutral), lo, hi)) - p.neutral) / step
        out.append((pars, P, tau, x0))
    return t0, out


def _theta_of(pars, x) -> dict:
    th = {}
    for j, (e, p) in enumerate(pars):
        lo, hi = p.prior.bounds
        th[e.qualified(p.name)] = float(np.clip(p.neutral + parameter_step(p) * x[j], lo, hi))
    return th


def _folds(keys: np.ndarray, n_folds: int, seed: int) -> list[list[str]]:
    uniq = list(dict.fromkeys(keys))
    k = min(n_folds, len(uniq))
    perm = np.random.default_rng(seed).permutation(len(uniq))
    return [[uniq[i] for i in f] for f in np.array_split(perm, k)] if k >= 2 else []


def _prefix(sets):
    first = list(sets[0])
    n = 0
    while all(len(s) > n + 1 and s[n] == first[n] for s in sets) and n < len(first) - 1:
        n += 1
    return first[:n]


def full_check(
    sim: ForwardModel,
    meas: Measurements,
    res: Residuals,
    candidates: Sequence[Sequence[str]],
    theta0: Mapping[str, float] | None = None,
    base_pred: np.ndarray | None = None,
    n_folds: int = 3,
    seed: int = 0,
    max_rows: int = MAX_ROWS,
    progress: bool = False,
    starts: Sequence[Mapping[str, float] | None] | None = None,
    base_effects: Sequence[str] | None = None,
):
    """Refit each candidate set (module doc); ``res``: residuals of the current model (the
    sets' common prefix of effects at ``theta0``); ``base_pred``: prediction of the model
    under diagnosis without any effect (default: the plain back end); ``starts``: per set,
    a start that overrides ``theta0`` (a pair's joint screen estimate); ``base_effects``: the
    effects of the model the sets are compared with (default: the sets' common prefix).
    Sorted by held-out RMSE."""
    sets = [list(s) for s in candidates]
    if not sets:
        return []
    pos = subsample(res.frame, max_rows, seed)
    frame = res.frame.iloc[pos].reset_index(drop=True)
    rows = frame["row"].to_numpy()
    obs = frame["observed_n"].to_numpy(float)
    keys = frame["design_key"].to_numpy(object)
    r0 = frame["residual_n"].to_numpy(float)
    offset = 0.0 if base_pred is None else np.asarray(base_pred, float)[rows] - sim.expected_force(meas, rows=rows)
    target = obs - offset
    all_rows = res.frame["row"].to_numpy()
    off_all = (
        0.0 if base_pred is None else np.asarray(base_pred, float)[all_rows] - sim.expected_force(meas, rows=all_rows)
    )
    sigma = res.noise_floor_n if res.noise_floor_n > 0 else float(np.std(r0))
    prefix = list(base_effects) if base_effects is not None else _prefix(sets)
    order = effect_order(prefix)
    t0, lay = _layout(order, sets, theta0, starts)
    folds = _folds(keys, n_folds, seed)
    weights = [np.ones(len(rows))] + [(~np.isin(keys, f)).astype(float) for f in folds]
    B = len(weights)
    P = np.stack([P for _, P, _, _ in lay for _ in range(B)])
    tau = np.stack([t for _, _, t, _ in lay for _ in range(B)])
    x0 = np.stack([x for _, _, _, x in lay for _ in range(B)])
    w = np.stack([wk for _ in lay for wk in weights])
    if progress:
        print(f"full check: refitting {len(sets)} candidate set(s) x {B} fits on {len(rows)} rows", flush=True)
    x, ok = sim.fit(
        meas, rows, target, order, np.broadcast_to(t0, (len(w), len(t0))), P, w, tau, x0, sigma, pad_rows=max_rows
    )
    prefix_theta = {k: v for k, v in (theta0 or {}).items() if k in fx.neutral_theta(prefix)}
    bic0 = _bic(sim, meas, rows, target, prefix, prefix_theta, r0)
    out = []
    for i, (s, (pars, _, _, _)) in enumerate(zip(sets, lay)):
        xs = x[i * B : (i + 1) * B]
        theta = _theta_of(pars, xs[0])
        pred = sim.expected_force(meas, s, theta, rows=rows) + offset
        r = obs - pred
        fold_theta = [_theta_of(pars, xs[k + 1]) for k in range(len(folds))]
        rt_all = np.full(len(rows), np.nan)
        for k, test in enumerate(folds):
            te = np.isin(keys, test)
            rt_all[te] = obs[te] - (
                sim.expected_force(meas, s, fold_theta[k], rows=rows[te]) + (offset[te] if np.ndim(offset) else offset)
            )
        # Rows the model has no number for under this candidate (every solver failed there:
        # past the Gent limit, a limit point). A few are named and left out of every figure
        # of this candidate and of its baseline alike; more than MAX_UNDEFINED and the
        # candidate is not evaluated, with the rows named (``undefined``).
        tested = np.isin(keys, [m for f in folds for m in f]) if folds else np.zeros(len(rows), bool)
        bad = ~np.isfinite(r) | (tested & ~np.isfinite(rt_all))
        undefined = _undefined_words(frame, bad) if bad.any() else ""
        if bad.mean() > MAX_UNDEFINED:
            out.append(_not_evaluated(s, theta, res.noise_floor_n, undefined))
            continue
        keep = ~bad
        sq = sq0 = 0.0
        cnt = 0
        fold_rows = []
        for k, test in enumerate(folds):
            te = np.isin(keys, test) & keep
            rt = rt_all[te]
            fold_rows.append(
                {
                    "test_membranes": test,
                    "theta": fold_theta[k],
                    "rmse_n": float(np.sqrt(np.mean(rt**2))) if te.any() else float("nan"),
                    "rmse_base_n": float(np.sqrt(np.mean(r0[te] ** 2))) if te.any() else float("nan"),
                }
            )
            sq += float(np.sum(rt**2))
            sq0 += float(np.sum(r0[te] ** 2))
            cnt += int(te.sum())
        free = [e.qualified(p.name) for e, p in pars]
        J = sim.jacobian(meas, free, s, theta, rows=rows[keep], pad_cols=KMAX)
        J = np.where(np.isfinite(J), J, 0.0)
        rk = r[keep]
        rho = lag1_autocorrelation(frame.loc[keep], rk)
        infl = (1 + rho) / (1 - rho)
        s2 = float(np.sum(rk**2)) / max(len(rk) - len(free), 1)
        cov = s2 * infl * np.linalg.pinv(J.T @ J)
        se = np.sqrt(np.clip(np.diag(cov), 0, None))
        corr = cov / np.maximum(np.outer(se, se), 1e-300)
        n = len(rk)
        # The noise floor under this candidate, from its own residuals on every row. Force
        # readings carry their noise whatever the model; in a lift the height is the reading
        # (whole millimetres) and the force error is slope x height error, so the floor there
        # follows the slope of the model: the plain model's residuals under-state it where
        # the truth is steeper (seen with a contact offset next to a ring, up to 1.4x).
        # Never below the floor the candidate was tested against.
        full = res.frame.assign(
            residual_n=res.frame["observed_n"].to_numpy(float)
            - (sim.expected_force(meas, s, theta, rows=all_rows) + off_all)
        )
        floor_c = noise_floor(full.loc[np.isfinite(full["residual_n"].to_numpy(float))])
        floor_c = max(res.noise_floor_n, floor_c) if np.isfinite(floor_c) else res.noise_floor_n
        # BIC of the set and of the model without it on the same rows
        b0 = bic0 if keep.all() else _bic(sim, meas, rows[keep], target[keep], prefix, prefix_theta, r0[keep])
        out.append(
            CheckResult(
                effects=tuple(s),
                theta=theta,
                stderr={q: float(se[j]) for j, q in enumerate(free)},
                rmse_n=float(np.sqrt(np.mean(rk**2))),
                heldout_rmse_n=float(np.sqrt(sq / cnt)) if cnt else float(np.sqrt(np.mean(rk**2))),
                heldout_rmse_base_n=float(np.sqrt(sq0 / cnt)) if cnt else float(np.sqrt(np.mean(r0[keep] ** 2))),
                delta_bic=float(_bic(sim, meas, rows[keep], target[keep], s, theta, rk) - b0),
                n_eff=float(n / infl),
                noise_floor_n=floor_c,
                folds=fold_rows,
                correlation=np.clip(corr[: len(free), : len(free)], -1.0, 1.0).round(6).tolist(),
                undefined=undefined,
            )
        )
        out[-1].folds.append({"converged": bool(np.all(ok[i * B : (i + 1) * B]))})
    out.sort(key=lambda c: c.heldout_rmse_n)
    return out


def calibrate_effects(
    sim: ForwardModel,
    meas: Measurements,
    res: Residuals,
    effects: Sequence[str | fx.Effect],
    theta0: Mapping[str, float] | None = None,
    base_offset: np.ndarray | None = None,
    max_rows: int = MAX_ROWS,
) -> tuple[dict, np.ndarray]:
    """Fit every parameter of ``effects`` (module doc, step 2) on the rows of ``res``; returns
    ``(theta, prediction per row of meas)`` (``base_offset``: base model - plain back end)."""
    names = [fx.effect(e).name for e in effects]
    pos = subsample(res.frame, max_rows)
    rows = res.frame["row"].to_numpy()[pos]
    off = np.zeros(len(meas)) if base_offset is None else np.asarray(base_offset, float)
    target = res.frame["observed_n"].to_numpy(float)[pos] - off[rows]
    order = effect_order(names)
    t0, [(pars, P, tau, x0)] = _layout(order, [names], theta0)
    sigma = res.noise_floor_n if res.noise_floor_n > 0 else float(np.std(res.residual))
    x, _ = sim.fit(
        meas,
        rows,
        target,
        order,
        t0[None],
        P[None],
        np.ones((1, len(rows))),
        tau[None],
        x0[None],
        sigma,
        pad_rows=max_rows,
    )
    theta = _theta_of(pars, x[0])
    return theta, sim.expected_force(meas, names, theta) + off
