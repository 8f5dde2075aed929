"""Full check of candidate effects: calibrate them, held-out error by membrane, information criterion.

For a set of effects the model becomes ``F(theta) = base + [E(theta) - E(theta0)]`` with
``E`` the expected observed force of the simulator with the effects
(:meth:`~mfdesign.diagnose.expected.PlaneSimulator.expected_force`) and ``base`` the
model under diagnosis (for the plain simulator ``base = E(theta0)``, so ``F = E``).

Two back ends:

* exact (:class:`~mfdesign.diagnose.emulated.EmulatorModel`: the emulator or the analytic
  stand-in in JAX), :mod:`mfdesign.diagnose.refit`: a real nonlinear refit of every
  parameter of the set (Levenberg-Marquardt, optimistix), on all membranes and per fold,
  in one compiled call; delta BIC with the calibration's likelihood
  (:meth:`~mfdesign.models.hierarchical.HierarchicalModel.log_lik`);
* linearised (:class:`~mfdesign.diagnose.expected.PlaneSimulator`, the full simulator whose
  planes cost minutes): the model is linearised by secants at the neutral point (the
  screen's planes; no new simulation), ``theta`` is the prior-weighted linear least squares
  fit, folds refit the same linear model without the test membranes, and delta BIC uses
  the effective sample size of the serially correlated residuals (Schwarz 1978).

Verdict (:func:`verdict`): nothing is claimed when the residual is already at the noise
floor (RMS <= ``floor_factor`` x noise floor) or when no candidate lowers both BIC (by
more than 10) and the held-out RMSE (by more than ``min_gain``); otherwise the best
candidate is "explains" if its held-out RMSE is within ``floor_factor`` x noise floor,
else "explains part".
"""

from __future__ import annotations

import math
from dataclasses import dataclass, field
from typing import Any, Mapping, Sequence

import numpy as np

from mfdesign.data.measurements import Measurements
from mfdesign.diagnose.expected import PlaneSimulator
from mfdesign.diagnose.residuals import Residuals
from mfdesign.diagnose.screen import lag1_autocorrelation, parameter_step, ridge_fit
from mfdesign.physics import effects as fx

__all__ = ["CheckResult", "calibrate_effects", "full_check", "verdict"]

FLOOR_FACTOR = 1.2


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

    @property
    def heldout_over_noise(self) -> float:
        return self.heldout_rmse_n / self.noise_floor_n if self.noise_floor_n > 0 else float("nan")

    def to_json(self) -> dict:
        d = dict(self.__dict__)
        d["effects"] = list(self.effects)
        d["heldout_over_noise"] = self.heldout_over_noise
        return d


def _bounds(e: fx.Effect, p: fx.Parameter, step: float) -> tuple[float, float]:
    lo, hi = p.prior.bounds
    scale = abs(step)
    lo = lo if math.isfinite(lo) else p.neutral - 10 * scale
    hi = hi if math.isfinite(hi) else p.neutral + 10 * scale
    return lo, hi


def _params(effects: Sequence[fx.Effect]):
    return [(e, p) for e in effects for p in e.parameters]


def calibrate_effects(sim: PlaneSimulator, meas: Measurements, res: Residuals, effects: Sequence[str | fx.Effect],
                      theta0: Mapping[str, float] | None = None, base_offset: np.ndarray | None = None,
                      max_nfev: int = 30) -> tuple[dict, np.ndarray]:
    """Least-squares ``theta`` of ``effects`` on the rows of ``res``; returns ``(theta, prediction per row of meas)``.

    ``base_offset``: ``base - E(theta0)`` per row of ``meas`` (0 for the plain simulator)."""
    if hasattr(sim, "jacobian"):  # exact JAX back end: nonlinear refit
        from mfdesign.diagnose.refit import calibrate_exact

        return calibrate_exact(sim, meas, res, effects, theta0, base_offset)
    max_nfev = 0  # plane simulator: linearised (a nonlinear refit needs new planes per step)
    effects = [fx.effect(e) for e in effects]
    pars = _params(effects)
    steps = np.array([parameter_step(p) for _, p in pars])
    neutral = np.array([p.neutral for _, p in pars])
    lo, hi = np.array([_bounds(e, p, s) for (e, p), s in zip(pars, steps)]).T
    xlo, xhi = np.minimum((lo - neutral) / steps, (hi - neutral) / steps), np.maximum((lo - neutral) / steps, (hi - neutral) / steps)
    rows = res.frame["row"].to_numpy()
    obs = res.frame["observed_n"].to_numpy(float)
    off = 0.0 if base_offset is None else base_offset
    cache: dict[tuple, np.ndarray] = {}

    def theta_of(x):
        return {e.qualified(p.name): float(v) for (e, p), v in zip(pars, neutral + steps * np.asarray(x))}

    def pred(x):
        k = tuple(np.round(np.asarray(x, float), 12))
        if k not in cache:
            cache[k] = sim.expected_force(meas, effects, theta_of(x)) + off
        return cache[k]

    x0 = np.zeros(len(pars))
    if theta0:
        x0 = np.array([(theta0.get(e.qualified(p.name), p.neutral) - p.neutral) / s for (e, p), s in zip(pars, steps)])
    x0 = np.clip(x0, xlo + 1e-9 * (xhi - xlo), xhi - 1e-9 * (xhi - xlo))
    if max_nfev == 0:  # linearised: secant at the neutral point (the screen's planes), ridge fit, clipped
        f0 = pred(np.zeros(len(pars)))
        J = np.stack([(pred(np.eye(len(pars))[j]) - f0)[rows] for j in range(len(pars))], axis=1)
        J = np.where(np.isfinite(J), J, 0.0)
        r = np.where(np.isfinite(obs - f0[rows]), obs - f0[rows], 0.0)
        sigma = res.noise_floor_n if res.noise_floor_n > 0 else float(np.std(r))
        x = np.clip(ridge_fit(J, r, sigma, np.full(len(pars), 1.0)), xlo, xhi)
        full = f0.copy()
        full[rows] = f0[rows] + J @ x
        return theta_of(x), full
    raise AssertionError("unreachable: the plane back end is always linearised")


