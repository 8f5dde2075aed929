"""Does the plate touch the membrane beyond the disk? A probe on the real lifts.

The shooting solver, like the authors' model, lets only the rigid disk touch the plate.
At the real operating points its membrane rises beside the disk, above the plate's plane,
by up to tens of millimetres (``SimResult.max_rise_mm``). A plate wider than the disk
would stop it there: the membrane would lie against the plate and push on it. This probe
solves the same rows with the finite-element reference (``mfdesign.physics.fe.fe_force``)
with the plate as a frictionless penalty contact (``plate_contact_k`` [N/mm^3]) and asks
which of the two models the measured forces follow:

* ``rows``: per membrane, on ``--per-membrane`` floating lift rows (seed ``--seed``), the
  force RMSE [N] without contact (shooting) and with it (FE), at the paper's constants and
  at the all-seven MAP of ``real_floor.py`` (read from ``experiments/out/real_floor.json``),
  with the rise of the contact-free membrane above the plate. The FE without contact is
  solved too: it must agree with the shooting (the sample's check).
* ``penalty``: the contact force at two penalty stiffnesses (a converged penalty changes
  the force by far less than the rig's noise).
* ``rubber``: contact pushes the force up; could a softer rubber take it back? The pooled
  RMSE of the contact model over a grid of mu x J_m.

    python experiments/real_plate_contact.py

Writes ``experiments/out/real_plate_contact.json``. Exploratory, in sample for the MAP.
"""

from __future__ import annotations

import json
import warnings

import numpy as np

from _common import Timing, command, machine, parser, write_json  # experiments/ is on a script's path
from _real import lift_sample, real_floor


