"""``mfdesign fit``, ``cv`` and ``import``, and how every command reads its ``DATA``.

``DATA`` is one or more sources (:func:`load_data`): Measurements Parquet / CSV files,
``mass-lift`` for the authors' real mass-lift data, SPA_Design pickles, rig job folders. Both print one line per result and write JSON; errors in inputs raise ``ValueError``
with a message fit for the terminal.
"""

from __future__ import annotations

from pathlib import Path
import shlex
import sys
from typing import TYPE_CHECKING, List, Optional

import typer

from mfdesign.cli._app import ALLOW_OUTSIDE, fail

if TYPE_CHECKING:
    from mfdesign.models.baselines import CurveFitConfig
    from mfdesign.models.ensemble import EnsembleConfig

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


def load_data(data, command: str | None = None, allow_outside_design_space: bool = False):
    """A Measurements table from the ``DATA`` argument of a command: one source or several
    (a Measurements Parquet or CSV file, ``mass-lift``, an SPA_Design pickle, a rig job
    folder; :func:`mfdesign.data.sources.load_sources`), concatenated with trial ids made
    unique per membrane.

    With ``command`` (a key of :data:`MIN_ROWS`) the table is also checked for what that
    command needs (:func:`check_table`); errors are ``InputError`` / ``MeasurementError``
    with one line saying what is allowed."""
    from mfdesign.data.sources import load_sources

    items = [data] if isinstance(data, (str, Path)) else list(data)
    table = load_sources(items)
    if command is not None:
        check_table(table, command, ", ".join(map(str, items)), allow_outside_design_space)
    return table


def check_table(table, command: str, where: str, allow_outside_design_space: bool = False) -> None:
    """Refuse a table ``command`` would turn into a silently wrong result: too few rows,
    all weights 0, mostly duplicated rows, designs outside the product's design space."""
    import sys

    from mfdesign.design import check_design_space
    from mfdesign.errors import InputError

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


def make_spec(model: str, members: int, steps: int, batch: int, degree: int, monotone: bool):
    from mfdesign.models.baselines import CurveFitConfig
    from mfdesign.models.ensemble import EnsembleConfig

    if model == "ensemble":
        return EnsembleConfig(n_members=members, steps=steps, batch=batch, degree=degree, monotone=monotone)
    if model == "curve-fit":
        return CurveFitConfig(degree=degree)
    raise ValueError(f"model must be one of {MODELS}, got {model!r}")


def fit(data: Path, out: Path, spec: "EnsembleConfig", seed: int = 0, allow_outside_design_space: bool = False) -> Path:
    """Fit an RPN ensemble (``spec``: an ``EnsembleConfig``, :func:`make_spec`) to all of
    ``data`` and save it to ``out`` (``Ensemble.load``-able)."""
    table = load_data(data, "fit", allow_outside_design_space)
    a = table.arrays()
    model = spec.fit(
        a["design"], a["height_mm"], a["pressure_pa"], a["force_n"], a["weight"], key=seed, progress=True
    ).ensemble
    model.save(out)
    mu, _ = model.mean_std(a["design"], a["height_mm"], a["pressure_pa"])
    rmse = float(((mu - a["force_n"]) ** 2).mean() ** 0.5)
    print(
        f"fitted {spec.n_members} members on {len(table)} rows of {len(table.design_keys)} membranes; "
        f"training RMSE {rmse:.3f} N; saved to {out}"
    )
    return Path(out)


def cv(
    data: Path,
    model: str,
    spec: "EnsembleConfig | CurveFitConfig",
    folds: int = 0,
    seed: int = 0,
    out: Path | None = None,
    allow_outside_design_space: bool = False,
) -> dict:
    """Leave-membranes-out CV of ``spec`` (:func:`make_spec` of the model type ``model``;
    ``folds`` = 0: leave-one-membrane-out); prints and returns metrics."""
    from mfdesign.models.cv import cross_validate

    table = load_data(data, "cv", allow_outside_design_space)
    splits = table.leave_one_out() if folds == 0 else table.kfold(folds, seed=seed)
    result = cross_validate(spec, splits, seed=seed, progress=True)
    for f in result.folds:
        print(
            f"fold {f['fold']}: RMSE {f['rmse_n']:.3f} N  median |e| {f['median_abs_n']:.3f} N  "
            f"cov68 {f['coverage68_total']:.2f}  cov95 {f['coverage95_total']:.2f}  {f['test_membranes']}"
        )
    o = result.overall
    print(
        f"overall: RMSE {o['rmse_n']:.3f} N (fold mean {o['fold_rmse_mean_n']:.3f})  median |e| "
        f"{o['median_abs_n']:.3f} N  coverage 68/95 %: {o['coverage68_total']:.2f}/{o['coverage95_total']:.2f}"
        f" (epistemic only {o['coverage68_epistemic']:.2f}/{o['coverage95_epistemic']:.2f})"
    )
    if out is not None:
        from mfdesign import outputs

        Path(out).parent.mkdir(parents=True, exist_ok=True)
        outputs.write_json(out, {"model": model, **result.to_json()})
    return result.to_json()


