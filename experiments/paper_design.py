"""The paper's design study (Campbell et al. 2025) against the real mass-lift data.

1. **Trajectories.** The five verification membranes lift 1.5 / 2.5 / 4.0 kg; way-points
   at 5 / 40 / 50 mm (measured pressure where the plate passes each height going up for
   the last time before the trial's top -- a resting plate's spikes are not the lift;
   ``mfdesign.models.trajectory.measured_waypoints`` -- the two trials of a mass averaged). Each membrane's way-points are a *target*. Error matrices
   (scaled trajectory RMSE, p_max 10 kPa; rows membranes, columns targets):
   ``measured`` (membrane m's measured pressures vs target t's) and ``model`` (the model's
   pressures for membrane m at target t's loads and heights vs target t's pressures; the
   diagonal is the paper's "known designs" error). For every target the optimiser designs
   a membrane (trajectory targeting, 0-2 rings) and its predicted error is reported.
2. **Height maximisation**, target sets A (6.9 kPa) and B (8.3 kPa) over the three masses:
   the score is the LogSumExp smooth minimum (tau = 15 mm, the authors' setting) of the
   three lift heights. Real scores of all seven membranes from the data (lift height where
   the trial's pressure first reaches the target; a trial that tops out below the target
   pressure is censored at its largest height), the model's scores of the same membranes
   (mean over members, and the members' spread), and the model-optimised design
   (predicted, member spread, the limits it sits on, simulator check). The paper: A 29.4
   vs 14.4 (average of prior designs), B 40.8 vs 25.7.

    python experiments/paper_design.py [--model DIR] [--starts 2500] [--no-check] [--name paper_design]

``--model``: any saved model folder (``mfdesign fit`` / ``mfdesign fit-mf``; default: an
RPN ensemble fitted once on all seven membranes and cached in
``experiments/out/paper_design_model``). A fit-mf model's winner is checked by the
simulator at its calibrated constants (posterior median), any other at the authors'.
Writes ``experiments/out/NAME.{json,png}`` and ``NAME_{A,B}.png``. The multi-fidelity
re-run (``paper_design_mf``):

    mfdesign fit-mf mass-lift --out experiments/out/paper_design_mf_model --physics emulator \
        --effects lift_preload --mcmc-steps 2500 --max-rows 400 --members 8 --delta-steps 1500
    python experiments/paper_design.py --model experiments/out/paper_design_mf_model \
        --name paper_design_mf --starts 500 --refine 16 --traj-refine 8
"""

from __future__ import annotations

import argparse
import json
from pathlib import Path

import numpy as np
import pandas as pd

from mfdesign.optimization import (
    HeightTargets,
    check_with_simulator,
    PAPER_WEIGHTS,
    TARGET_SETS,
    Waypoints,
    lift_heights,
    optimize,
    plot as plot_optimum,
    smooth_min,
)
from mfdesign.data.spa_design import load_mass_lift
from mfdesign.design import Membrane
from mfdesign.models.trajectory import P_MAX_PA, WAYPOINTS_MM, measured_waypoints, model_pressure

from _common import PAPER_DESIGN_MODEL, Timing, load, parser, timed, write_json  # experiments/ is on a script's path

NOTEBOOK_A = HeightTargets((24.525,) * 3, (4137.0, 5516.0, 6895.0))  # the authors' notebook variant


def get_model(path: Path | None, members: int, steps: int):
    """``(predictor, folder, (sim_params, constants))``: a saved model folder (any that
    ``mfdesign optimize --model`` reads), or the cached ensemble, fitted here the first time.
    The simulator check runs at the constants the model stands for: a fit-mf model's
    calibrated ones, else the authors'."""
    from mfdesign.workflows.models import load_fit, load_model, simulator_constants
    from mfdesign.models.ensemble import EnsembleConfig

    path = Path(path) if path else PAPER_DESIGN_MODEL
    if path.is_dir() and ((path / "ensemble.json").exists() or (path / "mf.json").exists()):
        fit = load_fit(path)
        return load_model(path, fit), str(path), simulator_constants(path, fit)
    if path != PAPER_DESIGN_MODEL:
        raise SystemExit(f"--model {path}: no ensemble.json nor mf.json there")
    data = load_mass_lift()
    a = data.arrays()
    cfg = EnsembleConfig(n_members=members, steps=steps, monotone=True)
    model = cfg.fit(a["design"], a["height_mm"], a["pressure_pa"], a["force_n"], a["weight"], key=0)
    model.ensemble.save(path)
    return model, str(path), simulator_constants(path)


