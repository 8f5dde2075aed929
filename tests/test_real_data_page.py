"""docs/real_data.md, the real rig's page for a lab: every number on it is read back from
committed JSON under experiments/out/ (no fitting; a second).

How: each sentence with numbers is a template here, formatted from the JSON and looked up in
the page (whitespace collapsed); the held-out table and the best-of-eight table are rendered
row by row from the JSON. Then everything matched is cut from the page, and no digit may be
left outside code, link targets, membrane labels and a few named references (issue 42's item
numbers, the paper's arXiv id, the nominal 90 % of the intervals). A changed, added or
unsourced number on the page fails here.
"""

from __future__ import annotations

import json
import re
from pathlib import Path

import pytest

ROOT = Path(__file__).resolve().parents[1]
PAGE = ROOT / "docs" / "real_data.md"
OUT = ROOT / "experiments" / "out"

RECOMMENDED = "real_mass_lift_rings_coupons_tensor"
# The eight leave-one-membrane-out variants the recommended one was chosen from, in the
# page's order: folder under experiments/out and the words the page gives it.
SUPERSEDED = "real_mass_lift_free_latents"
VARIANTS = {
    SUPERSEDED: "rubber free, latents, `fabric_inset`, tensor-jm (superseded)",
    "real_mass_lift_jm_coupons": "J_m held, latents, `fabric_inset`, tensor-jm",
    "real_mass_lift_material_coupons": "coupons' rubber, latents, `fabric_inset`, tensor-jm",
    "real_mass_lift_material_nolatents": "coupons' rubber, no latents, `fabric_inset`, tensor-jm",
    "real_mass_lift_nolatents": "rubber free, no latents, `fabric_inset`, tensor-jm",
    "real_mass_lift_rings": "rubber free, no latents, `fabric_inset` + `ring_stiffening`, tensor-jm",
    "real_mass_lift_rings_coupons": "coupons' rubber, no latents, `fabric_inset` + `ring_stiffening`, tensor-jm",
    RECOMMENDED: "**coupons' rubber, no latents, `fabric_inset` + `ring_stiffening`, tensor (recommended)**",
}
# The default file names hold the nested leave-one-membrane-out (issue 42 item 2): the
# variant chosen inside each fold from its candidates, beside the best of eight.
NESTED = "real_mass_lift.json"
# The ninth variant: an inset per membrane (issue 42 item 3), scored on the same folds.
PER_MEMBRANE = "real_mass_lift_inset_per_membrane"
DISCRIMINATE = "real_discriminate/discriminate.json"
# What each variant's settings must be for its words above to be true.
SETTINGS = {
    SUPERSEDED: dict(
        effects=["fabric_inset"], effect_axes="tensor-jm", material_coupons=False, jm_coupons=False, no_latents=False
    ),
    "real_mass_lift_jm_coupons": dict(
        effects=["fabric_inset"], effect_axes="tensor-jm", jm_coupons=True, no_latents=False
    ),
    "real_mass_lift_material_coupons": dict(
        effects=["fabric_inset"], effect_axes="tensor-jm", material_coupons=True, no_latents=False
    ),
    "real_mass_lift_material_nolatents": dict(
        effects=["fabric_inset"], effect_axes="tensor-jm", material_coupons=True, no_latents=True
    ),
    "real_mass_lift_nolatents": dict(
        effects=["fabric_inset"], effect_axes="tensor-jm", material_coupons=False, jm_coupons=False, no_latents=True
    ),
    "real_mass_lift_rings": dict(
        effects=["fabric_inset", "ring_stiffening"],
        effect_axes="tensor-jm",
        material_coupons=False,
        jm_coupons=False,
        no_latents=True,
    ),
    "real_mass_lift_rings_coupons": dict(
        effects=["fabric_inset", "ring_stiffening"], effect_axes="tensor-jm", material_coupons=True, no_latents=True
    ),
    RECOMMENDED: dict(
        effects=["fabric_inset", "ring_stiffening"],
        effect_axes="tensor",
        material_coupons=True,
        no_latents=True,
        physics="exact",
    ),
    PER_MEMBRANE: dict(
        effects=["fabric_inset", "ring_stiffening"],
        per_membrane=["fabric_inset"],
        effect_axes="tensor-jm",
        material_coupons=True,
        no_latents=True,
        physics="exact",
    ),
}
# The membranes' names on the page ("called below") and their short labels in table cells.
NAMES = {
    "[2.0, 25.4, nan, nan, nan, nan]": ("the ringless one", "[2.0, 25.4]"),
    "[2.0, 25.4, 49.0, 5.0, 62.0, 5.0]": ("[2.0, 25.4, 49, ...]", "[2.0, 25.4, 49, ...]"),
    "[2.33, 29.63, 37.63, 5.0, 62.0, 5.0]": ("[2.33, ...]", "[2.33, ...]"),
    "[2.0, 27.98, 45.58, 5.0, 60.29, 6.71]": ("[2.0, 27.98, ...]", "[2.0, 27.98, ...]"),
    "[2.0, 38.1, 47.55, 6.45, 62.0, 5.0]": ("the narrow gap (first ring just beyond the disk)", "the narrow gap"),
    "[2.0, 25.4, 33.4, 5.0, 46.4, 5.0]": (
        "[2.0, 25.4, 33.4, ...] (the authors' optimised design A)",
        "[2.0, 25.4, 33.4, ...]",
    ),
    "[2.0, 31.92, 46.0, 5.0, 59.0, 5.0]": ("[2.0, 31.92, ...] (the authors' optimised design B)", "[2.0, 31.92, ...]"),
}
STALLING = (
    "[2.0, 38.1, 47.55, 6.45, 62.0, 5.0]",
    "[2.0, 25.4, 33.4, 5.0, 46.4, 5.0]",
    "[2.0, 31.92, 46.0, 5.0, 59.0, 5.0]",
)
ODD = "[2.0, 27.98, 45.58, 5.0, 60.29, 6.71]"
MAX_WORDS = 2500


