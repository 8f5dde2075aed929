"""The Measurements table: one row per sample, for real, virtual and simulated data alike.

Every module downstream (models, calibration, diagnosis) reads this one table, so it is
checked once, on construction, and then cannot change: a ``Measurements`` is immutable
(``.df`` hands out a copy). Units are in the column names: mm, Pa, N, s.

Columns (all required, in this order):

============== ======= =====================================================================
design_key     str     canonical ``Membrane.key()`` ``"[t, c, r1, w1, r2, w2]"``
trial          int64   trial id >= 0; ids are per membrane, one trial = one experiment+source
experiment     str     ``"force"`` (plate held at a set height) | ``"lift"`` (mass lifted)
phase          str     ``"inflate"`` | ``"deflate"``
time_s         float64 time since trial start [s], >= 0, or NaN (files without time)
height_set_mm  float64 plate set-point [mm], in [-5, 200] or NaN (lift trials)
height_mm      float64 plate height [mm], finite, in [-5, 200]
pressure_pa    float64 gauge pressure [Pa], finite, in [-20e3, 200e3]
force_n        float64 force on the plate [N], finite, in [-50, 1000]
weight         float64 sample weight, finite, >= 0
source         str     ``"rig"`` | ``"virtual"`` | ``"simulated"`` | ``"file"``
============== ======= =====================================================================
"""

from __future__ import annotations

import math
import os
from pathlib import Path
from typing import Iterable, Sequence

import numpy as np
import pandas as pd

from mfdesign.design import DesignError, Membrane
from mfdesign.errors import InputError

__all__ = [
    "COLUMNS",
    "EXPERIMENTS",
    "PHASES",
    "SOURCES",
    "MeasurementError",
    "Measurements",
]

EXPERIMENTS = ("force", "lift")
PHASES = ("inflate", "deflate")
SOURCES = ("rig", "virtual", "simulated", "file")

# name -> (kind, low, high, nan_allowed); kind "str" columns carry their allowed set instead.
_FLOAT_RULES: dict[str, tuple[float, float, bool]] = {
    "time_s": (0.0, math.inf, True),
    "height_set_mm": (-5.0, 200.0, True),
    "height_mm": (-5.0, 200.0, False),
    "pressure_pa": (-20e3, 200e3, False),
    "force_n": (-50.0, 1000.0, False),
    "weight": (0.0, math.inf, False),
}
_CATEGORIES: dict[str, tuple[str, ...]] = {
    "experiment": EXPERIMENTS,
    "phase": PHASES,
    "source": SOURCES,
}
COLUMNS: tuple[str, ...] = (
    "design_key",
    "trial",
    "experiment",
    "phase",
    "time_s",
    "height_set_mm",
    "height_mm",
    "pressure_pa",
    "force_n",
    "weight",
    "source",
)


FORMAT_KEY = b"mfdesign.measurements.format_version"  # Parquet key-value metadata
FORMAT_VERSION = "1"
SUPPORTED_VERSIONS = (FORMAT_VERSION,)


class MeasurementError(InputError):
    """A Measurements table that breaks the schema; the message names column, row and rule."""


class _PathMissing(FileNotFoundError, InputError):
    """A file or folder that is not there: bad input (exit 2), still a FileNotFoundError."""


# -- validation helpers -------------------------------------------------------------------
def _first_bad(column: str, values: np.ndarray, bad: np.ndarray, rule: str) -> None:
    if bad.any():
        i = int(np.flatnonzero(bad)[0])
        value = values[i].item() if isinstance(values[i], np.generic) else values[i]
        raise MeasurementError(
            f"column {column!r}: row {i} has value {value!r}; allowed: {rule} "
            f"({int(bad.sum())} offending row(s) in all)"
        )


def _check_strings(column: str, series: pd.Series) -> np.ndarray:
    values = series.to_numpy(dtype=object)
    bad = np.fromiter((not isinstance(v, str) for v in values), dtype=bool, count=len(values))
    _first_bad(column, values, bad, "a string")
    return values


def _check_float(column: str, series: pd.Series) -> np.ndarray:
    low, high, nan_ok = _FLOAT_RULES[column]
    try:
        values = pd.to_numeric(series, errors="raise").to_numpy(dtype=np.float64, na_value=np.nan)
    except (TypeError, ValueError):
        raw = series.to_numpy(dtype=object)
        for i, v in enumerate(raw):
            try:  # what pandas cannot parse (float() takes '1_000' and full-width digits)
                pd.to_numeric(pd.Series([v], dtype=object), errors="raise")
            except (TypeError, ValueError):
                raise MeasurementError(
                    f"column {column!r}: row {i} has value {v!r}; allowed: a number (ASCII digits, no '_')"
                ) from None
        raise MeasurementError(f"column {column!r}: not a column of numbers; allowed: numbers") from None
    nan = np.isnan(values)
    rng = f"[{low:g}, {high:g}]" + (" or NaN" if nan_ok else ", finite (no NaN/inf)")
    if not nan_ok:
        _first_bad(column, values, nan, rng)
    _first_bad(column, values, ~nan & ~((values >= low) & (values <= high)), rng)
    return values


