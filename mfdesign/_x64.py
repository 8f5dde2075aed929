"""Float64 for JAX, switched on explicitly by mfdesign's entry points.

The physics runs in float64: the shooting solver and the Gent energy near its lock need
it, and a float32 run would be silently less accurate. Importing an mfdesign module never
changes JAX's configuration (a library must not flip a process-wide switch behind its
user's back); instead every entry point that computes calls :func:`enable_x64` first:
each CLI command (:mod:`mfdesign.cli._contract`), the public functions (``force_plane``,
``height_at``, ``calibrate``, ``diagnose``, ``propose``, ``optimize``, ...), the solver's
and the models' entry functions, the experiments' shared helper and the test suite's
``conftest.py``. A caller of an internal function that creates JAX arrays before any of
these ran calls :func:`enable_x64` itself.
"""

from __future__ import annotations

__all__ = ["enable_x64"]


def enable_x64() -> None:
    """Switch JAX to 64-bit floats (idempotent); mfdesign's entry points call it themselves.

    Call it first when you build JAX arrays for mfdesign's internals yourself (arrays made
    before keep their float32 dtype).

    **Arguments:** none.

    **Returns:** None.
    """
    import jax

    if not jax.config.read("jax_enable_x64"):
        jax.config.update("jax_enable_x64", True)
