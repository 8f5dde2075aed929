"""Benchmark of the exact force model (issue 17, item 3). Writes JSON.

* accuracy: the exact model against direct simulator calls (``force_at``) at random rows of
  the bundled data's six membranes and at random constants: mu, J_m and the thickness
  factor inside the calibration's reach (on calibration's tensor lattice), and each
  mechanical effect at a random value of its prior (one at a time, on the additive axes
  of diagnosis);
* timings (wall clock, with the load average before and after): ``mfdesign diagnose`` of a
  450-row, 6-membrane characterisation set (75 force rows per membrane, evenly spaced in
  each trial) with an empty cache (cold) and again (warm); ``mfdesign diagnose`` of the
  whole bundled set; ``mfdesign calibrate`` on the six membranes to the chain length the
  convergence report asks for.

    python experiments/bench_exact.py [--skip-timings] [--skip-accuracy] [--mcmc-steps 4000]

``calibrate`` stops once its chain is 50 autocorrelation times long (``--mcmc-steps`` is
the most it may take); its convergence report is copied into the JSON.
"""

from __future__ import annotations

import dataclasses
import json
import os
import subprocess
import sys
import tempfile
from pathlib import Path

import numpy as np

from _common import Timing, load, machine, parser, timed, write_json  # experiments/ is on a script's path

ROOT = Path(__file__).resolve().parents[1]
BUNDLED = ROOT / "mfdesign" / "data" / "files" / "bundled_virtual.parquet"


def accuracy(n_rows: int, seed: int) -> dict:
    import jax.numpy as jnp

    from mfdesign.data.store import read_parquet
    from mfdesign.design import Membrane
    from mfdesign.diagnosis.expected import query_heights
    from mfdesign.models.exact import build_exact
    from mfdesign.physics.params import SimParams
    from mfdesign.physics.solve import force_at

    meas = read_parquet(BUNDLED)
    df = meas.df
    h_all = query_heights(meas)
    keys = list(dict.fromkeys(df["design_key"]))
    rng = np.random.default_rng(seed)
    clock = Timing()
    # Each use in its own configuration: calibration varies mu, J_m and the thickness on a
    # tensor lattice (J_m x ring ratio: exact cross terms); diagnosis varies one mechanical
    # effect at a time on additive axes (exact for one effect, first order in cross terms,
    # which an additive lattice under the "constants" cases measured at up to 0.18 N).
    grid = dict(h_max_mm=float(np.nanmax(h_all)), p_max_pa=float(df["pressure_pa"].max()), progress=True)
    models = {
        "tensor": build_exact(keys, grow="tensor", **grid),
        "additive": build_exact(keys, grow="additive", **grid),
    }
    cases = []
    effects = {
        "offset": ("contact_offset_mm", 0.0, 6.0),
        "prestretch": ("clamp_prestretch", 1.0, 1.08),
        "gradient": ("thickness_gradient", -0.3, 0.3),
        "ring": ("ring_mu_pa", 0.1e6, 1e6),
    }
    for key in keys:
        idx = np.flatnonzero((df["design_key"] == key).to_numpy() & (df["pressure_pa"].to_numpy() > 200))
        for case in ("constants", "constants", "offset", "prestretch", "gradient", "ring"):
            if case == "ring" and Membrane.from_key(key).n_rings == 0:
                continue
            params = SimParams(
                mu_pa=31.7e3 * float(np.exp(rng.uniform(-0.1, 0.1))),
                jm=39.6 * float(np.exp(rng.uniform(-0.1, 0.1))),
                thickness_factor=float(np.exp(rng.uniform(-0.08, 0.08))),
            )
            if case != "constants":  # one mechanical effect, at the reference rubber (diagnosis' use)
                field, lo, hi = effects[case]
                m = Membrane.from_key(key)
                if case == "offset" and m.n_rings:  # the disk edge must stay 0.5 mm inside the first ring
                    hi = min(hi, m.rings[0].inner_mm - m.contact_radius_mm - 0.5)
                params = dataclasses.replace(SimParams(), **{field: float(rng.uniform(lo, hi))})
            use = "tensor" if case == "constants" else "additive"
            fm = models[use] = models[use].covering(params, progress=True)
            pick = rng.choice(idx, size=min(n_rows, idx.size), replace=False)
            h, p = h_all[pick], df["pressure_pa"].to_numpy(float)[pick]
            ref = force_at(Membrane.from_key(key), h, p, params).force_n
            d = np.broadcast_to(Membrane.from_key(key).to_array(), (pick.size, 6))
            got = np.asarray(fm(jnp.asarray(d), jnp.asarray(h), jnp.asarray(p), params))
            both = np.isfinite(ref) & np.isfinite(got)
            e = got[both] - ref[both]
            cases.append(
                {
                    "design": key,
                    "case": case,
                    "lattice": use,
                    "params": {f.name: float(getattr(params, f.name)) for f in dataclasses.fields(params)},
                    "n": int(both.sum()),
                    "model_nan_where_simulator_finite": int(np.sum(np.isfinite(ref) & ~np.isfinite(got))),
                    "rmse_n": float(np.sqrt(np.mean(e**2))) if e.size else None,
                    "max_abs_n": float(np.max(np.abs(e))) if e.size else None,
                }
            )
            print(
                f"{key} {case}: rmse {cases[-1]['rmse_n']} N, max {cases[-1]['max_abs_n']} N "
                f"(n {cases[-1]['n']}, model NaN where the simulator is finite: "
                f"{cases[-1]['model_nan_where_simulator_finite']})",
                flush=True,
            )
    sq = sum(c["rmse_n"] ** 2 * c["n"] for c in cases if c["n"])
    n = sum(c["n"] for c in cases)
    return {
        "cases": cases,
        "rmse_n": float(np.sqrt(sq / n)),
        "max_abs_n": float(max(c["max_abs_n"] for c in cases if c["n"])),
        "rows": int(n),
        "nan_where_simulator_finite": int(sum(c["model_nan_where_simulator_finite"] for c in cases)),
        "target": {"rmse_n": 0.05, "max_abs_n": 0.15},
        "wall_s": round(clock.elapsed(), 1),
        "lattice": {
            use: {
                "tensor": [(a.name, a.k0, a.n) for a in fm.tensor_axes],
                "additive": [(a.name, a.k0, a.n) for a in fm.additive_axes],
            }
            for use, fm in models.items()
        },
    }


