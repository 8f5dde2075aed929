"""mfdesign.physics.solve.KeptPrograms: the plane solver's compiled programs outlive JAX's
caches (a long job clears them between stages, and each stage then traced the solver
again: issue 40)."""

from __future__ import annotations

import threading

import jax
import jax.numpy as jnp
import numpy as np

from mfdesign.physics.solve import KeptPrograms


def _counting_kernel():
    traces = []

    def kernel(x, scale, n):
        traces.append(x.shape)  # runs only while JAX traces
        return {"y": x * scale * n}

    return kernel, traces


def test_a_kept_program_is_traced_once_and_survives_clear_caches():
    kept = KeptPrograms()
    kernel, traces = _counting_kernel()
    x = jnp.arange(4.0)
    first = kept(kernel, x, jnp.asarray(2.0), static=(3,))
    jax.clear_caches()
    again = kept(kernel, x + 1.0, jnp.asarray(2.0), static=(3,))
    np.testing.assert_allclose(first["y"], 6.0 * np.arange(4.0))
    np.testing.assert_allclose(again["y"], 6.0 * (np.arange(4.0) + 1.0))
    assert traces == [(4,)] and len(kept) == 1
    kept(kernel, jnp.arange(8.0), jnp.asarray(2.0), static=(3,))  # another shape: its own program
    kept(kernel, x, jnp.asarray(2.0), static=(5,))  # another static argument: its own program
    assert traces == [(4,), (8,), (4,)] and len(kept) == 3


def test_the_least_recently_used_program_goes_first():
    kept = KeptPrograms(size=2)
    kernel, traces = _counting_kernel()
    one = jnp.asarray(1.0)
    for n in (1, 2, 1, 3):  # 1 used again before 3 arrives: 2 goes
        kept(kernel, jnp.arange(2.0), one, static=(n,))
    assert len(kept) == 2 and len(traces) == 3
    kept(kernel, jnp.arange(2.0), one, static=(1,))
    assert len(traces) == 3  # still kept
    kept(kernel, jnp.arange(2.0), one, static=(2,))
    assert len(traces) == 4  # dropped before, traced again


def test_threads_calling_at_once_compile_once():
    kept = KeptPrograms()
    kernel, traces = _counting_kernel()
    out = [None] * 4

    def call(i):
        out[i] = kept(kernel, jnp.full(3, float(i)), jnp.asarray(1.0), static=(1,))

    threads = [threading.Thread(target=call, args=(i,)) for i in range(4)]
    for t in threads:
        t.start()
    for t in threads:
        t.join()
    assert len(traces) == 1
    for i in range(4):
        np.testing.assert_allclose(out[i]["y"], float(i))
