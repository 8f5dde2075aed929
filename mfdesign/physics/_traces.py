"""Traced programs kept on disk (``jax.export``), for the next process: the plane solver's
kernels (:func:`compiled`) and the few large programs a run calls once or twice, a MAP
search or an acquisition optimiser (:func:`stored_jit`).

JAX's persistent compilation cache spares a new process XLA's compilation, not the tracing
and lowering that come before it: a warm demo still spent ~23 s there on the solver's
kernels (py-spy, issue 40), and so does every CLI call of a campaign that solves a plane
or a point. :func:`compiled` stores each kernel's exported StableHLO (``Exported.serialize``)
under a key of everything that shapes it, and a later process compiles from the stored
module (a hit in the compilation cache) without tracing the solver at all.

The key holds the exact versions of jax, jaxlib and the solver libraries, the platform, a
hash of the code of the mfdesign sources the kernel's module and its arguments' classes
import (transitively; comments and docstrings aside: :func:`_code`), the argument signature
and the settings that change a trace (``EQX_ON_ERROR``, float64), so a stored kernel is
never used by code that would trace it differently (a lab's own effect file,
:mod:`mfdesign.user_effects`, is keyed by its code too). Only module-level kernels of
mfdesign are stored (a closure's captured values are not in the key). The demo's kernels
also ship in the package (:data:`SHIPPED_NAME`). Any failure (no folder, a kernel export refuses, a damaged file) falls
back to tracing as before: the store can only save time.

A run that calls the same kernels in the same order every time (the default demo) stores
that order as a plan (:data:`USED`, :func:`write_plan`; the pack ships the demo's), and the
next run on an empty compilation cache compiles the plan's kernels on a background thread
while it works (:func:`compile_ahead`; a caller waits for, or cancels, its own kernel).
"""

from __future__ import annotations

import ast
import concurrent.futures
import dataclasses
import functools
import hashlib
import importlib.metadata
import io
import json
import logging
import os
import pickle
import sys
import threading
import types
from pathlib import Path
from typing import Callable

import equinox as eqx
import jax
import jax.numpy as jnp
import numpy as np

from mfdesign import outputs

__all__ = [
    "COUNTS",
    "cancel_ahead",
    "compile_ahead",
    "compiled",
    "environment",
    "folder",
    "stale_shipped",
    "stored_jit",
    "stored_shapes",
    "write_plan",
]

log = logging.getLogger(__name__)

# lineax's QR (inside Levenberg-Marquardt) applies its reflectors with LAPACK's ormqr, a
# custom call whose format JAX does not guarantee across versions. Stored kernels run only
# on the jaxlib that wrote them (the key holds its version), so the guarantee is not needed.
UNGUARANTEED_CALLS = ("lapack_dormqr_ffi",)
_VERSIONED = ("jax", "jaxlib", "equinox", "diffrax", "optimistix", "lineax", "optax", "numpy", "flatbuffers")
SUFFIX = ".jaxexport"


def folder() -> Path | None:
    """``$MFDESIGN_CACHE_DIR/kernels`` (default ``~/.cache/mfdesign/kernels``) when JAX's
    persistent compilation cache is on (:func:`mfdesign._cache.enable_compilation_cache`:
    the CLI and the scripts) and equinox's runtime checks are NaN (a host callback cannot be
    exported); None otherwise (a library call, a test: nothing written)."""
    if not _compilation_cache_dir() or os.environ.get("EQX_ON_ERROR") != "nan":
        return None
    root = os.environ.get("MFDESIGN_CACHE_DIR")
    return (Path(root) if root else Path.home() / ".cache" / "mfdesign") / "kernels"


def _compilation_cache_dir() -> str | None:
    return getattr(jax.config, "jax_compilation_cache_dir", None)


_PACKAGE = Path(__file__).resolve().parents[1]  # the mfdesign package folder


def _source(module: str) -> Path | None:
    """The source file of mfdesign module ``module`` (``a.b`` -> ``a/b.py`` or ``a/b/__init__.py``), or None."""
    parts = module.split(".")
    if parts[0] != "mfdesign":
        return None
    base = _PACKAGE.joinpath(*parts[1:])
    for path in (base.with_suffix(".py"), base / "__init__.py"):
        if path.is_file():
            return path
    return None


