"""Pairwise ("corner") plots of posterior samples.

:func:`corner_plot` (matplotlib only; what the commands write): diagonal, histogram of
each parameter with its 5 / 50 / 95 % quantiles; below the diagonal, 2-d histograms of
each pair; optional ``truths`` drawn as lines. :func:`pair_plot`: the same with the
``corner`` package (Foreman-Mackey 2016; the ``[viz]`` extra), from a
:class:`~mfdesign.calibration.posterior.Posterior` or samples, truths as lines.
"""

from __future__ import annotations

from pathlib import Path
from typing import Sequence

import numpy as np

__all__ = ["corner_plot", "pair_plot"]


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
    import matplotlib.pyplot as plt

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
    if title:
        fig.suptitle(title, fontsize=9)
    path = Path(path)
    path.parent.mkdir(parents=True, exist_ok=True)
    from mfdesign import outputs

    outputs.savefig(fig, path, dpi=110)
    plt.close(fig)
    return path
