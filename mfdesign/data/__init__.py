"""Data layer: the validated Measurements table, Parquet storage, safe loaders of real data."""

from mfdesign.data.measurements import (
    COLUMNS,
    EXPERIMENTS,
    PHASES,
    SOURCES,
    MeasurementError,
    Measurements,
)
from mfdesign.data.spa_design import (
    SharedDataMissing,
    SimPlane,
    UnsafePickleError,
    load_mass_lift,
    load_sim_planes,
    restricted_load,
    restricted_loads,
    shared_data_dir,
    sim_planes_as_measurements,
)
from mfdesign.data.store import read_parquet, write_parquet

__all__ = [
    "COLUMNS",
    "EXPERIMENTS",
    "PHASES",
    "SOURCES",
    "MeasurementError",
    "Measurements",
    "SharedDataMissing",
    "SimPlane",
    "UnsafePickleError",
    "load_mass_lift",
    "load_sim_planes",
    "read_parquet",
    "restricted_load",
    "restricted_loads",
    "shared_data_dir",
    "sim_planes_as_measurements",
    "write_parquet",
]
