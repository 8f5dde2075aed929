"""How every command reads its ``DATA``, and the ``fit``, ``cv`` and ``import`` workflows.

``DATA`` is one or more sources (:func:`load_data`): Measurements Parquet / CSV files,
``mass-lift`` for the authors' real mass-lift data, SPA_Design pickles, rig job folders.
Errors in inputs raise :class:`~mfdesign.errors.InputError` (a ``ValueError``) with a
message fit for the terminal. Units: mm, Pa, N.
"""

from __future__ import annotations

import sys
from dataclasses import dataclass
from pathlib import Path
from typing import TYPE_CHECKING, Any

from mfdesign.errors import InputError

if TYPE_CHECKING:
    from mfdesign.models.baselines import CurveFitConfig
    from mfdesign.models.ensemble import EnsembleConfig

__all__ = [
    "CVResult",
    "FitResult",
    "ImportResult",
    "MIN_ROWS",
    "MODELS",
    "check_table",
    "cv",
    "fit",
    "import_measurements",
    "load_data",
    "make_spec",
]

MODELS = ("ensemble", "curve-fit")


# Fewest rows each command accepts (rows it actually uses: calibration and diagnosis drop
# mass-lift rows with the plate on its stop). Why these: fit/cv train on 100-row minibatches
# and need a handful of rows per membrane to mean anything; calibration and diagnosis
# estimate a noise floor and 2-10 parameters, and below ~20 rows the noise floor is NaN or
# the posterior is the prior.
MIN_ROWS = {"fit": 10, "cv": 10, "calibrate": 20, "fit-mf": 20, "diagnose": 20}
# A table whose rows are mostly exact copies of earlier ones is a concatenation mistake: it
# counts its evidence twice (doubling Delta BIC). The real mass-lift data has 8 % (whole-mm
# heights repeat), so the bar is well above that.
MAX_DUPLICATE_FRACTION = 0.5


def load_data(data: Any, command: str | None = None, allow_outside_design_space: bool = False) -> Any:
    """A Measurements table from the ``DATA`` argument of a command: one source or several
    (a Measurements Parquet or CSV file, ``mass-lift``, an SPA_Design pickle, a rig job
    folder; :func:`mfdesign.data.sources.load_sources`), concatenated with trial ids made
    unique per membrane.

    Arguments:
        data: one source (a path, or a keyword such as ``mass-lift``) or a list of them.
        command: a key of :data:`MIN_ROWS`: the table is also checked for what that command
            needs (:func:`check_table`); None: no check.
        allow_outside_design_space: accept membranes outside the product's design space (a
            warning on stderr names them).

    Errors are ``InputError`` / ``MeasurementError`` with one line saying what is allowed."""
    from mfdesign.data.sources import load_sources

    items = [data] if isinstance(data, (str, Path)) else list(data)
    table = load_sources(items)
    if command is not None:
        check_table(table, command, ", ".join(map(str, items)), allow_outside_design_space)
    return table


def check_table(table: Any, command: str, where: str, allow_outside_design_space: bool = False) -> None:
    """Refuse a table ``command`` would turn into a silently wrong result: too few rows,
    all weights 0, mostly duplicated rows, designs outside the product's design space.

    Arguments:
        table: the Measurements (heights in mm, pressures in Pa, forces in N).
        command: a key of :data:`MIN_ROWS` (the rows it needs; calibration and diagnosis
            count only lifted rows).
        where: what the table was read from (starts the message).
        allow_outside_design_space: warn about (instead of refusing) membranes outside
            the product's design space."""

    from mfdesign.design import check_design_space

    used = table
    if command in ("calibrate", "fit-mf", "diagnose"):
        from mfdesign.calibration.workflow import lifted_rows

        used = lifted_rows(table)
    need = MIN_ROWS[command]
    if len(used) < need:
        dropped = f" ({len(table) - len(used)} mass-lift rows below 2 mm dropped)" if len(used) < len(table) else ""
        raise InputError(
            f"{where}: {len(used)} usable rows{dropped}; allowed: at least {need} rows for `mfdesign {command}`"
        )
    weight = used.df["weight"].to_numpy(float)
    if not weight.sum() > 0:
        raise InputError(f"{where}: all {len(weight)} sample weights are 0; allowed: weights >= 0 with a positive sum")
    dup = int(used.df.duplicated().sum())
    if dup >= MAX_DUPLICATE_FRACTION * len(used):
        raise InputError(
            f"{where}: {dup} of {len(used)} rows ({dup / len(used):.0%}) repeat an earlier row exactly; "
            f"allowed: under {MAX_DUPLICATE_FRACTION:.0%} (a copied table counts its evidence twice)"
        )
    outside = [
        d.key() for d in table.designs() if check_design_space(d, allow_outside_design_space, what=f"{where}: membrane")
    ]
    if outside:
        print(
            f"warning: design space widened ({len(outside)} membrane(s) outside the product's: "
            f"{', '.join(outside[:3])}{' ...' if len(outside) > 3 else ''})",
            file=sys.stderr,
        )