def register(app: typer.Typer) -> None:
    @app.command("fit")
    def fit_command(
        data: List[Path] = typer.Argument(
            ...,
            help="Measurements .parquet/.csv file(s), SPA_Design .pkl, rig job folder(s), or 'mass-lift' (several: concatenated; docs/data.md).",
        ),
        out: Optional[Path] = typer.Option(None, help="Folder for the fitted model (not with a campaign folder)."),
        members: int = typer.Option(32, min=1, help="Ensemble members."),
        steps: int = typer.Option(10_000, "--train-steps", min=1, help="Training steps (Adam) of every member."),
        batch: int = typer.Option(100, min=1, help="Minibatch size."),
        degree: int = typer.Option(2, min=1, max=3, help="Degree of the head polynomial in pressure."),
        monotone: bool = typer.Option(True, help="Force non-decreasing in pressure."),
        seed: int = typer.Option(0, help="Random seed."),
        allow_outside_design_space: bool = ALLOW_OUTSIDE,
    ) -> None:
        """Fit the paper's RPN ensemble to measurements and save it; or, DATA a campaign's folder, its next round."""
        from mfdesign.campaign import Campaign

        if len(data) == 1 and Campaign.holds_campaign(data[0]):  # the campaign's settings rule its fit
            if out is not None:
                fail(f"{data[0]} is a campaign: its rounds go into it; allowed: no --out")
            typer.echo(
                Campaign.open(data[0]).fit(progress=True, call=shlex.join(["mfdesign", *sys.argv[1:]])).summary()
            )
            return
        if out is None:
            fail("--out is needed (the folder for the fitted model) unless DATA is one campaign folder")
        try:
            spec = make_spec("ensemble", members, steps, batch, degree, monotone)
            fit(data, out, spec, seed, allow_outside_design_space)
        except ValueError as err:
            fail(str(err))

    @app.command("cv")
    def cv_command(
        data: List[Path] = typer.Argument(
            ...,
            help="Measurements .parquet/.csv file(s), SPA_Design .pkl, rig job folder(s), or 'mass-lift' (several: concatenated; docs/data.md).",
        ),
        model: str = typer.Option("ensemble", "--model-type", help="Model type: ensemble | curve-fit."),
        folds: int = typer.Option(0, min=0, help="k of k-fold by membrane; 0 = leave one membrane out."),
        members: int = typer.Option(32, min=1),
        steps: int = typer.Option(10_000, "--train-steps", min=1, help="Training steps (Adam) of every member."),
        batch: int = typer.Option(100, min=1),
        degree: int = typer.Option(2, min=1, max=3),
        monotone: bool = typer.Option(True),
        seed: int = typer.Option(0),
        out: Path = typer.Option(None, help="Write the metrics as JSON here."),
        allow_outside_design_space: bool = ALLOW_OUTSIDE,
    ) -> None:
        """Leave-membranes-out cross-validation: RMSE [N], median error, interval coverage."""
        try:
            spec = make_spec(model, members, steps, batch, degree, monotone)
            cv(data, model, spec, folds, seed, out, allow_outside_design_space)
        except ValueError as err:
            fail(str(err))

    @app.command("import")
    def import_(
        sources: List[Path] = typer.Argument(
            ..., help="Files or rig job folders to read, or 'mass-lift' (several: concatenated)."
        ),
        out: Path = typer.Option(..., help="Measurements Parquet file to write."),
        fmt: str = typer.Option(
            "auto",
            "--format",
            help="auto (from the name and content) | parquet | csv | mass-lift | characterisation | sim-planes | rig-job.",
        ),
        columns: Optional[str] = typer.Option(
            None,
            "--columns",
            help="Column map for a CSV / Parquet table of your own layout: TARGET=SOURCE[:UNIT],... e.g. "
            "'design_key=design,pressure_pa=pressure_kpa:kPa'. Units: mm cm m in | Pa kPa mbar bar psi | "
            "N mN g kg lbf | s ms min. Missing optional columns take defaults (docs/data.md).",
        ),
    ) -> None:
        """Convert measurements into one Measurements Parquet file (schema: docs/data.md).

        Reads Measurements Parquet / CSV, the SPA_Design pickles (mass-lift and characterisation
        data dictionaries, through the restricted unpickler) and rig job folders.
        """
        from mfdesign.data.sources import load_sources

        table = load_sources(sources, fmt, columns)
        table.to_parquet(out)
        df = table.df
        trials = df.groupby(["design_key", "trial"]).first()["experiment"].value_counts().to_dict()
        typer.echo(f"{len(table)} rows, {len(table.design_keys)} membranes, trials {trials} -> {out}")
