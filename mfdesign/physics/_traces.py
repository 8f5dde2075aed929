"""Traced programs kept on disk (``jax.export``), for the next process: the plane solver's
kernels (:func:`compiled`) and the few large programs a run calls once or twice, a MAP
search or an acquisition optimiser (:func:`stored_jit`).

JAX's persistent compilation cache spares a new process XLA's compilation, not the tracing
and lowering that come before it: a warm demo still spent ~23 s there on the solver's
kernels (py-spy, issue 40), and so does every CLI call of a campaign that solves a plane
or a point. :func:`compiled` stores each kernel's exported StableHLO (``Exported.serialize``)
under a key of everything that shapes it, and a later process compiles from the stored
module (a hit in the compilation cache) without tracing the solver at all.

The key holds the exact versions of jax, jaxlib and the solver libraries, a hash of every
mfdesign source file, the argument signature and the settings that change a trace
(``EQX_ON_ERROR``, float64), so a stored kernel is never used by code that would trace it
differently. Only module-level kernels of mfdesign are stored (a closure's captured values
are not in the key). Any failure (no folder, a kernel export refuses, a damaged file) falls
back to tracing as before: the store can only save time.
"""

from __future__ import annotations

import dataclasses
import functools
import hashlib
import importlib.metadata
import io
import json
import logging
import os
import pickle
import types
from pathlib import Path
from typing import Callable

import equinox as eqx
import jax
import jax.numpy as jnp

from mfdesign import outputs

__all__ = ["compiled", "folder", "stored_jit", "stored_shapes"]

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


@functools.cache
def _code() -> str:
    """What every stored kernel depends on beyond its arguments: library versions and the
    bytes of every mfdesign source file."""
    h = hashlib.sha256()
    for name in _VERSIONED:
        try:
            h.update(f"{name}={importlib.metadata.version(name)};".encode())
        except importlib.metadata.PackageNotFoundError:
            h.update(f"{name}=none;".encode())
    package = Path(__file__).resolve().parents[1]
    for path in sorted(package.rglob("*.py")):
        h.update(str(path.relative_to(package)).encode())
        h.update(path.read_bytes())
    return h.hexdigest()


def _storable(kernel: Callable) -> bool:
    module, name = getattr(kernel, "__module__", "") or "", getattr(kernel, "__qualname__", "") or ""
    return module.startswith("mfdesign.") and "<locals>" not in name


