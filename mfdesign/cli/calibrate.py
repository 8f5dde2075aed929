"""``mfdesign calibrate`` and ``mfdesign fit-mf``: Bayesian calibration and the multi-fidelity fit.

``DATA`` is a Measurements Parquet file or ``mass-lift`` (the authors' real data). Both
commands print the posterior summary table (median, 5 / 95 %, MAP, with units) and write
into ``--out``: ``chain.h5`` (emcee HDF5 backend: rerunning the same command resumes a
killed run; unconstrained parameters), ``posterior.json`` + ``posterior.npz``,
``posterior.nc`` (ArviZ InferenceData in physical units, chain x draw, with
log_likelihood / posterior_predictive / observed_data: ``az.from_netcdf``), ``corner.png``; ``fit-mf`` adds the
discrepancy ensemble (``delta/``) and ``mf.json`` (residual noise, training RMSE and 90 %
coverage).
"""

from __future__ import annotations

import inspect
import json
from pathlib import Path
from typing import Annotated, List, Optional

import typer

from mfdesign.cli._app import ALLOW_OUTSIDE
from mfdesign.cli._contract import effect_name, item_parser


def _check_chain(chain: Path) -> None:
    """A chain.h5 to resume must be a readable HDF5 file (a truncated or foreign one would
    fail deep inside emcee, after the data were loaded and the model built)."""
    import h5py

    from mfdesign.errors import InputError

    try:
        with h5py.File(chain, "r") as f:
            f.visit(lambda name: None)
    except Exception as err:  # noqa: BLE001 -- h5py raises OSError, KeyError, RuntimeError on junk
        raise InputError(
            f"{chain} is not a readable chain ({type(err).__name__}: {str(err)[:120]}); allowed: a "
            "chain.h5 written by mfdesign calibrate / fit-mf, or --no-resume to start a new one"
        ) from None


