"""``mfdesign optimize``: design a membrane for a lift task (see :mod:`mfdesign.optimize`).

Targets: ``--target-set A|B`` (the paper's height-maximisation sets: the three masses at
6.9 / 8.3 kPa) or ``--targets FILE``, a CSV or JSON table with columns ``force_n`` and
``pressure_pa`` (height maximisation), plus ``height_mm`` (and optionally ``weight``) for
trajectory targeting through way-points.
"""

from __future__ import annotations

import json
from pathlib import Path

import typer

from mfdesign.cli._contract import item_parser


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


def load_model(path: Path):
    """The predictor (:class:`~mfdesign.models.predictor.AbstractPredictor`) of a saved model
    folder: the RPN ensemble of ``mfdesign fit`` (``ensemble.json``) or the multi-fidelity fit
    of ``mfdesign fit-mf`` (``mf.json``; 16 posterior draws)."""
    from mfdesign.models.ensemble import Ensemble
    from mfdesign.models.predictor import EnsemblePredictor

    path = Path(path)
    if not path.is_dir():
        raise ValueError(f"model folder {path} does not exist (fit one with `mfdesign fit` or `mfdesign fit-mf`)")
    if (path / "mf.json").is_file():
        from mfdesign.calibration.workflow import load_multi_fidelity

        return load_multi_fidelity(path).mf.predictor(16)
    try:
        return EnsemblePredictor(Ensemble.load(path))
    except (FileNotFoundError, ValueError, KeyError) as err:
        raise ValueError(f"cannot load a model from {path}: {err}") from None


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
        starts: int = typer.Option(2500, min=1, help="Random starts per ring count."),
        refine: int = typer.Option(64, min=0, help="Starts refined by gradient steps (0 = all)."),
        steps: int = typer.Option(100, "--opt-steps", min=0, help="Projected Adam steps per refined start."),
        seed: int = typer.Option(0, help="Random seed of the starts."),
        check: bool = typer.Option(True, help="Check the winner with the simulator (minutes)."),
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
            predictor = load_model(model)
        except ValueError as err:
            fail(str(err))
        result = optimize(
            predictor,
            problem,
            rings=ring_list,
            n_starts=starts,
            steps=steps,
            n_refine=refine or None,
            seed=seed,
            check=check,
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
