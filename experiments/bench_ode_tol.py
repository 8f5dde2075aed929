"""The shooting integration's tolerances: plane time and force change (issue 40). Writes JSON.

One simulator plane (the demo's grid: heights 0-80 mm, reduced pressures 0-16 kPa) of three
of the bundled membranes (ringless, one ring, two rings) at the authors' constants, solved
on one core at each tolerance pair ``(rtol, atol)`` of the ODE (``RTOL_ODE``, ``ATOL_ODE`` in
:mod:`mfdesign.physics.shooting`). Each plane is solved twice and the second (compiled)
solve is timed. Against the tightest pair it reports the time ratio, the largest and RMS
force change [N] and how many nodes changed between solved and unsolved: the budget the
default must fit is the planes' interpolation error (~3e-3 N RMS, ``bench_exact.py``).

    python experiments/bench_ode_tol.py [--tols 1e-8,1e-7,1e-6]
"""

from __future__ import annotations

import argparse
import time

import numpy as np

from _common import OUT, git_state, machine, write_json  # experiments/ is on a script's path

KEYS = ("[2.0, 25.4, nan, nan, nan, nan]", "[1.5, 30.0, 45.0, 6.0, nan, nan]", "[2.0, 38.1, 47.55, 6.45, 62.0, 5.0]")


def main() -> None:
    ap = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    ap.add_argument("--tols", default="1e-8,1e-7,1e-6", help="ODE rtol values, tightest first (atol = rtol / 10)")
    ap.add_argument("--out", default=str(OUT / "bench_ode_tol.json"))
    args = ap.parse_args()
    from mfdesign._x64 import enable_x64

    enable_x64()
    import jax

    import mfdesign.physics.shooting as sh
    from mfdesign.design import Membrane
    from mfdesign.physics.params import SimParams
    from mfdesign.physics.planes import PlaneGrid
    from mfdesign.physics.solve import force_plane

    commit, dirty = git_state()
    grid = PlaneGrid.covering(80.0, 8000.0)
    default = (sh.RTOL_ODE, sh.ATOL_ODE)
    rows, ref = [], {}
    for rtol in [float(t) for t in args.tols.split(",")]:
        # read at trace time: the traced kernels must go, or the old tolerance would be reused
        sh.RTOL_ODE, sh.ATOL_ODE = rtol, rtol / 10
        jax.clear_caches()
        for key in KEYS:
            design = Membrane.from_key(key)
            force_plane(design, grid.h, grid.p, SimParams(), signed=True, parts=1)  # compile
            t0 = time.perf_counter()
            f = np.asarray(force_plane(design, grid.h, grid.p, SimParams(), signed=True, parts=1).force_n, float)
            wall = time.perf_counter() - t0
            row = {"rtol": rtol, "atol": rtol / 10, "design": key, "plane_s": round(wall, 3)}
            if key not in ref:
                ref[key] = (f, wall)
            else:
                f0, w0 = ref[key]
                d = np.abs(f - f0)
                row.update(
                    speedup=round(w0 / wall, 2),
                    max_abs_df_n=float(np.nanmax(d)),
                    rms_df_n=float(np.sqrt(np.nanmean(d**2))),
                    solved_changed=int((np.isfinite(f) != np.isfinite(f0)).sum()),
                )
            rows.append(row)
            print(
                f"rtol {rtol:g}: {key}: {wall:.2f} s"
                + (f", {row['speedup']}x, max |dF| {row['max_abs_df_n']:.1e} N" if "speedup" in row else ""),
                flush=True,
            )
    out = {
        "grid": {"heights": int(grid.h.size), "pressures": int(grid.p.size)},
        "default": {"rtol": default[0], "atol": default[1]},
        "rows": rows,
        "commit": commit,
        "dirty": dirty,
        "machine": machine(),
    }
    print(f"wrote {write_json(args.out, out)}")


if __name__ == "__main__":
    main()
