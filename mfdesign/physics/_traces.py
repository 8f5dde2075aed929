"""The plane solver's traced kernels kept on disk (``jax.export``), for the next process.

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

import functools
import hashlib
import importlib.metadata
import json
import logging
import os
from pathlib import Path
from typing import Callable

import jax

from mfdesign import outputs

__all__ = ["compiled", "folder", "stored_shapes"]

log = logging.getLogger(__name__)

# lineax's QR (inside Levenberg-Marquardt) applies its reflectors with LAPACK's ormqr, a
# custom call whose format JAX does not guarantee across versions. Stored kernels run only
# on the jaxlib that wrote them (the key holds its version), so the guarantee is not needed.
UNGUARANTEED_CALLS = ("lapack_dormqr_ffi",)
_VERSIONED = ("jax", "jaxlib", "equinox", "diffrax", "optimistix", "lineax", "flatbuffers")
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
    from jax import export

    path = _module_file(where, kernel, static, tree, signature)
    exported = _read(path)
    if exported is None:
        try:
            checks = [export.DisabledSafetyCheck.custom_call(name) for name in UNGUARANTEED_CALLS]
            exported = export.export(jax.jit(flat), disabled_checks=checks)(*leaves)
        except Exception as err:  # noqa: BLE001 -- e.g. a host callback: compile as before
            log.debug("kernel %s not exported (%s): compiled directly", kernel.__name__, err)
            return jax.jit(flat).lower(*leaves).compile()
        if _write(path, exported):
            _list_shapes(where, kernel, static, tree, signature)

    def call(*xs):
        return exported.call(*xs)

    call.__name__ = kernel.__name__  # the program's name in logs (profile_compile reads them)
    return jax.jit(call).lower(*leaves).compile()
