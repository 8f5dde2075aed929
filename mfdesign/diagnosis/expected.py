"""Which rows diagnosis asks the model about, and how: query heights, usable rows, trial order.

Query heights: in a force trial the plate is held at ``height_set_mm`` (the recorded
height is a noisy reading of it), so the set-point is used where it is finite; in a lift
the recorded height. Lift rows where the plate rests on its stop (``h < resting_mm``) or
at the top of the rig carry no information on the membrane's push (the force column is
the weight) and are masked (:func:`usable_rows`). The forward model itself is
:class:`~mfdesign.diagnosis.forward.ForwardModel`.
"""

from __future__ import annotations

import numpy as np

from mfdesign.data.lifts import floating_rows
from mfdesign.data.measurements import Measurements

__all__ = ["query_heights", "trial_order", "usable_rows"]


def query_heights(meas: Measurements) -> np.ndarray:
    """Plate height [mm] at which the model is asked: set-point in force trials, else recorded."""
    df = meas._df
    hs = df["height_set_mm"].to_numpy(float)
    h = df["height_mm"].to_numpy(float)
    force = (df["experiment"] == "force").to_numpy()
    return np.where(force & np.isfinite(hs), hs, h)


def usable_rows(meas: Measurements, **kwargs) -> np.ndarray:
    """Rows whose force column says something about the membrane's push (bool mask):
    :func:`mfdesign.data.lifts.floating_rows` (force rows, and lift rows with the plate
    floating)."""
    return floating_rows(meas, **kwargs)


def trial_order(meas: Measurements) -> np.ndarray:
    """Order of each row's trial in its membrane's life (0 = first trial), int64."""
    df = meas._df
    return df.groupby("design_key", sort=False)["trial"].rank(method="dense").to_numpy(np.int64) - 1
