"""``mfdesign propose``: the next batch of membranes to fabricate (rig) or simulate (sim).

Reads a saved model folder (see :func:`load_predictor`), runs
:func:`mfdesign.acquire.propose` and writes ``proposal.json`` and ``proposal.png`` (the
designs' radial layouts and their place in the thickness / contact-radius plane).
"""

from __future__ import annotations

import math
from pathlib import Path

import typer

from mfdesign.cli._contract import item_parser


def load_predictor(model: Path):
    """A :class:`~mfdesign.models.predictor.AbstractPredictor` from a folder.

    * ``DIR/ensemble.json`` (``mfdesign fit``): the rig-only paper case;
    * ``DIR/sim/ensemble.json`` + ``DIR/discrepancy/ensemble.json``: a
      :class:`~mfdesign.acquire.SplitPredictor` offering ``rig`` and ``sim``;
    * ``DIR/mf.json`` (``mfdesign fit-mf``): the multi-fidelity model, ``rig`` and ``sim``
      (:meth:`~mfdesign.models.predictive.MultiFidelity.predictor`, 16 posterior draws).

    Raises ``ValueError`` with what was found when the folder is neither.
    """
    from mfdesign.models.predictor import EnsemblePredictor, SplitPredictor
    from mfdesign.models.ensemble import Ensemble

    model = Path(model)
    if not model.is_dir():
        raise ValueError(f"--model {model} is not a folder (give the output folder of 'mfdesign fit')")
    if (model / "mf.json").is_file():
        from mfdesign.calibration.workflow import load_multi_fidelity

        return load_multi_fidelity(model).mf.predictor(16)
    if (model / "ensemble.json").is_file():
        return EnsemblePredictor(Ensemble.load(model))
    if (model / "sim" / "ensemble.json").is_file() and (model / "discrepancy" / "ensemble.json").is_file():
        return SplitPredictor(Ensemble.load(model / "sim"), Ensemble.load(model / "discrepancy"))
    found = sorted(p.name for p in model.iterdir() if p.name != ".mfdesign.lock")[:8]
    raise ValueError(
        f"--model {model} holds no ensemble.json, mf.json, nor sim/ and discrepancy/ ensembles; found {found}"
    )


def plot_proposal(proposal, path: Path, space=None) -> Path:
    """PNG: left, the designs in the (thickness, contact radius) plane of the design space;
    right, each design's radial layout (disk, rings, clamp at 70 mm) with fidelity and score."""
    import matplotlib

    matplotlib.use("Agg")
    import matplotlib.pyplot as plt

    from mfdesign.design import DesignSpace

    space = space or DesignSpace()
    fig, (ax0, ax1) = plt.subplots(1, 2, figsize=(11, 0.9 * len(proposal.designs) + 3.2))
    (t0, t1), (c0, c1) = space.thickness_mm, space.contact_radius_mm
    ax0.add_patch(plt.Rectangle((t0, c0), t1 - t0, c1 - c0, fill=False, ls="--", color="gray"))
    markers = {"rig": "s", "sim": "o"}
    for j, (d, f) in enumerate(zip(proposal.designs, proposal.fidelities)):
        ax0.scatter(
            d.thickness_mm,
            d.contact_radius_mm,
            marker=markers.get(f, "^"),
            s=80,
            zorder=3,
            label=f"{j + 1}: {f}, {d.n_rings} ring(s)",
        )
        ax0.annotate(str(j + 1), (d.thickness_mm, d.contact_radius_mm), textcoords="offset points", xytext=(6, 4))
        y = len(proposal.designs) - j
        ax1.barh(y, d.contact_radius_mm, color="dimgray", height=0.5)
        for r in d.rings:
            ax1.barh(y, 2 * r.half_width_mm, left=r.inner_mm, color="tab:orange", height=0.5)
        ax1.text(
            d.outer_radius_mm + 1,
            y,
            f"{f}  t={d.thickness_mm:.2f} mm  score {proposal.scores[j]:.3g}",
            va="center",
            fontsize=8,
        )
    ax0.set_xlim(t0 - 0.2, t1 + 0.2)
    ax0.set_ylim(c0 - 1.5, c1 + 1.5)
    ax0.set_xlabel("thickness t [mm]")
    ax0.set_ylabel("contact radius c [mm]")
    ax0.legend(fontsize=8)
    ax1.axvline(70.0, color="k", lw=2)
    ax1.set_xlim(0, 110)
    ax1.set_yticks(range(1, len(proposal.designs) + 1))
    ax1.set_yticklabels([str(len(proposal.designs) - k + 1) for k in range(1, len(proposal.designs) + 1)])
    ax1.set_xlabel("radius [mm] (gray: disk, orange: rings, black: clamp)")
    fig.suptitle(
        f"proposal: utility {proposal.utility:.3g} N, cost {proposal.cost:g}, score {proposal.score:.3g} N/cost"
    )
    fig.tight_layout()
    path = Path(path)
    from mfdesign import outputs

    outputs.savefig(fig, path, dpi=110)
    plt.close(fig)
    return path


