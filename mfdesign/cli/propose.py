"""``mfdesign propose``: the next batch of membranes to fabricate (rig) or simulate (sim).

Reads a saved model folder (see :func:`load_predictor`), runs
:func:`mfdesign.acquire.propose` and writes ``proposal.json`` and ``proposal.png`` (the
designs' radial layouts and their place in the thickness / contact-radius plane). A
round's budget is ``--membranes Q --sim-runs S`` (or ``--q`` for a free mix of
``--fidelity``); ``--pending KEY`` names membranes already being built; the design-space
options narrow or fix thickness, contact radius and ring half-width. It prints the
membranes to fabricate, ranked, each with its expected reduction (N), cost and a reason,
and the simulator runs apart: the tool MAKES them (:mod:`mfdesign.sim_runs`; ``--no-simulate``
only lists them) at the model's constants (a fit-mf model's calibrated ones, else the
authors'), writes each plane to ``OUT/sim_runs/runK/`` (``plane.parquet``, ``plane.png``,
``summary.json``) and their usable points to ``OUT/sim_runs.parquet`` (Measurements, source
"simulated"), and reports per run its status, time and what it taught: the model's error
against the simulator there next to the spread the acquisition predicted. A run the
simulator could not solve (``NOT_CONVERGED`` points, or an error) is reported as such.
"""

from __future__ import annotations

import math
from pathlib import Path
from typing import Optional

import typer

from mfdesign.cli._app import ALLOW_OUTSIDE
from mfdesign.cli._contract import item_parser
from mfdesign.cli._space import CONTACT_RADIUS, HALF_WIDTH, THICKNESS, design_space


def load_predictor(model: Path, fit=None):
    """A :class:`~mfdesign.models.predictor.AbstractPredictor` from a folder.

    * ``DIR/ensemble.json`` (``mfdesign fit``): the rig-only paper case;
    * ``DIR/sim/ensemble.json`` + ``DIR/discrepancy/ensemble.json``: a
      :class:`~mfdesign.acquire.SplitPredictor` offering ``rig`` and ``sim``;
    * ``DIR/mf.json`` (``mfdesign fit-mf``): the multi-fidelity model, ``rig`` and ``sim``
      (:meth:`~mfdesign.models.predictive.MultiFidelity.predictor`, 16 posterior draws;
      ``fit``: that fit, already loaded by :func:`mfdesign.cli.optimize.load_fit`).

    Raises ``ValueError`` with what was found when the folder is neither.
    """
    from mfdesign.models.predictor import EnsemblePredictor, SplitPredictor
    from mfdesign.models.ensemble import Ensemble

    from mfdesign.models.sanity import check_predictor

    model = Path(model)
    if not model.is_dir():
        raise ValueError(f"--model {model} is not a folder (give the output folder of 'mfdesign fit')")
    if (model / "mf.json").is_file():
        from mfdesign.cli.optimize import load_fit

        return check_predictor((load_fit(model) if fit is None else fit).mf.predictor(16), str(model))
    if (model / "ensemble.json").is_file():
        return check_predictor(EnsemblePredictor(Ensemble.load(model)), str(model))
    if (model / "sim" / "ensemble.json").is_file() and (model / "discrepancy" / "ensemble.json").is_file():
        split = SplitPredictor(Ensemble.load(model / "sim"), Ensemble.load(model / "discrepancy"))
        return check_predictor(split, str(model))
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
            help="Make the chosen simulator runs and report what they taught (default), or only list them.",
        ),
        sim_heights: int = typer.Option(15, help="Heights of a made simulator plane (0-70 mm)."),
        sim_pressures: int = typer.Option(17, help="Pressures of a made simulator plane (0-8 kPa)."),
        out: Path = typer.Option(
            Path("out/propose"), help="Output folder (proposal.json, proposal.png, sim_runs/, sim_runs.parquet)."
        ),
    ) -> None:
        """Propose the next membranes to fabricate (and simulator runs to make): max uncertainty reduction per cost."""
        from mfdesign.cli._app import fail

        budget = None
        if membranes is not None or sim_runs is not None:
            if q is not None or fidelity is not None:
                fail("give --q/--fidelity (a free mix) or --membranes/--sim-runs (a fixed budget), not both")
            for name, k in (("membranes", membranes), ("sim-runs", sim_runs)):
                if k is not None and k < 0:
                    fail(f"--{name} must be an integer >= 0, got {k}")
            budget = {"rig": membranes or 0, "sim": sim_runs or 0}
            if sum(budget.values()) < 1:
                fail("the budget holds no run: give --membranes >= 1 or --sim-runs >= 1")
            fidelity = [f for f, k in budget.items() if k > 0]
        else:
            q = 2 if q is None else q
            fidelity = ["rig"] if fidelity is None else fidelity
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
        space = design_space(thickness_mm, contact_radius_mm, half_width_mm, allow_outside_design_space)
        from mfdesign.sim_runs import PlaneSpec

        try:
            spec = PlaneSpec(n_heights=sim_heights, n_pressures=sim_pressures)
        except ValueError as err:
            fail(f"--sim-heights / --sim-pressures: {err}")
        from mfdesign.design import DesignError, Membrane

        built = []
        for key in pending:
            try:
                built.append(Membrane.from_key(key))
            except DesignError as err:
                fail(f"--pending {key!r}: {err}")

        from mfdesign.acquire import propose as run_propose
        from mfdesign.cli.optimize import load_fit

        try:
            fit = load_fit(model) if Path(model).is_dir() else None
            predictor = load_predictor(model, fit)
        except (ValueError, OSError) as err:
            fail(str(err))
        missing = [f for f in fidelity if f not in predictor.fidelities]
        if missing:
            what = "--sim-runs" if budget is not None else f"{missing[0]!r}"
            fail(
                f"the model in {model} offers fidelities {list(predictor.fidelities)}, not {what} "
                "(the sim fidelity needs a fit-mf folder or a sim/ + discrepancy/ model folder)"
            )
        try:
            proposal = run_propose(
                predictor,
                q if budget is None else None,
                fidelities=tuple(fidelity),
                costs={"rig": cost_rig, "sim": cost_sim},
                n_restarts=restarts,
                n_refine=refine,
                n_rings=tuple(rings),
                n_steps=steps,
                key=seed,
                progress=True,
                space=space,
                budget=budget,
                pending=built,
            )
        except ValueError as err:
            fail(str(err))
        out.mkdir(parents=True, exist_ok=True)
        made, lines, sim_note = _make_sim_runs(proposal, predictor, model, fit, spec, simulate, out)
        from mfdesign import outputs

        report = proposal.to_json(made)
        if proposal.simulate:
            report["sim_runs"] = sim_note
        outputs.write_json(out / "proposal.json", report)
        plot_proposal(proposal, out / "proposal.png", space)
        for title, runs in (
            ("membranes to fabricate", proposal.fabricate),
            (sim_note["title"], proposal.simulate),
        ):
            if not runs:
                continue
            typer.echo(f"{title}:")
            for r in runs:
                typer.echo(
                    f"  {r.rank}. {r.design.key()}  expected reduction {r.reduction_rms_n:.3g} N RMS per member and grid point, cost {r.cost:g}: {r.reason}"
                )
                if r.rank in lines:
                    typer.echo(f"     {lines[r.rank]}")
        for r in proposal.simulate:
            entry = made.get(r.rank, {})
            if entry.get("made") and entry.get("state") != "converged":  # never silent: stderr too
                typer.echo(
                    f"warning: simulator run {r.rank} ({r.design.key()}): {entry['state']}, {entry['taught']}", err=True
                )
        if proposal.pending:
            typer.echo(f"pending (counted as measured): {', '.join(d.key() for d in proposal.pending)}")
        typer.echo(
            f"utility {proposal.utility:.4g} N, cost {proposal.cost:g}, score {proposal.score:.4g}; "
            f"wrote {out / 'proposal.json'} and {out / 'proposal.png'}"
        )


