"""Coverage of the calibration's credible intervals on virtual data with known truth.

Per seed: truth drawn (mu ~ U(26, 42) kPa, J_m ~ U(28, 60), effect parameters from their
priors), the virtual rig measures 3 membranes, emcee calibrates
(:func:`mfdesign.calibration.validation.truth_trial`); the 95 % intervals should cover the
truth in >= 85 % of cases. ``--simulator standin`` (fast) or ``emulator`` (the trained
emulator is both the virtual rig's simulator and the model's).

    python experiments/calibration_coverage.py [--seeds 20] [--simulator emulator] [--steps 1500]

Writes ``experiments/out/calibration_coverage_<simulator>.json``.
"""

from __future__ import annotations

from types import SimpleNamespace

import numpy as np


from _common import parser, timed, write_json  # experiments/ is on a script's path


def emulator_plane(emu):
    """The emulator as a ``VirtualRig`` simulator (grid layout of ``force_plane``)."""

    def plane(design, h_grid, p_grid, params):
        H, P = np.meshgrid(np.asarray(h_grid, float), np.asarray(p_grid, float), indexing="ij")
        d = np.broadcast_to(design.to_array(), (H.size, 6))
        f = np.asarray(emu(d, H.ravel(), P.ravel(), params)).reshape(H.shape)
        return SimpleNamespace(
            force_n=f, status=np.zeros(H.shape, np.int8), max_locking=np.zeros(H.shape), max_rise_mm=P / 250.0 - H / 2.0
        )

    return plane


def main():
    ap = parser(__doc__)
    ap.add_argument("--seeds", type=int, default=20)
    ap.add_argument("--steps", type=int, default=1500)
    ap.add_argument("--rows", type=int, default=400)
    ap.add_argument("--simulator", default="standin", choices=("standin", "emulator"))
    ap.add_argument("--effects", nargs="*", default=["pressure_sensor"])
    args = ap.parse_args()

    from mfdesign.calibration.validation import truth_trial
    from mfdesign.calibration.workflow import force_model_named

    fm = force_model_named(args.simulator)
    if args.simulator == "emulator":
        from mfdesign.calibration.workflow import model_for  # noqa: F401  (priors inside the ranges)
        from mfdesign.physics.effects import LogNormal

        plane, kw = (
            emulator_plane(fm),
            {
                "mu_prior": LogNormal(31.7e3, 0.5, 15e3, 50e3),
                "jm_prior": LogNormal(39.6, 0.6, 10.0, 100.0),
                "thickness_sd_prior": LogNormal(0.05, 0.8, 1e-3, 0.1),
            },
        )
    else:
        from mfdesign.models.standin import standin_plane

        plane, kw = standin_plane, {}
    trials = []
    with timed() as clock:
        for seed in range(args.seeds):
            trials.append(
                truth_trial(seed, fm, plane, tuple(args.effects), rows=args.rows, n_steps=args.steps, model_kwargs=kw)
            )
            t = trials[-1]
            print(f"seed {seed}: covered {t['covered']}  steps/tau {t['steps_over_tau']:.1f}", flush=True)
    names = list(trials[0]["covered"])
    per = {n: float(np.mean([t["covered"][n] for t in trials])) for n in names}
    overall = float(np.mean([[t["covered"][n] for n in names] for t in trials]))
    out = {
        "simulator": args.simulator,
        "effects": args.effects,
        "seeds": args.seeds,
        "steps": args.steps,
        "rows": args.rows,
        "level": 0.95,
        "coverage_per_parameter": per,
        "coverage_overall": overall,
        "target": ">= 0.85",
        "met": overall >= 0.85,
        "seconds": clock["wall_s"],
        "trials": trials,
    }
    path = write_json(args.out / f"calibration_coverage_{args.simulator}.json", out)
    print(f"coverage of 95 % intervals: overall {overall:.3f} (target >= 0.85); per parameter {per}; wrote {path}")


if __name__ == "__main__":
    main()