def _load(name: str) -> dict:
    return json.loads((OUT / name).read_text())


def _lomo(folder: str) -> dict:
    return _load(f"{folder}/real_mass_lift.json")


def _post(res: dict, name: str) -> dict:
    (p,) = [p for p in res["posterior_all_membranes"]["parameters"] if p["parameter"] == name]
    return p


def _flat(text: str) -> str:
    return re.sub(r"\s+", " ", text)


def _checks() -> list[str]:
    """Every sentence fragment of the page that carries numbers, rendered from the JSON."""
    rec = _lomo(RECOMMENDED)
    m, f = rec["metrics_held_out"], rec["folds"]
    keys = [x["membrane"] for x in f["a_sim_paper"]]
    i = {k: keys.index(k) for k in NAMES}

    def fold(model, key, metric):
        return f[model][i[key]][metric]

    floor = _load("real_floor.json")
    each = floor["cases"]["each"]["scores"]
    insets = {k: v["map"]["fabric_inset.inset_mm"] for k, v in each.items()}
    others = [v for k, v in insets.items() if k != ODD]
    forces = sorted({round(t["force_n"], 1) for t in floor["stalls"]})
    heights = sorted({w["h_mm"] for w in each[keys[0]]["waypoints"]})
    stall_rmse = [each[k]["rmse_n"] for k in STALLING]
    smooth_rmse = [v["rmse_n"] for k, v in each.items() if k not in STALLING]
    all7, alone = floor["cases"]["all7"]["summary"], floor["cases"]["each"]["summary"]
    variant_insets = [_post(_lomo(v), "fabric_inset.inset_mm")["median"] for v in VARIANTS]
    hoop = [
        s for v in _load("real_probes.json")["cases"]["rings"]["hoop_stretch"].values() for s in v["max_hoop_stretch"]
    ]
    fe = _load("real_rings_fe.json")["pooled_rmse_n"]["map"]
    best_factor, top_factor = min(fe, key=fe.get), max(fe, key=float)
    ring = _post(rec, "ring_stiffening.factor")
    noise = _post(rec, "noise_n")
    taus = [x["tau_ratio"] for x in f["b_sim_calibrated"]]
    conv = rec["posterior_all_membranes"]["convergence"]
    e = {v: _lomo(v)["metrics_held_out"]["e_multi_fidelity"] for v in VARIANTS}
    free = _lomo("real_mass_lift_nolatents")
    rings_free = _lomo("real_mass_lift_rings")
    old = _lomo(SUPERSEDED)
    latent_odd = _post(old, f"thickness_rel {ODD}")["median"]  # the run with latents: its relative thickness
    a, ee = "a_sim_paper", "e_multi_fidelity"
    return [
        "lift three weights ({:.1f}, {:.1f} and {:.1f} N), two trials a weight".format(*forces),
        "(`mfdesign.data.lifts.floating_rows`): {} rows.".format(sum(x["n"] for x in f[a])),
        "(pooled force {:.2f} and {:.2f} N)".format(m["c_ensemble"]["rmse_n"], m["d_curve_fit"]["rmse_n"]),
        "way-points {:g}, {:g} and {:g} mm".format(*heights),
        "on the narrow gap ({:.2f} N, trajectory {:.3f})".format(
            fold(a, keys[4], "rmse_n"), fold(a, keys[4], "traj_rmse_p")
        ),
        "[2.0, 31.92, ...] ({:.2f} N)".format(fold(a, keys[6], "rmse_n")),
        "on force ({:.2f} against {:.2f} N) and on trajectory ({:.3f} against {:.3f})".format(
            fold(ee, ODD, "rmse_n"), fold(a, ODD, "rmse_n"), fold(ee, ODD, "traj_rmse_p"), fold(a, ODD, "traj_rmse_p")
        ),
        "no fabric inset at all ({:.3f} mm, where the other six want {:.2f}-{:.2f} mm)".format(
            insets[ODD], min(others), max(others)
        ),
        "on trajectory** ({:.3f} against {:.3f}), though better on force ({:.2f} against {:.2f} N)".format(
            fold(ee, keys[1], "traj_rmse_p"),
            fold(a, keys[1], "traj_rmse_p"),
            fold(ee, keys[1], "rmse_n"),
            fold(a, keys[1], "rmse_n"),
        ),
        "better on force ({:.2f} against {:.2f} N) and mean trajectory ({:.3f} against {:.3f}), worse on median "
        "trajectory ({:.3f} against {:.3f}) and coverage ({:.2f} against {:.2f})".format(
            m[ee]["rmse_n"],
            m[a]["rmse_n"],
            m[ee]["traj_mean"],
            m[a]["traj_mean"],
            m[ee]["traj_median"],
            m[a]["traj_median"],
            m[ee]["coverage90"],
            m[a]["coverage90"],
        ),
        "far too narrow (coverage {:.2f})".format(fold(ee, keys[6], "coverage90")),
        "keep {:.2f}-{:.2f} N even when the model is fitted on each one's own rows, against {:.2f}-{:.2f} N "
        "for the other four".format(min(stall_rmse), max(stall_rmse), min(smooth_rmse), max(smooth_rmse)),
        "the trajectory error is {:.3f} mean / {:.3f} median; fitted on each membrane alone, {:.3f} / {:.3f}".format(
            all7["traj_mean"], all7["traj_median"], alone["traj_mean"], alone["traj_median"]
        ),
        "ranges {:.2f}-{:.2f} mm across the eight variants".format(min(variant_insets), max(variant_insets)),
        "it ranges from {:.3f} to {:.2f} mm, both ends".format(min(insets.values()), max(insets.values())),
        "stretch by {:.0f}-{:.0f} % around".format(100 * (min(hoop) - 1), 100 * (max(hoop) - 1)),
        "calibrates them {:.2f}x [{:.2f}, {:.2f}] as stiff".format(ring["median"], ring["q05"], ring["q95"]),
        "(pooled {:.2f} N at {}x, {:.2f} N at {}x, with the in-sample rubber".format(
            fe[best_factor], best_factor, fe[top_factor], top_factor
        ),
        "lowers the pooled force from {:.2f} to {:.2f} N".format(
            e["real_mass_lift_material_nolatents"]["rmse_n"], e["real_mass_lift_rings_coupons"]["rmse_n"]
        ),
        "mu {:.1f} kPa, J_m {:.1f} [{:.1f}, {:.1f}] against the coupons' {:.1f} kPa and {:.1f}".format(
            _post(free, "mu_pa")["median"] / 1e3,
            *(_post(free, "jm")[q] for q in ("median", "q05", "q95")),
            rec["mu_pa_paper_uniaxial"] / 1e3,
            rec["jm_paper"],
        ),
        "it still locks early (J_m {:.1f})".format(_post(rings_free, "jm")["median"]),
        "pooled force {:.2f} -> {:.2f} N (coupons' rubber), {:.2f} -> {:.2f} N (rubber free)".format(
            e["real_mass_lift_material_coupons"]["rmse_n"],
            e["real_mass_lift_material_nolatents"]["rmse_n"],
            e[SUPERSEDED]["rmse_n"],
            e["real_mass_lift_nolatents"]["rmse_n"],
        ),
        "calibrated noise {:.2f} N [{:.2f}, {:.2f}]".format(noise["median"], noise["q05"], noise["q95"]),
        "chain is {:.1f}-{:.1f} autocorrelation times long, the posterior on all seven {:.1f} (R-hat at most "
        "{:.2f})".format(min(taus), max(taus), conv["steps_over_tau"], conv["rhat_max"]),
        "its latent asked for {:+.0f} % more rubber".format(100 * latent_odd),
        "the {:.2f}x the lifts ask for".format(ring["median"]),
        *_per_membrane_checks(),
        *_discriminate_checks(),
        *_nested_checks(),
    ]


