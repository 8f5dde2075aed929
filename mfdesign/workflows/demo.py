"""The lab's whole loop on the bundled virtual dataset: the README's main job.

1. **data**: the bundled virtual-rig dataset (one hidden effect, see its card;
   :mod:`mfdesign.data.shipped`);
2. **diagnose** the plain simulator (the authors' constants): where it fails, which effect
   is missing, and the error with it added;
3. **calibrate** mu, J_m, every membrane's thickness and the effect(s) found with emcee on
   exact physics, **fit** the multi-fidelity model (discrepancy ensemble on the residuals);
   ``calibrate_plain`` also calibrates the plain model first, to show how it misfits;
4. **propose** the next two membranes with their fidelities (rig or simulator), and make
   the simulator runs chosen;
5. **optimise** a membrane for a lift task (the paper's height maximisation, target set A);
6. **leave a campaign** in the folder (round 0: the corrected fit);
7. **report**: one HTML page + JSON with the pictures.

Each stage writes its files as soon as it ends (``OUT/<stage>/``), so a crash loses at most
the stage it was in. ``quick=True`` shrinks every stage (CI, tutorials); the full run
targets < 10 minutes on a 2-core CPU.
"""

from __future__ import annotations

import json
import time
from dataclasses import dataclass
from pathlib import Path
from typing import TYPE_CHECKING

import numpy as np

from mfdesign import outputs  # atomic writes: a reader never sees a torn file
from mfdesign._memory import release_memory
from mfdesign.data.shipped import bundled_card_path, bundled_path, card_truths
from mfdesign.design import Membrane

if TYPE_CHECKING:
    from mfdesign.data.measurements import Measurements
    from mfdesign.models.force import ForceModel

__all__ = ["DemoSettings", "run_demo", "demo_report", "BUNDLED", "card_truths"]

BUNDLED = bundled_path()
CARD = bundled_card_path()


@dataclass(frozen=True)
class DemoSettings:
    """Sizes of every stage (defaults: the full demo)."""

    # Calibration and diagnosis run on exact physics (simulator planes of the six bundled
    # membranes, solved once and cached). emcee stops once the chain is 50 autocorrelation
    # times long (``mcmc_steps`` is the most it may take): with the centred thickness
    # latents and the two-stage independence move tau is ~8-10 steps (session 8), so
    # ~600 steps at ~0.05 s each. The ceiling is the campaign's (Settings.mcmc_steps: one
    # default for calibrate, fit-mf, the campaign and the demo; issue 41).
    mcmc_steps: int = 2000
    walkers: int = 32
    max_rows: int = 1500
    # The plain model calibrated by emcee too (its mu absorbs what the missing effect does):
    # off by default. It cost 228 of the cold demo's 715 s (issue 40: its lattice grew to
    # 36 planes, then a chain and an ensemble), and the diagnosis already shows the plain
    # simulator's misfit (before / after at the authors' constants); the page then draws the
    # plain simulator at those constants. ``mfdesign demo --calibrate-plain`` turns it on.
    calibrate_plain: bool = False
    plain_max_rows: int = 600
    # One thickness latent per membrane (the hierarchy). Off for a world whose membranes are
    # all cast alike: there the latents absorb a shared misfit membrane by membrane, and
    # nothing is left for the discrepancy to carry to the next membrane (issue 41).
    membrane_latents: bool = True
    delta_members: int = 8
    delta_steps: int = 2000
    check_top: int = 2  # effects refitted in full per diagnosis round
    # Design searches differentiate through every posterior draw at every grid point: with
    # 8 draws, 8 restarts x 3 ring counts x 10 L-BFGS steps on the 64-point grid one
    # fidelity took over 5 minutes, hence 3 restarts on a 4 x 4 grid here (the whole demo
    # aims at 5 minutes on a 2-core CPU with empty caches; measured 292 and 310 s in session 9).
    design_draws: int = 8
    propose_restarts: int = 3
    propose_steps: int = 10
    optimise_starts: int = 300
    optimise_refine: int = 8
    optimise_steps: int = 20
    force_model: str = "exact"  # where the model meets data: exact | emulator | standin (tests)
    search_model: str = "emulator"  # design searches (propose, optimise) over new membranes
    seed: int = 0

    @classmethod
    def quick(cls, force_model: str = "exact") -> "DemoSettings":
        search = "standin" if force_model == "standin" else "emulator"
        return cls(
            mcmc_steps=300,
            walkers=32,
            max_rows=300,
            delta_members=4,
            delta_steps=300,
            propose_restarts=2,
            propose_steps=5,
            optimise_starts=128,
            optimise_refine=4,
            optimise_steps=10,
            force_model=force_model,
            search_model=search,
        )


def _plan_name(s: DemoSettings, data_path) -> str | None:
    """The kernel plan of a default demo (``demo-full`` or ``demo-quick`` on the bundled
    data; :func:`mfdesign.physics._traces.compile_ahead`), None for any other run."""
    if Path(data_path) != BUNDLED:
        return None
    return "demo-full" if s == DemoSettings() else "demo-quick" if s == DemoSettings.quick() else None


def _short(key: str) -> str:
    """A design key for people: mm to 0.01 (the JSON keeps the full key)."""
    return "[" + ", ".join("nan" if v != v else f"{v:.2f}" for v in Membrane.from_key(key).to_array()) + "]"


def _plt():
    import matplotlib

    matplotlib.use("Agg")
    import matplotlib.pyplot as plt

    return plt


def _peak_rss_mb() -> float | None:
    """This process's peak resident set so far [MB] (``ru_maxrss``: kB on Linux, bytes on
    macOS); None where ``resource`` is missing (Windows)."""
    try:
        import resource
        import sys
    except ImportError:
        return None
    peak = resource.getrusage(resource.RUSAGE_SELF).ru_maxrss
    return round(peak / (1024.0 * 1024.0 if sys.platform == "darwin" else 1024.0), 1)


def _rss_mb() -> float | None:
    """This process's resident set now [MB] (psutil where it is installed: not one of
    mfdesign's dependencies; None without it)."""
    try:
        import psutil
    except ImportError:
        return None
    return round(psutil.Process().memory_info().rss / 2**20, 1)