def _family(kernel: Callable, static: tuple, tree, signature: tuple) -> str:
    """The key of everything but the arguments' shapes (``signature``: ``(shape, dtype,
    weak_type)`` per leaf): kernels of one family differ only in their batch sizes."""
    parts = (
        kernel.__module__,
        kernel.__qualname__,
        repr(static),
        str(tree),
        repr([kind for _, *kind in signature]),
        os.environ.get("EQX_ON_ERROR"),
        bool(getattr(jax.config, "jax_enable_x64", False)),
        _code(),
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
        listed = json.loads(_shapes_file(where, kernel, static, tree, signature).read_text())
    except (OSError, ValueError):
        return []
    found = []
    for shapes in listed if isinstance(listed, list) else []:
        try:
            shapes = tuple(tuple(int(n) for n in leaf) for leaf in shapes)
        except (TypeError, ValueError):
            continue
        sig = tuple((shape, *kind) for shape, (_, *kind) in zip(shapes, signature))
        if len(shapes) == len(signature) and _module_file(where, kernel, static, tree, sig).exists():
            found.append(shapes)
    return found


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
    return export.export(jax.jit(flat), disabled_checks=checks)(*leaves)


def _read(path: Path):
    from jax import export

    try:
        return export.deserialize(bytearray(path.read_bytes()))
    except FileNotFoundError:
        return None
    except Exception as err:  # noqa: BLE001 -- a damaged or foreign file: trace again, write it anew
        log.debug("stored kernel %s unreadable (%s): traced again", path.name, err)
        return None


def _write(path: Path, exported) -> bool:
    try:
        blob = exported.serialize()
        path.parent.mkdir(parents=True, exist_ok=True)
        outputs.write_bytes(path, blob)  # readers see the whole file or none
        return True
    except Exception as err:  # noqa: BLE001 -- no flatbuffers, a full disk: the run goes on
        log.debug("kernel %s not stored: %s", path.name, err)
        return False


def compiled(kernel: Callable, flat: Callable, leaves: list, static: tuple, tree, signature: tuple):
    """``flat(*leaves)`` (``kernel`` with its arguments flattened, ``static`` bound)
    compiled ahead of time: from the stored export when there is one, else exported (and
    stored) on the way; traced the usual way where the store is off or the export fails."""
    where = folder()
    if where is None or not _storable(kernel):
        return jax.jit(flat).lower(*leaves).compile()

    path = _module_file(where, kernel, static, tree, signature)
    exported = _read(path)
    if exported is None:
        try:
            exported = _export(flat, leaves)
        except Exception as err:  # noqa: BLE001 -- e.g. a host callback: compile as before
            log.debug("kernel %s not exported (%s): compiled directly", kernel.__name__, err)
            return jax.jit(flat).lower(*leaves).compile()
        if _write(path, exported):
            _list_shapes(where, kernel, static, tree, signature)

    def call(*xs):
        return exported.call(*xs)

    call.__name__ = kernel.__name__  # the program's name in logs (profile_compile reads them)
    return jax.jit(call).lower(*leaves).compile()


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

    def reducer_override(self, obj):
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


def _key_bytes(obj) -> bytes:
    buffer = io.BytesIO()
    _KeyPickler(buffer, protocol=4).dump(obj)
    return buffer.getvalue()


_EXPORT_FAILED: set = set()  # stored_jit functions export refused in this process: plain filter_jit since
_PROGRAMS: dict = {}  # stored_jit: key -> jax.jit(Exported.call), for this process


def stored_jit(fn: Callable) -> Callable:
    """``eqx.filter_jit(fn)``, its traced program also kept on disk for the next process.

    For a module-level function of mfdesign that a run calls a few times with large
    programs (a MAP search, an acquisition optimiser, a batch of least-squares fits): the
    persistent compilation cache spares a warm run their compilation, not their tracing
    and lowering (~16 s of a warm demo's ~28 s, issue 40; optimistix and optax trace slowly).
    With the store on (:func:`folder`), a call exports ``fn`` on its arguments' signature
    (``jax.export``), stores it, and a later process calls the stored module instead,
    compiled from the compilation cache, without tracing ``fn``.

    The key holds the library versions and mfdesign's sources (as :func:`compiled`), and
    the pickled bytes of every argument with each array replaced by its shape and type:
    equal bytes, equal static values (a float, a string, an eqx.Module's static fields,
    a module-level function by its name). A call falls back to the plain filter_jit call
    where the store is off, an argument does not pickle (a lambda, a closure: its captured
    values would not be in the key), the call is under a trace (tracers), the process has
    several devices, or export refuses ``fn`` (a host callback). Not for a function called
    every MCMC step: pickling its arguments each call would cost more than it saves."""
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
            blob = _key_bytes(eqx.combine(jax.tree.unflatten(tree, avals), static))
        except Exception as err:  # noqa: BLE001 -- a lambda, a closure, a lock: not keyable, traced as usual
            log.debug("%s not stored: arguments have no key (%s)", fn.__qualname__, err)
            return jitted(*args, **kwargs)
        parts = (fn.__module__, fn.__qualname__, os.environ.get("EQX_ON_ERROR"), bool(jax.config.jax_enable_x64))
        key = hashlib.sha256(repr(parts).encode() + blob + _code().encode()).hexdigest()[:40]
        program = _PROGRAMS.get(key)
        if program is None:
            path = where / f"{fn.__name__}-{key}{SUFFIX}"
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
                _write(path, exported)
            program = _PROGRAMS[key] = jax.jit(exported.call)
        return program(*leaves)

    call.jitted = jitted  # type: ignore[attr-defined]  # the plain program (tests count its compilations)
    return call
