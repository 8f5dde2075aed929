"""Fast effect screen: how much of the residual can each candidate effect explain, to first order?

For a candidate effect with parameters ``theta`` (neutral ``theta0``), the sensitivity of
the expected observed force at every recorded (h, p) is the derivative
``J[:, j] = dF/dtheta_j (theta0)`` of the forward model
(:meth:`~mfdesign.diagnosis.forward.ForwardModel.jacobian`: forward-mode autodiff,
``jax.jacfwd``, one call for every candidate's parameters at once; a mechanical effect
differentiates through the exact model's lattice).

The residuals are then regressed on ``J`` by prior-weighted (ridge) least squares,
``min |r - J d|^2 / s^2 + sum_j (d_j / tau_j)^2`` with ``s`` the noise floor and ``tau_j``
the prior's scale (Gaussian-prior MAP of a linear model; Bishop 2006, sec. 3.3). Reported
per effect: fitted parameters ``theta0 + d``, their standard errors (residual variance,
inflated for serial correlation within trials by the AR(1) factor ``(1 + rho) / (1 - rho)``),
the fraction of the residual's mean square explained, the fraction of its *structure*
(mean square above the noise floor) explained, and ``delta BIC`` (Schwarz 1978) with the
effective sample size ``n (1 - rho) / (1 + rho)``. Ranked by explained fraction.
"""

from __future__ import annotations

import math
from dataclasses import dataclass, field
from typing import TYPE_CHECKING, Any, Mapping, Sequence

import numpy as np

from mfdesign.data.measurements import Measurements
from mfdesign.diagnosis.residuals import Residuals, subsample
from mfdesign.physics import effects as fx

if TYPE_CHECKING:
    from mfdesign.diagnosis.forward import ForwardModel

SCREEN_ROWS = 10000  # rows the screen differentiates at most

__all__ = ["ScreenResult", "parameter_scale", "parameter_step", "screen", "screen_pairs"]


def parameter_scale(p: fx.Parameter) -> float:
    """The prior's scale (:attr:`~mfdesign.physics.effects.Prior.scale`)."""
    return float(p.prior.scale)


def parameter_step(p: fx.Parameter) -> float:
    """Secant step: the realistic magnitude ``typical - neutral`` (prior scale if that is 0)."""
    s = float(p.typical - p.neutral)
    return s if s != 0.0 else parameter_scale(p)


def lag1_autocorrelation(frame, r: np.ndarray) -> float:
    """Lag-1 autocorrelation of ``r`` within trials (rows of one trial are consecutive)."""
    key = frame["design_key"].astype(str).to_numpy() + "|" + frame["trial"].astype(str).to_numpy()
    same = key[1:] == key[:-1]
    a, b = r[1:][same], r[:-1][same]
    if a.size < 3 or np.std(a) == 0 or np.std(b) == 0:
        return 0.0
    return float(np.clip(np.corrcoef(a, b)[0, 1], 0.0, 0.999))


def ridge_fit(J: np.ndarray, r: np.ndarray, sigma: float, tau: np.ndarray) -> np.ndarray:
    """MAP ``d`` of ``r ~ J d + N(0, sigma^2)``, ``d_j ~ N(0, tau_j^2)`` (augmented least squares)."""
    A = np.vstack([J / sigma, np.diag(1.0 / tau)])
    b = np.concatenate([r / sigma, np.zeros(J.shape[1])])
    return np.linalg.lstsq(A, b, rcond=None)[0]


@dataclass(frozen=True)
class ScreenResult:
    """One candidate's line in the ranked table (see the module doc for the definitions)."""

    effect: str
    story: str
    theta: dict
    stderr: dict
    explained_fraction: float
    structure_explained_fraction: float
    rms_before_n: float
    rms_after_n: float
    delta_bic: float
    n_eff: float
    sensitivity_rms_n: dict = field(default_factory=dict)
    effects: tuple[str, ...] = ()  # the set fitted jointly (one effect, or a pair: :func:`screen_pairs`)

    def to_json(self) -> dict:
        d = dict(self.__dict__)
        d["effects"] = list(self.effects)
        return d