class _Log:
    """Stage timer and progress lines (stderr-free: the CLI's tqdm bars sit between them).

    ``times``: wall seconds per stage (``summary.json`` ``timings_s``); ``resources``: per
    stage also the CPU seconds of this process (every thread: the plane solves and XLA run
    on threads, not child processes), the peak RSS so far and the RSS at the stage's end
    [MB] (``summary.json`` ``stage_resources``; issue 40: a stage that raises the peak is
    the one holding memory). The peak is the process's high-water mark, never reset: a
    reset (``/proc/self/clear_refs``) would also hide the true peak from ``time -v``."""

    def __init__(self, echo) -> None:
        self.echo, self.t0 = echo, time.perf_counter()
        self.times: dict[str, float] = {}
        self.cpu0 = time.process_time()
        self.resources: dict[str, dict] = {}

    def stage(self, name: str, release: bool = True):
        log = self

        class _Stage:
            def __enter__(self):
                self.t, self.cpu = time.perf_counter(), time.process_time()
                log.echo(f"[{time.perf_counter() - log.t0:6.1f} s] {name} ...")

            def __exit__(self, *exc):
                # the stage's compiled programs and freed heap go back (mfdesign._memory:
                # the demo's peak RSS was the sum of its stages' compilations, issue 40;
                # kept, the programs of every stage held 4.05 GB against 1.79 GB, warm)
                if release:
                    release_memory()
                wall = round(time.perf_counter() - self.t, 2)
                log.times[name] = wall
                log.resources[name] = {
                    "wall_s": wall,
                    "cpu_s": round(time.process_time() - self.cpu, 2),
                    "peak_rss_mb": _peak_rss_mb(),
                    "rss_end_mb": _rss_mb(),
                }
                return False

        return _Stage()


def _plane_figure(meas, fits: dict, path: Path, columns: int = 3) -> None:
    """Force vs pressure of every measured membrane at (every other of) its set heights:
    data, each model's mean and the last model's 90 % posterior-predictive band; one colour
    per plate height, with its key (a colour bar in mm).

    ``fits``: name -> :class:`~mfdesign.models.predictive.MultiFidelity` (thinned). Each
    measured membrane is predicted with its own posterior thickness (``predict``; the
    population's spread of thicknesses belongs to new membranes, and drawn here it made
    bands ten times the data). The band holds the last fit's draws (physics + discrepancy)
    plus its Gaussian observation noise ``noise_n``: where the dots leave it, the model does
    not know what it does not know."""
    import math

    from matplotlib.colors import Normalize

    plt = _plt()
    rng = np.random.default_rng(0)  # noise draws for the band only: no demo number uses them
    df = meas.df
    df = df[df["experiment"] == "force"]
    keys = list(dict.fromkeys(df["design_key"]))  # every measured membrane (docs/figures.md)
    cols = min(columns, max(len(keys), 1))
    rows = max(math.ceil(len(keys) / cols), 1)
    fig, axes = plt.subplots(
        rows, cols, figsize=(4.2 * cols + 0.8, 3.4 * rows + 0.4), squeeze=False, layout="constrained"
    )
    heights_all = df["height_set_mm"].dropna()
    norm = Normalize(float(heights_all.min()), float(heights_all.max())) if len(heights_all) else Normalize(0, 1)
    names = list(fits)
    for ax, key in zip(axes.ravel(), keys):
        sub = df[df["design_key"] == key]
        heights = sorted(sub["height_set_mm"].dropna().unique())[::2]
        for i, hs in enumerate(heights):
            s = sub[sub["height_set_mm"] == hs]
            c = plt.cm.viridis(norm(hs))
            ax.plot(s["pressure_pa"] / 1e3, s["force_n"], ".", ms=1.5, color=c, alpha=0.4)
            p = np.linspace(max(50.0, s["pressure_pa"].min()), s["pressure_pa"].max(), 40)
            design = np.tile(Membrane.from_key(key).to_array(), (p.size, 1))
            for (name, mf), ls in zip(fits.items(), ("--", "-")):
                draws = np.asarray(mf.predict(design, np.full(p.size, hs), p))
                ax.plot(p / 1e3, draws.mean(0), ls, color=c, lw=1.2, label=f"{name}" if i == 0 else None)
                if name == names[-1]:
                    y = draws[None] + mf.noise_n * rng.standard_normal((8, *draws.shape))
                    lo, hi = np.quantile(y.reshape(-1, p.size), [0.05, 0.95], axis=0)
                    ax.fill_between(
                        p / 1e3, lo, hi, color=c, alpha=0.15, lw=0, label=f"{name}: 90 % band" if i == 0 else None
                    )
        ax.set_title(_short(key) + " mm", fontsize=8)
        ax.set_xlabel("pressure [kPa]")
        ax.set_ylabel("force [N]")
    for ax in axes.ravel()[len(keys) :]:
        ax.set_axis_off()
    axes[0][0].legend(fontsize=7)
    bar = fig.colorbar(plt.cm.ScalarMappable(norm=norm, cmap="viridis"), ax=axes, shrink=0.8)
    bar.set_label("plate height [mm]")
    fig.suptitle(
        f"all {len(keys)} measured membranes: data (dots) vs model means, {names[-1]}: 90 % predictive band; "
        "every other set height shown",
        fontsize=9,
    )
    outputs.savefig(fig, path, dpi=110)
    plt.close(fig)


def _because(p: dict) -> str:
    """The one-sentence reason of a ranked run, with its expected reduction and cost."""
    if "reason" not in p:  # a summary written before runs carried reasons
        return "reason not recorded"
    return f"because it {p['reason']} (cost {p['cost']:g})"


def _run_json(run) -> dict:
    """A ranked run of a proposal for summary.json (what the report shows)."""
    return {
        "design": run.design.key(),
        "fidelity": run.fidelity,
        "rank": run.rank,
        "reduction_n": run.reduction_n,
        "cost": run.cost,
        "reason": run.reason,
    }


def _make_sim_runs(proposal, predictor, fit, out: Path) -> tuple[list[dict], list[dict]]:
    """Make the proposal's simulator runs and check its membranes to fabricate, in one batch
    at the fit's calibrated constants (one plane program for both; issue 43: a proposal's
    predicted curve is re-computed by the simulator before it is shown). Planes of the runs
    in ``out/propose/sim_runs/runK``. Returns per simulator run what it taught, and per
    membrane to fabricate its ``simulator_check`` (the model's sim fidelity against the
    simulator on the run's plane: RMS / max error beside the predicted spread)."""
    from mfdesign import sim_runs
    from mfdesign.calibration.workflow import calibrated_sim_params
    from mfdesign.workflows.plane import write_plane

    params, constants = calibrated_sim_params(fit)
    done = sim_runs.make(list(proposal.simulate) + list(proposal.fabricate), predictor, params)
    made, checks = [], []
    for i, m in enumerate(done):
        entry = m.to_json() | {"taught": m.taught(), "constants": constants}
        if i >= len(proposal.simulate):
            rmse, spread = m.rmse_n, m.predicted_std_n
            checked = m.error is None and rmse is not None
            understated = rmse is not None and bool(spread) and rmse > UNDERSTATED_SPREAD * (spread or 0.0)
            checks.append(entry | {"checked": checked, "compared_fidelity": "sim", "understated": understated})
            continue
        if m.table is not None:
            write_plane(m.table, m.design, out / "propose" / "sim_runs" / f"run{m.rank}", extra={"run": entry})
        made.append(entry)
    return made, checks