@functools.cache
def _imports(module: str) -> frozenset[str]:
    """The mfdesign modules that ``module``'s source imports anywhere (function-level and
    ``TYPE_CHECKING`` imports too: more than it runs, never less), read from its syntax."""
    path = _source(module)
    if path is None or module == "mfdesign":
        # the package's __init__ is a lazy facade (names imported on first use): what its
        # functions import runs only where they are called, never inside a kernel
        return frozenset()
    package = module if path.name == "__init__.py" else module.rpartition(".")[0]
    found: set[str] = set()
    with _PARSE:
        tree = ast.parse(path.read_bytes())
    for node in ast.walk(tree):
        if isinstance(node, ast.Import):
            found.update(alias.name for alias in node.names)
        elif isinstance(node, ast.ImportFrom):
            base = node.module or ""
            if node.level:  # relative: from the package, up level - 1 packages
                up = package.split(".")[: len(package.split(".")) - node.level + 1]
                base = ".".join(up + ([base] if base else []))
            found.add(base)  # its __init__ runs
            found.update(f"{base}.{alias.name}" for alias in node.names)  # a submodule, where one is named
    return frozenset(name for name in found if _source(name) is not None)


def _closure(roots) -> list[Path]:
    """Source files of the mfdesign modules ``roots`` and of everything they import, transitively."""
    seen: set[str] = set()
    todo = [m for m in roots if _source(m) is not None]
    while todo:
        module = todo.pop()
        if module not in seen:
            seen.add(module)
            todo.extend(_imports(module) - seen)
    return sorted({p for p in map(_source, seen) if p is not None})


def environment() -> dict[str, str]:
    """What a kernel's key holds besides mfdesign's code: the libraries' versions and Python's
    (``tools.ship_kernels`` records it beside the pack)."""
    out = {}
    for name in _VERSIONED:
        try:
            out[name] = importlib.metadata.version(name)
        except importlib.metadata.PackageNotFoundError:
            out[name] = "none"
    return out | {"python": f"{sys.version_info[0]}.{sys.version_info[1]}"}


# CPython 3.11's ast.parse is not thread-safe ("AST constructor recursion depth mismatch"
# when two threads parse at once: seen with the plane solves' threads keying the solver's
# kernels together, bench_round22 in session 40). Every parse here runs under this lock.
_PARSE = threading.Lock()


@functools.cache
def _code(roots: frozenset[str]) -> str:
    """What a stored kernel depends on beyond its arguments: library versions and the bytes
    of the mfdesign sources its module and its arguments' classes import, transitively.
    Imports flow downstream (design -> physics -> models -> ...), so an edit of the CLI, the
    report or a workflow keeps the solver's kernels (and the shipped ones) valid, and an
    edit of anything a kernel could run retraces it."""
    h = hashlib.sha256()
    for name, version in environment().items():  # python: its syntax tree's layout
        h.update(f"{name}={version};".encode())
    for path in _closure(roots):
        h.update(str(path.relative_to(_PACKAGE)).encode())
        h.update(_digest(path))
    for name in sorted(r for r in roots if r.startswith(USER_MODULES)):  # a lab's own effect file
        file = getattr(sys.modules.get(name), "__file__", None)
        h.update(name.encode() + (_digest(Path(file)) if file and Path(file).is_file() else b"?"))
    return h.hexdigest()


# What mfdesign.user_effects names the modules it loads from a lab's files: their code keys
# the kernels their effects run in, as mfdesign's own sources do.
USER_MODULES = "mfdesign_user_effects_"


@functools.cache
def _digest(path: Path) -> bytes:
    """A source file's code without its comments and docstrings (its syntax tree, dumped):
    an edit of either traces nothing anew, and leaves the shipped kernels valid."""
    with _PARSE:
        tree = ast.parse(path.read_bytes())
    for node in ast.walk(tree):
        body = getattr(node, "body", None)
        if (
            isinstance(node, (ast.Module, ast.ClassDef, ast.FunctionDef, ast.AsyncFunctionDef))
            and body
            and isinstance(body[0], ast.Expr)
            and isinstance(body[0].value, ast.Constant)
            and isinstance(body[0].value.value, str)
        ):
            node.body = body[1:] or [ast.Pass()]
    with _PARSE:
        dumped = ast.dump(tree)
    return hashlib.sha256(dumped.encode()).digest()


