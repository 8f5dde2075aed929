"""Full check of candidate effects: calibrate them, held-out error by membrane, information criterion.

For a set of effects the model becomes ``F(theta) = base + [E(theta) - E(theta0)]`` with
``E`` the expected observed force of the forward model with the effects
(:meth:`~mfdesign.diagnosis.forward.ForwardModel.expected_force`) and ``base`` the model
under diagnosis (for the plain simulator ``base = E(theta0)``, so ``F = E``).

Every parameter of the set is refitted nonlinearly (:mod:`mfdesign.diagnosis.refit`:
Levenberg-Marquardt, optimistix), on all membranes and per fold, in one compiled call;
delta BIC with the calibration's likelihood
(:meth:`~mfdesign.models.hierarchical.HierarchicalModel.log_lik`). Mechanical effects are
refitted on the exact model's lattice, which grows where the fits go.

Verdict (:func:`verdict`): nothing is claimed when the residual is already at the noise
floor (RMS <= ``floor_factor`` x noise floor) or when no candidate lowers both BIC (by
more than 10) and the held-out RMSE (by more than ``min_gain``); otherwise the best
candidate is "explains" if its held-out RMSE is within ``floor_factor`` x the noise floor
under that candidate (its own residuals' floor, never below the tested model's: in a lift
the force error is slope x height error, and the slope is the model's), else "explains
part".

Sets of different sizes (single effects and pairs fitted jointly) are nested models: the
best set of each size is taken, smallest first, and a larger set replaces the smaller only
if it beats it by the same margins (BIC by more than ``bic_margin``, held-out RMSE by more
than ``min_gain``): a second effect must earn its place. Two sets of the claimed size that
the data cannot tell apart (held-out RMSE within ``tie`` of each other and BIC within
``bic_margin``) are both named, never one silently (``"alternatives"``).
"""

from __future__ import annotations

from typing import Sequence

import numpy as np

# The refits themselves live in :mod:`mfdesign.diagnosis.refit` (nonlinear, exact lattice).
from mfdesign.diagnosis.refit import CheckResult, calibrate_effects, full_check
from mfdesign.diagnosis.residuals import Residuals, shape_words

__all__ = ["CheckResult", "calibrate_effects", "full_check", "verdict"]

FLOOR_FACTOR = 1.2
TIE = 0.05  # held-out RMSEs within 5 % of each other: a tie on these data (with BIC within the margin)


def _pick(good: Sequence[CheckResult], min_gain: float, bic_margin: float) -> CheckResult:
    """The claimed set among ``good``: the best of each size, smallest first; a larger set
    replaces the smaller only if it beats it by the claim's margins (module doc)."""
    best = None
    for k in sorted({len(c.effects) for c in good}):
        cand = min((c for c in good if len(c.effects) == k), key=lambda c: (c.heldout_rmse_n, c.delta_bic))
        if best is None or (
            cand.delta_bic < best.delta_bic - bic_margin and cand.heldout_rmse_n < (1 - min_gain) * best.heldout_rmse_n
        ):
            best = cand
    assert best is not None
    return best


def ties(best: CheckResult, checks: Sequence[CheckResult], tie: float = TIE, bic_margin: float = 10.0) -> list:
    """Sets of ``best``'s size, other than it, that the data cannot tell from it (module doc)."""
    return [
        c
        for c in checks
        if c is not best
        and len(c.effects) == len(best.effects)
        and set(c.effects) != set(best.effects)
        and np.isfinite(c.heldout_rmse_n)
        and c.heldout_rmse_n <= (1 + tie) * best.heldout_rmse_n
        and c.delta_bic <= best.delta_bic + bic_margin
    ]


