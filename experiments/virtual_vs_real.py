"""Realism check: the virtual rig's mass lifts (plain physics, no hidden effect) beside the real ones.

For the 7 membranes of the real mass-lift file (``load_mass_lift()``) the virtual rig runs
the same masses (1.5, 2.5, 4.0 kg) with the authors' constants and no effect. Gaps: for
every real sample (height h, pressure p) of a (membrane, mass), the virtual pressure at
which the plate first reaches h on quasi-static inflation; RMSE and mean of
``p_virtual - p_real`` in Pa and relative to the mean real pressure, over the real samples
whose height the virtual plate reaches (``coverage``: the fraction of real samples that
could be matched).

Writes ``experiments/out/virtual_vs_real.json`` and ``.png`` (pressure vs height, one
panel per membrane, colour = mass; dots real, lines virtual noise-free, crosses one noisy
virtual trial).

    python experiments/virtual_vs_real.py [--cache-dir experiments/out/plane_cache]
"""

from __future__ import annotations

import json

import numpy as np

from _common import Timing, parser, timed, write_json  # experiments/ is on a script's path


def virtual_pressure_at(h_traj: np.ndarray, p_traj: np.ndarray, heights: np.ndarray) -> np.ndarray:
    """Pressure at which an inflation trajectory first reaches each height (NaN: never)."""
    ok = np.isfinite(h_traj) & np.isfinite(p_traj)
    h_traj, p_traj = h_traj[ok], p_traj[ok]
    out = np.full(len(heights), np.nan)
    if len(h_traj) < 2:
        return out
    reach = np.maximum.accumulate(h_traj)  # the highest the plate has been so far
    for k, h in enumerate(heights):
        idx = np.nonzero(reach >= h)[0]
        if idx.size == 0:
            continue
        i = idx[0]
        if i == 0:
            out[k] = p_traj[0]
            continue
        h0, h1 = reach[i - 1], reach[i]
        w = (h - h0) / (h1 - h0) if h1 > h0 else 1.0
        out[k] = p_traj[i - 1] + w * (p_traj[i] - p_traj[i - 1])
    return out