def target_waypoints(data) -> pd.DataFrame:
    """Mean of the two trials' way-point pressures per (membrane, force, height)."""
    wp = measured_waypoints(data)
    wp["force_n"] = wp["force_n"].round(3)
    return wp.groupby(["design_key", "force_n", "h_mm"], sort=False)["p_pa"].mean().reset_index()


def scaled_rmse(p, q) -> float:
    ok = np.isfinite(p) & np.isfinite(q)
    return float(np.sqrt(np.mean(((p[ok] - q[ok]) / P_MAX_PA) ** 2))) if ok.any() else float("nan")


def real_lift_height(g: pd.DataFrame, p_target: float) -> tuple[float, bool]:
    """Height (mm) where a trial's pressure first reaches ``p_target`` going up; the trial's
    top height (censored = True) when it never does."""
    h, p = g["height_mm"].to_numpy(), g["pressure_pa"].to_numpy()
    if h[0] > h[-1]:
        h, p = h[::-1], p[::-1]
    hit = np.nonzero(p >= p_target)[0]
    if hit.size == 0:
        return float(h.max()), True
    j = hit[0]
    if j == 0 or p[j] == p[j - 1]:
        return float(h[j]), False
    return float(h[j - 1] + (p_target - p[j - 1]) / (p[j] - p[j - 1]) * (h[j] - h[j - 1])), False


def real_scores(data, targets: HeightTargets, tau: float) -> dict:
    df = data.df[data.df["experiment"] == "lift"]
    out = {}
    for key in data.design_keys:
        hs, cens = [], []
        for F, p in zip(targets.force_n, targets.p_pa):
            g = df[(df["design_key"] == key) & (np.abs(df["force_n"] - F) < 0.05)]
            vals = [real_lift_height(t, p) for _, t in g.groupby("trial")]
            hs.append(float(np.mean([v[0] for v in vals])))
            cens.append(any(v[1] for v in vals))
        out[key] = dict(
            h_mm=hs, censored=cens, score_mm=float(smooth_min(np.asarray(hs), tau)), min_h_mm=float(min(hs))
        )
    return out


def model_scores(predictor, keys, targets: HeightTargets, tau: float) -> dict:
    import jax
    import jax.numpy as jnp

    f = jax.jit(
        lambda d: lift_heights(
            predictor,
            d,
            jnp.asarray(targets.force_n),
            jnp.asarray(targets.p_pa),
            jnp.linspace(0.0, 80.0, 81),
            members=True,
        )[0]
    )
    out = {}
    for key in keys:
        hm = np.asarray(f(jnp.asarray(Membrane.from_key(key).to_array())))  # [members, loads]
        h = hm.mean(0)
        member_scores = np.asarray(smooth_min(hm, tau))  # each member's own score [members]
        out[key] = dict(
            h_mm=h.tolist(),
            h_std_mm=hm.std(0).tolist(),
            score_mm=float(smooth_min(h, tau)),
            score_member_std_mm=float(member_scores.std()),
            score_member_q05_q95_mm=np.quantile(member_scores, [0.05, 0.95]).tolist(),
            min_h_mm=float(h.min()),
        )
    return out


def sim_score(check: dict, tau: float) -> dict:
    """The smooth-min score [mm] of a simulator check's heights: a height past the check's
    grid counts as its top (so the score is a lower bound, ``at_least``); None when a load
    has no height at all."""
    hs, low = [], False
    for h, st in zip(check["h_sim_mm"], check["status"]):
        if h is None and st == "BEYOND_GRID":
            h, low = check.get("h_max_mm", 120.0), True
        if h is None:
            return dict(score_mm=None, at_least=False)
        hs.append(h)
    return dict(score_mm=float(smooth_min(np.asarray(hs), tau)), at_least=low)


def _sim_line(entry: dict) -> str:
    """Simulated smooth-min scores [mm]: optimised (and after its simulator search) vs the
    authors' design."""

    def fmt(sc):
        if not sc or sc.get("score_mm") is None:
            return "n/a"
        return (">= " if sc["at_least"] else "") + f"{sc['score_mm']:.1f}"

    o = entry["optimised"]
    parts = [f"optimised {fmt((o.get('simulator') or {}).get('score_mm'))}"]
    if o.get("simulator_refined"):
        parts.append(f"after its simulator search {fmt(o['simulator_refined']['check']['score_mm'])}")
    parts.append(f"authors' design {fmt((entry.get('authors_design_simulator') or {}).get('score_mm'))}")
    return ", ".join(parts) + " mm"


