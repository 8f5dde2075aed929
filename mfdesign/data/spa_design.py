"""Safe loaders for the public SPA_Design files in ``../shared/data/spa_design``.

The two ``.pkl`` files hold JAX arrays pickled as
``jax._src.array._reconstruct_array(fun, args, arr_state, aval_state)`` with ``fun`` the
NumPy array reconstructor. Pickle runs whatever a file names, so they are read with
:func:`restricted_load`, which resolves only NumPy's array reconstruction (and maps the
JAX reconstructor onto a plain NumPy array) and refuses everything else.

What the mass-lift file holds (checked when this module was written):
7 membranes x 3 masses (14.715, 24.525, 39.24 N), and for every (membrane, mass) exactly
TWO runs stored back to back, 42 runs, 45,924 rows. Within a run the file order goes from
the top (largest height and pressure) down towards h = 0; a run boundary shows as a
height reset (a jump up of 49-77 mm, with the pressure jumping up too). Heights are whole
millimetres. The weights are constant per membrane and sum to 1000 per membrane. The loader
keeps the file order and numbers the runs of each membrane in that order, so trials 0, 1
are the 14.715 N runs, 2, 3 the 24.525 N runs and 4, 5 the 39.24 N runs.
"""

from __future__ import annotations

import importlib
import io
import os
import pickle
from dataclasses import dataclass, field
from pathlib import Path

import numpy as np
import pandas as pd

from mfdesign.design import DesignError, Membrane
from mfdesign.data.measurements import Measurements

__all__ = [
    "ENV_VAR",
    "MASS_LIFT_FILE",
    "SIM_PLANES_FILE",
    "RINGLESS_ORDER",
    "SharedDataMissing",
    "SimPlane",
    "UnsafePickleError",
    "load_mass_lift",
    "load_sim_planes",
    "restricted_load",
    "restricted_loads",
    "shared_data_dir",
    "sim_planes_as_measurements",
]

ENV_VAR = "MFDESIGN_SHARED_DATA"
MASS_LIFT_FILE = "mass_lift_data_dictionary_N_Pa.pkl"
SIM_PLANES_FILE = "sim_membranes.pkl"
# Upstream label defect: sim entries 1-6 are these ringless membranes, in this order.
RINGLESS_ORDER = ((1.0, 25.4), (1.0, 38.1), (1.5, 25.4), (1.5, 38.1), (2.0, 25.4), (2.0, 38.1))
RUN_RESET_MM = 20.0  # a height jump up by more than this starts a new run (observed: 49-77 mm)


# -- where the data lives -----------------------------------------------------------------
class SharedDataMissing(FileNotFoundError):
    """The shared SPA_Design data is not where we looked."""


def shared_data_dir(must_exist: bool = True) -> Path:
    """Folder of the SPA_Design files: ``$MFDESIGN_SHARED_DATA`` if set, else
    ``<repo root>/../shared/data/spa_design`` (repo root = parent of the ``mfdesign`` package).
    """
    env = os.environ.get(ENV_VAR)
    path = Path(env) if env else Path(__file__).resolve().parents[2].parent / "shared" / "data" / "spa_design"
    if must_exist and not path.is_dir():
        how = f"${ENV_VAR}={env}" if env else f"the default (no ${ENV_VAR} set)"
        raise SharedDataMissing(
            f"SPA_Design data folder not found: looked in {path} ({how}). Point {ENV_VAR} at "
            "the folder holding mass_lift_data_dictionary_N_Pa.pkl and sim_membranes.pkl."
        )
    return path


def _data_file(path: str | os.PathLike | None, name: str) -> Path:
    p = Path(path) if path is not None else shared_data_dir() / name
    if not p.is_file():
        raise SharedDataMissing(
            f"{name}: no file at {p}. Pass the path, or point {ENV_VAR} at the SPA_Design folder."
        )
    return p


# -- restricted unpickling ----------------------------------------------------------------
class UnsafePickleError(pickle.UnpicklingError):
    """A pickle named something other than a NumPy array reconstruction."""


def _numpy_reconstructors() -> dict[tuple[str, str], object]:
    """NumPy's array reconstructor under its old (< 2.0) and new module names."""
    out = {}
    for mod in ("numpy._core.multiarray", "numpy.core.multiarray"):
        try:
            out[(mod, "_reconstruct")] = getattr(importlib.import_module(mod), "_reconstruct")
        except (ImportError, AttributeError):
            pass
    return out


