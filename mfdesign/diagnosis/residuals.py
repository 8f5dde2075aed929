"""Residuals of a model against measurements: breakdowns, noise floor, worst regions in words.

Residual ``r = F_observed - F_predicted`` [N] at the recorded (height, pressure) of each
usable row (see :func:`mfdesign.diagnosis.expected.usable_rows`); ``r < 0`` means the model
over-predicts the force.

Noise floor: the white measurement noise, estimated from the data without any model of
their smooth part, by the second differences of the residual within each trial and phase
in time order (Rice 1984, "Bandwidth choice for nonparametric regression"; von Neumann's
ratio): for white noise of variance ``s^2`` the second difference
``r[i+1] - 2 r[i] + r[i-1]`` has variance ``6 s^2`` whatever the noise's distribution; a
smooth model error contributes almost nothing. The default is this mean-square estimate:
the rig's noise is not Gaussian (heights are read in whole millimetres, so ``dF/dh`` times
a quantised height gives rare large jumps), and a robust median-based estimate
(``robust=True``, exact for Gaussian noise only) fell 23 % short of the true noise RMSE on
virtual-rig data with nothing hidden (0.228 vs 0.297 N).
"""

from __future__ import annotations

import math
from dataclasses import dataclass, field
from typing import Callable

import numpy as np
import pandas as pd

from mfdesign.data.measurements import Measurements
from mfdesign.design import Membrane
from mfdesign.diagnosis.expected import query_heights, trial_order, usable_rows

__all__ = [
    "SHAPES",
    "Residuals",
    "breakdowns",
    "compute_residuals",
    "noise_floor",
    "residual_shape",
    "shape_words",
    "stall_words",
    "subsample",
    "worst_regions",
]

PRESSURE_BAND_PA = 2000.0
HEIGHT_BAND_MM = 20.0
FORCE_LEVELS_N = (0.0, 5.0, 10.0, 20.0, 40.0, 80.0, math.inf)


@dataclass(frozen=True)
class Residuals:
    """One row per usable measurement: inputs, design attributes, observed, predicted, residual.

    ``frame`` columns: ``design_key, trial, trial_order, experiment, phase, time_s,
    height_mm`` (the query height), ``pressure_pa, observed_n, predicted_n, residual_n,
    n_rings, thickness_mm, contact_mm``. ``dropped``: rows left out and why.
    """

    frame: pd.DataFrame
    noise_floor_n: float
    dropped: dict = field(default_factory=dict)

    @property
    def residual(self) -> np.ndarray:
        return self.frame["residual_n"].to_numpy(float)

    @property
    def rmse_n(self) -> float:
        r = self.residual
        return float(np.sqrt(np.mean(r**2))) if r.size else float("nan")

    @property
    def bias_n(self) -> float:
        r = self.residual
        return float(np.mean(r)) if r.size else float("nan")

    def take(self, positions) -> "Residuals":
        """The residuals of some rows (positions into ``frame``); same noise floor."""
        return Residuals(
            self.frame.iloc[np.asarray(positions)].reset_index(drop=True), self.noise_floor_n, self.dropped
        )

    def summary(self) -> dict:
        return {
            "n": int(len(self.frame)),
            "rmse_n": self.rmse_n,
            "bias_n": self.bias_n,
            "noise_floor_n": self.noise_floor_n,
            "rmse_over_noise": self.rmse_n / self.noise_floor_n if self.noise_floor_n > 0 else None,
            "membranes": int(self.frame["design_key"].nunique()),
            "dropped": self.dropped,
        }


def _design_attrs(keys: np.ndarray) -> dict[str, np.ndarray]:
    uniq, inv = np.unique(keys.astype(str), return_inverse=True)
    ms = [Membrane.from_key(k) for k in uniq]
    return {
        "n_rings": np.array([m.n_rings for m in ms])[inv],
        "thickness_mm": np.array([m.thickness_mm for m in ms], float)[inv],
        "contact_mm": np.array([m.contact_radius_mm for m in ms], float)[inv],
    }


