"""A lab's own CSV layout mapped onto the Measurements columns, with a unit per column.

A rig logs what its author chose: ``design,height_mm,pressure_kpa,force_n``. A column map
says which of its columns is which Measurements column and in what unit::

    design_key=design,pressure_pa=pressure_kpa:kPa

(``TARGET=SOURCE[:UNIT]``, comma separated; a target not named keeps its own name). Values
are converted to the schema's units (mm, Pa, N, s) before the plausibility checks
(:mod:`mfdesign.data.plausible`) look at them, so a unit mistaken here is still refused.

Only ``design_key``, ``height_mm``, ``pressure_pa`` and ``force_n`` are required. The others
take these documented defaults (docs/data.md) when the table has no such column:

============== =====================================================================
experiment     ``"force"`` (the plate held at a set height)
phase          ``"inflate"``
height_set_mm  the row's ``height_mm``
trial          one per membrane and set height, numbered in order of appearance (as the
               SPA_Design characterisation import does)
time_s         NaN (no time stamps)
weight         1.0
source         ``"file"``
============== =====================================================================
"""

from __future__ import annotations

import re
from dataclasses import dataclass
from typing import Mapping, Sequence

import numpy as np
import pandas as pd

from mfdesign.data.measurements import COLUMNS
from mfdesign.errors import InputError

__all__ = ["ColumnMap", "REQUIRED", "UNITS", "apply_column_map", "suggest_map"]

REQUIRED = ("design_key", "height_mm", "pressure_pa", "force_n")

_G = 9.80665  # standard gravity [m/s^2]: a gram-force is 9.80665 mN
# target -> {unit: factor to the schema's unit}; the first unit is the schema's own
UNITS: dict[str, dict[str, float]] = {
    "height_mm": {"mm": 1.0, "cm": 10.0, "m": 1000.0, "in": 25.4},
    "height_set_mm": {"mm": 1.0, "cm": 10.0, "m": 1000.0, "in": 25.4},
    "pressure_pa": {"Pa": 1.0, "kPa": 1e3, "mbar": 100.0, "hPa": 100.0, "bar": 1e5, "psi": 6894.757293168},
    "force_n": {
        "N": 1.0,
        "mN": 1e-3,
        "kN": 1e3,
        "g": _G * 1e-3,
        "gf": _G * 1e-3,
        "kg": _G,
        "kgf": _G,
        "lbf": 4.4482216,
    },
    "time_s": {"s": 1.0, "ms": 1e-3, "min": 60.0},
}
_DEFAULT_TEXT = {"experiment": "force", "phase": "inflate", "source": "file"}
_NAME = re.compile(r"^[A-Za-z_][A-Za-z0-9_ .\-]{0,63}$")


@dataclass(frozen=True)
class ColumnMap:
    """Measurements column -> (the table's column, unit). Build with :meth:`parse`."""

    entries: tuple[tuple[str, str, str], ...] = ()  # (target, source, unit)

    @classmethod
    def parse(cls, spec: str | Sequence[str] | Mapping[str, str] | None) -> "ColumnMap":
        """From ``"TARGET=SOURCE[:UNIT],..."`` (or a list of such items, or a mapping
        ``{target: "SOURCE[:UNIT]"}``); every mistake is one line naming what is allowed."""
        if spec is None:
            return cls()
        if isinstance(spec, Mapping):
            items = [f"{k}={v}" for k, v in spec.items()]
        else:
            items = [spec] if isinstance(spec, str) else list(spec)
        items = [part.strip() for item in items for part in str(item).split(",") if part.strip()]
        entries, seen = [], set()
        for item in items:
            target, eq, rest = item.partition("=")
            target, rest = target.strip(), rest.strip()
            source, _, unit = rest.partition(":")
            source, unit = source.strip(), unit.strip()
            if not eq or not source:
                raise InputError(f"column map item {item!r}; allowed: TARGET=SOURCE or TARGET=SOURCE:UNIT")
            if target not in COLUMNS:
                raise InputError(f"column map target {target!r} is not a Measurements column; allowed: {list(COLUMNS)}")
            if target in seen:
                raise InputError(f"column map names {target!r} twice; allowed: each target once")
            if not _NAME.match(source):
                raise InputError(
                    f"column map source {source[:40]!r}; allowed: a column name of letters, digits, '_', ' ', '.', '-'"
                )
            units = UNITS.get(target, {})
            if unit and not units:
                raise InputError(f"column {target!r} takes no unit (got {unit!r}); allowed: {target}={source}")
            if unit and unit not in units:
                raise InputError(f"unit {unit!r} for {target!r} is not known; allowed: {', '.join(units)}")
            seen.add(target)
            entries.append((target, source, unit or (next(iter(units)) if units else "")))
        return cls(tuple(entries))

    def __bool__(self) -> bool:
        return bool(self.entries)

    def __str__(self) -> str:
        return ",".join(
            f"{t}={s}" + (f":{u}" if u and u != next(iter(UNITS.get(t, {u: 1}))) else "") for t, s, u in self.entries
        )