def _storable(kernel: Callable) -> bool:
    module, name = getattr(kernel, "__module__", "") or "", getattr(kernel, "__qualname__", "") or ""
    return module.startswith("mfdesign.") and "<locals>" not in name


def _roots(kernel: Callable, *material) -> frozenset[str]:
    """The modules whose sources (and their imports) key ``kernel`` called on ``material``:
    its own module and those of the classes and functions in it; every mfdesign module where
    the material does not pickle (nothing left out of the key)."""
    try:
        return _key_bytes(material)[1] | {kernel.__module__}
    except Exception:  # noqa: BLE001 -- e.g. a closure among the static arguments
        return frozenset(
            "mfdesign." + ".".join(p.relative_to(_PACKAGE).with_suffix("").parts).removesuffix(".__init__")
            for p in _PACKAGE.rglob("*.py")
        )


def _family(kernel: Callable, static: tuple, tree, signature: tuple) -> str:
    """The key of everything but the arguments' shapes (``signature``: ``(shape, dtype,
    weak_type)`` per leaf): kernels of one family differ only in their batch sizes."""
    avals = [_Aval(tuple(shape), str(dtype), bool(weak)) for shape, dtype, weak in signature]
    parts = (
        kernel.__module__,
        kernel.__qualname__,
        repr(static),
        str(tree),
        repr([kind for _, *kind in signature]),
        os.environ.get("EQX_ON_ERROR"),
        bool(getattr(jax.config, "jax_enable_x64", False)),
        jax.default_backend(),  # an export runs only on the platform it was lowered for
        _code(_roots(kernel, static, jax.tree.unflatten(tree, avals))),
    )
    return hashlib.sha256(repr(parts).encode()).hexdigest()[:24]


def _key(kernel: Callable, static: tuple, tree, signature: tuple) -> str:
    shapes = repr([shape for shape, *_ in signature])
    return _family(kernel, static, tree, signature) + hashlib.sha256(shapes.encode()).hexdigest()[:16]


def _module_file(where: Path, kernel: Callable, static: tuple, tree, signature: tuple) -> Path:
    return where / f"{kernel.__name__}-{_key(kernel, static, tree, signature)}{SUFFIX}"


def _shapes_file(where: Path, kernel: Callable, static: tuple, tree, signature: tuple) -> Path:
    return where / f"{kernel.__name__}-{_family(kernel, static, tree, signature)}.shapes.json"


def stored_shapes(kernel: Callable, static: tuple, tree, signature: tuple) -> list[tuple]:
    """The leaf shapes of the stored kernels of ``kernel``'s family (same code, static
    arguments, tree and types): what a padded call may run on without tracing
    (:meth:`~mfdesign.physics.solve.KeptPrograms.holders`). Empty where the store is off."""
    where = folder()
    if where is None or not _storable(kernel):
        return []
    try:
        path = _shapes_file(where, kernel, static, tree, signature)
    except Exception as err:  # noqa: BLE001 -- no key (a source unreadable): nothing stored to offer
        log.debug("kernel %s has no key (%s)", kernel.__name__, err)
        return []
    listed = []
    for text in (_text(path), _shipped(path.name)):
        try:
            more = json.loads(text) if text else []
        except ValueError:
            continue
        listed += [shapes for shapes in more if shapes not in listed] if isinstance(more, list) else []
    found = []
    for shapes in listed:
        try:
            shapes = tuple(tuple(int(n) for n in leaf) for leaf in shapes)
        except (TypeError, ValueError):
            continue
        sig = tuple((shape, *kind) for shape, (_, *kind) in zip(shapes, signature))
        if len(shapes) == len(signature):
            module = _module_file(where, kernel, static, tree, sig)
            if module.exists() or _shipped(module.name) is not None:
                found.append(shapes)
    return found


def _text(path: Path) -> str | None:
    try:
        return path.read_text()
    except OSError:
        return None


def _list_shapes(where: Path, kernel: Callable, static: tuple, tree, signature: tuple) -> None:
    """Add a stored kernel's leaf shapes to its family's list (a lost race drops an entry:
    that kernel is then only found by its own signature)."""
    path = _shapes_file(where, kernel, static, tree, signature)
    try:
        listed = json.loads(path.read_text())
        listed = listed if isinstance(listed, list) else []
    except (OSError, ValueError):
        listed = []
    shapes = [list(shape) for shape, *_ in signature]
    if shapes in listed:
        return
    try:
        outputs.write_json(path, listed + [shapes], indent=None)
    except OSError as err:
        log.debug("shapes of %s not listed: %s", path.name, err)