def compute_residuals(
    meas: Measurements,
    predicted: np.ndarray | Callable[[Measurements], np.ndarray],
    outside: np.ndarray | None = None,
) -> Residuals:
    """Residuals of ``predicted`` (an array per row, or ``predict(meas) -> force [N]``).
    ``outside``: rows [N] bool outside the physical model (``ForwardModel.outside_model``:
    a force above ``p pi R^2``); they are dropped and counted (``dropped["outside_physical_model"]``),
    whatever number ``predicted`` holds there."""
    if not isinstance(meas, Measurements):
        raise TypeError(f"compute_residuals needs a Measurements table, got {type(meas).__name__}")
    pred = np.asarray(predicted(meas) if callable(predicted) else predicted, float).ravel()
    if pred.shape != (len(meas),):
        raise ValueError(f"the model returned {pred.shape[0]} predictions for {len(meas)} rows; one per row is needed")
    df = meas._df
    use = usable_rows(meas)
    out = np.zeros(len(meas), bool) if outside is None else np.asarray(outside, bool).ravel()
    if out.shape != (len(meas),):
        raise ValueError(f"outside has {out.shape[0]} rows for {len(meas)}; one per row is needed")
    finite = np.isfinite(pred) & ~out
    keep = use & finite
    attrs = _design_attrs(df["design_key"].to_numpy(object))
    frame = pd.DataFrame(
        {
            "design_key": df["design_key"].to_numpy(object),
            "trial": df["trial"].to_numpy(np.int64),
            "trial_order": trial_order(meas),
            "experiment": df["experiment"].to_numpy(object),
            "phase": df["phase"].to_numpy(object),
            "time_s": df["time_s"].to_numpy(float),
            "height_mm": query_heights(meas),
            "pressure_pa": df["pressure_pa"].to_numpy(float),
            "observed_n": df["force_n"].to_numpy(float),
            "predicted_n": pred,
            **attrs,
        }
    )
    frame["residual_n"] = frame["observed_n"] - frame["predicted_n"]
    frame["row"] = np.arange(len(df))
    frame = frame.loc[keep].reset_index(drop=True)
    dropped = {
        "lift_plate_resting_or_at_top": int((~use).sum()),
        "model_has_no_value": int((use & ~finite & ~out).sum()),
    }
    if outside is not None:
        dropped["outside_physical_model"] = int((use & out).sum())
    return Residuals(frame=frame, noise_floor_n=noise_floor(frame), dropped=dropped)


def noise_floor(frame: pd.DataFrame, robust: bool = False) -> float:
    """White-noise sd [N] of the residuals from second differences within trials (module doc).

    Triples straddling a change of trial or phase (the inflate/deflate turn, a kink) are
    left out. ``robust``: median absolute second difference / (0.6745 sqrt 6) instead of
    the root mean square / sqrt 6 (Gaussian noise only).
    """
    if len(frame) < 3:
        return float("nan")
    t = frame["time_s"].to_numpy(float)
    label = frame["design_key"].astype(str) + "|" + frame["trial"].astype(str)
    if "phase" in frame:
        label = label + "|" + frame["phase"].astype(str)
    tid = pd.factorize(label)[0]
    order = np.lexsort((t, tid)) if np.all(np.isfinite(t)) else np.argsort(tid, kind="stable")
    r = frame["residual_n"].to_numpy(float)[order]
    g = tid[order]
    same = (g[2:] == g[1:-1]) & (g[1:-1] == g[:-2])
    d = (r[2:] - 2.0 * r[1:-1] + r[:-2])[same]
    if d.size == 0:
        return float("nan")
    if robust:
        return float(np.median(np.abs(d)) / (0.6744897501960817 * math.sqrt(6.0)))
    return float(np.sqrt(np.mean(d**2) / 6.0))


def subsample(frame, max_rows: int, seed: int = 0) -> np.ndarray:
    """Positions into ``frame`` (residual rows): at most ``max_rows``, evenly within each trial."""
    n = len(frame)
    if n <= max_rows:
        return np.arange(n)
    rng = np.random.default_rng(seed)
    frac = max_rows / n
    keep = []
    for _, idx in frame.groupby(["design_key", "trial"], sort=False).indices.items():
        k = max(1, int(round(frac * len(idx))))
        pos = (rng.uniform() + np.arange(k)) * len(idx) / k
        keep.append(idx[np.minimum(pos.astype(int), len(idx) - 1)])
    keep = np.unique(np.concatenate(keep))
    if len(keep) > max_rows:  # rounding up per trial: trim to exactly max_rows
        keep = np.sort(rng.choice(keep, max_rows, replace=False))
    return keep


