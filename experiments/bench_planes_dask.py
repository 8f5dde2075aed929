"""Simulator planes on a Dask cluster: the speed-up with the number of workers (issue 40, item 5).

Solves the same planes (the exact model's lattice: ``--designs`` x ``--jm-nodes`` nodes of
the J_m axis, on ``PlaneGrid.covering(--h-max, --p-max)``) with
``mfdesign.physics.planes.solve_planes``, each time into an empty plane cache:

* ``local``: in this process, one thread per core (``force_planes`` without a scheduler),
  the reference;
* ``dask_N`` for each N of ``--workers``: a ``LocalCluster`` of N worker processes, one
  thread each, started as docs/physics.md says (``--preload mfdesign.physics.cluster``;
  their compilation cache in a temporary ``MFDESIGN_CACHE_DIR``), the planes sent with
  ``solve_planes(..., scheduler=client)``.

Before each timed solve every process compiles the kernels on a warm-up plane (each
worker at once, ``Client.run``), so the figures compare solving, not compiling; the
warm-up's seconds are reported beside them. Prints the wall seconds and the ratios (1
worker over N workers, local over N workers) and writes ``bench_planes_dask.json`` with the
commit, the machine and the load average before and after every run. The planes of every
run must equal the local ones (``max_abs_diff_n``). On a shared CPU the wall times are
upper bounds; the load average says how shared it was.

    python experiments/bench_planes_dask.py
"""

from __future__ import annotations

import tempfile
import time
from pathlib import Path

import numpy as np

from _common import command, git_state, load, machine, parser, timed, write_json  # experiments/ is on a script's path

DESIGNS = ["[2.0, 25.4, nan, nan, nan, nan]", "[2.0, 25.4, 33.4, 5.0, nan, nan]"]


def _warm(grid, job) -> float:
    """Solve one plane here as a plane of the timed runs is solved (whole, on one thread,
    repaired; not stored): this process compiles the kernels for the runs' shapes."""
    import functools

    from mfdesign.physics import planes as pl
    from mfdesign.physics import solve

    t0 = time.perf_counter()
    finish = functools.partial(pl._finish_plane, grid, None)
    solve._planes_here([job], grid.h, grid.p[1:], signed=True, then=finish, lanes=1)
    return time.perf_counter() - t0


def _solve(jobs, grid, folder: Path, scheduler) -> tuple[list, dict]:
    from mfdesign.physics import planes as pl

    pl._MEMO.clear()  # every run solves every plane (an empty cache folder, nothing in memory)
    with timed() as t:
        planes = pl.solve_planes(jobs, grid, cache=folder, scheduler=scheduler)
    pl._MEMO.clear()
    # wall seconds; this process's CPU seconds would leave out the workers'
    return planes, {k: (round(v, 2) if k == "wall_s" else v) for k, v in t.items() if k != "cpu_s"}


def _dask_run(n: int, jobs, grid, warm_job, tmp: Path) -> tuple[list, dict]:
    from dask.distributed import Client, LocalCluster

    with (
        LocalCluster(
            n_workers=n,
            threads_per_worker=1,
            processes=True,
            dashboard_address=None,
            preload=["mfdesign.physics.cluster"],
            env={"JAX_PLATFORMS": "cpu", "MFDESIGN_CACHE_DIR": str(tmp / "jax")},
        ) as cluster,
        Client(cluster, set_as_default=False) as client,
    ):
        t0 = time.perf_counter()
        client.run(_warm, grid, warm_job)  # every worker at once
        warm_s = time.perf_counter() - t0
        planes, run = _solve(jobs, grid, tmp / f"planes_dask_{n}", client)
    return planes, {"workers": n, "threads_per_worker": 1, "warm_up_s": round(warm_s, 2), **run}


