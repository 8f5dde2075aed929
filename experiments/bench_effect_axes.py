"""How exact is the exact model with an effect on an additive axis, where calibration meets the real data?

``experiments/real_mass_lift.py --effect-axes additive`` calibrates the fabric inset with
J_m and the ring ratio on a crossed (tensor) lattice and the inset's axis added at the
reference material: ``G = G_T(jm, ring) + G_inset(c) - G_inset(0)``, first order in the
cross terms. This measures that approximation against direct simulator calls
(``force_at``, the truth) on the real membranes' floating lift rows, at the constants the
calibration reaches (by default the posterior medians that the first variant's
``real_mass_lift_free_latents/real_mass_lift.json`` holds, the run the committed JSON measured,
else ``--mu-pa/--jm/--inset-mm``), and writes RMS / max error per membrane, and both
models' RMSE against the measured force on the same rows (what the lattice's error does to
a fit's figures).

    python experiments/bench_effect_axes.py [--rows 24] [--effect-axes tensor-jm]

``--effect-axes tensor-jm`` measures the other approximation: the effect crossed with J_m,
the ring ratio's axis added at the reference (``force_model_named``); it writes
``bench_effect_axes_tensor-jm.json``. ``--ring-factor F`` puts the rings at F times the
modelled fabric (``ring_stiffening``): how far the ring axis's cross terms carry.
``--rows N`` other than 24 adds ``_rows<N>`` to the JSON's name.
"""

from __future__ import annotations

import json

import numpy as np

from _common import OUT, machine, parser, timed, write_json  # experiments/ is on a script's path


def main():
    ap = parser(__doc__, seed=True)
    ap.add_argument("--rows", type=int, default=24, help="floating lift rows per membrane")
    ap.add_argument("--mu-pa", type=float, default=None)
    ap.add_argument("--jm", type=float, default=None)
    ap.add_argument("--inset-mm", type=float, default=None)
    ap.add_argument("--effect-axes", choices=("additive", "tensor-jm", "tensor"), default="additive")
    ap.add_argument(
        "--ring-factor",
        type=float,
        default=1.0,
        help="rings this many times the modelled fabric (ring_stiffening); the JSON's name gets _ring<F>",
    )
    args = ap.parse_args()

    import jax.numpy as jnp

    from mfdesign.calibration.workflow import force_model_named
    from mfdesign.data import load_mass_lift
    from mfdesign.data.lifts import floating_rows
    from mfdesign.design import Membrane
    from mfdesign.physics.params import SimParams
    from mfdesign.physics.solve import force_at

    # the first variant's run (real_mass_lift.json now holds the nested leave-one-membrane-out)
    src = OUT / "real_mass_lift_free_latents" / "real_mass_lift.json"
    post = {}
    if src.is_file():
        rows = {r["parameter"]: r for r in json.loads(src.read_text())["posterior_all_membranes"]["parameters"]}
        post = {k: rows[k]["median"] for k in ("mu_pa", "jm", "fabric_inset.inset_mm") if k in rows}
    params = SimParams(
        mu_pa=args.mu_pa or post.get("mu_pa", 31.7e3),
        jm=args.jm or post.get("jm", 39.6),
        fabric_inset_mm=args.inset_mm if args.inset_mm is not None else post.get("fabric_inset.inset_mm", 0.63),
        ring_mu_pa=SimParams().ring_mu_pa * args.ring_factor,
    )
    meas = load_mass_lift()
    df = meas.df[floating_rows(meas)].groupby("design_key").sample(n=args.rows, random_state=args.seed)
    out = {}
    with timed() as clock:
        fm = force_model_named("exact", meas, effect_axes=args.effect_axes).covering(params).strict(True)
        for key, g in df.groupby("design_key", sort=False):
            h, p = g["height_mm"].to_numpy(), g["pressure_pa"].to_numpy()
            d = np.broadcast_to(Membrane.from_key(key).to_array(), (len(h), 6))
            got = np.asarray(fm(jnp.asarray(d), jnp.asarray(h), jnp.asarray(p), params))
            ref = np.asarray(force_at(Membrane.from_key(key), h, p, params).force_n)
            ok = np.isfinite(got) & np.isfinite(ref)
            e = (got - ref)[ok]
            # what the lattice's error does to the figures that matter: both models' RMSE
            # against the measured force (the mass's weight) on the same rows
            w = g["force_n"].to_numpy()[ok]
            out[key] = {
                "rms_n": float(np.sqrt(np.mean(e**2))),
                "max_n": float(np.max(np.abs(e))),
                "n": int(e.size),
                "rmse_vs_data_lattice_n": float(np.sqrt(np.mean((got[ok] - w) ** 2))),
                "rmse_vs_data_simulator_n": float(np.sqrt(np.mean((ref[ok] - w) ** 2))),
            }
            print(
                f"{key}: {args.effect_axes} - simulator RMS {out[key]['rms_n']:.3f} N, max {out[key]['max_n']:.3f} N"
                f" (n {e.size}); against the data: lattice {out[key]['rmse_vs_data_lattice_n']:.3f} N,"
                f" simulator {out[key]['rmse_vs_data_simulator_n']:.3f} N",
                flush=True,
            )

    def pool(k):  # RMS over every row (membranes weighted by their rows; 24 each unless some fail)
        return float(np.sqrt(sum(v[k] ** 2 * v["n"] for v in out.values()) / sum(v["n"] for v in out.values())))

    pooled = pool("rms_n")
    vs_data = {"lattice_n": pool("rmse_vs_data_lattice_n"), "simulator_n": pool("rmse_vs_data_simulator_n")}
    print(
        f"pooled RMS {pooled:.3f} N at mu {params.mu_pa:.0f} Pa, J_m {params.jm:.2f}, inset {params.fabric_inset_mm:.3f} mm,"
        f" rings x{args.ring_factor:g}; against the data: lattice {vs_data['lattice_n']:.3f} N,"
        f" simulator {vs_data['simulator_n']:.3f} N"
    )
    name = "bench_effect_axes" + ("" if args.effect_axes == "additive" else f"_{args.effect_axes}")
    name += "" if args.ring_factor == 1.0 else f"_ring{args.ring_factor:g}"
    name += "" if args.rows == 24 else f"_rows{args.rows}"
    write_json(
        args.out / f"{name}.json",
        {
            "effect_axes": args.effect_axes,
            "params": {
                "mu_pa": params.mu_pa,
                "jm": params.jm,
                "fabric_inset_mm": params.fabric_inset_mm,
                "ring_factor": args.ring_factor,
            },
            "rows_per_membrane": args.rows,
            "per_membrane": out,
            "pooled_rms_n": pooled,
            "pooled_rmse_vs_data": vs_data,
            "timing": dict(clock),
            "machine": machine(),
        },
    )


if __name__ == "__main__":
    main()
