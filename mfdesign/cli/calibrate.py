"""``mfdesign calibrate`` and ``mfdesign fit-mf``: Bayesian calibration and the multi-fidelity
fit; the workflow is :func:`mfdesign.workflows.calibrate.calibrate`.

``DATA`` is a Measurements Parquet file or ``mass-lift`` (the authors' real data). Both
commands print the posterior summary table (median, 5 / 95 %, MAP, with units) and write
into ``--out``: ``chain.h5`` (emcee HDF5 backend: rerunning the same command resumes a
killed run; unconstrained parameters), ``posterior.json`` + ``posterior.npz``,
``posterior.nc`` (ArviZ InferenceData in physical units, chain x draw, with
log_likelihood / posterior_predictive / observed_data: ``az.from_netcdf``), ``corner.png``; ``fit-mf`` adds the
discrepancy ensemble (``delta/``) and ``mf.json`` (residual noise, training RMSE and 90 %
coverage). ``--effects-module FILE.py`` (repeat for several) imports a user's file that
registers effects (its code runs), so ``--effects`` may name them; ``OUT/effects/`` keeps a
copy (sha256 in ``effects/modules.json``) that every ``--model OUT`` imports again.
"""

from __future__ import annotations

import dataclasses
import inspect
from pathlib import Path
from types import SimpleNamespace
from typing import Annotated, List, Optional

import typer

from mfdesign.campaign import Settings
from mfdesign.cli._app import ALLOW_OUTSIDE, SCHEDULER, show
from mfdesign.cli._contract import effect_name, item_parser
from mfdesign.workflows.calibrate import bundled_truths as _bundled_truths  # noqa: F401 -- old name, still read
from mfdesign.workflows.calibrate import calibrate  # light: its heavy imports are inside its functions

# One set of defaults for a calibration, wherever it runs: the campaign's (issue 41; calibrate
# used to take 3000 steps / 3000 rows and fit-mf 2000 / 1500). A chain stops once it is 50
# autocorrelation times long, so the step count is a ceiling, not the work done. The
# fields' declared defaults, not ``Settings()``: its validation imports JAX, and a
# ``--help`` page must not (tests/cli/test_help.py).
DEFAULTS = SimpleNamespace(**{f.name: f.default for f in dataclasses.fields(Settings)})

# Options both commands take, declared once (typer reads them as parameter defaults).
DATA = typer.Argument(
    ...,
    help="Measurements .parquet/.csv file(s), SPA_Design .pkl, rig job folder(s), or 'mass-lift' (several: concatenated; docs/data.md).",
)


EFFECTS = typer.Option(
    None, "--effects", parser=item_parser(effect_name, "an effect name"), help="Active effect (repeat for several)."
)
EFFECTS_MODULE = typer.Option(
    None,
    "--effects-module",
    help="Python file registering new effects, imported first (its code runs) so that --effects may name "
    "them; OUT/effects/ keeps a copy, imported again by --model OUT (repeat for several; docs/calibration.md).",
)
PHYSICS = typer.Option(
    "exact",
    help="Force model where the model meets the data: exact (simulator planes of "
    "the measured membranes, at simulator accuracy) | emulator (neural emulator, ~1 N error) | "
    "standin (no physics; tests).",
)
LIKELIHOOD = typer.Option(
    "student_t",
    help="student_t (nu = 4: robust to rows the model cannot hold, e.g. a "
    "lifted plate mid snap-through or at the rig's top stop) | gaussian",
)
SEED = typer.Option(DEFAULTS.seed, help="Random seed.")
MATERIAL = typer.Option(
    "free",
    help="The rubber: free (the data calibrate mu and J_m) | coupons (held at the coupons' 31.5 kPa "
    "and 39.6; the data calibrate the effects and latents) | coupons-jm (J_m held).",
)
LATENTS = typer.Option(
    True,
    help="One thickness latent per membrane (the hierarchy); --no-latents: every membrane at its "
    "nominal thickness (an effect shared by the membranes is then not traded against each one's scale: "
    "what predicted new membranes best on the real lifts, docs/real_data_log.md section 7).",
)
PER_MEMBRANE = typer.Option(
    None,
    "--per-membrane",
    help="An effect parameter (effect.param, or an effect's name) that varies from membrane to membrane: "
    "each membrane has its own value, drawn from a population whose spread is calibrated; a new membrane's "
    "interval integrates over it. Repeatable; its effect must be among --effects.",
)
RESUME = typer.Option(True, help="Resume the chain in OUT/chain.h5 if it exists.")


