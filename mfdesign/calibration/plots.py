"""A small pairwise ("corner") plot of posterior samples, matplotlib only.

Diagonal: histogram of each parameter with its 5 / 50 / 95 % quantiles; below the
diagonal: 2-d histograms of each pair; optional ``truths`` drawn as lines.
"""

from __future__ import annotations

from pathlib import Path
from typing import Sequence

import numpy as np

__all__ = ["corner_plot"]


def corner_plot(samples, names: Sequence[str], path, truths: Sequence[float] | None = None,
                bins: int = 30, title: str | None = None) -> Path:
    """Write a pairwise plot of ``samples`` [S, d] to ``path`` (PNG) and return the path."""
    import matplotlib

    matplotlib.use("Agg")
    import matplotlib.pyplot as plt

    samples = np.asarray(samples, float)
    if samples.ndim != 2 or samples.shape[1] != len(names):
        raise ValueError(f"samples must be [S, {len(names)}], got {samples.shape}")
    d = samples.shape[1]
    fig, axes = plt.subplots(d, d, figsize=(1.9 * d + 1, 1.9 * d + 1), squeeze=False)
    lims = [np.quantile(samples[:, i], [0.002, 0.998]) for i in range(d)]
    lims = [(lo, hi) if hi > lo else (lo - 1e-9 - abs(lo) * 1e-3, hi + 1e-9 + abs(hi) * 1e-3) for lo, hi in lims]
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
                if truths is not None:
                    ax.axhline(truths[i], color="C3", lw=0.8)
            if truths is not None:
                ax.axvline(truths[j], color="C3", lw=0.8)
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
