"""Pairwise ("corner") plots of posterior samples.

:func:`corner_plot` (what the commands write): ArviZ's ``plot_pair`` (marginal histograms
on the diagonal, 2-d densities below it) in the figures' units (Pa shown as kPa, every
label with its unit; docs/figures.md), optional ``truths`` drawn as lines.
:func:`pair_plot`: the same with the ``corner`` package (Foreman-Mackey 2016; the
``[viz]`` extra), from a :class:`~mfdesign.calibration.posterior.Posterior` or samples.

:func:`pit` and :func:`predictive_check_plot`: is the posterior predictive calibrated? The
probability integral transform of each observed force under its replicated forces (an
``InferenceData`` with ``posterior_predictive`` and ``observed_data``, as
:func:`~mfdesign.calibration.posterior.save_inference_data` writes it with a model) is
uniform for a calibrated model; the share of observations inside the central interval of
each level is that level.
"""

from __future__ import annotations

from pathlib import Path
from typing import Sequence

import numpy as np

__all__ = ["corner_plot", "display_label", "pair_plot", "pit", "pit_coverage", "predictive_check_plot"]

LEVELS = (0.1, 0.2, 0.3, 0.4, 0.5, 0.6, 0.7, 0.8, 0.9, 0.95)


# Units the figures show instead of the stored ones (docs/figures.md): pascals read as
# "3.364e+04 Pa" and their tick labels run into each other; kPa reads as 33.64.
DISPLAY_UNITS = {"Pa": ("kPa", 1e-3)}


def display_label(name: str, unit: str | None) -> tuple[str, float]:
    """``(axis label, factor)`` of a parameter in the figures' units: ``mu_pa`` in Pa ->
    ``("mu [kPa]", 1e-3)``; a parameter without a unit keeps its name."""
    if not unit or unit == "1":
        return name, 1.0
    shown, factor = DISPLAY_UNITS.get(unit, (unit, 1.0))
    base = name[: -len("_pa")] if unit == "Pa" and name.endswith("_pa") else name
    return f"{base} [{shown}]", factor


def _reach(lims, value: float, margin: float = 0.05) -> tuple[float, float]:
    """Axis limits ``lims`` widened to include ``value`` with a margin (unchanged if inside)."""
    lo, hi = lims
    if lo <= value <= hi:
        return lo, hi
    lo, hi = min(lo, value), max(hi, value)
    return lo - margin * (hi - lo), hi + margin * (hi - lo)