def _export(flat: Callable, leaves: list):
    """``flat`` traced on ``leaves`` and exported (the custom calls of
    :data:`UNGUARANTEED_CALLS` allowed: the key pins the jaxlib that runs them)."""
    from jax import export

    checks = [export.DisabledSafetyCheck.custom_call(name) for name in UNGUARANTEED_CALLS]
    exported = export.export(jax.jit(flat), disabled_checks=checks)(*leaves)
    COUNTS["traced"] += 1
    return exported


# The kernels a cold demo (full and --quick) stores, shipped in the package as they were
# exported (``python -m tools.ship_kernels``): a lab's first demo then traces none of them
# (their tracing was ~38 s of a cold demo on 2 cores, experiments/profile_callers.py --full
# on 6b24fdf, issue 40); XLA still compiles each once. Keyed like the
# store (the file names), so a kernel whose code, arguments or libraries changed is traced
# as before: a stale pack costs time, never a wrong program. Read where the store is on and
# the user's folder lacks the file; "0" here turns it off.
SHIPPED_ENV = "MFDESIGN_SHIPPED_KERNELS"
SHIPPED_NAME = "kernels.npz"


@functools.cache
def _shipped_pack() -> dict[str, bytes]:
    """The shipped kernels (file name -> bytes), read whole once; empty where missing or unreadable."""
    from mfdesign.data.shipped import shipped_path

    try:
        with np.load(shipped_path(SHIPPED_NAME), allow_pickle=False) as pack:
            return {name: pack[name].tobytes() for name in pack.files}
    except (OSError, ValueError) as err:
        log.debug("shipped kernels unreadable (%s): every kernel is traced", err)
        return {}


def _shipped(name: str) -> bytes | None:
    """The shipped file ``name`` (a kernel or a family's shapes), or None (not shipped, or
    ``$MFDESIGN_SHIPPED_KERNELS=0``)."""
    if os.environ.get(SHIPPED_ENV, "1").strip() == "0":
        return None
    return _shipped_pack().get(name)


# This process's kernels by where they came from: "stored" (the user's store), "shipped"
# (the package's pack), "traced" (exported anew). The demo's summary.json holds them, so a
# stale pack shows as kernels traced in a cold run (bench_demo.py prints them).
COUNTS = {"stored": 0, "shipped": 0, "traced": 0}


# XLA's CPU compiler options by kind of stored program. Without XLA's newer fusion
# emitters, programs compile in about half the time and run as fast (the MAP kernel 18.0 ->
# 10.2 s of XLA, the diagnosis' least-squares fits 11.0 -> 7.1 s; 8 planes at 1.76 s each
# either way, equal to 6e-12 N of 460 N; session 43). LLVM's optimisation level 1 instead
# of XLA's default cuts another 7-37 % at about the same time a call (the MAP kernel +12 %,
# one simulator draw 0.19 -> 0.28 s) for the programs that are loops of small dense maths and
# control flow: the diagnosis' fits, the MAP search, the design searches, the simulator
# draws ("jit-fast"; session 45, the quick demo's stored
# programs on their recorded arguments, `experiments/bench_compile_options.py`: 52.5 s of
# XLA all default, 46.4 s with session 44's choice, 38.4 s with these). Not for:
# - the solver's kernels ("kernel"): level 1 walks ~15 % slower (0.42 -> 0.48 s a call),
#   and the planes are most of a campaign's round;
# - the ensembles' forward passes ("jit": `_predict`, `_delta_draws`): 1.7-2.1 x slower a
#   call without the emitters (set for every program by XLA_FLAGS, a quick demo's propose
#   and optimise ran 2.5-3.6 x slower, session 43).
# The options are part of a program's key in the compilation cache, so a kernel compiled
# ahead (:func:`_compiled_as`) is compiled with its caller's.
OPTIONS: dict[str, dict | None] = {
    "kernel": {"xla_cpu_use_fusion_emitters": False},
    "jit-fast": {"xla_cpu_use_fusion_emitters": False, "xla_backend_optimization_level": 1},
    "jit": None,
}


def _options(kind: str) -> dict | None:
    """The compiler options of a stored program of ``kind`` (:data:`USED`)."""
    return OPTIONS[kind]


