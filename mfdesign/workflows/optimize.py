"""``mfdesign optimize``: design a membrane for a lift task (:func:`optimize`; the search
itself is :func:`mfdesign.optimization.optimize`).

Targets: one of the paper's height-maximisation sets (``A`` / ``B``: the three masses at
6.9 / 8.3 kPa) or a CSV / JSON table (:func:`read_targets`) with columns ``force_n`` [N]
and ``pressure_pa`` [Pa] (height maximisation), plus ``height_mm`` [mm] (and optionally
``weight``) for trajectory targeting through way-points.

The winner is checked by the simulator by default when the exact simulator can serve the
model (:func:`~mfdesign.workflows.models.simulator_for_check`), at the constants the model
stands for (a fit-mf model's calibrated ones, else the authors':
:func:`~mfdesign.workflows.models.simulator_constants`; the output says which); the output
names the limits the winner sits on (grid tops, the rig's travel and pressure limit,
design-space bounds) and the near-ties.
"""

from __future__ import annotations

import json
from dataclasses import dataclass
from pathlib import Path
from typing import Any, Sequence

from mfdesign.errors import InputError

__all__ = ["OptimizeResult", "check_line", "optimize", "read_targets"]


def read_targets(path: Path) -> Any:
    """``HeightTargets`` or ``Waypoints`` (:mod:`mfdesign.optimization`) from a CSV / JSON file.

    Arguments:
        path: a ``.csv`` or ``.json`` table with columns ``force_n`` [N] and ``pressure_pa``
            [Pa], optionally ``height_mm`` [mm] (way-points) and ``weight``; a JSON file
            holds the rows, or an object whose ``targets`` are the rows.

    Raises ``ValueError`` (mostly :class:`~mfdesign.errors.InputError`) saying what is wrong."""
    import pandas as pd

    from mfdesign.optimization import HeightTargets, Waypoints

    path = Path(path)
    if not path.is_file():
        raise InputError(f"targets file {path} does not exist")
    try:
        if path.suffix.lower() == ".json":
            raw = json.loads(path.read_text())
            table = pd.DataFrame(raw["targets"] if isinstance(raw, dict) and "targets" in raw else raw)
        elif path.suffix.lower() == ".csv":
            table = pd.read_csv(path)
        else:
            raise InputError(f"targets file must be .csv or .json, got {path.name}")
    except (json.JSONDecodeError, pd.errors.ParserError, UnicodeDecodeError, TypeError) as err:
        raise InputError(f"cannot read targets from {path}: {err}") from None
    need = {"force_n", "pressure_pa"}
    if not need <= set(table.columns):
        raise InputError(
            f"targets need columns force_n and pressure_pa (optional height_mm, weight); "
            f"got {sorted(map(str, table.columns))}"
        )
    cols = {c: table[c].to_numpy() for c in table.columns}
    try:
        if "height_mm" in cols:
            return Waypoints(cols["force_n"], cols["pressure_pa"], cols["height_mm"], cols.get("weight"))
        return HeightTargets(cols["force_n"], cols["pressure_pa"])
    except ValueError as err:
        raise InputError(f"bad targets in {path}: {err}") from None


def _g(value) -> str:
    return "n/a" if value is None else f"{value:.4g}"


def check_line(sim: dict) -> str:
    """The simulator check in one line: simulated vs model height [mm] per target, MAE, status.

    Arguments:
        sim: the result's ``simulator`` entry (:func:`mfdesign.optimization.check_with_simulator`)."""
    pairs = ", ".join(
        f"{'-' if s is None else f'{s:.1f}'} vs {m:.1f}" for s, m in zip(sim["h_sim_mm"], sim["h_model_mm"])
    )
    mae = "n/a" if sim["mae_mm"] is None else f"{sim['mae_mm']:.2f} mm"
    return f"simulator check (simulated vs model height, mm): {pairs}; MAE {mae}; status {', '.join(sim['status'])}"


@dataclass(frozen=True)
class OptimizeResult:
    """What :func:`optimize` found and wrote.

    ``result``: the search's :class:`mfdesign.optimization.Result` (winner, prediction,
    limits, alternatives, simulator check); ``json_path`` / ``png_path``: the files;
    ``why_not_checked``: why the simulator did not check the winner ("" when it could)."""

    result: Any
    json_path: Path
    png_path: Path
    why_not_checked: str = ""

    def summary(self) -> str:
        """The winner and its score (mm or scaled RMSE), the limits it sits on, the near-ties
        and the simulator check."""
        from mfdesign.workflows.models import describe_constants

        r = self.result
        p = r.prediction
        what = (
            f"smooth-min height {p['score_mm']:.1f} mm (min {p['min_h_mm']:.1f} mm)"
            if r.problem == "height"
            else f"scaled trajectory RMSE {p['traj_rmse']:.3f}"
        )
        lines = [f"{r.design_key}: {what}; wrote {self.json_path} and {self.png_path}"]
        lines += [f"limit: {flag}" for flag in r.limits]
        lines += [
            f"alternative: {alt['design_key']} ({alt['n_rings']} ring(s)), loss {alt['loss']:.4g}, "
            f"{alt['gap_pct']:.2g} % from the best"
            for alt in r.alternatives
        ]
        if r.simulator is not None:
            lines.append(check_line(r.simulator))
            lines.append(f"simulator check at {describe_constants(r.simulator['constants'])}")
        ref = getattr(r, "simulator_refined", None)
        if ref is not None:
            lines.append(
                f"searched on the simulator near the optimum ({ref['steps']} projected-Adam steps; {ref['why']}): "
                f"{ref['design_key']}, simulator loss {_g(ref['loss_sim_start'])} -> {_g(ref['loss_sim'])}"
            )
            lines.append("  " + check_line(ref["check"]))
        else:
            lines.append(f"simulator check: not run ({self.why_not_checked or 'asked with --no-check'})")
        return "\n".join(lines)


