"""JAX's persistent compilation cache, for the CLI and for scripts alike (:func:`enable_compilation_cache`).

A library module (no ``typer``, no JAX import): the ``mfdesign`` group callback
(:mod:`mfdesign.cli._app`) and the scripts under ``experiments/`` call it the same way.
"""

from __future__ import annotations

import os
import sys
from pathlib import Path

__all__ = ["enable_compilation_cache"]


def enable_compilation_cache() -> Path:
    """JAX's persistent compilation cache, so a second CLI call (or script run) does not recompile.

    Folder: ``$MFDESIGN_CACHE_DIR`` (default ``~/.cache/mfdesign/jax``). Every program is
    stored, however fast it compiles: with JAX's default floor of 1 s, the demo's ~1,400
    small programs (eager glue ops, short kernels) were compiled again on every run, 14 s
    of a warm demo's backend compile (issue 40: 1,745 compile requests, 348 hits at a 1 s
    floor, 1,745 at 0; the cache then holds ~100 MB).

    Set through JAX's environment variables (``JAX_COMPILATION_CACHE_DIR``,
    ``JAX_PERSISTENT_CACHE_MIN_COMPILE_TIME_SECS``, ``JAX_PERSISTENT_CACHE_MIN_ENTRY_SIZE_BYTES``;
    jax reads them when it is first imported) rather than ``jax.config``: the group callback
    calls this before click parses a sub-command's ``--help``, and importing jax there made
    every ``mfdesign CMD --help`` take over 1 s. A caller that already imported jax (a
    script, a test) gets the same settings through ``jax.config``.

    Why ``EQX_ON_ERROR=nan`` (unless already set): equinox's runtime checks inside the
    solvers (``eqx.error_if``, used by optimistix / diffrax / lineax even with
    ``throw=False``) are host callbacks by default, and XLA never stores an executable that
    holds a host callback: the cache stayed empty after any number of ``simulate`` runs.
    With ``nan`` such a check turns its outputs into NaN, which the physics already reports
    as a failed point (every solve here runs with ``throw=False``). It must be set before
    equinox is imported, i.e. here, before any command body runs.
    """
    os.environ.setdefault("EQX_ON_ERROR", "nan")
    cache = Path(os.environ.get("MFDESIGN_CACHE_DIR", Path.home() / ".cache" / "mfdesign" / "jax"))
    try:  # a file or a read-only folder there is the user's setting, not a bug (exit 2)
        cache.mkdir(parents=True, exist_ok=True)
        if not os.access(cache, os.W_OK | os.X_OK):
            raise PermissionError(13, "not writable")
    except OSError as err:
        from mfdesign.errors import InputError

        raise InputError(
            f"cache folder {cache} (MFDESIGN_CACHE_DIR or the default) cannot be used: {err.strerror or err}; "
            "allowed: a folder you can write (set MFDESIGN_CACHE_DIR to one)"
        ) from None
    settings = {
        "jax_compilation_cache_dir": str(cache),
        "jax_persistent_cache_min_compile_time_secs": 0.0,
        "jax_persistent_cache_min_entry_size_bytes": 0,
        # JAX's default adds XLA's GPU autotuning folder, a path inside this one, to every
        # program's compile options, and so to its cache key: a cache copied or moved to
        # another folder (a CI cache restored elsewhere, a warm cache carried to the rig's
        # laptop, bench_demo's copies) missed every program and compiled it again (session
        # 32: a "warm" demo on a copied cache spent 270 s in XLA). "none": keys without it.
        "jax_persistent_cache_enable_xla_caches": "none",
    }
    os.environ.update({name.upper(): str(value) for name, value in settings.items()})
    if "jax" in sys.modules:  # already imported: it read its environment then, tell it now
        jax = sys.modules["jax"]
        for name, value in settings.items():
            jax.config.update(name, value)
    return cache