def _proposal_figure(meas, proposal, path: Path) -> None:
    plt = _plt()
    fig, ax = plt.subplots(figsize=(5.5, 4))
    for key in meas.design_keys:
        d = Membrane.from_key(key)
        ax.plot(d.contact_radius_mm, d.thickness_mm, "ko", ms=5)
    for m, fid in zip(proposal.designs, proposal.fidelities):
        ax.plot(
            m.contact_radius_mm,
            m.thickness_mm,
            "*",
            ms=14,
            color="tab:red" if fid == "rig" else "tab:blue",
            label=f"{fid}: {_short(m.key())}",
        )
    ax.set_xlabel("contact radius c [mm]")
    ax.set_ylabel("thickness t [mm]")
    ax.set_title("black: membranes measured; stars: proposed next", fontsize=9)
    ax.legend(fontsize=6, loc="best")
    fig.tight_layout()
    outputs.savefig(fig, path, dpi=110)
    plt.close(fig)


def _truth_check(post, card: dict) -> dict:
    """Each parameter with a known truth (the authors' constants, the card's hidden effect):
    its 90 % interval and whether the truth lies inside."""
    truth = card_truths(card)
    out = {}
    for name, value in truth.items():
        if name not in post.names:
            continue
        x = post.samples[:, post.names.index(name)]
        lo, hi = (float(v) for v in np.quantile(x, [0.05, 0.95]))
        out[name] = {"truth": value, "q05": lo, "q95": hi, "inside": bool(lo <= value <= hi)}
    return out


def _verdict(diag) -> str:
    """One sentence on what the diagnosis found, from every round together: the report's
    summary and its diagnosis section both print this one (a round's own verdict speaks
    only for that round: a last round that finds nothing more does not undo the first)."""
    from mfdesign.diagnosis.check import FLOOR_FACTOR  # the factor the verdicts use

    found = list(diag.found)
    b, floor = diag.before.rmse_n, diag.before.noise_floor_n
    if not found or diag.after is None:
        if floor > 0 and b <= FLOOR_FACTOR * floor:
            return f"Diagnosis: the model already fits to the noise: RMSE {b:.2f} N, noise floor {floor:.2f} N."
        return f"Diagnosis: no candidate effect explains the misfit: RMSE {b:.2f} N" + (
            f", {b / floor:.1f}x the noise floor ({floor:.2f} N)." if floor > 0 else "."
        )
    a = diag.after.rmse_n
    ratio = a / floor if floor > 0 else float("inf")
    head = f"Diagnosis: adding {', '.join(found)} brings the residual RMSE from {b:.2f} N to {a:.2f} N"
    if ratio <= FLOOR_FACTOR:
        return head + f", {ratio:.2f}x the noise floor ({floor:.2f} N): it explains the misfit."
    rest = (
        "no further candidate effect explains the rest"
        if diag.steps and diag.steps[-1]["verdict"].get("status") == "unexplained"
        else "the rest stays unexplained"
    )
    return (
        head + f", but that is still {ratio:.1f}x the noise floor ({floor:.2f} N): {', '.join(found)} "
        f"explains only part of the misfit, and {rest}."
    )


def _optimum_json(result, task: str, unchecked: str | None) -> dict:
    """The optimum as summary.json holds it: design, limits, near-ties (with their gap to the
    best loss, %), the emulator's lift heights and the simulator's check at the same loads
    (``simulator``: heights, emulator minus simulator per load, constants; None with
    ``unchecked`` saying why)."""
    pred, sim = result.prediction, result.simulator
    out = {
        "design": result.design_key,
        "task": task,
        "limits": list(result.limits),
        "alternatives": [a["design_key"] for a in result.alternatives],
        "alternatives_gap_pct": [a["gap_pct"] for a in result.alternatives],
        "tie_tol_pct": 100.0 * result.settings.get("tie_tol", 0.02),
        "force_n": list(pred.get("force_n", [])),
        "p_pa": list(pred.get("p_pa", [])),
        "h_model_mm": list(pred.get("h_mean_force_mm", [])),
        "simulator": None,
        "unchecked": unchecked,
    }
    if sim is not None:
        out["simulator"] = {
            "h_sim_mm": sim["h_sim_mm"],
            "status": sim["status"],
            # model minus simulator, the sign of "the emulator says higher than the physics"
            "model_error_mm": [None if d is None else -d for d in sim["diff_mm"]],
            "mae_mm": sim["mae_mm"],
            "constants": sim.get("constants"),
        }
    ref = getattr(result, "simulator_refined", None)
    if ref is not None:
        out["simulator_refined"] = {
            "design": ref["design_key"],
            "why": ref["why"],
            "steps": ref["steps"],
            "loss_sim_start": ref["loss_sim_start"],
            "loss_sim": ref["loss_sim"],
            "h_sim_mm": ref["check"]["h_sim_mm"],
            "status": ref["check"]["status"],
        }
    return out


def _heights(values) -> str:
    return ", ".join("beyond the grid" if v is None else f"{v:.1f}" for v in values)


def _optimum_headline(opt: dict) -> str:
    """The summary's line on the optimum: the design, the simulator's heights at it and the
    emulator's error there (or why it was not checked)."""
    head = f"Optimised for lift task {opt.get('task', 'A')}: {_short(opt['design'])}"
    sim = opt.get("simulator")
    if not sim:
        why = opt.get("unchecked") or "not run"
        return head + f"; not checked by the simulator ({why}): the heights are the model's word alone."
    errs = [e for e in sim["model_error_mm"] if e is not None]
    which = (sim.get("constants") or {}).get("constants", "the authors'")
    err = f"{min(errs):+.1f} to {max(errs):+.1f} mm" if errs else "not measurable (no load lifted within the grid)"
    line = (
        head + f"; the simulator ({which} constants) lifts the loads to {_heights(sim['h_sim_mm'])} mm; "
        f"the emulator's error there (emulator minus simulator): {err}."
    )
    ref = opt.get("simulator_refined")
    if ref:
        line += (
            f" Searched on the simulator near it ({ref['steps']} steps, as {ref['why']}): "
            f"{_short(ref['design'])} lifts them to {_heights(ref['h_sim_mm'])} mm."
        )
    return line


