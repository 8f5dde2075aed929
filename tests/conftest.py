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
