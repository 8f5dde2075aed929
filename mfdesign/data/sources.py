"""Every way measurements come in, read into one :class:`Measurements` table.

One function, :func:`load_sources`, is what every command's ``DATA`` argument goes
through (via :func:`mfdesign.workflows.data.load_data`) and what ``mfdesign import``
converts. A source is:

* ``mass-lift``: the authors' real mass-lift file from the shared data folder;
* ``bundled``: the virtual-rig dataset shipped with the package (the demo's data,
  :mod:`mfdesign.data.shipped`);
* a Measurements **Parquet** file (``mfdesign.data.store``; a plain Parquet file with the
  Measurements columns is accepted too);
* a **CSV** file with the Measurements columns (``docs/data.md``); a missing column is
  refused with the list of missing ones;
* a **pickle** in one of the SPA_Design formats, read with the restricted unpickler
  (:func:`mfdesign.data.spa_design.restricted_load`, NumPy arrays only):

  - ``mass-lift``: the mass-lift dictionary (:func:`~mfdesign.data.spa_design.load_mass_lift`);
  - ``characterisation``: the "data dictionary" of the characterisation rig, key
    ``"[t, c, r1, w1, r2, w2]"`` -> ``((us [n, 7], ys [n, 1]), Fs [n, 1], ws [n, 1])``,
    ``us[:, 0]`` the plate's set height [mm], ``ys`` pressure [Pa], ``Fs`` the force [N]
    on the held plate over a pressure sweep: FORCE trials, one per (membrane, set height);
  - ``sim-planes``: the authors' simulated planes, ``sim_membranes.pkl``
    (:func:`~mfdesign.data.spa_design.sim_planes_as_measurements`, source "simulated");

* a **rig job folder** (``mfdesign rig characterize / lift --out DIR``): its journal
  (completed trials), or its ``measurements.parquet``.

Several sources are concatenated; trial ids are renumbered per membrane so that they stay
unique (``Measurements.concat(..., renumber_trials=True)``). One source keeps its ids.
"""

from __future__ import annotations

import os
from pathlib import Path
from typing import Sequence

import numpy as np
import pandas as pd

from mfdesign.data.columns import ColumnMap, apply_column_map
from mfdesign.data.measurements import COLUMNS, MeasurementError, Measurements
from mfdesign.data.plausible import MAX_ROWS, check_columns, check_rows
from mfdesign.data.shipped import BUNDLED_NAME, bundled_path
from mfdesign.errors import InputError

__all__ = [
    "FORMATS",
    "MASS_LIFT_NAME",
    "detect_format",
    "load_sources",
    "read_characterisation",
    "read_csv",
    "read_source",
]

FORMATS = ("parquet", "csv", "mass-lift", "characterisation", "sim-planes", "rig-job")
MASS_LIFT_NAME = "mass-lift"
_PICKLE_SUFFIXES = (".pkl", ".pickle")
_ALLOWED = (
    f"allowed: '{MASS_LIFT_NAME}', '{BUNDLED_NAME}', a Measurements .parquet or .csv file, an SPA_Design .pkl "
    "(mass-lift or characterisation data dictionary, simulated planes) or a rig job folder"
)


def _is_rig_job(path: Path) -> bool:
    return path.is_dir() and ((path / "job.json").is_file() or (path / "measurements.parquet").is_file())


def _sniff(path: Path) -> bytes:
    try:
        with open(path, "rb") as fh:
            return fh.read(8)
    except OSError as err:
        raise InputError(f"cannot read {path}: {err.strerror or err}") from None