def _check_trial(series: pd.Series) -> np.ndarray:
    raw = series.to_numpy(dtype=object)
    if pd.api.types.is_integer_dtype(series.dtype):
        values = series.to_numpy(dtype=np.int64)
    else:
        for i, v in enumerate(raw):
            ok = isinstance(v, (int, np.integer)) and not isinstance(v, bool)
            ok = ok or (isinstance(v, (float, np.floating)) and math.isfinite(v) and float(v).is_integer())
            if not ok:
                raise MeasurementError(f"column 'trial': row {i} has value {v!r}; allowed: an integer >= 0")
        values = np.asarray([int(v) for v in raw], dtype=np.int64)
    _first_bad("trial", values, values < 0, "an integer >= 0")
    return values


def _canonical_keys(series: pd.Series) -> np.ndarray:
    values = _check_strings("design_key", series)
    codes, uniques = pd.factorize(values, sort=False)
    canon = []
    for j, key in enumerate(uniques):
        try:
            canon.append(Membrane.from_key(key).key())
        except DesignError as err:
            row = int(np.flatnonzero(codes == j)[0])
            raise MeasurementError(
                f"column 'design_key': row {row} has value {key!r}, not a valid design: {err}"
            ) from None
    return np.asarray(canon, dtype=object)[codes]


def _check_trials_consistent(df: pd.DataFrame) -> None:
    """A trial id names one trial of one membrane: one experiment, one source."""
    for column in ("experiment", "source"):
        n = df.groupby(["design_key", "trial"], sort=False)[column].nunique()
        mixed = n[n > 1]
        if len(mixed):
            key, trial = mixed.index[0]
            rows = np.flatnonzero((df["design_key"] == key).to_numpy() & (df["trial"] == trial).to_numpy())
            found = sorted(df[column].iloc[rows].unique())
            raise MeasurementError(
                f"column 'trial': trial {trial} of membrane {key} (first row {int(rows[0])}) "
                f"mixes {column} values {found}; allowed: one {column} per trial (trial ids "
                "are unique within a membrane; concatenating tables with clashing ids needs "
                "Measurements.concat(..., renumber_trials=True))"
            )


def _validate(df: pd.DataFrame, extra_ok: bool) -> pd.DataFrame:
    if not isinstance(df, pd.DataFrame):
        raise MeasurementError(f"Measurements needs a pandas DataFrame, got {type(df).__name__}")
    missing = [c for c in COLUMNS if c not in df.columns]
    if missing:
        raise MeasurementError(f"missing column(s) {missing}; required columns: {list(COLUMNS)}")
    extra = [c for c in df.columns if c not in COLUMNS]
    if extra and not extra_ok:
        raise MeasurementError(
            f"unexpected column(s) {extra}; allowed columns: {list(COLUMNS)} "
            "(pass extra_ok=True to keep additional columns)"
        )
    if df.columns.duplicated().any():
        raise MeasurementError(f"duplicate column names: {sorted(set(df.columns[df.columns.duplicated()]))}")
    df = df.reset_index(drop=True)
    out = {"design_key": _canonical_keys(df["design_key"]), "trial": _check_trial(df["trial"])}
    for column, allowed in _CATEGORIES.items():
        values = _check_strings(column, df[column])
        bad = ~pd.Series(values).isin(allowed).to_numpy()
        _first_bad(column, values, bad, f"one of {list(allowed)}")
        out[column] = values
    for column in _FLOAT_RULES:
        out[column] = _check_float(column, df[column])
    clean = pd.DataFrame({c: out[c] for c in COLUMNS})
    for column in ("design_key", *_CATEGORIES):
        clean[column] = clean[column].astype(str)
    for column in extra:
        clean[column] = df[column].to_numpy()
    _check_trials_consistent(clean)
    return clean


