"""``mfdesign simulate``: one membrane's force plane (Parquet + PNG + JSON)."""

from __future__ import annotations

import json
from pathlib import Path

import typer

from mfdesign.cli._app import ALLOW_OUTSIDE, fail


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
        from mfdesign.design import DesignError, Membrane, check_design_space
        from mfdesign.physics.params import SimParams
        from mfdesign.cli._plane import simulate_plane, write_plane

        defaults = SimParams()
        mu_pa = defaults.mu_pa if mu_pa is None else mu_pa
        jm = defaults.jm if jm is None else jm
        try:
            membrane = Membrane.from_key(design)
            widened = check_design_space(membrane, allow_outside_design_space)
        except DesignError as err:
            fail(f"bad design {design!r}: {err}")
        for name, value, lo in (
            ("h-max-mm", h_max_mm, 0.0),
            ("p-max-pa", p_max_pa, 0.0),
            ("mu-pa", mu_pa, 0.0),
            ("jm", jm, 0.0),
        ):
            if not (value > lo and value < float("inf")):
                fail(f"--{name} must be a positive finite number, got {value}")
        params = SimParams(mu_pa=mu_pa, jm=jm)
        table = simulate_plane(membrane, h_max_mm, p_max_pa, n_heights, n_pressures, params, progress=True)
        note = (
            {"design_space": "widened (--allow-outside-design-space): outside the product's membranes"}
            if widened
            else {}
        )
        paths = write_plane(table, membrane, out, extra=note)
        if widened:
            typer.echo(
                f"warning: {membrane.key()} is outside the product's design space (widened on request)", err=True
            )
        typer.echo(json.dumps({k: str(v) for k, v in paths.items()}))
