"""``mfdesign propose``: the next batch of membranes to fabricate (rig) or simulate (sim)
(:func:`propose`; the acquisition itself is :func:`mfdesign.acquire.propose`).

Reads a saved model folder (:func:`mfdesign.workflows.models.load_predictor`) and writes
``proposal.json`` and ``proposal.png`` (the designs' radial layouts and their place in the
thickness / contact-radius plane). A round's budget is ``membranes`` rig runs plus
``sim_runs`` simulator planes (or ``q`` runs, a free mix of ``fidelity``); ``pending``
membranes are already being built. The simulator runs the proposal chooses are MADE
(:mod:`mfdesign.sim_runs`; ``simulate=False`` only lists them) at the model's constants (a
fit-mf model's calibrated ones, else the authors'); each plane goes into
``OUT/sim_runs/runK/`` (``plane.parquet``, ``plane.png``, ``summary.json``) and their
usable points into ``OUT/sim_runs.parquet`` (Measurements, source "simulated"). The
summary reports per run its status, time and what it taught: the model's error against
the simulator there next to the spread the acquisition predicted. A run the simulator
could not solve (``NOT_CONVERGED`` points, or an error) is reported as such, and warned of.
"""

from __future__ import annotations

import math
import sys
from dataclasses import dataclass, field
from pathlib import Path
from typing import Any, Sequence

from mfdesign.errors import InputError

__all__ = ["ProposeResult", "make_sim_runs", "plot_proposal", "propose"]


def plot_proposal(proposal: Any, path: Path, space: Any = None) -> Path:
    """PNG: left, the designs in the (thickness, contact radius) plane of the design space;
    right, each design's radial layout (disk, rings, clamp at 70 mm) with fidelity and score.

    Arguments:
        proposal: the :class:`mfdesign.acquire.Proposal` to draw.
        path: the PNG file to write (atomically).
        space: the design space searched (None: the product's), drawn as a dashed box.
    """
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


def make_sim_runs(
    proposal: Any, predictor: Any, model: Path, fit: Any, spec: Any, simulate: bool, out: Path
) -> tuple[dict, dict, dict]:
    """Make (or only list) the proposal's simulator runs; write their planes
    (``out/sim_runs/runK/``, :func:`mfdesign.workflows.plane.write_plane`) and their usable
    points (``out/sim_runs.parquet``).

    Arguments:
        proposal: the :class:`mfdesign.acquire.Proposal` whose ``simulate`` runs to make.
        predictor: the model that proposed them (its spread is what a run is compared with).
        model: the model folder (which constants the simulator runs at).
        fit: its multi-fidelity fit (:func:`mfdesign.workflows.models.load_fit`), or None.
        spec: the plane to make (:class:`mfdesign.sim_runs.PlaneSpec`: heights in mm,
            pressures in Pa).
        simulate: make the runs (False: only list them).
        out: the output folder.

    Returns the per-rank JSON entries for ``proposal.json``, one console line per rank, and
    the ``sim_runs`` note (title, constants, plane, files)."""
    import dataclasses

    from mfdesign.workflows.models import describe_constants, simulator_constants, simulator_for_check

    runs = proposal.simulate
    if not runs:
        return {}, {}, {"title": "simulator runs"}
    available, why_not = simulator_for_check(model)
    if not simulate or not available:
        why = "--no-simulate" if not simulate else why_not
        made = {r.rank: {"made": False, "why_not_made": why} for r in runs}
        return made, {}, {"title": f"simulator runs (listed, not made: {why})", "made": False, "why_not_made": why}
    from mfdesign import outputs, sim_runs
    from mfdesign.workflows.plane import write_plane
    from mfdesign.data.store import write_parquet

    params, constants = simulator_constants(model, fit)
    what = describe_constants(constants)
    print(f"making {len(runs)} simulator run(s) at {what} ...", file=sys.stderr)
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
    files: dict[str, str] = {"folder": str(out / "sim_runs")}
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