def main(argv=None) -> dict:
    ap = parser(__doc__, seed=True, plane_cache=True)
    args = ap.parse_args(argv)

    from mfdesign._cache import enable_compilation_cache

    enable_compilation_cache()
    import matplotlib

    matplotlib.use("Agg")
    import matplotlib.pyplot as plt

    from mfdesign.data.spa_design import load_mass_lift
    from mfdesign.design import Membrane
    from mfdesign.rig.virtual import Noise, Protocol, VirtualRig, simulator_fingerprint
    from mfdesign.units import G_M_S2 as G

    out = args.out
    out.mkdir(parents=True, exist_ok=True)
    real = load_mass_lift().df
    keys = list(dict.fromkeys(real["design_key"]))
    masses_n = sorted(real["force_n"].unique())
    masses_kg = [round(f / G, 3) for f in masses_n]
    cache = args.cache_dir
    proto = Protocol(lift_trials=1)
    clean = VirtualRig(seed=args.seed, noise=Noise.none(), protocol=proto, cache_dir=cache)
    noisy = VirtualRig(seed=args.seed, protocol=proto, cache_dir=cache)
    gaps, clock = [], Timing()
    fig, axes = plt.subplots(2, 4, figsize=(18, 8.5), sharex=True, sharey=True)
    colours = dict(zip(masses_n, ["tab:blue", "tab:orange", "tab:red"]))
    for ax, key in zip(axes.ravel(), keys):
        design = Membrane.from_key(key)
        with timed() as t:
            vc = clean.mass_lift(design, masses_kg).df
            vn = noisy.mass_lift(design, masses_kg).df
        print(f"{key}: {t['wall_s']:.0f} s", flush=True)
        for f_n in masses_n:
            r = real[(real["design_key"] == key) & (real["force_n"] == f_n)]
            load = f_n
            c = vc[np.isclose(vc["force_n"], load, atol=0.01)]
            n = vn[np.isclose(vn["force_n"], load, atol=0.01)]
            pv = virtual_pressure_at(c["height_mm"].to_numpy(), c["pressure_pa"].to_numpy(), r["height_mm"].to_numpy())
            ok = np.isfinite(pv)
            d = pv[ok] - r["pressure_pa"].to_numpy()[ok]
            mean_real = float(r["pressure_pa"].mean())
            row = dict(
                design_key=key,
                mass_kg=round(f_n / G, 3),
                force_n=float(f_n),
                n_real=int(len(r)),
                coverage=float(ok.mean()) if len(r) else 0.0,
                rmse_pa=float(np.sqrt(np.mean(d**2))) if d.size else None,
                bias_pa=float(np.mean(d)) if d.size else None,
                mean_real_pa=mean_real,
                rmse_rel=float(np.sqrt(np.mean(d**2)) / mean_real) if d.size else None,
                virtual_max_height_mm=float(np.nanmax(c["height_mm"])) if len(c) else None,
                real_max_height_mm=float(r["height_mm"].max()) if len(r) else None,
            )
            gaps.append(row)
            col = colours[f_n]
            ax.plot(r["height_mm"], r["pressure_pa"] / 1e3, ".", ms=1.5, color=col, alpha=0.25)
            ax.plot(c["height_mm"], c["pressure_pa"] / 1e3, "-", lw=1.8, color=col, label=f"{row['mass_kg']:g} kg")
            ax.plot(n["height_mm"].iloc[::10], n["pressure_pa"].iloc[::10] / 1e3, "x", ms=2.5, color=col, alpha=0.6)
        ax.set_title(key, fontsize=8)
        ax.set_xlim(-2, 80)
        ax.set_ylim(0, 10.5)
        ax.grid(alpha=0.3)
    for ax in axes[-1]:
        ax.set_xlabel("plate height [mm]")
    for ax in axes[:, 0]:
        ax.set_ylabel("pressure [kPa]")
    axes.ravel()[0].legend(title="dots real, lines virtual", fontsize=7)
    axes.ravel()[-1].axis("off")
    fig.suptitle("Mass lift: real (dots) vs virtual rig, plain physics (lines; crosses: one noisy trial)")
    fig.tight_layout()
    fig.savefig(out / "virtual_vs_real.png", dpi=110)
    d_all = [g for g in gaps if g["rmse_pa"] is not None]
    w = np.array([g["n_real"] * g["coverage"] for g in d_all])
    summary = dict(
        overall_rmse_pa=float(np.sqrt(np.sum(w * np.array([g["rmse_pa"] ** 2 for g in d_all])) / w.sum())),
        overall_bias_pa=float(np.sum(w * np.array([g["bias_pa"] for g in d_all])) / w.sum()),
        median_rmse_rel=float(np.median([g["rmse_rel"] for g in d_all])),
        mean_coverage=float(np.mean([g["coverage"] for g in gaps])),
        n_pairs=len(gaps),
        n_pairs_matched=len(d_all),
    )
    result = dict(
        what="virtual mass lift (plain physics, SimParams() defaults, no effect) vs real mass-lift file",
        metric="p_virtual(h) - p_real at the real samples' heights; p_virtual(h): pressure at which "
        "the noise-free virtual plate first reaches h on inflation",
        protocol=dict(
            ramp_pa_per_s=proto.ramp_pa_per_s,
            sample_hz=proto.sample_hz,
            height_step_mm=proto.height_step_mm,
            pressure_step_pa=proto.pressure_step_pa,
            lift_limit_pa=proto.lift_limit_pa,
            lift_height_max_mm=proto.lift_height_max_mm,
        ),
        simulator_fingerprint=simulator_fingerprint(),
        summary=summary,
        gaps=gaps,
        burst_events=[e for e in clean.events if e["status"] == "burst"],
        seconds=round(clock.elapsed(), 1),
    )
    write_json(out / "virtual_vs_real.json", result, indent=1)
    print(json.dumps(summary, indent=1))
    return result


if __name__ == "__main__":
    main()
