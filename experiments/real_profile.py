"""Which rubber do the real lifts ask for? A profile over the constants that shape a plane.

The calibration (``real_mass_lift.py``, docs/real_data_log.md section 5) answers the real
membranes with a rubber that locks at J_m ~18 where the coupons say 39.6. Is that the
rubber, or a plain Gent law standing in for a rubber whose energy also depends on the
second invariant (the ``rubber_i2`` effect: a Mooney-Rivlin term that uniaxial coupons
barely see and an inflated membrane does)? This script answers it on the simulator's own
planes, with nothing else free:

* for every combination of J_m, I2 share and fabric inset given on the command line
  (lattice nodes of ``mfdesign.physics.planes.AXES``), one simulator plane per membrane
  (cached; the ring ratio at its reference);
* each membrane's ``s = mu tf / mu0`` (rubber modulus times thickness, the one number a
  lift cannot split) fitted alone by weighted least squares on its floating rows, using the
  planes' exact scaling ``F(h, p; s) = s G(h, p / s)``;
* the pooled weighted RMS of the floating rows (``mfdesign.data.lifts.floating_rows``) at
  each combination, and the per-membrane ``s``.

A profile, not a posterior: each membrane's ``s`` is free (no population prior), the plane
is read by linear interpolation (the exact model's cubic differs by a few 0.01 N), and a
combination is judged by its fit only; the held-out check is ``real_mass_lift.py``'s.

    python experiments/real_profile.py [--jm 18.2 25.4 39.6] [--i2 0 0.15 0.3] [--inset 0.5 1.0]

Writes ``experiments/out/real_profile.json``.
"""

from __future__ import annotations

import itertools
import math

import numpy as np

from _common import Timing, parser, write_json  # experiments/ is on a script's path

S_GRID = np.exp(np.linspace(-0.6, 0.6, 241))  # s = mu tf / mu0 searched per membrane


def main():
    ap = parser(__doc__)
    ap.add_argument("--jm", type=float, nargs="+", default=[18.2, 25.4, 39.6], help="J_m values (snapped to nodes)")
    ap.add_argument("--i2", type=float, nargs="+", default=[0.0, 0.15, 0.3], help="I2 shares (snapped to nodes)")
    ap.add_argument("--inset", type=float, nargs="+", default=[0.5, 1.0], help="fabric insets [mm] (snapped)")
    args = ap.parse_args()

    from scipy.interpolate import RegularGridInterpolator

    from mfdesign.calibration.workflow import lifted_rows
    from mfdesign.data.spa_design import load_mass_lift
    from mfdesign.design import Membrane
    from mfdesign.physics import planes as pl
    from mfdesign.physics.params import SimParams

    clock = Timing()
    data = load_mass_lift()
    df = data.df
    grid = pl.PlaneGrid.covering(
        float(
            max(df["height_mm"].max(), df["height_set_mm"].max(skipna=True) if df["height_set_mm"].notna().any() else 0)
        ),
        float(df["pressure_pa"].max()),
    )
    rows = lifted_rows(data).df
    keys = list(dict.fromkeys(df["design_key"]))

    def node(axis, coord):  # the lattice node nearest to a coordinate: cached planes are found
        return round(coord / pl.AXES[axis].step) * pl.AXES[axis].step

    combos = []
    for jm, i2, inset in itertools.product(args.jm, args.i2, args.inset):
        prm = pl.AXES["jm"].at(SimParams(), node("jm", math.log(jm / SimParams().jm)))
        prm = pl.AXES["i2"].at(prm, node("i2", i2))
        combos.append(pl.AXES["inset"].at(prm, node("inset", inset)))
    jobs = [(Membrane.from_key(k), prm) for prm in combos for k in keys]
    print(f"{len(combos)} combinations x {len(keys)} membranes: {len(jobs)} planes (cached ones are read)", flush=True)
    planes = pl.solve_planes(jobs, grid, progress=True)

    results = []
    for c, prm in enumerate(combos):
        sse, wsum, per = 0.0, 0.0, {}
        for m, key in enumerate(keys):
            g = rows[rows["design_key"] == key]
            h, p = g["height_mm"].to_numpy(float), g["pressure_pa"].to_numpy(float)
            f, w = g["force_n"].to_numpy(float), g["weight"].to_numpy(float)
            interp = RegularGridInterpolator((grid.h, grid.p), planes[c * len(keys) + m], bounds_error=False)
            # [S, n] model forces for every s of the search grid: s G(h, p / s), clipped at 0
            pts = np.stack(np.broadcast_arrays(h[None, :], p[None, :] / S_GRID[:, None]), -1)
            model = np.maximum(S_GRID[:, None] * interp(pts), 0.0)
            ok = np.all(np.isfinite(model), 0)  # rows some s cannot reach are left out for every s
            err = np.sum(w[ok] * (model[:, ok] - f[ok]) ** 2, 1)
            best = int(np.argmin(err))
            per[key] = {
                "s": float(S_GRID[best]),
                "rms_n": float(np.sqrt(err[best] / w[ok].sum())),
                "rows": int(ok.sum()),
                "rows_left_out": int((~ok).sum()),
                "s_on_search_limit": best in (0, S_GRID.size - 1),
            }
            sse += float(err[best])
            wsum += float(w[ok].sum())
        res = {
            "jm": float(prm.jm),
            "i2_share": float(prm.i2_share),
            "inset_mm": float(prm.fabric_inset_mm),
            "rms_n": math.sqrt(sse / wsum),
            "membranes": per,
        }
        results.append(res)
        print(
            f"J_m {res['jm']:6.2f}  I2 {res['i2_share']:.2f}  inset {res['inset_mm']:.2f} mm: RMS {res['rms_n']:.3f} N"
            "  (s " + " ".join(f"{v['s']:.2f}" + ("*" if v["s_on_search_limit"] else "") for v in per.values()) + ")",
            flush=True,
        )
    if any(v["s_on_search_limit"] for r in results for v in r["membranes"].values()):
        print(
            f"*: s on its search limit exp(+-{math.log(S_GRID[-1]):.1f}); that membrane's RMS is an upper bound there"
        )
    best = min(results, key=lambda r: r["rms_n"])
    plain = [r for r in results if r["i2_share"] == 0.0]
    best_plain = min(plain, key=lambda r: r["rms_n"]) if plain else None
    print(
        f"best: J_m {best['jm']:.2f}, I2 {best['i2_share']:.2f}, inset {best['inset_mm']:.2f} mm, RMS {best['rms_n']:.3f} N"
        + (
            f"; best plain Gent: J_m {best_plain['jm']:.2f}, inset {best_plain['inset_mm']:.2f} mm, RMS {best_plain['rms_n']:.3f} N"
            f" (ratio {best_plain['rms_n'] / best['rms_n']:.3f})"
            if best_plain
            else ""
        )
    )
    write_json(
        args.out / "real_profile.json",
        {
            "combinations": results,
            "best": {k: best[k] for k in ("jm", "i2_share", "inset_mm", "rms_n")},
            "best_plain_gent": {k: best_plain[k] for k in ("jm", "i2_share", "inset_mm", "rms_n")}
            if best_plain
            else None,
            "rows": int(len(rows)),
            "grid": {"h_top_mm": grid.h_top_mm, "p_top_pa": grid.p_top_pa},
            "seconds": clock.elapsed(),
            "notes": "per-membrane s = mu tf / mu0 free (least squares on a grid of 241 values in exp(+-0.6)); "
            "linear interpolation of the planes; ring ratio at its reference; floating rows with their weights",
        },
        indent=1,
    )


if __name__ == "__main__":
    main()
