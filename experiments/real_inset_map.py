"""What pins the fabric inset: the MAP of the real lifts' calibration, with and without the
membranes' thickness latents, on all seven membranes or without one (a fold).

The calibration of ``real_mass_lift.py`` (the ``tensor-jm`` exact planes, 400 likelihood
rows, Student-t noise, the fabric inset calibrated), searched for its MAP only
(``mfdesign.calibration.mcmc.map_on_lattice``, four starts, as ``calibrate`` does), once
per case of ``--cases``: ``LATENTS:DROP`` with LATENTS ``latents`` or ``nolatents`` and
DROP a membrane's index in the file's order (0-6, the fold that holds it out) or ``none``.
``--material coupons`` holds mu and J_m at the coupons' 31.5 kPa and 39.6 (uniform priors
31.3-31.7 kPa, 39.4-39.8); ``free`` calibrates them.

    python experiments/real_inset_map.py --cases latents:4 nolatents:4 nolatents:none

Writes ``experiments/out/real_inset_map.json`` (every case's MAP in physical units).
"""

from __future__ import annotations

import warnings

import numpy as np

from _common import Timing, parser, write_json  # experiments/ is on a script's path


def _case(text: str) -> tuple[bool, int | None]:
    latents, _, drop = text.partition(":")
    if latents not in ("latents", "nolatents") or not (drop == "none" or (drop.isdigit() and int(drop) < 7)):
        raise ValueError(f"case {text!r}: expected LATENTS:DROP, LATENTS latents|nolatents, DROP 0-6 or none")
    return latents == "latents", None if drop == "none" else int(drop)


def main():
    ap = parser(__doc__, seed=True)
    ap.add_argument("--cases", nargs="+", default=["latents:4", "nolatents:4", "nolatents:none"])
    ap.add_argument("--material", choices=("coupons", "free"), default="coupons")
    args = ap.parse_args()
    try:
        cases = [(c, *_case(c)) for c in args.cases]
    except ValueError as err:
        ap.error(str(err))

    from mfdesign._x64 import enable_x64
    from mfdesign.calibration.mcmc import map_on_lattice
    from mfdesign.calibration.workflow import force_model_named, material_priors, model_for
    from mfdesign.data.spa_design import load_mass_lift
    from mfdesign.models.hierarchical import CalibrationData

    enable_x64()
    warnings.simplefilter("ignore")
    data = load_mass_lift()
    keys = list(dict.fromkeys(data.df["design_key"]))
    emu = force_model_named("exact", data, progress=False, effect_axes="tensor-jm")
    priors = material_priors(args.material)
    out = {"material": args.material, "seed": args.seed, "membranes": keys, "cases": {}}
    # one model per case (their parameter layouts differ): a loop over cases, not points
    for name, latents, drop in cases:
        clock = Timing()
        train = data if drop is None else data.subset([k for i, k in enumerate(keys) if i != drop])
        cd = CalibrationData.from_measurements(train, max_rows=400, seed=args.seed)
        model = model_for(
            emu, cd.design_keys, ("fabric_inset",), likelihood="student_t", membrane_latents=latents, **priors
        )
        model, res = map_on_lattice(model, cd, starts=4, seed=args.seed)
        x = {n: float(v) for n, v in zip(model.names, np.asarray(res.x))}
        out["cases"][name] = {
            "held_out": None if drop is None else keys[drop],
            "map": x,
            "map_converged": bool(res.converged),
            "seconds": clock.elapsed(),
        }
        print(f"{name}: inset {x['fabric_inset.inset_mm']:.3f} mm, " + ", ".join(f"{k} {v:.4g}" for k, v in x.items()))
    write_json(args.out / "real_inset_map.json", out, indent=1)


if __name__ == "__main__":
    main()
