"""Pictures, HTML and JSON of a :class:`~mfdesign.diagnosis.pipeline.Diagnosis`.

Diagnosis produces the numbers and the words (``Diagnosis.to_json()``); this module draws
them and renders the page. ``write_report(diagnosis, out_dir)`` writes ``diagnosis.json``,
``index.html`` (template ``diagnosis.html.j2``, through
:func:`mfdesign.report.render.write_html`; it links the PNGs by relative path, so the
folder can be moved) and:

* ``maps_before.png`` / ``maps_after.png``: per-membrane height x pressure maps of the mean
  residual (observed - predicted, N; red = model under-predicts), one colour scale;
* ``parity.png``: observed vs predicted force; ``trial_order.png``: mean residual per trial;
* ``breakdown.png``: RMS residual by height, pressure, ring count, phase, trial order;
* ``screen.png``: explained fraction per candidate effect;
* ``joint_<round>_<k>.png``: where the data cannot tell two explanations apart, their
  joint posterior (Laplace approximation of the union's refit: 1 and 2 sigma ellipses of
  the first parameter of each);
* ``shapes.png`` (optional, the real simulator only): the simulated membrane at the worst points.
"""

from __future__ import annotations

import json
import math
from pathlib import Path

import numpy as np

from mfdesign import outputs  # atomic writes: a reader never sees a torn file
from mfdesign.diagnosis.check import FLOOR_FACTOR
from mfdesign.diagnosis.residuals import Residuals, breakdowns
from mfdesign.report.render import write_html

__all__ = ["floor_banner", "limit_banners", "write_report"]


def _plt():
    import matplotlib

    matplotlib.use("Agg")
    import matplotlib.pyplot as plt

    return plt


def _save(fig, path: Path) -> None:
    """Lay out, write (90 dpi: the report shows many small figures) and free a figure."""
    if fig.get_layout_engine() is None:  # a figure made with constrained layout keeps it
        fig.tight_layout()
    outputs.savefig(fig, path, dpi=90)
    _plt().close(fig)


def floor_banner(diag) -> str | None:
    """A warning when the final model (with the effects added, else the one diagnosed) sits
    above ``FLOOR_FACTOR`` x the noise floor (the factor the verdicts use), else None."""
    res = diag.after if diag.after is not None else diag.before
    floor = diag.before.noise_floor_n
    if not floor > 0 or res.rmse_n <= FLOOR_FACTOR * floor:
        return None
    which = f"after adding {', '.join(diag.effects)}" if diag.after is not None else "as diagnosed"
    return (
        f"The model {which} still sits at {res.rmse_n / floor:.1f}x the noise floor "
        f"(RMSE {res.rmse_n:.2f} N vs {floor:.2f} N; more than {FLOOR_FACTOR:g}x): something is still missing."
    )


def limit_banners(diag) -> list[str]:
    """What a reader must know before trusting the verdict, for the top of a page: the
    model above the noise floor (:func:`floor_banner`), effect sets the data cannot tell
    apart (the verdict names both; here they are said first), and candidates that could not
    be evaluated (neither the simulator nor the FE reference has a value at their rows)."""
    out = [b for b in (floor_banner(diag),) if b]
    for i, step in enumerate(diag.steps):
        v = step["verdict"]
        if v.get("alternatives"):
            others = "; ".join("+".join(a["effects"]) for a in v["alternatives"])
            out.append(
                f"Round {i + 1}: the data cannot tell {'+'.join(v.get('effects') or [])} from {others}: "
                "both are named, neither is preferred (the diagnosis section gives the trial that would separate them)."
            )
        if v.get("not_evaluated"):
            names = ", ".join("+".join(e) for e in v["not_evaluated"])
            out.append(
                f"Round {i + 1}: candidate(s) not evaluated ({names}): neither the simulator nor the FE reference "
                "has a value at their rows; the verdict cannot rule them out."
            )
    return out


