"""Benchmark of the shooting simulator (issue 2, item 6). Writes JSON.

* converged points per second on a 50 x 50 grid (h 0-70 mm, p 0-10 kPa) for a ringless
  and a two-ring design, after compilation, and the compile time;
* convergence over random designs of the design space on the reachable region.

Reachable: a grid point (h, p) is reachable when quasi-static inflation at fixed plate
height h reaches p without first crossing a pressure limit point (snap-through, detected
by the sign change of the shooting Jacobian's determinant along the path: status
LIMIT_POINT) or the Gent extension limit (the last converged state had (I1 - 3)/J_m >
0.9: status EXTENSION_LIMIT). Everything else on the grid is reachable; converged =
OK or NO_CONTACT.

    python experiments/bench_simulator.py [--n-designs 200] [--grid 50]
"""

from __future__ import annotations

import argparse
import json
import os
import platform
import time
from pathlib import Path

import numpy as np

import mfdesign._x64  # noqa: F401  (float64 before any JAX array)
from mfdesign.design import DesignSpace, Membrane
from mfdesign.physics.solve import force_plane
from mfdesign.physics.status import Status, summarize

OUT = Path(__file__).parent / "out"
UNREACHABLE = (Status.LIMIT_POINT, Status.EXTENSION_LIMIT, Status.INVALID_INPUT)


def timed_plane(design: Membrane, h, p):
    # Wall time and process CPU time: other jobs share the cores, so wall time alone
    # says as much about the load as about the simulator.
    t0, c0 = time.perf_counter(), time.process_time()
    first = force_plane(design, h, p)
    t1, c1 = time.perf_counter(), time.process_time()
    again = force_plane(design, h, p)
    t2, c2 = time.perf_counter(), time.process_time()
    conv = np.isin(again.status, [Status.OK, Status.NO_CONTACT])
    return {
        "design": design.key(),
        "grid": [len(h), len(p)],
        "load_average_1_5_15min": os.getloadavg(),
        "first_call_s": t1 - t0,
        "first_call_cpu_s": c1 - c0,
        "run_s": t2 - t1,
        "run_cpu_s": c2 - c1,
        "compile_s_estimate": (t1 - t0) - (t2 - t1),
        "converged_points": int(conv.sum()),
        "converged_points_per_s": float(conv.sum() / (t2 - t1)),
        "converged_points_per_cpu_s": float(conv.sum() / (c2 - c1)),
        "status": summarize(again.status),
        "identical_on_rerun": bool(np.array_equal(first.force_n, again.force_n, equal_nan=True)),
    }


def reachable_convergence(n_designs: int, grid: int, seed: int):
    from tqdm.auto import tqdm

    space = DesignSpace()
    rng = np.random.default_rng(seed)
    h = np.linspace(0.0, 70.0, grid)
    p = np.linspace(0.0, 10_000.0, grid)
    rows = []
    t0, c0 = time.perf_counter(), time.process_time()
    for k in tqdm(range(n_designs), desc="random designs"):
        design = space.sample(rng, 1, n_rings=k % 3)[0]
        res = force_plane(design, h, p)
        reach = ~np.isin(res.status, UNREACHABLE)
        conv = np.isin(res.status, [Status.OK, Status.NO_CONTACT]) & reach
        rows.append(
            {
                "design": design.key(),
                "reachable": int(reach.sum()),
                "converged": int(conv.sum()),
                "plane_usable_points": int(np.isfinite(res.force_n).sum()),
                "status": summarize(res.status),
            }
        )
    reach = sum(r["reachable"] for r in rows)
    conv = sum(r["converged"] for r in rows)
    return {
        "n_designs": n_designs,
        "grid": [grid, grid],
        "reachable_points": reach,
        "converged_reachable_points": conv,
        "converged_fraction_of_reachable": conv / max(reach, 1),
        "designs_with_a_plane": sum(r["plane_usable_points"] > 0 for r in rows),
        "wall_s": time.perf_counter() - t0,
        "cpu_s": time.process_time() - c0,
        "per_design": rows,
    }


def main():
    ap = argparse.ArgumentParser(description=__doc__.split("\n")[0])
    ap.add_argument("--grid", type=int, default=50)
    ap.add_argument("--n-designs", type=int, default=200)
    ap.add_argument("--design-grid", type=int, default=12, help="grid for the random-design sweep")
    ap.add_argument("--seed", type=int, default=0)
    ap.add_argument("--out", type=Path, default=OUT / "bench_simulator.json")
    args = ap.parse_args()
    h = np.linspace(0.0, 70.0, args.grid)
    p = np.linspace(0.0, 10_000.0, args.grid)
    result = {
        "command": f"python experiments/bench_simulator.py --grid {args.grid} --n-designs {args.n_designs} --design-grid {args.design_grid}",
        "machine": f"{platform.machine()} {platform.processor()} cpus={__import__('os').cpu_count()}",
        "targets": {"two_ring_converged_points_per_s": 500, "converged_fraction_of_reachable": 0.99},
        "load_average_at_start": os.getloadavg(),
        "planes": [],
    }
    t0, c0 = time.perf_counter(), time.process_time()
    for key in ("[2.0, 25.4, nan, nan, nan, nan]", "[2.0, 25.4, 33.4, 5.0, 46.4, 5.0]"):
        row = timed_plane(Membrane.from_key(key), h, p)
        print(json.dumps(row))
        result["planes"].append(row)
    if args.n_designs:
        result["random_designs"] = reachable_convergence(args.n_designs, args.design_grid, args.seed)
        rd = result["random_designs"]
        print(f"reachable convergence {rd['converged_fraction_of_reachable']:.4f} over {rd['n_designs']} designs")
    result["load_average_at_end"] = os.getloadavg()
    result["wall_s"] = time.perf_counter() - t0
    result["cpu_s"] = time.process_time() - c0
    args.out.parent.mkdir(parents=True, exist_ok=True)
    args.out.write_text(json.dumps(result, indent=2))
    print(f"wrote {args.out}")


if __name__ == "__main__":
    main()