def _fit_one(res: Residuals, J: np.ndarray, e: fx.Effect | Sequence[fx.Effect]) -> ScreenResult:
    """The ridge fit of one effect, or of a set of effects jointly (``J``: their columns, in order)."""
    es = [e] if isinstance(e, fx.Effect) else list(e)
    pars = [(x, p) for x in es for p in x.parameters]
    r = res.residual
    sigma = res.noise_floor_n if res.noise_floor_n > 0 else max(float(np.std(r)), 1e-9)
    tau = np.array([parameter_scale(p) for _, p in pars])
    ok = np.all(np.isfinite(J), axis=1)
    Jo, ro = J[ok], r[ok]
    d = ridge_fit(Jo, ro, sigma, tau)
    post = ro - Jo @ d
    ss0, ss1, n = float(np.sum(ro**2)), float(np.sum(post**2)), ro.size
    rho = lag1_autocorrelation(res.frame.loc[ok], post)
    infl = (1.0 + rho) / (1.0 - rho)
    n_eff = max(n / infl, 2.0)
    s2 = ss1 / max(n - len(d), 1)
    H = Jo.T @ Jo + s2 * np.diag(1.0 / tau**2)
    cov = s2 * infl * np.linalg.pinv(H)
    se = np.sqrt(np.clip(np.diag(cov), 0.0, None))
    k = len(d)
    dbic = n_eff * math.log(max(ss1, 1e-300) / max(ss0, 1e-300)) + k * math.log(n_eff)
    excess = ss0 / n - sigma**2
    struct = (ss0 - ss1) / n / excess if excess > 0 else 0.0
    return ScreenResult(
        effect="+".join(x.name for x in es),
        story="; ".join(x.story for x in es),
        theta={x.qualified(p.name): float(p.neutral + d[j]) for j, (x, p) in enumerate(pars)},
        stderr={x.qualified(p.name): float(se[j]) for j, (x, p) in enumerate(pars)},
        explained_fraction=float(1.0 - ss1 / ss0) if ss0 > 0 else 0.0,
        structure_explained_fraction=float(min(struct, 1.5)),
        rms_before_n=float(math.sqrt(ss0 / n)),
        rms_after_n=float(math.sqrt(ss1 / n)),
        delta_bic=float(dbic),
        n_eff=float(n_eff),
        sensitivity_rms_n={
            x.qualified(p.name): float(np.sqrt(np.mean(Jo[:, j] ** 2))) for j, (x, p) in enumerate(pars)
        },
        effects=tuple(x.name for x in es),
    )


def _sensitivities(res, meas, sim, candidates, base_effects, base_theta, max_rows):
    """``(residuals on at most max_rows rows, candidate effects, J [rows, their parameters])``:
    one ``jacfwd`` for every candidate's parameters at once."""
    if len(res.frame) > max_rows:
        res = res.take(subsample(res.frame, max_rows))
    base = [fx.effect(b) for b in base_effects]
    names = {b.name for b in base}
    cands = [fx.effect(c) for c in (candidates if candidates is not None else sorted(fx.EFFECTS))]
    cands = [c for c in cands if c.name not in names]
    rows = res.frame["row"].to_numpy()
    free = [c.qualified(p.name) for c in cands for p in c.parameters]
    J_all = sim.jacobian(meas, free, base, base_theta, rows=rows)
    cols, j = {}, 0
    for c in cands:
        cols[c.name] = slice(j, j + len(c.parameters))
        j += len(c.parameters)
    return res, cands, J_all, cols


def screen(
    res: Residuals,
    meas: Measurements,
    sim: ForwardModel,
    candidates: Sequence[str | fx.Effect] | None = None,
    base_effects: Sequence[str | fx.Effect] = (),
    base_theta: Mapping[str, Any] | None = None,
    progress: bool = False,
    max_rows: int = SCREEN_ROWS,
) -> list[ScreenResult]:
    """Rank ``candidates`` (default: every registered effect not in ``base_effects``) by the
    fraction of the residual ``res`` each explains to first order; best first. At most
    ``max_rows`` rows, evenly spaced within each trial (neighbouring samples of a 10 Hz
    ramp add little: the lag-1 correlation of the remainder sets ``n_eff`` anyway)."""
    res, cands, J_all, cols = _sensitivities(res, meas, sim, candidates, base_effects, base_theta, max_rows)
    out = [_fit_one(res, J_all[:, cols[c.name]], c) for c in cands]
    out.sort(key=lambda s: -s.explained_fraction)
    return out


def screen_pairs(
    res: Residuals,
    meas: Measurements,
    sim: ForwardModel,
    candidates: Sequence[str | fx.Effect] | None = None,
    base_effects: Sequence[str | fx.Effect] = (),
    base_theta: Mapping[str, Any] | None = None,
    max_rows: int = SCREEN_ROWS,
) -> list[ScreenResult]:
    """Every pair of ``candidates`` fitted jointly to first order (the same ridge fit on both
    effects' sensitivity columns at once), best first.

    Why: two effects acting together can each look like something else on its own. A
    one-at-a-time screen then ranks wrong candidates first (a pressure offset plus a thinner
    membrane read as a rubber effect), and the right pair is never refitted. An exhaustive
    best-subset search of size two (Furnival & Wilson 1974) costs only small least-squares
    solves on the Jacobian the screen computes anyway."""
    res, cands, J_all, cols = _sensitivities(res, meas, sim, candidates, base_effects, base_theta, max_rows)
    out = [
        _fit_one(res, np.concatenate([J_all[:, cols[a.name]], J_all[:, cols[b.name]]], axis=1), (a, b))
        for i, a in enumerate(cands)
        for b in cands[i + 1 :]
    ]
    out.sort(key=lambda s: -s.explained_fraction)
    return out
