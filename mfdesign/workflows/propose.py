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

Every membrane to fabricate is checked before it is shown (:func:`check_fabricate`): the
simulator, at the same constants, solves its force on the acquisition grid (one batched
:func:`mfdesign.sim_runs.make` call over the membranes, seconds), and ``proposal.json``
records per membrane the simulator's forces, the model's predicted curve and the model's
error there (RMS and max, N) beside its predicted spread; a membrane the simulator cannot
check says why (``why_not_checked``). Where the error exceeds the predicted spread, a
banner heads the console summary, ``proposal.json`` (``banners``) and ``proposal.png``.
"""

from __future__ import annotations

import math
import sys
import time
from dataclasses import dataclass, field
from pathlib import Path
from typing import Any, Sequence

from mfdesign.errors import InputError

__all__ = ["ProposeResult", "banners", "check_fabricate", "make_sim_runs", "plot_proposal", "propose"]


def plot_proposal(
    proposal: Any, path: Path, space: Any = None, checks: dict | None = None, banners: Sequence[str] = ()
) -> Path:
    """PNG: left, the designs in the (thickness, contact radius) plane of the design space;
    middle, each design's radial layout (disk, rings, clamp at 70 mm) with fidelity, score
    and, for a membrane to fabricate, its simulator check beside the model's spread; right
    (when a membrane was checked), force vs plate height at the grid's top pressure: the
    model's predicted curve (line, band: +-1 member std) and the simulator's (dots); the
    banners in red at the top.

    Arguments:
        proposal: the :class:`mfdesign.acquire.Proposal` to draw.
        path: the PNG file to write (atomically).
        space: the design space searched (None: the product's), drawn as a dashed box.
        checks: per rank, the membranes' simulator checks (:func:`check_fabricate`).
        banners: the proposal's limits (:func:`banners`), one line each.
    """
    import textwrap

    import matplotlib

    matplotlib.use("Agg")
    import matplotlib.pyplot as plt

    from mfdesign.design import DesignSpace

    space = space or DesignSpace()
    checks = checks or {}
    checked = [(r, checks[r.rank]) for r in proposal.fabricate if checks.get(r.rank, {}).get("checked")]
    text = [line for b in banners for line in textwrap.wrap(b, 150)]
    height = 0.9 * len(proposal.designs) + 3.2 + 0.15 * len(text)
    widths = [1.0, 1.0] + ([1.0] if checked else [])
    fig, axes = plt.subplots(1, len(widths), figsize=(5.5 * len(widths), height))
    ax0, ax1 = axes[0], axes[1]
    (t0, t1), (c0, c1) = space.thickness_mm, space.contact_radius_mm
    ax0.add_patch(plt.Rectangle((t0, c0), t1 - t0, c1 - c0, fill=False, ls="--", color="gray"))
    markers = {"rig": "s", "sim": "o"}
    rank_of = {r.design.key(): r.rank for r in proposal.fabricate}
    for j, (d, f) in enumerate(zip(proposal.designs, proposal.fidelities)):
        ax0.scatter(
            d.thickness_mm,
            d.contact_radius_mm,
            marker=markers.get(f, "^"),
            s=80,
            zorder=3,
            color=f"C{j}",
            label=f"{j + 1}: {f}, {d.n_rings} ring(s)",
        )
        ax0.annotate(str(j + 1), (d.thickness_mm, d.contact_radius_mm), textcoords="offset points", xytext=(6, 4))
        y = len(proposal.designs) - j
        ax1.barh(y, d.contact_radius_mm, color="dimgray", height=0.5)
        for r in d.rings:
            ax1.barh(y, 2 * r.half_width_mm, left=r.inner_mm, color="tab:orange", height=0.5)
        check = checks.get(rank_of.get(d.key()), {}) if f == "rig" else {}
        label = f"{f}  t={d.thickness_mm:.2f} mm  score {proposal.scores[j]:.3g}"
        if check.get("checked"):
            label += f"\nsimulator check: {check['rmse_n']:.2g} N RMS off, spread {check['predicted_std_n']:.2g} N"
        elif check:
            label += "\nnot checked by the simulator"
        colour = "tab:red" if check.get("understated") or (check and not check.get("checked")) else "k"
        ax1.text(d.outer_radius_mm + 1, y, label, va="center", fontsize=8, color=colour)
    ax0.set_xlim(t0 - 0.2, t1 + 0.2)
    ax0.set_ylim(c0 - 1.5, c1 + 1.5)
    ax0.set_xlabel("thickness t [mm]")
    ax0.set_ylabel("contact radius c [mm]")
    ax0.legend(fontsize=8)
    ax1.axvline(70.0, color="k", lw=2)
    ax1.set_xlim(0, 130)
    ax1.set_yticks(range(1, len(proposal.designs) + 1))
    ax1.set_yticklabels([str(len(proposal.designs) - k + 1) for k in range(1, len(proposal.designs) + 1)])
    ax1.set_xlabel("radius [mm] (gray: disk, orange: rings, black: clamp)")
    if checked:
        _plot_checks(axes[2], proposal, checked)
    fig.suptitle(
        f"proposal: utility {proposal.utility:.3g} N, cost {proposal.cost:g}, score {proposal.score:.3g} N/cost",
        y=0.995,
        va="top",
    )
    top = 1.0 - (0.3 + 0.15 * len(text)) / height
    if text:
        fig.text(0.5, 1.0 - 0.28 / height, "\n".join(text), ha="center", va="top", fontsize=8, color="tab:red")
    fig.tight_layout(rect=(0, 0, 1, top))
    path = Path(path)
    from mfdesign import outputs

    outputs.savefig(fig, path, dpi=110)
    plt.close(fig)
    return path


def _plot_checks(ax: Any, proposal: Any, checked: list) -> None:
    """The checked membranes' force vs plate height at the grid's top pressure: the model's
    predicted curve of the compared fidelity (line, +-1 member std band) and the simulator's
    (dots), colour by design as in the other panels."""
    import numpy as np

    p_top = max(checked[0][1]["p_pa"])
    for r, c in checked:
        j = next(k for k, d in enumerate(proposal.designs) if d.key() == r.design.key())
        at = np.asarray(c["p_pa"]) == p_top
        h = np.asarray(c["h_mm"])[at]
        model = np.asarray(c["model_n"], float)[at]
        std = np.asarray(c["model_std_n"], float)[at]
        sim = np.asarray([np.nan if v is None else v for v in c["simulator_n"]], float)[at]
        ax.plot(h, model, color=f"C{j}", label=f"{j + 1}: model ({c['compared_fidelity']} fidelity)")
        ax.fill_between(h, model - std, model + std, color=f"C{j}", alpha=0.2, lw=0)
        ax.plot(h, sim, "o", color=f"C{j}", mec="k", ms=4, label=f"{j + 1}: simulator, {c['rmse_n']:.2g} N RMS off")
    ax.set_xlabel("plate height [mm]")
    ax.set_ylabel("force [N]")
    ax.set_title(f"membranes to fabricate, checked at {p_top / 1e3:g} kPa (band: model spread)", fontsize=9)
    ax.legend(fontsize=7)


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


# The text proposal.json and the console give for what the check compares.
_COMPARED = {
    "sim": "the model's simulator part (sim fidelity: its emulator or sim ensemble, no sim-to-real discrepancy)",
    "rig": (
        "the model's rig prediction (the model has no separate simulator part: the difference includes "
        "any sim-to-real discrepancy it learned)"
    ),
}


def _finite(values) -> list:
    return [None if not math.isfinite(v) else float(v) for v in map(float, values)]


def check_fabricate(
    proposal: Any, predictor: Any, model: Path, fit: Any, simulate: bool = True, grid: Any = None
) -> tuple[dict, dict]:
    """Check the predicted curve of every membrane to fabricate with the simulator: its force
    at the model's constants (:func:`~mfdesign.workflows.models.simulator_constants`) on the
    acquisition grid, all membranes in one batched :func:`mfdesign.sim_runs.make` call.

    Arguments:
        proposal: the :class:`mfdesign.acquire.Proposal` whose ``fabricate`` runs to check.
        predictor: the model that proposed them.
        model: the model folder (which constants; whether a simulator stands behind it,
            :func:`~mfdesign.workflows.models.simulator_for_check`).
        fit: its multi-fidelity fit (:func:`~mfdesign.workflows.models.load_fit`), or None.
        simulate: run the simulator (False, ``--no-simulate``: nothing is checked).
        grid: the height x pressure grid (None: the acquisition's default
            :class:`~mfdesign.models.predictor.Grid`).

    Returns ``(checks, note)``: per rank the ``simulator_check`` entry of ``proposal.json``
    (``checked`` True: ``h_mm`` / ``p_pa`` the points, ``simulator_n`` and ``status`` the
    simulator's, ``model_n`` / ``model_std_n`` the compared fidelity's member mean and
    spread, ``prediction_rig_n`` / ``prediction_rig_std_n`` the rig curve, ``rmse_n`` /
    ``max_error_n`` = RMS / max ``|model - simulator|`` [N] over the usable points,
    ``predicted_std_n``, ``error_over_predicted``, ``understated``; ``checked`` False:
    ``why_not_checked``), and the note (constants, grid, fidelity, seconds)."""
    import numpy as np

    from mfdesign.acquire import Grid
    from mfdesign.workflows.models import describe_constants, simulator_constants, simulator_for_check

    runs = proposal.fabricate
    grid = Grid() if grid is None else grid
    if not runs:
        return {}, {}
    available, why_not = simulator_for_check(model)
    why = "--no-simulate: the simulator was not run" if not simulate else why_not
    if not simulate or not available:
        return {r.rank: {"checked": False, "why_not_checked": why} for r in runs}, {"checked": False, "why": why}
    from mfdesign import sim_runs

    params, constants = simulator_constants(model, fit)
    fidelity = "sim" if "sim" in predictor.fidelities else "rig"
    what = describe_constants(constants)
    print(f"checking {len(runs)} membrane(s) to fabricate with the simulator at {what} ...", file=sys.stderr)
    surrogate = None if fit is None else (lambda d, h, p: fit.model.force_model(d, h, p, params))
    t0 = time.perf_counter()
    done = sim_runs.make(runs, predictor, params, sim_runs.GridSpec.of(grid), fidelity=fidelity, surrogate=surrogate)
    seconds = time.perf_counter() - t0
    rows = np.stack([r.design.to_array() for r in runs])
    curves = {f: np.asarray(predictor.grid_members(f, rows, grid), float) for f in {fidelity, "rig"}}  # [M, Q, G]
    h, p = grid.points()
    checks = {}
    for j, m in enumerate(done):
        entry = {
            "checked": m.error is None and m.rmse_n is not None,
            "compared_fidelity": fidelity,
            "compared": _COMPARED[fidelity],
            "constants": constants,
            "h_mm": h.tolist(),
            "p_pa": p.tolist(),
            "simulator_n": None if m.table is None else _finite(m.table["force_n"]),
            "status": None if m.table is None else m.table["status_name"].tolist(),
            "model_n": _finite(curves[fidelity][:, j].mean(axis=0)),
            "model_std_n": _finite(curves[fidelity][:, j].std(axis=0)),
        }
        if fidelity != "rig":
            entry["prediction_rig_n"] = _finite(curves["rig"][:, j].mean(axis=0))
            entry["prediction_rig_std_n"] = _finite(curves["rig"][:, j].std(axis=0))
        run = m.to_json()
        for k in ("state", "status", "points", "usable_points", "failed_points", "seconds", "error"):
            entry["status_counts" if k == "status" else k] = run[k]
        for k in ("rmse_n", "max_error_n", "predicted_std_n", "error_over_predicted", "surrogate_rmse_n"):
            entry[k] = run[k]
        entry["understated"] = None if not entry["checked"] else bool(run["rmse_n"] > run["predicted_std_n"])
        if not entry["checked"]:
            entry["why_not_checked"] = m.taught()
        checks[m.rank] = entry
    note = {
        "checked": True,
        "constants": constants,
        "compared_fidelity": fidelity,
        "grid": {"h_mm": list(grid.h_mm), "p_pa": list(grid.p_pa)},
        "seconds": seconds,
    }
    return checks, note


def check_line(entry: dict) -> str:
    """A membrane's simulator check in one line: the model's error there (RMS, max) beside
    its predicted spread, and the grid point where they differ most (model vs simulator, N).

    Arguments:
        entry: the membrane's ``simulator_check`` entry (:func:`check_fabricate`)."""
    if not entry.get("checked"):
        return f"simulator check: none ({entry.get('why_not_checked', 'no reason recorded')})"
    sim, mod = entry["simulator_n"], entry["model_n"]
    gaps = [abs(a - b) if a is not None and b is not None else -1.0 for a, b in zip(mod, sim)]
    k = max(range(len(gaps)), key=gaps.__getitem__)
    ratio = entry["error_over_predicted"]
    times = "" if ratio is None else f" ({ratio:.2g}x)"
    return (
        f"simulator check ({entry['compared_fidelity']} fidelity vs simulator, {entry['usable_points']} of "
        f"{entry['points']} points): error {entry['rmse_n']:.3g} N RMS, max {entry['max_error_n']:.3g} N, "
        f"predicted spread {entry['predicted_std_n']:.3g} N RMS{times}; largest at {entry['h_mm'][k]:g} mm, "
        f"{entry['p_pa'][k] / 1e3:g} kPa: model {mod[k]:.3g} N, simulator {sim[k]:.3g} N"
    )


def banners(checks: dict, made: dict | None = None) -> list[str]:
    """The limits of what the proposal shows, one line each: membranes (and made simulator
    runs) where the model's error against the simulator exceeds its predicted spread (the
    understated-spread case), and membranes the simulator could not check.

    Arguments:
        checks: per rank, the membranes' ``simulator_check`` entries (:func:`check_fabricate`).
        made: per rank, the made simulator runs (:func:`make_sim_runs`)."""
    off = [
        f"{rank} ({e['rmse_n']:.3g} N RMS vs {e['predicted_std_n']:.3g} N"
        + ("" if e["error_over_predicted"] is None else f", {e['error_over_predicted']:.2g}x")
        + ")"
        for rank, e in sorted(checks.items())
        if e.get("understated")
    ]
    runs = [
        f"{rank} ({e['rmse_n']:.3g} N RMS vs {e['predicted_std_n']:.3g} N, {e['error_over_predicted']:.2g}x)"
        for rank, e in sorted((made or {}).items())
        if e.get("made") and (e.get("error_over_predicted") or 0.0) > 1.0
    ]
    out = []
    if off or runs:
        where = "; ".join(
            part
            for part in (
                off and "membrane(s) to fabricate " + ", ".join(off),
                runs and "simulator run(s) " + ", ".join(runs),
            )
            if part
        )
        out.append(
            f"the model is off the simulator by more than its predicted spread at {where}: its spread is "
            "understated there; read the simulator's numbers, not the model's"
        )
    unchecked = sorted(rank for rank, e in checks.items() if not e.get("checked"))
    if unchecked:
        why = checks[unchecked[0]].get("why_not_checked", "")
        out.append(
            f"membrane(s) to fabricate {', '.join(map(str, unchecked))} not checked by the simulator: {why}; "
            "their predicted curves are the model's word alone"
        )
    return out


@dataclass(frozen=True)
class ProposeResult:
    """What :func:`propose` chose and wrote.

    ``proposal``: the :class:`mfdesign.acquire.Proposal`; ``made``: per rank, what became
    of each simulator run (``proposal.json``'s entries); ``lines``: per rank, the console
    line of a made run; ``sim_title``: how the simulator runs are listed; ``json_path`` /
    ``png_path``: the files; ``checks``: per rank, the simulator check of each membrane to
    fabricate (:func:`check_fabricate`); ``banners``: the limits of what the proposal
    shows (:func:`banners`)."""

    proposal: Any
    json_path: Path
    png_path: Path
    sim_title: str = "simulator runs"
    made: dict = field(default_factory=dict)
    lines: dict = field(default_factory=dict)
    checks: dict = field(default_factory=dict)
    banners: tuple[str, ...] = ()

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
        """The banners first (an understated spread, an unchecked membrane); the membranes
        to fabricate and the simulator runs, ranked, each with its expected reduction [N],
        cost and reason (a membrane's simulator check, what a made run taught); the pending
        membranes; the batch's utility [N], cost and score."""
        p = self.proposal
        lines = [f"BANNER: {b}" for b in self.banners]
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
                if r.rank in self.checks:
                    lines.append(f"     {check_line(self.checks[r.rank])}")
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
    checks, check_note = check_fabricate(proposal, predictor, model, fit, simulate)
    report = proposal.to_json(made)
    for entry in report["fabricate"]:
        entry["simulator_check"] = checks[entry["rank"]]
    if proposal.fabricate:
        report["simulator_check"] = check_note
    if proposal.simulate:
        report["sim_runs"] = sim_note
    report["banners"] = banner_lines = banners(checks, made)
    from mfdesign.provenance import call_line, input_hashes, provenance

    record = provenance(call_line("mfdesign.workflows.propose.propose()"), {"seed": seed}, input_hashes([model]))
    outputs.write_json(out / "proposal.json", report | {"provenance": record})
    plot_proposal(proposal, out / "proposal.png", space, checks, banner_lines)
    paths = (out / "proposal.json", out / "proposal.png")
    return ProposeResult(proposal, *paths, sim_note["title"], made, lines, checks, tuple(banner_lines))
