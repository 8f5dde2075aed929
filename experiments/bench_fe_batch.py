"""How large a vmapped batch the finite-element reference should take (``fe_forces(batch=)``).

A vmapped Newton loop runs as long as its slowest point, so one batch of many unlike points
(other membranes, stiff rings that need every allowed step) can cost more CPU than the same
points in small batches. This solves the same points, the real lifts' sampled floating rows
of the ringed membranes with the authors' rings and rings 30x stiffer (where points run out
of steps), once per batch size, and reports wall and CPU seconds and the ratio to the
smallest batch. The forces must agree across batch sizes (``max_force_diff_n``; points that
converge in one and not another are counted).

    python experiments/bench_fe_batch.py

Writes ``experiments/out/bench_fe_batch.json``. On a shared CPU the wall times are upper
bounds; the CPU times are the steadier figure.
"""

from __future__ import annotations

import dataclasses
import resource
import time

import numpy as np

from _common import command, machine, parser, timed, write_json  # experiments/ is on a script's path
from _real import lift_sample


def _cpu() -> float:
    r = resource.getrusage(resource.RUSAGE_SELF)
    return r.ru_utime + r.ru_stime


def main() -> None:
    ap = parser(__doc__, seed=True)
    ap.add_argument("--per-membrane", type=int, default=16, help="floating rows sampled per membrane")
    ap.add_argument("--ring-factors", type=float, nargs="+", default=[1.0, 30.0], help="ring_mu_pa x")
    ap.add_argument(
        "--batches",
        type=int,
        nargs="+",
        default=[16, 1, 8, 64, 0],
        help="batch sizes (ratios to the first); 0: all points in one",
    )
    ap.add_argument("--elements", type=int, default=300, help="finite elements along r")
    args = ap.parse_args()

    from mfdesign.design import Membrane
    from mfdesign.physics.fe import fe_forces
    from mfdesign.physics.params import SimParams

    lifts = lift_sample(args.per_membrane, args.seed)
    ringed = [k for k in lifts.keys if Membrane.from_key(k).rings]
    cases = [(k, f) for k in ringed for f in args.ring_factors]
    jobs = [
        (Membrane.from_key(k), dataclasses.replace(SimParams(), ring_mu_pa=SimParams().ring_mu_pa * f))
        for k, f in cases
    ]
    rows = {k: lifts.df.iloc[lifts.rows[k]] for k in ringed}
    hs = [rows[k]["height_mm"].to_numpy() for k, _ in cases]
    ps = [rows[k]["pressure_pa"].to_numpy() for k, _ in cases]
    n = sum(h.size for h in hs)
    # compile every batch shape first, so that the timings below are solves only
    results, runs = {}, []
    for b in args.batches:
        size = b if b > 0 else n
        fe_forces(jobs[:1], [hs[0][:1]], [ps[0][:1]], args.elements, batch=size)
    for b in args.batches:
        size = b if b > 0 else n
        c0 = _cpu()
        with timed() as t:
            res = fe_forces(jobs, hs, ps, args.elements, batch=size)
        f = np.concatenate([np.asarray(r.force_n) for r in res])
        results[size] = f
        runs.append(
            {
                "batch": size,
                "wall_s": round(t["wall_s"], 2),
                "cpu_s": round(_cpu() - c0, 2),
                "unconverged": int(np.isnan(f).sum()),
                "load_average_before": t["load_average_before"],
                "load_average_after": t["load_average_after"],
            }
        )
        print(
            f"batch {size:5d}: {runs[-1]['wall_s']:7.1f} s wall, {runs[-1]['cpu_s']:7.1f} s CPU, "
            f"{runs[-1]['unconverged']} of {n} points unconverged",
            flush=True,
        )
    base = runs[0]
    ref = results[base["batch"]]
    for r in runs:
        r["wall_ratio_to_first"] = round(r["wall_s"] / base["wall_s"], 2)
        r["cpu_ratio_to_first"] = round(r["cpu_s"] / base["cpu_s"], 2)
        both = np.isfinite(ref) & np.isfinite(results[r["batch"]])
        r["max_force_diff_n"] = float(np.max(np.abs(ref[both] - results[r["batch"]][both]))) if both.any() else None
        r["converged_in_one_only"] = int((np.isfinite(ref) != np.isfinite(results[r["batch"]])).sum())
    out = {
        "command": command(__file__, args),
        "points": n,
        "jobs": len(jobs),
        "runs": runs,
        "machine": machine(),
        "time": time.strftime("%Y-%m-%dT%H:%M:%S"),
    }
    path = write_json(args.out / "bench_fe_batch.json", out)
    for r in runs:
        print(
            f"batch {r['batch']}: x{r['wall_ratio_to_first']} wall, x{r['cpu_ratio_to_first']} CPU of batch {base['batch']}"
        )
    print(f"-> {path}")


if __name__ == "__main__":
    main()