def make_spec(model: str, members: int, steps: int, batch: int, degree: int, monotone: bool) -> Any:
    """The training settings of a model type: an ``EnsembleConfig`` or a ``CurveFitConfig``.

    Arguments:
        model: ``ensemble`` (the paper's RPN ensemble) or ``curve-fit`` (the baseline).
        members: ensemble members.
        steps: training steps (Adam) of every member.
        batch: minibatch rows.
        degree: degree of the head polynomial in pressure (1-3).
        monotone: force the prediction non-decreasing in pressure.

    Raises :class:`~mfdesign.errors.InputError` for an unknown model type."""
    from mfdesign.models.baselines import CurveFitConfig
    from mfdesign.models.ensemble import EnsembleConfig

    if model == "ensemble":
        return EnsembleConfig(n_members=members, steps=steps, batch=batch, degree=degree, monotone=monotone)
    if model == "curve-fit":
        return CurveFitConfig(degree=degree)
    raise InputError(f"model must be one of {MODELS}, got {model!r}")


@dataclass(frozen=True)
class FitResult:
    """A fitted ensemble: where it was saved, its size and its training RMSE [N]."""

    out: Path
    members: int
    rows: int
    membranes: int
    rmse_n: float

    def summary(self) -> str:
        return (
            f"fitted {self.members} members on {self.rows} rows of {self.membranes} membranes; "
            f"training RMSE {self.rmse_n:.3f} N; saved to {self.out}"
        )


def fit(
    data: Any, out: Path, spec: "EnsembleConfig", seed: int = 0, allow_outside_design_space: bool = False
) -> FitResult:
    """Fit an RPN ensemble to all of ``data`` and save it to ``out`` (``Ensemble.load``-able).

    Arguments:
        data: the ``DATA`` sources (:func:`load_data`).
        out: folder for the fitted model.
        spec: the training settings, an ``EnsembleConfig`` (:func:`make_spec`).
        seed: random seed of the members.
        allow_outside_design_space: accept membranes outside the product's design space.

    Raises :class:`~mfdesign.errors.InputError` for bad data."""
    try:
        table = load_data(data, "fit", allow_outside_design_space)
        a = table.arrays()
        model = spec.fit(
            a["design"], a["height_mm"], a["pressure_pa"], a["force_n"], a["weight"], key=seed, progress=True
        ).ensemble
        model.save(out)
    except ValueError as err:
        raise InputError(str(err)) from None
    mu, _ = model.mean_std(a["design"], a["height_mm"], a["pressure_pa"])
    rmse = float(((mu - a["force_n"]) ** 2).mean() ** 0.5)
    return FitResult(Path(out), spec.n_members, len(table), len(table.design_keys), rmse)