def corner_plot(
    samples,
    names: Sequence[str],
    path,  # a PNG path, or None for the figure
    truths: Sequence[float | None] | None = None,
    bins: int = 30,
    title: str | None = None,
    units: Sequence[str] | None = None,
) -> Path:
    """Write a pairwise plot of ``samples`` [S, d] to ``path`` (PNG) and return the path.

    Drawn by ArviZ (``az.plot_pair``: 2-d KDE below the diagonal, marginal densities on it),
    a dependency already, rather than by hand. ``units``: one per parameter (e.g. a
    Posterior's ``units``); Pa is shown in kPa and every axis label carries its unit
    (:func:`display_label`). At most three ticks per axis, rotated, so that their labels
    do not run into each other. ``truths``: one value per parameter (stored units), drawn
    as red lines; None (or NaN) draws no line for that parameter. ``bins``: the marginal
    histograms' bins. ``path`` None: return the matplotlib figure instead of writing it."""
    import arviz as az
    import matplotlib

    matplotlib.use("Agg")
    import matplotlib.pyplot as plt
    from matplotlib.ticker import MaxNLocator

    samples = np.asarray(samples, float)
    if samples.ndim != 2 or samples.shape[1] != len(names):
        raise ValueError(f"samples must be [S, {len(names)}], got {samples.shape}")
    d = samples.shape[1]
    if truths is not None and len(truths) != d:
        raise ValueError(f"{len(truths)} truths for {d} parameters {list(names)}")
    if units is not None and len(units) != d:
        raise ValueError(f"{len(units)} units for {d} parameters {list(names)}")
    shown = [display_label(n, None if units is None else units[i]) for i, n in enumerate(names)]
    labels = [lab for lab, _ in shown]
    x = samples * np.array([f for _, f in shown])
    given = [None] * d if truths is None else list(truths)
    truth: list[float | None] = [
        None if t is None or not np.isfinite(t) else float(t) * factor for t, (_, factor) in zip(given, shown)
    ]
    size = 1.9 * d + 1.2
    data = {lab: x[None, :, i] for i, lab in enumerate(labels)}  # one chain: the draws are pooled
    axes = az.plot_pair(
        data,
        kind="kde" if len(x) >= 20 else "scatter",
        marginals=True,
        figsize=(size, size),
        textsize=8,
        marginal_kwargs={"kind": "hist", "hist_kwargs": {"bins": bins, "color": "0.45"}},
        kde_kwargs={
            "contour": True,
            "fill_last": False,
            "contourf_kwargs": {"cmap": "Greys"},
            "contour_kwargs": {"colors": "0.3", "linewidths": 0.5},
        },
        backend_kwargs={"layout": "constrained"},
        show=False,
    )
    axes = np.atleast_2d(axes)
    fig = axes.ravel()[0].figure
    for i in range(d):
        for j in range(d):
            ax = axes[i, j]
            if ax is None or not ax.get_visible() or j > i:
                continue
            # a truth outside the posterior's bulk still shows: the axis reaches it
            tx, ty = truth[j], truth[i]
            if tx is not None:
                ax.axvline(tx, color="C3", lw=0.8)
                ax.set_xlim(_reach(ax.get_xlim(), tx))
            if i == j:
                ax.set_yticks([])  # a marginal's density scale says nothing here
            else:
                ax.yaxis.set_major_locator(MaxNLocator(3))
                if ty is not None:
                    ax.axhline(ty, color="C3", lw=0.8)
                    ax.set_ylim(_reach(ax.get_ylim(), ty))
            ax.xaxis.set_major_locator(MaxNLocator(3))
            ax.tick_params(axis="x", labelrotation=45, labelsize=7)
            ax.tick_params(axis="y", labelsize=7)
    if title:
        fig.suptitle(title, fontsize=9)
    if path is None:  # the figure itself (tests measure its tick labels)
        return fig
    path = Path(path)
    path.parent.mkdir(parents=True, exist_ok=True)
    from mfdesign import outputs

    outputs.savefig(fig, path, dpi=110)
    plt.close(fig)
    return path


def pair_plot(
    posterior,
    path,
    truths=None,
    names: Sequence[str] | None = None,
    title: str | None = None,
    quantiles: Sequence[float] = (0.05, 0.5, 0.95),
) -> Path:
    """A ``corner.corner`` pair plot (PNG) of a Posterior (or samples [S, d] with ``names``).

    ``truths``: a dict ``{name: value}`` (parameters not in it get no line) or a sequence
    in the order of the plotted names; drawn as lines. For a Posterior the per-membrane
    latents ``thickness[*]`` are left out unless ``names`` asks for them.
    """
    try:
        import corner
    except ImportError:  # pragma: no cover -- depends on the install
        raise ImportError("pair_plot needs the corner package: pip install 'mfdesign[viz]'") from None
    import matplotlib

    matplotlib.use("Agg")

    from mfdesign.calibration.posterior import Posterior

    if isinstance(posterior, Posterior):
        all_names = list(posterior.names)
        names = list(names) if names is not None else [n for n in all_names if not n.startswith("thickness[")]
        missing = [n for n in names if n not in all_names]
        if missing:
            raise KeyError(f"no parameter(s) {missing}; parameters: {all_names}")
        samples = np.asarray(posterior.samples, float)[:, [all_names.index(n) for n in names]]
        units = {n: u for n, u in zip(all_names, posterior.units)}
        labels = [f"{n} [{units[n]}]" if units.get(n, "1") not in ("", "1") else n for n in names]
    else:
        samples = np.asarray(posterior, float)
        if names is None or samples.ndim != 2 or samples.shape[1] != len(names):
            raise ValueError(f"samples must be [S, len(names)], got {samples.shape} and names {names}")
        names, labels = list(names), list(names)
    if isinstance(truths, dict):
        truths = [truths.get(n) for n in names]
    elif truths is not None and len(truths) != len(names):
        raise ValueError(f"{len(truths)} truths for {len(names)} parameters {names}")
    fig = corner.corner(
        samples,
        labels=labels,
        truths=truths,
        truth_color="C3",
        quantiles=list(quantiles),
        show_titles=True,
        title_fmt=".3g",
        title_kwargs={"fontsize": 8},
        label_kwargs={"fontsize": 8},
    )
    return _save(fig, path, title)


