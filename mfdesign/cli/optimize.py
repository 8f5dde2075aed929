"""``mfdesign optimize``: design a membrane for a lift task (see :mod:`mfdesign.optimize`).

Targets: ``--target-set A|B`` (the paper's height-maximisation sets: the three masses at
6.9 / 8.3 kPa) or ``--targets FILE``, a CSV or JSON table with columns ``force_n`` and
``pressure_pa`` (height maximisation), plus ``height_mm`` (and optionally ``weight``) for
trajectory targeting through way-points.

The winner is checked by the simulator by default when the exact simulator can serve the
model (:func:`simulator_for_check`), at the constants the model stands for (a fit-mf
model's calibrated ones, else the authors': :func:`simulator_constants`; the output says
which); the output names the limits the winner sits on (grid
tops, the rig's travel and pressure limit, design-space bounds) and the near-ties.
"""

from __future__ import annotations

import json
from pathlib import Path
from typing import Optional

import typer

from mfdesign.cli._app import ALLOW_OUTSIDE
from mfdesign.cli._contract import item_parser
from mfdesign.cli._space import CONTACT_RADIUS, HALF_WIDTH, THICKNESS, design_space


def read_targets(path: Path):
    """``HeightTargets`` or ``Waypoints`` from a CSV/JSON file; ``ValueError`` says what is wrong."""
    import pandas as pd

    from mfdesign.optimize import HeightTargets, Waypoints

    path = Path(path)
    if not path.is_file():
        raise ValueError(f"targets file {path} does not exist")
    try:
        if path.suffix.lower() == ".json":
            raw = json.loads(path.read_text())
            table = pd.DataFrame(raw["targets"] if isinstance(raw, dict) and "targets" in raw else raw)
        elif path.suffix.lower() == ".csv":
            table = pd.read_csv(path)
        else:
            raise ValueError(f"targets file must be .csv or .json, got {path.name}")
    except (json.JSONDecodeError, pd.errors.ParserError, UnicodeDecodeError, TypeError) as err:
        raise ValueError(f"cannot read targets from {path}: {err}") from None
    need = {"force_n", "pressure_pa"}
    if not need <= set(table.columns):
        raise ValueError(
            f"targets need columns force_n and pressure_pa (optional height_mm, weight); "
            f"got {sorted(map(str, table.columns))}"
        )
    cols = {c: table[c].to_numpy() for c in table.columns}
    try:
        if "height_mm" in cols:
            return Waypoints(cols["force_n"], cols["pressure_pa"], cols["height_mm"], cols.get("weight"))
        return HeightTargets(cols["force_n"], cols["pressure_pa"])
    except ValueError as err:
        raise ValueError(f"bad targets in {path}: {err}") from None


def load_fit(path: Path):
    """The multi-fidelity fit (:class:`~mfdesign.calibration.workflow.MFFit`) of a
    ``mfdesign fit-mf`` folder (``mf.json``), or None for any other folder. ``ValueError``
    (``InputError``) when the folder holds a broken fit."""
    path = Path(path)
    if not (path / "mf.json").is_file():
        return None
    from mfdesign.calibration.workflow import load_multi_fidelity

    return load_multi_fidelity(path)


def load_model(path: Path, fit=None):
    """The predictor (:class:`~mfdesign.models.predictor.AbstractPredictor`) of a saved model
    folder: the RPN ensemble of ``mfdesign fit`` (``ensemble.json``) or the multi-fidelity fit
    of ``mfdesign fit-mf`` (``mf.json``; 16 posterior draws; ``fit``: that fit, already
    loaded by :func:`load_fit`)."""
    from mfdesign.models.ensemble import Ensemble
    from mfdesign.models.predictor import EnsemblePredictor

    path = Path(path)
    if not path.is_dir():
        raise ValueError(f"model folder {path} does not exist (fit one with `mfdesign fit` or `mfdesign fit-mf`)")
    from mfdesign.models.sanity import check_predictor

    if (path / "mf.json").is_file():
        return check_predictor((load_fit(path) if fit is None else fit).mf.predictor(16), str(path))
    try:
        predictor = EnsemblePredictor(Ensemble.load(path))
    except (FileNotFoundError, ValueError, KeyError) as err:
        raise ValueError(f"cannot load a model from {path}: {err}") from None
    return check_predictor(predictor, str(path))