# This process's kernels in the order it first called them: (file name, kind), kind
# "kernel" (the solver's, :func:`compiled`), "jit" or "jit-fast" (:func:`stored_jit`,
# compiled with :data:`OPTIONS` of their kind). A run that is
# the same every time (the demo at its default settings) stores them as its plan
# (:func:`write_plan`), from which its next cold run compiles ahead (:func:`compile_ahead`).
USED: list[tuple[str, str]] = []
PLAN_SUFFIX = ".plan.json"
# compile_ahead's work: kernel file name -> Future (True: compiled into the compilation cache)
_AHEAD: dict[str, concurrent.futures.Future] = {}


def _used(name: str, kind: str) -> None:
    if (name, kind) not in USED:
        USED.append((name, kind))


def _blob(name: str) -> bytes | None:
    """The bytes of the stored file ``name``: the user's store, else the shipped pack (None:
    neither has it)."""
    where = folder()
    if where is not None:
        try:
            return (where / name).read_bytes()
        except OSError:
            pass
    return _shipped(name)


def write_plan(plan: str) -> None:
    """Store :data:`USED` as the plan ``plan`` (``NAME.plan.json`` in the kernel store; the
    pack ships the demo's, ``tools.ship_kernels``). Nothing where the store is off. The
    store's folder is made first: a cold run that read every kernel from the pack stored
    none, and had no folder yet."""
    where = folder()
    if where is not None and USED:
        try:
            where.mkdir(parents=True, exist_ok=True)
            outputs.write_json(where / f"{plan}{PLAN_SUFFIX}", USED, indent=None)
        except OSError as err:  # a full disk: the next run compiles as it goes
            log.debug("plan %s not stored: %s", plan, err)


def compile_ahead(plan: str) -> int:
    """Compile the kernels of the plan ``plan`` (:func:`write_plan`) on one background
    thread, in the order that run first called them, into the persistent compilation cache,
    while this run works on the others.

    Why: a cold demo waits ~77 s (of ~180 s, --quick) for XLA to compile its 17 stored
    kernels, one at a time, while a core is idle (CPU 1.3 x wall; profile_compile.py,
    session 41). Compiled ahead, each caller finds its program in the compilation cache
    (the same program, named alike) and loads it. The programs themselves are not kept:
    held until called, the full demo's 18 took ~0.38 GB (session 41). A caller of a kernel
    still queued cancels it and compiles it itself (waiting would also wait for the queue
    before it); a caller of one being compiled waits for it (:func:`_wait_ahead`). The
    store must be on (:func:`folder`, which needs the compilation cache), and a plan's
    names that neither the store nor the pack holds are skipped. Returns the number of
    kernels queued; :func:`cancel_ahead` drops what is left."""
    if folder() is None or len(jax.local_devices()) > 1:
        return 0
    blob = _blob(plan + PLAN_SUFFIX)
    try:
        entries = [(str(n), str(k)) for n, k in json.loads(blob or b"[]")]
    except (ValueError, TypeError):
        return 0
    if not entries:
        return 0
    pool = concurrent.futures.ThreadPoolExecutor(
        1, thread_name_prefix="mfdesign-compile-ahead", initializer=_lowest_priority
    )
    queued = 0
    for name, kind in entries:
        if name not in _AHEAD:
            _AHEAD[name] = pool.submit(_compile_one, name, kind)
            queued += 1
    pool.shutdown(wait=False)  # its thread ends with the queue
    return queued


def _lowest_priority() -> None:
    """This thread at the lowest CPU priority (Linux: a thread's nice value is its own):
    its own work (deserialising, lowering) yields to the run's. XLA's compilation itself
    runs on jaxlib's compile threads, at their priority, not this one's (a big compile
    beside a main thread: the nice-19 thread 4 CPU ticks, three native threads 190-530,
    session 43), so compiling ahead still competes with the run for the CPU."""
    try:
        os.setpriority(os.PRIO_PROCESS, threading.get_native_id(), 19)
    except (AttributeError, OSError):  # not Linux, or not allowed: the default priority
        pass


