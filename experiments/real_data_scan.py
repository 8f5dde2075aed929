"""Which single physical change moves the plain simulator toward the real mass lifts?

One change at a time to the simulator's constants (``SimParams``: a softer rubber, the
session-9 calibrated constants, softer fabric rings, a thinner membrane, a smaller contact
radius, a larger J_m), evaluated by the exact simulator (``force_at``) on the rows of the
shared mass-lift file where the plate floats (``mfdesign.data.lifts.floating_rows``),
``--rows`` per membrane drawn at random. A lift row's residual is W - F(h, p) [N]
(positive: the model under-predicts the membrane's push). Prints RMS / mean per membrane
and pooled, and writes ``real_data_scan.json``.

    python experiments/real_data_scan.py [--rows 350]
"""

from __future__ import annotations

import numpy as np

from _common import machine, parser, timed, write_json  # experiments/ is on a script's path

VARIANTS = {
    "paper constants": {},
    "mu 26 kPa": {"mu_pa": 26e3},
    "mu 26 kPa, J_m 32": {"mu_pa": 26e3, "jm": 32.0},
    "rings 0.3 MPa": {"ring_mu_pa": 0.3e6},
    "rings 0.1 MPa": {"ring_mu_pa": 0.1e6},
    "J_m 80": {"jm": 80.0},
    "thickness x0.93": {"thickness_factor": 0.93},
    "contact radius -3 mm": {"contact_offset_mm": -3.0},
}


def main():
    ap = parser(__doc__, seed=True)
    ap.add_argument("--rows", type=int, default=350, help="floating lift rows per membrane")
    args = ap.parse_args()

    from mfdesign.data import load_mass_lift
    from mfdesign.data.lifts import floating_rows
    from mfdesign.design import Membrane
    from mfdesign.physics.params import SimParams
    from mfdesign.physics.solve import force_at

    meas = load_mass_lift()
    df = meas.df[floating_rows(meas)]
    df = df.groupby("design_key").sample(n=args.rows, random_state=args.seed)
    out = {}
    with timed() as clock:
        for name, change in VARIANTS.items():
            params = SimParams(**change)
            for key, g in df.groupby("design_key", sort=False):
                f = force_at(Membrane.from_key(key), g["height_mm"].to_numpy(), g["pressure_pa"].to_numpy(), params)
                r = g["force_n"].to_numpy() - np.asarray(f.force_n)
                out.setdefault(key, {})[name] = {
                    "rms_n": float(np.sqrt(np.nanmean(r**2))),
                    "mean_n": float(np.nanmean(r)),
                    "n_nan": int(np.isnan(r).sum()),
                }
            print(f"{name}: {clock.elapsed():.0f} s", flush=True)
    pooled = {n: float(np.sqrt(np.mean([out[k][n]["rms_n"] ** 2 for k in out]))) for n in VARIANTS}
    width = max(len(k) for k in out)
    print("membrane".ljust(width), " | ".join(n for n in VARIANTS))
    for key, v in out.items():
        print(key.ljust(width), " | ".join(f"{v[n]['rms_n']:.2f}/{v[n]['mean_n']:+.1f}" for n in VARIANTS))
    print("pooled RMS".ljust(width), " | ".join(f"{pooled[n]:.2f}" for n in VARIANTS))
    base = pooled["paper constants"]
    print("ratio to paper constants:", {n: round(pooled[n] / base, 3) for n in VARIANTS})
    write_json(
        args.out / "real_data_scan.json",
        {
            "rows_per_membrane": args.rows,
            "seed": args.seed,
            "variants": VARIANTS,
            "per_membrane": out,
            "pooled_rms_n": pooled,
            "ratio_to_paper": {n: pooled[n] / base for n in VARIANTS},
            "timing": dict(clock),
            "machine": machine(),
        },
    )


if __name__ == "__main__":
    main()
