"""Make the simulator runs a proposal chose, and say what each one taught.

:func:`mfdesign.acquire.propose` picks designs at the ``sim`` fidelity because the model's
simulator part is unsure there; a simulator run costs the tool seconds, so the tool makes
it instead of handing it to the lab. :func:`make` solves the chosen designs' force planes
(:func:`~mfdesign.physics.solve.force_planes`: the exact shooting simulator, each plane
``vmap``-ed over its heights, the planes spread over the cores) at the model's constants
(a fit-mf model's calibrated ones, :func:`~mfdesign.calibration.workflow.calibrated_sim_params`,
else the authors'), and compares the model's ``sim``-fidelity members with each plane:

* ``rmse_n``: the members' mean against the simulator [N RMS over the plane's usable
  points] -- the emulator's (or the simulator surrogate's) error at that design, what
  the run teaches;
* ``predicted_std_n``: the members' spread there [N RMS of the member standard deviation
  over the same points] -- the uncertainty the acquisition acted on;
* ``surrogate_rmse_n`` (when a ``surrogate`` is given, e.g. a fit-mf model's emulator at
  the same constants): the surrogate alone against the simulator [N RMS] -- its error with
  the parameter and thickness spread of the members taken out.

A point the shooting did not solve (``NOT_CONVERGED``, ``ODE_FAILURE``) is counted and
reported; a run whose simulator raised is reported as failed with the error. Nothing is
dropped silently. :func:`as_measurements` turns the usable points into the project's
Measurements (source ``"simulated"``, one force trial per run) for the next fit.
"""

from __future__ import annotations

import dataclasses
import time
from typing import Callable, Sequence

import jax.numpy as jnp
import numpy as np
import pandas as pd

from mfdesign._x64 import enable_x64
from mfdesign.design import Membrane
from mfdesign.physics.params import SimParams
from mfdesign.physics.status import SOLVER_FAILED, Status, is_valid, summarize

__all__ = ["PlaneSpec", "GridSpec", "MadeRun", "make", "compare", "as_measurements", "simulate_planes"]

# Statuses where the simulator failed at a point that has a solution (physics.status).
FAILED = SOLVER_FAILED


@dataclasses.dataclass(frozen=True)
class PlaneSpec:
    """The plane a run solves: heights ``0 .. h_max_mm`` (``n_heights``) x pressures
    ``0 .. p_max_pa`` (``n_pressures``). The default covers the acquisition's grid
    (:class:`~mfdesign.models.predictor.Grid`: 0-70 mm, up to 8 kPa) at 5 mm x 500 Pa."""

    h_max_mm: float = 70.0
    p_max_pa: float = 8000.0
    n_heights: int = 15
    n_pressures: int = 17

    def __post_init__(self):
        for name in ("h_max_mm", "p_max_pa"):
            v = getattr(self, name)
            if not (isinstance(v, (int, float)) and 0 < v < float("inf")):
                raise ValueError(f"{name} must be a positive finite number, got {v!r}")
        for name in ("n_heights", "n_pressures"):
            v = getattr(self, name)
            if not (isinstance(v, (int, np.integer)) and not isinstance(v, bool) and 2 <= v <= 400):
                raise ValueError(f"{name} must be an integer in [2, 400], got {v!r}")

    @property
    def h_mm(self) -> np.ndarray:
        return np.linspace(0.0, self.h_max_mm, self.n_heights)

    @property
    def p_pa(self) -> np.ndarray:
        return np.linspace(0.0, self.p_max_pa, self.n_pressures)


@dataclasses.dataclass(frozen=True)
class GridSpec:
    """A plane on given heights [mm] and pressures [Pa, strictly increasing], e.g. the
    acquisition's :class:`~mfdesign.models.predictor.Grid` (:meth:`of`): what ``propose``
    checks a proposed membrane's predicted curve on. Quacks like :class:`PlaneSpec` for
    :func:`make` and :func:`simulate_planes` (``h_mm``, ``p_pa``, ``n_heights``, ``n_pressures``)."""

    heights_mm: tuple[float, ...]
    pressures_pa: tuple[float, ...]

    @classmethod
    def of(cls, grid) -> "GridSpec":
        return cls(tuple(map(float, grid.h_mm)), tuple(map(float, grid.p_pa)))

    @property
    def h_mm(self) -> np.ndarray:
        return np.asarray(self.heights_mm, float)

    @property
    def p_pa(self) -> np.ndarray:
        return np.asarray(self.pressures_pa, float)

    @property
    def n_heights(self) -> int:
        return len(self.heights_mm)

    @property
    def n_pressures(self) -> int:
        return len(self.pressures_pa)