def simulator_for_check(model: Path) -> tuple[bool, str]:
    """Whether the exact simulator can check this model's winner, and why not. A model fitted
    with ``--physics standin`` (``mf.json``) stands for no physics at all: checking its
    designs against the simulator would compare two unrelated models (and take minutes)."""
    try:
        import mfdesign.physics.solve  # noqa: F401
    except ImportError as err:  # a broken install: say so rather than fail after the search
        return False, f"the simulator cannot be imported ({err})"
    meta_path = Path(model) / "mf.json"
    if meta_path.is_file():
        try:
            meta = json.loads(meta_path.read_text())
        except (ValueError, UnicodeDecodeError):
            meta = {}
        physics = meta.get("physics", meta.get("search_physics")) if isinstance(meta, dict) else None
        if physics == "standin":
            return False, "the model was fitted with --physics standin (no simulator behind it)"
    return True, ""


def simulator_constants(model: Path, fit=None) -> tuple:
    """The constants the simulator runs at for the model in folder ``model``: a fit-mf
    model's calibrated ones (posterior median,
    :func:`~mfdesign.calibration.workflow.calibrated_sim_params`; ``fit``: that fit, already
    loaded), else the authors'. Returns ``(SimParams, description)``; the description
    (JSON-ready) says which."""
    from mfdesign.calibration.workflow import authors_sim_params, calibrated_sim_params

    fit = load_fit(model) if fit is None else fit
    if fit is None:
        return authors_sim_params()
    params, description = calibrated_sim_params(fit)
    return params, description | {"model": str(model)}


def describe_constants(description: dict) -> str:
    """``"calibrated constants (posterior median of DIR): mu 29.4 kPa, J_m 45.7"`` or the authors'."""
    which = (
        f"calibrated constants (posterior median of {description.get('model', 'the fit')})"
        if description.get("constants") == "calibrated"
        else "the authors' constants"
    )
    others = ", ".join(
        f"{k} {v:.4g}" for k, v in description.items() if k not in ("constants", "rule", "model", "mu_pa", "jm")
    )
    if "mu_pa" not in description or "jm" not in description:
        return which
    return f"{which}: mu {description['mu_pa'] / 1e3:.4g} kPa, J_m {description['jm']:.4g}" + (
        f", {others}" if others else ""
    )


def _echo_check(sim: dict) -> None:
    pairs = ", ".join(
        f"{'-' if s is None else f'{s:.1f}'} vs {m:.1f}" for s, m in zip(sim["h_sim_mm"], sim["h_model_mm"])
    )
    mae = "n/a" if sim["mae_mm"] is None else f"{sim['mae_mm']:.2f} mm"
    typer.echo(
        f"simulator check (simulated vs model height, mm): {pairs}; MAE {mae}; status {', '.join(sim['status'])}"
    )


