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


def test_holders_are_the_kept_programs_a_padded_call_fits():
    kept = KeptPrograms()
    kernel, _ = _counting_kernel()
    one = jnp.asarray(1.0)
    kept(kernel, jnp.arange(8.0), one, static=(1,))
    assert kept.holders(kernel, (jnp.arange(5.0), one), static=(1,), padded=(0,)) == [{0: (8,)}]
    assert kept.holders(kernel, (jnp.arange(9.0), one), static=(1,), padded=(0,)) == []  # larger than kept
    assert kept.holders(kernel, (jnp.arange(5.0), one), static=(2,), padded=(0,)) == []  # another static
    assert kept.holders(kernel, (jnp.arange(5.0), one), static=(1,)) == []  # may not be padded
    assert kept.holders(kernel, (jnp.arange(5), one), static=(1,), padded=(0,)) == []  # another type


def test_a_kept_call_pads_to_a_kept_program_and_cuts_its_outputs(monkeypatch):
    """_kept_call: a smaller call runs on the kept program of a larger one (padded, its
    outputs cut back), unless the padding would cost more than PAD_WORK_LIMIT x its work."""
    from mfdesign.physics import solve

    monkeypatch.setattr(solve, "KEPT", KeptPrograms())
    monkeypatch.setattr(solve, "PAD_WORK_FLOOR", 0)  # the ratio rule alone (the floor: below)
    traces = []

    def kernel(rows, path):  # rows x path outputs; a NaN path entry is padding
        traces.append((rows.shape, path.shape))
        return {"y": rows[:, None] * jnp.where(jnp.isfinite(path), path, -1.0)[None, :]}

    def call(rows, path):
        return solve._kept_call(
            kernel,
            (np.asarray(rows, float), np.asarray(path, float)),
            {0: solve._edge, 1: solve._filled(np.nan)},
            work=lambda s: s[0][0] * s[1][0],
            lead=lambda s: (s[0][0], s[1][0]),
        )

    big = call(np.arange(1.0, 9.0), np.arange(1.0, 11.0))  # 8 x 10: compiled
    small = call([2.0, 3.0], [5.0, 6.0, 7.0])  # 2 x 3 = 6 lanes, 80 / 6 > the limit: its own program
    mid = call([2.0, 3.0, 4.0, 5.0], [5.0, 6.0, 7.0])  # 12 lanes, 80 / 12 <= the limit: the 8 x 10 program
    assert traces == [((8,), (10,)), ((2,), (3,))]
    assert big["y"].shape == (8, 10) and small["y"].shape == (2, 3)
    np.testing.assert_array_equal(mid["y"], np.outer([2.0, 3.0, 4.0, 5.0], [5.0, 6.0, 7.0]))
    # Under PAD_WORK_FLOOR any padding goes (a program of its own costs more to compile).
    monkeypatch.setattr(solve, "PAD_WORK_FLOOR", 80)
    tiny = call([2.0], [5.0, 6.0])
    assert len(traces) == 2
    np.testing.assert_array_equal(tiny["y"], [[10.0, 12.0]])