def _stats(r: np.ndarray) -> dict:
    return {
        "n": int(r.size),
        "mean_n": float(np.mean(r)),
        "rms_n": float(np.sqrt(np.mean(r**2))),
        "abs_max_n": float(np.max(np.abs(r))),
    }


def _binned(values: np.ndarray, r: np.ndarray, edges, fmt: Callable[[float, float], str]) -> list[dict]:
    edges = np.asarray(edges, float)
    idx = np.clip(np.searchsorted(edges, values, side="right") - 1, 0, len(edges) - 2)
    out = []
    for b in range(len(edges) - 1):
        m = idx == b
        if m.any():
            out.append(
                {
                    "bin": fmt(edges[b], edges[b + 1]),
                    "low": float(edges[b]),
                    "high": float(edges[b + 1]),
                    **_stats(r[m]),
                }
            )
    return out


def _categorical(values: np.ndarray, r: np.ndarray, fmt=str) -> list[dict]:
    out = []
    for v in pd.unique(values):
        m = values == v
        out.append({"bin": fmt(v), **_stats(r[m])})
    return out


def _edges(lo: float, hi: float, step: float) -> np.ndarray:
    return np.arange(step * math.floor(lo / step), step * (math.floor(hi / step) + 1) + step / 2, step)


def breakdowns(res: Residuals) -> dict[str, list[dict]]:
    """Residual statistics (n, mean, RMS, max |r|) per height, pressure, force level, ring
    count, thickness, contact radius, trial order, phase, experiment and membrane."""
    f, r = res.frame, res.residual
    if not len(f):
        return {}
    h, p = f["height_mm"].to_numpy(float), f["pressure_pa"].to_numpy(float)
    ko = f["trial_order"].to_numpy(int)
    order_edges = np.unique(np.concatenate([[0, 1, 3], np.arange(6, ko.max() + 7, 6)])).astype(float)
    return {
        "height": _binned(h, r, _edges(h.min(), h.max(), 10.0), lambda a, b: f"{a:g}-{b:g} mm"),
        "pressure": _binned(p, r, _edges(p.min(), p.max(), 1000.0), lambda a, b: f"{a / 1e3:g}-{b / 1e3:g} kPa"),
        "force_level": _binned(
            f["observed_n"].to_numpy(float),
            r,
            (-math.inf, *FORCE_LEVELS_N[1:]),
            lambda a, b: f"< {b:g} N" if a == -math.inf else (f">= {a:g} N" if b == math.inf else f"{a:g}-{b:g} N"),
        ),
        "ring_count": _categorical(f["n_rings"].to_numpy(int), r, lambda v: f"{v} ring(s)"),
        "thickness": _categorical(f["thickness_mm"].to_numpy(float), r, lambda v: f"{v:g} mm"),
        "contact_radius": _categorical(f["contact_mm"].to_numpy(float), r, lambda v: f"{v:g} mm"),
        "trial_order": _binned(
            ko.astype(float), r, order_edges, lambda a, b: f"trial {a:g}" if b - a == 1 else f"trials {a:g}-{b - 1:g}"
        ),
        "phase": _categorical(f["phase"].to_numpy(object), r),
        "experiment": _categorical(f["experiment"].to_numpy(object), r),
        "membrane": _categorical(f["design_key"].to_numpy(object), r),
    }


def _group_label(n_rings: int, t: float) -> str:
    rings = "ringless" if n_rings == 0 else f"{n_rings}-ring"
    return f"{rings} {t:g} mm membranes"