def _reconstruct_jax_array(fun, args, arr_state, aval_state):
    """Stand-in for ``jax._src.array._reconstruct_array``: same signature, plain NumPy out."""
    if fun not in _numpy_reconstructors().values():
        raise UnsafePickleError(f"JAX array reconstruction through {fun!r}: only NumPy's is allowed")
    arr = fun(*args)
    arr.__setstate__(arr_state)
    return np.asarray(arr)


def _safe_dtype(*args):
    dtype = np.dtype(*args)
    if dtype.hasobject:
        raise UnsafePickleError("object arrays are not allowed: only numeric NumPy arrays")
    return dtype


def _allowed() -> dict[tuple[str, str], object]:
    """The only globals a pickle may name, and what each resolves to."""
    return {
        ("numpy", "ndarray"): np.ndarray,
        ("numpy", "dtype"): _safe_dtype,
        ("jax._src.array", "_reconstruct_array"): _reconstruct_jax_array,
        **_numpy_reconstructors(),
    }


class _RestrictedUnpickler(pickle.Unpickler):
    def find_class(self, module: str, name: str):
        target = _allowed().get((module, name))
        if target is None:
            raise UnsafePickleError(
                f"refused to load {module}.{name}: this loader allows only NumPy arrays "
                "(numpy _reconstruct / ndarray / dtype, and JAX arrays mapped onto NumPy)"
            )
        return target


def _check_no_objects(obj, depth: int = 0) -> None:
    if depth > 20:
        raise UnsafePickleError("pickle nests containers deeper than 20 levels")
    if isinstance(obj, np.ndarray):
        if obj.dtype.hasobject:
            raise UnsafePickleError("object arrays are not allowed: only numeric NumPy arrays")
    elif isinstance(obj, dict):
        for k, v in obj.items():
            _check_no_objects(k, depth + 1)
            _check_no_objects(v, depth + 1)
    elif isinstance(obj, (list, tuple)):
        for v in obj:
            _check_no_objects(v, depth + 1)


def restricted_loads(data: bytes):
    """Unpickle bytes allowing only NumPy arrays inside plain containers."""
    obj = _RestrictedUnpickler(io.BytesIO(data)).load()
    _check_no_objects(obj)
    return obj


def restricted_load(path: str | os.PathLike):
    """Unpickle a file allowing only NumPy arrays; anything else -> :class:`UnsafePickleError`."""
    with open(path, "rb") as fh:
        return restricted_loads(fh.read())


# -- mass-lift trials ---------------------------------------------------------------------
def _design_of(key: str, where: str) -> Membrane:
    try:
        return Membrane.from_key(key)
    except DesignError as err:
        raise ValueError(f"{where}: {key!r} is not a valid design: {err}") from None


def _column(a, n: int, what: str) -> np.ndarray:
    a = np.asarray(a, dtype=np.float64)
    if a.ndim == 2 and a.shape[1] == 1:
        a = a[:, 0]
    if a.shape != (n,):
        raise ValueError(f"mass-lift file: {what} has shape {a.shape}, expected ({n},) or ({n}, 1)")
    return a


def _trial_ids(force: np.ndarray, height: np.ndarray) -> np.ndarray:
    """Run number in file order: a new run where the mass changes or the height resets."""
    new_mass = np.r_[True, force[1:] != force[:-1]]
    reset = np.r_[False, np.diff(height) > RUN_RESET_MM]
    return (np.cumsum(new_mass | reset) - 1).astype(np.int64)


def load_mass_lift(path: str | os.PathLike | None = None) -> Measurements:
    """The real mass-lift trials as Measurements (experiment "lift", source "file").

    Heights in mm (``us[:, 0]``), pressure in Pa, force = weight of the mass in N.
    No time stamps (``time_s`` NaN) and no set-point (``height_set_mm`` NaN).
    """
    p = _data_file(path, MASS_LIFT_FILE)
    data = restricted_load(p)
    if not isinstance(data, dict):
        raise ValueError(f"{p}: expected a dict of membranes, got {type(data).__name__}")
    frames = []
    for key, value in data.items():
        design = _design_of(key, str(p))
        try:
            (us, ys), fs, ws = value
        except (TypeError, ValueError):
            raise ValueError(f"{p}: entry {key} is not ((us, ys), Fs, ws)") from None
        us = np.asarray(us, dtype=np.float64)
        if us.ndim != 2 or us.shape[1] != 7:
            raise ValueError(f"{p}: entry {key}: us has shape {us.shape}, expected (n, 7)")
        n = len(us)
        if not np.allclose(us[:, 1:7], design.to_array(), rtol=1e-6, atol=1e-5, equal_nan=True):
            raise ValueError(f"{p}: entry {key}: the design columns us[:, 1:7] disagree with the key")
        height = us[:, 0]
        force = _column(fs, n, "Fs")
        frames.append(pd.DataFrame({
            "design_key": design.key(),
            "trial": _trial_ids(force, height),
            "experiment": "lift",
            "phase": "inflate",
            "time_s": np.nan,
            "height_set_mm": np.nan,
            "height_mm": height,
            "pressure_pa": _column(ys, n, "ys"),
            "force_n": force,
            "weight": _column(ws, n, "ws"),
            "source": "file",
        }))
    return Measurements(pd.concat(frames, ignore_index=True))


