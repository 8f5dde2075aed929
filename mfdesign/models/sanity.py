"""A loaded model is tried on a few points before anything trusts it.

Why: a model folder can load cleanly and still be useless. All-zero weights, a zero
normalisation scale, weights of 1e30, a NaN discrepancy gate or ``beta = -1e9`` all load,
and then predict NaN or absurd forces everywhere. ``optimize`` took that for "every load
lifted to the top" and ``propose`` blamed the user ("thickness must be finite, got nan").
Here the predictor answers on a small fixed set of membranes and set-points inside the
design space, and must give finite forces in a physical range, or the folder is refused
in one line naming it and what is wrong.
"""

from __future__ import annotations

import numpy as np

from mfdesign.errors import InputError

__all__ = ["FORCE_RANGE_N", "check_predictor"]

# What a membrane of the design space can push, with room: p pi R^2 at 20 kPa is 308 N;
# the Measurements schema allows [-50, 1000] N.
FORCE_RANGE_N = (-100.0, 2000.0)
_DESIGNS = np.array(
    [
        [2.0, 25.4, np.nan, np.nan, np.nan, np.nan],
        [1.5, 31.92, 46.0, 5.0, 59.0, 5.0],
        [3.0, 38.1, 50.0, 6.0, np.nan, np.nan],
    ]
)
_HEIGHTS_MM = np.array([5.0, 30.0, 60.0])
_PRESSURES_PA = np.array([2000.0, 5000.0, 8000.0])


def check_predictor(predictor, where: str):
    """``predictor`` (an :class:`~mfdesign.models.predictor.AbstractPredictor`) if its
    members give finite forces within :data:`FORCE_RANGE_N` on every fidelity at the probe
    points; else :class:`InputError` naming ``where`` (the model folder)."""
    d = np.repeat(_DESIGNS, _HEIGHTS_MM.size * _PRESSURES_PA.size, axis=0)
    h, p = (a.ravel() for a in np.meshgrid(_HEIGHTS_MM, _PRESSURES_PA, indexing="ij"))
    h, p = np.tile(h, len(_DESIGNS)), np.tile(p, len(_DESIGNS))
    low, high = FORCE_RANGE_N
    for fidelity in predictor.fidelities:
        try:
            f = np.asarray(predictor.members(fidelity, d, h, p), dtype=float)
        except (ArithmeticError, ValueError, TypeError) as err:
            raise InputError(
                f"model {where}: cannot predict ({type(err).__name__}: {err}); allowed: a model folder "
                "written by mfdesign fit or fit-mf (refit it)"
            ) from None
        bad = ~np.isfinite(f)
        if bad.all() or f.size == 0:
            what = "NaN or infinite forces everywhere"
        elif bad.any():
            what = f"NaN or infinite forces at {int(bad.sum())} of {f.size} probe points"
        elif f.min() < low or f.max() > high:
            what = f"forces from {f.min():.4g} to {f.max():.4g} N"
        else:
            continue
        raise InputError(
            f"model {where} predicts {what} ({fidelity} fidelity, membranes of the design space at "
            f"5-60 mm, 2-8 kPa); allowed: finite forces within {low:g} to {high:g} N (refit the model)"
        )
    return predictor