@dataclasses.dataclass(frozen=True)
class MadeRun:
    """One simulator run made: ``design`` (mm) of proposal rank ``rank``; ``table`` the plane
    (``design_key, height_mm, pressure_pa, force_n, status, status_name, max_locking``, one
    row per grid point; force NaN where not usable); ``status`` counts per status name;
    ``failed_points`` (the simulator's failures, :data:`FAILED`); ``seconds`` (wall, this
    run's share of the batch); ``rmse_n`` / ``max_error_n`` / ``predicted_std_n`` (N, over the
    usable points; None when there is none); ``error``: why the whole run failed, or None."""

    rank: int
    design: Membrane
    table: pd.DataFrame | None
    status: dict
    failed_points: int
    points: int
    seconds: float
    rmse_n: float | None = None
    max_error_n: float | None = None
    predicted_std_n: float | None = None
    usable_points: int = 0
    error: str | None = None
    surrogate_rmse_n: float | None = None

    @property
    def converged(self) -> bool:
        """Every point solved or known to have no state (no simulator failure)."""
        return self.error is None and self.failed_points == 0

    @property
    def state(self) -> str:
        if self.error is not None:
            return "failed"
        if self.failed_points == 0:
            return "converged"
        return "partly converged" if self.usable_points else "not converged"

    def taught(self) -> str:
        """One sentence: what the run says about the model at this design."""
        if self.error is not None:
            return f"simulator failed: {self.error}"
        if self.rmse_n is None:
            return f"no usable point ({self.failed_points} of {self.points} not converged): nothing learned"
        ratio = self.rmse_n / self.predicted_std_n if self.predicted_std_n else float("inf")
        verdict = (
            "within the predicted spread"
            if ratio <= 1.0
            else "beyond the predicted spread"
            if ratio <= 2.0
            else "well beyond the predicted spread (the members under-state the error here)"
        )
        surrogate = (
            ""
            if self.surrogate_rmse_n is None
            else f"; the surrogate alone at the run's constants {self.surrogate_rmse_n:.3g} N RMS"
        )
        return (
            f"model (sim fidelity) vs simulator {self.rmse_n:.3g} N RMS (max {self.max_error_n:.3g} N) over "
            f"{self.usable_points} points; predicted spread {self.predicted_std_n:.3g} N RMS: {verdict}{surrogate}"
        )

    def to_json(self) -> dict:
        return {
            "made": True,
            "state": self.state,
            "converged": self.converged,
            "status": self.status,
            "points": self.points,
            "usable_points": self.usable_points,
            "failed_points": self.failed_points,
            "seconds": self.seconds,
            "rmse_n": self.rmse_n,
            "max_error_n": self.max_error_n,
            "predicted_std_n": self.predicted_std_n,
            "surrogate_rmse_n": self.surrogate_rmse_n,
            "error_over_predicted": (
                None if self.rmse_n is None or not self.predicted_std_n else float(self.rmse_n / self.predicted_std_n)
            ),
            "taught": self.taught(),
            "error": self.error,
        }


def simulate_planes(designs: Sequence[Membrane], spec: PlaneSpec | GridSpec, params: SimParams) -> list:
    """Force planes of ``designs`` at ``params``: one :func:`~mfdesign.physics.solve.force_planes`
    call (each plane ``vmap``-ed over its heights, planes spread over the cores). Returns
    one ``(force_n [H, P] N, status [H, P], max_locking [H, P])`` per design."""
    from mfdesign.physics.solve import force_planes

    results = force_planes([(d, params) for d in designs], spec.h_mm.tolist(), spec.p_pa.tolist())
    return [(np.asarray(r.force_n, float), np.asarray(r.status), np.asarray(r.max_locking, float)) for r in results]


def _table(design: Membrane, spec: PlaneSpec | GridSpec, force, status, locking) -> pd.DataFrame:
    H, P = np.meshgrid(spec.h_mm, spec.p_pa, indexing="ij")
    status = np.asarray(status).ravel()
    return pd.DataFrame(
        {
            "design_key": design.key(),
            "height_mm": H.ravel(),
            "pressure_pa": P.ravel(),
            "force_n": np.asarray(force, float).ravel(),
            "status": status.astype(np.int8),
            "status_name": [Status(int(s)).name for s in status],
            "max_locking": np.asarray(locking, float).ravel(),
        }
    )


