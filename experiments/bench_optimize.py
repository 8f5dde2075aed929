"""Benchmark: 2,500-start design optimisation on this CPU (target <= 20 s after compilation).

The model is the paper's RPN ensemble (the cached ``experiments/out/paper_design_model``
if present, else an untrained 16-member ensemble: the cost does not depend on training).
Cases, each run twice (the first call compiles; the second is timed):

* ``height_screen_refine``: height maximisation, target set A, 2 rings (6 unit-cube
  coordinates), 2,500 random starts all scored, the best 64 refined by 100 projected
  Adam steps (the default of ``mfdesign optimize``);
* ``height_refine_all``: the same with every one of the 2,500 starts refined (25 steps);
* ``trajectory_screen_refine``: trajectory targeting through 9 way-points (3 masses x
  5/40/50 mm), 2,500 starts, best 32 refined by 60 steps.

Wall and CPU time (s) and the load average are recorded: the machine is shared, so the
load average says how much of the 2 cores the run had.

    python experiments/bench_optimize.py [--members 16]

Writes ``experiments/out/bench_optimize.json``.
"""

from __future__ import annotations

import jax
import numpy as np

from mfdesign.optimization import MASSES_N, TARGET_SETS, Waypoints, height_loss, multistart, trajectory_loss
from mfdesign.design import DesignSpace

from _common import PAPER_DESIGN_MODEL, machine, parser, timed, write_json  # experiments/ is on a script's path


def model(members: int):
    from mfdesign.models.ensemble import Ensemble, EnsembleConfig, Normaliser, init_ensemble

    cached = PAPER_DESIGN_MODEL
    if (cached / "ensemble.json").exists():
        m = Ensemble.load(cached)
        return m, f"{cached} ({m.n_members} members)"
    rng = np.random.default_rng(0)
    d = np.tile([[2.0, 30.0, 45.0, 5.0, 60.0, 5.0]], (64, 1))
    norm = Normaliser.fit(d, rng.uniform(0, 60, 64), rng.uniform(0, 1e4, 64), rng.uniform(0, 60, 64))
    return init_ensemble(
        EnsembleConfig(n_members=members, monotone=True), norm, jax.random.PRNGKey(0)
    ), f"untrained RPN ensemble ({members} members)"


def run_timed(fn):
    with timed() as t:
        out = fn()
    return out, t


def main():
    ap = parser(__doc__)
    ap.add_argument("--members", type=int, default=16)
    ap.add_argument("--starts", type=int, default=2500)
    args = ap.parse_args()
    ens, what = model(args.members)
    space = DesignSpace()
    wp = Waypoints(np.repeat(MASSES_N, 3), np.tile([2500.0, 4500.0, 5200.0], 3), np.tile([5.0, 40.0, 50.0], 3))
    cases = {
        "height_screen_refine": (height_loss(ens, TARGET_SETS["A"], space, 2), 6, dict(steps=100, n_refine=64)),
        "trajectory_screen_refine": (trajectory_loss(ens, wp, space, 2), 6, dict(steps=60, n_refine=32)),
        "height_refine_all": (height_loss(ens, TARGET_SETS["A"], space, 2), 6, dict(steps=25, n_refine=None)),
    }
    host = machine()
    result = dict(
        model=what,
        n_starts=args.starts,
        target_s=20.0,
        machine=host,
        cpu_count=host["cpus"],
        jax=host["jax"],
        cases={},
    )
    for name, (loss, dim, kw) in cases.items():
        run = lambda: multistart(loss, dim, n_starts=args.starts, seed=0, **kw)  # noqa: E731
        _, first = run_timed(run)
        res, t = run_timed(run)
        t.update(
            first_call_wall_s=first["wall_s"],
            screen_s=res["screen_s"],
            refine_s=res["refine_s"],
            best_loss=res["loss"],
            settings=kw,
            meets_target=t["wall_s"] <= 20.0,
        )
        result["cases"][name] = t
        print(
            f"{name}: {t['wall_s']:.1f} s wall after compilation ({t['cpu_s']:.1f} s CPU; first call "
            f"{first['wall_s']:.1f} s; load {t['load_average_before'][0]:.1f}); ratio to the 20 s target "
            f"{t['wall_s'] / 20:.2f}",
            flush=True,
        )
        write_json(args.out / "bench_optimize.json", result)  # after every case: a long run leaves what it measured


if __name__ == "__main__":
    main()