def trajectory_study(model, data, args) -> dict:
    wp = target_waypoints(data)
    keys = data.design_keys[:5]
    forces = sorted(wp["force_n"].unique())
    grid = [(F, h) for F in forces for h in WAYPOINTS_MM]

    def pressures(key):
        g = wp[wp["design_key"] == key].set_index(["force_n", "h_mm"])["p_pa"]
        return np.array([g.get((F, h), np.nan) for F, h in grid])

    measured = {k: pressures(k) for k in keys}
    Fg, hg = np.array([F for F, _ in grid]), np.array([h for _, h in grid])
    modelled = {k: model_pressure(model, Membrane.from_key(k).to_array(), Fg, hg) for k in keys}
    E_real = [[scaled_rmse(measured[m], measured[t]) for t in keys] for m in keys]
    E_model = [
        [scaled_rmse(np.where(np.isnan(modelled[m]), 2e4, modelled[m]), measured[t]) for t in keys] for m in keys
    ]
    designed = {}
    for t in keys:
        ok = np.isfinite(measured[t])
        problem = Waypoints(Fg[ok], measured[t][ok], hg[ok])
        with timed() as clock:  # (t is the target)
            # checked by the simulator (its height at each way-point's load and target
            # pressure against the way-point's height), but not refined on it: the
            # trajectory loss inverts 81 pressures per way-point, ~10x a height task's
            # simulator work per step
            res = optimize(
                model,
                problem,
                n_starts=args.starts,
                steps=args.traj_steps,
                n_refine=args.traj_refine,
                seed=args.seed,
                progress=False,
                check=args.check,
                sim_params=args.sim_params,
                sim_constants=args.sim_constants,
                sim_refine_steps=0,
            )
        designed[t] = dict(
            design_key=res.design_key,
            predicted_traj_rmse=res.prediction["traj_rmse"],
            model_traj_rmse_of_target_membrane=E_model[keys.index(t)][keys.index(t)],
            per_rings={r: v["loss"] for r, v in res.per_rings.items()},
            simulator=res.simulator,
            limits=res.limits,
            seconds=clock["wall_s"],
        )
        sim = res.simulator
        print(
            f"target {t}: designed {res.design_key}, predicted e_p {res.prediction['traj_rmse']:.3f} "
            f"(the target membrane itself, model: {designed[t]['model_traj_rmse_of_target_membrane']:.3f})"
            + (f"; simulator at the way-points: {sim['h_sim_mm']} mm vs {sim['h_model_mm']} mm" if sim else ""),
            flush=True,
        )
    diag = np.diag(np.asarray(E_model))
    print(
        f"model trajectory error on the five membranes (diagonal): mean {np.nanmean(diag):.3f} "
        f"(paper: 0.02 known designs)",
        flush=True,
    )
    return dict(
        membranes=keys,
        waypoints=[dict(force_n=F, h_mm=h) for F, h in grid],
        measured_p_pa={k: v.tolist() for k, v in measured.items()},
        model_p_pa={k: v.tolist() for k, v in modelled.items()},
        error_matrix_measured=E_real,
        error_matrix_model=E_model,
        model_diagonal_mean=float(np.nanmean(diag)),
        designed=designed,
    )


