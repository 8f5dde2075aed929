"""The multi-fidelity model on the active-learning rig's first three membranes, with and
without the effect diagnosis names (issue 7's learning curves, item 6 of the product).

Truth: the virtual rig of ``experiments/active_learning.py`` (authors' constants,
pressure-sensor offset 150 Pa, sensor noise) on the simulator's planes (``--physics exact``,
default) or on the emulator (``--physics emulator``, the issue-5 figures). Data: the three
initial membranes of ``--seed``, the same rows the active-learning arms see. For each
effect set the issue-5 fit (``fit_multi_fidelity``: emcee over mu, J_m, the thickness
hierarchy and the effects' parameters, then the RPN discrepancy) on the same physics as the
truth (exact: simulator planes of the three membranes and of the six held-out ones) and
its held-out force RMSE [N] with and without the discrepancy; the nominal simulator alone
(no data) is the reference.

    python experiments/few_membranes_mf.py [--seed 0] [--mcmc-steps 4000] [--physics exact]

Writes ``experiments/out/few_membranes_mf.json`` (``few_membranes_mf_emulator.json`` with
``--physics emulator``).
"""

from __future__ import annotations

import json

import numpy as np

from _common import command, parser, timed, write_json  # experiments/ is on a script's path


def main() -> None:
    ap = parser(__doc__, seed=True)
    ap.add_argument("--mcmc-steps", type=int, default=4000, help="most emcee steps (the chain stops once converged)")
    ap.add_argument("--physics", choices=("exact", "emulator"), default="exact")
    ap.add_argument("--walkers", type=int, default=28)
    ap.add_argument("--rows", type=int, default=800)
    args = ap.parse_args()

    from active_learning import Lab, initial_designs  # experiments/ is on the path of a script run from it
    from mfdesign.calibration.workflow import fit_multi_fidelity, force_model_named
    from mfdesign._cache import enable_compilation_cache
    from mfdesign.data.measurements import Measurements
    from mfdesign.models.ensemble import EnsembleConfig
    from mfdesign.models.backends import force_model_for
    from mfdesign.models.predictive import MultiFidelity
    from mfdesign.physics.params import SimParams

    enable_compilation_cache()
    lab = Lab("simulator" if args.physics == "exact" else "emulator")
    h = lab.held

    def rmse(f):  # held-out rows the model has no value for are counted in the JSON, not hidden
        e = np.asarray(f, float) - h["force_n"]
        return float(np.sqrt(np.nanmean(e**2)))

    def n_nan(f):
        return int(np.sum(~np.isfinite(np.asarray(f, float))))

    table = Measurements.concat([lab.table(d, args.seed) for d in initial_designs(args.seed)])
    if args.physics == "exact":
        # Planes of the three fitted membranes and of the held-out six (the exact model holds
        # the designs it is asked about; it never extrapolates to others).
        from active_learning import HELD_OUT

        keys = tuple(dict.fromkeys([*table.df["design_key"], *HELD_OUT]))
        fm = force_model_for(
            "exact",
            keys,
            h_max_mm=float(max(table.df["height_mm"].max(), h["height_mm"].max())),
            p_max_pa=float(max(table.df["pressure_pa"].max(), h["pressure_pa"].max())),
            progress=True,
        )
        nominal = np.asarray(fm(h["design"], h["height_mm"], h["pressure_pa"], SimParams()))
        simulator_alone = float(np.sqrt(np.nanmean((nominal - h["force_n"]) ** 2)))
    else:
        fm = force_model_named("emulator")
        simulator_alone = lab.simulator_rmse()
    out = {
        "command": command(__file__, args),
        "membranes": [d.key() for d in initial_designs(args.seed)],
        "truth": {"effect": "pressure_sensor", "offset_pa": 150.0, "mu_pa": 31.7e3, "jm": 39.6},
        "physics": args.physics,
        "simulator_alone_rmse_n": simulator_alone,
        "fits": [],
    }
    cfg = EnsembleConfig(monotone=False, n_members=8, steps=1500, chunk=500, batch=100)
    for effects in ((), ("pressure_sensor",)):
        with timed() as t:
            fit = fit_multi_fidelity(
                table,
                fm,
                effects,
                n_steps=args.mcmc_steps,
                n_walkers=args.walkers,
                max_rows=args.rows,
                ensemble_config=cfg,
                seed=args.seed,
                progress=False,
            )
        fit_s = t["wall_s"]
        mf = fit.mf.thinned(32)
        bare = MultiFidelity(mf.model, mf.theta, None, mf.noise_n, mf.design_keys)
        post = fit.posterior
        row = {
            "effects": list(effects),
            "fit_s": fit_s,
            "convergence": {
                k: post.convergence.get(k) for k in ("converged", "steps_over_tau", "tau_max", "acceptance")
            },
            "posterior_median": {
                n: float(np.median(post.samples[:, i]))
                for i, n in enumerate(post.names)
                if not n.startswith("thickness[")
            },
            "heldout_rmse_n": rmse(
                mean := np.asarray(mf.predict(h["design"], h["height_mm"], h["pressure_pa"])).mean(0)
            ),
            "heldout_rows": int(len(mean)),
            "heldout_rows_without_prediction": n_nan(mean),
            "heldout_rmse_without_discrepancy_n": rmse(
                np.asarray(bare.predict(h["design"], h["height_mm"], h["pressure_pa"])).mean(0)
            ),
        }
        out["fits"].append(row)
        print(json.dumps(row), flush=True)
    path = write_json(
        args.out / ("few_membranes_mf.json" if args.physics == "exact" else "few_membranes_mf_emulator.json"), out
    )
    print(f"nominal simulator alone {out['simulator_alone_rmse_n']:.2f} N; wrote {path}", flush=True)


if __name__ == "__main__":
    main()