def worst_regions(res: Residuals, top: int = 3, min_rows: int = 30) -> list[dict]:
    """The regions where the model is most wrong, as numbers and as a sentence.

    Cells: membrane group (ring count, thickness) x pressure band (2 kPa) x height band
    (20 mm). The worst cells by ``|mean residual|`` are grown along pressure over the
    neighbouring bands with the same sign and at least half the magnitude, so a sentence
    can say "above 6 kPa"; each reported region is disjoint from the earlier ones.
    """
    f = res.frame
    if len(f) == 0:
        return []
    n_min = max(min_rows, int(0.002 * len(f)))
    pb = np.floor(f["pressure_pa"].to_numpy(float) / PRESSURE_BAND_PA).astype(int)
    hb = np.floor(f["height_mm"].to_numpy(float) / HEIGHT_BAND_MM).astype(int)
    g = f["n_rings"].astype(str) + "|" + f["thickness_mm"].map("{:g}".format)
    cells = pd.DataFrame({"g": g, "pb": pb, "hb": hb, "r": f["residual_n"].to_numpy(float)})
    stats = cells.groupby(["g", "pb", "hb"])["r"].agg(["mean", "count"]).reset_index()
    stats = stats[stats["count"] >= n_min].copy()
    stats["abs"] = stats["mean"].abs()
    stats = stats.sort_values("abs", ascending=False)
    used: set = set()
    out = []
    p_top = int(pb.max())
    for _, row in stats.iterrows():
        if len(out) >= top:
            break
        if (row.g, row.pb, row.hb) in used:
            continue
        same = stats[(stats["g"] == row.g) & (stats["hb"] == row.hb)].set_index("pb")
        lo = hi = int(row.pb)
        ok = lambda b, same=same, row=row: (
            b in same.index
            and (row.g, b, row.hb) not in used
            and np.sign(same.loc[b, "mean"]) == np.sign(row["mean"])
            and same.loc[b, "abs"] >= 0.5 * row["abs"]
        )
        while ok(lo - 1):
            lo -= 1
        while ok(hi + 1):
            hi += 1
        for b in range(lo, hi + 1):
            used.add((row.g, b, row.hb))
        m = (g.to_numpy() == row.g) & (hb == row.hb) & (pb >= lo) & (pb <= hi)
        r = f["residual_n"].to_numpy(float)[m]
        n_rings, t = row.g.split("|")
        p_lo, p_hi = lo * PRESSURE_BAND_PA / 1e3, (hi + 1) * PRESSURE_BAND_PA / 1e3
        where_p = (
            f"above {p_lo:g} kPa"
            if hi >= p_top and lo > 0
            else (f"below {p_hi:g} kPa" if lo <= 0 else f"at {p_lo:g}-{p_hi:g} kPa")
        )
        h_lo, h_hi = row.hb * HEIGHT_BAND_MM, (row.hb + 1) * HEIGHT_BAND_MM
        mean = float(np.mean(r))
        verb = "over-predicts" if mean < 0 else "under-predicts"
        words = (
            f"{where_p} and {h_lo:g}-{h_hi:g} mm on {_group_label(int(n_rings), float(t))} the model "
            f"{verb} force by {abs(mean):.2f} N (mean of {r.size} samples, RMS {np.sqrt(np.mean(r**2)):.2f} N)"
        )
        out.append(
            {
                "words": words,
                "n_rings": int(n_rings),
                "thickness_mm": float(t),
                "pressure_kpa": [p_lo, p_hi],
                "height_mm": [float(h_lo), float(h_hi)],
                "mean_n": mean,
                "rms_n": float(np.sqrt(np.mean(r**2))),
                "n": int(r.size),
            }
        )
    return out


def trend_words(res: Residuals) -> list[str]:
    """Sentences on how the error grows along each breakdown (largest RMS bin vs smallest)."""
    out = []
    for name, bins in breakdowns(res).items():
        if name == "membrane" or len(bins) < 2:
            continue
        big = max(bins, key=lambda b: b["rms_n"])
        small = min(bins, key=lambda b: b["rms_n"])
        if big["rms_n"] > 2.0 * max(small["rms_n"], res.noise_floor_n if res.noise_floor_n > 0 else 0.0):
            out.append(
                f"by {name.replace('_', ' ')}: RMS {big['rms_n']:.2f} N at {big['bin']} "
                f"(mean {big['mean_n']:+.2f} N) vs {small['rms_n']:.2f} N at {small['bin']}"
            )
    return out


# The shapes a missing effect leaves in the residual, from the coarsest to the finest: a
# constant (a sensor or load offset), one value per ring count (ring physics), per
# membrane (fabrication: thickness, bonding), per lift (the plate, the mass stack, a
# trial's friction), then trends within a lift with height and with pressure.
SHAPES = ("constant", "per ring count", "per membrane", "per lift", "grows with height", "grows with pressure")