def _run(
    data: Path,
    effects: list[str],
    out: Path,
    steps: int,
    walkers: int,
    max_rows: int,
    physics: str,
    likelihood: str,
    seed: int,
    resume: bool,
    allow_outside_design_space: bool = False,
    multi_fidelity: bool = False,
    members: int = 0,
    delta_steps: int = 0,
    material: str = "free",
    latents: bool = True,
) -> None:
    from mfdesign.cli._app import fail

    if likelihood not in ("gaussian", "student_t"):
        fail(f"--likelihood must be 'gaussian' or 'student_t', got {likelihood!r}")
    if walkers and walkers < 2:
        fail(f"--walkers must be >= 2 (0 = automatic), got {walkers}")
    from mfdesign.calibration.workflow import MATERIALS, material_priors

    if material not in MATERIALS:
        fail(f"--material must be one of {', '.join(MATERIALS)}, got {material!r}")
    priors = material_priors(material)
    import warnings

    from mfdesign.calibration.plots import corner_plot
    from mfdesign.calibration.workflow import fit_multi_fidelity, force_model_named, model_for
    from mfdesign.calibration.mcmc import ConvergenceWarning, calibrate
    from mfdesign.data.measurements import MeasurementError
    from mfdesign.cli.data import load_data
    from mfdesign.models.hierarchical import CalibrationData
    from mfdesign.physics.effects import EFFECTS

    unknown = [e for e in effects if e not in EFFECTS]
    if unknown:
        fail(f"unknown effect(s) {unknown}; registered: {sorted(EFFECTS)}")
    try:
        table = load_data(data, "fit-mf" if multi_fidelity else "calibrate", allow_outside_design_space)
        force_model = force_model_named(physics, table, progress=True)
    except (ValueError, MeasurementError, FileNotFoundError) as err:
        fail(str(err))
    out.mkdir(parents=True, exist_ok=True)
    chain = out / "chain.h5"
    if not resume and chain.exists():
        chain.unlink()
    if chain.exists():
        _check_chain(chain)
    with warnings.catch_warnings(record=True) as caught:
        warnings.simplefilter("always", ConvergenceWarning)
        try:
            if multi_fidelity:
                from mfdesign.models.ensemble import EnsembleConfig

                cfg = EnsembleConfig(n_members=members, steps=delta_steps, monotone=False)
                fit = fit_multi_fidelity(
                    table,
                    force_model,
                    effects,
                    n_steps=steps,
                    n_walkers=walkers or None,
                    max_rows=max_rows,
                    chain_path=chain,
                    ensemble_config=cfg,
                    seed=seed,
                    likelihood=likelihood,
                    membrane_latents=latents,
                    **priors,
                )
                post = fit.posterior
            else:
                cdata = CalibrationData.from_measurements(table, max_rows=max_rows, seed=seed)
                model = model_for(
                    force_model, cdata.design_keys, effects, likelihood=likelihood, membrane_latents=latents, **priors
                )
                post = calibrate(
                    cdata,
                    model,
                    n_steps=steps,
                    n_walkers=walkers or None,
                    chain_path=chain,
                    seed=seed,
                    stop_when_converged=True,
                )
        except ValueError as err:
            fail(str(err))
    from mfdesign.calibration.posterior import save_inference_data  # ArviZ: az.from_netcdf(OUT/posterior.nc)

    # Written first: the R-hat and ESS printed below and saved in posterior.json are those
    # ArviZ computes on this file's draws (every walker's kept draws, one per tau).
    save_inference_data(
        post,
        out / "posterior.nc",
        fit.model if multi_fidelity else model,
        table,
        seed=seed,
        max_rows=max_rows,
    )
    typer.echo(post.format_table())
    c = post.convergence
    typer.echo(
        f"chain {c['n_steps']} steps x {c['n_walkers']} walkers (resumed from {c['resumed_from']}); "
        f"tau_max {c['tau_max']:.1f} -> {c['steps_over_tau']:.1f} tau; acceptance {c['acceptance']:.2f}; "
        # ArviZ's R-hat and ESS over the walkers (per parameter: posterior.json "convergence")
        f"R-hat max {c.get('rhat_max', float('nan')):.3f}, ESS bulk min {c.get('ess_bulk_min', float('nan')):.0f}, "
        f"tail min {c.get('ess_tail_min', float('nan')):.0f} (ArviZ); "
        f"BIC {post.bic:.1f}; Laplace log evidence {post.log_evidence_laplace:.1f}"
    )
    for w in caught:
        typer.echo(f"warning: {w.message}", err=True)
    post.save(out / "posterior")  # after posterior.nc: its R-hat and ESS are those of the file
    keep = [i for i, n in enumerate(post.names) if not n.startswith("thickness[")]
    names = [post.names[i] for i in keep]
    truths = _bundled_truths(data)  # the bundled data's card knows what made them: red lines
    corner_plot(
        post.samples[:, keep],
        names,
        out / "corner.png",
        units=[post.units[i] for i in keep],
        truths=[truths.get(n) for n in names] if truths else None,
        title=f"{data}: effects {effects or 'none'}" + (" (red: the values the data were made with)" if truths else ""),
    )
    written = {
        "chain": str(chain),
        "posterior": str(out / "posterior.json"),
        "inference_data": str(out / "posterior.nc"),
        "corner": str(out / "corner.png"),
    }
    if multi_fidelity:
        meta = fit.save(out, physics=physics, material=material, table=table)  # posterior again: the same bytes
        typer.echo(
            f"multi-fidelity: residual noise {fit.noise_n:.3f} N; training RMSE {meta['train_rmse_n']:.3f} N, "
            f"90 % coverage {meta['train_coverage90']:.2f}; {fit.delta.describe()}"
        )
        written.update(delta=str(out / "delta"), mf=str(out / "mf.json"))
    typer.echo(json.dumps(written))


# Options both commands take, declared once (typer reads them as parameter defaults).
DATA = typer.Argument(
    ...,
    help="Measurements .parquet/.csv file(s), SPA_Design .pkl, rig job folder(s), or 'mass-lift' (several: concatenated; docs/data.md).",
)


