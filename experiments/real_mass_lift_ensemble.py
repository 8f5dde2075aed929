"""Leave-one-membrane-out on the 7 real mass-lift membranes: RPN ensemble vs curve fit.

For each held-out membrane both models are fitted on the other six (lift data: the force
is the lifted weight, the inputs the measured height and pressure; per-trial weights from
the file). Reported per fold and pooled: force RMSE [N] at the measured (h, p), median
absolute error, 68/95 % coverage, and the paper's scaled trajectory RMSE (way-points at
5/40/50 mm per mass, p_max 10 kPa, h_max 50 mm; see ``mfdesign.models.trajectory``) on the
held-out membrane ("new designs") and, for the ensemble fitted on all 7, on the training
membranes ("known designs").

    python experiments/real_mass_lift_ensemble.py [--steps 10000] [--members 32]

Writes ``experiments/out/real_mass_lift_ensemble.{json,png}``.
"""

from __future__ import annotations

import numpy as np
import pandas as pd

from mfdesign.data.spa_design import load_mass_lift
from mfdesign.models.baselines import CurveFitConfig
from mfdesign.models.cv import cross_validate
from mfdesign.models.ensemble import EnsembleConfig
from mfdesign.models.trajectory import measured_waypoints, trajectory_errors

from _common import machine, parser, timed, write_json  # experiments/ is on a script's path


def loo_trajectories(models, folds, waypoints):
    """Score each fold's held-out membrane's trajectory with that fold's fitted model."""
    per, rows = {}, []
    for model, (train, test) in zip(models, folds):
        wp = waypoints[waypoints["design_key"].isin(test.design_keys)]
        table, summary = trajectory_errors(model, wp)
        per.update(summary)
        rows.append(table)
    table = pd.concat(rows)
    e = (table["p_model_pa"] - table["p_pa"]) / 1e4
    return per, float(np.sqrt(np.mean(e**2))), float(np.sqrt(table["dist2"].mean())), table


def main():
    ap = parser(__doc__, seed=True)
    ap.add_argument("--steps", type=int, default=10_000)
    ap.add_argument("--members", type=int, default=32)
    ap.add_argument("--curve-degree", type=int, default=1)
    args = ap.parse_args()

    data = load_mass_lift()
    folds = data.leave_one_out()
    waypoints = measured_waypoints(data)
    specs = {
        "ensemble": EnsembleConfig(n_members=args.members, steps=args.steps, monotone=True),
        "curve_fit": CurveFitConfig(degree=args.curve_degree),
    }
    result = {
        "data": "mass_lift_data_dictionary_N_Pa.pkl (7 membranes, 45,924 rows)",
        "protocol": "leave-one-membrane-out; force = lifted weight at measured (h, p)",
        "machine": machine(),
        "models": {},
    }
    tables = {}
    for name, spec in specs.items():
        with timed() as t:
            cv = cross_validate(spec, folds, seed=args.seed, keep_models=True)
            per, traj_p, traj_d, table = loo_trajectories(cv.models, folds, waypoints)
        tables[name] = (cv, table)
        result["models"][name] = {
            "config": spec.__dict__ if not hasattr(spec, "to_dict") else spec.to_dict(),
            "cv": cv.to_json(),
            "trajectory_new_designs": per,
            "trajectory_rmse_p_new": traj_p,
            "trajectory_rmse_dist_new": traj_d,
            "seconds": t["wall_s"],
        }
        print(
            f"{name}: force RMSE {cv.overall['rmse_n']:.2f} N (fold mean "
            f"{cv.overall['fold_rmse_mean_n']:.2f}), trajectory RMSE new designs {traj_p:.3f} "
            f"(dist {traj_d:.3f})",
            flush=True,
        )
    # the ensemble on known designs: fit on all 7, score the same 7
    a = data.arrays()
    full = specs["ensemble"].fit(
        a["design"], a["height_mm"], a["pressure_pa"], a["force_n"], a["weight"], key=args.seed, progress=False
    )
    table, per = trajectory_errors(full, waypoints)
    result["models"]["ensemble"]["trajectory_table_known"] = table.to_dict(orient="records")
    e = (table["p_model_pa"] - table["p_pa"]) / 1e4
    result["models"]["ensemble"]["trajectory_known_designs"] = per
    result["models"]["ensemble"]["trajectory_rmse_p_known"] = float(np.sqrt(np.mean(e**2)))
    print(f"ensemble, known designs: trajectory RMSE {np.sqrt(np.mean(e**2)):.3f}")
    write_json(args.out / "real_mass_lift_ensemble.json", result)
    plot(tables, waypoints, args.out / "real_mass_lift_ensemble.png")


def plot(tables, waypoints, path):
    import matplotlib

    matplotlib.use("Agg")
    import matplotlib.pyplot as plt

    keys = list(dict.fromkeys(waypoints["design_key"]))
    fig, axes = plt.subplots(1, 2, figsize=(13, 5))
    width = 0.38
    for j, (name, (cv, _)) in enumerate(tables.items()):
        rm = [next(f["rmse_n"] for f in cv.folds if f["test_membranes"] == [k]) for k in keys]
        axes[0].bar(np.arange(len(keys)) + (j - 0.5) * width, rm, width, label=name)
    axes[0].set_xticks(range(len(keys)), keys, rotation=30, ha="right", fontsize=7)
    axes[0].set_ylabel("held-out force RMSE [N]")
    axes[0].legend()
    axes[0].set_title("leave-one-membrane-out, real mass-lift data")
    for marker, (name, (_, table)) in zip("ox", tables.items()):
        axes[1].scatter(table["p_pa"] / 1e3, table["p_model_pa"] / 1e3, marker=marker, label=name, alpha=0.7)
    axes[1].plot([0, 10], [0, 10], "k--", lw=0.8)
    axes[1].set_xlabel("measured way-point pressure [kPa]")
    axes[1].set_ylabel("model pressure at (F, h) [kPa]")
    axes[1].set_title("way-points 5/40/50 mm, held-out membranes")
    axes[1].legend()
    fig.tight_layout()
    fig.savefig(path, dpi=120)


if __name__ == "__main__":
    main()
