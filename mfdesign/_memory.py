"""Memory a long job gives back between its stages (:func:`release_memory`).

Every program XLA compiles stays alive in JAX's caches with its code and buffers, and
glibc keeps the freed heap of the compilations in its arenas. Measured on the demo's
diagnosis (exact physics, 2-core CPU, issue 40): the process held 1.83 GB after it;
``jax.clear_caches()`` alone gave back almost nothing, followed by ``malloc_trim(0)``
0.65 GB. Each executable also holds ~15 memory maps (the test suite met Linux's
``vm.max_map_count`` that way: tests/conftest.py). A stage boundary is the place to drop
them: the next stage compiles programs of its own, and the persistent compilation cache
(:mod:`mfdesign._cache`) brings back any slow one it shares.
"""

from __future__ import annotations

import ctypes
import ctypes.util
import gc
import sys

__all__ = ["malloc_trim", "release_memory"]


def malloc_trim() -> None:
    """glibc's ``malloc_trim(0)``: hand the arenas' free pages back (Linux; a no-op elsewhere)."""
    if not sys.platform.startswith("linux"):
        return
    try:
        libc = ctypes.CDLL(ctypes.util.find_library("c") or "libc.so.6")
        libc.malloc_trim(0)
    except (OSError, AttributeError):  # musl or another libc: nothing to trim with
        pass


def release_memory() -> None:
    """Drop JAX's compiled programs and traces (``jax.clear_caches``), collect garbage and
    return free heap pages to the operating system. Arrays still referenced are kept."""
    if "jax" in sys.modules:  # never import jax only to clear it
        sys.modules["jax"].clear_caches()
    gc.collect()
    malloc_trim()