# A simulator run whose error is more than this many times the spread the model predicted
# there puts a banner on the report: the bands elsewhere are too narrow by about as much.
UNDERSTATED_SPREAD = 2.0


def _banners(diag, convergence: dict, optimum: dict | None = None, sim_runs=(), proposals=()) -> list[str]:
    """Warnings for the top of the report, what a reader must know before trusting any
    number below: chains that have not converged, a model (after the effects found) far
    above the noise floor, an optimum at a grid or rig limit or in a near-tie, a predicted
    spread that the simulator's own runs show to be understated, an optimum the simulator
    puts elsewhere than the emulator."""
    from mfdesign.report.diagnosis import limit_banners

    out = []
    for tag, c in convergence.items():
        if not c.get("converged"):
            why = "; ".join(c.get("problems") or []) or "see posterior.json"
            out.append(
                f"The {tag.replace('_', ' ')} model's chain has not converged ({why}): its intervals are not trustworthy."
            )
    out += limit_banners(diag)
    runs = [("the simulator run", r["design"], r) for r in sim_runs]
    runs += [
        ("the proposed membrane", p["design"], p["simulator_check"]) for p in proposals if p.get("simulator_check")
    ]
    for what, design, run in runs:
        rmse, spread = run.get("rmse_n"), run.get("predicted_std_n")
        if rmse is not None and spread and rmse > UNDERSTATED_SPREAD * spread:
            out.append(
                f"The predicted spread is understated: at {what} {_short(design)} the model is "
                f"{rmse:.3g} N RMS off the simulator against a predicted spread of {spread:.3g} N RMS "
                f"({rmse / spread:.0f}x): its bands are too narrow."
            )
    if optimum:
        task = f"lift task {optimum.get('task', 'A')}"
        limits = optimum.get("limits") or []
        if limits:
            more = f" (and {len(limits) - 1} more limit(s), listed in its section)" if len(limits) > 1 else ""
            out.append(f"The optimum for {task} sits at a limit: {limits[0]}{more}.")
        ties = optimum.get("alternatives") or []
        if ties:
            tol = optimum.get("tie_tol_pct", 2.0)
            out.append(
                f"The optimum for {task} is a near-tie: {len(ties)} other design(s) come within {tol:g} % of its "
                f"loss ({'; '.join(map(_short, ties))}): the search does not single it out."
            )
        sim = optimum.get("simulator")
        if not sim:
            out.append(
                f"The optimum for {task} is the model's answer alone: {optimum.get('unchecked') or 'not checked by the simulator'}."
            )
        else:
            errs = [abs(e) for e in sim["model_error_mm"] if e is not None]
            if len(errs) < len(sim["model_error_mm"]) or (errs and max(errs) > OPTIMUM_ERROR_MM):
                out.append(
                    f"At the optimum for {task} the simulator disagrees with the emulator the search ran on: "
                    f"simulator {_heights(sim['h_sim_mm'])} mm against the emulator's "
                    f"{_heights(optimum.get('h_model_mm') or [])} mm."
                )
    return out


# An optimum whose heights the simulator puts more than this far from the emulator's (mm)
# puts a banner on the report (the rig's height readout resolves ~1 mm).
OPTIMUM_ERROR_MM = 2.0


def _num(v: float) -> str:
    """A number for people: whole numbers from 1000 up, 4 significant digits below."""
    return f"{v:.0f}" if abs(v) >= 1000 else f"{v:.4g}"


def _shown(value, factor: float):
    """A stored number in the page's units (Pa as kPa: docs/figures.md), 4 significant digits."""
    return None if value is None else float(f"{value * factor:.4g}")


def _display_rows(rows: list[dict]) -> list[dict]:
    """Posterior rows (``summary.json``: stored units, Pa) as the page shows them: pressures
    and moduli in kPa (``3.364e+04 Pa`` read badly beside ``39.6``), other units as stored."""
    from mfdesign.calibration.plots import DISPLAY_UNITS

    out = []
    for r in rows:
        unit, factor = DISPLAY_UNITS.get(r.get("unit") or "", (r.get("unit"), 1.0))
        out.append(r | {"unit": unit} | {k: _shown(r[k], factor) for k in ("median", "q05", "q95") if k in r})
    return out


def _truth_table(check: dict, table: list[dict]) -> list[dict]:
    """``_truth_check``'s rows beside the posterior medians (``table``: the posterior rows),
    every number in the page's units (Pa as kPa), the interval in the same format as the truth."""
    from mfdesign.calibration.plots import DISPLAY_UNITS

    rows = {r["parameter"]: r for r in table}
    out = []
    for name, c in check.items():
        unit, factor = DISPLAY_UNITS.get((rows.get(name) or {}).get("unit") or "", (None, 1.0))
        if unit is None:
            unit = (rows.get(name) or {}).get("unit") or ""
        out.append(
            {
                "parameter": name,
                "unit": unit,
                "truth": _shown(c["truth"], factor),
                "median": _shown((rows.get(name) or {}).get("median"), factor),
                "90 % interval": f"{_num(c['q05'] * factor)} to {_num(c['q95'] * factor)}",
                "inside": "yes" if c["inside"] else "NO",
            }
        )
    return out


def _rule(summary: dict) -> str:
    """The convergence rule as the chains' reports state it (one rule, stated once:
    :func:`~mfdesign.calibration.posterior.convergence_rule`)."""
    from mfdesign.calibration.posterior import convergence_rule

    rules = {c.get("rule") for c in summary["convergence"].values() if c.get("rule")}
    return "Rule: " + (rules.pop() if len(rules) == 1 else convergence_rule())


def _convergence_table(convergence: dict) -> list[dict]:
    """Both chains' per-parameter rows (``summary["convergence"][tag]["parameters"]``: emcee's
    tau, ArviZ's R-hat and ESS) in one table, model first."""
    return [
        {"model": tag.replace("_", " "), **row} for tag, c in convergence.items() for row in c.get("parameters") or []
    ]