def height_study(model, data, args) -> dict:
    keys = data.design_keys
    prior, authors = keys[:5], {"A": keys[5], "B": keys[6]}
    tau = PAPER_WEIGHTS.temperature_mm
    predictor = model
    out = {}
    for name, targets in (("A", TARGET_SETS["A"]), ("B", TARGET_SETS["B"]), ("A_notebook", NOTEBOOK_A)):
        real = real_scores(data, targets, tau)
        mod = model_scores(predictor, keys, targets, tau)
        entry = dict(
            targets=dict(force_n=list(targets.force_n), p_pa=list(targets.p_pa)),
            real=real,
            model=mod,
            prior_real_mean_score_mm=float(np.mean([real[k]["score_mm"] for k in prior])),
            prior_model_mean_score_mm=float(np.mean([mod[k]["score_mm"] for k in prior])),
        )
        ak = authors.get(name[0])
        entry["authors_design"] = ak
        entry["authors_design_real_score_mm"] = real[ak]["score_mm"]
        if args.check and name in ("A", "B"):
            # the authors' own design on the simulator at the same constants: the yardstick
            # the optimum's simulated heights are set beside
            chk = check_with_simulator(
                Membrane.from_key(ak), targets.force_n, targets.p_pa, mod[ak]["h_mm"], args.sim_params
            )
            entry["authors_design_simulator"] = chk | {"score_mm": sim_score(chk, tau)}
        print(
            f"set {name}: real smooth-min score, authors' optimised {ak}: {real[ak]['score_mm']:.1f} mm vs "
            f"prior average {entry['prior_real_mean_score_mm']:.1f} mm (paper A 29.4 vs 14.4, B 40.8 vs 25.7); "
            f"model: {mod[ak]['score_mm']:.1f} vs {entry['prior_model_mean_score_mm']:.1f}",
            flush=True,
        )
        if name in ("A", "B"):
            with timed() as t:
                res = optimize(
                    model,
                    targets,
                    n_starts=args.starts,
                    steps=args.steps,
                    n_refine=args.refine,
                    seed=args.seed,
                    check=args.check,
                    sim_params=args.sim_params,
                    sim_constants=args.sim_constants,
                    progress=False,
                )
            entry["optimised"] = res.to_json()
            entry["optimised"]["seconds"] = t["wall_s"]
            if res.simulator:
                entry["optimised"]["simulator"]["score_mm"] = sim_score(res.simulator, tau)
            if res.simulator_refined:
                ref = entry["optimised"]["simulator_refined"]
                ref["check"]["score_mm"] = sim_score(ref["check"], tau)
            entry["optimised"]["model_scores"] = model_scores(predictor, [res.design_key], targets, tau)[
                res.design_key
            ]  # the same numbers as the membranes' (81-point grid, member spread of the score)
            args.out.mkdir(parents=True, exist_ok=True)
            plot_optimum(res, args.out / f"{args.name}_{name}.png", title=f"set {name}: {res.design_key}")
            p = res.prediction
            sim = res.simulator
            print(
                f"set {name}: optimised {res.design_key}: model score {p['score_mm']:.1f} mm (min {p['min_h_mm']:.1f}, "
                f"member std {np.round(p['h_member_std_mm'], 1).tolist()} mm); ratio to prior model mean "
                f"{p['score_mm'] / entry['prior_model_mean_score_mm']:.2f}"
                + (
                    f"; simulator heights {sim['h_sim_mm']} ({sim['status']}, {sim['constants']['constants']} constants)"
                    if sim
                    else ""
                )
                + (
                    f"\n  searched on the simulator near it: {res.simulator_refined['design_key']}, heights "
                    f"{res.simulator_refined['check']['h_sim_mm']} ({res.simulator_refined['why']})"
                    if res.simulator_refined
                    else ""
                )
                + "".join(f"\n  limit: {flag}" for flag in res.limits),
                flush=True,
            )
        out[name] = entry
    return out


def plot(result: dict, path: Path) -> None:
    import matplotlib

    matplotlib.use("Agg")
    import matplotlib.pyplot as plt

    tr, hs = result["trajectories"], result["height"]
    keys = tr["membranes"]
    fig, axes = plt.subplots(2, 3, figsize=(15, 9))
    for ax, name in zip(axes[0, :2], ("error_matrix_measured", "error_matrix_model")):
        E = np.asarray(tr[name])
        im = ax.imshow(E, cmap="viridis", vmin=0)
        for i in range(len(keys)):
            for j in range(len(keys)):
                ax.text(j, i, f"{E[i, j]:.2f}", ha="center", va="center", color="w", fontsize=8)
        ax.set_xticks(range(len(keys)), [f"T{j + 1}" for j in range(len(keys))])
        ax.set_yticks(range(len(keys)), [f"M{i + 1}" for i in range(len(keys))])
        ax.set_xlabel("target (membrane's measured way-points)")
        ax.set_ylabel("membrane" + (" (model)" if "model" in name else " (measured)"))
        ax.set_title(name.replace("_", " ") + " (scaled RMSE)", fontsize=9)
        fig.colorbar(im, ax=ax, fraction=0.046)
    ax = axes[0, 2]
    wps = tr["waypoints"]
    for i, k in enumerate(keys):
        m, q = np.asarray(tr["measured_p_pa"][k]), np.asarray(tr["model_p_pa"][k])
        ax.scatter(m / 1e3, q / 1e3, s=14, label=f"M{i + 1}")
    ax.plot([0, 10], [0, 10], "k--", lw=0.8)
    ax.set_xlabel("measured way-point pressure [kPa]")
    ax.set_ylabel("model pressure [kPa]")
    ax.set_title(f"way-points ({len(wps)} per membrane)", fontsize=9)
    ax.legend(fontsize=7)
    for ax, name in zip(axes[1, :2], ("A", "B")):
        e = hs[name]
        allk = list(e["real"])
        x = np.arange(len(allk))
        ax.bar(x - 0.2, [e["real"][k]["score_mm"] for k in allk], 0.4, label="real data")
        ax.bar(x + 0.2, [e["model"][k]["score_mm"] for k in allk], 0.4, label="model")
        if "optimised" in e:
            o = e["optimised"]
            ax.bar(len(allk), o["prediction"]["score_mm"], 0.4, color="C3", label="optimised (model)")
            allk = allk + [o["design_key"]]
        ax.set_xticks(range(len(allk)), [f"M{i + 1}" for i in range(len(allk) - 1)] + ["opt"])
        ax.set_ylabel("smooth-min lift height [mm]")
        ax.set_title(f"set {name} ({e['targets']['p_pa'][0] / 1e3:.1f} kPa): M6/M7 = authors' designs", fontsize=9)
        ax.legend(fontsize=7)
    axes[1, 2].axis("off")
    axes[1, 2].text(
        0,
        1,
        "\n".join(f"{k}: {v}" for k, v in result["summary"].items()),
        va="top",
        fontsize=7,
        family="monospace",
        wrap=True,
    )
    fig.tight_layout()
    fig.savefig(path, dpi=110)
    plt.close(fig)


