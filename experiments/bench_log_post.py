"""Benchmark: one emcee log-posterior call of the demo's calibration (issue 40).

The demo's sampler spends most of a warm run's calibration in ``LogPosterior.batch``: 16
walkers (emcee's red-blue half of 32) at a time, each the exact force model on the bundled
data's six membranes, contracted at the walker's J_m and ring ratio on the lattice the
calibration grows (``jm -1..1, ring -1..1``), then interpolated at each of its rows. This
script builds that posterior (planes from ``--cache-dir``, solved there when missing: ~3
min on 2 cores), times ``--calls`` calls after a warm-up (compilation), and times the
force model's whole-plane contraction alone. Values are checked against a second
evaluation with the lattice tables derived per call.

    python experiments/bench_log_post.py [--cache-dir DIR] [--calls 50]

To compare commits, run it from a clone of each (``PYTHONPATH=<clone>``) on the same
machine, one after the other. Writes ``experiments/out/bench_log_post.json``.
"""

from __future__ import annotations

import dataclasses
import time

import numpy as np

from _common import command, git_state, load, machine, parser, write_json


def _per_call_ms(fn, calls: int) -> float:
    import jax

    jax.block_until_ready(fn(0))  # compile
    start = time.perf_counter()
    for i in range(calls):
        jax.block_until_ready(fn(i + 1))
    return 1e3 * (time.perf_counter() - start) / calls


def main():
    ap = parser(__doc__, plane_cache=True, seed=True)
    ap.add_argument("--calls", type=int, default=50, help="timed calls of 16 walkers")
    ap.add_argument("--max-rows", type=int, default=1500, help="rows the likelihood uses (the demo's)")
    args = ap.parse_args()

    import equinox as eqx
    import jax
    import jax.numpy as jnp

    from mfdesign.calibration.mcmc import WALKER_CHUNK, LogPosterior
    from mfdesign.calibration.workflow import model_for
    from mfdesign.data.shipped import bundled_path
    from mfdesign.data.store import read_parquet
    from mfdesign.models.exact import build_exact
    from mfdesign.models.hierarchical import CalibrationData
    from mfdesign.physics import planes as pl

    commit, dirty = git_state()
    table = read_parquet(bundled_path())
    df = table.df
    keys = tuple(dict.fromkeys(df["design_key"]))
    half = {k: (-pl.AXES[k].step, pl.AXES[k].step) for k in ("jm", "ring")}  # nodes -1..1: what the demo grows
    t0 = time.perf_counter()
    fm = build_exact(
        keys,
        h_max_mm=float(df["height_mm"].max()),
        p_max_pa=float(df["pressure_pa"].max()),
        tensor=half,
        outside="clamp",  # as the sampler runs it
        cache=args.cache_dir if args.cache_dir is not None else False,
    )
    planes_s = time.perf_counter() - t0
    data = CalibrationData.from_measurements(table, max_rows=args.max_rows, seed=args.seed)
    model = model_for(fm, data.design_keys, ("pressure_sensor",))
    u0 = np.asarray(model.to_unconstrained(model.initial_physical()))
    rng = np.random.default_rng(args.seed)
    walkers = u0 + 0.01 * rng.standard_normal((WALKER_CHUNK, model.dim))
    logp = LogPosterior(model, data)
    call_ms = _per_call_ms(lambda i: logp.batch(walkers + 1e-4 * i), args.calls)

    axes = fm.tensor_axes
    rel = contract_ms = None
    if hasattr(fm, "tables"):  # a commit before the lattice tables (dda41af) times the call only
        # the same values with the lattice tables derived on each call (a model made by hand)
        bare = LogPosterior(eqx.tree_at(lambda m: m.force_model, model, dataclasses.replace(fm, tables=())), data)
        values, again = logp.batch(walkers), bare.batch(walkers)
        rel = float(np.max(np.abs(values - again) / np.abs(values)))

        # the whole-plane contraction alone, at each walker's J_m and ring ratio
        coords = [
            jnp.asarray(rng.uniform(a.lo + 0.2 * a.axis.step, a.hi - 0.2 * a.axis.step, WALKER_CHUNK)) for a in axes
        ]
        both = lambda m, c: (  # noqa: E731
            m._contract_planes(0, axes, list(c))[0],
            m._contract_planes(0, axes, list(c), touch=True)[0],
        )
        contract = eqx.filter_jit(lambda m, cs: jax.vmap(lambda *c: both(m, c))(*cs))
        contract_ms = _per_call_ms(lambda i: contract(fm, [c + 1e-6 * i for c in coords]), args.calls)

    result = {
        "command": command(__file__, args),
        "commit": commit,
        "dirty": dirty,
        "walkers_per_call": WALKER_CHUNK,
        "rows": int(len(data.force_n)),
        "lattice": {a.name: [a.k0, a.k0 + a.n - 1] for a in axes},
        "tensor_shape": list(fm.tensor.shape),
        "planes_s": planes_s,
        "log_post_call_ms": call_ms,
        "contraction_ms": contract_ms,
        "max_rel_diff_tables_made_vs_derived": rel,
        "load_average_after": load(),
        "machine": machine(),
    }
    print(f"log posterior: {call_ms:.2f} ms a call of {WALKER_CHUNK} walkers x {result['rows']} rows")
    if contract_ms is not None:
        print(
            f"whole-plane contraction {contract_ms:.2f} ms ({contract_ms / call_ms:.2f} of a call); "
            f"tables made vs derived: {rel:.1e} relative"
        )
    write_json(args.out / "bench_log_post.json", result)


if __name__ == "__main__":
    main()