def full_check(sim: PlaneSimulator, meas: Measurements, res: Residuals, candidates: Sequence[Sequence[str]],
               theta0: Mapping[str, float] | None = None, base_pred: np.ndarray | None = None,
               n_folds: int = 3, seed: int = 0, max_nfev: int = 30, max_nfev_mechanical: int | None = None,
               progress: bool = False) -> list[CheckResult]:
    """Calibrate each candidate effect set (a list of names), held-out RMSE and delta BIC;
    sorted by held-out RMSE (best first). ``res``: residuals of the model without them;
    ``base_pred``: that model's prediction per row of ``meas`` (default: the plain simulator).
    ``max_nfev_mechanical``: budget of simulator evaluations for sets with a mechanical
    effect (each costs one plane per membrane); ``0`` = linearised check on the screen's
    secant planes (no new simulation: for the full simulator on a small CPU). With an
    exact back end (``sim.jacobian`` exists) the sets are refitted nonlinearly
    (:func:`mfdesign.diagnose.refit.full_check_exact`); ``max_nfev*`` are then unused."""
    if hasattr(sim, "jacobian"):
        from mfdesign.diagnose.refit import full_check_exact

        return full_check_exact(sim, meas, res, candidates, theta0=theta0, base_pred=base_pred,
                                n_folds=n_folds, seed=seed, progress=progress)
    max_nfev = max_nfev_mechanical = 0  # plane back end: linearised check only
    e0 = sim.expected_force(meas)
    base_offset = None if base_pred is None else np.asarray(base_pred, float) - e0
    rows = res.frame["row"].to_numpy()
    obs = res.frame["observed_n"].to_numpy(float)
    keys = res.frame["design_key"].to_numpy(object)
    uniq = list(dict.fromkeys(keys))
    k = min(n_folds, len(uniq))
    order = np.random.default_rng(seed).permutation(len(uniq))
    folds = [[uniq[i] for i in f] for f in np.array_split(order, k)] if k >= 2 else []
    r0 = res.residual
    sigma = res.noise_floor_n if res.noise_floor_n > 0 else float(np.std(r0))
    it = list(candidates)
    if progress:
        from tqdm.auto import tqdm

        it = tqdm(it, desc="full check", unit="candidate")
    out = []
    for names in it:
        effects = [fx.effect(n) for n in names]
        cheap = not any(e.acts_on_mechanics for e in effects)
        nfev = max_nfev if (cheap or max_nfev_mechanical is None) else max_nfev_mechanical
        e_neutral = None
        if nfev == 0:
            e_neutral = sim.expected_force(meas, effects, {}) + (0.0 if base_offset is None else base_offset)
        theta, pred = calibrate_effects(sim, meas, res, effects, theta0, base_offset, max_nfev=nfev)
        r = obs - pred[rows]
        ok = np.isfinite(r)
        r = np.where(ok, r, 0.0)
        # linearisation about the optimum for the folds and the standard errors
        pars = _params(effects)
        J = []
        for e, p in pars:
            s = (1.0 if nfev == 0 else 0.1) * parameter_step(p)
            th = dict(theta)
            lo, hi = _bounds(e, p, parameter_step(p))
            if not (lo <= th[e.qualified(p.name)] + s <= hi):
                s = -s
            th[e.qualified(p.name)] += s
            if nfev == 0:  # linearised mode: the secant planes at neutral + step (already computed)
                th = {**theta, **{q.qualified(pp.name): pp.neutral for q, pp in pars}}
                th[e.qualified(p.name)] = p.neutral + s
                J.append((sim.expected_force(meas, effects, th) + (0.0 if base_offset is None else base_offset) - e_neutral)[rows] / s)
                continue
            J.append(((sim.expected_force(meas, effects, th) + (0.0 if base_offset is None else base_offset)) - pred)[rows] / s)
        J = np.where(np.isfinite(np.stack(J, axis=1)), np.stack(J, axis=1), 0.0)
        tau = np.array([abs(parameter_step(p)) * 10 for _, p in pars])
        rho = lag1_autocorrelation(res.frame, r)
        infl = (1 + rho) / (1 - rho)
        n = r.size
        n_eff = max(n / infl, 2.0)
        s2 = float(np.sum(r**2)) / max(n - len(pars), 1)
        cov = s2 * infl * np.linalg.pinv(J.T @ J)
        se = np.sqrt(np.clip(np.diag(cov), 0, None))
        fold_rows, sq, sq0, cnt = [], 0.0, 0.0, 0
        for test in folds:
            te = np.isin(keys, test)
            d = ridge_fit(J[~te], r[~te], sigma, tau)  # shift of theta fitted without the test membranes
            rt = r[te] - J[te] @ d
            fold_rows.append({"test_membranes": test, "rmse_n": float(np.sqrt(np.mean(rt**2))),
                              "rmse_base_n": float(np.sqrt(np.mean(r0[te] ** 2)))})
            sq += float(np.sum(rt**2)); sq0 += float(np.sum(r0[te] ** 2)); cnt += int(te.sum())
        ss0, ss1 = float(np.sum(r0**2)), float(np.sum(r**2))
        dbic = n_eff * math.log(max(ss1, 1e-300) / max(ss0, 1e-300)) + len(pars) * math.log(n_eff)
        out.append(CheckResult(
            effects=tuple(e.name for e in effects), theta=theta,
            stderr={e.qualified(p.name): float(se[j]) for j, (e, p) in enumerate(pars)},
            rmse_n=float(np.sqrt(ss1 / n)),
            heldout_rmse_n=float(np.sqrt(sq / cnt)) if cnt else float(np.sqrt(ss1 / n)),
            heldout_rmse_base_n=float(np.sqrt(sq0 / cnt)) if cnt else float(np.sqrt(ss0 / n)),
            delta_bic=float(dbic), n_eff=float(n_eff), noise_floor_n=res.noise_floor_n, folds=fold_rows))
    out.sort(key=lambda c: c.heldout_rmse_n)
    return out


