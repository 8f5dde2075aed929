"""``mfdesign fit``, ``cv`` and ``import``: the workflows are in :mod:`mfdesign.workflows.data`
(which also reads every command's ``DATA``: :func:`mfdesign.workflows.data.load_data`).

``DATA`` is one or more sources: Measurements Parquet / CSV files, ``mass-lift`` for the
authors' real mass-lift data, SPA_Design pickles, rig job folders. Each command prints one
line per result and writes JSON or Parquet.
"""

from __future__ import annotations

import shlex
import sys
from pathlib import Path
from typing import List, Optional

import typer

from mfdesign.cli._app import ALLOW_OUTSIDE, SCHEDULER, fail, show

DATA = typer.Argument(
    ...,
    help="Measurements .parquet/.csv file(s), SPA_Design .pkl, rig job folder(s), or 'mass-lift' (several: concatenated; docs/data.md).",
)


def fit_command(
    data: List[Path] = DATA,
    out: Optional[Path] = typer.Option(None, help="Folder for the fitted model (not with a campaign folder)."),
    members: int = typer.Option(32, min=1, help="Ensemble members."),
    steps: int = typer.Option(10_000, "--train-steps", min=1, help="Training steps (Adam) of every member."),
    batch: int = typer.Option(100, min=1, help="Minibatch size."),
    degree: int = typer.Option(2, min=1, max=3, help="Degree of the head polynomial in pressure."),
    monotone: bool = typer.Option(True, help="Force non-decreasing in pressure."),
    seed: int = typer.Option(0, help="Random seed."),
    allow_outside_design_space: bool = ALLOW_OUTSIDE,
    scheduler: Optional[str] = SCHEDULER,
) -> None:
    """Fit the paper's RPN ensemble to measurements and save it; or, DATA a campaign's folder, its next round."""
    from mfdesign.campaign import Campaign

    if len(data) == 1 and Campaign.holds_campaign(data[0]):  # the campaign's settings rule its fit
        if out is not None:
            fail(f"{data[0]} is a campaign: its rounds go into it; allowed: no --out")
        typer.echo(Campaign.open(data[0]).fit(progress=True, call=shlex.join(["mfdesign", *sys.argv[1:]])).summary())
        return
    if out is None:
        fail("--out is needed (the folder for the fitted model) unless DATA is one campaign folder")
    from mfdesign.workflows import data as workflow

    spec = workflow.make_spec("ensemble", members, steps, batch, degree, monotone)
    show(workflow.fit(data, out, spec, seed, allow_outside_design_space))


def cv_command(
    data: List[Path] = DATA,
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
    from mfdesign.workflows import data as workflow

    spec = workflow.make_spec(model, members, steps, batch, degree, monotone)
    show(workflow.cv(data, model, spec, folds, seed, out, allow_outside_design_space))


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
    from mfdesign.workflows.data import import_measurements

    show(import_measurements(sources, out, fmt, columns))


def register(app: typer.Typer) -> None:
    app.command("fit")(fit_command)
    app.command("cv")(cv_command)
    app.command("import")(import_)
