"""``mfdesign discriminate``: the experiments that would tell the standing hypotheses apart;
the workflow is :func:`mfdesign.workflows.discriminate.discriminate`.

    mfdesign discriminate DATA --hypotheses "fabric_inset" "fabric_inset+ring_stiffening" "none"
                          [--physics emulator|exact|standin] [--new-design KEY ...] --out DIR

Each hypothesis (effects joined by ``+``, or ``none``; ``:coupons`` after one holds the
rubber at the coupons' values) is fitted with small settings; the candidates (force
sweeps at ``--heights-mm``, lifts with ``--masses-kg``, on the measured membranes and on
each ``--new-design``) are ranked by Box & Hill's (1967) expected log Bayes factor. It
prints the ranked list with each hypothesis's predictions (90 % intervals) and writes
``OUT/discriminate.json`` and ``OUT/discriminate.png``.
"""

from __future__ import annotations

from pathlib import Path
from typing import List, Optional

import typer

from mfdesign.cli._app import SCHEDULER, show
from mfdesign.cli._contract import item_parser


def register(app: typer.Typer) -> None:
    @app.command()
    def discriminate(
        data: Path = typer.Argument(..., help="Measurements file, rig job folder, or 'mass-lift' (docs/data.md)."),
        more: Optional[List[str]] = typer.Argument(None, hidden=True, metavar=""),
        hypotheses: List[str] = typer.Option(
            ...,
            "--hypotheses",
            help='Hypotheses, two or more: the values after --hypotheses (or repeat it), e.g. "fabric_inset" '
            '"fabric_inset+ring_stiffening" "none"; NAME[m] varies per membrane; options after ":", comma-separated: '
            'a material (coupons, coupons-jm, free) and no-latents, e.g. "fabric_inset[m]+ring_stiffening:coupons,no-latents".',
        ),
        out: Path = typer.Option(Path("out/discriminate"), help="Output folder (discriminate.json, discriminate.png)."),
        physics: str = typer.Option(
            "emulator",
            help="emulator | exact | standin (the fits' and the candidates' force model; exact solves the "
            "simulator's planes of the measured and the new membranes).",
        ),
        effect_axes: str = typer.Option(
            "tensor", help="Exact physics' lattice: tensor | tensor-jm | additive (docs/physics.md)."
        ),
        new_design: List[str] = typer.Option(
            [], "--new-design", help='A membrane that could be made, "[t, c, r1, w1, r2, w2]" mm (repeat).'
        ),
        heights_mm: List[float] = typer.Option(
            [0.0, 20.0, 40.0],
            parser=item_parser(float, "a height in mm"),
            help="Plate heights of force sweeps [mm] (repeat).",
        ),
        masses_kg: List[float] = typer.Option(
            [1.5, 2.5, 4.0], parser=item_parser(float, "a mass in kg"), help="Lift masses [kg] (repeat)."
        ),
        cost_membrane: float = typer.Option(3.0, help="Cost of making a new membrane, in trials."),
        mcmc_steps: int = typer.Option(300, help="emcee steps per hypothesis (small: a ranking, not a paper)."),
        max_rows: int = typer.Option(400, help="Rows each fit's likelihood uses."),
        seed: int = typer.Option(0, help="Random seed (same seed, same ranking)."),
        top: int = typer.Option(5, help="Ranked experiments to print."),
        scheduler: Optional[str] = SCHEDULER,
    ) -> None:
        """Rank the experiments that would tell hypotheses apart (expected log Bayes factor, Box & Hill 1967)."""
        from mfdesign.workflows.discriminate import discriminate as run

        show(
            run(
                data,
                [*hypotheses, *(more or [])],
                out,
                physics=physics,
                new_designs=new_design,
                heights_mm=heights_mm,
                masses_kg=masses_kg,
                cost_membrane=cost_membrane,
                mcmc_steps=mcmc_steps,
                max_rows=max_rows,
                seed=seed,
                top=top,
                effect_axes=effect_axes,
            )
        )
