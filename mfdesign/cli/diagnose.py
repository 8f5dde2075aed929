"""``mfdesign diagnose``: compare a model with measurements, find the missing effect, add it;
the workflow is :func:`mfdesign.workflows.diagnose.diagnose`.

    mfdesign diagnose DATA [--model DIR] [--effects NAME ...] [--theta JSON] [--config FILE]
                      [--effects-module FILE.py ...] [--physics exact|emulator|standin] --out DIR

``DATA``: a Measurements Parquet file or ``mass-lift``. Without ``--model`` the model is
the plain simulator (authors' constants), evaluated by ``--physics``: ``exact`` (default:
simulator planes of the measured membranes at simulator accuracy, solved once and cached;
autodiff screen and nonlinear refit of every candidate), ``emulator`` (the bundled neural
emulator, about 1 N RMS off the simulator: fast, but its error is as large as the gaps
diagnosis looks for) or ``standin`` (a cheap stand-in, for trials); ``--effects`` adds effects to it (calibrated
unless ``--theta`` fixes every parameter), giving a before/after report. A config file
(TOML or JSON) may hold any of ``effects``, ``theta``, ``effects_module``, ``model``,
``physics``, ``candidates``; command-line values win. ``effects_module`` (like
``--effects-module``) imports the Python files it names, so a config file runs code: treat
one from elsewhere as a script (docs/diagnose.md).
"""

from __future__ import annotations

from pathlib import Path
from typing import List, Optional

import typer

from mfdesign.cli._app import SCHEDULER, show
from mfdesign.cli._contract import effect_name, item_parser

# The options, declared once here so that the command reads as what it does.
DATA = typer.Argument(
    ...,
    help="Measurements .parquet/.csv file(s), SPA_Design .pkl, rig job folder(s), or 'mass-lift' (several: concatenated; docs/data.md).",
)
OUT = typer.Option(..., help="Folder for index.html, diagnosis.json and the PNGs.")
MODEL = typer.Option(None, help="Saved ensemble folder (default: the plain simulator).")
EFFECTS = typer.Option(
    None,
    "--effects",
    parser=item_parser(effect_name, "an effect name"),
    help="Effects to add (repeat for several).",
)
THETA = typer.Option(None, help="Effect parameters as JSON, e.g. '{\"pressure_sensor.offset_pa\": 150}'.")
CONFIG = typer.Option(
    None,
    help="TOML/JSON file with effects, theta, effects_module, ... (its effects_module runs the Python files it names: treat a config as code).",
)
EFFECTS_MODULE = typer.Option(
    None, "--effects-module", help="Python file(s) registering new effects (imported: their code runs)."
)
CANDIDATES = typer.Option(
    None,
    "--candidates",
    parser=item_parser(effect_name, "an effect name"),
    help="Effects the search may try (repeat; default: all).",
)
PHYSICS = typer.Option(
    "exact",
    help="exact (simulator planes of the measured membranes, cached) | emulator (neural emulator, ~1 N RMS error) | standin (no physics; trials).",
)
CHECK_PAIRS = typer.Option(
    3, min=0, help="Pairs of the joint screen given the full check as well (0: single effects only)."
)
FOLDS = typer.Option(
    3,
    min=2,
    help="Folds of held-out membranes in each candidate's check (more than the membranes: one membrane a fold).",
)
ALLOW_OUTSIDE = typer.Option(
    False,
    "--allow-outside-design-space",
    help="Research: accept membranes outside the product's design space (wider physical range).",
)


def diagnose(
    data: List[Path] = DATA,
    out: Path = OUT,
    model: Optional[Path] = MODEL,
    effects: Optional[List[str]] = EFFECTS,
    theta: Optional[str] = THETA,
    config: Optional[Path] = CONFIG,
    effects_module: Optional[List[Path]] = EFFECTS_MODULE,
    candidates: Optional[List[str]] = CANDIDATES,
    physics: str = PHYSICS,
    search: bool = typer.Option(True, help="Search for the missing effect."),
    check_top: int = typer.Option(3, min=1, help="Candidates given the full check."),
    check_pairs: int = CHECK_PAIRS,
    max_steps: int = typer.Option(2, min=1, help="Rounds of forward selection."),
    folds: int = FOLDS,
    shapes: bool = typer.Option(True, help="Plot the simulated shape at the worst points (exact physics only)."),
    cache_dir: Optional[Path] = typer.Option(None, help="Plane cache (default ~/.cache/mfdesign/planes)."),
    allow_outside_design_space: bool = ALLOW_OUTSIDE,
    scheduler: Optional[str] = SCHEDULER,
) -> None:
    """Residuals by height, pressure, design, trial and phase; worst regions in words; which
    effect is missing (screen + full check); before/after with --effects. Writes HTML + JSON."""
    options = dict(locals())  # every option, by name: the workflow takes them as they are
    options.pop("scheduler")  # the contract's (mfdesign.cli._app.SCHEDULER)
    from mfdesign.workflows.diagnose import diagnose as run

    show(run(**options))


def register(app: typer.Typer) -> None:
    app.command()(diagnose)