def verdict(
    res: Residuals,
    checks: Sequence[CheckResult],
    floor_factor: float = FLOOR_FACTOR,
    min_gain: float = 0.1,
    bic_margin: float = 10.0,
    tie: float = TIE,
) -> dict:
    """What may be claimed (see the module doc): ``{"status", "effects", "words", ...}``."""
    floor = res.noise_floor_n
    rms = res.rmse_n
    base: dict = {"rmse_n": rms, "noise_floor_n": floor, "rmse_over_noise": rms / floor if floor > 0 else None}
    if floor > 0 and rms <= floor_factor * floor:
        return {
            **base,
            "status": "at_noise_floor",
            "effects": [],
            "words": (
                f"nothing to explain: the residual RMS {rms:.3f} N is within {floor_factor:g} x the "
                f"noise floor {floor:.3f} N; no effect is claimed"
            ),
        }
    # a refit whose forces are not finite (the simulator did not converge there) is named,
    # never ranked: NaN compares False, so min() would pick one silently
    failed = [c for c in checks if not (np.isfinite(c.heldout_rmse_n) and np.isfinite(c.delta_bic))]
    checks = [c for c in checks if c not in failed]
    # the planes grow to whatever a fit needs and the FE reference fills the nodes the
    # shooting cannot solve, so what is left is a genuine failure of both: name the rows
    not_evaluated = (
        "; not evaluated (neither the simulator nor the FE reference has a value there): "
        + ", ".join(f"{'+'.join(c.effects)} at {c.undefined or 'its rows'}" for c in failed)
        if failed
        else ""
    )
    base["not_evaluated"] = [list(c.effects) for c in failed]
    base["not_evaluated_rows"] = {"+".join(c.effects): c.undefined for c in failed}
    good = [
        c for c in checks if c.delta_bic < -bic_margin and c.heldout_rmse_n < (1 - min_gain) * c.heldout_rmse_base_n
    ]
    if not good:
        best = min(checks, key=lambda c: c.heldout_rmse_n) if checks else None
        extra = (
            (
                f"; the best candidate, {'+'.join(best.effects)}, leaves held-out RMSE {best.heldout_rmse_n:.3f} N "
                f"(was {best.heldout_rmse_base_n:.3f} N, delta BIC {best.delta_bic:+.1f})"
            )
            if best
            else ""
        )
        return {
            **base,
            "status": "unexplained",
            "effects": [],
            "words": (
                f"no candidate effect explains the residual structure: RMS {rms:.3f} N vs noise floor "
                f"{floor:.3f} N{extra}{not_evaluated}; the residual's shape: {shape_words(res)}"
            ),
        }
    best = _pick(good, min_gain, bic_margin)
    floor = max(floor, best.noise_floor_n)  # the floor under the candidate (refit.full_check)
    full = floor > 0 and best.heldout_rmse_n <= floor_factor * floor
    th = ", ".join(f"{k} = {v:.4g} +- {best.stderr.get(k, float('nan')):.2g}" for k, v in best.theta.items())
    alts = ties(best, good, tie, bic_margin)
    either = (
        (
            "; the data cannot tell it from "
            + ", ".join(
                f"{'+'.join(c.effects)} (held-out RMSE {c.heldout_rmse_n:.3f} N, delta BIC {c.delta_bic:+.1f})"
                for c in alts
            )
            + ": both are named, neither is preferred"
        )
        if alts
        else ""
    )
    return {
        **base,
        "status": "explained" if full else "partly_explained",
        "effects": list(best.effects),
        "theta": best.theta,
        "stderr": best.stderr,
        "heldout_rmse_n": best.heldout_rmse_n,
        "heldout_rmse_base_n": best.heldout_rmse_base_n,
        "delta_bic": best.delta_bic,
        "alternatives": [
            {
                "effects": list(c.effects),
                "theta": c.theta,
                "stderr": c.stderr,
                "heldout_rmse_n": c.heldout_rmse_n,
                "delta_bic": c.delta_bic,
            }
            for c in alts
        ],
        "words": (
            f"{'+'.join(best.effects)} {'explains' if full else 'explains part of'} the residual: {th}; "
            f"held-out RMSE {best.heldout_rmse_base_n:.3f} -> {best.heldout_rmse_n:.3f} N "
            f"(noise floor {floor:.3f} N, ratio {best.heldout_over_noise:.2f}), delta BIC {best.delta_bic:+.1f}"
            f"{either}{not_evaluated}"
        ),
    }
