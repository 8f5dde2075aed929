"""``mfdesign calibrate`` and ``mfdesign fit-mf``: Bayesian calibration and the multi-fidelity
fit (:func:`calibrate`).

``DATA`` is a Measurements Parquet file or ``mass-lift`` (the authors' real data). Both
write into the output folder: ``chain.h5`` (emcee HDF5 backend: rerunning the same
command resumes a killed run; unconstrained parameters), ``posterior.json`` +
``posterior.npz``, ``posterior.nc`` (ArviZ InferenceData in physical units, chain x
draw, with log_likelihood / posterior_predictive / observed_data: ``az.from_netcdf``),
``corner.png``; ``fit-mf`` adds the discrepancy ensemble (``delta/``) and ``mf.json``
(residual noise, training RMSE and 90 % coverage). The summary is the posterior table
(median, 5 / 95 %, MAP, with units) and the chain's convergence. ``effects_module``
(``--effects-module FILE.py``, repeatable) imports a user's effects files first
(:func:`mfdesign.user_effects.load_effects_module`: their code runs), so ``effects`` may
name what they register.
"""

from __future__ import annotations

import json
from dataclasses import dataclass
from pathlib import Path
from typing import Any, Sequence

from mfdesign.errors import InputError

__all__ = ["CalibrationResult", "bundled_truths", "calibrate", "check_chain"]

LIKELIHOODS = ("gaussian", "student_t")


def check_chain(chain: Path) -> None:
    """A chain.h5 to resume must be a readable HDF5 file (a truncated or foreign one would
    fail deep inside emcee, after the data were loaded and the model built).

    Arguments:
        chain: the emcee HDF5 backend file (``OUT/chain.h5``).

    Raises :class:`~mfdesign.errors.InputError` when it cannot be read."""
    import h5py

    try:
        with h5py.File(chain, "r") as f:
            f.visit(lambda name: None)
    except Exception as err:  # noqa: BLE001 -- h5py raises OSError, KeyError, RuntimeError on junk
        raise InputError(
            f"{chain} is not a readable chain ({type(err).__name__}: {str(err)[:120]}); allowed: a "
            "chain.h5 written by mfdesign calibrate / fit-mf, or --no-resume to start a new one"
        ) from None


def bundled_truths(data: Any) -> dict[str, float]:
    """The parameters the bundled dataset was made with (its card: ``mu_pa`` in Pa, ``jm``,
    the hidden effect's), when DATA is exactly that dataset (the ``bundled`` keyword or its
    file); else empty.

    Arguments:
        data: the ``DATA`` sources of the command (a list of paths or keywords)."""
    from mfdesign.data.shipped import BUNDLED_NAME, bundled_card_path, bundled_path, card_truths

    paths = list(data or [])
    if len(paths) != 1 or not bundled_card_path().is_file():
        return {}
    only = Path(paths[0])
    if str(only) != BUNDLED_NAME and not (only.is_file() and only.resolve() == bundled_path().resolve()):
        return {}
    return card_truths(json.loads(bundled_card_path().read_text()))


@dataclass(frozen=True)
class CalibrationResult:
    """What :func:`calibrate` sampled and wrote.

    ``posterior``: the :class:`mfdesign.calibration.mcmc.Posterior` (its table and
    convergence); ``written``: the files by kind (chain, posterior, inference_data,
    corner; fit-mf adds delta and mf); ``mf_line``: fit-mf's residual noise [N], training
    RMSE [N] and coverage ("" for calibrate); ``warnings``: the sampler's convergence
    warnings, one line each."""

    posterior: Any
    written: dict
    mf_line: str = ""
    warnings: tuple[str, ...] = ()

    def summary(self) -> str:
        """The posterior table, the chain's convergence line (emcee's tau, ArviZ's R-hat /
        ESS, BIC, Laplace evidence), fit-mf's line, and the files as one JSON line."""
        post = self.posterior
        c = post.convergence
        lines = [
            post.format_table(),
            f"chain {c['n_steps']} steps x {c['n_walkers']} walkers (resumed from {c['resumed_from']}); "
            f"tau_max {c['tau_max']:.1f} -> {c['steps_over_tau']:.1f} tau; acceptance {c['acceptance']:.2f}; "
            # ArviZ's R-hat and ESS over the walkers (per parameter: posterior.json "convergence")
            f"R-hat max {c.get('rhat_max', float('nan')):.3f}, ESS bulk min {c.get('ess_bulk_min', float('nan')):.0f}, "
            f"tail min {c.get('ess_tail_min', float('nan')):.0f} (ArviZ); "
            f"BIC {post.bic:.1f}; Laplace log evidence {post.log_evidence_laplace:.1f}",
        ]
        if self.mf_line:
            lines.append(self.mf_line)
        lines.append(json.dumps(self.written))
        return "\n".join(lines)