def _short(folder: str) -> str:
    return "`" + folder.removeprefix("real_mass_lift_") + "`"


def _nested_checks() -> list[str]:
    """The sentences of the nested leave-one-membrane-out, from the default file names' JSON."""
    nest = _load(NESTED)
    n, b = nest["nested"]["pooled"], nest["best_of_eight"]["pooled"]
    chosen = [r["variant"] for r in nest["nested"]["folds"]]
    counts = sorted({v: chosen.count(v) for v in chosen}.items(), key=lambda kv: (-kv[1], kv[0]))
    words = ("none", "one", "two", "three", "four", "five", "six", "seven", "eight")
    return [
        "Candidates: {} ({} of the eight)".format(
            ", ".join(_short(v) for v in nest["candidates"]), words[len(nest["candidates"])]
        ),
        "every fold chose {}".format(_short(chosen[0]))
        if len(counts) == 1
        else "the folds chose {}".format(
            ", ".join(f"{_short(v)} {words[c]} times" if c > 1 else f"{_short(v)} once" for v, c in counts)
        ),
        "pooled force {:.2f} against {:.2f} N, trajectory mean / median {:.3f} / {:.3f} against {:.3f} / {:.3f}, "
        "coverage {:.2f} against {:.2f}".format(
            n["rmse_n"],
            b["rmse_n"],
            n["traj_mean"],
            n["traj_median"],
            b["traj_mean"],
            b["traj_median"],
            n["coverage90"],
            b["coverage90"],
        ),
    ]


