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

import json

import numpy as np

from mfdesign.design import DesignSpace, Membrane
from mfdesign.physics.solve import force_plane
from mfdesign.physics.status import Status, summarize

from _common import command, load, machine, parser, timed, write_json  # experiments/ is on a script's path

UNREACHABLE = (Status.LIMIT_POINT, Status.EXTENSION_LIMIT, Status.INVALID_INPUT)


def timed_plane(design: Membrane, h, p):
    # Wall time and process CPU time: other jobs share the cores, so wall time alone
    # says as much about the load as about the simulator.
    load_at_start = load()
    with timed() as first_t:
        first = force_plane(design, h, p)
    with timed() as run_t:
        again = force_plane(design, h, p)
    conv = np.isin(again.status, [Status.OK, Status.NO_CONTACT])
    return {
        "design": design.key(),
        "grid": [len(h), len(p)],
        "load_average_1_5_15min": load_at_start,
        "first_call_s": first_t["wall_s"],
        "first_call_cpu_s": first_t["cpu_s"],
        "run_s": run_t["wall_s"],
        "run_cpu_s": run_t["cpu_s"],
        "compile_s_estimate": first_t["wall_s"] - run_t["wall_s"],
        "converged_points": int(conv.sum()),
        "converged_points_per_s": float(conv.sum() / run_t["wall_s"]),
        "converged_points_per_cpu_s": float(conv.sum() / run_t["cpu_s"]),
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
    with timed() as t:
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
        "wall_s": t["wall_s"],
        "cpu_s": t["cpu_s"],
        "per_design": rows,
    }


def main():
    ap = parser(__doc__, seed=True)
    ap.add_argument("--grid", type=int, default=50)
    ap.add_argument("--n-designs", type=int, default=200)
    ap.add_argument("--design-grid", type=int, default=12, help="grid for the random-design sweep")
    args = ap.parse_args()
    h = np.linspace(0.0, 70.0, args.grid)
    p = np.linspace(0.0, 10_000.0, args.grid)
    result = {
        "command": command(__file__, args),
        "machine": machine(),
        "targets": {"two_ring_converged_points_per_s": 500, "converged_fraction_of_reachable": 0.99},
        "load_average_at_start": load(),
        "planes": [],
    }
    with timed() as t:
        for key in ("[2.0, 25.4, nan, nan, nan, nan]", "[2.0, 25.4, 33.4, 5.0, 46.4, 5.0]"):
            row = timed_plane(Membrane.from_key(key), h, p)
            print(json.dumps(row))
            result["planes"].append(row)
        if args.n_designs:
            result["random_designs"] = reachable_convergence(args.n_designs, args.design_grid, args.seed)
            rd = result["random_designs"]
            print(f"reachable convergence {rd['converged_fraction_of_reachable']:.4f} over {rd['n_designs']} designs")
    result["load_average_at_end"] = t["load_average_after"]
    result["wall_s"] = t["wall_s"]
    result["cpu_s"] = t["cpu_s"]
    path = write_json(args.out / "bench_simulator.json", result)
    print(f"wrote {path}")


if __name__ == "__main__":
    main()