@dataclass(frozen=True)
class ProposeResult:
    """What :func:`propose` chose and wrote.

    ``proposal``: the :class:`mfdesign.acquire.Proposal`; ``made``: per rank, what became
    of each simulator run (``proposal.json``'s entries); ``lines``: per rank, the console
    line of a made run; ``sim_title``: how the simulator runs are listed; ``json_path`` /
    ``png_path``: the files."""

    proposal: Any
    json_path: Path
    png_path: Path
    sim_title: str = "simulator runs"
    made: dict = field(default_factory=dict)
    lines: dict = field(default_factory=dict)

    @property
    def warnings(self) -> tuple[str, ...]:
        """One line per simulator run made that did not converge (never silent)."""
        out = []
        for r in self.proposal.simulate:
            entry = self.made.get(r.rank, {})
            if entry.get("made") and entry.get("state") != "converged":
                out.append(f"warning: simulator run {r.rank} ({r.design.key()}): {entry['state']}, {entry['taught']}")
        return tuple(out)

    def summary(self) -> str:
        """The membranes to fabricate and the simulator runs, ranked, each with its expected
        reduction [N], cost and reason (and what a made run taught); the pending membranes;
        the batch's utility [N], cost and score."""
        p = self.proposal
        lines = []
        for title, runs in (("membranes to fabricate", p.fabricate), (self.sim_title, p.simulate)):
            if not runs:
                continue
            lines.append(f"{title}:")
            for r in runs:
                lines.append(
                    f"  {r.rank}. {r.design.key()}  expected reduction {r.reduction_rms_n:.3g} N RMS per member and grid point, cost {r.cost:g}: {r.reason}"
                )
                if r.rank in self.lines:
                    lines.append(f"     {self.lines[r.rank]}")
        if p.pending:
            lines.append(f"pending (counted as measured): {', '.join(d.key() for d in p.pending)}")
        lines.append(
            f"utility {p.utility:.4g} N, cost {p.cost:g}, score {p.score:.4g}; "
            f"wrote {self.json_path} and {self.png_path}"
        )
        return "\n".join(lines)


def _budget(
    q: int | None, membranes: int | None, sim_runs: int | None, fidelity: Sequence[str] | None
) -> tuple[int | None, dict | None, list[str]]:
    """``(q, budget, fidelities)`` from the batch options; ``InputError`` for a bad mix."""
    if membranes is None and sim_runs is None:
        q = 2 if q is None else q
        if q < 1:
            raise InputError(f"--q must be an integer >= 1, got {q}")
        return q, None, ["rig"] if fidelity is None else list(fidelity)
    if q is not None or fidelity is not None:
        raise InputError("give --q/--fidelity (a free mix) or --membranes/--sim-runs (a fixed budget), not both")
    for name, k in (("membranes", membranes), ("sim-runs", sim_runs)):
        if k is not None and k < 0:
            raise InputError(f"--{name} must be an integer >= 0, got {k}")
    budget = {"rig": membranes or 0, "sim": sim_runs or 0}
    if sum(budget.values()) < 1:
        raise InputError("the budget holds no run: give --membranes >= 1 or --sim-runs >= 1")
    return None, budget, [f for f, k in budget.items() if k > 0]


def _check_search(
    restarts: int, refine: int, steps: int, fidelity: list[str], rings: Sequence[int], costs: dict[str, float]
) -> None:
    if restarts < 1:
        raise InputError(f"--restarts must be >= 1, got {restarts}")
    if refine < 1:
        raise InputError(f"--refine must be >= 1, got {refine}")
    if steps < 0:
        raise InputError(f"--opt-steps must be >= 0, got {steps}")
    bad = [f for f in fidelity if f not in ("rig", "sim")]
    if bad:
        raise InputError(f"--fidelity must be rig or sim, got {bad[0]!r}")
    bad_rings = [n for n in rings if n not in (0, 1, 2)]
    if bad_rings:
        raise InputError(f"--rings must be 0, 1 or 2, got {bad_rings[0]}")
    for name, c in (("cost-rig", costs["rig"]), ("cost-sim", costs["sim"])):
        if not (math.isfinite(c) and c > 0):
            raise InputError(f"--{name} must be a positive finite number, got {c}")


def _plane_spec(sim_heights: int, sim_pressures: int) -> Any:
    from mfdesign.sim_runs import PlaneSpec

    try:
        return PlaneSpec(n_heights=sim_heights, n_pressures=sim_pressures)
    except ValueError as err:
        raise InputError(f"--sim-heights / --sim-pressures: {err}") from None


def _pending(keys: Sequence[str]) -> list:
    from mfdesign.design import DesignError, Membrane

    built = []
    for key in keys:
        try:
            built.append(Membrane.from_key(key))
        except DesignError as err:
            raise InputError(f"--pending {key!r}: {err}") from None
    return built


def _predictor(model: Path, fidelity: list[str], fixed_budget: bool) -> tuple[Any, Any]:
    """``(fit or None, predictor)`` of the model folder, offering every fidelity asked for."""
    from mfdesign.workflows.models import load_fit, load_predictor

    try:
        fit = load_fit(model) if Path(model).is_dir() else None
        predictor = load_predictor(model, fit)
    except (ValueError, OSError) as err:
        raise InputError(str(err)) from None
    missing = [f for f in fidelity if f not in predictor.fidelities]
    if missing:
        what = "--sim-runs" if fixed_budget else f"{missing[0]!r}"
        raise InputError(
            f"the model in {model} offers fidelities {list(predictor.fidelities)}, not {what} "
            "(the sim fidelity needs a fit-mf folder or a sim/ + discrepancy/ model folder)"
        )
    return fit, predictor