def residual_shape(res: Residuals) -> list[dict]:
    """Sequential decomposition of the residual's mean square into :data:`SHAPES`.

    Each step explains what the steps before it left: the overall mean, then the means by
    ring count, by membrane, by trial ("per lift"), then per-trial linear trends in height
    and in pressure (one pooled slope each, on what the trial means leave). Returns
    ``[{"shape", "share", "rms_n"}]`` with ``share`` the fraction of the residual's mean
    square and ``rms_n`` its RMS [N], and a last entry ``"unstructured"`` for the rest.
    """
    f = res.frame
    r = res.residual.astype(float)
    total = float(np.mean(r**2)) if r.size else 0.0
    if total <= 0:
        return []
    out = []
    left = r.copy()

    def take(name: str, fitted: np.ndarray):
        nonlocal left
        out.append(
            {"shape": name, "share": float(np.mean(fitted**2) / total), "rms_n": float(np.sqrt(np.mean(fitted**2)))}
        )
        left = left - fitted

    take("constant", np.full_like(r, left.mean()))
    for name, keys in (
        ("per ring count", [f["n_rings"]]),
        ("per membrane", [f["design_key"]]),
        ("per lift", [f["design_key"], f["trial"]]),
    ):
        take(name, pd.Series(left).groupby([k.to_numpy() for k in keys]).transform("mean").to_numpy())
    for name, col in (("grows with height", "height_mm"), ("grows with pressure", "pressure_pa")):
        x = f[col].to_numpy(float)
        x = x - pd.Series(x).groupby([f["design_key"].to_numpy(), f["trial"].to_numpy()]).transform("mean").to_numpy()
        slope = float(np.dot(x, left) / np.dot(x, x)) if np.dot(x, x) > 0 else 0.0
        take(name, slope * x)
    out.append(
        {"shape": "unstructured", "share": float(np.mean(left**2) / total), "rms_n": float(np.sqrt(np.mean(left**2)))}
    )
    return out


def shape_words(res: Residuals, min_share: float = 0.1) -> str:
    """The residual's shape in words: the parts of :func:`residual_shape` holding at least
    ``min_share`` of its mean square, largest first."""
    parts = sorted((s for s in residual_shape(res) if s["share"] >= min_share), key=lambda s: -s["share"])
    if not parts:
        return "no dominant shape (no part holds 10 % of the mean square)"
    return ", ".join(f"{s['shape']} {100 * s['share']:.0f} % (RMS {s['rms_n']:.2f} N)" for s in parts)


def _spans(heights) -> str:
    """Whole-mm heights as ranges: [28, 43, 44, 45, 47] -> '28, 43-47' (gaps up to 2 mm joined)."""
    hs = sorted({int(round(h)) for h in heights})
    out, lo = [], hs[0]
    for a, b in zip(hs, hs[1:] + [None]):
        if b is None or b - a > 2:
            out.append(f"{lo}" if lo == a else f"{lo}-{a}")
            lo = b
    return ", ".join(out)


def stall_words(stalls: pd.DataFrame) -> list[str]:
    """One line per membrane whose lift plates stall (:func:`mfdesign.data.lifts.stalls`):
    where, at which masses, and what the other trials say. A stall repeated by another trial
    of the same mass in mid-travel is the membrane's own mechanics (a smooth quasi-static model
    cannot follow it); one at a trial's top is a hold at the end of travel; one its replicate
    does not repeat is an event of the rig."""
    lines = []
    for key, g in stalls.groupby("design_key", sort=False):
        parts = []
        for label, sel in (
            (
                "mid-travel, repeated by another trial of the same mass (the membrane's own steps)",
                ~g["at_top"] & g["repeats"],
            ),
            ("at the trials' tops (holds at the end of travel)", g["at_top"]),
            ("mid-travel, not repeated by the other trial (an event of the rig)", ~g["at_top"] & ~g["repeats"]),
        ):
            s = g[sel]
            if len(s):
                masses = "; ".join(f"{f:.1f} N: {_spans(m['height_mm'])} mm" for f, m in s.groupby("force_n"))
                parts.append(f"{label} at {masses}")
        lines.append(f"{key.replace(', nan', '')}: the plate stalls " + "; and ".join(parts))
    return lines
