"""Data layer: the validated Measurements table, Parquet storage, safe loaders of real data."""

from mfdesign.data import measurements
from mfdesign.data.measurements import (  # "X as X": re-exported (PEP 484), listed in measurements.__all__
    COLUMNS as COLUMNS,
    EXPERIMENTS as EXPERIMENTS,
    PHASES as PHASES,
    SOURCES as SOURCES,
    MeasurementError as MeasurementError,
    Measurements as Measurements,
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

__all__ = measurements.__all__ + [
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
