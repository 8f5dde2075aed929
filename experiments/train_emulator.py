"""Train the simulator emulator and report its held-out accuracy (issue 5, item 1).

Data: simulator samples made by ``python -m mfdesign.models.emulator_data`` (parts in
``data/emulator/parts``; each sample is one random design + SimParams on an 8 x 8 grid).
Held out: every sample whose id is ``test_mod - 1`` modulo ``test_mod`` -- designs and
parameters never seen in training. Reported against the simulator: RMSE, RMSE / force
range (target <= 1 %), max error, per ring count; JSON + parity PNG in experiments/out/.
The trained artifact goes into the package, ``mfdesign/data/files/emulator/`` (``emulator.eqx`` + ``emulator.json``).

    python -m mfdesign.models.emulator_data --n 3000          # simulator runs (resumable)
    python experiments/train_emulator.py [--steps 20000] [--width 128] [--depth 4]
"""

from __future__ import annotations

from pathlib import Path

import numpy as np

from mfdesign.models import emulator as em
from mfdesign.models.emulator_data import load_training

from _common import parser, timed, write_json  # experiments/ is on a script's path

ROOT = Path(__file__).resolve().parents[1]


def main(argv=None) -> dict:
    ap = parser(__doc__)
    ap.add_argument("--data", type=Path, default=ROOT / "data" / "emulator" / "parts")
    ap.add_argument("--artifact", type=Path, default=em.DEFAULT_DIR)
    ap.add_argument("--steps", type=int, default=20_000)
    ap.add_argument("--width", type=int, default=128)
    ap.add_argument("--depth", type=int, default=4)
    ap.add_argument("--members", type=int, default=4)
    ap.add_argument("--batch", type=int, default=512)
    ap.add_argument("--lr", type=float, default=3e-3)
    ap.add_argument("--test-mod", type=int, default=10)
    ap.add_argument("--tag", default="emulator", help="output name (<tag>.json, <tag>.png) in --out")
    ap.add_argument("--no-save", action="store_true", help="do not overwrite the artifact")
    a = ap.parse_args(argv)

    df = load_training(a.data)
    test = (df["sample"].to_numpy() % a.test_mod) == a.test_mod - 1
    arrays = em.table_arrays(df)
    train_a = {k: v[~test] for k, v in arrays.items()}
    test_a = {k: v[test] for k, v in arrays.items()}
    print(
        f"{df['sample'].nunique()} samples, {len(df)} points: train {int((~test).sum())}, "
        f"held out {int(test.sum())} ({df.loc[test, 'sample'].nunique()} samples)",
        flush=True,
    )

    cfg = em.EmulatorConfig(n_members=a.members, width=a.width, depth=a.depth, steps=a.steps, batch=a.batch, lr=a.lr)
    with timed() as t:
        emu, hist = em.fit_emulator(train_a, cfg)
    train_s = t["wall_s"]

    acc = em.evaluate(emu, test_a)
    acc_train = em.evaluate(emu, train_a)
    pred = acc.pop("_pred")
    acc_train.pop("_pred")
    import jax

    f = jax.jit(emu.__call__)
    f(test_a["design"], test_a["h"], test_a["p"], em.params_of(test_a)).block_until_ready()  # compiles
    with timed() as t:
        f(test_a["design"], test_a["h"], test_a["p"], em.params_of(test_a)).block_until_ready()
    eval_s = t["wall_s"]
    report = {
        "config": cfg.to_dict(),
        "dtype": "float64",
        "n_samples": int(df["sample"].nunique()),
        "n_train_points": int((~test).sum()),
        "n_test_points": int(test.sum()),
        "n_test_samples": int(df.loc[test, "sample"].nunique()),
        "status_counts": {str(k): int(v) for k, v in df["status"].value_counts().items()},
        "held_out": acc,
        "train": acc_train,
        "train_seconds": train_s,
        "predict_points_per_s": float(test.sum() / max(eval_s, 1e-9)),
        "final_loss": hist["loss"][-1],
        "target_rmse_over_range": 0.01,
        "target_met": bool(acc["all"]["rmse_over_range"] <= 0.01),
    }
    write_json(a.out / f"{a.tag}.json", report)
    _parity(test_a, pred, acc, a.out / f"{a.tag}.png")
    if not a.no_save:
        emu.save(
            a.artifact,
            extra={"held_out": acc, "n_samples": report["n_samples"], "n_train_points": report["n_train_points"]},
        )
    h = acc["all"]
    print(
        f"held-out RMSE {h['rmse_n']:.3f} N = {100 * h['rmse_over_range']:.2f} % of the force range "
        f"{acc['force_range_n']:.1f} N (target 1 %), max error {h['max_abs_err_n']:.2f} N",
        flush=True,
    )
    for k in range(3):
        r = acc[f"rings_{k}"]
        if r.get("n"):
            print(
                f"  {k} rings: RMSE {r['rmse_n']:.3f} N ({100 * r['rmse_over_range']:.2f} %), "
                f"max {r['max_abs_err_n']:.2f} N, n={r['n']}",
                flush=True,
            )
    print(f"train RMSE {acc_train['all']['rmse_n']:.3f} N; trained in {train_s:.0f} s", flush=True)
    return report


def _parity(test_a, pred, acc, path: Path) -> None:
    import matplotlib

    matplotlib.use("Agg")
    import matplotlib.pyplot as plt

    n_rings = (~np.isnan(test_a["design"][:, [2, 4]])).sum(1)
    fig, axes = plt.subplots(1, 2, figsize=(10, 4.5))
    lim = [0, max(float(test_a["F"].max()), float(pred.max())) * 1.02]
    for k, col in zip(range(3), ("C0", "C1", "C2")):
        m = n_rings == k
        axes[0].scatter(test_a["F"][m], pred[m], s=4, alpha=0.5, color=col, label=f"{k} rings")
    axes[0].plot(lim, lim, "k--", lw=0.8)
    axes[0].set(
        xlabel="simulator force [N]",
        ylabel="emulator force [N]",
        title=f"held out: RMSE {acc['all']['rmse_n']:.2f} N ({100 * acc['all']['rmse_over_range']:.2f} % of range)",
    )
    axes[0].legend()
    axes[1].scatter(test_a["p"], pred - test_a["F"], s=4, alpha=0.5, c=test_a["h"], cmap="viridis")
    axes[1].axhline(0, color="k", lw=0.8)
    axes[1].set(xlabel="pressure [Pa]", ylabel="emulator - simulator [N]", title="error (colour: h)")
    fig.tight_layout()
    fig.savefig(path, dpi=110)
    plt.close(fig)


if __name__ == "__main__":
    main()
