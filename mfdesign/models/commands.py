"""Plain functions behind ``mfdesign fit`` and ``mfdesign cv`` (registered in ``mfdesign.cli``).

``DATA`` is a Measurements Parquet file, or ``mass-lift`` for the authors' real mass-lift
data. Both print one line per result and write JSON; errors in inputs raise ``ValueError``
with a message fit for the terminal.
"""

from __future__ import annotations

import json
from pathlib import Path

from mfdesign.models.baselines import CurveFitConfig
from mfdesign.models.cv import cross_validate
from mfdesign.models.ensemble import EnsembleConfig

MODELS = ("ensemble", "curve-fit")


def load_data(data: Path):
    """A Measurements table from a Parquet path or the name ``mass-lift``."""
    if str(data) == "mass-lift":
        from mfdesign.data.spa_design import load_mass_lift

        return load_mass_lift()
    from mfdesign.data.measurements import Measurements

    path = Path(data)
    if not path.exists():
        raise ValueError(f"data file {path} does not exist (give a Measurements .parquet or 'mass-lift')")
    return Measurements.from_parquet(path)


def make_spec(model: str, members: int, steps: int, batch: int, degree: int, monotone: bool):
    if model == "ensemble":
        return EnsembleConfig(n_members=members, steps=steps, batch=batch, degree=degree, monotone=monotone)
    if model == "curve-fit":
        return CurveFitConfig(degree=degree)
    raise ValueError(f"model must be one of {MODELS}, got {model!r}")


def fit(data: Path, out: Path, members: int = 32, steps: int = 10_000, batch: int = 100,
        degree: int = 2, monotone: bool = True, seed: int = 0) -> Path:
    """Fit an RPN ensemble to all of ``data`` and save it to ``out`` (``Ensemble.load``-able)."""
    table = load_data(data)
    a = table.arrays()
    cfg = make_spec("ensemble", members, steps, batch, degree, monotone)
    model = cfg.fit(a["design"], a["height_mm"], a["pressure_pa"], a["force_n"], a["weight"],
                    key=seed, progress=True)
    model.save(out)
    mu, _ = model.mean_std(a["design"], a["height_mm"], a["pressure_pa"])
    rmse = float(((mu - a["force_n"]) ** 2).mean() ** 0.5)
    print(f"fitted {members} members on {len(table)} rows of {len(table.design_keys)} membranes; "
          f"training RMSE {rmse:.3f} N; saved to {out}")
    return Path(out)


def cv(data: Path, model: str = "ensemble", folds: int = 0, members: int = 32, steps: int = 10_000,
       batch: int = 100, degree: int = 2, monotone: bool = True, seed: int = 0,
       out: Path | None = None) -> dict:
    """Leave-membranes-out CV (``folds`` = 0: leave-one-membrane-out); prints and returns metrics."""
    table = load_data(data)
    splits = table.leave_one_out() if folds == 0 else table.kfold(folds, seed=seed)
    spec = make_spec(model, members, steps, batch, degree, monotone)
    result = cross_validate(spec, splits, seed=seed, progress=True)
    for f in result.folds:
        print(f"fold {f['fold']}: RMSE {f['rmse_n']:.3f} N  median |e| {f['median_abs_n']:.3f} N  "
              f"cov68 {f['coverage68_total']:.2f}  cov95 {f['coverage95_total']:.2f}  {f['test_membranes']}")
    o = result.overall
    print(f"overall: RMSE {o['rmse_n']:.3f} N (fold mean {o['fold_rmse_mean_n']:.3f})  median |e| "
          f"{o['median_abs_n']:.3f} N  coverage 68/95 %: {o['coverage68_total']:.2f}/{o['coverage95_total']:.2f}"
          f" (epistemic only {o['coverage68_epistemic']:.2f}/{o['coverage95_epistemic']:.2f})")
    if out is not None:
        Path(out).parent.mkdir(parents=True, exist_ok=True)
        Path(out).write_text(json.dumps({"model": model, **result.to_json()}, indent=2))
    return result.to_json()