def _make_sim_runs(proposal, predictor, model: Path, fit, spec, simulate: bool, out: Path):
    """Make (or only list) the proposal's simulator runs; write their planes. Returns the
    per-rank JSON entries for ``proposal.json``, one console line per rank, and the
    ``sim_runs`` note (title, constants, plane, files)."""
    import dataclasses

    from mfdesign.cli.optimize import describe_constants, simulator_constants, simulator_for_check

    runs = proposal.simulate
    if not runs:
        return {}, {}, {"title": "simulator runs"}
    available, why_not = simulator_for_check(model)
    if not simulate or not available:
        why = "--no-simulate" if not simulate else why_not
        made = {r.rank: {"made": False, "why_not_made": why} for r in runs}
        return made, {}, {"title": f"simulator runs (listed, not made: {why})", "made": False, "why_not_made": why}
    from mfdesign import outputs, sim_runs
    from mfdesign.cli._plane import write_plane
    from mfdesign.data.store import write_parquet

    params, constants = simulator_constants(model, fit)
    what = describe_constants(constants)
    typer.echo(f"making {len(runs)} simulator run(s) at {what} ...", err=True)
    # A fit's force model (the emulator) at the runs' own constants, scored alone: its error
    # without the members' parameter and thickness spread.
    surrogate = None if fit is None else (lambda d, h, p: fit.model.force_model(d, h, p, params))
    done = sim_runs.make(runs, predictor, params, spec, surrogate=surrogate)
    made, lines = {}, {}
    for m in done:
        folder = out / "sim_runs" / f"run{m.rank}"
        entry = m.to_json() | {"design": m.design.key(), "constants": constants, "folder": str(folder)}
        if m.table is not None:
            write_plane(m.table, m.design, folder, extra={"proposal_rank": m.rank, "run": entry})
            entry["plane"] = str(folder / "plane.parquet")
        else:
            outputs.write_json(folder / "summary.json", {"design": m.design.key(), "run": entry})
        made[m.rank] = entry
        counts = ", ".join(f"{k} {v}" for k, v in m.status.items())
        lines[m.rank] = f"made: {m.state} ({counts or 'no points'}), {m.seconds:.1f} s; {m.taught()}"
    data = sim_runs.as_measurements(done)
    files = {"folder": str(out / "sim_runs")}
    if data is not None:
        files["measurements"] = str(write_parquet(data, out / "sim_runs.parquet"))
    note = {
        "title": f"simulator runs (made by the tool at {what})",
        "made": True,
        "constants": constants,
        "plane": dataclasses.asdict(spec),
        "compared_fidelity": "sim",
        **files,
    }
    return made, lines, note
