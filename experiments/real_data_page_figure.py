"""The figure of docs/real_data.md: where the recommended variant fails, membrane by membrane.

Reads one committed leave-one-membrane-out result (``experiments/real_mass_lift.py``'s
JSON; no fitting, a second or two) and draws, per held-out membrane, the force RMSE, the
scaled trajectory RMSE and the 90 % coverage of plain physics (a, the paper's constants),
the calibrated simulator (b) and the multi-fidelity model (e). The title names the
variant, read from the JSON's settings; bars are labelled by membrane.

    python experiments/real_data_page_figure.py
"""

from __future__ import annotations

import argparse
import json
from pathlib import Path

ROOT = Path(__file__).resolve().parents[1]
SOURCE = ROOT / "experiments" / "out" / "real_mass_lift_rings_coupons_tensor" / "real_mass_lift.json"
OUT = ROOT / "docs" / "img" / "real_data" / "held_out_recommended.png"
MODELS = (
    ("a_sim_paper", "a plain physics (paper constants)"),
    ("b_sim_calibrated", "b calibrated simulator"),
    ("e_multi_fidelity", "e multi-fidelity"),
)


def variant_name(settings: dict) -> str:
    """The variant in words, from ``real_mass_lift.py``'s settings."""
    rubber = (
        "coupons' rubber"
        if settings.get("material_coupons")
        else ("J_m held" if settings.get("jm_coupons") else "rubber free")
    )
    latents = "no latents" if settings.get("no_latents") else "thickness latents"
    return f"{' + '.join(settings['effects'])}, {rubber}, {latents}, {settings['effect_axes']} lattice"


def short(key: str) -> str:
    return key.replace(", nan", "")


def main() -> None:
    ap = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    ap.add_argument("--json", type=Path, default=SOURCE)
    ap.add_argument("--out", type=Path, default=OUT)
    args = ap.parse_args()
    import matplotlib

    matplotlib.use("Agg")
    import matplotlib.pyplot as plt
    import numpy as np

    res = json.loads(args.json.read_text())
    folds = res["folds"]
    keys = [f["membrane"] for f in folds["a_sim_paper"]]
    x = np.arange(len(keys))
    fig, axes = plt.subplots(1, 3, figsize=(16, 5.2))
    for ax, metric, label in zip(
        axes, ("rmse_n", "traj_rmse_p", "coverage90"), ("force RMSE [N]", "scaled trajectory RMSE", "90 % coverage")
    ):
        for k, (name, legend) in enumerate(MODELS):
            ax.bar(x + (k - 1) * 0.27, [f[metric] for f in folds[name]], 0.27, label=legend)
        ax.set_xticks(x, [short(k) for k in keys], rotation=35, ha="right", fontsize=7)
        ax.set_title(label)
        if metric == "coverage90":
            ax.axhline(0.9, color="k", ls="--", lw=0.8)
    axes[0].legend(fontsize=8)
    rel = args.json.relative_to(ROOT) if args.json.is_relative_to(ROOT) else args.json
    fig.suptitle(f"held out, one membrane at a time. Variant: {variant_name(res['settings'])}\n({rel})", fontsize=10)
    fig.tight_layout()
    args.out.parent.mkdir(parents=True, exist_ok=True)
    fig.savefig(args.out, dpi=100)
    print(args.out)


if __name__ == "__main__":
    main()
