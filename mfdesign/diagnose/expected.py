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
import pandas as pd

from mfdesign.data.measurements import Measurements

__all__ = ["query_heights", "trial_order", "usable_rows"]

RESTING_MM = 1.5  # a lifted plate below this rests on its stop (the sensor reads 0 or 1 mm there)
JUMP_MM = 2.0  # a lifted plate moving more than this between samples is not in equilibrium
HELD_PA = 400.0  # pressure a plate may gain within HELD_BAND_MM of its trial's end and still float
HELD_BAND_MM = 1.0


def query_heights(meas: Measurements) -> np.ndarray:
    """Plate height [mm] at which the model is asked: set-point in force trials, else recorded."""
    df = meas._df
    hs = df["height_set_mm"].to_numpy(float)
    h = df["height_mm"].to_numpy(float)
    force = (df["experiment"] == "force").to_numpy()
    return np.where(force & np.isfinite(hs), hs, h)


def usable_rows(
    meas: Measurements,
    resting_mm: float = RESTING_MM,
    top_mm: float | None = None,
    jump_mm: float = JUMP_MM,
    held_pa: float = HELD_PA,
    held_band_mm: float = HELD_BAND_MM,
) -> np.ndarray:
    """Rows whose force column says something about the membrane's push (bool mask).

    A lift row is an equation ``F(h, p) = W`` only while the plate floats. Excluded:

    * the plate on its stop (``h < resting_mm``);
    * a plate held at either end of its travel: per trial, the rows within
      ``held_band_mm`` of the trial's lowest (highest) height when their pressures span
      more than ``held_pa``. A floating plate rises about 10 mm per kPa, so it cannot stay
      in a 1 mm band while the pressure changes by hundreds of pascals; a plate resting on
      a support that is not at 0 mm (the real rig's height zero sits a few mm below some
      plates' rest) or pinned by the rig's top (lower for a taller mass stack) does;
    * the rig's top (``h >= top_mm``, default: the largest lift height recorded minus
      0.5 mm, when several rows sit there);
    * a jumping plate (snap-through: the height changes by more than ``jump_mm`` from a
      neighbouring sample of the trial, so the plate is not in equilibrium).
    """
    df = meas._df
    lift = (df["experiment"] == "lift").to_numpy()
    h = df["height_mm"].to_numpy(float)
    p = df["pressure_pa"].to_numpy(float)
    bad = lift & (h < resting_mm)
    tid = df["design_key"].to_numpy(object).astype(str) + "|" + df["trial"].to_numpy().astype(str)
    same = tid[1:] == tid[:-1]
    dh = np.abs(np.diff(h)) > jump_mm
    jump = np.zeros(len(h), bool)
    jump[1:] |= same & dh
    jump[:-1] |= same & dh
    bad |= lift & jump
    bad |= lift & _held_at_an_end(tid, h, p, held_band_mm, held_pa)
    if top_mm is None and lift.any():
        top = float(np.max(h[lift]))
        if np.sum(lift & (h >= top - 0.5)) > 5:
            top_mm = top - 0.5
    if top_mm is not None:
        bad |= lift & (h >= top_mm)
    return ~bad


def _held_at_an_end(tid: np.ndarray, h: np.ndarray, p: np.ndarray, band_mm: float, span_pa: float) -> np.ndarray:
    """Rows of each trial held at the top or bottom of its travel (vectorised over trials).

    Top: within ``band_mm`` of the trial's highest height while the pressure spans more
    than ``span_pa`` there. Bottom: the plate's reading at rest is the highest height among
    the trial's lowest-pressure rows (the lowest 5 % of its pressure range; a resting plate's
    reading jitters by a few mm on the real rig); rows up to ``band_mm`` above it rest too,
    when the pressure spans more than ``span_pa`` there."""
    frame = pd.DataFrame({"t": tid, "h": h, "p": p}).dropna()
    g = frame.groupby("t", sort=False)
    p_lo, p_hi = g["p"].transform("min"), g["p"].transform("max")
    first = frame["p"] <= p_lo + 0.05 * (p_hi - p_lo)
    rest_h = frame["h"].where(first).groupby(frame["t"]).transform("max")
    held = pd.Series(False, index=frame.index)
    for near in (frame["h"] >= g["h"].transform("max") - band_mm, frame["h"] <= rest_h + band_mm):
        q = frame["p"].where(near)
        span = q.groupby(frame["t"]).transform("max") - q.groupby(frame["t"]).transform("min")
        held |= near & (span > span_pa)
    out = np.zeros(len(h), bool)
    out[frame.index.to_numpy()] = held.to_numpy()
    return out


def trial_order(meas: Measurements) -> np.ndarray:
    """Order of each row's trial in its membrane's life (0 = first trial), int64."""
    df = meas._df
    return df.groupby("design_key", sort=False)["trial"].rank(method="dense").to_numpy(np.int64) - 1