def _pickle_kind(obj, where: str) -> str:
    """``mass-lift``, ``characterisation`` (or ``sim-planes``) for a loaded SPA_Design pickle.

    The two dictionaries have the same layout; what differs is which column is held: a
    mass-lift trial holds the force (the weight of its mass: a few distinct values per
    membrane) while the plate height moves; a characterisation trial holds the plate at a
    few set heights while the force changes at nearly every sample. So: fewer distinct
    forces than distinct heights in every membrane means mass-lift."""
    if (
        isinstance(obj, list)
        and obj
        and all(isinstance(e, tuple) and len(e) == 2 and isinstance(e[0], str) for e in obj)
    ):
        return "sim-planes"
    if not isinstance(obj, dict) or not obj:
        raise InputError(
            f"{where}: a pickle, but not an SPA_Design data dictionary (a non-empty dict of "
            f"design key -> ((us, ys), Fs, ws)); got {type(obj).__name__}; {_ALLOWED}"
        )
    from mfdesign.data.spa_design import checked_entries

    lift = []
    for design, value in checked_entries(obj, where):
        key = design.key()
        try:
            (us, _), fs, _ = value
            f = np.asarray(fs, dtype=np.float64).reshape(-1)
            h = np.asarray(us, dtype=np.float64)[:, 0]
        except (TypeError, ValueError, IndexError):
            raise InputError(f"{where}: entry {key!r} is not ((us, ys), Fs, ws); {_ALLOWED}") from None
        lift.append(len(np.unique(f[np.isfinite(f)])) < len(np.unique(h[np.isfinite(h)])))
    if all(lift):
        return "mass-lift"
    if not any(lift):
        return "characterisation"
    raise InputError(
        f"{where}: some membranes look like mass-lift trials, others like characterisation; "
        "give --format mass-lift or --format characterisation"
    )


def detect_format(path: str | os.PathLike) -> str:
    """The format of ``path`` (one of :data:`FORMATS`), from the name and the first bytes;
    an unknown one raises ``InputError`` in one line."""
    if str(path) == MASS_LIFT_NAME:
        return "mass-lift"
    p = Path(path)
    if not p.exists():
        raise InputError(f"data {p} does not exist; {_ALLOWED}")
    if p.is_dir():
        if _is_rig_job(p):
            return "rig-job"
        raise InputError(f"data {p} is a folder without job.json or measurements.parquet (not a rig job); {_ALLOWED}")
    head, suffix = _sniff(p), p.suffix.lower()
    if head.startswith(b"PAR1") or suffix == ".parquet":
        return "parquet"
    if suffix in _PICKLE_SUFFIXES or head[:1] == b"\x80":
        from mfdesign.data.spa_design import restricted_load

        return _pickle_kind(restricted_load(p), str(p))
    if suffix == ".csv":
        return "csv"
    raise InputError(f"data {p}: unknown format (suffix {suffix or 'none'!r}, first bytes {head[:4]!r}); {_ALLOWED}")


def _checked_frame(df: pd.DataFrame, where: str, columns: ColumnMap = ColumnMap()) -> Measurements:
    # mapped, converted to mm / Pa / N / s and the optional columns filled (mfdesign.data.columns)
    df = apply_column_map(df, columns, where)
    check_columns(df, where)  # on the raw table: units, booleans, lifts (mfdesign.data.plausible)
    try:
        return Measurements(df[list(COLUMNS)])
    except MeasurementError as err:
        raise MeasurementError(f"{where}: {err}") from None


def read_csv(path: str | os.PathLike, columns: ColumnMap | str | None = None) -> Measurements:
    """A CSV with the Measurements columns (any order, extra columns ignored; docs/data.md),
    or any columns with a column map ``columns`` (``"design_key=design,pressure_pa=pressure_kpa:kPa"``,
    :class:`~mfdesign.data.columns.ColumnMap`); optional columns take documented defaults."""
    p = Path(path)
    cmap = columns if isinstance(columns, ColumnMap) else ColumnMap.parse(columns)
    text = {"design_key", "experiment", "phase", "source"}
    dtype = {s: str for t, s, _ in cmap.entries if t in text} | {
        c: str for c in text if c not in {t for t, _, _ in cmap.entries}
    }
    try:
        # one row past the bound is enough to refuse: a 10-million-row file is not read whole
        df = pd.read_csv(p, dtype=dtype, nrows=MAX_ROWS + 1)
    except (pd.errors.ParserError, pd.errors.EmptyDataError, UnicodeDecodeError, ValueError) as err:
        raise InputError(f"{p}: not a readable CSV ({type(err).__name__}: {str(err)[:160]})") from None
    if len(df) > MAX_ROWS:
        raise InputError(
            f"{p}: more than {MAX_ROWS:,} rows; allowed: at most {MAX_ROWS:,} rows per source (split the file)"
        )
    return _checked_frame(df, str(p), cmap)