def _nested_rows() -> list[str]:
    """The nested table: per held-out membrane the variant its fold chose and that variant's
    (e) row, beside the best of eight's; then the pooled figures."""
    nest = _load(NESTED)
    cell = lambda x: f"{x['rmse_n']:.2f} / {x['traj_rmse_p']:.3f} / {x['coverage90']:.2f}"  # noqa: E731
    rows = []
    for x, y in zip(nest["nested"]["folds"], nest["best_of_eight"]["folds"]):
        assert x["membrane"] == y["membrane"]
        rows.append(f"| {NAMES[x['membrane']][1]} | {_short(x['variant'])} | {cell(x)} | {cell(y)} |")
    n, b = nest["nested"]["pooled"], nest["best_of_eight"]["pooled"]
    rows += [
        f"| pooled force RMSE | | {n['rmse_n']:.2f} | {b['rmse_n']:.2f} |",
        f"| trajectory mean / median | | {n['traj_mean']:.3f} / {n['traj_median']:.3f} | "
        f"{b['traj_mean']:.3f} / {b['traj_median']:.3f} |",
        f"| 90 % coverage | | {n['coverage90']:.2f} | {b['coverage90']:.2f} |",
    ]
    return rows


def _per_membrane_checks() -> list[str]:
    """The sentences of the per-membrane inset section, from its JSON."""
    pm, rec = _lomo(PER_MEMBRANE), _lomo(RECOMMENDED)
    e, e_rec = pm["metrics_held_out"]["e_multi_fidelity"], rec["metrics_held_out"]["e_multi_fidelity"]
    f = pm["folds"]
    (odd,) = [k for k, x in enumerate(f["a_sim_paper"]) if x["membrane"] == ODD]
    params = {p["parameter"]: p["median"] for p in pm["posterior_all_membranes"]["parameters"]}
    q = "fabric_inset.inset_mm"
    own = {k: params[f"{q} {k}"] for k in NAMES}
    others = [v for k, v in own.items() if k != ODD]
    taus = [x["tau_ratio"] for x in f["b_sim_calibrated"]]
    conv = pm["posterior_all_membranes"]["convergence"]
    return [
        "pooled force {:.2f} against {:.2f} N, coverage {:.2f} against {:.2f}".format(
            e["rmse_n"], e_rec["rmse_n"], e["coverage90"], e_rec["coverage90"]
        ),
        "trajectory mean / median {:.3f} / {:.3f} against {:.3f} / {:.3f}".format(
            e["traj_mean"], e["traj_median"], e_rec["traj_mean"], e_rec["traj_median"]
        ),
        "the other six get {:.2f}-{:.2f} mm around a centre of {:.2f} mm, [2.0, 27.98, ...] {:.2f} mm".format(
            min(others), max(others), params[q], own[ODD]
        ),
        "still worse than plain physics ({:.2f} against {:.2f} N, trajectory {:.3f} against {:.3f})".format(
            f["e_multi_fidelity"][odd]["rmse_n"],
            f["a_sim_paper"][odd]["rmse_n"],
            f["e_multi_fidelity"][odd]["traj_rmse_p"],
            f["a_sim_paper"][odd]["traj_rmse_p"],
        ),
        "{} of its seven folds' chains are shorter than 50 autocorrelation times ({:.1f}-{:.1f})".format(
            sum(t < 50 for t in taus), min(taus), max(taus)
        ),
        "the posterior on all seven {:.1f} ({})".format(
            conv["steps_over_tau"], "converged" if conv["converged"] else "not converged"
        ),
    ]