def register(app: typer.Typer) -> None:
    @app.command()
    def optimize(
        model: Path = typer.Option(
            ..., help="Folder of a fitted model (`mfdesign fit` or `mfdesign fit-mf ... --out DIR`)."
        ),
        out: Path = typer.Option(..., help="Output folder: optimize.json and optimize.png."),
        targets: Path = typer.Option(None, help="CSV/JSON: force_n, pressure_pa[, height_mm, weight]."),
        target_set: str = typer.Option(None, help="The paper's height-maximisation set: A or B."),
        rings: list[int] = typer.Option(
            [0, 1, 2], parser=item_parser(int, "a ring count"), help="Ring counts to try (repeat): 0, 1, 2."
        ),
        starts: int = typer.Option(2500, min=1, help="Sobol starts per ring count (scipy.stats.qmc)."),
        refine: int = typer.Option(64, min=0, help="Starts refined by gradient steps (0 = all)."),
        steps: int = typer.Option(100, "--opt-steps", min=0, help="Projected Adam steps per refined start."),
        seed: int = typer.Option(0, help="Random seed of the starts."),
        check: Optional[bool] = typer.Option(
            None,
            "--check/--no-check",
            help="Check the winner with the simulator (minutes). Default: check when the exact simulator can serve the model.",
        ),
        thickness_mm: Optional[tuple[float, float]] = THICKNESS,
        contact_radius_mm: Optional[tuple[float, float]] = CONTACT_RADIUS,
        half_width_mm: Optional[tuple[float, float]] = HALF_WIDTH,
        allow_outside_design_space: bool = ALLOW_OUTSIDE,
        tie_tol: float = typer.Option(
            0.02, help="Report other designs within this fraction of the best loss as alternatives."
        ),
    ) -> None:
        """Optimise a membrane: height maximisation or trajectory targeting; JSON + PNG."""
        from mfdesign.cli._app import fail

        if (targets is None) == (target_set is None):
            fail("give exactly one of --targets FILE or --target-set A|B")
        ring_list = tuple(dict.fromkeys(rings))
        bad_rings = [n for n in ring_list if n not in (0, 1, 2)]
        if not ring_list or bad_rings:
            fail(
                f"--rings must be 0, 1 or 2 (repeat the option for several), got {bad_rings[0] if bad_rings else 'none'}"
            )
        if refine > starts:
            fail(f"--refine ({refine}) cannot exceed --starts ({starts})")
        if not (tie_tol >= 0 and tie_tol < float("inf")):
            fail(f"--tie-tol must be a finite number >= 0, got {tie_tol}")
        space = design_space(thickness_mm, contact_radius_mm, half_width_mm, allow_outside_design_space)
        from mfdesign.optimize import TARGET_SETS, optimize, plot

        if target_set is not None:
            if target_set.upper() not in TARGET_SETS:
                fail(f"--target-set must be one of {sorted(TARGET_SETS)}, got {target_set!r}")
            problem = TARGET_SETS[target_set.upper()]
        else:
            try:
                problem = read_targets(targets)
            except ValueError as err:
                fail(str(err))
        try:
            fit = load_fit(model)
            predictor = load_model(model, fit)
        except ValueError as err:
            fail(str(err))
        available, why_not = simulator_for_check(model)
        check = available if check is None else check
        # The check runs the simulator at the constants the model stands for: a fit-mf
        # model's calibrated ones, not the authors' (their heights differ by mm).
        sim_params, constants = simulator_constants(model, fit) if check else (None, None)
        result = optimize(
            predictor,
            problem,
            rings=ring_list,
            space=space,
            n_starts=starts,
            steps=steps,
            n_refine=refine or None,
            seed=seed,
            check=check,
            sim_params=sim_params,
            sim_constants=constants,
            tie_tol=tie_tol,
        )
        out.mkdir(parents=True, exist_ok=True)
        from mfdesign import outputs

        outputs.write_json(out / "optimize.json", result.to_json())
        plot(result, out / "optimize.png")
        p = result.prediction
        what = (
            f"smooth-min height {p['score_mm']:.1f} mm (min {p['min_h_mm']:.1f} mm)"
            if result.problem == "height"
            else f"scaled trajectory RMSE {p['traj_rmse']:.3f}"
        )
        typer.echo(f"{result.design_key}: {what}; wrote {out / 'optimize.json'} and {out / 'optimize.png'}")
        for flag in result.limits:
            typer.echo(f"limit: {flag}")
        for alt in result.alternatives:
            typer.echo(
                f"alternative: {alt['design_key']} ({alt['n_rings']} ring(s)), loss {alt['loss']:.4g}, "
                f"{alt['gap_pct']:.2g} % from the best"
            )
        if result.simulator is not None:
            _echo_check(result.simulator)
            typer.echo(f"simulator check at {describe_constants(result.simulator['constants'])}")
        else:
            typer.echo(f"simulator check: not run ({why_not or 'asked with --no-check'})")