def propose(
    model: Path,
    out: Path,
    q: int | None = None,
    membranes: int | None = None,
    sim_runs: int | None = None,
    pending: Sequence[str] = (),
    fidelity: Sequence[str] | None = None,
    cost_rig: float = 1.0,
    cost_sim: float = 0.01,
    rings: Sequence[int] = (0, 1, 2),
    thickness_mm: tuple[float, float] | None = None,
    contact_radius_mm: tuple[float, float] | None = None,
    half_width_mm: tuple[float, float] | None = None,
    allow_outside_design_space: bool = False,
    restarts: int = 1000,
    refine: int = 32,
    steps: int = 20,
    seed: int = 0,
    simulate: bool = True,
    sim_heights: int = 15,
    sim_pressures: int = 17,
) -> ProposeResult:
    """Propose the next membranes to fabricate (and simulator runs to make): the largest
    expected uncertainty reduction per cost. Writes ``proposal.json``, ``proposal.png`` and
    the simulator runs (``sim_runs/``, ``sim_runs.parquet``) into ``out``.

    Arguments:
        model: model folder: ``mfdesign fit`` / ``fit-mf`` output, or sim/ + discrepancy/
            ensembles (:func:`mfdesign.workflows.models.load_predictor`).
        out: output folder (created).
        q: batch size, a free mix of ``fidelity`` (None: 2, unless a budget is given).
        membranes: budget: membranes to fabricate this round (rig runs).
        sim_runs: budget: simulator planes made this round (needs a sim fidelity).
        pending: design keys ``"[t, c, r1, w1, r2, w2]"`` (mm) of membranes already being
            built: counted as measured.
        fidelity: fidelities to choose from with ``q``: ``rig``, ``sim`` (None: rig).
        cost_rig: cost of one rig membrane (e.g. days; > 0).
        cost_sim: cost of one simulator plane, same unit (> 0).
        rings: ring counts to search (0, 1, 2).
        thickness_mm, contact_radius_mm, half_width_mm: design-space bounds ``(LO, HI)``
            [mm] (:func:`mfdesign.workflows.space.design_space`); None: the product's.
        allow_outside_design_space: allow bounds up to the research range.
        restarts: random batches scored per ring count and fidelity (>= 1).
        refine: best scored batches refined by L-BFGS (>= 1).
        steps: L-BFGS iterations per refined batch (>= 0).
        seed: random seed of the restarts.
        simulate: make the chosen simulator runs (False: only list them).
        sim_heights: heights of a made simulator plane (0-70 mm).
        sim_pressures: pressures of a made simulator plane (0-8 kPa).

    Raises :class:`~mfdesign.errors.InputError` (one line) for bad options, pending keys
    or model folder."""
    from mfdesign import outputs
    from mfdesign.acquire import propose as run_propose
    from mfdesign.workflows.space import design_space

    q, budget, fidelities = _budget(q, membranes, sim_runs, fidelity)
    costs = {"rig": cost_rig, "sim": cost_sim}
    _check_search(restarts, refine, steps, fidelities, rings, costs)
    space = design_space(thickness_mm, contact_radius_mm, half_width_mm, allow_outside_design_space)
    spec = _plane_spec(sim_heights, sim_pressures)
    built = _pending(pending)
    fit, predictor = _predictor(model, fidelities, budget is not None)
    try:
        proposal = run_propose(
            predictor,
            q,
            fidelities=tuple(fidelities),
            costs=costs,
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
        raise InputError(str(err)) from None
    out = Path(out)
    out.mkdir(parents=True, exist_ok=True)
    made, lines, sim_note = make_sim_runs(proposal, predictor, model, fit, spec, simulate, out)
    report = proposal.to_json(made)
    if proposal.simulate:
        report["sim_runs"] = sim_note
    from mfdesign.provenance import call_line, input_hashes, provenance

    record = provenance(call_line("mfdesign.workflows.propose.propose()"), {"seed": seed}, input_hashes([model]))
    outputs.write_json(out / "proposal.json", report | {"provenance": record})
    plot_proposal(proposal, out / "proposal.png", space)
    return ProposeResult(proposal, out / "proposal.json", out / "proposal.png", sim_note["title"], made, lines)
