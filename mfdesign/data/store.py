"""Parquet storage of Measurements: atomic writes, a format version, validation on read.

Why atomic: a crash half-way through a write must never leave a truncated file where a
good one (or none) was; we write a temporary file beside the target, fsync it and
``os.replace`` it into place. Why a version: a later schema change must be detected, not
mis-read; the version lives in the Parquet key-value metadata.
"""

from __future__ import annotations

import os
import tempfile
from pathlib import Path

import pyarrow as pa
import pyarrow.parquet as pq

from mfdesign.data.measurements import MeasurementError, Measurements

__all__ = ["FORMAT_KEY", "FORMAT_VERSION", "read_parquet", "write_parquet"]

FORMAT_KEY = b"mfdesign.measurements.format_version"
FORMAT_VERSION = "1"
SUPPORTED_VERSIONS = (FORMAT_VERSION,)


def write_parquet(m: Measurements, path: str | os.PathLike) -> Path:
    """Write ``m`` to ``path`` atomically; return the path. The parent folder must exist."""
    if not isinstance(m, Measurements):
        raise TypeError(f"write_parquet takes a Measurements, got {type(m).__name__}")
    path = Path(path)
    if not path.parent.is_dir():
        raise FileNotFoundError(f"folder {path.parent} does not exist; create it first")
    table = pa.Table.from_pandas(m.df, preserve_index=False)
    meta = dict(table.schema.metadata or {})
    meta[FORMAT_KEY] = FORMAT_VERSION.encode()
    table = table.replace_schema_metadata(meta)
    fd, tmp = tempfile.mkstemp(dir=path.parent, prefix=f".{path.name}.", suffix=".tmp")
    try:
        with os.fdopen(fd, "wb") as fh:
            pq.write_table(table, fh)
            fh.flush()
            os.fsync(fh.fileno())
        os.replace(tmp, path)
    except BaseException:
        try:
            os.unlink(tmp)
        except FileNotFoundError:
            pass
        raise
    return path


def read_parquet(path: str | os.PathLike, extra_ok: bool = False) -> Measurements:
    """Read a file written by :func:`write_parquet`; checks the format version and the table."""
    path = Path(path)
    if not path.is_file():
        raise FileNotFoundError(f"no Measurements file at {path}")
    try:
        table = pq.read_table(path)
    except (pa.ArrowInvalid, OSError) as err:
        raise MeasurementError(f"{path} is not a readable Parquet file: {err}") from None
    meta = table.schema.metadata or {}
    if FORMAT_KEY not in meta:
        raise MeasurementError(
            f"{path} has no {FORMAT_KEY.decode()!r} metadata: not written by "
            "mfdesign.data.store.write_parquet"
        )
    version = meta[FORMAT_KEY].decode(errors="replace")
    if version not in SUPPORTED_VERSIONS:
        raise MeasurementError(
            f"{path} has Measurements format version {version!r}; this mfdesign reads "
            f"versions {list(SUPPORTED_VERSIONS)} (upgrade mfdesign or convert the file)"
        )
    return Measurements(table.to_pandas(), extra_ok=extra_ok)
