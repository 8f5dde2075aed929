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
import math
import os
import pickle
import pickletools
from dataclasses import dataclass, field
from pathlib import Path
from typing import Any

import numpy as np
import pandas as pd

from mfdesign.design import DesignError, Membrane
from mfdesign.data.measurements import Measurements
from mfdesign.data.plausible import check_rows
from mfdesign.errors import InputError

__all__ = [
    "ENV_VAR",
    "MASS_LIFT_FILE",
    "SIM_PLANES_FILE",
    "RINGLESS_ORDER",
    "SharedDataMissing",
    "SimPlane",
    "UnsafePickleError",
    "load_mass_lift",
    "checked_entries",
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
class SharedDataMissing(FileNotFoundError, InputError):
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
        raise SharedDataMissing(f"{name}: no file at {p}. Pass the path, or point {ENV_VAR} at the SPA_Design folder.")
    return p


# -- restricted unpickling ----------------------------------------------------------------
class UnsafePickleError(pickle.UnpicklingError, InputError):
    """A pickle that names, builds or sizes something this loader does not allow."""


# Bounds of what one pickle may build. The real files: ~2 MB of arrays, < 2,000 opcodes,
# < 1,000 containers, nesting depth 6. Why bounds at all: pickle memoises, so a file of a
# few hundred bytes can describe a DAG of shared lists that a tree walk visits 10^16 times,
# or name an array shape of terabytes; both must be refused in milliseconds.
MAX_PICKLE_BYTES = 512 * 2**20
MAX_ARRAY_BYTES = 256 * 2**20  # all arrays of one file together, checked before allocation
MAX_OPCODES = 5_000_000
MAX_NODES = 1_000_000  # distinct containers and arrays (shared ones counted once)
MAX_TREE_NODES = 10_000_000  # the structure unfolded into a tree (what np.asarray would walk)
MAX_DEPTH = 32
MAX_MEMO_GETS = 100_000  # real files: < 400 re-uses of a memoised object
# Opcodes that build things outside "numeric arrays in dict / list / tuple of str / bytes /
# numbers": refused before anything is loaded, with what they would have built.
_REFUSED_OPCODES = {
    "EMPTY_SET": "a set",
    "ADDITEMS": "a set",
    "FROZENSET": "a frozenset",
    "BYTEARRAY8": "a bytearray",
    "INST": "a class instance",
    "OBJ": "a class instance",
    "NEWOBJ": "a class instance",
    "NEWOBJ_EX": "a class instance",
    "EXT1": "an extension-registry object",
    "EXT2": "an extension-registry object",
    "EXT4": "an extension-registry object",
    "PERSID": "a persistent reference",
    "BINPERSID": "a persistent reference",
    "NEXT_BUFFER": "an out-of-band buffer",
    "READONLY_BUFFER": "an out-of-band buffer",
}
_ALLOWED_WORDS = (
    "allowed: dict, list, tuple, str, bytes, numbers, None and numeric NumPy arrays "
    "(numpy _reconstruct / ndarray / dtype, and JAX arrays mapped onto NumPy)"
)
_LEAVES = (str, bytes, int, float, complex, bool, type(None), np.number, np.bool_)


def _numpy_reconstructors() -> dict[tuple[str, str], object]:
    """NumPy's array reconstructor under its old (< 2.0) and new module names."""
    out = {}
    for mod in ("numpy._core.multiarray", "numpy.core.multiarray"):
        try:
            out[(mod, "_reconstruct")] = importlib.import_module(mod)._reconstruct
        except (ImportError, AttributeError):
            pass
    # A file pickled under NumPy 2 names numpy._core, one pickled under NumPy 1 numpy.core:
    # both mean the same reconstructor, whichever NumPy reads them.
    if out:
        fun = next(iter(out.values()))
        for mod in ("numpy._core.multiarray", "numpy.core.multiarray"):
            out.setdefault((mod, "_reconstruct"), fun)
    return out


class _NdarrayType:
    """What ``numpy.ndarray`` resolves to: a token the reconstructors accept as the array
    type. Not the class itself, so a pickle cannot call ``ndarray(shape)`` and allocate an
    unchecked shape."""

    def __repr__(self) -> str:
        return "numpy.ndarray"


_NDARRAY = _NdarrayType()


def _safe_dtype(*args):
    try:
        dtype = np.dtype(*args)
    except (TypeError, ValueError) as err:
        raise UnsafePickleError(f"bad dtype {args!r} in the pickle: {err}") from None
    if dtype.hasobject:
        raise UnsafePickleError("object arrays are not allowed: only numeric NumPy arrays")
    return dtype


class _ArrayBudget:
    """Bytes of arrays built so far by one load; refuses a shape before it is allocated."""

    def __init__(self, limit_bytes: int):
        self.limit_bytes, self.used_bytes = int(limit_bytes), 0

    def charge(self, shape, dtype) -> None:
        if not (
            isinstance(shape, tuple)
            and len(shape) <= MAX_DEPTH
            and all(isinstance(n, int) and not isinstance(n, bool) and n >= 0 for n in shape)
        ):
            raise UnsafePickleError(f"array shape {shape!r} in the pickle is not a tuple of sizes >= 0")
        dtype = dtype if isinstance(dtype, np.dtype) else _safe_dtype(dtype)
        if dtype.hasobject:
            raise UnsafePickleError("object arrays are not allowed: only numeric NumPy arrays")
        nbytes = math.prod(shape) * dtype.itemsize  # Python ints: no overflow
        self.used_bytes += nbytes
        if self.used_bytes > self.limit_bytes:
            raise UnsafePickleError(
                f"array of shape {shape} ({dtype}, {nbytes / 2**20:.4g} MiB) takes the pickle's arrays "
                f"past {self.limit_bytes / 2**20:g} MiB; allowed: at most {self.limit_bytes / 2**20:g} MiB "
                "of arrays per file (refused before allocating)"
            )

    def reconstruct(self, subtype, shape, dtype):
        """``numpy._core.multiarray._reconstruct`` for plain ndarrays, shape checked first."""
        if subtype is not _NDARRAY and subtype is not np.ndarray:
            raise UnsafePickleError(f"array reconstruction of {subtype!r}: only numpy.ndarray is allowed")
        self.charge(shape, dtype)
        fun = next(iter(_numpy_reconstructors().values()))
        return fun(np.ndarray, shape, _safe_dtype(dtype))

    def setstate(self, arr, state) -> np.ndarray:
        """``arr.__setstate__(state)`` with ``state = (version, shape, dtype, fortran, data)``
        checked first (numpy would allocate the shape)."""
        if not (isinstance(arr, np.ndarray) and isinstance(state, tuple) and len(state) == 5):
            raise UnsafePickleError("malformed array state in the pickle")
        self.charge(state[1], state[2])
        try:
            arr.__setstate__(state)
        except (TypeError, ValueError) as err:
            raise UnsafePickleError(f"malformed array state in the pickle: {err}") from None
        return arr

    def reconstruct_jax(self, fun, args, arr_state, aval_state):
        """Stand-in for ``jax._src.array._reconstruct_array``: same signature, plain NumPy out."""
        if fun != self.reconstruct:
            raise UnsafePickleError(f"JAX array reconstruction through {fun!r}: only NumPy's is allowed")
        if not isinstance(args, tuple):
            raise UnsafePickleError("malformed JAX array arguments in the pickle")
        return np.asarray(self.setstate(fun(*args), arr_state))


class _RestrictedUnpickler(pickle.Unpickler):
    def __init__(self, file, max_array_bytes: int = MAX_ARRAY_BYTES):
        super().__init__(file)
        self.budget = _ArrayBudget(max_array_bytes)

    def find_class(self, module: str, name: str):
        allowed = {
            ("numpy", "ndarray"): _NDARRAY,
            ("numpy", "dtype"): _safe_dtype,
            ("jax._src.array", "_reconstruct_array"): self.budget.reconstruct_jax,
            **{key: self.budget.reconstruct for key in _numpy_reconstructors()},
        }
        target = allowed.get((module, name))
        if target is None:
            raise UnsafePickleError(
                f"refused to load {module}.{name}: this loader allows only NumPy arrays "
                "(numpy _reconstruct / ndarray / dtype, and JAX arrays mapped onto NumPy)"
            )
        return target


class _Sym:
    """What the prescan knows of one stack item: its kind and how deep it nests."""

    __slots__ = ("kind", "depth")

    def __init__(self, kind: str, depth: int = 0):
        self.kind, self.depth = kind, depth


_MARK = _Sym("mark")
_STR_OPS = {"STRING", "BINSTRING", "SHORT_BINSTRING", "UNICODE", "BINUNICODE", "SHORT_BINUNICODE", "BINUNICODE8"}
_KIND_OF = {"TUPLE": "tuple", "EMPTY_TUPLE": "tuple", "TUPLE1": "tuple", "TUPLE2": "tuple", "TUPLE3": "tuple"}
_KIND_OF |= {"EMPTY_LIST": "list", "LIST": "list", "EMPTY_DICT": "dict", "DICT": "dict"}
_KIND_OF |= dict.fromkeys(_STR_OPS, "str")
# Opcodes that hand back the object they were given (mutated): it keeps its identity.
_SAME_OBJECT = {"APPEND", "APPENDS", "SETITEM", "SETITEMS", "BUILD", "MEMOIZE"}


def _prescan(data: bytes) -> None:
    """Refuse set / instance / extension opcodes, overlong streams, non-string dict keys,
    deep nesting and heavy memo re-use, before anything is built.

    Why a symbolic run of the stack: the unpickler hashes a dict key the moment it sets
    it, and hashing a tuple is recursive C. A key that is a 100-level DAG of shared tuples
    costs 2^100 hash steps (a hang); a 400,000-deep tuple overflows the C stack (SIGSEGV).
    Both happen inside ``Unpickler.load``, before any check on the result could run, so
    the keys' kinds and the nesting depth are followed here, on the opcodes alone."""
    stack: list[_Sym] = []
    memo: dict[object, _Sym] = {}
    gets = 0

    def pop_to_mark() -> list[_Sym]:
        items = []
        while stack and stack[-1] is not _MARK:
            items.append(stack.pop())
        if not stack:
            raise pickle.UnpicklingError("not a valid pickle (truncated or corrupt): MARK missing")
        stack.pop()
        return items[::-1]

    def pop(n: int) -> list[_Sym]:
        if len(stack) < n:
            raise pickle.UnpicklingError("not a valid pickle (truncated or corrupt): stack underflow")
        items = stack[len(stack) - n :]
        del stack[len(stack) - n :]
        return items

    def check_keys(keys: list[_Sym]) -> None:
        for key in keys:
            if key.kind != "str":
                raise UnsafePickleError(
                    f"the pickle uses a {key.kind} as a dict key; allowed: string keys only (" + _ALLOWED_WORDS + ")"
                )

    try:
        for n, (op, arg, _) in enumerate(pickletools.genops(data)):
            name = op.name
            if name in _REFUSED_OPCODES:
                raise UnsafePickleError(
                    f"the pickle builds {_REFUSED_OPCODES[name]} (opcode {name}); " + _ALLOWED_WORDS
                )
            if n >= MAX_OPCODES:
                raise UnsafePickleError(f"the pickle has more than {MAX_OPCODES:,} opcodes; allowed: fewer")
            if name == "MARK":
                stack.append(_MARK)
                continue
            if name in ("PUT", "BINPUT", "LONG_BINPUT", "MEMOIZE"):
                if not stack:
                    raise pickle.UnpicklingError("not a valid pickle (truncated or corrupt): memo of nothing")
                memo[len(memo) if name == "MEMOIZE" else arg] = stack[-1]
                continue
            if name in ("GET", "BINGET", "LONG_BINGET"):
                gets += 1
                if gets > MAX_MEMO_GETS:
                    raise UnsafePickleError(
                        f"the pickle re-uses memoised objects more than {MAX_MEMO_GETS:,} times; allowed: fewer"
                    )
                if arg not in memo:
                    raise pickle.UnpicklingError(f"not a valid pickle (truncated or corrupt): memo {arg} unset")
                stack.append(memo[arg])
                continue
            if name == "DUP":
                stack.append(pop(1)[0])
                stack.append(stack[-1])
                continue
            before, after = op.stack_before, op.stack_after
            if pickletools.stackslice in before:
                items = pop_to_mark()
                below = pop(before.index(pickletools.markobject))
            else:
                items, below = pop(len(before)), []
            if name in ("SETITEM", "SETITEMS", "DICT"):
                check_keys(items[0::2] if name != "SETITEM" else items[1:2])  # [dict, key, value]
            target = None
            if name in _SAME_OBJECT:  # the container (or array) is below the mark, else first
                target = below[0] if below else items.pop(0)
            depth = 1 + max((i.depth for i in items), default=0)
            if depth > MAX_DEPTH:
                raise UnsafePickleError(f"pickle nests containers deeper than {MAX_DEPTH} levels")
            if target is not None:
                target.depth = max(target.depth, depth)
                stack.append(target)
            elif after:
                stack.extend(_Sym(_KIND_OF.get(name, "other"), depth if len(items) else 0) for _ in after)
    except (UnsafePickleError, pickle.UnpicklingError):
        raise
    except Exception as err:  # noqa: BLE001 -- pickletools raises ValueError and worse on junk
        raise pickle.UnpicklingError(f"not a valid pickle (truncated or corrupt): {err}") from None


def _children(o) -> list:
    if isinstance(o, dict):
        return [x for kv in o.items() for x in kv]
    if isinstance(o, (list, tuple)):
        return list(o)
    return []


def _check_no_objects(
    obj, max_nodes: int = MAX_NODES, max_tree_nodes: int = MAX_TREE_NODES, max_depth: int = MAX_DEPTH
) -> None:
    """Check every object's type and bound the structure's size, visiting each distinct
    object once. The size that matters downstream (``np.asarray`` on nested lists, a tree
    walk) is that of the structure unfolded into a tree; it is computed bottom-up with one
    memoised count per shared object, so a DAG of shared lists that unfolds to 10^16 nodes
    costs a few operations per distinct list. Cycles are refused."""
    tree_size: dict[int, int] = {}  # id -> unfolded node count, for finished objects
    open_ids: set[int] = set()  # expanded, not finished: the current depth-first path
    stack = [(obj, 0, False)]
    while stack:
        o, depth, finished = stack.pop()
        if isinstance(o, _LEAVES):
            continue
        k = id(o)  # stable: ``obj`` keeps every object alive during the walk
        if finished:
            tree_size[k] = 1 + sum(tree_size.get(id(c), 1) for c in _children(o))
            open_ids.discard(k)
            if tree_size[k] > max_tree_nodes:
                raise UnsafePickleError(
                    f"the pickle's shared references unfold to more than {max_tree_nodes:,} nodes "
                    f"({tree_size[k]:.3g}); allowed: at most {max_tree_nodes:,}"
                )
            continue
        if k in tree_size:
            continue
        if k in open_ids:
            raise UnsafePickleError("the pickle holds a container that contains itself; " + _ALLOWED_WORDS)
        if depth > max_depth:
            raise UnsafePickleError(f"pickle nests containers deeper than {max_depth} levels")
        if isinstance(o, np.ndarray):
            if o.dtype.hasobject:
                raise UnsafePickleError("object arrays are not allowed: only numeric NumPy arrays")
            tree_size[k] = 1
        elif isinstance(o, (dict, list, tuple)):
            if len(tree_size) + len(open_ids) >= max_nodes:
                raise UnsafePickleError(f"the pickle holds more than {max_nodes:,} containers; allowed: fewer")
            open_ids.add(k)
            stack.append((o, depth, True))
            stack.extend((c, depth + 1, False) for c in _children(o))
        else:
            raise UnsafePickleError(f"the pickle holds a {type(o).__name__}; " + _ALLOWED_WORDS)


def restricted_loads(data: bytes, max_array_bytes: int = MAX_ARRAY_BYTES):
    """Unpickle bytes allowing only NumPy arrays inside plain containers, within the bounds
    above; anything else raises :class:`UnsafePickleError` (refused content) or
    ``pickle.UnpicklingError`` (a truncated or corrupt file)."""
    if len(data) > MAX_PICKLE_BYTES:
        raise UnsafePickleError(f"pickle of {len(data):,} bytes; allowed: at most {MAX_PICKLE_BYTES:,}")
    _prescan(data)
    try:
        obj = _RestrictedUnpickler(io.BytesIO(data), max_array_bytes).load()
    except pickle.UnpicklingError:
        raise
    except Exception as err:  # noqa: BLE001 -- a corrupt stream fails in many ways; all mean "bad file"
        raise pickle.UnpicklingError(
            f"not a valid pickle (truncated or corrupt): {type(err).__name__}: {err}"
        ) from None
    _check_no_objects(obj)
    return obj


def restricted_load(path: str | os.PathLike, max_array_bytes: int = MAX_ARRAY_BYTES):
    """Unpickle a file allowing only NumPy arrays; anything else -> :class:`UnsafePickleError`."""
    path = Path(path)
    try:
        size = path.stat().st_size
        if size > MAX_PICKLE_BYTES:
            raise UnsafePickleError(f"{path}: pickle of {size:,} bytes; allowed: at most {MAX_PICKLE_BYTES:,}")
        data = path.read_bytes()
    except OSError as err:
        raise SharedDataMissing(f"cannot read {path}: {err.strerror or err}") from None
    try:
        return restricted_loads(data, max_array_bytes)
    except pickle.UnpicklingError as err:
        raise type(err)(f"{path}: {err}") from None


# -- mass-lift trials ---------------------------------------------------------------------
def _design_of(key: str, where: str) -> Membrane:
    if not isinstance(key, str):
        raise InputError(f"{where}: a design key must be a string, got {type(key).__name__}")
    try:
        return Membrane.from_key(key)
    except DesignError as err:
        raise InputError(f"{where}: {key!r} is not a valid design: {err}") from None


def _rows_of(key, value, where: str) -> int:
    """Rows an entry ``((us, ys), Fs, ws)`` will expand to."""
    try:
        (us, _), _, _ = value
        return len(us)
    except (TypeError, ValueError):
        raise InputError(
            f"{where}: entry {key!r} is not ((us, ys), Fs, ws); allowed: an SPA_Design data dictionary "
            "of design key -> ((us [n, 7], ys [n, 1]), Fs [n, 1], ws [n, 1])"
        ) from None


def checked_entries(data: dict, where: str) -> list[tuple[Membrane, Any]]:
    """The entries of an SPA_Design data dictionary as (design, value), refused in one line
    when two keys spell one design or the entries expand to too many rows.

    Why before any frame is built: entries can share one value through the pickle's memo,
    so a 470 kB file of 2,000 spellings of one key (``2``, ``2.0``, ``+2.0``, ...) over one
    10,000-row value expands to 2e7 rows and gigabytes of frames. Canonical keys make the
    spellings one design; the row count is summed from the entries' lengths alone."""
    seen: dict[str, str] = {}
    out, rows = [], 0
    for key, value in data.items():
        rows += _rows_of(key, value, where)
        check_rows(rows, where)
        design = _design_of(key, where)
        canonical = design.key()
        if canonical in seen:
            raise InputError(
                f"{where}: keys {seen[canonical]!r} and {key!r} are one design {canonical}; "
                "allowed: one entry per membrane"
            )
        seen[canonical] = key
        out.append((design, value))
    return out


def _column(a, n: int, what: str) -> np.ndarray:
    try:
        a = np.asarray(a, dtype=np.float64)
    except (TypeError, ValueError) as err:
        raise InputError(f"mass-lift file: {what} is not a numeric array ({err})") from None
    if a.ndim == 2 and a.shape[1] == 1:
        a = a[:, 0]
    if a.shape != (n,):
        raise InputError(f"mass-lift file: {what} has shape {a.shape}, expected ({n},) or ({n}, 1)")
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
    if not isinstance(data, dict) or not data:
        raise InputError(
            f"{p}: expected a non-empty dict of membranes, got {type(data).__name__} "
            f"of {len(data) if hasattr(data, '__len__') else '?'} entries"
        )
    frames = []
    for design, value in checked_entries(data, str(p)):
        key = design.key()
        try:
            (us, ys), fs, ws = value
        except (TypeError, ValueError):
            raise InputError(f"{p}: entry {key} is not ((us, ys), Fs, ws)") from None
        try:
            us = np.asarray(us, dtype=np.float64)
        except (TypeError, ValueError) as err:
            raise InputError(f"{p}: entry {key}: us is not a numeric array ({err})") from None
        if us.ndim != 2 or us.shape[1] != 7:
            raise InputError(f"{p}: entry {key}: us has shape {us.shape}, expected (n, 7)")
        n = len(us)
        if not np.allclose(us[:, 1:7], design.to_array(), rtol=1e-6, atol=1e-5, equal_nan=True):
            raise InputError(f"{p}: entry {key}: the design columns us[:, 1:7] disagree with the key")
        height = us[:, 0]
        force = _column(fs, n, "Fs")
        frames.append(
            pd.DataFrame(
                {
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
                }
            )
        )
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
        raise InputError(
            f"{where}: the names of entries 1-6 are {keys[:6]}; expected the known upstream "
            f"shift {shifted} (or the corrected {correct}). The file changed: check it by hand."
        )
    return [Membrane.from_key(k) for k in correct + keys[6:]]


def load_sim_planes(path: str | os.PathLike | None = None) -> list[SimPlane]:
    """The authors' 18 simulated planes, heights converted from m to mm, labels fixed."""
    p = _data_file(path, SIM_PLANES_FILE)
    data = restricted_load(p)
    if not isinstance(data, list) or len(data) < 7:
        raise InputError(
            f"{p}: expected a list of at least 7 (name, (F, p, h)), got {type(data).__name__} "
            f"of {len(data) if hasattr(data, '__len__') else '?'} entries"
        )
    names, arrays, rows = [], [], 0
    for i, entry in enumerate(data):
        try:
            name, (f, pr, h) = entry
        except (TypeError, ValueError):
            raise InputError(f"{p}: entry {i + 1} is not (name, (F, p, h))") from None
        try:
            f, pr, h = (np.asarray(a, dtype=np.float64).reshape(-1) for a in (f, pr, h))
        except (TypeError, ValueError) as err:
            raise InputError(f"{p}: entry {i + 1}: F, p, h are not numeric arrays ({err})") from None
        if not (f.shape == pr.shape == h.shape):
            raise InputError(f"{p}: entry {i + 1}: F, p, h lengths {len(f)}, {len(pr)}, {len(h)} differ")
        names.append(str(name))
        arrays.append((f, pr, h * 1e3))  # file: metres -> mm
        rows += len(f)
        check_rows(rows, str(p))  # entries may share one array: bound what they expand to
    designs = _fixed_designs(names, str(p))
    return [SimPlane(d, f, pr, h, label_in_file=n) for d, n, (f, pr, h) in zip(designs, names, arrays)]


def sim_planes_as_measurements(path: str | os.PathLike | None = None) -> Measurements:
    """The simulated planes as Measurements: experiment "force", source "simulated".

    One trial per plane (trial id = plane index 0..17); the set-point equals the height
    (the simulator holds the plate exactly); weight 1 per point; no time stamps.
    """
    frames = []
    for i, plane in enumerate(load_sim_planes(path)):
        frames.append(
            pd.DataFrame(
                {
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
                }
            )
        )
    return Measurements(pd.concat(frames, ignore_index=True))
