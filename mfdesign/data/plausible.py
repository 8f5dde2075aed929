"""Bounds and plausibility checks on what an import reads, before it becomes Measurements.

The Measurements schema (:mod:`mfdesign.data.measurements`) checks each value against a
wide physical range. That range lets a wrong unit through: heights in metres (0.03 fits
in [-5, 200] mm), pressures in kPa (7.5 fits in [-20e3, 200e3] Pa), time stamps in
nanoseconds since 1970 (>= 0 s). The checks here look at a column as a whole, the way a
person would, and refuse in one line naming the column, what it looks like and what is
allowed.

Why a row bound: every table is held in memory several times over (pandas, the models'
arrays); a 10-million-row file would end in an out-of-memory kill, not a message. The real
mass-lift file has 45,924 rows; a day of rig sampling at 10 Hz is under 10^6.
"""

from __future__ import annotations

import numpy as np
import pandas as pd

from mfdesign.errors import InputError

__all__ = ["MAX_ROWS", "check_columns", "check_rows"]

MAX_ROWS = 2_000_000
MAX_WEIGHT = 1e9  # weights are relative (the real files: each membrane's sum to 1000)


def check_rows(n: int, where: str) -> None:
    """Refuse a source of more than :data:`MAX_ROWS` rows (call before building a frame)."""
    if n > MAX_ROWS:
        raise InputError(f"{where}: {n:,} rows; allowed: at most {MAX_ROWS:,} rows per source (split the file)")


def _refuse(where: str, column: str, what: str, allowed: str) -> None:
    raise InputError(f"{where}: column {column!r} {what}; allowed: {allowed}")


def check_columns(df: pd.DataFrame, where: str) -> None:
    """Per-column plausibility of a raw table with the Measurements columns (docs/data.md).

    Types: numeric columns must not be booleans (a True/False pressure would read as 0/1 Pa).
    Units: heights that all lie within 0.25 (metres, not mm), pressures whose magnitudes all
    lie within 200 (kPa, not Pa) while some are non-zero, times beyond 10^7 s (115 days:
    an epoch time stamp, not seconds since the trial's start).
    Ranges: a clearly negative pressure (below -1 kPa) with a clearly positive force.
    Lifts: the force of a lift trial is the weight of its mass, one value per trial.
    """
    check_rows(len(df), where)
    for column in ("time_s", "height_set_mm", "height_mm", "pressure_pa", "force_n", "weight", "trial"):
        if column in df.columns and pd.api.types.is_bool_dtype(df[column].dtype):
            _refuse(where, column, "holds True/False values", "numbers in the column's unit (docs/data.md)")
    num = {}
    for column in ("time_s", "height_mm", "pressure_pa", "force_n", "weight"):
        if column in df.columns:
            num[column] = pd.to_numeric(df[column], errors="coerce").to_numpy(dtype=np.float64, na_value=np.nan)
    if "height_mm" in num:
        h = num["height_mm"][np.isfinite(num["height_mm"])]
        if len(h) >= 10 and np.ptp(h) > 0 and np.abs(h).max() <= 0.25:
            _refuse(
                where,
                "height_mm",
                f"spans only {h.min():g} to {h.max():g}: that looks like metres",
                "millimetres (multiply metres by 1000)",
            )
    if "pressure_pa" in num:
        p = num["pressure_pa"][np.isfinite(num["pressure_pa"])]
        if len(p) >= 10 and np.abs(p).max() > 0 and np.abs(p).max() <= 200.0:
            _refuse(
                where,
                "pressure_pa",
                f"never exceeds {np.abs(p).max():g} in magnitude: that looks like kPa",
                "pascals (multiply kPa by 1000, or map the column with unit kPa: --columns pressure_pa=COLUMN:kPa)",
            )
    if "time_s" in num:
        t = num["time_s"][np.isfinite(num["time_s"])]
        if len(t) and t.max() > 1e7:
            _refuse(
                where,
                "time_s",
                f"reaches {t.max():.4g} s: that looks like a clock time stamp",
                "seconds since the trial's start (subtract the first time stamp; NaN if unknown)",
            )
    if "weight" in num:
        w = num["weight"][np.isfinite(num["weight"])]
        if len(w) and w.max() > MAX_WEIGHT:
            _refuse(
                where,
                "weight",
                f"reaches {w.max():.4g}",
                f"relative weights up to {MAX_WEIGHT:g} (sums of 1e308 overflow: 'math domain error')",
            )
    if "pressure_pa" in num and "force_n" in num:
        bad = (num["pressure_pa"] < -1e3) & (num["force_n"] > 1.0)
        if bad.any():
            i = int(np.flatnonzero(bad)[0])
            _refuse(
                where,
                "pressure_pa",
                f"row {i} has {num['pressure_pa'][i]:g} Pa with a force of {num['force_n'][i]:g} N",
                "a pushing force needs a positive gauge pressure (check the sign of the pressure column)",
            )
    if {"experiment", "design_key", "trial"} <= set(df.columns) and "force_n" in num:
        _check_trials(df, num, where)
    if "pressure_pa" in num and "force_n" in num and "experiment" in df.columns:
        _check_force_unit(df, num, where)  # after the trials: a stuck constant is the more specific word