def residual_maps(res: Residuals, path: Path, title: str, vmax: float | None = None) -> float:
    """Per-membrane mean-residual maps on 5 mm x 500 Pa cells; returns the colour limit used."""
    plt = _plt()
    f = res.frame
    keys = list(dict.fromkeys(f["design_key"]))
    n = max(len(keys), 1)
    cols = min(3, n)
    rows = math.ceil(n / cols)
    # constrained layout: without it the top row's x labels ran into the bottom row's titles
    fig, axes = plt.subplots(rows, cols, figsize=(4.2 * cols, 3.4 * rows), squeeze=False, layout="constrained")
    he = np.arange(0.0, max(float(f["height_mm"].max()) + 5.0, 10.0), 5.0) if len(f) else np.arange(0, 10, 5.0)
    pe = (
        np.arange(0.0, max(float(f["pressure_pa"].max()) + 500.0, 1000.0), 500.0)
        if len(f)
        else np.arange(0, 1000, 500.0)
    )
    grids = []
    for k in keys:
        g = f[f["design_key"] == k]
        s, _, _ = np.histogram2d(g["height_mm"], g["pressure_pa"], [he, pe], weights=g["residual_n"])
        c, _, _ = np.histogram2d(g["height_mm"], g["pressure_pa"], [he, pe])
        grids.append(np.where(c > 0, s / np.maximum(c, 1), np.nan))
    if vmax is None:
        finite = np.concatenate([np.abs(m[np.isfinite(m)]) for m in grids]) if grids else np.array([1.0])
        vmax = float(np.quantile(finite, 0.98)) if finite.size else 1.0
        vmax = max(vmax, 1e-3)
    for ax in axes.ravel()[n:]:
        ax.axis("off")
    im = None
    for ax, k, m in zip(axes.ravel(), keys, grids):
        im = ax.pcolormesh(pe / 1e3, he, m, cmap="RdBu_r", vmin=-vmax, vmax=vmax, shading="flat")
        ax.set_title(k, fontsize=8)
        ax.set_xlabel("pressure [kPa]")
        ax.set_ylabel("height [mm]")
    if im is not None:
        fig.colorbar(im, ax=axes.ravel().tolist(), label="mean residual (obs - model) [N]")
    fig.suptitle(f"{title}: RMSE {res.rmse_n:.3f} N, noise floor {res.noise_floor_n:.3f} N")
    outputs.savefig(fig, path, dpi=90)
    plt.close(fig)
    return vmax


def parity(res: Residuals, path: Path, after: Residuals | None = None) -> None:
    """Observed vs model force (left) and the residual against the model force on its own
    scale (right): on the 0-200 N axes of the left panel a 1.5 N residual is invisible."""
    plt = _plt()
    fig, (ax, axr) = plt.subplots(1, 2, figsize=(10, 4.6), layout="constrained")
    rng = np.random.default_rng(0)
    for r, label, c in ((res, "before", "tab:red"), (after, "after", "tab:blue")):
        if r is None or not len(r.frame):
            continue
        idx = rng.choice(len(r.frame), size=min(len(r.frame), 8000), replace=False)
        model = r.frame["predicted_n"].to_numpy()[idx]
        observed = r.frame["observed_n"].to_numpy()[idx]
        ax.scatter(model, observed, s=2, alpha=0.3, c=c, label=f"{label} (RMSE {r.rmse_n:.2f} N)")
        axr.scatter(model, observed - model, s=2, alpha=0.3, c=c, label=label)
    top = float(res.frame[["observed_n", "predicted_n"]].max().max()) if len(res.frame) else 1.0
    ax.plot([0, top], [0, top], "k--", lw=1)
    ax.set_xlabel("model force [N]")
    ax.set_ylabel("observed force [N]")
    ax.set_title("parity", fontsize=9)
    ax.legend(markerscale=4, loc="upper left")
    axr.axhline(0.0, color="k", lw=0.8)
    if res.noise_floor_n > 0:
        for sign in (-1, 1):
            axr.axhline(sign * res.noise_floor_n, color="k", ls="--", lw=0.8, label="noise floor" if sign > 0 else None)
    axr.set_xlabel("model force [N]")
    axr.set_ylabel("residual: observed - model [N]")
    axr.set_title("residuals on their own scale", fontsize=9)
    axr.legend(markerscale=4, loc="upper left", fontsize=8)
    _save(fig, path)


def trial_plot(res: Residuals, path: Path, after: Residuals | None = None) -> None:
    plt = _plt()
    fig, ax = plt.subplots(figsize=(7, 3.5))
    for r, ls in ((res, "-"), (after, ":")):
        if r is None:
            continue
        for k, g in r.frame.groupby("design_key", sort=False):
            m = g.groupby("trial_order")["residual_n"].mean()
            ax.plot(m.index, m.values, ls, marker=".", label=k if r is res else None)
    ax.axhline(0, color="k", lw=0.8)
    ax.set_xlabel("trial order in the membrane's life (0 = first)")
    ax.set_ylabel("mean residual [N]")
    ax.legend(fontsize=6, loc="upper right")
    ax.set_title("residual vs trial order (solid: before, dotted: after)")
    _save(fig, path)