def _discriminate_checks() -> list[str]:
    """The sentences of the discriminating experiments, from discriminate.json."""
    d = _load(DISCRIMINATE)
    bic = [h["bic"] for h in d["hypotheses"]]
    top = d["ranked"][0]
    return [
        "BIC {:.1f} against {:.1f} for one inset and {:.1f} without stiff rings".format(bic[1], bic[0], bic[2]),
        "`{}`".format(top["experiment"]["design"]),
        "lifting {:.1f} N ({:.2f} kg) to {:g} Pa".format(
            top["experiment"]["load_n"], top["experiment"]["load_n"] / 9.80665, top["experiment"]["p_max_pa"]
        ),
        "expected log Bayes factor {:.2f}, expected probability of the truth after it {:.2f}".format(
            top["score_expected_log_bf"], top["expected_p_truth"]
        ),
    ]


def _worse_on_trajectory(res: dict, model: str) -> list[str]:
    a, m = res["folds"]["a_sim_paper"], res["folds"][model]
    return [NAMES[x["membrane"]][1] for x, y in zip(a, m) if y["traj_rmse_p"] > x["traj_rmse_p"]]


def _table_rows() -> list[str]:
    """The page's tables, rendered from the JSON: the membranes, the recommended variant held
    out, and the eight variants it was chosen from."""
    rec = _lomo(RECOMMENDED)
    f, m = rec["folds"], rec["metrics_held_out"]
    models = ("a_sim_paper", "e_multi_fidelity")
    rows = [f"| {x['membrane']} | {NAMES[x['membrane']][0]} | {x['n']} |" for x in f["a_sim_paper"]]
    for k, x in enumerate(f["a_sim_paper"]):
        cells = [
            f"{f[n][k]['rmse_n']:.2f} / {f[n][k]['traj_rmse_p']:.3f} / {f[n][k]['coverage90']:.2f}" for n in models
        ]
        rows.append(f"| {x['membrane']} | {' | '.join(cells)} |")
    rows.append("| pooled force RMSE | " + " | ".join(f"{m[n]['rmse_n']:.2f}" for n in models) + " |")
    rows.append(
        "| trajectory mean / median | "
        + " | ".join(f"{m[n]['traj_mean']:.3f} / {m[n]['traj_median']:.3f}" for n in models)
        + " |"
    )
    rows.append("| 90 % coverage | " + " | ".join(f"{m[n]['coverage90']:.2f}" for n in models) + " |")
    worse_force = [", ".join(NAMES[k][1] for k in m[n]["worse_than_paper"]) for n in models[1:]]
    rows.append("| worse than plain physics on force | | " + " | ".join(worse_force) + " |")
    worse_traj = [", ".join(_worse_on_trajectory(rec, n)) for n in models[1:]]
    rows.append("| worse than plain physics on trajectory | | " + " | ".join(worse_traj) + " |")
    rows += _per_membrane_rows()
    rows += _nested_rows()
    for folder, words in VARIANTS.items():
        res = _lomo(folder)
        e = res["metrics_held_out"]["e_multi_fidelity"]
        taus = [x["tau_ratio"] for x in res["folds"]["b_sim_calibrated"]]
        name = folder + "/"
        inset = _post(res, "fabric_inset.inset_mm")["median"]
        rows.append(
            f"| {words} | {name} | {e['rmse_n']:.2f} | {e['traj_mean']:.3f} / {e['traj_median']:.3f} | "
            f"{e['coverage90']:.2f} | {min(taus):.1f}-{max(taus):.1f} | {inset:.2f} |"
        )
    return rows


