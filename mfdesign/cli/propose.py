"""``mfdesign propose``: the next batch of membranes to fabricate (rig) or simulate (sim);
the workflow is :func:`mfdesign.workflows.propose.propose`.

A round's budget is ``--membranes Q --sim-runs S`` (or ``--q`` for a free mix of
``--fidelity``); ``--pending KEY`` names membranes already being built; the design-space
options narrow or fix thickness, contact radius and ring half-width. It prints the
membranes to fabricate, ranked, each with its expected reduction (N), cost and a reason,
and its simulator check (the model's error against the simulator on the acquisition grid
beside its predicted spread; a banner where the spread is understated), and the simulator
runs apart: the tool MAKES them (``--no-simulate`` only lists them, and checks nothing) and
writes them under ``OUT/sim_runs/`` and ``OUT/sim_runs.parquet``.
"""

from __future__ import annotations

from pathlib import Path
from typing import Optional

import typer

from mfdesign.cli._app import ALLOW_OUTSIDE, SCHEDULER, show
from mfdesign.cli._contract import item_parser
from mfdesign.cli._space import CONTACT_RADIUS, HALF_WIDTH, THICKNESS


def register(app: typer.Typer) -> None:
    @app.command()
    def propose(
        model: Path = typer.Option(..., help="Model folder: 'mfdesign fit' output, or sim/ + discrepancy/ ensembles."),
        q: Optional[int] = typer.Option(
            None, help="Batch size, a free mix of --fidelity (default 2; or give --membranes / --sim-runs)."
        ),
        membranes: Optional[int] = typer.Option(
            None, "--membranes", help="Budget: membranes to fabricate this round (rig runs)."
        ),
        sim_runs: Optional[int] = typer.Option(
            None, "--sim-runs", help="Budget: simulator planes the tool makes this round (needs a sim fidelity)."
        ),
        pending: list[str] = typer.Option(
            [],
            "--pending",
            help='A membrane already being built, "[t, c, r1, w1, r2, w2]" mm (repeat): counted as measured.',
        ),
        fidelity: Optional[list[str]] = typer.Option(
            None, help="Fidelities to choose from with --q (repeat): rig, sim. Default: rig."
        ),
        cost_rig: float = typer.Option(1.0, help="Cost of one rig membrane (e.g. days)."),
        cost_sim: float = typer.Option(0.01, help="Cost of one simulator plane, same unit."),
        rings: list[int] = typer.Option(
            [0, 1, 2], parser=item_parser(int, "a ring count"), help="Ring counts to search (repeat): 0, 1, 2."
        ),
        thickness_mm: Optional[tuple[float, float]] = THICKNESS,
        contact_radius_mm: Optional[tuple[float, float]] = CONTACT_RADIUS,
        half_width_mm: Optional[tuple[float, float]] = HALF_WIDTH,
        allow_outside_design_space: bool = ALLOW_OUTSIDE,
        restarts: int = typer.Option(1000, help="Random batches scored per ring count and fidelity."),
        refine: int = typer.Option(32, help="Best scored batches refined by L-BFGS."),
        steps: int = typer.Option(20, "--opt-steps", help="L-BFGS iterations per refined batch."),
        seed: int = typer.Option(0, help="Random seed of the restarts."),
        simulate: bool = typer.Option(
            True,
            "--simulate/--no-simulate",
            help="Run the simulator: make the chosen simulator runs and check each membrane to fabricate (default), or only list them, unchecked.",
        ),
        sim_heights: int = typer.Option(15, help="Heights of a made simulator plane (0-70 mm)."),
        sim_pressures: int = typer.Option(17, help="Pressures of a made simulator plane (0-8 kPa)."),
        out: Path = typer.Option(
            Path("out/propose"), help="Output folder (proposal.json, proposal.png, sim_runs/, sim_runs.parquet)."
        ),
        scheduler: Optional[str] = SCHEDULER,
    ) -> None:
        """Propose the next membranes to fabricate (and simulator runs to make): max uncertainty reduction per cost."""
        options = dict(locals())  # every option, by name: the workflow takes them as they are
        options.pop("scheduler")  # the contract's (mfdesign.cli._app.SCHEDULER)
        from mfdesign.workflows.propose import propose as run

        show(run(**options))
