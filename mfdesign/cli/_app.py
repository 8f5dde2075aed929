"""The ``mfdesign`` application object and what every command module shares.

Bad input (a design that cannot be built, a file that is not what it should be) prints
one line saying what was wrong and what is allowed, and exits with status 2; an unexpected
error prints one line naming a log file with the traceback and exits with status 1
(:mod:`mfdesign.cli._contract`).
"""

from __future__ import annotations

import logging
from typing import NoReturn

import typer

from mfdesign._cache import enable_compilation_cache
from mfdesign.cli._contract import ContractGroup
from mfdesign.cli._runlog import VERBOSITY_KEY, _EchoHandler

# Said at the foot of every command's --help (:func:`plain_help`): the design key and the
# units are what a new user needs first, whichever command they opened.
UNITS_EPILOG = (
    'Designs are the key "[t, c, r1, w1, r2, w2]" in mm: thickness, contact radius, then each '
    "ring's centre radius and half-width, nan for an absent ring. Units: heights and lengths "
    "in mm, pressures in Pa, forces in N."
)

# ContractGroup turns whatever escapes a command into the one-line contract (module doc).
# rich_markup_mode=None: Rich markup reads "[t, c, r1, w1, r2, w2]" and "[mm]" as style
# tags and prints nothing for them, and puts a "<bool>" placeholder on flags; plain click
# help prints the text as written (and does not import rich, which keeps --help fast).
app = typer.Typer(
    help="Multi-fidelity Bayesian design of soft pneumatic actuators.",
    no_args_is_help=True,
    add_completion=False,
    cls=ContractGroup,
    rich_markup_mode=None,
    epilog=UNITS_EPILOG,
)


def plain_help(typer_app: typer.Typer) -> None:
    """Plain help text (no Rich markup, see ``app``) for ``typer_app`` and every sub-app,
    with :data:`UNITS_EPILOG` under every command that has no epilog of its own."""
    typer_app.rich_markup_mode = None
    typer_app.info.epilog = typer_app.info.epilog or UNITS_EPILOG
    for command in typer_app.registered_commands:
        command.epilog = command.epilog or UNITS_EPILOG
    for group in typer_app.registered_groups:
        if group.typer_instance is not None:
            group.epilog = group.epilog or UNITS_EPILOG
            plain_help(group.typer_instance)


# Declared once; the data commands and simulate take it.
ALLOW_OUTSIDE = typer.Option(
    False,
    "--allow-outside-design-space",
    help="Research: accept designs outside the product's space (thickness 1-3 mm, ...) "
    "up to a wider physical range; the output says so.",
)


# Declared once; the commands that solve simulator planes take it. The contract hands it to
# the planes' solver for the whole command (mfdesign.cli._contract.ContractCommand,
# mfdesign.physics.cluster.use_scheduler); the command bodies pass it nowhere.
SCHEDULER = typer.Option(
    None,
    "--scheduler",
    metavar="ADDRESS",
    help="Dask scheduler (e.g. tcp://host:8786) whose workers solve the simulator planes; default "
    '$MFDESIGN_SCHEDULER, else this machine\'s cores. Needs pip install "mfdesign[dask]" and '
    "MFDESIGN_CACHE_DIR on a folder every worker sees (docs/physics.md).",
)


def fail(message: str) -> NoReturn:
    """Print one line to stderr and exit with status 2."""
    typer.echo(f"error: {message}", err=True)
    raise typer.Exit(code=2)


def show(result) -> None:
    """Print a workflow's result (:mod:`mfdesign.workflows`): its ``summary()`` on stdout,
    then each of its ``warnings`` (if it has any) on stderr."""
    text = result.summary()
    if text:
        typer.echo(text)
    for line in getattr(result, "warnings", ()):
        typer.echo(line, err=True)


def _print_version(value: bool) -> None:
    if value:
        from importlib.metadata import version

        typer.echo(f"mfdesign {version('mfdesign')}")
        raise typer.Exit()


def show_lattice_growth() -> None:
    """The exact force model's one line per lattice growth ("exact planes: lattice grows to
    ...", :mod:`mfdesign.models.exact`) on stderr: a calibration can solve planes for an
    hour, and the progress bar alone does not say why."""
    log = logging.getLogger("mfdesign.models.exact")
    if not any(isinstance(h, _EchoHandler) for h in log.handlers):
        handler = _EchoHandler()
        handler.setFormatter(logging.Formatter("%(asctime)s %(message)s", datefmt="%H:%M:%S"))
        log.addHandler(handler)
        log.setLevel(logging.INFO)


@app.callback()
def _main(
    ctx: typer.Context,
    version: bool = typer.Option(
        False, "--version", callback=_print_version, is_eager=True, help="Print the version and exit."
    ),
    verbose: bool = typer.Option(
        False, "--verbose", "-v", help="Every log record on stderr (DEBUG); run.log holds them too."
    ),
    quiet: bool = typer.Option(False, "--quiet", "-q", help="Only warnings and errors on stderr."),
) -> None:
    """Every command with --out writes run.log beside its outputs: version, command line,
    settings, log records, exit status (mfdesign.cli._runlog)."""
    from mfdesign.cli._runlog import console, plain_warnings

    if verbose and quiet:
        fail("--verbose and --quiet exclude each other; give one")
    enable_compilation_cache()
    show_lattice_growth()
    console(verbose, quiet)
    plain_warnings()
    ctx.meta[VERBOSITY_KEY] = "verbose" if verbose else "quiet" if quiet else "normal"
