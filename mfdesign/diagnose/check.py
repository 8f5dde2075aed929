"""Full check of candidate effects: calibrate them, held-out error by membrane, information criterion.

For a set of effects the model becomes ``F(theta) = base + [E(theta) - E(theta0)]`` with
``E`` the expected observed force of the forward model with the effects
(:meth:`~mfdesign.diagnose.emulated.ForwardModel.expected_force`) and ``base`` the model
under diagnosis (for the plain simulator ``base = E(theta0)``, so ``F = E``).

Every parameter of the set is refitted nonlinearly (:mod:`mfdesign.diagnose.refit`:
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
"""

from __future__ import annotations

from typing import Sequence

import numpy as np

# The refits themselves live in :mod:`mfdesign.diagnose.refit` (nonlinear, exact lattice).
from mfdesign.diagnose.refit import CheckResult, calibrate_effects, full_check
from mfdesign.diagnose.residuals import Residuals, shape_words

__all__ = ["CheckResult", "calibrate_effects", "full_check", "verdict"]

FLOOR_FACTOR = 1.2


def verdict(
    res: Residuals,
    checks: Sequence[CheckResult],
    floor_factor: float = FLOOR_FACTOR,
    min_gain: float = 0.1,
    bic_margin: float = 10.0,
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
    not_evaluated = (
        "; not evaluated (non-finite forces in the refit: the simulator did not converge there): "
        + ", ".join("+".join(c.effects) for c in failed)
        if failed
        else ""
    )
    base["not_evaluated"] = [list(c.effects) for c in failed]
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
    best = min(good, key=lambda c: (c.heldout_rmse_n, c.delta_bic))
    floor = max(floor, best.noise_floor_n)  # the floor under the candidate (refit.full_check)
    full = floor > 0 and best.heldout_rmse_n <= floor_factor * floor
    th = ", ".join(f"{k} = {v:.4g} +- {best.stderr.get(k, float('nan')):.2g}" for k, v in best.theta.items())
    return {
        **base,
        "status": "explained" if full else "partly_explained",
        "effects": list(best.effects),
        "theta": best.theta,
        "stderr": best.stderr,
        "heldout_rmse_n": best.heldout_rmse_n,
        "heldout_rmse_base_n": best.heldout_rmse_base_n,
        "delta_bic": best.delta_bic,
        "words": (
            f"{'+'.join(best.effects)} {'explains' if full else 'explains part of'} the residual: {th}; "
            f"held-out RMSE {best.heldout_rmse_base_n:.3f} -> {best.heldout_rmse_n:.3f} N "
            f"(noise floor {floor:.3f} N, ratio {best.heldout_over_noise:.2f}), delta BIC {best.delta_bic:+.1f}"
            f"{not_evaluated}"
        ),
    }