def _check_options(
    effects: Sequence[str], walkers: int, likelihood: str, material: str, per_membrane: Sequence[str] = ()
) -> dict:
    """The material's priors; ``InputError`` for a bad likelihood, walker count, material,
    effect or per-membrane parameter."""
    from mfdesign.calibration.workflow import MATERIALS, material_priors
    from mfdesign.physics.effects import EFFECTS

    if likelihood not in LIKELIHOODS:
        raise InputError(f"--likelihood must be 'gaussian' or 'student_t', got {likelihood!r}")
    if walkers and walkers < 2:
        raise InputError(f"--walkers must be >= 2 (0 = automatic), got {walkers}")
    if material not in MATERIALS:
        raise InputError(f"--material must be one of {', '.join(MATERIALS)}, got {material!r}")
    priors = material_priors(material)
    unknown = [e for e in effects if e not in EFFECTS]
    if unknown:
        raise InputError(
            f"unknown effect(s) {unknown}; registered: {sorted(EFFECTS)} (a user's own effect: "
            "--effects-module FILE.py, the file that registers it)"
        )
    from mfdesign.models.hierarchical import membrane_parameters

    try:
        membrane_parameters(effects, per_membrane)
    except ValueError as err:
        raise InputError(f"--per-membrane: {err} (name the effect with --effects first)") from None
    return priors


def _load(data: Any, physics: str, multi_fidelity: bool, allow_outside_design_space: bool) -> tuple[Any, Any]:
    """The measurements and the force model (``physics``) they are calibrated against."""
    from mfdesign.calibration.workflow import force_model_named
    from mfdesign.workflows.data import load_data

    try:
        table = load_data(data, "fit-mf" if multi_fidelity else "calibrate", allow_outside_design_space)
        return table, force_model_named(physics, table, progress=True)
    except (ValueError, FileNotFoundError) as err:  # MeasurementError is a ValueError
        raise InputError(str(err)) from None


def _sample(table: Any, force_model: Any, effects: list[str], chain: Path, s: dict, priors: dict) -> tuple[Any, Any]:
    """``(fit or None, (posterior, model))``: emcee, plus the discrepancy for fit-mf."""
    from mfdesign.calibration.mcmc import calibrate as run_emcee
    from mfdesign.calibration.workflow import fit_multi_fidelity, model_for
    from mfdesign.models.hierarchical import CalibrationData

    if s["multi_fidelity"]:
        from mfdesign.models.ensemble import EnsembleConfig

        cfg = EnsembleConfig(n_members=s["members"], steps=s["delta_steps"], monotone=False)
        fit = fit_multi_fidelity(
            table,
            force_model,
            effects,
            n_steps=s["steps"],
            n_walkers=s["walkers"] or None,
            max_rows=s["max_rows"],
            chain_path=chain,
            ensemble_config=cfg,
            seed=s["seed"],
            likelihood=s["likelihood"],
            membrane_latents=s["latents"],
            membrane_effects=s["per_membrane"],
            **priors,
        )
        return fit, (fit.posterior, fit.model)
    cdata = CalibrationData.from_measurements(table, max_rows=s["max_rows"], seed=s["seed"])
    model = model_for(
        force_model,
        cdata.design_keys,
        effects,
        likelihood=s["likelihood"],
        membrane_latents=s["latents"],
        membrane_effects=s["per_membrane"],
        **priors,
    )
    post = run_emcee(
        cdata,
        model,
        n_steps=s["steps"],
        n_walkers=s["walkers"] or None,
        chain_path=chain,
        seed=s["seed"],
        stop_when_converged=True,
    )
    return None, (post, model)


def _corner(post: Any, data: Any, effects: list[str], path: Path) -> None:
    """The corner plot (no per-membrane thickness rows); red lines at the bundled data's truths."""
    from mfdesign.calibration.plots import corner_plot

    from mfdesign.models.hierarchical import membrane_block

    keep = [i for i, n in enumerate(post.names) if membrane_block(n) is None]
    names = [post.names[i] for i in keep]
    truths = bundled_truths(data)  # the bundled data's card knows what made them: red lines
    corner_plot(
        post.samples[:, keep],
        names,
        path,
        units=[post.units[i] for i in keep],
        truths=[truths.get(n) for n in names] if truths else None,
        title=f"{data}: effects {effects or 'none'}" + (" (red: the values the data were made with)" if truths else ""),
    )


