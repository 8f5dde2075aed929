"""Which lift rows are equations ``F(h, p) = W``: the plate must float.

In a mass lift the force column is the lifted weight, not a reading; it equals the
membrane's push only while the plate floats in equilibrium. Diagnosis, calibration and
the discrepancy fit all ask this one question (:func:`floating_rows`); force-trial rows
always count.
"""

from __future__ import annotations

import numpy as np
import pandas as pd

__all__ = [
    "HELD_BAND_MM",
    "HELD_MIN_ROWS",
    "HELD_PA",
    "JUMP_MM",
    "JUMP_MM_PER_PA",
    "RESTING_MM",
    "STALL_PA",
    "floating_rows",
    "stalls",
]

RESTING_MM = 1.5  # a lifted plate below this rests on its stop (the sensor reads 0 or 1 mm there)
JUMP_MM = 2.0  # a lifted plate moving more than this between samples is not in equilibrium
JUMP_MM_PER_PA = 0.1  # ... when it moves faster than this with pressure (2x the steepest lift curve)
HELD_PA = 400.0  # pressure a plate may gain within HELD_BAND_MM of its trial's end and still float
HELD_BAND_MM = 1.0
HELD_MIN_ROWS = 5  # a hold shows as a run of samples; two sparse samples prove nothing
STALL_PA = 400.0  # pressure a plate may spend on one mm of rise before it "stalls" (it needs ~100 Pa)
STALL_ABOVE_MM = 8.0  # stalls are looked for above this (a resting plate reads up to 6-7 mm)
STALL_TOP_MM = 2.0  # a stall this close to its trial's top is a hold at the end of travel
STALL_REPEAT_MM = 2.0  # ... and one this close to a stall of another trial of the same mass repeats


def floating_rows(
    table,
    resting_mm: float = RESTING_MM,
    top_mm: float | None = None,
    jump_mm: float = JUMP_MM,
    held_pa: float = HELD_PA,
    held_band_mm: float = HELD_BAND_MM,
) -> np.ndarray:
    """Rows whose force column says something about the membrane's push (bool mask).

    ``table``: a :class:`~mfdesign.data.measurements.Measurements` or its DataFrame.

    A lift row is an equation ``F(h, p) = W`` only while the plate floats. Excluded:

    * the plate on its stop (``h < resting_mm``);
    * a plate held at either end of its travel: per trial, the rows within
      ``held_band_mm`` of the trial's lowest (highest) height when their pressures span
      more than ``held_pa`` (and at least ``HELD_MIN_ROWS`` rows sit there). A floating plate rises about 10 mm per kPa, so it cannot stay
      in a 1 mm band while the pressure changes by hundreds of pascals; a plate resting on
      a support that is not at 0 mm (the real rig's height zero sits a few mm below some
      plates' rest) or pinned by the rig's top (lower for a taller mass stack) does;
    * the rig's top (``h >= top_mm``, default: the largest lift height recorded minus
      0.5 mm, when several rows sit there);
    * a jumping plate (snap-through: the height changes by more than ``jump_mm`` from a
      neighbouring sample of the trial, faster than ``JUMP_MM_PER_PA`` with pressure, so
      the plate is not in equilibrium).
    """
    df = table if isinstance(table, pd.DataFrame) else table.df
    lift = (df["experiment"] == "lift").to_numpy()
    h = df["height_mm"].to_numpy(float)
    p = df["pressure_pa"].to_numpy(float)
    bad = lift & (h < resting_mm)
    tid = df["design_key"].to_numpy(object).astype(str) + "|" + df["trial"].to_numpy().astype(str)
    same = tid[1:] == tid[:-1]
    # a jump moves the plate far for almost no pressure (sparse samples of a steady rise
    # are not jumps: a floating plate rises at most ~50 mm/kPa, ringless near lift-off)
    dh = (np.abs(np.diff(h)) > jump_mm) & (np.abs(np.diff(h)) > JUMP_MM_PER_PA * np.abs(np.diff(p)))
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
        count = near.groupby(frame["t"]).transform("sum")
        held |= near & (span > span_pa) & (count >= HELD_MIN_ROWS)
    out = np.zeros(len(h), bool)
    out[frame.index.to_numpy()] = held.to_numpy()
    return out


def stalls(table, min_pa: float = STALL_PA, above_mm: float = STALL_ABOVE_MM) -> pd.DataFrame:
    """Where each lift trial's plate stalls, from the data alone (no model).

    ``table``: a :class:`~mfdesign.data.measurements.Measurements` or its DataFrame.

    A floating plate rises about 10 mm per kPa (100 Pa a millimetre). A stall is a height
    level (whole mm of the trial's running top, the sensor's resolution) at which the
    pressure climbed more than ``min_pa`` before the plate rose a millimetre further, above
    ``above_mm``. Each is classed by what the other trials say: ``at_top`` (within
    ``STALL_TOP_MM`` of its trial's top: a hold at the end of travel, which
    :func:`floating_rows` drops only within ``HELD_BAND_MM``) and ``repeats`` (another trial
    of the same membrane and mass stalls within ``STALL_REPEAT_MM``: the membrane's own
    mechanics rather than an event of the rig).

    Returns one row per stall: ``design_key``, ``trial``, ``force_n`` [N], ``height_mm``,
    ``spent_pa`` (the pressure climbed there), ``at_top``, ``repeats`` (empty without lifts).
    """
    df = table if isinstance(table, pd.DataFrame) else table.df
    cols = ["design_key", "trial", "force_n", "height_mm", "spent_pa", "at_top", "repeats"]
    lift = df[df["experiment"] == "lift"].dropna(subset=["height_mm", "pressure_pa"])
    # inflation order within each trial (some trials are stored top-down), then the running
    # top of the height: one group per (trial, level), vectorised over trials
    seen = pd.factorize(lift["design_key"].astype(str) + "|" + lift["trial"].astype(str))[0]  # the file's order
    f = lift.assign(_seen=seen).sort_values(["_seen", "pressure_pa"], kind="stable")
    trial = [f["design_key"], f["trial"]]
    level = f["height_mm"].groupby(trial).cummax()
    g = f.groupby([f["design_key"], f["trial"], level.rename("level")], sort=False)
    out = pd.DataFrame(
        {
            "force_n": g["force_n"].first().round(3),
            "spent_pa": g["pressure_pa"].max() - g["pressure_pa"].min(),
            "top": level.groupby(trial).max().reindex(g.size().index.droplevel("level")).to_numpy(),
        }
    ).reset_index()
    out = out[(out["level"] >= above_mm) & (out["spent_pa"] > min_pa)].rename(columns={"level": "height_mm"})
    out["at_top"] = out["height_mm"] >= out.pop("top") - STALL_TOP_MM
    out = out.astype({"trial": int, "height_mm": float})[cols[:-1]].reset_index(drop=True)
    if out.empty:
        return pd.DataFrame(columns=cols)
    # repeats: a stall of ANOTHER trial of the same membrane and mass within STALL_REPEAT_MM
    pair = out.merge(out, on=["design_key", "force_n"], suffixes=("", "_o"))
    near = (pair["trial"] != pair["trial_o"]) & ((pair["height_mm"] - pair["height_mm_o"]).abs() <= STALL_REPEAT_MM)
    hit = pair[near].groupby(["design_key", "trial", "height_mm"]).size()
    idx = pd.MultiIndex.from_frame(out[["design_key", "trial", "height_mm"]])
    out["repeats"] = idx.isin(hit.index)
    return out