def characterisation_450(path: Path) -> None:
    from mfdesign.data.measurements import Measurements
    from mfdesign.data.store import read_parquet, write_parquet

    df = read_parquet(BUNDLED).df
    df = df[df["experiment"] == "force"]
    keep = []
    for _, g in df.groupby("design_key", sort=False):
        keep.append(g.index[np.linspace(0, len(g) - 1, 75).astype(int)])
    write_parquet(Measurements(df.loc[np.concatenate(keep)].reset_index(drop=True)), path)


def run_cli(cmd: list[str], cache: Path) -> dict:
    """Run ``cmd`` (an ``mfdesign`` command) with its own cache folder; its wall time and tail."""
    env = dict(os.environ, MFDESIGN_CACHE_DIR=str(cache))
    with timed() as t:
        r = subprocess.run(cmd, env=env, capture_output=True, text=True)
    tail = [ln for ln in r.stdout.splitlines() if ln.strip()][-6:]
    return {
        "cmd": " ".join(cmd),
        "wall_s": round(t["wall_s"], 1),
        "rc": r.returncode,
        "load_before": t["load_average_before"],
        "load_after": t["load_average_after"],
        "stdout_tail": tail,
        "stderr_tail": r.stderr.splitlines()[-3:] if r.returncode else [],
    }


def main() -> None:
    ap = parser(__doc__, seed=True)
    ap.add_argument("--rows", type=int, default=30, help="random rows per design and case")
    ap.add_argument("--skip-timings", action="store_true")
    ap.add_argument("--skip-accuracy", action="store_true")
    ap.add_argument("--mcmc-steps", type=int, default=4000)
    args = ap.parse_args()
    out = {"machine": machine() | {"load_at_start": load()}}
    path = args.out / "bench_exact.json"
    if path.exists():  # keep the other half of an earlier run
        old = json.loads(path.read_text())
        out = {**old, **out}
    if not args.skip_accuracy:
        out["accuracy"] = accuracy(args.rows, args.seed)
        print(
            f"accuracy: rmse {out['accuracy']['rmse_n']:.4f} N, max {out['accuracy']['max_abs_n']:.4f} N over "
            f"{out['accuracy']['rows']} rows",
            flush=True,
        )
        write_json(path, out, indent=1)
    if not args.skip_timings:
        exe = [sys.executable, "-m", "mfdesign.cli"]
        with tempfile.TemporaryDirectory() as tmp:
            tmp = Path(tmp)
            small = tmp / "char450.parquet"
            characterisation_450(small)
            cold = tmp / "cache_cold"
            t = {}
            t["diagnose_450_cold"] = run_cli(exe + ["diagnose", str(small), "--out", str(tmp / "d1")], cold)
            t["diagnose_450_warm"] = run_cli(exe + ["diagnose", str(small), "--out", str(tmp / "d2")], cold)
            t["diagnose_bundled"] = run_cli(exe + ["diagnose", str(BUNDLED), "--out", str(tmp / "d3")], cold)
            t["calibrate_6_membranes"] = run_cli(
                exe
                + [
                    "calibrate",
                    str(BUNDLED),
                    "--out",
                    str(tmp / "c1"),
                    "--effects",
                    "pressure_sensor",
                    "--mcmc-steps",
                    str(args.mcmc_steps),
                    "--max-rows",
                    "1500",
                ],
                cold,
            )
            try:
                conv = json.loads((tmp / "c1" / "posterior.json").read_text())["convergence"]
                t["calibrate_6_membranes"]["convergence"] = {
                    k: conv.get(k)
                    for k in (
                        "converged",
                        "n_steps",
                        "n_walkers",
                        "tau_max",
                        "steps_over_tau",
                        "acceptance",
                        "problems",
                        "rhat",
                    )
                }
            except (OSError, KeyError, ValueError) as err:
                t["calibrate_6_membranes"]["convergence"] = f"unreadable: {err!r}"
            t["targets_s"] = {
                "diagnose_450_cold": 90,
                "diagnose_450_warm": 30,
                "diagnose_bundled": 180,
                "calibrate_6_membranes": 180,
            }
        out["timings"] = t
        for k, v in t.items():
            if isinstance(v, dict) and "wall_s" in v:
                before, after = (" ".join(f"{x:.2f}" for x in v[w]) for w in ("load_before", "load_after"))
                print(f"{k}: {v['wall_s']} s (rc {v['rc']}; load {before} -> {after})", flush=True)
    out["machine"]["load_at_end"] = load()
    write_json(path, out, indent=1)
    print(f"wrote {path}")


if __name__ == "__main__":
    main()
