"""Shared pytest fixtures."""

import signal

import pytest

from mfdesign._x64 import enable_x64

# The suite checks float64 physics; mfdesign's entry points switch 64-bit on themselves,
# but tests also build JAX arrays directly before calling internals, so switch it on here,
# explicitly, once (importing mfdesign never does: tests/test_x64.py).
enable_x64()


@pytest.fixture
def ctrl_c():
    """Make SIGINT raise KeyboardInterrupt in this process while the test runs.

    A shell without job control starts background jobs (``pytest &``, ``.ci/run &``) with
    SIGINT ignored, and Python then never installs its Ctrl-C handler; the tests that press
    Ctrl-C would fail for a reason that has nothing to do with the rig code."""
    old = signal.signal(signal.SIGINT, signal.default_int_handler)
    try:
        yield
    finally:
        signal.signal(signal.SIGINT, old)


# Why: every executable XLA compiles stays alive in JAX's caches for the life of the
# process and holds ~15 memory maps (JIT code and data); the suite compiles thousands, and
# at Linux's default vm.max_map_count (65,530) the next compile's mmap fails inside LLVM
# and the process dies with a segmentation fault (seen at ~72 % of the suite, always in
# tests/test_optimize.py). Dropping the caches once the maps pass a threshold costs a few
# recompiles and keeps the suite well under the limit.
_MAPS_LIMIT = 30_000


def _n_maps() -> int:
    try:
        with open("/proc/self/maps", "rb") as fh:
            return sum(1 for _ in fh)
    except OSError:  # not Linux: no such limit to watch
        return 0


@pytest.fixture(autouse=True)
def _bounded_compiled_executables():
    yield
    if _n_maps() > _MAPS_LIMIT:
        import gc

        import jax

        jax.clear_caches()
        gc.collect()
