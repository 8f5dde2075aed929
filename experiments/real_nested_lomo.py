"""Nested leave-one-membrane-out on the 7 real mass-lift membranes (issue 42 item 2).

The page's variant was the best of eight scored on the same seven held-out membranes: a
selection on the test folds. Here the choice is made inside each fold. For outer fold m
(membrane m held out, T = the other six) and each candidate variant v, an inner
leave-one-membrane-out on T scores v with a **MAP plug-in** of its calibrated physics (no
MCMC, no discrepancy): v's hierarchical model is fitted at its MAP on T minus {j}
(``mfdesign.calibration.mcmc.map_on_lattice``: the MAP as ``calibrate`` finds it before
sampling, the exact lattice grown around it) and predicts j's floating lift rows at the MAP,
a new membrane at its nominal thickness. Inner score = pooled force RMSE over the six inner
folds (row-count weighted); the inner scaled trajectory RMSE is recorded beside it. The
variant with the lowest inner score, v*(m), is chosen; its outer score is v*(m)'s committed
fold row for membrane m (its full fit, MCMC + discrepancy, trained on T: no leak). The
training set of (m, j) is all but {m, j}: 21 distinct five-membrane fits per variant.

Candidates (``--variants``): folders under experiments/out holding each variant's committed
``real_mass_lift.json`` (its ``settings`` give effects, lattice, rubber, latents).

    python experiments/real_nested_lomo.py [--variants DIR ...] [--only-variant DIR] [--measure]

``--measure``: one five-membrane MAP per variant, timed, no table (how long the planes take).
Checkpoints: one JSON per (variant, pair) under ``OUT/cache/real_nested_lomo/``. Writes the
held-out result under the default file names, ``OUT/real_mass_lift.{json,png}`` (issue 42:
"the default file names hold this run"; each variant's own run is in its folder).
"""

from __future__ import annotations

import itertools
import json
import logging
import os
import time
import warnings

import numpy as np

from _common import OUT, Timing, parser, write_json  # experiments/ is on a script's path

# the eight variants of docs/real_data.md, in the page's order (folder under experiments/out)
VARIANTS = (
    "real_mass_lift_free_latents",
    "real_mass_lift_jm_coupons",
    "real_mass_lift_material_coupons",
    "real_mass_lift_material_nolatents",
    "real_mass_lift_nolatents",
    "real_mass_lift_rings",
    "real_mass_lift_rings_coupons",
    "real_mass_lift_rings_coupons_tensor",
)
BEST_OF_EIGHT = "real_mass_lift_rings_coupons_tensor"  # the page's recommended variant
E = "e_multi_fidelity"


def _committed(folder: str) -> dict:
    return json.loads((OUT / folder / "real_mass_lift.json").read_text())


def _material(s: dict) -> str:
    return "coupons" if s.get("material_coupons") else "coupons-jm" if s.get("jm_coupons") else "free"


def _pooled(rows: list[dict]) -> dict:
    """Pooled figures as experiments/real_mass_lift.py pools them (row-count weighted)."""
    w = np.array([x["n"] for x in rows], float)
    traj = [x["traj_rmse_p"] for x in rows]
    return {
        "rmse_n": float(np.sqrt(np.sum(w * np.array([x["rmse_n"] for x in rows]) ** 2) / w.sum())),
        "coverage90": float(np.sum(w * np.array([x["coverage90"] for x in rows])) / w.sum()),
        "traj_mean": float(np.mean(traj)),
        "traj_median": float(np.median(traj)),
    }