def _compile_one(name: str, kind: str) -> bool:
    """Compile the stored kernel ``name`` as its caller would (the same program, named
    alike, so the compilation cache holds it for the caller); False where it is missing."""
    from jax import export

    from mfdesign._memory import malloc_trim

    blob = _blob(name)
    if blob is None:
        return False
    exported = export.deserialize(bytearray(blob))
    fn = exported.call
    if kind == "kernel":  # as compiled() names it

        def fn(*xs):
            return exported.call(*xs)

        fn.__name__ = name.split("-")[0]
    avals = [jax.ShapeDtypeStruct(a.shape, a.dtype, weak_type=a.weak_type) for a in exported.in_avals]
    _compiled_as(kind, fn, avals)
    # this thread's heap arena keeps what XLA freed: given back, as release_memory does
    # for the main thread's
    malloc_trim()
    return True


def _wait_ahead(name: str) -> None:
    """Before kernel ``name`` is compiled by its caller: wait while it is being compiled
    ahead (the caller then loads it from the compilation cache); cancel it while queued."""
    job = _AHEAD.pop(name, None)
    if job is None or job.cancel():
        return
    try:
        job.result()
    except Exception as err:  # noqa: BLE001 -- compiled by the caller instead
        log.debug("kernel %s not compiled ahead: %s", name, err)


def cancel_ahead() -> None:
    """Drop the kernels queued by :func:`compile_ahead` and not called (the one compiling finishes)."""
    while _AHEAD:
        _, job = _AHEAD.popitem()
        job.cancel()


def stale_shipped() -> list[str]:
    """The shipped kernels whose sources changed since they were packed (their
    ``.roots.json`` hash differs from today's, or is missing): each is traced again in a
    cold run until ``python -m tools.ship_kernels`` packs it anew."""
    pack = _shipped_pack()
    stale = []
    for name in sorted(n for n in pack if n.endswith(SUFFIX)):
        try:
            meta = json.loads(pack[name.removesuffix(SUFFIX) + ROOTS_SUFFIX])
            current = meta["code"] == _code(frozenset(meta["roots"]))
        except (KeyError, ValueError, TypeError):
            current = False
        if not current:
            stale.append(name)
    return stale


def _read(path: Path):
    from jax import export

    origin = "stored"
    blob: bytes | None
    try:
        blob = path.read_bytes()
    except FileNotFoundError:
        blob, origin = _shipped(path.name), "shipped"
        if blob is None:
            return None
    try:
        exported = export.deserialize(bytearray(blob))
        COUNTS[origin] += 1
        return exported
    except Exception as err:  # noqa: BLE001 -- a damaged or foreign file: trace again, write it anew
        log.debug("stored kernel %s unreadable (%s): traced again", path.name, err)
        return None


ROOTS_SUFFIX = ".roots.json"


def _roots_file(path: Path) -> Path:
    return path.with_name(path.name.removesuffix(SUFFIX) + ROOTS_SUFFIX)


def _write(path: Path, exported, roots: frozenset[str]) -> bool:
    """Store ``exported`` at ``path``, and beside it the modules whose sources key it and
    their hash (``.roots.json``: what :func:`stale_shipped` checks a shipped kernel by)."""
    try:
        blob = exported.serialize()
        path.parent.mkdir(parents=True, exist_ok=True)
        outputs.write_bytes(path, blob)  # readers see the whole file or none
        outputs.write_json(_roots_file(path), {"roots": sorted(roots), "code": _code(roots)}, indent=None)
        return True
    except Exception as err:  # noqa: BLE001 -- no flatbuffers, a full disk: the run goes on
        log.debug("kernel %s not stored: %s", path.name, err)
        return False


def plan_stored(plan: str) -> bool:
    """Whether an earlier run stored the kernel plan ``plan`` in this kernel store (its
    programs then sit in the compilation cache), or the store is off."""
    store = folder()
    return store is None or (store / f"{plan}{PLAN_SUFFIX}").is_file()


def _compiled_as(kind: str, fn: Callable, args: list):
    """``fn`` compiled for ``args`` (arrays or shapes) with the options of ``kind``
    (:func:`_options`): the solver's kernels here, and a plan's kernels compiled ahead
    with their caller's options (the compilation cache keys them)."""
    return jax.jit(fn, compiler_options=_options(kind)).lower(*args).compile()


def _lazy_program(kind: str, fn: Callable) -> Callable:
    """``fn`` jitted with the options of ``kind``, compiled at its first call (a stored
    module's ``Exported.call``: :func:`stored_jit`)."""
    return jax.jit(fn, compiler_options=_options(kind))


