"""``mfdesign`` command line (typer). Units: mm, Pa, N.

Bad input (a design that cannot be built, a file that is not what it should be) prints
one line saying what was wrong and what is allowed, and exits with status 2; an unexpected
error prints one line naming a log file with the traceback and exits with status 1
(:mod:`mfdesign.cli_contract`).
"""

from __future__ import annotations

import json
import os
from pathlib import Path
from typing import List

import typer

from mfdesign.cli_contract import ContractGroup

# ContractGroup turns whatever escapes a command into the one-line contract (module doc).
app = typer.Typer(
    help="Multi-fidelity Bayesian design of soft pneumatic actuators.",
    no_args_is_help=True,
    add_completion=False,
    cls=ContractGroup,
)


def enable_compilation_cache() -> Path:
    """JAX's persistent compilation cache, so a second CLI call does not recompile.

    Folder: ``$MFDESIGN_CACHE_DIR`` (default ``~/.cache/mfdesign/jax``). Programs that
    compile in under 1 s are not stored (recompiling them is as fast as reading them).

    Why ``EQX_ON_ERROR=nan`` (unless already set): equinox's runtime checks inside the
    solvers (``eqx.error_if``, used by optimistix / diffrax / lineax even with
    ``throw=False``) are host callbacks by default, and XLA never stores an executable that
    holds a host callback: the cache stayed empty after any number of ``simulate`` runs.
    With ``nan`` such a check turns its outputs into NaN, which the physics already reports
    as a failed point (every solve here runs with ``throw=False``). It must be set before
    equinox is imported, i.e. here, before any command body runs.
    """
    os.environ.setdefault("EQX_ON_ERROR", "nan")
    import jax

    cache = Path(os.environ.get("MFDESIGN_CACHE_DIR", Path.home() / ".cache" / "mfdesign" / "jax"))
    cache.mkdir(parents=True, exist_ok=True)
    jax.config.update("jax_compilation_cache_dir", str(cache))
    jax.config.update("jax_persistent_cache_min_compile_time_secs", 1.0)
    jax.config.update("jax_persistent_cache_min_entry_size_bytes", 0)
    return cache


# Declared once; the data commands and simulate take it.
ALLOW_OUTSIDE = typer.Option(False, "--allow-outside-design-space",
                             help="Research: accept designs outside the product's space (thickness 1-3 mm, ...) "
                                  "up to a wider physical range; the output says so.")


def fail(message: str) -> None:
    """Print one line to stderr and exit with status 2."""
    typer.echo(f"error: {message}", err=True)
    raise typer.Exit(code=2)


def _print_version(value: bool) -> None:
    if value:
        from mfdesign import __version__

        typer.echo(f"mfdesign {__version__}")
        raise typer.Exit()


@app.callback()
def _main(
    version: bool = typer.Option(False, "--version", callback=_print_version, is_eager=True,
                                 help="Print the version and exit."),
) -> None:
    enable_compilation_cache()


@app.command()
def simulate(
    design: str = typer.Option(
        "[2.0, 25.4, nan, nan, nan, nan]",
        help='Design key "[t, c, r1, w1, r2, w2]" in mm (nan = no ring).',
    ),
    out: Path = typer.Option(Path("out/simulate"), help="Output folder."),
    h_max_mm: float = typer.Option(70.0, help="Largest plate height [mm]."),
    p_max_pa: float = typer.Option(10_000.0, help="Largest pressure [Pa]."),
    n_heights: int = typer.Option(50, min=2, max=400, help="Heights in the grid."),
    n_pressures: int = typer.Option(50, min=2, max=2000, help="Pressures in the grid."),
    mu_pa: float = typer.Option(31.7e3, help="Gent shear modulus of the rubber [Pa]."),
    jm: float = typer.Option(39.6, help="Gent locking parameter J_m of the rubber."),
    allow_outside_design_space: bool = ALLOW_OUTSIDE,
) -> None:
    """Simulate one membrane on a height x pressure grid: Parquet plane + PNG + JSON."""
    from mfdesign.design import DesignError, Membrane, check_design_space
    from mfdesign.physics.params import SimParams
    from mfdesign.simulate_plane import simulate_plane, write_plane

    try:
        membrane = Membrane.from_key(design)
        widened = check_design_space(membrane, allow_outside_design_space)
    except DesignError as err:
        fail(f"bad design {design!r}: {err}")
    for name, value, lo in (("h-max-mm", h_max_mm, 0.0), ("p-max-pa", p_max_pa, 0.0), ("mu-pa", mu_pa, 0.0), ("jm", jm, 0.0)):
        if not (value > lo and value < float("inf")):
            fail(f"--{name} must be a positive finite number, got {value}")
    params = SimParams(mu_pa=mu_pa, jm=jm)
    table = simulate_plane(membrane, h_max_mm, p_max_pa, n_heights, n_pressures, params, progress=True)
    note = {"design_space": "widened (--allow-outside-design-space): outside the product's membranes"} if widened else {}
    paths = write_plane(table, membrane, out, extra=note)
    if widened:
        typer.echo(f"warning: {membrane.key()} is outside the product's design space (widened on request)", err=True)
    typer.echo(json.dumps({k: str(v) for k, v in paths.items()}))


