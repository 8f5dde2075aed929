"""``mfdesign create``, ``ask``, ``tell`` and ``status``: a campaign's loop from the command line.

Each command parses its options, calls one method of :class:`mfdesign.campaign.Campaign`
and prints its summary; ``mfdesign fit D`` (in :mod:`.data`) refits a campaign. The
campaign folder ``D`` is made by ``create`` (:meth:`~mfdesign.campaign.Campaign.create`:
the first data, the settings, a user's effects files kept in the folder) or by ``mfdesign
demo`` (docs/campaign.md).
"""

from __future__ import annotations

import shlex
import sys
from pathlib import Path
from typing import List, Optional

import typer

from mfdesign.cli._app import SCHEDULER
from mfdesign.cli._contract import effect_name, item_parser

FOLDER = typer.Argument(..., help="The campaign's folder (holds campaign.json).")
EFFECTS = typer.Option(
    None,
    "--effects",
    parser=item_parser(effect_name, "an effect name"),
    help="Effects in force from the first round (repeat for several; a diagnosis adds what it finds).",
)
EFFECTS_MODULE = typer.Option(
    None,
    "--effects-module",
    help="Python file registering new effects (repeat for several; its code runs): copied into the campaign "
    "with its sha256 and imported again whenever the campaign is opened (docs/campaign.md).",
)
PHYSICS = typer.Option(
    "exact",
    help="exact (simulator planes of the measured membranes, cached; searches on the emulator) | emulator "
    "(neural emulator, ~1 N error) | standin (no physics; trials).",
)
QUICK = typer.Option(False, "--quick", help="Smoke-test sizes for every step (tiny chains, ensembles and searches).")


def _call() -> str:
    """The command line, for the campaign's provenance."""
    return shlex.join(["mfdesign", *sys.argv[1:]])


def create(
    folder: Path = typer.Argument(..., help="The new campaign's folder (created; no campaign in it yet)."),
    data: List[str] = typer.Argument(
        ..., help="The first measurements: Parquet/CSV file(s), rig job folder(s), or 'bundled'."
    ),
    effects: Optional[List[str]] = EFFECTS,
    effects_module: Optional[List[Path]] = EFFECTS_MODULE,
    physics: str = PHYSICS,
    quick: bool = QUICK,
    seed: int = typer.Option(0, help="The campaign's seed (every step derives its own from it)."),
) -> None:
    """Make a campaign: its first measurements, settings and your effects files (next: fit, ask, tell)."""
    from mfdesign.campaign import Campaign, Settings

    named = tuple(effects or ())
    settings = (Settings.quick if quick else Settings)(physics=physics, effects=named, seed=seed)
    made = Campaign.create(folder, data=data, settings=settings, effects_module=effects_module, call=_call())
    typer.echo(f"{made.status().summary()}\nnext: mfdesign fit {folder}")


def register(app: typer.Typer) -> None:
    app.command()(create)

    @app.command()
    def ask(
        folder: Path = FOLDER,
        q: int = typer.Option(2, help="Membranes to fabricate this round (rig runs)."),
        sim_runs: int = typer.Option(0, "--sim-runs", help="Simulator planes the tool makes now (they join the data)."),
        rings: List[int] = typer.Option(
            [0, 1, 2], parser=item_parser(int, "a ring count"), help="Ring counts to search (repeat): 0, 1, 2."
        ),
        each_ring_count: bool = typer.Option(
            False, "--each-ring-count", help="Q membranes of each ring count in --rings (one ask per ring count)."
        ),
        scheduler: Optional[str] = SCHEDULER,
    ) -> None:
        """Ask a campaign which membranes to build next (the latest round's model; pending ones count as measured)."""
        from mfdesign.campaign import Campaign

        campaign = Campaign.open(folder)
        entries = campaign.ask(q, sim_runs, n_rings=rings, each_ring_count=each_ring_count, progress=True, call=_call())
        for e in entries:
            typer.echo(f"{e.id}  {e.fidelity}  {e.design}  {e.status}: {e.reason} {e.note}".rstrip())

    @app.command()
    def tell(
        folder: Path = FOLDER,
        proposal_id: str = typer.Argument(..., help="The proposal's id, as ask printed it (p1, p2, ...)."),
        data: List[Path] = typer.Argument(..., help="Its measurements: rig job folder(s), Parquet or CSV file(s)."),
        any_design: bool = typer.Option(
            False, "--any-design", help="Take data that hold no membrane of the proposal's design key."
        ),
    ) -> None:
        """Tell a campaign the measurements of a proposal: they join its data for the next fit."""
        from mfdesign.campaign import Campaign

        entry = Campaign.open(folder).tell(proposal_id, data, check_design=not any_design, call=_call())
        typer.echo(f"{entry.id}: {entry.design} {entry.status} (source {entry.source}); next: mfdesign fit {folder}")

    @app.command()
    def status(folder: Path = FOLDER) -> None:
        """A campaign's rounds (training and held-out error), sources and proposals."""
        from mfdesign.campaign import Campaign

        typer.echo(Campaign.open(folder).status().summary())