def _problem(targets: Path | None, target_set: str | None) -> Any:
    from mfdesign.optimization import TARGET_SETS

    if target_set is not None:
        if target_set.upper() not in TARGET_SETS:
            raise InputError(f"--target-set must be one of {sorted(TARGET_SETS)}, got {target_set!r}")
        return TARGET_SETS[target_set.upper()]
    assert targets is not None
    try:
        return read_targets(targets)
    except ValueError as err:  # pandas' own (an empty file) too: bad input, one line
        raise InputError(str(err)) from None


def optimize(
    model: Path,
    out: Path,
    targets: Path | None = None,
    target_set: str | None = None,
    rings: Sequence[int] = (0, 1, 2),
    starts: int = 2500,
    refine: int = 64,
    steps: int = 100,
    seed: int = 0,
    check: bool | None = None,
    thickness_mm: tuple[float, float] | None = None,
    contact_radius_mm: tuple[float, float] | None = None,
    half_width_mm: tuple[float, float] | None = None,
    allow_outside_design_space: bool = False,
    tie_tol: float = 0.02,
    sim_refine_steps: int = 6,
) -> OptimizeResult:
    """Optimise a membrane for a lift task with a saved model; write ``optimize.json`` and
    ``optimize.png`` into ``out``.

    Arguments:
        model: folder of a fitted model (``mfdesign fit`` or ``mfdesign fit-mf``).
        out: output folder (created).
        targets: CSV / JSON targets file (:func:`read_targets`); exactly one of it and
            ``target_set``.
        target_set: the paper's height-maximisation set, ``A`` or ``B``.
        rings: ring counts to try (0, 1, 2).
        starts: Sobol starts per ring count.
        refine: starts refined by gradient steps (0: all); at most ``starts``.
        steps: projected Adam steps per refined start.
        seed: random seed of the starts.
        check: check the winner with the simulator (minutes); None: when the exact
            simulator can serve the model.
        thickness_mm, contact_radius_mm, half_width_mm: design-space bounds ``(LO, HI)``
            [mm] (:func:`mfdesign.workflows.space.design_space`); None: the product's.
        allow_outside_design_space: allow bounds up to the research range.
        tie_tol: report designs within this fraction of the best loss as alternatives.
        sim_refine_steps: with the check, where it disagrees with the model, this many
            gradient steps on the simulator itself from the winner
            (:func:`mfdesign.optimization.simulator_refine`; 0: never).

    Raises :class:`~mfdesign.errors.InputError` (one line) for bad options, targets or
    model folder."""
    from mfdesign import outputs
    from mfdesign.optimization import optimize as search, plot
    from mfdesign.workflows.models import load_fit, load_model, simulator_constants, simulator_for_check
    from mfdesign.workflows.space import design_space

    if (targets is None) == (target_set is None):
        raise InputError("give exactly one of --targets FILE or --target-set A|B")
    ring_list = tuple(dict.fromkeys(rings))
    bad_rings = [n for n in ring_list if n not in (0, 1, 2)]
    if not ring_list or bad_rings:
        got = bad_rings[0] if bad_rings else "none"
        raise InputError(f"--rings must be 0, 1 or 2 (repeat the option for several), got {got}")
    if refine > starts:
        raise InputError(f"--refine ({refine}) cannot exceed --starts ({starts})")
    if sim_refine_steps < 0:
        raise InputError(f"--sim-refine-steps must be >= 0, got {sim_refine_steps}")
    if not (tie_tol >= 0 and tie_tol < float("inf")):
        raise InputError(f"--tie-tol must be a finite number >= 0, got {tie_tol}")
    space = design_space(thickness_mm, contact_radius_mm, half_width_mm, allow_outside_design_space)
    problem = _problem(targets, target_set)
    try:
        fit = load_fit(model)
        predictor = load_model(model, fit)
    except ValueError as err:
        raise InputError(str(err)) from None
    available, why_not = simulator_for_check(model)
    check = available if check is None else check
    # The check runs the simulator at the constants the model stands for: a fit-mf
    # model's calibrated ones, not the authors' (their heights differ by mm).
    sim_params, constants = simulator_constants(model, fit) if check else (None, None)
    result = search(
        predictor,
        problem,
        rings=ring_list,
        space=space,
        n_starts=starts,
        steps=steps,
        n_refine=refine or None,
        seed=seed,
        check=check,
        sim_params=sim_params,
        sim_constants=constants,
        tie_tol=tie_tol,
        sim_refine_steps=sim_refine_steps,
    )
    out = Path(out)
    out.mkdir(parents=True, exist_ok=True)
    from mfdesign.provenance import call_line, input_hashes, provenance

    inputs = input_hashes([model] + ([targets] if targets is not None else []))
    record = provenance(call_line("mfdesign.workflows.optimize.optimize()"), {"seed": seed}, inputs)
    outputs.write_json(out / "optimize.json", result.to_json() | {"provenance": record})
    plot(result, out / "optimize.png")
    return OptimizeResult(result, out / "optimize.json", out / "optimize.png", why_not)