@dataclass(frozen=True)
class CVResult:
    """Leave-membranes-out cross-validation: the metrics (``to_json`` of
    :class:`mfdesign.models.cv.CVResult`: per fold and overall; RMSE and errors in N) and
    the file they were written to, if any."""

    metrics: dict
    out: Path | None = None

    def summary(self) -> str:
        """One line per fold, then the overall line."""
        lines = [
            f"fold {f['fold']}: RMSE {f['rmse_n']:.3f} N  median |e| {f['median_abs_n']:.3f} N  "
            f"cov68 {f['coverage68_total']:.2f}  cov95 {f['coverage95_total']:.2f}  {f['test_membranes']}"
            for f in self.metrics["folds"]
        ]
        o = self.metrics["overall"]
        lines.append(
            f"overall: RMSE {o['rmse_n']:.3f} N (fold mean {o['fold_rmse_mean_n']:.3f})  median |e| "
            f"{o['median_abs_n']:.3f} N  coverage 68/95 %: {o['coverage68_total']:.2f}/{o['coverage95_total']:.2f}"
            f" (epistemic only {o['coverage68_epistemic']:.2f}/{o['coverage95_epistemic']:.2f})"
        )
        return "\n".join(lines)


def cv(
    data: Any,
    model: str,
    spec: "EnsembleConfig | CurveFitConfig",
    folds: int = 0,
    seed: int = 0,
    out: Path | None = None,
    allow_outside_design_space: bool = False,
) -> CVResult:
    """Leave-membranes-out cross-validation of ``spec``; writes the metrics as JSON to ``out``.

    Arguments:
        data: the ``DATA`` sources (:func:`load_data`).
        model: the model type of ``spec`` (``ensemble`` | ``curve-fit``), recorded in the JSON.
        spec: the training settings (:func:`make_spec`).
        folds: k of k-fold by membrane; 0: leave one membrane out.
        seed: random seed of the folds and of the training.
        out: JSON file for the metrics (None: not written).
        allow_outside_design_space: accept membranes outside the product's design space.

    Raises :class:`~mfdesign.errors.InputError` for bad data."""
    from mfdesign.models.cv import cross_validate

    try:
        table = load_data(data, "cv", allow_outside_design_space)
        splits = table.leave_one_out() if folds == 0 else table.kfold(folds, seed=seed)
        result = cross_validate(spec, splits, seed=seed, progress=True)
    except ValueError as err:
        raise InputError(str(err)) from None
    metrics = result.to_json()
    if out is not None:
        from mfdesign import outputs

        Path(out).parent.mkdir(parents=True, exist_ok=True)
        from mfdesign.provenance import call_line, input_hashes, provenance

        inputs = input_hashes(data if isinstance(data, (list, tuple)) else [data])
        record = provenance(call_line("mfdesign.workflows.data.cv()"), {"seed": seed}, inputs)
        outputs.write_json(out, {"model": model, **metrics, "provenance": record})
    return CVResult(metrics, None if out is None else Path(out))


@dataclass(frozen=True)
class ImportResult:
    """An imported Measurements file: its rows, membranes and trials by experiment."""

    out: Path
    rows: int
    membranes: int
    trials: dict

    def summary(self) -> str:
        return f"{self.rows} rows, {self.membranes} membranes, trials {self.trials} -> {self.out}"


def import_measurements(sources: Any, out: Path, fmt: str = "auto", columns: str | None = None) -> ImportResult:
    """Convert measurements into one Measurements Parquet file (schema: docs/data.md).

    Arguments:
        sources: files or rig job folders to read, or ``mass-lift`` (several: concatenated).
        out: the Parquet file to write.
        fmt: ``auto`` (from the name and content) | ``parquet`` | ``csv`` | ``mass-lift`` |
            ``characterisation`` | ``sim-planes`` | ``rig-job``.
        columns: column map ``TARGET=SOURCE[:UNIT],...`` for a table of your own layout
            (:func:`mfdesign.data.sources.load_sources`).

    Raises :class:`~mfdesign.errors.InputError` for an unreadable or ill-formed source."""
    from mfdesign.data.sources import load_sources

    table = load_sources(sources, fmt, columns)
    table.to_parquet(out)
    df = table.df
    trials = df.groupby(["design_key", "trial"]).first()["experiment"].value_counts().to_dict()
    return ImportResult(Path(out), len(table), len(table.design_keys), trials)
