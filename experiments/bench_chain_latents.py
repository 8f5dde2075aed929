"""The chain of a 22-membrane round: acceptance, tau, steps, wall (issue 40, item 4).

The calibration of ``bench_round22.py``'s round on its own: the virtual rig's Parquet of
the 22 membranes (``--data``, made by ``bench_round22.py``), the round's settings (1500
rows, at most 2000 steps, automatic walkers, Student-t likelihood, one thickness latent
per membrane, material free, the effects the round's diagnosis found: ``pressure_sensor``)
through ``mfdesign.calibration.mcmc.calibrate`` with its default moves and
``stop_when_converged``, as ``Campaign.fit`` calls it (``fit_multi_fidelity``).
``--physics emulator`` (default): the bundled emulator, no simulator planes, for
development; ``exact``: the round's physics (~270 simulator planes, cached under
``MFDESIGN_CACHE_DIR``: set it to a fixed folder to pay once).

Per run: mean acceptance of the adaptation stage and of the chain after it (from the
stored chain: a walker that did not move was rejected), tau_max and its parameter, steps,
chain / tau, converged, wall. ``--per-move N``: then every move of the two stages alone
for N steps from the walkers at the end of the adaptation (emcee reports one acceptance
for a mixture; this says which move does the work).

Runs are merged into the JSON by ``--label`` (a rerun replaces the run of the same label),
so a run before and after a change of the moves sit side by side.

    MFDESIGN_CACHE_DIR=/tmp/s28/chain_cache python experiments/bench_chain_latents.py \\
        --data /tmp/br22_data/rig22.parquet --physics emulator --label after --per-move 100

Writes ``bench_chain_latents.json`` into ``--out``; prints one line per run and per move.
"""

from __future__ import annotations

import json
import tempfile
import time
from pathlib import Path

import numpy as np

from _common import command, git_state, machine, parser, timed, write_json

NAME = "bench_chain_latents"


def stage_acceptance(chain: np.ndarray, adapt: int) -> dict:
    """Mean acceptance of the steps before / after ``adapt`` from a chain [steps, walkers,
    dim]: a walker's position changes exactly when its proposal was accepted."""
    moved = np.any(chain[1:] != chain[:-1], axis=2)  # [steps - 1, walkers]; step 0 is unknown
    acc = moved.mean(axis=1)
    first, second = acc[: max(adapt - 1, 0)], acc[max(adapt - 1, 0) :]
    return {
        "adapt": float(first.mean()) if first.size else None,
        "after_adapt": float(second.mean()) if second.size else None,
    }


def per_move(logp, moves_by_stage: dict, start: np.ndarray, steps: int, seed: int) -> list[dict]:
    """Every move alone for ``steps`` steps from ``start`` [walkers, dim]: its acceptance
    and the walkers' mean squared jump per step in units of the start's per-coordinate sd."""
    import emcee

    rows = []
    sd = np.std(start, axis=0)
    sd[sd <= 0] = 1.0
    for stage, moves in moves_by_stage.items():
        for move, weight in moves:
            s = emcee.EnsembleSampler(len(start), start.shape[1], logp, vectorize=True, moves=[(move, 1.0)])
            s.random_state = np.random.RandomState(seed).get_state()
            t0 = time.perf_counter()
            s.run_mcmc(start, steps, progress=False)
            ch = s.get_chain()
            jump = float(np.mean(np.sum(((ch[1:] - ch[:-1]) / sd) ** 2, axis=2)))
            rows.append(
                {
                    "stage": stage,
                    "move": type(move).__name__,
                    "weight": float(weight),
                    "steps": steps,
                    "acceptance": float(np.mean(s.acceptance_fraction)),
                    "msjd_per_dim": jump / start.shape[1],
                    "wall_s": round(time.perf_counter() - t0, 2),
                }
            )
            r = rows[-1]
            print(
                f"{NAME}:   {stage:8s} {r['move']:18s} share {weight:.2f}: acceptance {r['acceptance']:.3f}, "
                f"jump^2/dim {r['msjd_per_dim']:.3f} sd^2",
                flush=True,
            )
    return rows