def _per_membrane_rows() -> list[str]:
    """The per-membrane inset's held-out table beside the recommended variant's (e) (plain
    physics is in the table above it)."""
    pm, rec = _lomo(PER_MEMBRANE), _lomo(RECOMMENDED)
    f, g = pm["folds"], rec["folds"]
    cell = lambda x: f"{x['rmse_n']:.2f} / {x['traj_rmse_p']:.3f} / {x['coverage90']:.2f}"  # noqa: E731
    rows = []
    for k, x in enumerate(f["a_sim_paper"]):
        (j,) = [i for i, y in enumerate(g["a_sim_paper"]) if y["membrane"] == x["membrane"]]
        rows.append(
            f"| {NAMES[x['membrane']][1]} | {cell(g['e_multi_fidelity'][j])} | {cell(f['e_multi_fidelity'][k])} |"
        )
    worse = [
        ", ".join(NAMES[k][1] for k in r["metrics_held_out"]["e_multi_fidelity"]["worse_than_paper"]) for r in (rec, pm)
    ]
    rows.append(f"| worse than plain physics on force | {worse[0]} | {worse[1]} |")
    traj = [", ".join(_worse_on_trajectory(r, "e_multi_fidelity")) for r in (rec, pm)]
    rows.append(f"| worse than plain physics on trajectory | {traj[0]} | {traj[1]} |")
    return rows