def verdict(res: Residuals, checks: Sequence[CheckResult], floor_factor: float = FLOOR_FACTOR,
            min_gain: float = 0.1, bic_margin: float = 10.0) -> dict:
    """What may be claimed (see the module doc): ``{"status", "effects", "words", ...}``."""
    floor = res.noise_floor_n
    rms = res.rmse_n
    base = {"rmse_n": rms, "noise_floor_n": floor, "rmse_over_noise": rms / floor if floor > 0 else None}
    if floor > 0 and rms <= floor_factor * floor:
        return {**base, "status": "at_noise_floor", "effects": [],
                "words": (f"nothing to explain: the residual RMS {rms:.3f} N is within {floor_factor:g} x the "
                          f"noise floor {floor:.3f} N; no effect is claimed")}
    good = [c for c in checks if c.delta_bic < -bic_margin and c.heldout_rmse_n < (1 - min_gain) * c.heldout_rmse_base_n]
    if not good:
        best = min(checks, key=lambda c: c.heldout_rmse_n) if checks else None
        extra = (f"; the best candidate, {'+'.join(best.effects)}, leaves held-out RMSE {best.heldout_rmse_n:.3f} N "
                 f"(was {best.heldout_rmse_base_n:.3f} N, delta BIC {best.delta_bic:+.1f})") if best else ""
        return {**base, "status": "unexplained", "effects": [],
                "words": (f"no candidate effect explains the residual structure: RMS {rms:.3f} N vs noise floor "
                          f"{floor:.3f} N{extra}; see the worst regions for what remains")}
    best = min(good, key=lambda c: (c.heldout_rmse_n, c.delta_bic))
    full = floor > 0 and best.heldout_rmse_n <= floor_factor * floor
    th = ", ".join(f"{k} = {v:.4g} +- {best.stderr.get(k, float('nan')):.2g}" for k, v in best.theta.items())
    return {**base, "status": "explained" if full else "partly_explained", "effects": list(best.effects),
            "theta": best.theta, "stderr": best.stderr, "heldout_rmse_n": best.heldout_rmse_n,
            "heldout_rmse_base_n": best.heldout_rmse_base_n, "delta_bic": best.delta_bic,
            "words": (f"{'+'.join(best.effects)} {'explains' if full else 'explains part of'} the residual: {th}; "
                      f"held-out RMSE {best.heldout_rmse_base_n:.3f} -> {best.heldout_rmse_n:.3f} N "
                      f"(noise floor {floor:.3f} N, ratio {best.heldout_over_noise:.2f}), delta BIC {best.delta_bic:+.1f}")}