def _mcmc_steps(default: int):
    return typer.Option(
        default,
        "--mcmc-steps",
        min=1,
        help="Most emcee steps (total; a rerun resumes); sampling stops earlier once the chain is >= 50 "
        "autocorrelation times long.",
    )


# The discrepancy ensemble's options: fit-mf's only (Annotated, so that their defaults are
# plain values: calibrate's command never receives them and the workflow ignores them there).
ENSEMBLE_OPTIONS = ("members", "delta_steps")


def _register(
    app: typer.Typer,
    name: str,
    doc: str,
    *,
    multi_fidelity: bool,
    out_help: str,
    walkers_help: str,
    rows_help: str,
) -> None:
    """Add ``calibrate`` or ``fit-mf`` to ``app``: one parameter list for both commands, with
    the campaign's defaults (:data:`DEFAULTS`); they differ in help texts and (fit-mf only)
    the :data:`ENSEMBLE_OPTIONS`."""

    def command(
        data: List[Path] = DATA,
        out: Path = typer.Option(..., help=out_help),
        effects: Optional[List[str]] = EFFECTS,
        effects_module: Optional[List[Path]] = EFFECTS_MODULE,
        steps: int = _mcmc_steps(DEFAULTS.mcmc_steps),
        walkers: int = typer.Option(DEFAULTS.walkers, min=0, help=walkers_help),
        max_rows: int = typer.Option(DEFAULTS.max_rows, min=10, help=rows_help),
        physics: str = PHYSICS,
        likelihood: str = LIKELIHOOD,
        members: Annotated[int, typer.Option(min=1, help="Discrepancy ensemble members.")] = DEFAULTS.members,
        delta_steps: Annotated[int, typer.Option(min=1, help="Discrepancy training steps.")] = DEFAULTS.delta_steps,
        seed: int = SEED,
        resume: bool = RESUME,
        allow_outside_design_space: bool = ALLOW_OUTSIDE,
        material: str = MATERIAL,
        latents: bool = LATENTS,
        per_membrane: Optional[List[str]] = PER_MEMBRANE,
        scheduler: Optional[str] = SCHEDULER,
    ) -> None:
        show(
            calibrate(
                *(data, list(effects or []), out, steps, walkers, max_rows),
                physics=physics,
                likelihood=likelihood,
                seed=seed,
                resume=resume,
                allow_outside_design_space=allow_outside_design_space,
                multi_fidelity=multi_fidelity,
                members=members,
                delta_steps=delta_steps,
                material=material,
                latents=latents,
                effects_module=effects_module,
                per_membrane=list(per_membrane or []),
            )
        )

    command.__doc__ = doc
    if not multi_fidelity:  # calibrate's command has no ensemble options
        _drop_options(command, ENSEMBLE_OPTIONS)
    app.command(name)(command)


def _drop_options(command, names) -> None:
    """Remove ``names`` from the options of ``command`` (typer reads a command's options
    from its signature)."""
    sig = inspect.signature(command)
    command.__signature__ = sig.replace(parameters=[p for n, p in sig.parameters.items() if n not in names])


def register(app: typer.Typer) -> None:
    _register(
        app,
        "calibrate",
        "Calibrate mu [Pa], J_m and the effects' parameters with emcee (posterior table, corner plot, chain).",
        multi_fidelity=False,
        out_help="Output folder (chain.h5, posterior.json/.npz, corner.png).",
        walkers_help="emcee walkers (0: max(32, 2 dim + 2)).",
        rows_help="Rows used by the likelihood (evenly within trials).",
    )
    _register(
        app,
        "fit-mf",
        "Multi-fidelity fit: calibrated simulator + RPN discrepancy ensemble + noise.",
        multi_fidelity=True,
        out_help="Output folder.",
        walkers_help="emcee walkers (0: automatic).",
        rows_help="Rows used by the likelihood.",
    )