# Digits the page may carry that are no measurement: issue 42's item numbers, the paper's
# arXiv id, the nominal level of the intervals, the membrane table's column names.
REFERENCES = (
    r"issue 42 item [0-9]",
    r"issue 42",
    r"arXiv 2504\.01156",
    r"Box & Hill 1967",
    r"90 %",
    r"\[thickness, contact radius, r1, w1, r2, w2\]",
)


def test_the_page_is_short():
    assert len(PAGE.read_text().split()) <= MAX_WORDS


def test_every_number_is_read_back_from_committed_json():
    text = PAGE.read_text()
    flat = _flat(text)
    missing = [c for c in _checks() if c not in flat]
    assert not missing, "page and JSON disagree (or the sentence changed):\n" + "\n".join(missing)
    lines = set(text.splitlines())
    rows = _table_rows()
    missing = [r for r in rows if r not in lines]
    assert not missing, "table rows the JSON does not give:\n" + "\n".join(missing)
    # nothing numeric is left once the checked fragments and rows are cut out
    rest = "\n".join(line for line in text.splitlines() if line not in set(rows))
    rest = re.sub(r"^\s*[0-9]+\. ", "", rest, flags=re.M)  # list numbering
    rest = _flat(rest)
    for c in sorted(_checks(), key=len, reverse=True):
        assert c.count("`") % 2 == 0, c  # a check cuts whole code spans only
        rest = rest.replace(c, " ")
    rest = re.sub(r"`[^`]*`", " ", rest)  # code, file names
    rest = re.sub(r"\]\([^)]*\)", "]", rest)  # link targets
    for ref in REFERENCES:
        rest = re.sub(ref, " ", rest, flags=re.I)
    for label in sorted({*NAMES, *(n for _, n in NAMES.values())}, key=len, reverse=True):
        rest = rest.replace(label, " ")  # the membranes' labels, full and short
    left = re.findall(r"[^ ]*[0-9][^ ]*", rest)
    assert not left, f"numbers on the page that no JSON check covers: {left}"


def test_the_variants_are_what_the_page_says():
    for folder, want in SETTINGS.items():
        res = _lomo(folder)
        got = {k: res["settings"].get(k, res.get(k)) for k in want}
        assert got == want, folder
    rec = _lomo(RECOMMENDED)
    taus = [x["tau_ratio"] for x in rec["folds"]["b_sim_calibrated"]]
    conv = rec["posterior_all_membranes"]["convergence"]
    assert min(taus) >= conv["min_steps_over_tau"] and conv["converged"]
    assert len(rec["metrics_held_out"]["e_multi_fidelity"]["worse_than_paper"]) == 1
    # "[2.0, 27.98, ...], worse than plain physics held out in every variant"
    assert all(ODD in _lomo(v)["metrics_held_out"]["e_multi_fidelity"]["worse_than_paper"] for v in VARIANTS)
    # the lowest pooled force of the eight: the rubber-free rings, one fold unconverged, two membranes worse
    e = {v: _lomo(v)["metrics_held_out"]["e_multi_fidelity"] for v in VARIANTS}
    assert min(e, key=lambda v: e[v]["rmse_n"]) == "real_mass_lift_rings"
    rings = _lomo("real_mass_lift_rings")
    assert sum(x["tau_ratio"] < 50 for x in rings["folds"]["b_sim_calibrated"]) == 1
    assert len(e["real_mass_lift_rings"]["worse_than_paper"]) == 2
    # the superseded run, unconverged
    old = _lomo(SUPERSEDED)
    assert not old["posterior_all_membranes"]["convergence"]["converged"]
    assert max(x["tau_ratio"] for x in old["folds"]["b_sim_calibrated"]) < 50
    # two trials a weight on every membrane
    trials = {}
    for t in _load("real_floor.json")["stalls"]:
        trials[(t["membrane"], t["force_n"])] = trials.get((t["membrane"], t["force_n"]), 0) + 1
    assert set(trials.values()) == {2} and len(trials) == 7 * 3


