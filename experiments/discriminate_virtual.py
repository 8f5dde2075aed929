"""Issue 42 item 5: does the discrimination tool's top experiment decide between two
hypotheses that fit the passive data equally well, and at what cost do random experiments?

Truth: the virtual rig (stand-in simulator, ``mfdesign.models.standin``) with ONE hidden
effect, either

* ``fabric_inset`` (the disk's effective radius shrinks by the inset: force x ((c - i) / c)^2), or
* ``load_cell_gain`` (a user effect defined in this file, "written in one short file" as
  docs/effects.md says: every force-trial reading x gain; a lift reads no load cell).

Passive data: force sweeps (0, 20, 40 mm) of two membranes with the same contact radius
c = 25.4 mm. On them the two hypotheses are the same scale factor of the force: they fit
equally well (their BIC probabilities are printed). They part on a membrane with another
contact radius (the inset's share of the radius changes) and on mass lifts (the gain does
not touch them).

Per case (truth x seed): fit both hypotheses (``fit_multi_fidelity``, stand-in physics,
small settings), rank the candidates (``mfdesign.discriminate.rank_experiments``), run the
top experiment on the virtual rig, add it, refit both, and compute the hypotheses'
posterior probabilities from their BIC on all data. Random baseline: candidates drawn at
random (seeded) and run until their summed cost first reaches 1x, then 2x the top
experiment's cost, refitting at each.

    nice -n 19 python experiments/discriminate_virtual.py [--seeds 5] [--fresh]

Writes ``experiments/out/discriminate_virtual.json`` and ``.png``; each finished case is
kept in ``experiments/out/discriminate_virtual_cases/`` so a killed run resumes.
"""

from __future__ import annotations

import argparse
import json
import os
import sys
import time
from pathlib import Path

os.environ.setdefault("JAX_PLATFORMS", "cpu")

import jax.numpy as jnp
import numpy as np

from mfdesign.physics.effects import MeasurementEffect, Normal, Parameter, register_effect

ROOT = Path(__file__).resolve().parents[1]
OUT = ROOT / "experiments" / "out"
CASES = OUT / "discriminate_virtual_cases"


@register_effect
class LoadCellGain(MeasurementEffect):
    """Force trials read ``gain * F`` [N]; a lift reads no load cell (its force is the weight)."""

    name = "load_cell_gain"
    story = "the load cell's calibration factor is off: every force reading is scaled"
    direct_check = "hang known weights on the load cell"
    parameters = (Parameter("gain", "1", Normal(1.0, 0.05, 0.7, 1.3), 1.0, 1.05, "reading / true force"),)

    def observed_force_fn(self, theta, force_fn, rows):
        return lambda h, p: force_fn(h, p) * jnp.where(rows.is_force, theta["gain"], 1.0)


PASSIVE = ("[2.0, 25.4, nan, nan, nan, nan]", "[2.33, 25.4, 37.63, 5.0, 62.0, 5.0]")
NEW = (
    "[2.0, 15.0, nan, nan, nan, nan]",
    "[2.0, 20.0, nan, nan, nan, nan]",
    "[1.5, 30.0, nan, nan, nan, nan]",
    "[2.0, 35.0, nan, nan, nan, nan]",
)
HYPOTHESES = ("fabric_inset", "load_cell_gain")
FIT = dict(n_steps=200, max_rows=400)
TARGET = 0.95


def make_rig(truth: str, value: float, seed: int, heights=(0.0, 20.0, 40.0), p_max=None, masses=(1.5,)):
    from mfdesign.models.standin import standin_plane
    from mfdesign.physics.params import SimParams
    from mfdesign.rig.virtual import Protocol, VirtualRig

    extra = {} if p_max is None else dict(ringed_limits_pa=(p_max,), ringless_limit_pa=p_max)
    param = {"fabric_inset": "fabric_inset.inset_mm", "load_cell_gain": "load_cell_gain.gain"}[truth]
    return VirtualRig(
        effects=[truth],
        theta={param: value},
        seed=seed,
        protocol=Protocol(
            sample_hz=1.0,
            trials_per_height=1,
            heights_mm=tuple(heights),
            lift_masses_kg=tuple(masses),
            lift_trials=1,
            **extra,
        ),
        simulator=standin_plane,
        base_params=SimParams(mu_pa=34e3, jm=45.0),
    )