def _bundled_truths(data) -> dict[str, float]:
    """The parameters the bundled dataset was made with (its card), when DATA is exactly that
    dataset (the ``bundled`` keyword or its file); else empty."""
    import json

    from mfdesign.cli._demo import card_truths
    from mfdesign.data.shipped import BUNDLED_NAME, bundled_card_path, bundled_path

    paths = list(data or [])
    if len(paths) != 1 or not bundled_card_path().is_file():
        return {}
    only = Path(paths[0])
    if str(only) != BUNDLED_NAME and not (only.is_file() and only.resolve() == bundled_path().resolve()):
        return {}
    return card_truths(json.loads(bundled_card_path().read_text()))


EFFECTS = typer.Option(
    None, "--effects", parser=item_parser(effect_name, "an effect name"), help="Active effect (repeat for several)."
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
SEED = typer.Option(0, help="Random seed.")
MATERIAL = typer.Option(
    "free",
    help="The rubber: free (the data calibrate mu and J_m) | coupons (held at the coupons' 31.5 kPa "
    "and 39.6; the data calibrate the effects and latents) | coupons-jm (J_m held).",
)
LATENTS = typer.Option(
    True,
    help="One thickness latent per membrane (the hierarchy); --no-latents: every membrane at its "
    "nominal thickness (an effect shared by the membranes is then not traded against each one's scale: "
    "what predicted new membranes best on the real lifts, docs/real_data.md section 7).",
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
# plain values: calibrate's command never receives them and _run ignores them there).
ENSEMBLE_OPTIONS = ("members", "delta_steps")


def _register(
    app: typer.Typer,
    name: str,
    doc: str,
    *,
    multi_fidelity: bool,
    steps_default: int,
    rows_default: int,
    out_help: str,
    walkers_help: str,
    rows_help: str,
) -> None:
    """Add ``calibrate`` or ``fit-mf`` to ``app``: one parameter list for both commands, which
    differ in defaults, help texts and (fit-mf only) the :data:`ENSEMBLE_OPTIONS`."""

    def command(
        data: List[Path] = DATA,
        out: Path = typer.Option(..., help=out_help),
        effects: Optional[List[str]] = EFFECTS,
        steps: int = _mcmc_steps(steps_default),
        walkers: int = typer.Option(0, min=0, help=walkers_help),
        max_rows: int = typer.Option(rows_default, min=10, help=rows_help),
        physics: str = PHYSICS,
        likelihood: str = LIKELIHOOD,
        members: Annotated[int, typer.Option(min=1, help="Discrepancy ensemble members.")] = 8,
        delta_steps: Annotated[int, typer.Option(min=1, help="Discrepancy training steps.")] = 3000,
        seed: int = SEED,
        resume: bool = RESUME,
        allow_outside_design_space: bool = ALLOW_OUTSIDE,
        material: str = MATERIAL,
        latents: bool = LATENTS,
    ) -> None:
        _run(
            data,
            list(effects or []),
            out,
            steps,
            walkers,
            max_rows,
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
        )

    command.__doc__ = doc
    if not multi_fidelity:
        # typer reads a command's options from its signature: calibrate's has no ensemble options.
        sig = inspect.signature(command)
        command.__signature__ = sig.replace(  # type: ignore[attr-defined]
            parameters=[p for n, p in sig.parameters.items() if n not in ENSEMBLE_OPTIONS]
        )
    app.command(name)(command)


def register(app: typer.Typer) -> None:
    _register(
        app,
        "calibrate",
        "Calibrate mu [Pa], J_m and the effects' parameters with emcee (posterior table, corner plot, chain).",
        multi_fidelity=False,
        steps_default=3000,
        rows_default=3000,
        out_help="Output folder (chain.h5, posterior.json/.npz, corner.png).",
        walkers_help="emcee walkers (0: max(32, 2 dim + 2)).",
        rows_help="Rows used by the likelihood (evenly within trials).",
    )
    _register(
        app,
        "fit-mf",
        "Multi-fidelity fit: calibrated simulator + RPN discrepancy ensemble + noise.",
        multi_fidelity=True,
        steps_default=2000,
        rows_default=1500,
        out_help="Output folder.",
        walkers_help="emcee walkers (0: automatic).",
        rows_help="Rows used by the likelihood.",
    )