def compiled(kernel: Callable, flat: Callable, leaves: list, static: tuple, tree, signature: tuple):
    """``flat(*leaves)`` (``kernel`` with its arguments flattened, ``static`` bound)
    compiled ahead of time: from the stored export when there is one, else exported (and
    stored) on the way; traced the usual way where the store is off or the export fails."""
    where = folder()
    if where is None or not _storable(kernel):
        return _compiled_as("kernel", flat, leaves)

    try:
        path = _module_file(where, kernel, static, tree, signature)
    except Exception as err:  # noqa: BLE001 -- no key (a source unreadable): compile as before
        log.debug("kernel %s has no key (%s): compiled directly", kernel.__name__, err)
        return _compiled_as("kernel", flat, leaves)
    _used(path.name, "kernel")
    _wait_ahead(path.name)
    exported = _read(path)
    if exported is None:
        try:
            exported = _export(flat, leaves)
        except Exception as err:  # noqa: BLE001 -- e.g. a host callback: compile as before
            log.debug("kernel %s not exported (%s): compiled directly", kernel.__name__, err)
            return _compiled_as("kernel", flat, leaves)
        avals = [_Aval(tuple(shape), str(dtype), bool(weak)) for shape, dtype, weak in signature]
        if _write(path, exported, _roots(kernel, static, jax.tree.unflatten(tree, avals))):
            _list_shapes(where, kernel, static, tree, signature)

    def call(*xs):
        return exported.call(*xs)

    call.__name__ = kernel.__name__  # the program's name in logs (profile_compile reads them)
    return _compiled_as("kernel", call, leaves)


@dataclasses.dataclass(frozen=True)
class _Aval:
    """An array argument in :func:`stored_jit`'s key: its shape and type, not its values."""

    shape: tuple
    dtype: str
    weak_type: bool


def _named(*identity) -> None:
    """What :class:`_KeyPickler` writes in a function's place, with the function's identity
    as its arguments (never called: the key's bytes are only compared)."""


class _KeyPickler(pickle.Pickler):
    """Pickles :func:`stored_jit`'s key material: a module-level function by its module and
    name (as pickle does), a jitted one (``jnp.tanh`` is a ``PjitFunction``, which pickle
    refuses) by the function it wraps, a module-level lambda by its code and constants; a
    closure or a local function refuses, as its captured values would not be in the key."""

    def __init__(self, *args, **kwargs) -> None:
        super().__init__(*args, **kwargs)
        self.modules: set[str] = set()  # of every class and function met (the key's sources: _code)

    def reducer_override(self, obj):
        owner = obj if isinstance(obj, (type, types.FunctionType)) else type(obj)
        self.modules.add(getattr(owner, "__module__", None) or "")
        wrapped = getattr(obj, "__wrapped__", None)
        if isinstance(wrapped, types.FunctionType):
            self.modules.add(wrapped.__module__ or "")
        inner = getattr(obj, "__wrapped__", None) if callable(obj) and not isinstance(obj, type) else None
        if obj is _named or (not isinstance(obj, types.FunctionType) and not isinstance(inner, types.FunctionType)):
            return NotImplemented
        fn = obj if isinstance(obj, types.FunctionType) else inner
        if "<locals>" in fn.__qualname__ or fn.__closure__:
            raise pickle.PicklingError(f"{fn.__qualname__}: a closure or local function has no stable key")
        if fn.__name__ == "<lambda>":
            # a module-level lambda (equinox's MLP keeps one as its default final
            # activation) has no name to be found by: its code and constants are the key
            code = fn.__code__
            consts = tuple(c for c in code.co_consts if not isinstance(c, types.CodeType))
            return _named, ("lambda", fn.__module__, code.co_code, consts, code.co_names, fn.__defaults__)
        # by module and name, as pickle does, but also where that name now holds a wrapper
        # of it (jax.nn.relu: the module's attribute is the jitted function)
        return _named, ("function", fn.__module__, fn.__qualname__)


def _key_bytes(obj) -> tuple[bytes, frozenset[str]]:
    """``obj`` pickled as key material, and the modules of its classes and functions."""
    buffer = io.BytesIO()
    pickler = _KeyPickler(buffer, protocol=4)
    pickler.dump(obj)
    return buffer.getvalue(), frozenset(pickler.modules)