def _read_parquet(path: Path, columns: ColumnMap = ColumnMap()) -> Measurements:
    from mfdesign.data.store import FORMAT_KEY, read_parquet

    import pyarrow as pa
    import pyarrow.parquet as pq

    try:
        meta = pq.read_schema(path).metadata or {}
        check_rows(pq.read_metadata(path).num_rows, str(path))  # from the footer, before reading
    except (pa.ArrowInvalid, OSError) as err:
        raise MeasurementError(f"{path} is not a readable Parquet file: {err}") from None
    if FORMAT_KEY in meta and not columns:
        return read_parquet(path)
    return _checked_frame(pq.read_table(path).to_pandas(), str(path), columns)  # a plain table with the columns


def read_characterisation(source, where: str | None = None) -> Measurements:
    """The SPA_Design characterisation data dictionary (a path, or the loaded dict) as
    Measurements: experiment "force", source "file", one trial per (membrane, set height)
    numbered in order of first appearance, ``height_set_mm = height_mm = us[:, 0]``,
    phase "inflate", no time stamps, weights ``ws``."""
    from mfdesign.data.spa_design import _column, checked_entries, restricted_load

    if isinstance(source, (str, os.PathLike)):
        where = where or str(source)
        source = restricted_load(source)
    where = where or "characterisation data"
    if not isinstance(source, dict) or not source:
        raise InputError(f"{where}: expected a non-empty dict of membranes, got {type(source).__name__}")
    frames = []
    for design, value in checked_entries(source, where):
        key = design.key()
        try:
            (us, ys), fs, ws = value
            us = np.asarray(us, dtype=np.float64)
        except (TypeError, ValueError):
            raise InputError(f"{where}: entry {key} is not ((us [n, 7], ys), Fs, ws) of numbers") from None
        if us.ndim != 2 or us.shape[1] != 7:
            raise InputError(f"{where}: entry {key}: us has shape {us.shape}, expected (n, 7)")
        n = len(us)
        if not np.allclose(us[:, 1:7], design.to_array(), rtol=1e-6, atol=1e-5, equal_nan=True):
            raise InputError(f"{where}: entry {key}: the design columns us[:, 1:7] disagree with the key")
        height = us[:, 0]
        _, trial = np.unique(np.round(height, 6), return_inverse=True)
        first: dict[int, int] = {}
        for t in trial:  # number the set heights in order of first appearance
            first.setdefault(int(t), len(first))
        frames.append(
            pd.DataFrame(
                {
                    "design_key": design.key(),
                    "trial": np.array([first[int(t)] for t in trial], dtype=np.int64),
                    "experiment": "force",
                    "phase": "inflate",
                    "time_s": np.nan,
                    "height_set_mm": height,
                    "height_mm": height,
                    "pressure_pa": _column(ys, n, "ys"),
                    "force_n": _column(fs, n, "Fs"),
                    "weight": _column(ws, n, "ws"),
                    "source": "file",
                }
            )
        )
    try:
        return Measurements(pd.concat(frames, ignore_index=True))
    except MeasurementError as err:
        raise MeasurementError(f"{where}: {err}") from None


def _read_rig_job(path: Path) -> Measurements:
    if (path / "job.json").is_file() and (path / "samples.csv").is_file():
        from mfdesign.rig.procedures import to_measurements

        try:
            return to_measurements(path)
        except (MeasurementError, InputError):
            raise
        except Exception as err:  # noqa: BLE001 -- a damaged journal fails in many ways
            raise InputError(f"rig job {path}: journal not readable ({type(err).__name__}: {str(err)[:160]})") from None
    return _read_parquet(path / "measurements.parquet")