def demo_report(out: str | Path, summary: dict):
    """The demo's page (a :class:`~mfdesign.report.Report`, not yet written) from what the
    stages left in ``out``: ``summary`` (``summary.json``'s content), the diagnosis's
    ``diagnose/diagnosis.json`` and the pictures beside them. It computes nothing: every
    number on the page is one of those files' (tests/cli/test_demo.py reads them back off
    the page rendered by headless Chromium)."""
    from mfdesign.report import Report

    out = Path(out)
    diagnosis = json.loads((out / "diagnose" / "diagnosis.json").read_text())
    d = summary["diagnosis"]
    found, verdict = list(d["found"]), d["verdict"]
    post0, post1 = summary.get("posterior_plain"), summary["posterior_with_effects"]
    proposals, covered = summary["proposals"], summary["coverage_90"]
    hidden = summary.get("hidden_effect")

    def figure(path: Path, caption: str) -> list[tuple[Path, str]]:
        """A picture the stages may not have drawn (a diagnosis without a second round)."""
        return [(path, caption)] if path.is_file() else []

    rep = Report("mfdesign demo: calibrate, diagnose, add the missing effect, propose, optimise")
    rep.banners = list(summary.get("banners") or [])
    rep.summary = [
        f"{summary['rows']} rows of {summary['membranes']} membranes from {Path(summary['data']).name}.",
        verdict + (f" (Hidden truth: {hidden}.)" if hidden else ""),
        "Build next (ranked): " + "; ".join(f"{_short(p['design'])} ({p['fidelity']})" for p in proposals) + ".",
        _optimum_headline(summary["optimum"]),
    ]
    rep.add(
        "Data and model",
        [
            "Measured force against pressure, with the plain model's"
            + (" mean" if post0 is not None else " force (the simulator at the authors' constants)")
            + " and the corrected model's mean and 90 % posterior-predictive band (its draws plus observation "
            "noise)."
        ],
        images=[(out / "figures" / "planes.png", "data vs model planes")],
    )
    if post0 is not None:  # ``--calibrate-plain``
        rep.add(
            "Calibration (plain model)",
            ["Posterior of the global parameters (emcee)."],
            table=_display_rows(post0),
            images=[(out / "plain" / "corner.png", "posterior, plain model")],
        )
    rep.add(
        "Convergence of the chains: autocorrelation time (emcee), R-hat and ESS (ArviZ)",
        [
            "Per parameter: the integrated autocorrelation time tau in steps (emcee), R-hat over the walkers "
            "and the bulk / tail effective sample sizes (ArviZ, on the draws each posterior.nc holds).",
            _rule(summary),
        ]
        + [
            f"{tag.replace('_', ' ')}: {c['steps_over_tau']:.1f} tau long, acceptance {c['acceptance']:.2f}, "
            f"R-hat max {c['rhat_max']:.3f}, ESS bulk min {c['ess_bulk_min']:.0f}, tail min {c['ess_tail_min']:.0f}"
            + ("." if c["converged"] else ": NOT converged.")
            for tag, c in summary["convergence"].items()
        ],
        table=_convergence_table(summary["convergence"]),
    )
    diag_dir = out / "diagnose"
    rep.add(
        "Diagnosis: where it fails, which effect is missing",
        [w["words"] for w in diagnosis["before"]["worst_regions"]][:4] + [verdict],
        images=[
            im
            for k in ("maps_before", "parity", "breakdown")
            for im in figure(diag_dir / f"{k}.png", k.replace("_", " "))
        ],
    )
    # Every round of the forward selection: its screen and its own verdict (round 2 is
    # asked with round 1's effect already in the model).
    for i, step in enumerate(diagnosis["search"]):
        base = step.get("base_effects") or []
        rep.add(
            f"Diagnosis round {i + 1}: "
            + (f"what is missing besides {', '.join(base)}" if base else "which effect is missing"),
            [f"Round {i + 1}'s verdict: {step['verdict'].get('words', '')}"],
            table=[
                {"effect": r["effect"], "explained fraction": float(r["explained_fraction"])}
                for r in step["screen"][:6]
            ],
            images=figure(diag_dir / f"screen_{i + 1}.png", f"round {i + 1}: effect screen"),
        )
    rep.add(
        "Predictive check: are the calibrated model's intervals honest?",
        [
            "Each observed force (the rows the chain saw) against the calibrated model's replicated "
            "forces (posterior draws plus observation noise, without the discrepancy ensemble; "
            "posterior.nc). A calibrated model has a flat PIT histogram and a coverage curve on the "
            "diagonal.",
            "Share of observations inside the 90 % predictive interval: "
            + ", ".join(f"{name} {c:.2f}" for name, c in covered.items())
            + " (calibrated: 0.90).",
        ]
        # how far the sim-to-real discrepancy reaches beyond the measured membranes (new designs)
        + ([f"The multi-fidelity model's {summary['discrepancy_gate']}."] if summary.get("discrepancy_gate") else []),
        images=[(out / "figures" / "predictive_check.png", "PIT histogram and coverage curve")],
        data={"coverage_90": covered},
    )
    rep.add(
        f"After adding {', '.join(found) if found else 'nothing'}",
        ["Posterior with the effect(s)."]
        + (
            [
                f"Residual RMSE {d['rmse_before_n']:.2f} N before, {d['rmse_after_n']:.2f} N after; "
                f"noise floor {d['noise_floor_n']:.2f} N."
            ]
            if d["rmse_after_n"] is not None
            else []
        ),
        table=_display_rows(post1),
        images=(figure(diag_dir / "maps_after.png", "residual maps after") if d["rmse_after_n"] is not None else [])
        + figure(out / "with_effects" / "corner.png", "posterior with effects"),
    )
    if "truth_check" in summary:
        rep.add(
            "Truths: does the posterior find the values the data were made with?",
            [
                "The bundled data were simulated with the authors' rubber constants and the hidden effect of "
                "the data card; each truth beside the corrected model's posterior median and 90 % interval "
                "(red lines in the corner plots)."
            ],
            table=_truth_table(summary["truth_check"], post1),
        )
    sims = summary.get("simulator_runs") or []
    rep.add(
        "Next membranes to build",
        [
            "Ranked by the expected reduction of the predictive spread over the height-pressure grid, "
            "after the membranes ranked above them; each with why."
        ]
        + [
            line
            for p in proposals
            for line in (f"{_short(p['design'])}: {p['fidelity']}", _because(p))
            + (
                (f"simulator check ({p['simulator_check']['state']}): {p['simulator_check']['taught']}",)
                if p.get("simulator_check")
                else ()
            )
        ]
        + (
            ["Simulator runs the tool chose and made itself (no one builds these):"]
            + [
                f"{_short(p['design'])}: {p['fidelity']} ({_because(p)})"
                + (f"; made, {p['state']}: {p['taught']}" if p.get("made") else "; not made")
                for p in sims
            ]
            if sims
            else []
        ),
        images=[(out / "propose" / "proposal.png", "proposals in the design space")],
    )
    opt = summary["optimum"]
    ties, gaps = opt.get("alternatives") or [], opt.get("alternatives_gap_pct") or []
    rep.add(
        f"Optimised membrane for lift task {opt.get('task', 'A')}",
        [
            "The search runs on the emulator; its winner is re-computed by the simulator before it is shown. "
            "Per load: the emulator's lift height, the simulator's, and the emulator's error (emulator minus "
            "simulator).",
            _optimum_headline(opt),
        ]
        + [f"At a limit: {why}" for why in opt.get("limits") or []]
        + (
            [
                f"Near-ties (within {opt.get('tie_tol_pct', 2.0):g} % of the best loss): "
                + "; ".join(
                    _short(t) + (f" ({gaps[i]:.2g} % worse)" if i < len(gaps) else "") for i, t in enumerate(ties)
                )
            ]
            if ties
            else []
        ),
        table=_optimum_table(opt),
        images=[(out / "optimize" / "optimize.png", "predicted lift, simulator check as crosses")],
    )
    return rep