def run_experiment(e, truth, value, seed, table):
    """The experiment on the virtual rig (its own protocol), trial ids after the membrane's."""
    from mfdesign.data.measurements import Measurements
    from mfdesign.design import Membrane

    m = Membrane.from_array(e.design)
    df = table.df
    prev = df[df["design_key"] == m.key()]
    first = int(prev["trial"].max()) + 1 if len(prev) else 0
    if e.kind == "force":
        rig = make_rig(truth, value, seed + 1000 + first, e.heights_mm, p_max=e.p_max_pa)
        new = rig.characterise(m, first_trial=first)
    else:
        rig = make_rig(truth, value, seed + 1000 + first, masses=(e.load_n / 9.80665,))
        new = rig.mass_lift(m, first_trial=first)
    return Measurements(__import__("pandas").concat([df, new.df], ignore_index=True))


def fit_all(table, seed):
    from mfdesign.calibration.workflow import fit_multi_fidelity
    from mfdesign.models.ensemble import EnsembleConfig

    fits = {}
    for h in HYPOTHESES:
        fits[h] = fit_multi_fidelity(
            table,
            "standin",
            [h],
            ensemble_config=EnsembleConfig(n_members=2, steps=20, monotone=False),
            seed=seed,
            progress=False,
            **FIT,
        )
    return fits


def probs(fits):
    from mfdesign.discriminate import hypothesis_probabilities

    return hypothesis_probabilities([fits[h].posterior.bic for h in HYPOTHESES])


def one_case(truth: str, seed: int) -> dict:
    import warnings

    from mfdesign.design import Membrane
    from mfdesign.discriminate import candidate_experiments, rank_experiments

    warnings.simplefilter("ignore")
    rng = np.random.default_rng(seed)
    value = float(rng.uniform(0.8, 1.6)) if truth == "fabric_inset" else float(rng.uniform(0.88, 0.95))
    t0 = time.time()
    table = make_rig(truth, value, seed).run([Membrane.from_key(k) for k in PASSIVE], lift=False, progress=False)
    fits = fit_all(table, seed)
    p0 = probs(fits)
    cands = candidate_experiments(PASSIVE, NEW)
    ranking = rank_experiments(fits, cands, seed=seed)
    top = cands[ranking.order[0]]
    after = run_experiment(top, truth, value, seed, table)
    p_top = probs(fit_all(after, seed))
    ti = HYPOTHESES.index(truth)
    # random baseline: random candidates, each taken if it fits the budget left, until none
    # fits a budget of 1x, then 2x the top experiment's cost (the 2x run continues the 1x one)
    rng_r = np.random.default_rng(10_000 + seed)
    random_runs, data, spent, used = [], table, 0.0, set()
    for mult in (1.0, 2.0):
        chosen = []
        for j in rng_r.permutation(len(cands)):
            e = cands[j]
            if j in used or spent + e.cost > mult * top.cost + 1e-9:
                continue
            data = run_experiment(e, truth, value, seed + 17 * len(used), data)
            spent += e.cost
            used.add(j)
            chosen.append(e.label())
        p = probs(fit_all(data, seed)) if chosen or not random_runs else np.asarray(random_runs[-1]["p"])
        random_runs.append(
            {"cost_multiple": mult, "cost": spent, "added": chosen, "p": p.tolist(), "p_truth": float(p[ti])}
        )
    return {
        "truth": truth,
        "value": value,
        "seed": seed,
        "passive_rows": len(table),
        "p_passive": p0.tolist(),
        "p_truth_passive": float(p0[ti]),
        "bic_passive": {h: float(fits[h].posterior.bic) for h in HYPOTHESES},
        "top": {
            "label": top.label(),
            "cost": top.cost,
            "score": float(ranking.score[ranking.order[0]]),
            "expected_p_truth": float(ranking.p_truth[ranking.order[0]]),
        },
        "top5": [ranking.experiments[i].label() for i in ranking.top(5)],
        "p_after_top": p_top.tolist(),
        "p_truth_after_top": float(p_top[ti]),
        "random": random_runs,
        "wall_s": time.time() - t0,
    }


