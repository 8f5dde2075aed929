"""Leave-membranes-out cross-validation of any force model, and its metrics.

A model is a :class:`ForceModelSpec` (an unfitted config) whose ``fit`` returns an
:class:`~mfdesign.models.predictor.AbstractPredictor`; held-out rows are scored with its
``rig`` members (the measurements are the rig's).

Folds hold out whole membranes (``Measurements.kfold`` / ``leave_one_out``): the question
is how well a model predicts a design it has never seen (Campbell et al. 2025 used
11-fold by membrane on 22 membranes).

Metrics on held-out rows, with ``mu`` the ensemble mean and ``s`` its member std:

- RMSE [N] = sqrt(mean (F - mu)^2), per fold and pooled over all held-out rows;
- median absolute error [N];
- coverage of the central q-interval mu +- z_q * sigma, z_{0.68} = 0.9945,
  z_{0.95} = 1.9600 (Gaussian quantiles), for two sigmas:
  ``epistemic``: sigma = s (the spread of the members only; 0 for a curve fit), and
  ``total``: sigma = sqrt(s^2 + sigma_eps^2), with sigma_eps the RMS residual of the mean
  on the fold's own training rows (a homoscedastic noise term fitted without test data).
"""

from __future__ import annotations

import dataclasses
from typing import Any, Protocol, runtime_checkable

import numpy as np
from tqdm.auto import tqdm

from mfdesign.models.predictor import RIG, AbstractPredictor

Z = {0.68: 0.994457883, 0.95: 1.959963985}


@runtime_checkable
class ForceModelSpec(Protocol):
    """An unfitted model (its config): ``fit(design [n, 6] mm, h [n] mm, p [n] Pa, F [n] N,
    w [n], key=..., progress=...)`` returns the fitted predictor."""

    def fit(self, design, h_mm, p_pa, force_n, weight=None, *, key=None, progress=False) -> AbstractPredictor: ...


def predict_mean_std(model: AbstractPredictor, design, h, p, batch: int = 20_000):
    """Mean and member std [n] (N) of the ``rig`` members at design rows [n, 6] mm, heights
    [n] mm and pressures [n] Pa, in batches of rows (bounded memory)."""
    mus, sds = [], []
    for s in range(0, len(h), batch):
        f = np.asarray(model.members(RIG, design[s : s + batch], h[s : s + batch], p[s : s + batch]))
        mus.append(f.mean(0))
        sds.append(f.std(0))
    return (np.concatenate(mus), np.concatenate(sds)) if mus else (np.zeros(0), np.zeros(0))


def metrics(force, mean, std, noise_sd: float = 0.0) -> dict[str, float]:
    """RMSE, median |error| and 68/95 % coverage (module docstring) of one set of rows."""
    force, mean, std = (np.asarray(a, dtype=np.float64) for a in (force, mean, std))
    if not (force.shape == mean.shape == std.shape) or force.ndim != 1:
        raise ValueError(f"force, mean, std must be equal 1-d shapes, got {force.shape}, {mean.shape}, {std.shape}")
    err = force - mean
    out = {
        "n": int(len(err)),
        "rmse_n": float(np.sqrt(np.mean(err**2))) if len(err) else float("nan"),
        "median_abs_n": float(np.median(np.abs(err))) if len(err) else float("nan"),
    }
    total = np.sqrt(std**2 + noise_sd**2)
    for q, z in Z.items():
        tag = int(round(q * 100))
        out[f"coverage{tag}_epistemic"] = float(np.mean(np.abs(err) <= z * std)) if len(err) else float("nan")
        out[f"coverage{tag}_total"] = float(np.mean(np.abs(err) <= z * total)) if len(err) else float("nan")
    return out


@dataclasses.dataclass(frozen=True)
class CVResult:
    """Per-fold metrics, pooled metrics and the held-out predictions (row order of ``folds``)."""

    folds: list[dict[str, Any]]
    overall: dict[str, float]
    predictions: dict[str, np.ndarray]
    models: list[AbstractPredictor] = dataclasses.field(default_factory=list)

    def to_json(self) -> dict[str, Any]:
        return {"folds": self.folds, "overall": self.overall}


def cross_validate(
    spec: ForceModelSpec,
    folds,
    *,
    seed: int = 0,
    progress: bool = True,
    inner_progress: bool = False,
    keep_models: bool = False,
) -> CVResult:
    """Fit ``spec`` on each fold's training Measurements and score its test Measurements.

    ``folds``: ``[(train, test), ...]`` as made by ``Measurements.kfold`` or
    ``leave_one_out``. Training uses the table's ``weight`` column. Seeds: fold i fits
    with ``key = seed + i``. ``keep_models`` keeps the fitted models in ``CVResult.models``.
    """
    folds = list(folds)
    if not folds:
        raise ValueError("cross_validate needs at least one (train, test) fold")
    rows, models, keep = [], [], {k: [] for k in ("force", "mean", "std", "total_sd", "fold", "design", "h", "p")}
    for i, (train, test) in enumerate(tqdm(folds, desc="cv folds", disable=not progress)):
        overlap = set(train.design_keys) & set(test.design_keys)
        if overlap:
            raise ValueError(f"fold {i}: membranes in both train and test: {sorted(overlap)}")
        a, b = train.arrays(), test.arrays()
        model = spec.fit(
            a["design"],
            a["height_mm"],
            a["pressure_pa"],
            a["force_n"],
            a["weight"],
            key=seed + i,
            progress=inner_progress,
        )
        mu_tr, _ = predict_mean_std(model, a["design"], a["height_mm"], a["pressure_pa"])
        noise = float(np.sqrt(np.average((a["force_n"] - mu_tr) ** 2, weights=a["weight"])))
        mu, sd = predict_mean_std(model, b["design"], b["height_mm"], b["pressure_pa"])
        m = metrics(b["force_n"], mu, sd, noise)
        m.update(
            fold=i,
            test_membranes=list(test.design_keys),
            train_rmse_n=float(np.sqrt(np.mean((a["force_n"] - mu_tr) ** 2))),
            noise_sd_n=noise,
        )
        rows.append(m)
        if keep_models:
            models.append(model)
        for k, v in (
            ("force", b["force_n"]),
            ("mean", mu),
            ("std", sd),
            ("fold", np.full(len(mu), i)),
            ("total_sd", np.sqrt(sd**2 + noise**2)),
            ("design", b["design"]),
            ("h", b["height_mm"]),
            ("p", b["pressure_pa"]),
        ):
            keep[k].append(v)
    pred = {k: np.concatenate(v) for k, v in keep.items()}
    overall = metrics(pred["force"], pred["mean"], pred["std"])
    for q, z in Z.items():
        overall[f"coverage{int(round(q * 100))}_total"] = float(
            np.mean(np.abs(pred["force"] - pred["mean"]) <= z * pred["total_sd"])
        )
    overall["fold_rmse_mean_n"] = float(np.mean([r["rmse_n"] for r in rows]))
    return CVResult(rows, overall, pred, models)