def pit(idata, var: str = "force_n") -> np.ndarray:
    """PIT [row] in [0, 1]: the share of replicated ``var`` (``posterior_predictive``, all
    chains and draws) below each observation (``observed_data``), ties counted half."""
    rep = np.asarray(idata.posterior_predictive[var], float)
    rep = rep.reshape(-1, rep.shape[-1])
    obs = np.asarray(idata.observed_data[var], float)
    return (rep < obs).mean(0) + 0.5 * (rep == obs).mean(0)


def pit_coverage(pit_values, levels: Sequence[float] = LEVELS) -> dict[float, float]:
    """Share of observations inside the central interval of each level: those whose PIT is
    within level / 2 of one half."""
    u = np.asarray(pit_values, float)
    return {float(a): float(np.mean(np.abs(u - 0.5) <= a / 2)) for a in levels}


def predictive_check_plot(pits: dict, path, title: str | None = None, bins: int = 20) -> Path:
    """Two panels from ``pits`` (name -> PIT values, :func:`pit`): the PIT histograms
    (flat at 1 for a calibrated model; a U: intervals too narrow, a hump: too wide) and the
    coverage curves (empirical vs nominal level; the diagonal is calibrated)."""
    import matplotlib

    matplotlib.use("Agg")
    import matplotlib.pyplot as plt

    fig, (ax0, ax1) = plt.subplots(1, 2, figsize=(10, 4), layout="constrained")
    edges = np.linspace(0.0, 1.0, bins + 1)
    for i, (name, u) in enumerate(pits.items()):
        ax0.hist(np.asarray(u, float), bins=edges, density=True, histtype="step", lw=1.5, color=f"C{i}", label=name)
        cov = pit_coverage(u)
        ax1.plot(list(cov), list(cov.values()), "o-", color=f"C{i}", label=f"{name} (90 %: {cov[0.9]:.2f})")
    ax0.axhline(1.0, color="k", ls="--", lw=0.8)
    ax0.set_xlabel("PIT: share of replicated forces below the observed one")
    ax0.set_ylabel("density")
    ax0.set_title("PIT histogram (flat = calibrated)", fontsize=9)
    ax0.legend(fontsize=7)
    ax1.plot([0, 1], [0, 1], "k--", lw=0.8)
    ax1.set_xlabel("nominal level of the central interval")
    ax1.set_ylabel("share of observations inside")
    ax1.set_title("coverage (diagonal = calibrated)", fontsize=9)
    ax1.legend(fontsize=7, loc="upper left")
    return _save(fig, path, title)


def _save(fig, path, title: str | None = None) -> Path:
    """Title, write atomically (folder created), close: the end of every figure here."""
    import matplotlib.pyplot as plt

    from mfdesign import outputs

    if title:
        fig.suptitle(title, fontsize=9)
    path = Path(path)
    path.parent.mkdir(parents=True, exist_ok=True)
    outputs.savefig(fig, path, dpi=110)
    plt.close(fig)
    return path