class Measurements:
    """An immutable, validated table of samples (see the module docstring for the schema).

    ``Measurements(df, extra_ok=False)`` checks every column and raises
    :class:`MeasurementError` naming the column, the first offending row and the rule.
    Design keys are re-canonicalised (``Membrane.from_key(k).key()``) so that equal designs
    have equal keys whatever their spelling.

    **Arguments:**

    - `df`: a pandas DataFrame with the columns of the module docstring (mm, Pa, N, s).
    - `extra_ok`: keep columns beyond those (default: refuse them).

    Read one with :func:`mfdesign.load` (``"bundled"``, a file, a rig job folder) or
    :meth:`from_parquet`; ``df`` hands out a copy of the table.
    """

    __slots__ = ("_df",)

    def __init__(self, df: pd.DataFrame, extra_ok: bool = False):
        object.__setattr__(self, "_df", _validate(df, extra_ok))

    def __setattr__(self, name, value):
        raise AttributeError("Measurements is immutable; build a new one from m.df")

    # pickling (multiprocessing pools) and copy.copy go through these, not __setattr__
    def __getstate__(self) -> pd.DataFrame:
        return self._df

    def __setstate__(self, df: pd.DataFrame) -> None:
        object.__setattr__(self, "_df", df)

    # -- basic access --------------------------------------------------------------------
    @property
    def df(self) -> pd.DataFrame:
        """A copy of the table (changing it does not change this object)."""
        return self._df.copy()

    def __len__(self) -> int:
        return len(self._df)

    def __repr__(self) -> str:
        return f"Measurements({len(self)} rows, {len(self.design_keys)} membranes)"

    @property
    def design_keys(self) -> list[str]:
        """Unique design keys in order of first appearance."""
        return list(pd.unique(self._df["design_key"].to_numpy(dtype=object)))

    def designs(self) -> list[Membrane]:
        """The membranes, in the order of :attr:`design_keys`."""
        return [Membrane.from_key(k) for k in self.design_keys]

    def groups(self) -> np.ndarray:
        """Membrane index per row (int64), indexing :attr:`design_keys`."""
        codes, _ = pd.factorize(self._df["design_key"].to_numpy(dtype=object), sort=False)
        return codes.astype(np.int64)

    def design_array(self) -> np.ndarray:
        """``[n, 6]`` float64 ``[t, c, r1, w1, r2, w2]`` per row (mm), NaN for absent rings."""
        table = np.stack([d.to_array() for d in self.designs()]) if len(self) else np.empty((0, 6))
        return table[self.groups()] if len(self) else table

    def arrays(self) -> dict[str, np.ndarray]:
        """Float64 arrays ``height_mm, pressure_pa, force_n, weight`` and ``design`` ``[n, 6]``."""
        out = {
            c: self._df[c].to_numpy(dtype=np.float64, copy=True)
            for c in ("height_mm", "pressure_pa", "force_n", "weight")
        }
        out["design"] = self.design_array()
        return out

    # -- selection -----------------------------------------------------------------------
    def subset(self, keys: Iterable[str | Membrane]) -> "Measurements":
        """Rows of the given membranes (keys or Membrane objects), in the original order."""
        wanted = []
        for k in keys:
            try:
                wanted.append(k.key() if isinstance(k, Membrane) else Membrane.from_key(k).key())
            except DesignError as err:
                raise MeasurementError(f"subset: {k!r} is not a valid design key: {err}") from None
        unknown = sorted(set(wanted) - set(self.design_keys))
        if unknown:
            raise MeasurementError(f"subset: membrane(s) {unknown} not in this table")
        mask = self._df["design_key"].isin(wanted).to_numpy()
        return self._from_clean(self._df.loc[mask].reset_index(drop=True))

    @classmethod
    def _from_clean(cls, df: pd.DataFrame) -> "Measurements":
        """Wrap a table derived from an already validated one (no re-validation)."""
        obj = cls.__new__(cls)
        object.__setattr__(obj, "_df", df)
        return obj

    @classmethod
    def concat(
        cls,
        parts: Sequence["Measurements"],
        extra_ok: bool = False,
        renumber_trials: bool = False,
    ) -> "Measurements":
        """Stack tables (validated again).

        ``renumber_trials=True`` shifts the trial ids of each later part, per membrane, past
        those already used, so that e.g. real and virtual trials of one membrane can share
        a table; otherwise clashing ids are reported as an error.
        """
        parts = list(parts)
        if not parts:
            raise MeasurementError("concat needs at least one Measurements")
        for p in parts:
            if not isinstance(p, Measurements):
                raise MeasurementError(f"concat takes Measurements objects, got {type(p).__name__}")
        frames = [p._df for p in parts]
        if renumber_trials:
            next_id: dict[str, int] = {}
            shifted = []
            for frame in frames:
                frame = frame.copy()
                offsets = frame["design_key"].map(lambda k: next_id.get(k, 0)).to_numpy(dtype=np.int64)
                frame["trial"] = frame["trial"].to_numpy() + offsets
                for key, top in frame.groupby("design_key", sort=False)["trial"].max().items():
                    next_id[key] = int(top) + 1
                shifted.append(frame)
            frames = shifted
        return cls(pd.concat(frames, ignore_index=True), extra_ok=extra_ok)

    # -- cross-validation ----------------------------------------------------------------
    def kfold(self, k: int, seed: int) -> list[tuple["Measurements", "Measurements"]]:
        """Leave-membranes-out folds: ``[(train, test), ...]``.

        Membranes are shuffled with ``numpy.random.default_rng(seed)`` and dealt into
        ``k`` folds whose sizes differ by at most one; each membrane is in exactly one
        test fold. Why by membrane: the model must predict designs it has not seen.
        """
        keys = self.design_keys
        if isinstance(k, bool) or not isinstance(k, (int, np.integer)):
            raise MeasurementError(f"kfold: k must be an integer, got {k!r}")
        if k < 2 or k > len(keys):
            raise MeasurementError(
                f"kfold: k = {k} folds but {len(keys)} membrane(s); allowed: 2 <= k <= "
                f"number of membranes ({len(keys)})"
            )
        order = np.random.default_rng(seed).permutation(len(keys))
        return self._folds([[keys[i] for i in fold] for fold in np.array_split(order, k)])

    def leave_one_out(self) -> list[tuple["Measurements", "Measurements"]]:
        """One fold per membrane, in the order of :attr:`design_keys` (deterministic)."""
        keys = self.design_keys
        if len(keys) < 2:
            raise MeasurementError(f"leave_one_out needs at least 2 membranes, this table has {len(keys)}")
        return self._folds([[key] for key in keys])

    def _folds(self, test_sets: list[list[str]]) -> list[tuple["Measurements", "Measurements"]]:
        key_col = self._df["design_key"]
        out = []
        for test_keys in test_sets:
            mask = key_col.isin(test_keys).to_numpy()
            out.append(
                (
                    self._from_clean(self._df.loc[~mask].reset_index(drop=True)),
                    self._from_clean(self._df.loc[mask].reset_index(drop=True)),
                )
            )
        return out

    # -- storage -------------------------------------------------------------------------
    # Why atomic: a crash half-way through a write must never leave a truncated file where
    # a good one (or none) was (mfdesign.outputs.atomic_path). Why a version: a later schema
    # change must be detected, not mis-read; it lives in the Parquet key-value metadata.
    def to_parquet(self, path: str | os.PathLike) -> "Path":
        """Write atomically to Parquet with the format version; the parent folder must exist."""
        import pyarrow as pa
        import pyarrow.parquet as pq

        from mfdesign.outputs import atomic_path

        path = Path(path)
        if not path.parent.is_dir():
            raise _PathMissing(f"folder {path.parent} does not exist; allowed: a file in an existing folder")
        table = pa.Table.from_pandas(self._df, preserve_index=False)
        table = table.replace_schema_metadata({**(table.schema.metadata or {}), FORMAT_KEY: FORMAT_VERSION.encode()})
        with atomic_path(path) as tmp:
            with open(tmp, "wb") as fh:
                pq.write_table(table, fh)
                fh.flush()
                os.fsync(fh.fileno())
        return path

    @classmethod
    def from_parquet(cls, path: str | os.PathLike, extra_ok: bool = False) -> "Measurements":
        """Read a file written by :meth:`to_parquet`; checks the format version and the table."""
        import pyarrow as pa
        import pyarrow.parquet as pq

        path = Path(path)
        if not path.is_file():
            raise _PathMissing(f"no Measurements file at {path}; allowed: a file written by to_parquet")
        try:
            table = pq.read_table(path)
        except (pa.ArrowInvalid, OSError) as err:
            raise MeasurementError(f"{path} is not a readable Parquet file: {err}") from None
        meta = table.schema.metadata or {}
        if FORMAT_KEY not in meta:
            raise MeasurementError(
                f"{path} has no {FORMAT_KEY.decode()!r} metadata: not written by mfdesign.data.store.write_parquet"
            )
        version = meta[FORMAT_KEY].decode(errors="replace")
        if version not in SUPPORTED_VERSIONS:
            raise MeasurementError(
                f"{path} has Measurements format version {version!r}; this mfdesign reads "
                f"versions {list(SUPPORTED_VERSIONS)} (upgrade mfdesign or convert the file)"
            )
        return cls(table.to_pandas(), extra_ok=extra_ok)