def compare(predictor, fidelity: str, table: pd.DataFrame, surrogate: Callable | None = None) -> dict:
    """The predictor's ``fidelity`` members against a simulated plane ``table`` at its
    usable points: ``rmse_n``, ``max_error_n`` (members' mean vs simulator), ``predicted_std_n``
    (RMS of the member standard deviation), ``usable_points`` (all N); with ``surrogate(design
    [n, 6], h_mm [n], p_pa [n]) -> [n]`` N, also ``surrogate_rmse_n`` (None without)."""
    none = {"rmse_n": None, "max_error_n": None, "predicted_std_n": None, "usable_points": 0, "surrogate_rmse_n": None}
    ok = is_valid(table["status"].to_numpy()) & np.isfinite(table["force_n"].to_numpy())
    n = int(ok.sum())
    if n == 0:
        return none
    rows = jnp.asarray(np.tile(Membrane.from_key(str(table["design_key"].iloc[0])).to_array(), (n, 1)))
    h, p = (jnp.asarray(table[c].to_numpy()[ok]) for c in ("height_mm", "pressure_pa"))
    truth = table["force_n"].to_numpy()[ok]
    members = np.asarray(predictor.members(fidelity, rows, h, p), float)  # [M, n]
    err = members.mean(axis=0) - truth
    good = np.isfinite(err)
    if not good.any():  # the members are NaN there (outside their support): say so by None
        return none
    std = members.std(axis=0)[good]
    out = {
        "rmse_n": float(np.sqrt(np.mean(err[good] ** 2))),
        "max_error_n": float(np.max(np.abs(err[good]))),
        "predicted_std_n": float(np.sqrt(np.mean(std**2))),
        "usable_points": int(good.sum()),
        "surrogate_rmse_n": None,
    }
    if surrogate is not None:
        s_err = np.asarray(surrogate(rows, h, p), float) - truth
        if np.isfinite(s_err).any():
            out["surrogate_rmse_n"] = float(np.sqrt(np.nanmean(s_err[np.isfinite(s_err)] ** 2)))
    return out


def make(
    runs,
    predictor,
    params: SimParams = SimParams(),
    spec: PlaneSpec | GridSpec = PlaneSpec(),
    fidelity: str = "sim",
    simulate: Callable | None = None,
    surrogate: Callable | None = None,
) -> list[MadeRun]:
    """Make ``runs`` (:class:`~mfdesign.acquire.Run`, the proposal's simulator runs): their
    planes in one batch at ``params``, each compared with ``predictor``'s ``fidelity``
    members (:func:`compare`). ``simulate(designs, spec, params)`` (default
    :func:`simulate_planes`) returns ``(force, status, max_locking)`` per design. A batch
    that raises is retried design by design, so that one failing design fails alone.
    ``surrogate(design, h_mm, p_pa) -> [N]`` (optional): the model's force model at the
    same constants, scored alone (``surrogate_rmse_n``)."""
    enable_x64()  # float64 physics: mfdesign._x64
    simulate = simulate_planes if simulate is None else simulate
    runs = list(runs)
    if not runs:
        return []
    designs = [r.design for r in runs]
    t0 = time.perf_counter()
    try:
        solved = list(simulate(designs, spec, params))
        shares = [(time.perf_counter() - t0) / len(runs)] * len(runs)
    except Exception:  # noqa: BLE001 -- one bad design must not hide the others: retry alone
        solved, shares = [], []
        for d in designs:
            t1 = time.perf_counter()
            try:
                solved.append(simulate([d], spec, params)[0])
            except Exception as err:  # noqa: BLE001 -- reported in the run, never silent
                solved.append(err)
            shares.append(time.perf_counter() - t1)
    points = spec.n_heights * spec.n_pressures
    out = []
    for run, res, secs in zip(runs, solved, shares):
        if isinstance(res, Exception):
            from mfdesign.errors import one_line

            out.append(
                MadeRun(
                    run.rank,
                    run.design,
                    None,
                    {},
                    points,
                    points,
                    secs,
                    error=f"{type(res).__name__}: {one_line(res, 200)}",
                )
            )
            continue
        table = _table(run.design, spec, *res)
        status = table["status"].to_numpy()
        failed = int(np.isin(status, [int(s) for s in FAILED]).sum())
        out.append(
            MadeRun(
                run.rank,
                run.design,
                table,
                summarize(status),
                failed,
                points,
                secs,
                **compare(predictor, fidelity, table, surrogate),
            )
        )
    return out


def as_measurements(made: Sequence[MadeRun]):
    """The usable points of the made runs as Measurements (experiment ``"force"``, source
    ``"simulated"``, one trial per run numbered by its rank - 1, set-point = height, weight
    1), or None when no run has a usable point. NO_CONTACT points record 0 N."""
    from mfdesign.data.measurements import Measurements

    frames = []
    for m in made:
        if m.table is None:
            continue
        t = m.table[is_valid(m.table["status"].to_numpy()) & np.isfinite(m.table["force_n"].to_numpy())]
        if t.empty:
            continue
        frames.append(
            pd.DataFrame(
                {
                    "design_key": t["design_key"].to_numpy(),
                    "trial": m.rank - 1,
                    "experiment": "force",
                    "phase": "inflate",
                    "time_s": np.nan,
                    "height_set_mm": t["height_mm"].to_numpy(),
                    "height_mm": t["height_mm"].to_numpy(),
                    "pressure_pa": t["pressure_pa"].to_numpy(),
                    "force_n": t["force_n"].to_numpy(),
                    "weight": 1.0,
                    "source": "simulated",
                }
            )
        )
    return Measurements(pd.concat(frames, ignore_index=True)) if frames else None