OUTER_AREA_M2 = 3.141592653589793 * 0.070**2  # the membranes' outer radius is 70 mm


def _check_force_unit(df: pd.DataFrame, num: dict[str, np.ndarray], where: str) -> None:
    """A held plate cannot be pushed by more than the pressure on the whole membrane,
    ``p pi R^2`` (R = 70 mm). Forces that mostly exceed it many times over were logged in
    grams (or mN), not newtons. Lift trials are left out: before lift-off their force (the
    mass) is above what the pressure can give."""
    force = (df["experiment"].astype(str) == "force").to_numpy()
    p, f = num["pressure_pa"][force], num["force_n"][force]
    ok = np.isfinite(p) & np.isfinite(f) & (p > 1e3)
    if ok.sum() < 10:
        return
    ratio = f[ok] / (p[ok] * OUTER_AREA_M2)
    if np.median(ratio) > 3.0:
        _refuse(
            where,
            "force_n",
            f"is a median {np.median(ratio):.3g} times the pressure on the whole membrane (p pi R^2): "
            "that is not newtons (grams? millinewtons?)",
            "newtons (multiply grams by 0.00981, or map the column with unit g: --columns force_n=COLUMN:g)",
        )


def _check_trials(df: pd.DataFrame, num: dict[str, np.ndarray], where: str) -> None:
    """Per trial: a lift holds one force (its mass); a force trial's force follows the pressure."""
    if "pressure_pa" in num:
        force = (df["experiment"].astype(str) == "force").to_numpy()
        sub = pd.DataFrame(
            {
                "k": df["design_key"].to_numpy()[force],
                "t": df["trial"].to_numpy()[force],
                "f": num["force_n"][force],
                "p": num["pressure_pa"][force],
            }
        )
        span = sub.groupby(["k", "t"], sort=False).agg(f=("f", np.ptp), p=("p", np.ptp), n=("f", "size"))
        stuck = span[(span["n"] >= 10) & (span["f"] == 0) & (span["p"] > 1e3)]
        if len(stuck):
            key, trial = stuck.index[0]
            _refuse(
                where,
                "force_n",
                f"stays at one value through force trial {trial} of {key} while the pressure "
                f"spans {stuck['p'].iloc[0]:.4g} Pa",
                "a measured force, which changes with the pressure (a constant is a placeholder or a stuck sensor)",
            )
    lift = (df["experiment"].astype(str) == "lift").to_numpy()
    if lift.any():
        sub = pd.DataFrame(
            {"k": df["design_key"].to_numpy()[lift], "t": df["trial"].to_numpy()[lift], "f": num["force_n"][lift]}
        )
        spread = sub.groupby(["k", "t"], sort=False)["f"].agg(lambda f: np.nanmax(f) - np.nanmin(f))
        moving = spread[spread > 1e-6]
        if len(moving):
            key, trial = moving.index[0]
            _refuse(
                where,
                "force_n",
                f"changes within lift trial {trial} of {key} (by {moving.iloc[0]:.4g} N)",
                "one force per lift trial (the weight of its mass)",
            )