# -- simulated planes ---------------------------------------------------------------------
@dataclass(frozen=True, eq=False)
class SimPlane:
    """The authors' simulator output for one membrane: converged points (F [N], p [Pa], h [mm]).

    ``label_in_file`` keeps the name the file gave (wrong for entries 1-6, see README).
    """

    design: Membrane
    force_n: np.ndarray
    pressure_pa: np.ndarray
    height_mm: np.ndarray
    label_in_file: str = field(default="")

    def __len__(self) -> int:
        return len(self.force_n)


def _ringless(k: int) -> str:
    t, c = RINGLESS_ORDER[k]
    return Membrane(t, c).key()


def _fixed_designs(names: list[str], where: str) -> list[Membrane]:
    """Apply the README's label fix; refuse a file whose labels match neither pattern."""
    keys = [_design_of(n, f"{where}, entry {i + 1}").key() for i, n in enumerate(names)]
    correct = [_ringless(k) for k in range(6)]
    shifted = correct[1:] + [keys[6] if len(keys) > 6 else None]
    if keys[:6] == correct:  # already fixed upstream
        return [Membrane.from_key(k) for k in keys]
    if keys[:6] != shifted:
        raise ValueError(
            f"{where}: the names of entries 1-6 are {keys[:6]}; expected the known upstream "
            f"shift {shifted} (or the corrected {correct}). The file changed: check it by hand."
        )
    return [Membrane.from_key(k) for k in correct + keys[6:]]


def load_sim_planes(path: str | os.PathLike | None = None) -> list[SimPlane]:
    """The authors' 18 simulated planes, heights converted from m to mm, labels fixed."""
    p = _data_file(path, SIM_PLANES_FILE)
    data = restricted_load(p)
    if not isinstance(data, list):
        raise ValueError(f"{p}: expected a list of (name, (F, p, h)), got {type(data).__name__}")
    names, arrays = [], []
    for i, entry in enumerate(data):
        try:
            name, (f, pr, h) = entry
        except (TypeError, ValueError):
            raise ValueError(f"{p}: entry {i + 1} is not (name, (F, p, h))") from None
        f, pr, h = (np.asarray(a, dtype=np.float64).reshape(-1) for a in (f, pr, h))
        if not (f.shape == pr.shape == h.shape):
            raise ValueError(f"{p}: entry {i + 1}: F, p, h lengths {len(f)}, {len(pr)}, {len(h)} differ")
        names.append(str(name))
        arrays.append((f, pr, h * 1e3))  # file: metres -> mm
    designs = _fixed_designs(names, str(p))
    return [SimPlane(d, f, pr, h, label_in_file=n) for d, n, (f, pr, h) in zip(designs, names, arrays)]


def sim_planes_as_measurements(path: str | os.PathLike | None = None) -> Measurements:
    """The simulated planes as Measurements: experiment "force", source "simulated".

    One trial per plane (trial id = plane index 0..17); the set-point equals the height
    (the simulator holds the plate exactly); weight 1 per point; no time stamps.
    """
    frames = []
    for i, plane in enumerate(load_sim_planes(path)):
        frames.append(pd.DataFrame({
            "design_key": plane.design.key(),
            "trial": i,
            "experiment": "force",
            "phase": "inflate",
            "time_s": np.nan,
            "height_set_mm": plane.height_mm,
            "height_mm": plane.height_mm,
            "pressure_pa": plane.pressure_pa,
            "force_n": plane.force_n,
            "weight": 1.0,
            "source": "simulated",
        }))
    return Measurements(pd.concat(frames, ignore_index=True))