def main():
    ap = parser(__doc__, seed=True)
    ap.add_argument("--model", type=Path, default=None)
    ap.add_argument("--members", type=int, default=16)
    ap.add_argument("--fit-steps", type=int, default=3000)
    ap.add_argument("--starts", type=int, default=2500)
    ap.add_argument("--refine", type=int, default=64)
    ap.add_argument("--steps", type=int, default=100)
    ap.add_argument("--traj-refine", type=int, default=32)
    ap.add_argument("--traj-steps", type=int, default=60)
    ap.add_argument("--check", action=argparse.BooleanOptionalAction, default=True)
    ap.add_argument("--name", default="paper_design", help="stem of the output files (NAME.json, NAME.png)")
    args = ap.parse_args()
    clock = Timing()
    data = load_mass_lift()
    model, model_path, (args.sim_params, args.sim_constants) = get_model(args.model, args.members, args.fit_steps)
    tr = trajectory_study(model, data, args)
    hs = height_study(model, data, args)
    summary = {
        "model diagonal traj RMSE": round(tr["model_diagonal_mean"], 4),
        **{
            f"{s} real authors/prior": f"{hs[s]['authors_design_real_score_mm']:.1f}/{hs[s]['prior_real_mean_score_mm']:.1f}"
            for s in ("A", "B")
        },
        **{
            f"{s} model opt/prior": f"{hs[s]['optimised']['prediction']['score_mm']:.1f}/{hs[s]['prior_model_mean_score_mm']:.1f}"
            for s in ("A", "B")
        },
        **{
            f"{s} authors' design model/real": "{:.1f} +- {:.1f} / {:.1f}".format(
                hs[s]["model"][hs[s]["authors_design"]]["score_mm"],
                hs[s]["model"][hs[s]["authors_design"]]["score_member_std_mm"],
                hs[s]["authors_design_real_score_mm"],
            )
            for s in ("A", "B")
        },
        **{
            f"{s} simulator check": (
                "not run"
                if not hs[s]["optimised"]["simulator"]
                else f"{hs[s]['optimised']['simulator']['h_sim_mm']} mm "
                f"({hs[s]['optimised']['simulator']['constants']['constants']} constants)"
            )
            for s in ("A", "B")
        },
        **{
            f"{s} simulator score": _sim_line(hs[s]) if hs[s]["optimised"]["simulator"] else "not run"
            for s in ("A", "B")
        },
        "paper": "A 29.4/14.4, B 40.8/25.7",
    }
    result = dict(
        model=model_path,
        simulator_constants=args.sim_constants,
        settings={k: v for k, v in vars(args).items() if k not in ("out", "sim_params", "sim_constants")}
        | {"model": model_path},
        trajectories=tr,
        height=hs,
        summary=summary,
        seconds=clock.elapsed(),
        load_average=load(),
    )
    write_json(args.out / f"{args.name}.json", result)
    plot(result, args.out / f"{args.name}.png")
    print(json.dumps(summary, indent=1), flush=True)


if __name__ == "__main__":
    main()
