"""Towards inextensible rings: the real lifts with fabric rings up to 100x stiffer (FE reference).

``real_probes.py`` found that rings 2-4x stiffer than the authors' 1 MPa let the coupons'
rubber (J_m 39.6) fit the lifts as well as the calibrated early-locking rubber (J_m 21) does
with the model's rings, and the shooting solver stops converging beyond ~4x. A woven fabric
barely stretches: does the limit of *inextensible* rings, with the coupons' rubber, explain
the lifts? The finite-element reference (``mfdesign.physics.fe.fe_force``, a Newton
minimiser of the energy) still converges with rings 100x stiffer, so this probe scores the
ringed membranes' sampled floating rows (the same sample as ``real_probes.py``: 40 a
membrane, seed 0) over ring factors x two rubbers:

* ``map``: the all-seven MAP of ``real_floor.py`` (mu, J_m 20.9, inset), read from
  ``experiments/out/real_floor.json`` (run that first);
* ``coupons``: the paper's uniaxial coupons (mu 31.5 kPa, J_m 39.6) with the MAP's inset.

Per membrane and factor: the force RMSE [N] on the rows every factor of that rubber solved,
the rows left unsolved, and the largest hoop strain R / r - 1 inside a ring (how close to
inextensible the factor is). The FE agrees with the shooting at the factors both solve
(``fe_vs_shooting_max_n``, factor 1).

    python experiments/real_rings_fe.py

Writes ``experiments/out/real_rings_fe.json``. Exploratory and in sample for the MAP.
"""

from __future__ import annotations

import dataclasses
import warnings

import numpy as np

from _common import Timing, command, machine, parser, write_json  # experiments/ is on a script's path
from _real import lift_sample, real_floor


def main():
    ap = parser(__doc__, seed=True)
    ap.add_argument("--per-membrane", type=int, default=40, help="floating rows sampled per membrane")
    ap.add_argument(
        "--ring-factors", type=float, nargs="+", default=[1.0, 2.0, 4.0, 10.0, 30.0, 100.0], help="ring_mu_pa x"
    )
    ap.add_argument("--elements", type=int, default=300, help="finite elements along r")
    args = ap.parse_args()

    from mfdesign.design import Membrane
    from mfdesign.physics.fe import fe_forces
    from mfdesign.physics.params import SimParams
    from mfdesign.physics.solve import force_at

    warnings.simplefilter("ignore")
    x = real_floor()["cases"]["all7"]["map"]
    inset = x["fabric_inset.inset_mm"]
    rubbers = {
        "map": SimParams(mu_pa=x["mu_pa"], jm=x["jm"], fabric_inset_mm=inset),
        "coupons": SimParams(mu_pa=31.5e3, jm=39.6, fabric_inset_mm=inset),
    }
    lifts = lift_sample(args.per_membrane, args.seed)
    df, keys, sample = lifts.df, lifts.keys, lifts.rows
    ringed = [k for k in keys if Membrane.from_key(k).rings]
    clock = Timing()
    rows = {key: df.iloc[sample[key]] for key in ringed}
    pts = {key: tuple(rows[key][c].to_numpy() for c in ("height_mm", "pressure_pa", "force_n")) for key in ringed}
    # every rubber x membrane x factor in one solve (the meshes stack: fe_forces)
    cases = [(name, key, fac) for name in rubbers for key in ringed for fac in args.ring_factors]
    jobs = [
        (Membrane.from_key(key), dataclasses.replace(rubbers[name], ring_mu_pa=rubbers[name].ring_mu_pa * fac))
        for name, key, fac in cases
    ]
    solved = dict(
        zip(
            cases,
            fe_forces(
                jobs, [pts[k][0] for _, k, _ in cases], [pts[k][1] for _, k, _ in cases], args.elements, progress=True
            ),
        )
    )
    out_rows = {}
    # per rubber and factor: the residuals [N] of the rows every factor solved, membrane after membrane
    solved_res = {name: {fac: [] for fac in args.ring_factors} for name in rubbers}
    for name, base in rubbers.items():
        out_rows[name] = {}
        for key in ringed:
            m = Membrane.from_key(key)
            h, p, f = pts[key]
            edges = [(g.inner_mm + inset, g.outer_mm - inset) for g in m.rings]
            forces, hoop = {}, {}
            for fac in args.ring_factors:
                res = solved[name, key, fac]
                # a plate the membrane does not reach carries nothing (the rig reads 0)
                forces[fac] = np.maximum(np.asarray(res.force_n), 0.0)
                r, R = np.asarray(res.r_mm).reshape(-1, res.R_mm.shape[-1])[0], np.asarray(res.R_mm)  # one mesh
                inside = np.zeros(r.shape, bool)
                for a, b in edges:
                    inside |= (r >= a) & (r <= b)
                hoop[fac] = float(np.nanmax(R[:, inside] / r[inside] - 1.0))
            common = np.all([np.isfinite(v) for v in forces.values()], axis=0)
            shoot = np.asarray(force_at(m, h, p, base).force_n)
            per = {
                f"{fac:g}": {
                    "rmse_n": float(np.sqrt(np.mean((f[common] - v[common]) ** 2))) if common.any() else None,
                    "unsolved": int(np.isnan(v).sum()),
                    "max_hoop_strain": hoop[fac],
                }
                for fac, v in forces.items()
            }
            out_rows[name][key] = {
                "factors": per,
                "rows_common": int(common.sum()),
                "fe_vs_shooting_max_n": float(np.nanmax(np.abs(forces[1.0] - shoot))) if 1.0 in forces else None,
            }
            for fac, v in forces.items():
                solved_res[name][fac].append((f - v)[common])
            print(f"{name} {key}: " + ", ".join(f"{k}x {v['rmse_n']:.2f}" for k, v in per.items()), flush=True)
    # pooled over the ringed membranes' rows that every factor of the rubber solved
    pooled = {
        name: {f"{fac:g}": float(np.sqrt(np.mean(np.concatenate(res) ** 2))) for fac, res in by_factor.items()}
        for name, by_factor in solved_res.items()
    }
    clock.stop()
    out = {
        "command": command(__file__, args),
        "seed": args.seed,
        "per_membrane": args.per_membrane,
        "map": x,
        "rubbers": {n: {"mu_pa": float(b.mu_pa), "jm": float(b.jm), "inset_mm": inset} for n, b in rubbers.items()},
        "rows": out_rows,
        "pooled_rmse_n": pooled,
        "timing": clock,
        "machine": machine(),
    }
    path = write_json(args.out / "real_rings_fe.json", out)
    for name, v in pooled.items():
        print(f"{name}: pooled RMSE by ring factor " + ", ".join(f"{k}x {r:.2f}" for k, r in v.items()))
    print(f"-> {path}")


if __name__ == "__main__":
    main()
