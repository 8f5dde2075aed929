"""Pairwise ("corner") plots of posterior samples.

:func:`corner_plot` (matplotlib only; what the commands write): diagonal, histogram of
each parameter with its 5 / 50 / 95 % quantiles; below the diagonal, 2-d histograms of
each pair; optional ``truths`` drawn as lines. :func:`pair_plot`: the same with the
``corner`` package (Foreman-Mackey 2016; the ``[viz]`` extra), from a
:class:`~mfdesign.calibration.posterior.Posterior` or samples, truths as lines.

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

__all__ = ["corner_plot", "pair_plot", "pit", "pit_coverage", "predictive_check_plot"]

LEVELS = (0.1, 0.2, 0.3, 0.4, 0.5, 0.6, 0.7, 0.8, 0.9, 0.95)


def corner_plot(
    samples, names: Sequence[str], path, truths: Sequence[float] | None = None, bins: int = 30, title: str | None = None
) -> Path:
    """Write a pairwise plot of ``samples`` [S, d] to ``path`` (PNG) and return the path.

    ``truths``: one value per parameter, drawn as red lines; None (or NaN) for a parameter
    whose truth is unknown draws no line for it."""
    import matplotlib

    matplotlib.use("Agg")
    import matplotlib.pyplot as plt

    samples = np.asarray(samples, float)
    if samples.ndim != 2 or samples.shape[1] != len(names):
        raise ValueError(f"samples must be [S, {len(names)}], got {samples.shape}")
    d = samples.shape[1]
    if truths is not None and len(truths) != d:
        raise ValueError(f"{len(truths)} truths for {d} parameters {list(names)}")
    truth = (
        [None if t is None or not np.isfinite(t) else float(t) for t in truths] if truths is not None else [None] * d
    )
    fig, axes = plt.subplots(d, d, figsize=(1.9 * d + 1, 1.9 * d + 1), squeeze=False)
    lims = [np.quantile(samples[:, i], [0.002, 0.998]) for i in range(d)]
    lims = [(lo, hi) if hi > lo else (lo - 1e-9 - abs(lo) * 1e-3, hi + 1e-9 + abs(hi) * 1e-3) for lo, hi in lims]
    # A truth outside the posterior's bulk still shows: the axis reaches it (with a margin).
    lims = [
        (lo, hi)
        if t is None or lo <= t <= hi
        else (min(lo, t) - 0.05 * (max(hi, t) - min(lo, t)), max(hi, t) + 0.05 * (max(hi, t) - min(lo, t)))
        for (lo, hi), t in zip(lims, truth)
    ]
    for i in range(d):
        for j in range(d):
            ax = axes[i, j]
            if j > i:
                ax.set_axis_off()
                continue
            if i == j:
                ax.hist(samples[:, i], bins=bins, range=lims[i], color="0.35", histtype="step")
                for q in np.quantile(samples[:, i], [0.05, 0.5, 0.95]):
                    ax.axvline(q, color="C0", lw=0.8, ls="--")
                ax.set_yticks([])
            else:
                ax.hist2d(samples[:, j], samples[:, i], bins=bins, range=[lims[j], lims[i]], cmap="Greys")
                if truth[i] is not None:
                    ax.axhline(truth[i], color="C3", lw=0.8)
            if truth[j] is not None:
                ax.axvline(truth[j], color="C3", lw=0.8)
            ax.tick_params(labelsize=6)
            if i == d - 1:
                ax.set_xlabel(names[j], fontsize=7)
            else:
                ax.set_xticklabels([])
            if j == 0 and i > 0:
                ax.set_ylabel(names[i], fontsize=7)
            elif j > 0:
                ax.set_yticklabels([])
    if title:
        fig.suptitle(title, fontsize=9)
    fig.tight_layout()
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