_EXPORT_FAILED: set = set()  # stored_jit functions export refused in this process: plain filter_jit since
_PROGRAMS: dict = {}  # stored_jit: key -> jax.jit(Exported.call), for this process


def stored_jit(fn: Callable | None = None, *, fast_compile: bool = False) -> Callable:
    """``eqx.filter_jit(fn)``, its traced program also kept on disk for the next process.
    ``@stored_jit(fast_compile=True)``: the stored program is compiled with
    ``OPTIONS["jit-fast"]`` (for programs whose compilation outweighs the emitters' and
    LLVM's full optimisation: not an ensemble's forward pass, :data:`OPTIONS`).

    For a module-level function of mfdesign that a run calls a few times with large
    programs (a MAP search, an acquisition optimiser, a batch of least-squares fits): the
    persistent compilation cache spares a warm run their compilation, not their tracing
    and lowering (~16 s of a warm demo's ~28 s, issue 40; optimistix and optax trace slowly).
    With the store on (:func:`folder`), a call exports ``fn`` on its arguments' signature
    (``jax.export``), stores it, and a later process calls the stored module instead,
    compiled from the compilation cache, without tracing ``fn``.

    The key holds the library versions and the code of the sources it imports (as :func:`compiled`), and
    the pickled bytes of every argument with each array replaced by its shape and type:
    equal bytes, equal static values (a float, a string, an eqx.Module's static fields,
    a module-level function by its name). A call falls back to the plain filter_jit call
    where the store is off, an argument does not pickle (a lambda, a closure: its captured
    values would not be in the key), the call is under a trace (tracers), the process has
    several devices, or export refuses ``fn`` (a host callback). Not for a function called
    every MCMC step: pickling its arguments each call would cost more than it saves."""
    if fn is None:
        return functools.partial(stored_jit, fast_compile=fast_compile)
    kind = "jit-fast" if fast_compile else "jit"
    jitted = eqx.filter_jit(fn)

    @functools.wraps(fn)
    def call(*args, **kwargs):
        where = folder()
        # several devices: arguments may carry shardings an exported module would not match
        if where is None or fn in _EXPORT_FAILED or not _storable(fn) or len(jax.local_devices()) > 1:
            return jitted(*args, **kwargs)
        dynamic, static = eqx.partition((args, kwargs), eqx.is_array)
        leaves, tree = jax.tree.flatten(dynamic)
        if any(isinstance(x, jax.core.Tracer) for x in leaves):
            return jitted(*args, **kwargs)
        leaves = [jnp.asarray(x) for x in leaves]
        avals = [_Aval(tuple(x.shape), str(x.dtype), bool(getattr(x, "weak_type", False))) for x in leaves]
        try:
            blob, modules = _key_bytes(eqx.combine(jax.tree.unflatten(tree, avals), static))
            roots = modules | {fn.__module__}
            code = _code(roots)
        except Exception as err:  # noqa: BLE001 -- a lambda, a closure, a lock: not keyable, traced as usual
            log.debug("%s not stored: arguments have no key (%s)", fn.__qualname__, err)
            return jitted(*args, **kwargs)
        parts = (
            fn.__module__,
            fn.__qualname__,
            os.environ.get("EQX_ON_ERROR"),
            bool(jax.config.jax_enable_x64),
            jax.default_backend(),  # an export runs only on the platform it was lowered for
        )
        key = hashlib.sha256(repr(parts).encode() + blob + code.encode()).hexdigest()[:40]
        program = _PROGRAMS.get(key)
        if program is None:
            path = where / f"{fn.__name__}-{key}{SUFFIX}"
            _used(path.name, kind)
            _wait_ahead(path.name)
            exported = _read(path)
            if exported is None:

                def flat(*xs):
                    a, k = eqx.combine(jax.tree.unflatten(tree, xs), static)
                    return fn(*a, **k)

                try:
                    exported = _export(flat, leaves)
                except Exception as err:  # noqa: BLE001 -- e.g. a host callback: traced as usual from now on
                    log.debug("%s not exported (%s): plain jit", fn.__qualname__, err)
                    _EXPORT_FAILED.add(fn)
                    return jitted(*args, **kwargs)
                _write(path, exported, roots)
            program = _PROGRAMS[key] = _lazy_program(kind, exported.call)
        return program(*leaves)

    call.jitted = jitted  # type: ignore[attr-defined]  # the plain program (tests count its compilations)
    return call