def _optimum_table(opt: dict) -> list[dict] | None:
    """Per load of the task: pressure [kPa], the emulator's and the simulator's lift height
    and the emulator's error [mm] (None for a summary written before the optimum carried them)."""
    if not opt.get("force_n"):
        return None
    sim = opt.get("simulator") or {}
    n = len(opt["force_n"])
    h_sim = sim.get("h_sim_mm") or [None] * n
    err = sim.get("model_error_mm") or [None] * n
    return [
        {
            "load [N]": f,
            "pressure [kPa]": p / 1e3,
            "emulator height [mm]": h,
            "simulator height [mm]": "not checked" if not sim else ("beyond the grid" if hs is None else hs),
            "emulator error [mm]": "" if e is None else e,
        }
        for f, p, h, hs, e in zip(opt["force_n"], opt["p_pa"], opt["h_model_mm"], h_sim, err)
    ]


@dataclass(frozen=True)
class _Run:
    """What every stage of one demo run reads: its folder, sizes, data and force model."""

    out: Path
    s: DemoSettings
    meas: "Measurements"
    force_model: "ForceModel"
    progress: bool
    truths: dict

    def fit(self, effects, tag: str, max_rows: int):
        """Calibrate (emcee) and fit the discrepancy with ``effects``; chain in ``out/tag``."""
        from mfdesign.calibration.workflow import fit_multi_fidelity
        from mfdesign.models.ensemble import EnsembleConfig

        s = self.s
        cfg = EnsembleConfig(
            n_members=s.delta_members, steps=s.delta_steps, monotone=False, chunk=min(1000, s.delta_steps)
        )
        return fit_multi_fidelity(
            self.meas,
            self.force_model,
            effects,
            n_steps=s.mcmc_steps,
            n_walkers=s.walkers,
            max_rows=max_rows,
            chain_path=self.out / tag / "chain.h5",
            ensemble_config=cfg,
            seed=s.seed,
            progress=self.progress,
            membrane_latents=s.membrane_latents,
            release_memory=True,
        )

    def write_posterior(self, fit, tag: str, max_rows: int) -> list[dict]:
        """``out/tag``: posterior.nc (``az.from_netcdf``: every walker's kept draws one
        autocorrelation time apart, and the pointwise groups on the rows the chain saw),
        then posterior.json + .npz (``Posterior.load``), written second so that its R-hat
        and ESS are those ArviZ computes on posterior.nc; the corner plot. Returns the
        summary rows (with the per-membrane thickness rows: spurious latents show there)."""
        from mfdesign.calibration.plots import corner_plot
        from mfdesign.calibration.posterior import save_inference_data

        d = self.out / tag
        d.mkdir(parents=True, exist_ok=True)
        post = fit.posterior
        save_inference_data(post, d / "posterior.nc", fit.model, self.meas, seed=self.s.seed, max_rows=max_rows)
        from mfdesign.provenance import call_line

        post.save(d / "posterior", call=call_line("run_demo()"), seeds={"seed": self.s.seed})
        keep = [i for i, n in enumerate(post.names) if not n.startswith("thickness[")]
        names = [post.names[i] for i in keep]
        corner_plot(
            post.samples[:, keep],
            names,
            d / "corner.png",
            units=[post.units[i] for i in keep],
            truths=[self.truths.get(n) for n in names] if self.truths else None,
            title="red lines: the values the data were made with" if self.truths else None,
        )
        rows = post.summary()[["parameter", "unit", "median", "q05", "q95"]].to_dict("records")
        return [{k: (round(v, 4) if isinstance(v, float) else v) for k, v in r.items()} for r in rows]


CONVERGENCE_KEYS = (
    "converged",
    "steps_over_tau",
    "tau_max",
    "acceptance",
    "problems",
    "rhat_max",
    "ess_bulk_min",
    "ess_tail_min",
    "draws_in_file",
    "rule",
)


def _convergence(fits: dict) -> dict:
    """The chains' own checks (emcee's tau, ArviZ's R-hat / ESS: posterior.json
    "convergence"), with one row per parameter for the report's convergence table."""
    from mfdesign.calibration.posterior import convergence_rows

    return {
        tag: {k: f.posterior.convergence.get(k) for k in CONVERGENCE_KEYS}
        | {"parameters": convergence_rows(f.posterior.convergence)}
        for tag, f in fits.items()
    }


def _diagnose_stage(run: _Run):
    """Diagnose the plain simulator (the authors' constants), as docs/diagnose.md does.

    Not the calibrated model at its posterior median: its per-membrane thickness latents
    soak up part of a measurement effect, and without them (diagnosis has none) the
    leftover looks like a thickness deviation (seen on the bundled data)."""
    from mfdesign.diagnosis.forward import forward_model
    from mfdesign.diagnosis.pipeline import diagnose
    from mfdesign.report.diagnosis import write_report

    s = run.s
    sim = forward_model("standin" if s.force_model == "standin" else s.force_model, run.meas, progress=run.progress)
    diag = diagnose(
        run.meas,
        sim=sim,
        model_name=f"plain simulator ({s.force_model} physics, authors' constants)",
        check_top=s.check_top,
        progress=run.progress,
    )
    from mfdesign.provenance import call_line

    write_report(diag, run.out / "diagnose", call=call_line("run_demo()"), seeds={"seed": s.seed})
    floor = diag.before.noise_floor_n
    summary = {
        "found": list(diag.found),
        "rmse_before_n": diag.before.rmse_n,
        "rmse_after_n": None if diag.after is None else diag.after.rmse_n,
        "noise_floor_n": floor,
        "after_over_floor": (None if diag.after is None or not floor > 0 else diag.after.rmse_n / floor),
        "physics": s.force_model,
    }
    return diag, summary


DEMO_GRID_MM_PA = ((0.0, 20.0, 40.0, 60.0), (2000.0, 4000.0, 6000.0, 8000.0))  # heights [mm], pressures [Pa]