def main() -> None:
    ap = parser(__doc__, seed=True)
    ap.add_argument("--data", type=Path, default=Path("/tmp/br22_data/rig22.parquet"), help="Parquet of the rig's rows")
    ap.add_argument("--physics", default="emulator", choices=("emulator", "exact"))
    ap.add_argument("--effects", default="pressure_sensor", help="comma-separated effects ('' none)")
    ap.add_argument("--membranes", type=int, default=0, help="the first N membranes only (0: all)")
    ap.add_argument("--steps", type=int, default=2000, help="the most steps (stop_when_converged)")
    ap.add_argument("--rows", type=int, default=1500, help="rows the likelihood uses")
    ap.add_argument("--per-move", type=int, default=0, metavar="N", help="steps of every move alone (0: none)")
    ap.add_argument("--label", default="run", help="name of this run in the JSON (a rerun replaces it)")
    ap.add_argument(
        "--from-chain",
        type=Path,
        default=None,
        metavar="H5",
        help="summarise a stored chain (a copy of a killed run's HDF5) instead of sampling",
    )
    ap.add_argument("--adapt", type=int, default=200, help="with --from-chain: its adaptation steps")
    ap.add_argument("--note", default="", help="a sentence stored with the run")
    args = ap.parse_args()
    if args.from_chain is not None:
        _merge(
            args,
            from_chain(args.from_chain, args.adapt)
            | {"label": args.label, "note": args.note, "command": command(__file__, args)},
        )
        return

    import emcee

    from mfdesign._cache import enable_compilation_cache
    from mfdesign.calibration import mcmc
    from mfdesign.calibration.workflow import force_model_named, model_for
    from mfdesign.data.store import read_parquet
    from mfdesign.models.hierarchical import CalibrationData

    enable_compilation_cache()
    commit, dirty = git_state()
    table = read_parquet(args.data)
    if args.membranes:
        table = table.subset(list(table.design_keys)[: args.membranes])
    effects = tuple(e for e in args.effects.split(",") if e)
    seed = args.seed
    with timed() as t_physics:
        fm = force_model_named(args.physics, table, progress=False)
    # as fit_multi_fidelity prepares them (padded: one compile across folds)
    data = CalibrationData.from_measurements(table, max_rows=args.rows, seed=seed)
    n_trials = table.df.groupby(["design_key", "trial"]).ngroups
    data = data.padded(max(len(data), args.rows + n_trials))
    model = model_for(fm, data.design_keys, effects, likelihood="student_t", membrane_latents=True)
    print(f"{NAME}: {len(data.design_keys)} membranes, {model.dim} parameters, {args.physics} physics", flush=True)

    with tempfile.TemporaryDirectory() as tmp:
        path = Path(tmp) / "chain.h5"
        with timed() as t_cal:
            post = mcmc.calibrate(
                data,
                model,
                n_steps=args.steps,
                chain_path=path,
                seed=seed,
                progress=False,
                stop_when_converged=True,
                warn=False,
            )
        rep = post.convergence
        backend = emcee.backends.HDFBackend(str(path), name="mcmc", read_only=True)
        chain = backend.get_chain()
        adapt = int(rep["adapt_steps"])
        acc = stage_acceptance(chain, adapt)
        worst = max(rep["tau"], key=lambda k: rep["tau"][k]) if rep["tau"] else None
        run = {
            "label": args.label,
            "commit": commit,
            "dirty": dirty,
            "physics": args.physics,
            "membranes": len(data.design_keys),
            "dim": model.dim,
            "walkers": rep["n_walkers"],
            "steps": rep["n_steps"],
            "adapt_steps": adapt,
            "converged": bool(rep["converged"]),
            "problems": rep["problems"],
            "tau_max": rep["tau_max"],
            "tau_max_of": worst,
            "steps_over_tau": rep["steps_over_tau"],
            "acceptance": rep["acceptance"],
            "acceptance_by_stage": acc,
            "rhat_max": rep.get("rhat_max"),
            "ess_bulk_min": rep.get("ess_bulk_min"),
            "physics_s": round(t_physics["wall_s"], 1),
            "calibrate_wall_s": round(t_cal["wall_s"], 1),
            "calibrate_cpu_s": round(t_cal["cpu_s"], 1),
            "load_average": t_cal["load_average_after"],
        }
        print(
            f"{NAME}: {args.label}: {rep['n_steps']} steps ({adapt} adapting), acceptance {rep['acceptance']:.3f} "
            f"(adapt {acc['adapt']:.3f}, after {acc['after_adapt']:.3f}), tau_max {rep['tau_max']:.1f} ({worst}), "
            f"{rep['steps_over_tau']:.1f} tau, converged {rep['converged']}, calibrate {t_cal['wall_s']:.0f} s",
            flush=True,
        )
        if args.per_move and adapt and chain.shape[0] > adapt:
            import equinox as eqx
            import h5py

            with h5py.File(path, "r") as f:
                g = f["mfdesign"]
                res = mcmc.MapResult(
                    np.asarray(g["u"]), np.asarray(g["x"]), float(g.attrs["log_post"]), np.asarray(g["hessian"]), True
                )
            # the last adaptation round's draws: what the chain after it is sampled with
            rounds = [0, *mcmc.ADAPT_ROUNDS] if adapt == mcmc.ADAPT_STEPS else [adapt // 2, adapt]
            draws = chain[rounds[-2] : adapt].reshape(-1, chain.shape[2])
            fitted = post.force_model if post.force_model is not None else model.force_model
            logp = mcmc.LogPosterior(eqx.tree_at(lambda m: m.force_model, model, fitted), data)
            stages = {"adapt": mcmc.default_moves(res), "adapted": mcmc.adapted_moves(draws)}
            run["per_move"] = per_move(logp, stages, chain[adapt - 1], args.per_move, seed)

    _merge(args, run | {"note": args.note, "command": command(__file__, args)})


def from_chain(path: Path, adapt: int) -> dict:
    """The figures of a stored (partial) chain: steps, acceptance per stage, tau after ``adapt``."""
    import emcee
    import h5py

    with h5py.File(path, "r") as f:
        it = int(f["mcmc"].attrs["iteration"])
        chain = np.asarray(f["mcmc"]["chain"][:it])
        names = json.loads(f["mfdesign"].attrs["names"])
    tau = np.asarray(emcee.autocorr.integrated_time(chain[adapt:], tol=0, quiet=True), float)
    acc = stage_acceptance(chain, adapt)
    run = {
        "partial": True,
        "steps": it,
        "adapt_steps": adapt,
        "walkers": int(chain.shape[1]),
        "dim": int(chain.shape[2]),
        "tau_max": float(np.max(tau)),
        "tau_max_of": names[int(np.argmax(tau))],
        "steps_over_tau": float((it - adapt) / np.max(tau)),
        "acceptance": float(np.mean(np.any(chain[1:] != chain[:-1], axis=2))),
        "acceptance_by_stage": acc,
    }
    print(
        f"{NAME}: {path}: {it} steps ({adapt} adapting), acceptance adapt {acc['adapt']:.3f}, after "
        f"{acc['after_adapt']:.3f}, tau_max {run['tau_max']:.1f} ({run['tau_max_of']}), {run['steps_over_tau']:.1f} tau",
        flush=True,
    )
    return run


def _merge(args, run: dict) -> None:
    out = args.out / f"{NAME}.json"
    old = json.loads(out.read_text()) if out.exists() else {}
    runs = [r for r in old.get("runs", []) if r.get("label") != args.label] + [run]
    write_json(
        out,
        {
            "what": "the 22-membrane round's chain (bench_round22 settings) per version of the moves",
            "data": str(args.data),
            "machine": machine(),
            "runs": runs,
        },
    )
    print(f"{NAME}: wrote {out}", flush=True)


if __name__ == "__main__":
    main()