def register(app: typer.Typer) -> None:
    @app.command()
    def propose(
        model: Path = typer.Option(..., help="Model folder: 'mfdesign fit' output, or sim/ + discrepancy/ ensembles."),
        q: int = typer.Option(2, help="Batch size (designs to propose)."),
        fidelity: list[str] = typer.Option(["rig"], help="Fidelities to choose from (repeat): rig, sim."),
        cost_rig: float = typer.Option(1.0, help="Cost of one rig membrane (e.g. days)."),
        cost_sim: float = typer.Option(0.01, help="Cost of one simulator plane, same unit."),
        rings: list[int] = typer.Option(
            [0, 1, 2], parser=item_parser(int, "a ring count"), help="Ring counts to search (repeat): 0, 1, 2."
        ),
        restarts: int = typer.Option(1000, help="Random batches scored per ring count and fidelity."),
        refine: int = typer.Option(32, help="Best scored batches refined by L-BFGS."),
        steps: int = typer.Option(20, "--opt-steps", help="L-BFGS iterations per refined batch."),
        seed: int = typer.Option(0, help="Random seed of the restarts."),
        out: Path = typer.Option(Path("out/propose"), help="Output folder (proposal.json, proposal.png)."),
    ) -> None:
        """Propose the next q membranes: max uncertainty reduction per cost (Campbell et al. 2025 for rig only)."""
        from mfdesign.cli._app import fail

        if q < 1:
            fail(f"--q must be an integer >= 1, got {q}")
        if restarts < 1:
            fail(f"--restarts must be >= 1, got {restarts}")
        if refine < 1:
            fail(f"--refine must be >= 1, got {refine}")
        if steps < 0:
            fail(f"--opt-steps must be >= 0, got {steps}")
        bad = [f for f in fidelity if f not in ("rig", "sim")]
        if bad:
            fail(f"--fidelity must be rig or sim, got {bad[0]!r}")
        bad_rings = [n for n in rings if n not in (0, 1, 2)]
        if bad_rings:
            fail(f"--rings must be 0, 1 or 2, got {bad_rings[0]}")
        for name, c in (("cost-rig", cost_rig), ("cost-sim", cost_sim)):
            if not (math.isfinite(c) and c > 0):
                fail(f"--{name} must be a positive finite number, got {c}")

        from mfdesign.acquire import propose as run_propose

        try:
            predictor = load_predictor(model)
        except (ValueError, OSError) as err:
            fail(str(err))
        missing = [f for f in fidelity if f not in predictor.fidelities]
        if missing:
            fail(
                f"the model in {model} offers fidelities {list(predictor.fidelities)}, not {missing[0]!r} "
                "(the sim fidelity needs a fit-mf folder or a sim/ + discrepancy/ model folder)"
            )
        try:
            proposal = run_propose(
                predictor,
                q,
                fidelities=tuple(fidelity),
                costs={"rig": cost_rig, "sim": cost_sim},
                n_restarts=restarts,
                n_refine=refine,
                n_rings=tuple(rings),
                n_steps=steps,
                key=seed,
                progress=True,
            )
        except ValueError as err:
            fail(str(err))
        out.mkdir(parents=True, exist_ok=True)
        proposal.save(out / "proposal.json")
        plot_proposal(proposal, out / "proposal.png")
        for d, f, s in zip(proposal.designs, proposal.fidelities, proposal.scores):
            typer.echo(f"{f}: {d.key()}  score {s:.4g}")
        typer.echo(
            f"utility {proposal.utility:.4g} N, cost {proposal.cost:g}, score {proposal.score:.4g}; "
            f"wrote {out / 'proposal.json'} and {out / 'proposal.png'}"
        )