def _propose_stage(run: _Run, predictor):
    """The next two membranes to build and one simulator run (``out/propose``)."""
    from mfdesign.acquire import Grid, propose

    s = run.s
    proposal = propose(
        predictor,
        budget={"rig": 2, "sim": 1},
        n_restarts=s.propose_restarts,
        n_steps=s.propose_steps,
        grid=Grid(h_mm=DEMO_GRID_MM_PA[0], p_pa=DEMO_GRID_MM_PA[1]),
        key=s.seed,
        progress=run.progress,
    )
    (run.out / "propose").mkdir(exist_ok=True)
    outputs.write_text(run.out / "propose" / "proposal.json", json.dumps(proposal.to_json(), indent=1, default=str))
    _proposal_figure(run.meas, proposal, run.out / "propose" / "proposal.png")
    return proposal


def _optimise_stage(run: _Run, predictor, fit) -> dict:
    """Optimise a membrane for lift task A. The search runs on the emulator (1-3 N off the
    simulator at lift points), so its winner is re-computed by the simulator at the
    calibrated constants before the report shows it (seconds): the headline gives the
    simulator's heights and the emulator's error there, not the emulator's word alone. A
    stand-in fit stands for no physics: checking it would compare unrelated models."""
    from mfdesign.optimization import TARGET_SETS, optimize, plot as plot_optimum

    s = run.s
    check = s.force_model != "standin"
    sim_params, sim_constants = None, None
    if check:
        from mfdesign.calibration.workflow import calibrated_sim_params

        sim_params, sim_constants = calibrated_sim_params(fit)
    result = optimize(
        predictor,
        TARGET_SETS["A"],
        n_starts=s.optimise_starts,
        n_refine=s.optimise_refine,
        steps=s.optimise_steps,
        seed=s.seed,
        progress=run.progress,
        batch_size=50,
        check=check,
        sim_params=sim_params,
        sim_constants=sim_constants,
    )
    (run.out / "optimize").mkdir(exist_ok=True)
    plot_optimum(result, run.out / "optimize" / "optimize.png", title="lift task A")
    outputs.write_text(run.out / "optimize" / "optimize.json", json.dumps(result.to_json(), indent=1, default=str))
    return _optimum_json(result, "A", None if check else "stand-in physics: no simulator behind it")


@dataclass(frozen=True)
class _AtConstants:
    """The plain simulator at the authors' constants, drawn like a fit (one draw, no noise):
    what the diagnosis calls "before", when the plain model is not calibrated."""

    force_model: "ForceModel"
    noise_n: float = 0.0

    def predict(self, design, h_mm, p_pa):
        return np.asarray(self.force_model(design, h_mm, p_pa))[None]


def _report_stage(run: _Run, summary: dict, fits: dict, diag, card: dict | None):
    """The page, rendered from the stages' JSON (summary, diagnose/diagnosis.json) and the
    pictures on disk, so that every number on the page is one a sub-report holds."""
    from mfdesign.calibration.plots import pit, pit_coverage, predictive_check_plot
    from mfdesign.calibration.posterior import load_inference_data

    fig_dir = run.out / "figures"
    fig_dir.mkdir(exist_ok=True)
    plain = (
        {"plain": fits["plain"].mf.thinned(16)}
        if "plain" in fits
        else {"plain, authors' constants": _AtConstants(run.force_model)}
    )
    _plane_figure(run.meas, plain | {"with effects": fits["with_effects"].mf.thinned(16)}, fig_dir / "planes.png")
    pits = {
        name: pit(load_inference_data(run.out / tag))
        for name, tag in (("plain", "plain"), ("with effects", "with_effects"))
        if (run.out / tag / "posterior.nc").is_file()
    }
    predictive_check_plot(pits, fig_dir / "predictive_check.png")
    summary["diagnosis"]["verdict"] = _verdict(diag)
    summary["banners"] = _banners(
        diag, summary["convergence"], summary["optimum"], summary["simulator_runs"], summary.get("proposals") or []
    )
    summary["coverage_90"] = {name: pit_coverage(u)[0.9] for name, u in pits.items()}
    if card is not None:
        summary["hidden_effect"] = card["hidden_effect"]["name"]
    return demo_report(run.out, summary)


def check_campaign_folder(out: str | Path) -> None:
    """Refuse to run the demo into a campaign a lab has continued (rounds after the demo's,
    sources or proposals told): the demo would replace it. The demo's own, untouched, is
    replaced by a new run."""
    from mfdesign.campaign import Campaign
    from mfdesign.errors import InputError

    if not Campaign.holds_campaign(out):
        return
    c = Campaign.open(out)
    st = c.status()
    if len(c.rounds()) > 1 or len(st.sources) > 1 or st.proposals:
        raise InputError(
            f"--out {out} holds a campaign continued after the demo ({len(c.rounds())} round(s), "
            f"{len(st.proposals)} proposal(s)); allowed: a new --out folder (the demo would replace it)"
        )


def _leave_campaign(run: _Run, found: list[str], fit, diag):
    """Make ``out`` a campaign whose round 0 is the demo's corrected fit, so that
    ``mfdesign ask / tell / fit / status OUT`` continue it (docs/campaign.md)."""
    import shutil

    from mfdesign.campaign import CAMPAIGN_FILE, Campaign, Settings

    s = run.s
    for old in (run.out / CAMPAIGN_FILE, run.out / "sources", run.out / "rounds", run.out / "asks"):
        if old.is_dir():  # the demo's own campaign of an earlier run (check_campaign_folder)
            shutil.rmtree(old)
        elif old.exists():
            old.unlink()
    settings = Settings(
        physics=s.force_model,
        effects=tuple(found),
        mcmc_steps=s.mcmc_steps,
        walkers=s.walkers,
        max_rows=s.max_rows,
        membrane_latents=s.membrane_latents,
        members=s.delta_members,
        delta_steps=s.delta_steps,
        check_top=s.check_top,
        # the next asks search as the demo's proposal did, a little wider: the campaign's
        # defaults (1000 screened starts, 32 refined for 20 steps on the 64-point grid) held
        # an exact-physics ask of the demo's fit at 7.6 GB and over 14 minutes on 2 cores
        restarts=64,
        refine=4,
        opt_steps=s.propose_steps,
        seed=s.seed,
    )
    from mfdesign.provenance import call_line

    call = call_line("run_demo()")
    campaign = Campaign.create(run.out, data=run.meas, settings=settings, call=call)
    # the fit's posterior.nc, written by write_posterior on the same rows and seed: copied
    campaign.adopt(fit, diag, call=call, posterior_nc=run.out / "with_effects" / "posterior.nc")
    return campaign


