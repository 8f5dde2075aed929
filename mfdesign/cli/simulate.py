"""``mfdesign simulate``: one membrane's force plane (Parquet + PNG + JSON)."""

from __future__ import annotations

from pathlib import Path

import typer

from mfdesign.cli._app import ALLOW_OUTSIDE, show


def register(app: typer.Typer) -> None:
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
        mu_pa: float = typer.Option(
            None, help="Gent shear modulus of the rubber [Pa] (default: the authors' 31.7 kPa)."
        ),
        jm: float = typer.Option(None, help="Gent locking parameter J_m of the rubber (default: the authors' 39.6)."),
        allow_outside_design_space: bool = ALLOW_OUTSIDE,
    ) -> None:
        """Simulate one membrane on a height x pressure grid: Parquet plane + PNG + JSON."""
        from mfdesign.workflows.plane import simulate as run

        show(
            run(
                design,
                out,
                h_max_mm,
                p_max_pa,
                n_heights,
                n_pressures,
                mu_pa=mu_pa,
                jm=jm,
                allow_outside_design_space=allow_outside_design_space,
            )
        )