class MapFit:
    """One variant's MAP plug-in: fit on some membranes, predict a new one at nominal thickness."""

    def __init__(self, folder, data, force_models, max_rows):
        from mfdesign.calibration.workflow import material_priors

        self.folder = folder
        self.s = _committed(folder)["settings"]
        self.data = data
        self.max_rows = int(self.s.get("max_rows", max_rows))
        axes = self.s["effect_axes"]
        if axes not in force_models:
            from mfdesign.calibration.workflow import force_model_named

            # one force model over all seven membranes, as real_mass_lift.py builds it
            force_models[axes] = force_model_named("exact", data, progress=False, effect_axes=axes)
        self.fm = force_models[axes]
        self.priors = material_priors(_material(self.s))

    def fit(self, train_keys, seed):
        """The MAP on ``train_keys``: ``(model, x, seconds)``, the lattice grown around it."""
        import equinox as eqx

        from mfdesign.calibration.mcmc import map_on_lattice
        from mfdesign.calibration.workflow import model_for
        from mfdesign.models.hierarchical import CalibrationData

        train = self.data.subset(train_keys)
        # the calibration's rows as fit_multi_fidelity builds them
        cal = CalibrationData.from_measurements(train, max_rows=self.max_rows, seed=seed)
        n_trials = train.df.groupby(["design_key", "trial"]).ngroups
        cal = cal.padded(max(len(cal), self.max_rows + n_trials))
        model = model_for(
            self.fm,
            cal.design_keys,
            tuple(self.s["effects"]),
            likelihood="student_t",
            membrane_latents=not self.s.get("no_latents", False),
            membrane_effects=tuple(self.s.get("per_membrane") or ()),
            **self.priors,
        )
        # as calibrate() does: the optimiser sees the lattice's edge clamped, not NaN
        model = eqx.tree_at(lambda m: m.force_model, model, model.force_model.strict(False))
        t0 = time.perf_counter()
        model, res = map_on_lattice(model, cal, starts=4, seed=seed)
        # the next fit starts from this lattice (it only grows): the lattice's rounds and the
        # MAP kernel's compilations are paid once a variant, not once a fit (the first fit of
        # rings_coupons: 343 s, nearly all of it growth rounds and compiling)
        self.fm = model.force_model
        return model, res, cal.design_keys, time.perf_counter() - t0

    def predict(self, model, res, design_keys, test_key, waypoints) -> dict:
        """Force RMSE [N] on ``test_key``'s floating rows and its scaled trajectory RMSE, at the
        MAP, the membrane new to the model at its nominal thickness."""
        import jax.numpy as jnp

        from mfdesign.models.predictive import MultiFidelity
        from mfdesign.models.trajectory import trajectory_errors

        x = np.asarray(res.x, float).copy()
        if "thickness_sd" in model.names:  # a new membrane at its nominal thickness
            x[model.names.index("thickness_sd")] = 0.0
        noise = float(x[model.names.index("noise_n")])
        mf = MultiFidelity(model, jnp.asarray(x[None]), None, noise, tuple(design_keys))
        dat = mf.data_for(None, None, None, table=self.data.subset([test_key]))
        f = np.asarray(dat.force_n)
        mean = np.asarray(mf.sample_data(dat))[0]
        ok = np.isfinite(mean)
        _, traj = trajectory_errors(mf.predictor(1), waypoints[waypoints["design_key"] == test_key])
        return {
            "test": test_key,
            "rmse_n": float(np.sqrt(np.mean((f[ok] - mean[ok]) ** 2))),
            "n": int(ok.sum()),
            "n_without_prediction": int((~ok).sum()),
            "traj_rmse_p": traj[test_key]["traj_rmse_p"],
        }

    def fit_predict(self, train_keys, test_keys, seed, waypoints) -> list[dict]:
        t0 = time.perf_counter()
        model, res, dk, t_map = self.fit(train_keys, seed)
        fit = {
            "train": list(train_keys),
            "map": {k: float(v) for k, v in zip(model.names, np.asarray(res.x, float)) if "[" not in k},
            "map_converged": bool(res.converged),
            "seconds_map": t_map,
        }
        rows = [{**self.predict(model, res, dk, k, waypoints), **fit} for k in test_keys]
        for r in rows:
            r["seconds"] = time.perf_counter() - t0
        return rows


