"""``mfdesign demo``: the main job on the embedded default (the pipeline: :mod:`mfdesign.workflows.demo`)."""

from __future__ import annotations

from pathlib import Path
from typing import Optional

import typer

from mfdesign.cli._app import SCHEDULER, fail


def register(app: typer.Typer) -> None:
    @app.command()
    def demo(
        out: Path = typer.Option(Path("out/demo"), help="Output folder (report: OUT/index.html)."),
        quick: bool = typer.Option(False, help="Shrink every stage (a smoke test of the whole loop)."),
        physics: str = typer.Option(
            "exact",
            help="Where the model meets the data: exact (simulator planes) | emulator | standin (tests: the bundled "
            "designs measured on the virtual rig over the stand-in, a world of its own).",
        ),
        seed: int = typer.Option(0, help="Random seed."),
        calibrate_plain: bool = typer.Option(
            False, help="Also calibrate the plain model (emcee + discrepancy) to show its misfit; slower."
        ),
        scheduler: Optional[str] = SCHEDULER,
    ) -> None:
        """The main job on the embedded default (no hardware, no external data).

        On the bundled virtual-rig dataset: diagnose the plain simulator and find the hidden
        effect, calibrate mu, J_m and the effect (emcee), fit the multi-fidelity model, propose the next two
        membranes with their fidelities, optimise a membrane for a lift task, and write one
        HTML report (OUT/index.html) with JSON beside it.
        """
        import dataclasses

        from mfdesign.workflows.demo import DemoSettings, run_demo

        if physics not in ("exact", "emulator", "standin"):
            fail(f"--physics must be one of ['exact', 'emulator', 'standin'], got {physics!r}")
        settings = (
            DemoSettings.quick(physics)
            if quick
            else DemoSettings(force_model=physics, search_model="standin" if physics == "standin" else "emulator")
        )
        settings = dataclasses.replace(settings, seed=seed, calibrate_plain=calibrate_plain)
        try:
            run_demo(out, settings, echo=typer.echo)
        except (ValueError, FileNotFoundError) as err:
            fail(str(err))