def breakdown_plot(res: Residuals, path: Path, after: Residuals | None = None) -> None:
    plt = _plt()
    names = ("height", "pressure", "ring_count", "phase", "trial_order", "force_level")
    # constrained layout and 8-point labels at 45 degrees: at 6 points and 60 degrees the
    # tick labels came out ~5 px tall in the report
    fig, axes = plt.subplots(2, 3, figsize=(13, 7.5), layout="constrained")
    b0 = breakdowns(res)
    b1 = breakdowns(after) if after is not None else {}
    for ax, name in zip(axes.ravel(), names):
        bins = b0.get(name, [])
        x = np.arange(len(bins))
        ax.bar(x - 0.2, [b["rms_n"] for b in bins], 0.4, label="before", color="tab:red")
        if name in b1:
            m = {b["bin"]: b["rms_n"] for b in b1[name]}
            ax.bar(x + 0.2, [m.get(b["bin"], np.nan) for b in bins], 0.4, label="after", color="tab:blue")
        ax.axhline(res.noise_floor_n, color="k", ls="--", lw=0.8, label="noise floor")
        ax.set_xticks(x, [b["bin"] for b in bins], rotation=45, ha="right", rotation_mode="anchor", fontsize=8)
        ax.set_ylabel("RMS residual [N]")
        ax.set_title(f"RMS residual by {name.replace('_', ' ')}", fontsize=10)
    axes[0, 0].legend(fontsize=7)
    _save(fig, path)


def screen_plot(step: dict, path: Path) -> None:
    plt = _plt()
    rows = step["screen"]
    fig, ax = plt.subplots(figsize=(6, 0.35 * len(rows) + 1.2))
    y = np.arange(len(rows))[::-1]
    ax.barh(y, [r.explained_fraction for r in rows], color="tab:green")
    ax.set_yticks(y, [r.effect for r in rows])
    ax.set_xlim(0, 1)
    ax.set_xlabel("fraction of residual mean square explained (first order)")
    ax.set_title(
        "effect screen" + (f" (model already has {', '.join(step['base_effects'])})" if step["base_effects"] else "")
    )
    _save(fig, path)


def shapes_plot(res: Residuals, path: Path, params=None, n: int = 3) -> list[dict]:
    """The simulated meridian (``solve.shape``) at the ``n`` points with the largest |residual|."""
    from mfdesign.design import Membrane
    from mfdesign.physics.params import SimParams
    from mfdesign.physics.solve import shape

    plt = _plt()
    f = res.frame[res.frame["experiment"] == "force"] if (res.frame["experiment"] == "force").any() else res.frame
    worst = f.reindex(f["residual_n"].abs().sort_values(ascending=False).index)
    picked, seen = [], set()
    for _, row in worst.iterrows():
        if row.design_key in seen:
            continue
        seen.add(row.design_key)
        picked.append(row)
        if len(picked) >= n:
            break
    fig, ax = plt.subplots(figsize=(7, 4))
    out = []
    for row in picked:
        s = shape(
            Membrane.from_key(row.design_key), float(row.height_mm), float(row.pressure_pa), params or SimParams()
        )
        ax.plot(
            s.R_mm,
            s.Z_mm - s.Z_mm[-1],
            label=f"{row.design_key} h={row.height_mm:g} mm p={row.pressure_pa / 1e3:.2f} kPa r={row.residual_n:+.2f} N",
        )
        out.append(
            {
                "design_key": row.design_key,
                "height_mm": float(row.height_mm),
                "pressure_pa": float(row.pressure_pa),
                "residual_n": float(row.residual_n),
                "status": int(s.status),
            }
        )
    ax.set_xlabel("R [mm]")
    ax.set_ylabel("Z above the clamp [mm]")
    ax.legend(fontsize=6, loc="upper right")
    ax.set_title("simulated membrane at the worst points")
    _save(fig, path)
    return out