@app.command()
def demo(
    out: Path = typer.Option(Path("out/demo"), help="Output folder (report: OUT/index.html)."),
    quick: bool = typer.Option(False, help="Shrink every stage (a smoke test of the whole loop)."),
    physics: str = typer.Option("exact", help="Where the model meets the data: exact (simulator planes) | emulator | standin (tests)."),
    seed: int = typer.Option(0, help="Random seed."),
) -> None:
    """The main job on the embedded default (no hardware, no external data).

    On the bundled virtual-rig dataset: calibrate mu and J_m (emcee), fit the multi-fidelity
    model, diagnose it and find the hidden effect, add it and refit, propose the next two
    membranes with their fidelities, optimise a membrane for a lift task, and write one
    HTML report (OUT/index.html) with JSON beside it.
    """
    import dataclasses

    from mfdesign.demo import DemoSettings, run_demo

    if physics not in ("exact", "emulator", "standin"):
        fail(f"--physics must be one of ['exact', 'emulator', 'standin'], got {physics!r}")
    settings = DemoSettings.quick(physics) if quick else DemoSettings(
        force_model=physics, search_model="standin" if physics == "standin" else "emulator")
    settings = dataclasses.replace(settings, seed=seed)
    try:
        run_demo(out, settings, echo=typer.echo)
    except (ValueError, FileNotFoundError) as err:
        fail(str(err))


@app.command()
def fit(
    data: List[Path] = typer.Argument(..., help="Measurements .parquet/.csv file(s), SPA_Design .pkl, rig job folder(s), or 'mass-lift' (several: concatenated; docs/data.md)."),
    out: Path = typer.Option(..., help="Folder for the fitted model."),
    members: int = typer.Option(32, min=1, help="Ensemble members."),
    steps: int = typer.Option(10_000, "--train-steps", min=1, help="Training steps (Adam) of every member."),
    batch: int = typer.Option(100, min=1, help="Minibatch size."),
    degree: int = typer.Option(2, min=1, max=3, help="Degree of the head polynomial in pressure."),
    monotone: bool = typer.Option(True, help="Force non-decreasing in pressure."),
    seed: int = typer.Option(0, help="Random seed."),
    allow_outside_design_space: bool = ALLOW_OUTSIDE,
) -> None:
    """Fit the paper's RPN ensemble to measurements and save it."""
    from mfdesign.models import commands

    try:
        commands.fit(data, out, members, steps, batch, degree, monotone, seed, allow_outside_design_space)
    except ValueError as err:
        fail(str(err))


@app.command()
def cv(
    data: List[Path] = typer.Argument(..., help="Measurements .parquet/.csv file(s), SPA_Design .pkl, rig job folder(s), or 'mass-lift' (several: concatenated; docs/data.md)."),
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
    from mfdesign.models import commands

    try:
        commands.cv(data, model, folds, members, steps, batch, degree, monotone, seed, out, allow_outside_design_space)
    except ValueError as err:
        fail(str(err))


@app.command("import")
def import_(
    sources: List[Path] = typer.Argument(..., help="Files or rig job folders to read, or 'mass-lift' (several: concatenated)."),
    out: Path = typer.Option(..., help="Measurements Parquet file to write."),
    fmt: str = typer.Option("auto", "--format",
                            help="auto (from the name and content) | parquet | csv | mass-lift | characterisation | sim-planes | rig-job."),
) -> None:
    """Convert measurements into one Measurements Parquet file (schema: docs/data.md).

    Reads Measurements Parquet / CSV, the SPA_Design pickles (mass-lift and characterisation
    data dictionaries, through the restricted unpickler) and rig job folders.
    """
    from mfdesign.data.sources import load_sources

    table = load_sources(sources, fmt)
    table.to_parquet(out)
    df = table.df
    trials = df.groupby(["design_key", "trial"]).first()["experiment"].value_counts().to_dict()
    typer.echo(f"{len(table)} rows, {len(table.design_keys)} membranes, trials {trials} -> {out}")


# Modules that add commands to ``app``: each defines ``register(app: typer.Typer)`` and
# imports its heavy dependencies (JAX, emcee, ...) inside the command bodies, so that
# ``mfdesign --help`` stays fast.
_COMMAND_MODULES = (
    "mfdesign.cli_calibrate",  # calibrate, fit --multi-fidelity helpers
    "mfdesign.cli_diagnose",  # diagnose
    "mfdesign.cli_propose",  # propose
    "mfdesign.cli_optimize",  # optimize
)


def _register_subcommands() -> None:
    import importlib
    import importlib.util

    from mfdesign import cli_contract

    from mfdesign.rig.commands import rig_app

    app.add_typer(rig_app, name="rig", help="Drive the test rig (or its emulator) over a serial port.")
    for name in _COMMAND_MODULES:
        if importlib.util.find_spec(name) is not None:
            importlib.import_module(name).register(app)
    cli_contract.apply(app)  # every command: --out checked and locked before computing


_register_subcommands()


if __name__ == "__main__":  # pragma: no cover
    app()