def calibrate(
    data: Any,
    effects: Sequence[str],
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
    effects_module: Sequence[Path] | None = None,
    per_membrane: Sequence[str] = (),
) -> CalibrationResult:
    """Calibrate the rubber's ``mu`` [Pa] and ``J_m`` and the effects' parameters with emcee
    (``calibrate``), or fit the multi-fidelity model: calibrated simulator + RPN
    discrepancy ensemble + noise (``fit-mf``, ``multi_fidelity=True``).

    Arguments:
        data: the ``DATA`` sources (:func:`mfdesign.workflows.data.load_data`).
        effects: names of the active effects (:data:`mfdesign.physics.effects.EFFECTS`).
        out: output folder (created; ``chain.h5`` in it is resumed when ``resume``).
        steps: most emcee steps (total; sampling stops once the chain is long enough).
        walkers: emcee walkers (0: automatic; else >= 2).
        max_rows: rows the likelihood uses.
        physics: force model where the model meets the data: ``exact`` | ``emulator`` | ``standin``.
        likelihood: ``student_t`` (nu = 4) | ``gaussian``.
        seed: random seed.
        resume: resume ``out/chain.h5`` if it exists (False: start a new chain).
        allow_outside_design_space: accept membranes outside the product's design space.
        multi_fidelity: fit-mf (adds the discrepancy ensemble, ``delta/`` and ``mf.json``).
        members: discrepancy ensemble members (fit-mf).
        delta_steps: discrepancy training steps (fit-mf).
        material: ``free`` | ``coupons`` | ``coupons-jm`` (which rubber constants are held).
        latents: one thickness latent per membrane (False: nominal thicknesses).
        effects_module: Python files registering new effects, imported before ``effects``
            are checked (their code runs); their sha256 join the provenance's inputs, and
            ``out/effects/`` keeps copies that every ``--model out`` imports again.
        per_membrane: parameters of ``effects`` (``effect.param``, or an effect's name) that
            vary from membrane to membrane around a calibrated population (a hierarchical
            random effect; a new membrane's interval integrates over it).

    Raises :class:`~mfdesign.errors.InputError` (one line) for bad options, data or chain."""
    import warnings

    from mfdesign.calibration.mcmc import ConvergenceWarning
    from mfdesign.calibration.posterior import save_inference_data  # ArviZ: az.from_netcdf(OUT/posterior.nc)

    from mfdesign.user_effects import keep_in_output, load_effects_module

    modules = [Path(m) for m in effects_module or []]
    registered = [load_effects_module(m) for m in modules]  # before the names are checked: they may register them
    effects = list(effects)
    priors = _check_options(effects, walkers, likelihood, material, per_membrane)
    table, force_model = _load(data, physics, multi_fidelity, allow_outside_design_space)
    out = Path(out)
    out.mkdir(parents=True, exist_ok=True)
    chain = out / "chain.h5"
    if not resume and chain.exists():
        chain.unlink()
    if chain.exists():
        check_chain(chain)
    settings = dict(
        multi_fidelity=multi_fidelity,
        members=members,
        delta_steps=delta_steps,
        steps=steps,
        walkers=walkers,
        max_rows=max_rows,
        seed=seed,
        likelihood=likelihood,
        latents=latents,
        per_membrane=tuple(per_membrane),
    )
    with warnings.catch_warnings(record=True) as caught:
        warnings.simplefilter("always", ConvergenceWarning)
        try:
            fit, (post, model) = _sample(table, force_model, effects, chain, settings, priors)
        except ValueError as err:
            raise InputError(str(err)) from None
    # Written first: the R-hat and ESS printed and saved in posterior.json are those ArviZ
    # computes on this file's draws (every walker's kept draws, one per tau).
    save_inference_data(post, out / "posterior.nc", model, table, seed=seed, max_rows=max_rows)
    from mfdesign.provenance import call_line, input_hashes

    call = call_line("mfdesign.workflows.calibrate.calibrate()")
    inputs = input_hashes([*(data if isinstance(data, (list, tuple)) else [data]), *modules])
    # after posterior.nc: its R-hat and ESS are those of the file
    post.save(out / "posterior", call=call, seeds={"seed": seed}, inputs=inputs)
    _corner(post, data, effects, out / "corner.png")
    written = {
        "chain": str(chain),
        "posterior": str(out / "posterior.json"),
        "inference_data": str(out / "posterior.nc"),
        "corner": str(out / "corner.png"),
    }
    # copies of the effects files, imported again by every --model OUT (propose, optimize, ...)
    keep_in_output(out, modules, registered)
    if modules:
        written["effects_modules"] = str(out / "effects" / "modules.json")
    mf_line = ""
    if fit is not None:
        # posterior.json again: the same numbers (its provenance's time may be a second later)
        meta = fit.save(out, physics=physics, material=material, table=table, call=call, inputs=inputs)
        mf_line = (
            f"multi-fidelity: residual noise {fit.noise_n:.3f} N; training RMSE {meta['train_rmse_n']:.3f} N, "
            f"90 % coverage {meta['train_coverage90']:.2f}; {fit.delta.describe()}"
        )
        written.update(delta=str(out / "delta"), mf=str(out / "mf.json"))
    # the chain's convergence only: a library's own notices (ArviZ's "undergoing a major
    # refactor" FutureWarning on import) are not the user's business
    said = tuple(f"warning: {w.message}" for w in caught if issubclass(w.category, ConvergenceWarning))
    return CalibrationResult(post, written, mf_line, said)