def main():
    ap = parser(__doc__, seed=True)
    ap.add_argument("--variants", nargs="+", default=list(VARIANTS), help="candidate variants (folders)")
    ap.add_argument("--only-variant", default=None, help="compute only this variant's pairs (checkpoints), no table")
    ap.add_argument("--measure", action="store_true", help="one five-membrane MAP per variant, timed")
    args = ap.parse_args()

    from mfdesign._x64 import enable_x64
    from mfdesign.data.spa_design import load_mass_lift
    from mfdesign.models.trajectory import measured_waypoints

    enable_x64()
    warnings.simplefilter("ignore")
    logging.basicConfig(format="%(asctime)s %(message)s", datefmt="%H:%M:%S")
    logging.getLogger("mfdesign.models.exact").setLevel(logging.INFO)
    clock = Timing()
    load0 = os.getloadavg()
    data = load_mass_lift()
    keys = list(data.design_keys)
    waypoints = measured_waypoints(data)
    force_models: dict = {}
    cache = args.out / "cache" / "real_nested_lomo"
    cache.mkdir(parents=True, exist_ok=True)

    if args.measure:
        times = {}
        for v in [args.only_variant] if args.only_variant else args.variants:
            t0 = time.perf_counter()
            fitter = MapFit(v, data, force_models, 400)
            (r,) = fitter.fit_predict(keys[2:], [keys[0]], args.seed, waypoints)
            times[v] = {"seconds_total": time.perf_counter() - t0, **r}
            print(f"{v}: {times[v]['seconds_total']:.0f} s, held out {keys[0]}: {r['rmse_n']:.2f} N", flush=True)
        write_json(cache / f"measure_{os.getpid()}.json", times, indent=1, default=float)
        return

    # outer fold m's inner fold j trains on all but {m, j} and predicts j; outer fold j's inner
    # fold m trains on the same five and predicts m: one fit per pair predicts both
    pairs = list(itertools.combinations(range(len(keys)), 2))
    inner = {}  # (variant, test index, left-out index) -> row
    for v in [args.only_variant] if args.only_variant else args.variants:
        fitter = None
        for a, b in pairs:
            path = cache / f"{v}_{a}{b}.json"
            if path.exists():
                saved = json.loads(path.read_text())
            else:
                fitter = fitter or MapFit(v, data, force_models, 400)
                train = [k for i, k in enumerate(keys) if i not in (a, b)]
                # one five-membrane fit predicts both left-out membranes
                saved = {"variant": v, "rows": fitter.fit_predict(train, [keys[a], keys[b]], args.seed, waypoints)}
                write_json(path, saved, indent=1, default=float)
                r0, r1 = saved["rows"]
                print(
                    f"{v} pair ({a}, {b}): {r0['rmse_n']:.2f} / {r1['rmse_n']:.2f} N "
                    f"({r0['seconds']:.0f} s; load {os.getloadavg()[0]:.2f})",
                    flush=True,
                )
            inner[(v, a, b)] = saved["rows"][0]  # fitted without a, b; predicts a
            inner[(v, b, a)] = saved["rows"][1]  # predicts b
    if args.only_variant:
        print(f"{args.only_variant} done (--only-variant: no table)", flush=True)
        return

    # outer fold m: inner folds j != m predict j from all-but-{m, j}
    committed = {v: _committed(v) for v in args.variants}
    inner_scores, choice, nested_rows = {}, {}, []
    for m, key in enumerate(keys):
        scores = {}
        for v in args.variants:
            rows = [inner[(v, j, m)] for j in range(len(keys)) if j != m]
            w = np.array([r["n"] for r in rows], float)
            scores[v] = {
                "force_rmse_n": float(np.sqrt(np.sum(w * np.array([r["rmse_n"] for r in rows]) ** 2) / w.sum())),
                "traj_mean": float(np.mean([r["traj_rmse_p"] for r in rows])),
            }
        best = min(scores, key=lambda v: scores[v]["force_rmse_n"])
        inner_scores[key], choice[key] = scores, best
        (row,) = [r for r in committed[best]["folds"][E] if r["membrane"] == key]
        nested_rows.append(
            {"membrane": key, "variant": best, **{k: row[k] for k in ("rmse_n", "traj_rmse_p", "coverage90", "n")}}
        )
        print(
            f"outer {m} {key}: chose {best} ({scores[best]['force_rmse_n']:.2f} N inner) -> {row['rmse_n']:.2f} N",
            flush=True,
        )
    rec = committed.get(BEST_OF_EIGHT) or _committed(BEST_OF_EIGHT)
    best_rows = [
        {
            "membrane": r["membrane"],
            "variant": BEST_OF_EIGHT,
            **{k: r[k] for k in ("rmse_n", "traj_rmse_p", "coverage90", "n")},
        }
        for r in rec["folds"][E]
    ]
    out = {
        "what": "nested leave-one-membrane-out: the variant chosen inside each fold, scored on the held-out membrane (issue 42 item 2)",
        "settings": {
            **{k: v for k, v in vars(args).items() if k not in ("out", "only_variant", "measure")},
            "inner_criterion": "pooled force RMSE [N] of a MAP plug-in (no MCMC, no discrepancy) over the inner leave-one-membrane-out on the six training membranes; a new membrane at its nominal thickness",
            "outer_score": "the chosen variant's committed (e) multi-fidelity fold row (MCMC + discrepancy, trained on the six)",
            "map": "mfdesign.calibration.mcmc.map_on_lattice, 4 BFGS starts, the variant's max_rows rows, seed",
        },
        "candidates": {v: committed[v]["settings"] for v in args.variants},
        "inner_scores": inner_scores,
        "choice": choice,
        "nested": {"folds": nested_rows, "pooled": _pooled(nested_rows)},
        "best_of_eight": {
            "variant": BEST_OF_EIGHT,
            "note": "the best of eight scored on these same held-out membranes: a selection on the test folds",
            "folds": best_rows,
            "pooled": _pooled(best_rows),
        },
        "inner_fits": {f"{v} | {keys[a]} | without {keys[b]}": r for (v, a, b), r in inner.items()},
        "load_avg": {"start": load0, "end": os.getloadavg()},
        "seconds": clock.elapsed(),
        "seconds_inner_fits": float(sum(r["seconds"] for (v, a, b), r in inner.items() if a < b)),
    }
    write_json(args.out / "real_mass_lift.json", out, indent=1, default=float)
    print(json.dumps({"nested": out["nested"]["pooled"], "best_of_eight": out["best_of_eight"]["pooled"]}, indent=1))
    _plot(out, args.out / "real_mass_lift.png")


