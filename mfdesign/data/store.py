"""Parquet storage of Measurements, as functions: :meth:`Measurements.to_parquet` (atomic,
with a format version) and :meth:`Measurements.from_parquet` (validated) do the work.
"""

from __future__ import annotations

import os
from pathlib import Path

from mfdesign.data.measurements import FORMAT_KEY, FORMAT_VERSION, SUPPORTED_VERSIONS, Measurements

__all__ = ["FORMAT_KEY", "FORMAT_VERSION", "SUPPORTED_VERSIONS", "read_parquet", "write_parquet"]


def write_parquet(m: Measurements, path: str | os.PathLike) -> Path:
    """Write ``m`` to ``path`` atomically; return the path. The parent folder must exist."""
    if not isinstance(m, Measurements):
        raise TypeError(f"write_parquet takes a Measurements, got {type(m).__name__}")
    return m.to_parquet(path)


def read_parquet(path: str | os.PathLike, extra_ok: bool = False) -> Measurements:
    """Read a file written by :func:`write_parquet`; checks the format version and the table."""
    return Measurements.from_parquet(path, extra_ok=extra_ok)