def main() -> None:
    ap = parser(__doc__)
    ap.add_argument("--designs", nargs="+", default=DESIGNS, metavar="KEY", help="membranes of the lattice")
    ap.add_argument("--jm-nodes", type=int, default=4, help="J_m lattice nodes per membrane (planes per membrane)")
    ap.add_argument("--h-max", type=float, default=40.0, help="highest plate height of the grid [mm]")
    ap.add_argument("--p-max", type=float, default=4000.0, help="pressure the grid covers [Pa] (x2 margin)")
    ap.add_argument(
        "--workers", type=int, nargs="+", default=[1, 2], help="Dask worker counts (the first: the ratios' base)"
    )
    ap.add_argument("--no-local", action="store_true", help="skip the in-process reference run")
    args = ap.parse_args()

    from mfdesign.design import Membrane
    from mfdesign.physics import planes as pl
    from mfdesign.physics.params import SimParams

    commit, dirty = git_state()
    grid = pl.PlaneGrid.covering(args.h_max, args.p_max)
    designs = [Membrane.from_key(k) for k in args.designs]
    jobs, _ = pl.lattice_jobs(designs, SimParams(), {"jm": (1, args.jm_nodes)})
    warm_job = pl.lattice_jobs(designs[-1:], SimParams(), {"jm": (0, 0)})[0][0]  # not among the timed planes
    print(f"{len(jobs)} planes of {grid.h.size} heights x {grid.p.size} pressures; load {load()}")
    t_all = time.perf_counter()
    runs, planes = {}, {}
    with tempfile.TemporaryDirectory(prefix="mfdesign_bench_planes_dask_") as tmp:
        tmp = Path(tmp)
        if not args.no_local:
            warm_s = _warm(grid, warm_job)
            planes["local"], run = _solve(jobs, grid, tmp / "planes_local", False)
            runs["local"] = {"warm_up_s": round(warm_s, 2), **run}
        for n in args.workers:
            planes[f"dask_{n}"], runs[f"dask_{n}"] = _dask_run(n, jobs, grid, warm_job, tmp)
        for name, r in runs.items():
            print(
                f"{name:8s} solve {r['wall_s']:7.1f} s  (warm-up {r['warm_up_s']:.1f} s)  load {r['load_average_before'][0]:.2f} -> {r['load_average_after'][0]:.2f}"
            )
    ref = planes.get("local", planes[f"dask_{args.workers[0]}"])
    for name, r in runs.items():
        diff = np.nanmax([np.nanmax(np.abs(a - b)) if np.isfinite(a).any() else 0.0 for a, b in zip(ref, planes[name])])
        same_nan = all(np.array_equal(np.isnan(a), np.isnan(b)) for a, b in zip(ref, planes[name]))
        r.update(max_abs_diff_n=float(diff), same_nan_nodes=same_nan)
    base = runs[f"dask_{args.workers[0]}"]["wall_s"]
    ratios = {
        f"dask_{args.workers[0]}_over_dask_{n}": round(base / runs[f"dask_{n}"]["wall_s"], 2) for n in args.workers[1:]
    }
    if "local" in runs:
        ratios.update(
            {
                f"local_over_dask_{n}": round(runs["local"]["wall_s"] / runs[f"dask_{n}"]["wall_s"], 2)
                for n in args.workers
            }
        )
    print("speed-up: " + ", ".join(f"{k} {v:.2f}x" for k, v in ratios.items()))
    path = write_json(
        args.out / "bench_planes_dask.json",
        {
            "command": command(__file__, args),
            "commit": commit,
            "dirty": dirty,
            "machine": machine(),
            "planes": len(jobs),
            "grid": {
                "heights": int(grid.h.size),
                "pressures": int(grid.p.size),
                "h_top_mm": grid.h_top_mm,
                "p_top_pa": grid.p_top_pa,
            },
            "designs": list(args.designs),
            "runs": runs,
            "ratios": ratios,
            "total_s": round(time.perf_counter() - t_all, 1),
            "load_average_end": load(),
        },
    )
    print(f"wrote {path}")


if __name__ == "__main__":
    main()