def plot(cases, path):
    import matplotlib

    matplotlib.use("Agg")
    import matplotlib.pyplot as plt

    from mfdesign import outputs

    fig, ax = plt.subplots(figsize=(8, 4.2))
    x = np.arange(len(cases))
    w = 0.2
    ax.bar(x - 1.5 * w, [c["p_truth_passive"] for c in cases], w, label="passive data")
    ax.bar(x - 0.5 * w, [c["p_truth_after_top"] for c in cases], w, label="+ tool's top experiment")
    ax.bar(x + 0.5 * w, [c["random"][0]["p_truth"] for c in cases], w, label="+ random, same cost")
    ax.bar(x + 1.5 * w, [c["random"][1]["p_truth"] for c in cases], w, label="+ random, 2x cost")
    ax.axhline(TARGET, color="k", ls="--", lw=1)
    ax.set_xticks(x)
    ax.set_xticklabels([f"{c['truth'][:8]}\ns{c['seed']}" for c in cases], fontsize=7)
    ax.set_ylabel("posterior probability of the truth (BIC)")
    ax.set_ylim(0, 1.05)
    ax.set_title("discriminate: fabric_inset vs load_cell_gain on the virtual rig (stand-in physics)")
    ax.legend(fontsize=7, loc="lower right")
    fig.tight_layout()
    outputs.savefig(fig, path, dpi=110)
    plt.close(fig)


def main(argv=None):
    ap = argparse.ArgumentParser()
    ap.add_argument("--seeds", type=int, default=5, help="seeds per truth (cases = 2 x seeds)")
    ap.add_argument("--fresh", action="store_true", help="ignore the kept cases")
    args = ap.parse_args(argv)
    from mfdesign import outputs

    CASES.mkdir(parents=True, exist_ok=True)
    t0 = time.time()
    cases = []
    for seed in range(args.seeds):
        for truth in HYPOTHESES:
            f = CASES / f"{truth}_s{seed}.json"
            if f.is_file() and not args.fresh:
                cases.append(json.loads(f.read_text()))
                continue
            case = one_case(truth, seed)
            outputs.write_json(f, case)
            cases.append(case)
            print(
                f"{truth} s{seed}: P(truth) passive {case['p_truth_passive']:.3f} -> top {case['p_truth_after_top']:.3f}"
                f" (cost {case['top']['cost']:g}); random 1x {case['random'][0]['p_truth']:.3f}, 2x {case['random'][1]['p_truth']:.3f}"
                f"  [{case['wall_s']:.0f} s]",
                flush=True,
            )
            write_summary(cases, args, t0, final=False)  # partial results after every case
    write_summary(cases, args, t0)


def write_summary(cases, args, t0, final=True):
    from mfdesign import outputs

    n = len(cases)
    top_ok = sum(c["p_truth_after_top"] > TARGET for c in cases)
    r1 = sum(c["random"][0]["p_truth"] > TARGET for c in cases)
    r2 = sum(c["random"][1]["p_truth"] > TARGET for c in cases)
    summary = {
        "command": "nice -n 19 python experiments/discriminate_virtual.py --seeds %d" % args.seeds,
        "method": "Box & Hill (1967) expected log Bayes factor (mfdesign.discriminate)",
        "truths": list(HYPOTHESES),
        "hypotheses": list(HYPOTHESES),
        "physics": "stand-in (truth and models)",
        "fit": FIT | {"discrepancy": "2 members x 20 steps"},
        "n_cases": n,
        "seeds_per_truth": args.seeds,
        "complete": len(cases) == 2 * args.seeds,
        "target": TARGET,
        "passive_p_truth_median": float(np.median([c["p_truth_passive"] for c in cases])),
        "top_success": top_ok / n,
        "random_same_cost_success": r1 / n,
        "random_2x_cost_success": r2 / n,
        "acceptance": {
            "top_raises_truth_above_0.95_in_90pct": top_ok / n >= 0.9,
            "random_needs_2x_cost": r1 / n < top_ok / n,
        },
        "wall_s_this_run": time.time() - t0,
        "wall_s_cases_total": float(sum(c["wall_s"] for c in cases)),
        "cases": cases,
    }
    outputs.write_json(OUT / "discriminate_virtual.json", summary)
    plot(cases, OUT / "discriminate_virtual.png")
    if final:
        print(json.dumps({k: v for k, v in summary.items() if k != "cases"}, indent=1))


if __name__ == "__main__":
    sys.exit(main())
