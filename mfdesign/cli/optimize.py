"""``mfdesign optimize``: design a membrane for a lift task; the workflow is
:func:`mfdesign.workflows.optimize.optimize` (targets, the simulator check, what is printed).

Targets: ``--target-set A|B`` (the paper's height-maximisation sets: the three masses at
6.9 / 8.3 kPa) or ``--targets FILE``, a CSV or JSON table with columns ``force_n`` and
``pressure_pa`` (height maximisation), plus ``height_mm`` (and optionally ``weight``) for
trajectory targeting through way-points.
"""

from __future__ import annotations

from pathlib import Path
from typing import Optional

import typer

from mfdesign.cli._app import ALLOW_OUTSIDE, show
from mfdesign.cli._contract import item_parser
from mfdesign.cli._space import CONTACT_RADIUS, HALF_WIDTH, THICKNESS


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
        sim_refine_steps: int = typer.Option(
            6,
            min=0,
            help="Where the simulator's check disagrees with the model (over 2 mm): this many gradient steps "
            "on the simulator itself from the winner, checked again (0 = never; ~1-2 minutes on 2 cores).",
        ),
    ) -> None:
        """Optimise a membrane: height maximisation or trajectory targeting; JSON + PNG."""
        from mfdesign.workflows.optimize import optimize as run

        show(
            run(
                model,
                out,
                targets,
                target_set,
                rings=rings,
                starts=starts,
                refine=refine,
                steps=steps,
                seed=seed,
                check=check,
                thickness_mm=thickness_mm,
                contact_radius_mm=contact_radius_mm,
                half_width_mm=half_width_mm,
                allow_outside_design_space=allow_outside_design_space,
                tie_tol=tie_tol,
                sim_refine_steps=sim_refine_steps,
            )
        )