def _plot(out, path):
    import matplotlib

    matplotlib.use("Agg")
    import matplotlib.pyplot as plt

    nested, best = out["nested"]["folds"], out["best_of_eight"]["folds"]
    # the membrane's first three design numbers and, below, the variant its fold chose
    labels = [
        "["
        + ", ".join(r["membrane"].strip("[]").split(", ")[:3])
        + ", ...]\n"
        + r["variant"].removeprefix("real_mass_lift_")
        for r in nested
    ]
    fig, axes = plt.subplots(1, 3, figsize=(13, 4.2))
    x = np.arange(len(nested))
    for ax, metric, label in zip(
        axes, ("rmse_n", "traj_rmse_p", "coverage90"), ("force RMSE [N]", "scaled trajectory RMSE", "90 % coverage")
    ):
        ax.bar(x - 0.2, [r[metric] for r in nested], 0.4, label="nested (chosen inside the folds)", color="C0")
        ax.bar(x + 0.2, [r[metric] for r in best], 0.4, label="best of eight (chosen on the test folds)", color="C2")
        ax.set_xticks(x, labels, rotation=60, ha="right", fontsize=6)
        ax.set_title(label, fontsize=9)
        if metric == "coverage90":
            ax.axhline(0.9, color="k", lw=0.8, ls="--")
    axes[0].legend(fontsize=7)
    pn, pb = out["nested"]["pooled"], out["best_of_eight"]["pooled"]
    fig.suptitle(
        f"real mass-lift, held out per membrane, (e) multi-fidelity: nested leave-one-membrane-out "
        f"(pooled {pn['rmse_n']:.2f} N) vs the best of eight (pooled {pb['rmse_n']:.2f} N, optimistic)",
        fontsize=9,
    )
    fig.tight_layout()
    fig.savefig(path, dpi=110)
    plt.close(fig)


if __name__ == "__main__":
    main()
