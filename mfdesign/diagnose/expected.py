"""Which rows diagnosis asks the model about, and how: query heights, usable rows, trial order.

Query heights: in a force trial the plate is held at ``height_set_mm`` (the recorded
height is a noisy reading of it), so the set-point is used where it is finite; in a lift
the recorded height. Lift rows where the plate rests on its stop (``h < resting_mm``) or
at the top of the rig carry no information on the membrane's push (the force column is
the weight) and are masked (:func:`usable_rows`). The forward model itself is
:class:`~mfdesign.diagnose.emulated.ForwardModel`.
"""

from __future__ import annotations

import numpy as np

from mfdesign.data.measurements import Measurements

__all__ = ["query_heights", "trial_order", "usable_rows"]

RESTING_MM = 1.5  # a lifted plate below this rests on its stop (the sensor reads 0 or 1 mm there)
JUMP_MM = 2.0  # a lifted plate moving more than this between samples is not in equilibrium


def query_heights(meas: Measurements) -> np.ndarray:
    """Plate height [mm] at which the model is asked: set-point in force trials, else recorded."""
    df = meas._df
    hs = df["height_set_mm"].to_numpy(float)
    h = df["height_mm"].to_numpy(float)
    force = (df["experiment"] == "force").to_numpy()
    return np.where(force & np.isfinite(hs), hs, h)


def usable_rows(
    meas: Measurements, resting_mm: float = RESTING_MM, top_mm: float | None = None, jump_mm: float = JUMP_MM
) -> np.ndarray:
    """Rows whose force column says something about the membrane's push (bool mask).

    Excludes lift rows with the plate on its stop (``h < resting_mm``), at the rig's top
    (``h >= top_mm``, default: the largest lift height recorded minus 0.5 mm, when several
    rows sit there) or jumping (snap-through: the height changes by more than ``jump_mm``
    from a neighbouring sample of the trial, so the plate is not in equilibrium)."""
    df = meas._df
    lift = (df["experiment"] == "lift").to_numpy()
    h = df["height_mm"].to_numpy(float)
    bad = lift & (h < resting_mm)
    tid = df["design_key"].to_numpy(object).astype(str) + "|" + df["trial"].to_numpy().astype(str)
    same = tid[1:] == tid[:-1]
    dh = np.abs(np.diff(h)) > jump_mm
    jump = np.zeros(len(h), bool)
    jump[1:] |= same & dh
    jump[:-1] |= same & dh
    bad |= lift & jump
    if top_mm is None and lift.any():
        top = float(np.max(h[lift]))
        if np.sum(lift & (h >= top - 0.5)) > 5:
            top_mm = top - 0.5
    if top_mm is not None:
        bad |= lift & (h >= top_mm)
    return ~bad


def trial_order(meas: Measurements) -> np.ndarray:
    """Order of each row's trial in its membrane's life (0 = first trial), int64."""
    df = meas._df
    return df.groupby("design_key", sort=False)["trial"].rank(method="dense").to_numpy(np.int64) - 1