def read_source(source: str | os.PathLike, fmt: str = "auto", columns: ColumnMap | str | None = None) -> Measurements:
    """One source (module doc) as Measurements; ``fmt``: ``auto`` or one of :data:`FORMATS`;
    ``columns``: a column map for a CSV or a plain Parquet table (:mod:`mfdesign.data.columns`)."""
    if fmt not in ("auto",) + FORMATS:
        raise InputError(f"--format {fmt!r} is not known; allowed: auto, {', '.join(FORMATS)}")
    cmap = columns if isinstance(columns, ColumnMap) else ColumnMap.parse(columns)
    if cmap and str(source) == MASS_LIFT_NAME:
        raise InputError(f"a column map (--columns) reads a CSV or Parquet table, not {source}; allowed: no map")
    if str(source) == MASS_LIFT_NAME and fmt in ("auto", "mass-lift"):
        from mfdesign.data.spa_design import load_mass_lift

        return load_mass_lift()
    if str(source) == BUNDLED_NAME and fmt in ("auto", "parquet") and not Path(source).exists():
        return _read_parquet(bundled_path())
    kind = detect_format(source) if fmt == "auto" else fmt
    p = Path(source)
    if fmt != "auto" and not p.exists():
        raise InputError(f"data {p} does not exist; {_ALLOWED}")
    if cmap and kind not in ("csv", "parquet"):
        raise InputError(
            f"{p}: a column map (--columns) reads a CSV or Parquet table, not {kind} data; allowed: no map"
        )
    m = _read_kind(p, kind, cmap)
    if kind != "csv":  # a CSV was checked on its raw table (_checked_frame)
        check_columns(m.df, str(p))
    return m


def _read_kind(p: Path, kind: str, cmap: ColumnMap = ColumnMap()) -> Measurements:
    """One source of a known format (module doc)."""
    if kind == "rig-job":
        if not _is_rig_job(p):
            raise InputError(f"{p} is not a rig job folder (no job.json or measurements.parquet)")
        return _read_rig_job(p)
    if p.is_dir():
        raise InputError(f"data {p} is a folder; --format {kind} reads a file")
    if kind == "parquet":
        return _read_parquet(p, cmap)
    if kind == "csv":
        return read_csv(p, cmap)
    if kind in ("mass-lift", "characterisation"):
        from mfdesign.data.spa_design import load_mass_lift, restricted_load

        obj = restricted_load(p)
        found = _pickle_kind_or_mixed(obj, str(p))
        if found not in (kind, None):
            # --format must not turn lifts (the force held: the mass) into force trials, or back
            raise InputError(
                f"{p}: --format {kind}, but the file holds {found} trials (" + _KIND_WHY[found] + "); "
                f"allowed: --format {found} or auto"
            )
        return load_mass_lift(p) if kind == "mass-lift" else read_characterisation(obj, str(p))
    if kind == "sim-planes":
        from mfdesign.data.spa_design import sim_planes_as_measurements

        return sim_planes_as_measurements(p)
    raise InputError(f"--format {kind!r} is not known; allowed: auto, {', '.join(FORMATS)}")


_KIND_WHY = {
    "mass-lift": "every membrane has fewer distinct forces than heights: masses lifted",
    "characterisation": "every membrane has more distinct forces than heights: the plate held",
    "sim-planes": "a list of simulated planes",
}


def _pickle_kind_or_mixed(obj, where: str) -> str | None:
    """:func:`_pickle_kind`, or None where membranes disagree (an explicit --format decides)."""
    try:
        return _pickle_kind(obj, where)
    except InputError as err:
        if "some membranes look like" in str(err):
            return None
        raise


def load_sources(
    sources: str | os.PathLike | Sequence[str | os.PathLike], fmt: str = "auto", columns: ColumnMap | str | None = None
) -> Measurements:
    """Several sources (module doc) as one Measurements; trial ids renumbered per membrane
    when there is more than one source; ``columns``: one column map for every CSV / Parquet
    table among them (:mod:`mfdesign.data.columns`)."""
    if isinstance(sources, (str, os.PathLike)):
        items: list = [sources]
    elif isinstance(sources, (list, tuple)):
        items = list(sources)
    else:
        items = [sources]
    bad = [s for s in items if not isinstance(s, (str, os.PathLike))]
    if bad:
        raise InputError(f"data {bad[0]!r} is a {type(bad[0]).__name__}, not a name or a path; {_ALLOWED}")
    if not items:
        raise InputError(f"no data given; {_ALLOWED}")
    parts = [read_source(s, fmt, columns) for s in items]
    if len(parts) == 1:
        return parts[0]
    return Measurements.concat(parts, renumber_trials=True)