def main():
    ap = parser(__doc__, seed=True)
    ap.add_argument("--per-membrane", type=int, default=50, help="floating rows sampled per membrane")
    ap.add_argument("--k", type=float, nargs=2, default=[10.0, 1.0], help="penalty stiffnesses [N/mm^3]: used, check")
    ap.add_argument("--mu-kpa", type=float, nargs="+", default=[20.0, 25.0, 31.7, 40.0, 50.0, 65.0], help="rubber grid")
    ap.add_argument("--jm", type=float, nargs="+", default=[21.0, 39.6, 100.0], help="rubber grid")
    ap.add_argument("--elements", type=int, default=300, help="finite elements along r")
    args = ap.parse_args()

    from mfdesign.design import Membrane
    from mfdesign.physics.fe import fe_forces
    from mfdesign.physics.params import SimParams
    from mfdesign.physics.solve import force_at

    warnings.simplefilter("ignore")
    x = real_floor()["cases"]["all7"]["map"]
    rubbers = {
        "paper": SimParams(),
        "map": SimParams(mu_pa=x["mu_pa"], jm=x["jm"], fabric_inset_mm=x["fabric_inset.inset_mm"]),
    }
    lifts = lift_sample(args.per_membrane, args.seed)
    keys = lifts.keys
    rows = {k: lifts.df.iloc[idx] for k, idx in lifts.rows.items()}
    k_used, k_check = args.k

    clock = Timing()
    grid_params = {(mu, jm): SimParams(mu_pa=mu * 1e3, jm=jm) for mu in args.mu_kpa for jm in args.jm}
    # every membrane x constants x penalty this probe scores, in one solve (the meshes
    # stack: fe_forces); looked up by (membrane, constants, penalty)
    cases = [(key, params, k) for key in keys for params in rubbers.values() for k in (0.0, k_used)]
    cases += [(key, rubbers["paper"], k_check) for key in keys]
    cases += [(key, params, k_used) for params in grid_params.values() for key in keys]
    cases = list(dict.fromkeys(cases))  # SimParams are frozen dataclasses: equal ones solve once
    solved = fe_forces(
        [(Membrane.from_key(key), params) for key, params, _ in cases],
        [rows[key]["height_mm"].to_numpy() for key, _, _ in cases],
        [rows[key]["pressure_pa"].to_numpy() for key, _, _ in cases],
        args.elements,
        plate_contact_k=[k for _, _, k in cases],
        progress=True,
    )
    # a plate the membrane does not reach carries no force (the rig reads 0; the FE's
    # envelope force is then negative, the shooting reports NO_CONTACT with 0)
    forces = {case: np.maximum(np.asarray(res.force_n), 0.0) for case, res in zip(cases, solved)}

    def fe(key, params, k):
        return forces[key, params, k]

    def rmse(f, fm):
        ok = np.isfinite(fm)
        return float(np.sqrt(np.mean((f[ok] - fm[ok]) ** 2))) if ok.any() else None

    per = {}
    for key in keys:
        f = rows[key]["force_n"].to_numpy()
        per[key], touched = {}, {}
        for name, params in rubbers.items():
            shoot = force_at(
                Membrane.from_key(key), rows[key]["height_mm"].to_numpy(), rows[key]["pressure_pa"].to_numpy(), params
            )
            free, touch = fe(key, params, 0.0), fe(key, params, k_used)
            touched[name] = touch
            rise = np.asarray(shoot.max_rise_mm)
            fs = np.asarray(shoot.force_n)
            per[key][name] = {
                "rmse_no_contact_n": rmse(f, fs),
                "rmse_contact_n": rmse(f, touch),
                "mean_contact_minus_free_n": float(np.nanmean(touch - fs)),
                "fe_vs_shooting_max_n": float(np.nanmax(np.abs(free - fs))),
                "rise_mm_median": float(np.nanmedian(rise)),
                "rise_mm_max": float(np.nanmax(rise)),
                "rows_rising_1mm": int(np.sum(rise > 1.0)),
                "unsolved_contact": int(np.isnan(touch).sum()),
            }
        per[key]["penalty_check_max_n"] = float(
            np.nanmax(np.abs(touched["paper"] - fe(key, rubbers["paper"], k_check)))
        )
        print(
            f"{key}: {json.dumps({n: round(v['rmse_contact_n'], 2) for n, v in per[key].items() if isinstance(v, dict)})}",
            flush=True,
        )

    def pooled(name, field):
        return float(np.sqrt(np.mean([per[k][name][field] ** 2 for k in keys])))

    grid = []
    for (mu, jm), params in grid_params.items():
        res = np.concatenate([rows[k]["force_n"].to_numpy() - fe(k, params, k_used) for k in keys])
        ok = np.isfinite(res)
        grid.append(
            {"mu_kpa": mu, "jm": jm, "rmse_n": float(np.sqrt(np.mean(res[ok] ** 2))), "unsolved": int((~ok).sum())}
        )
    best = min(grid, key=lambda g: g["rmse_n"])
    clock.stop()
    out = {
        "command": command(__file__, args),
        "seed": args.seed,
        "per_membrane": args.per_membrane,
        "k_n_per_mm3": {"used": k_used, "check": k_check},
        "map": x,
        "rows": per,
        "pooled": {
            name: {"no_contact_n": pooled(name, "rmse_no_contact_n"), "contact_n": pooled(name, "rmse_contact_n")}
            for name in rubbers
        },
        "rubber_grid_contact": grid,
        "best_contact_rubber": best,
        "timing": clock,
        "machine": machine(),
    }
    path = write_json(args.out / "real_plate_contact.json", out)
    for name, v in out["pooled"].items():
        print(
            f"{name}: pooled RMSE no contact {v['no_contact_n']:.2f} N, plate contact {v['contact_n']:.2f} N "
            f"({v['contact_n'] / v['no_contact_n']:.2f}x)"
        )
    print(f"best rubber with contact: mu {best['mu_kpa']} kPa, J_m {best['jm']}: {best['rmse_n']:.2f} N -> {path}")


if __name__ == "__main__":
    main()