def joint_plot(verdict: dict, alt: dict, path: Path) -> None:
    """The joint posterior of the claimed set and an indistinguishable one (module doc)."""
    joint = alt["joint"]
    names = list(joint["theta"])
    first = lambda eff: next(n for n in names if n.split(".")[0] == eff)  # noqa: E731
    a = first(next(e for e in verdict["effects"] if e not in alt["effects"]))
    b = first(next(e for e in alt["effects"] if e not in verdict["effects"]))
    i, j = names.index(a), names.index(b)
    sa, sb = joint["stderr"][a], joint["stderr"][b]
    rho = joint["correlation"][i][j] if joint["correlation"] else 0.0
    cov = np.array([[sa * sa, rho * sa * sb], [rho * sa * sb, sb * sb]])
    w, v = np.linalg.eigh(cov)
    t = np.linspace(0, 2 * math.pi, 200)
    plt = _plt()
    fig, ax = plt.subplots(figsize=(4.6, 4.0))
    for k, ls in ((1, "-"), (2, "--")):
        e = v @ (k * np.sqrt(np.clip(w, 0, None))[:, None] * np.stack([np.cos(t), np.sin(t)]))
        ax.plot(joint["theta"][a] + e[0], joint["theta"][b] + e[1], ls, c="tab:blue", label=f"{k} sigma")
    ax.plot([joint["theta"][a]], [joint["theta"][b]], "o", c="tab:blue")
    ax.set_xlabel(a)
    ax.set_ylabel(b)
    ax.set_title(f"joint posterior (Laplace), correlation {rho:+.2f}", fontsize=9)
    ax.legend(fontsize=8)
    _save(fig, path)


def write_report(
    diag,
    out_dir,
    shapes: bool = False,
    params=None,
    *,
    call: str = "",
    seeds: dict | None = None,
    inputs: dict | None = None,
) -> dict[str, Path]:
    """Write JSON, PNGs and ``index.html`` into ``out_dir``; returns the paths.

    ``diagnosis.json`` carries a ``"provenance"`` (:func:`mfdesign.provenance.provenance`):
    the version, ``call`` (default: the command line when run as ``mfdesign ...``, else
    ``mfdesign.report.diagnosis.write_report()``), ``seeds``, ``inputs`` (name -> sha256 of
    the input files, as the caller knows them) and the machine. Readers of the file ignore it."""
    from mfdesign.provenance import call_line, provenance

    out = Path(out_dir)
    out.mkdir(parents=True, exist_ok=True)
    paths: dict[str, Path] = {}
    data = diag.to_json()
    vmax = residual_maps(diag.before, out / "maps_before.png", "before")
    paths["maps_before"] = out / "maps_before.png"
    if diag.after is not None:
        residual_maps(diag.after, out / "maps_after.png", "after (" + ", ".join(diag.effects) + ")", vmax=vmax)
        paths["maps_after"] = out / "maps_after.png"
    parity(diag.before, out / "parity.png", diag.after)
    trial_plot(diag.before, out / "trial_order.png", diag.after)
    breakdown_plot(diag.before, out / "breakdown.png", diag.after)
    paths.update(parity=out / "parity.png", trial_order=out / "trial_order.png", breakdown=out / "breakdown.png")
    for i, step in enumerate(diag.steps):
        screen_plot(step, out / f"screen_{i + 1}.png")
        paths[f"screen_{i + 1}"] = out / f"screen_{i + 1}.png"
        for k, alt in enumerate(step["verdict"].get("alternatives", [])):
            if alt.get("joint"):
                joint_plot(step["verdict"], alt, out / f"joint_{i + 1}_{k + 1}.png")
                paths[f"joint_{i + 1}_{k + 1}"] = out / f"joint_{i + 1}_{k + 1}.png"
    if shapes:
        data["worst_point_shapes"] = shapes_plot(diag.before, out / "shapes.png", params)
        paths["shapes"] = out / "shapes.png"
    record = provenance(call or call_line("mfdesign.report.diagnosis.write_report()"), seeds, inputs)
    outputs.write_text(out / "diagnosis.json", json.dumps(data | {"provenance": record}, indent=1, default=str))
    paths["json"] = out / "diagnosis.json"
    paths["html"] = write_html(
        out / "index.html",
        "diagnosis.html.j2",
        title="mfdesign diagnosis",
        banners=limit_banners(diag),
        data=data,
        images={k: p.name for k, p in paths.items() if p.suffix == ".png"},
    )
    return paths
