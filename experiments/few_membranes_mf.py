"""The multi-fidelity model on the active-learning rig's first three membranes, with and
without the effect diagnosis names (issue 7's learning curves, item 6 of the product).

Truth: the virtual rig of ``experiments/active_learning.py`` (emulator, authors' constants,
pressure-sensor offset 150 Pa, sensor noise). Data: the three initial membranes of
``--seed``, the same rows the active-learning arms see. For each effect set the issue-5
fit (``fit_multi_fidelity``: emcee over mu, J_m, the thickness hierarchy and the effects'
parameters through the emulator, then the RPN discrepancy) and its held-out force RMSE
[N] with and without the discrepancy; the nominal simulator alone is the reference.

    python experiments/few_membranes_mf.py [--seed 0] [--mcmc-steps 200]

Writes ``experiments/out/few_membranes_mf.json``.
"""

from __future__ import annotations

import argparse
import json
import time
from pathlib import Path

import numpy as np

ROOT = Path(__file__).resolve().parents[1]
OUT = ROOT / "experiments" / "out"


def main() -> None:
    ap = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    ap.add_argument("--seed", type=int, default=0)
    ap.add_argument("--mcmc-steps", type=int, default=200)
    ap.add_argument("--walkers", type=int, default=28)
    ap.add_argument("--rows", type=int, default=800)
    args = ap.parse_args()

    import sys

    sys.path.insert(0, str(ROOT / "experiments"))
    import mfdesign  # noqa: F401  (float64)
    from active_learning import Lab, initial_designs
    from mfdesign.calibration.workflow import fit_multi_fidelity, force_model_named
    from mfdesign.cli import enable_compilation_cache
    from mfdesign.data.measurements import Measurements
    from mfdesign.models.ensemble import EnsembleConfig
    from mfdesign.models.predictive import MultiFidelity

    enable_compilation_cache()
    lab = Lab("emulator")
    h = lab.held
    rmse = lambda f: float(np.sqrt(np.mean((np.asarray(f) - h["force_n"]) ** 2)))  # noqa: E731
    out = {"command": "python experiments/few_membranes_mf.py " + " ".join(
               f"--{k.replace('_', '-')} {v}" for k, v in vars(args).items()),
           "membranes": [d.key() for d in initial_designs(args.seed)],
           "truth": {"effect": "pressure_sensor", "offset_pa": 150.0, "mu_pa": 31.7e3, "jm": 39.6},
           "simulator_alone_rmse_n": lab.simulator_rmse(), "fits": []}
    table = Measurements.concat([lab.table(d, args.seed) for d in initial_designs(args.seed)])
    cfg = EnsembleConfig(monotone=False, n_members=8, steps=1500, chunk=500, batch=100)
    for effects in ((), ("pressure_sensor",)):
        t = time.perf_counter()
        fit = fit_multi_fidelity(table, force_model_named("emulator"), effects, n_steps=args.mcmc_steps,
                                 n_walkers=args.walkers, max_rows=args.rows, ensemble_config=cfg, seed=args.seed,
                                 progress=False)
        fit_s = time.perf_counter() - t
        mf = fit.mf.thinned(32)
        bare = MultiFidelity(mf.model, mf.theta, None, mf.noise_n, mf.design_keys)
        post = fit.posterior
        row = {"effects": list(effects), "fit_s": fit_s,
               "posterior_median": {n: float(np.median(post.samples[:, i])) for i, n in enumerate(post.names)
                                    if not n.startswith("z_")},
               "heldout_rmse_n": rmse(np.asarray(mf.predict(h["design"], h["height_mm"], h["pressure_pa"])).mean(0)),
               "heldout_rmse_without_discrepancy_n": rmse(
                   np.asarray(bare.predict(h["design"], h["height_mm"], h["pressure_pa"])).mean(0))}
        out["fits"].append(row)
        print(json.dumps(row), flush=True)
    path = OUT / "few_membranes_mf.json"
    path.write_text(json.dumps(out, indent=2))
    print(f"nominal simulator alone {out['simulator_alone_rmse_n']:.2f} N; wrote {path}", flush=True)


if __name__ == "__main__":
    main()