def test_the_nested_selection_is_what_its_json_says():
    """The default file names' JSON: every fold's choice is the lowest inner score of its
    candidates; its held-out row is that variant's committed (e) row (trained on the same six,
    no leak); the pooled figures are pooled as real_mass_lift.py pools them; the best of eight
    beside it is the recommended variant's table."""
    nest = _load(NESTED)
    assert set(nest["candidates"]) <= set(VARIANTS)
    for folder, s in nest["candidates"].items():
        assert {k: s.get(k) for k in SETTINGS[folder] if k != "physics"} == {
            k: v for k, v in SETTINGS[folder].items() if k != "physics"
        }, folder
    rows = nest["nested"]["folds"]
    assert [r["membrane"] for r in rows] == list(NAMES)
    for r in rows:
        scores = nest["inner_scores"][r["membrane"]]
        assert set(scores) == set(nest["candidates"])
        assert r["variant"] == min(scores, key=lambda v: scores[v]["force_rmse_n"]) == nest["choice"][r["membrane"]]
        (own,) = [x for x in _lomo(r["variant"])["folds"]["e_multi_fidelity"] if x["membrane"] == r["membrane"]]
        assert all(r[k] == own[k] for k in ("rmse_n", "traj_rmse_p", "coverage90", "n"))
    rec = _lomo(RECOMMENDED)["metrics_held_out"]["e_multi_fidelity"]
    assert nest["best_of_eight"]["variant"] == RECOMMENDED
    for k in ("rmse_n", "coverage90", "traj_mean", "traj_median"):
        assert nest["best_of_eight"]["pooled"][k] == pytest.approx(rec[k], abs=1e-12)


def test_the_figure_names_its_variant():
    import importlib.util

    spec = importlib.util.spec_from_file_location("fig", ROOT / "experiments" / "real_data_page_figure.py")
    fig = importlib.util.module_from_spec(spec)
    spec.loader.exec_module(fig)
    images = re.findall(r"!\[[^\]]*\]\(([^)]+)\)", PAGE.read_text())
    assert images == [str(fig.OUT.relative_to(ROOT / "docs"))], "every figure on the page must name its variant"
    assert fig.OUT.is_file() and fig.SOURCE == OUT / RECOMMENDED / "real_mass_lift.json"
    assert fig.variant_name(_lomo(RECOMMENDED)["settings"]) == (
        "fabric_inset + ring_stiffening, coupons' rubber, no latents, tensor lattice"
    )


def test_the_page_command_parses():
    import shlex

    import typer

    from mfdesign.cli import app

    (command,) = re.findall(r"`(mfdesign fit-mf [^`]+)`", PAGE.read_text())
    cli = typer.main.get_command(app)
    fit = cli.get_command(None, "fit-mf")
    params = fit.make_context("fit-mf", shlex.split(command)[2:]).params
    assert params["latents"] is False and params["material"] == "coupons"
    assert list(params["effects"]) == ["fabric_inset", "ring_stiffening"]


if __name__ == "__main__":  # pragma: no cover
    pytest.main([__file__, "-q"])