def _standin_world(card: dict) -> "Measurements":
    """The bundled card's designs, hidden effect, noise and protocol, measured on the virtual
    rig over the stand-in plane: the world a stand-in demo lives in. The bundled data were
    made by the simulator, which the stand-in only approximates: fitted with the stand-in
    they read as a missing effect (thickness_deviation at 49x the noise floor), so the
    stand-in demo diagnosed the wrong effect and its campaign could not improve (issue 41)."""
    from mfdesign.models.standin import standin_plane
    from mfdesign.rig.virtual import VirtualRig

    rig = VirtualRig.from_card(card, simulator=standin_plane)
    return rig.run([Membrane.from_key(k) for k in card["designs"]], progress=False)


def run_demo(
    out: str | Path,
    settings: DemoSettings = DemoSettings(),
    data_path: str | Path = BUNDLED,
    echo=print,
    progress: bool = True,
) -> dict:
    """Run the whole loop (module doc) into ``out``; returns the summary written to
    ``out/summary.json`` (paths of the report, timings, headline numbers). ``out`` is left
    a campaign (round 0: the corrected fit) that ``mfdesign ask / tell / fit`` continue."""
    import dataclasses

    from mfdesign.calibration.workflow import for_search, force_model_named
    from mfdesign.data.store import read_parquet

    out = Path(out)
    out.mkdir(parents=True, exist_ok=True)
    check_campaign_folder(out)
    s, log = settings, _Log(echo)
    summary: dict = {"settings": dataclasses.asdict(s), "data": str(data_path)}
    from mfdesign.physics import _traces

    # The default demo calls the same kernels in the same order every time: its kernels
    # compile on a second thread while it works (physics._traces.compile_ahead; the plan
    # ships with the pack and is stored again at the end of each run). Where an earlier
    # run stored it, its programs are in the compilation cache already: loading them ahead
    # only slowed a warm diagnosis (20.6 -> 25.4 s, bench_demo, session 41).
    plan = _plan_name(s, data_path)
    if plan and not _traces.plan_stored(plan):
        _traces.compile_ahead(plan)
    card = json.loads(CARD.read_text()) if Path(data_path) == BUNDLED and CARD.exists() else None
    try:
        # Loading compiles only the plane solver's kernels, and the diagnosis solves planes
        # with the same ones: dropping them retraced the solver (~10 s of one core, cold).
        with log.stage("load data and force model", release=False):
            meas = read_parquet(data_path) if card is None or s.force_model != "standin" else _standin_world(card)
            if card is not None and s.force_model == "standin":
                summary["data"] = (
                    f"the bundled designs measured on the virtual rig over the stand-in ({Path(data_path).name}'s card)"
                )
            run = _Run(
                out,
                s,
                meas,
                force_model_named(s.force_model, meas, progress=progress),
                progress,
                card_truths(card) if card else {},
            )
        summary["rows"], summary["membranes"] = len(meas), len(meas.design_keys)
        fits: dict = {}
        if s.calibrate_plain:
            plain_rows = min(s.plain_max_rows, s.max_rows)
            with log.stage("calibrate mu, J_m (emcee) and fit the discrepancy: plain model"):
                fits["plain"] = run.fit((), "plain", plain_rows)
                summary["posterior_plain"] = run.write_posterior(fits["plain"], "plain", plain_rows)
        with log.stage("diagnose: where the model fails, which effect is missing"):
            diag, summary["diagnosis"] = _diagnose_stage(run)
        found = list(diag.found)
        with log.stage(f"calibrate mu, J_m{''.join(', ' + f for f in found)} (emcee) and fit the discrepancy"):
            fits["with_effects"] = run.fit(found, "with_effects", s.max_rows)
            summary["posterior_with_effects"] = run.write_posterior(fits["with_effects"], "with_effects", s.max_rows)
        fit1 = fits["with_effects"]
        summary["convergence"] = _convergence(fits)
        summary["discrepancy_gate"] = fit1.delta.describe()
        if card is not None:
            summary["truth_check"] = _truth_check(fit1.posterior, card)
        predictor = (for_search(fit1, s.search_model) if s.force_model == "exact" else fit1.mf).predictor(
            s.design_draws
        )
        with log.stage("propose 2 membranes to build and 1 simulator run"):
            proposal = _propose_stage(run, predictor)
        # membranes a person builds, ranked, each with why; simulator runs are the tool's own work
        summary["proposals"] = [_run_json(r) for r in proposal.fabricate]
        summary["simulator_runs"] = [_run_json(r) for r in proposal.simulate]
        if proposal.simulate and s.force_model != "standin":  # a stand-in's runs would teach nothing real
            with log.stage(f"make the {len(proposal.simulate)} simulator run(s) the proposal chose"):
                made, checks = _make_sim_runs(proposal, predictor, fit1, out)
                for entry, m in zip(summary["simulator_runs"], made):
                    entry.update(m)
                for entry, check in zip(summary["proposals"], checks):
                    entry["simulator_check"] = check
        with log.stage("optimise a membrane for lift task A (height maximisation), check it with the simulator"):
            summary["optimum"] = _optimise_stage(run, predictor, fit1)
        with log.stage("leave a campaign: round 0 is the corrected fit"):
            summary["campaign"] = {"folder": str(out), "round": _leave_campaign(run, found, fit1, diag).rounds()[-1]}
        with log.stage("report"):
            rep = _report_stage(run, summary, fits, diag, card)
            rep.meta = {"timings_s": log.times}
            paths = rep.write(out)
    finally:  # a failed stage leaves nothing compiling behind it
        _traces.cancel_ahead()
    if plan:
        _traces.write_plan(plan)
    summary.update(
        report=str(paths["html"]),
        json=str(paths["json"]),
        timings_s=log.times,
        stage_resources=log.resources,
        total_s=round(time.perf_counter() - log.t0, 1),
        total_cpu_s=round(time.process_time() - log.cpu0, 1),
        peak_rss_mb=_peak_rss_mb(),
        # traced programs by origin (physics._traces.COUNTS): in a cold run, "traced" counts
        # the kernels the shipped pack did not hold (stale after a code change: tools.ship_kernels)
        kernels=dict(_traces.COUNTS),
    )
    from mfdesign.provenance import call_line, input_hashes, provenance

    summary["provenance"] = provenance(call_line("run_demo()"), {"seed": s.seed}, input_hashes([data_path]))
    outputs.write_text(out / "summary.json", json.dumps(summary, indent=1, default=str))
    echo(f"report: {paths['html']} ({summary['total_s']} s)")
    echo(f"campaign: continue it with  mfdesign ask {out} --q 2   (then tell, fit, status; docs/campaign.md)")
    return summary