def suggest_map(columns: Sequence[str]) -> str:
    """A column map for the required columns a table lacks, guessed from its column names
    (``pressure_kpa`` -> ``pressure_pa=pressure_kpa:kPa``, ``design`` -> ``design_key=design``);
    empty when nothing can be guessed."""
    names = [str(c) for c in columns]
    lower = {n.lower(): n for n in names}
    out = []
    for target in REQUIRED:
        if target in names:
            continue
        stem = target.rsplit("_", 1)[0]  # design, height, pressure, force
        hit = next((n for low, n in lower.items() if low == stem or low.startswith(stem + "_")), None)
        if hit is None:
            continue
        unit = ""
        suffix = hit.lower()[len(stem) + 1 :] if hit.lower() != stem else ""
        for u in UNITS.get(target, {}):
            if suffix == u.lower():
                unit = u
        out.append(f"{target}={hit}" + (f":{unit}" if unit and unit != next(iter(UNITS[target])) else ""))
    return ",".join(out)


def apply_column_map(df: pd.DataFrame, cmap: ColumnMap, where: str) -> pd.DataFrame:
    """``df`` with the Measurements columns: mapped, converted to mm / Pa / N / s, and the
    optional columns filled with their defaults (module doc). Raises :class:`InputError`
    naming what to add when a required column is still missing."""
    out = pd.DataFrame(index=df.index)
    mapped = {t for t, _, _ in cmap.entries}
    for target, source, unit in cmap.entries:
        if source not in df.columns:
            raise InputError(
                f"{where}: column map {target}={source}, but the table has no column {source!r}; "
                f"allowed: one of {[str(c) for c in df.columns][:12]}"
            )
        values = df[source]
        factor = UNITS.get(target, {}).get(unit, 1.0)
        if factor != 1.0:
            values = pd.to_numeric(values, errors="coerce") * factor
        out[target] = values
    for c in COLUMNS:
        if c not in mapped and c in df.columns:
            out[c] = df[c]
    missing = [c for c in REQUIRED if c not in out.columns]
    if missing:
        hint = suggest_map(list(df.columns))
        add = (
            f"add a column map, e.g. --columns {hint}"
            if hint
            else "add a column map --columns TARGET=SOURCE[:UNIT],..."
        )
        raise InputError(
            f"{where}: missing column(s) {missing} (the table has {[str(c) for c in df.columns][:12]}); "
            f"{add} (units: docs/data.md)"
        )
    return _fill_defaults(out)


def _fill_defaults(df: pd.DataFrame) -> pd.DataFrame:
    out = df.copy()
    for c, v in _DEFAULT_TEXT.items():
        if c not in out.columns:
            out[c] = v
    if "height_set_mm" not in out.columns:
        out["height_set_mm"] = out["height_mm"]
    if "time_s" not in out.columns:
        out["time_s"] = np.nan
    if "weight" not in out.columns:
        out["weight"] = 1.0
    if "trial" not in out.columns:
        # one trial per (membrane, set height), in order of appearance
        h = pd.to_numeric(out["height_set_mm"], errors="coerce").round(6)
        codes, _ = pd.factorize(pd.MultiIndex.from_arrays([out["design_key"].astype(str), h]), sort=False)
        key_codes, _ = pd.factorize(out["design_key"].astype(str), sort=False)
        frame = pd.DataFrame({"k": key_codes, "c": codes})
        first = frame.drop_duplicates("c")
        rank = first.groupby("k").cumcount()
        out["trial"] = frame["c"].map(dict(zip(first["c"], rank))).to_numpy(dtype=np.int64)
    return out[list(COLUMNS)]
