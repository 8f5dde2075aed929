"""A simulated force plane of one membrane: compute it (with a progress bar), save it
(``mfdesign simulate``: :func:`simulate`).

The plane is ``F(h, p)`` on a height x pressure grid (mm, Pa, N) with one status per
point; the picture is the paper's: force against pressure, one curve per height.
"""

from __future__ import annotations

import json
from dataclasses import dataclass
from pathlib import Path
from typing import Any

import numpy as np
import pandas as pd

from mfdesign.design import Membrane
from mfdesign.physics.params import SimParams
from mfdesign.physics.solve import force_plane
from mfdesign.physics.status import Status, is_valid, summarize

HEIGHTS_PER_CHUNK = 10  # one compiled batch size; chunks feed the progress bar


def simulate_plane(
    design: Membrane,
    h_max_mm: float = 70.0,
    p_max_pa: float = 10_000.0,
    n_heights: int = 50,
    n_pressures: int = 50,
    params: SimParams = SimParams(),
    progress: bool = False,
) -> pd.DataFrame:
    """The plane as a table: ``height_mm, pressure_pa, force_n, status, status_name,
    max_locking`` (one row per grid point).

    Arguments:
        design: the membrane.
        h_max_mm: largest plate height [mm]; heights run evenly from 0.
        p_max_pa: largest pressure [Pa]; pressures run evenly from 0.
        n_heights, n_pressures: grid points along each axis.
        params: the simulator's constants (rubber ``mu_pa`` [Pa], ``jm``, ...).
        progress: show a progress bar (one step per chunk of heights).
    """
    from tqdm.auto import tqdm

    h_grid: Any = np.linspace(0.0, h_max_mm, n_heights)
    p_grid: Any = np.linspace(0.0, p_max_pa, n_pressures)
    # Pad the height list to whole chunks so every chunk reuses one compiled kernel.
    n_chunks = -(-n_heights // HEIGHTS_PER_CHUNK)
    padded: Any = np.concatenate([h_grid, np.full(n_chunks * HEIGHTS_PER_CHUNK - n_heights, h_grid[-1])])
    parts = []
    for k in tqdm(range(n_chunks), desc=f"simulate {design.key()}", unit="chunk", disable=not progress):
        chunk = padded[k * HEIGHTS_PER_CHUNK : (k + 1) * HEIGHTS_PER_CHUNK]
        parts.append(force_plane(design, chunk, p_grid, params))
    cat = {f: np.concatenate([getattr(r, f) for r in parts])[:n_heights] for f in ("force_n", "status", "max_locking")}
    H, P = np.meshgrid(h_grid, p_grid, indexing="ij")
    return pd.DataFrame(
        {
            "design_key": design.key(),
            "height_mm": H.ravel(),
            "pressure_pa": P.ravel(),
            "force_n": cat["force_n"].ravel(),
            "status": cat["status"].ravel().astype(np.int8),
            "status_name": [Status(int(s)).name for s in cat["status"].ravel()],
            "max_locking": cat["max_locking"].ravel(),
        }
    )


def plot_plane(table: pd.DataFrame, title: str, path: Path) -> None:
    """Force vs pressure coloured by height (the paper's figure); unusable points omitted."""
    import matplotlib

    matplotlib.use("Agg")
    import matplotlib.pyplot as plt

    fig, ax = plt.subplots(figsize=(7, 4.5), dpi=120)
    heights = np.sort(table.height_mm.unique())
    cmap = plt.get_cmap("viridis")
    for k, h in enumerate(heights):
        rows = table[table.height_mm == h]
        ax.plot(rows.pressure_pa / 1e3, rows.force_n, color=cmap(k / max(len(heights) - 1, 1)), lw=1.2)
    sm = plt.cm.ScalarMappable(cmap=cmap, norm=plt.Normalize(heights.min(), heights.max()))
    fig.colorbar(sm, ax=ax, label="plate height h [mm]")
    bad = table[~is_valid(table.status)]
    if len(bad):
        ax.plot([], [], " ", label=f"{len(bad)} of {len(table)} points unusable (see status)")
        ax.legend(loc="upper left", fontsize=8)
    ax.set_xlabel("pressure p [kPa]")
    ax.set_ylabel("force F [N]")
    ax.set_title(title, fontsize=9)
    ax.grid(alpha=0.3)
    fig.tight_layout()
    from mfdesign import outputs

    outputs.savefig(fig, path)
    plt.close(fig)


def write_plane(table: pd.DataFrame, design: Membrane, out: Path, extra: dict | None = None) -> dict[str, Path]:
    """``plane.parquet``, ``plane.png`` and ``summary.json`` in ``out`` (each written
    atomically); ``extra`` joins the summary.

    Arguments:
        table: the plane (:func:`simulate_plane`: heights in mm, pressures in Pa, forces in N).
        design: the membrane it belongs to (its key names the files' contents).
        out: folder to write into (created).
        extra: JSON-ready entries added to ``summary.json``.

    Returns the three paths by kind: ``parquet``, ``png``, ``json``.
    """
    from mfdesign import outputs

    out = Path(out)
    out.mkdir(parents=True, exist_ok=True)
    paths = {"parquet": out / "plane.parquet", "png": out / "plane.png", "json": out / "summary.json"}
    with outputs.atomic_path(paths["parquet"]) as tmp:
        table.to_parquet(tmp, index=False)
    plot_plane(table, f"simulated force plane, design {design.key()}", paths["png"])
    summary = {
        "design": design.key(),
        "points": int(len(table)),
        "status": summarize(table.status.to_numpy()),
        "max_force_n": float(np.nanmax(table.force_n)) if np.isfinite(table.force_n).any() else None,
        **(extra or {}),
    }
    from mfdesign.provenance import call_line, provenance

    summary["provenance"] = provenance(call_line("mfdesign.workflows.plane.write_plane()"))
    outputs.write_json(paths["json"], summary)
    return paths


@dataclass(frozen=True)
class PlaneResult:
    """What :func:`simulate` wrote: the files by kind (``parquet``, ``png``, ``json``)
    and whether the design lay outside the product's design space (widened on request)."""

    design_key: str
    paths: dict[str, Path]
    widened: bool = False

    @property
    def warnings(self) -> tuple[str, ...]:
        if not self.widened:
            return ()
        return (f"warning: {self.design_key} is outside the product's design space (widened on request)",)

    def summary(self) -> str:
        """The files as one JSON line (kind -> path)."""
        return json.dumps({k: str(v) for k, v in self.paths.items()})


def simulate(
    design: str,
    out: Path,
    h_max_mm: float = 70.0,
    p_max_pa: float = 10_000.0,
    n_heights: int = 50,
    n_pressures: int = 50,
    mu_pa: float | None = None,
    jm: float | None = None,
    allow_outside_design_space: bool = False,
    progress: bool = True,
) -> PlaneResult:
    """Simulate one membrane on a height x pressure grid and write the plane into ``out``
    (:func:`write_plane`: Parquet + PNG + JSON).

    Arguments:
        design: design key ``"[t, c, r1, w1, r2, w2]"`` in mm (nan: no ring).
        out: output folder.
        h_max_mm: largest plate height [mm] (> 0).
        p_max_pa: largest pressure [Pa] (> 0).
        n_heights, n_pressures: grid points along each axis.
        mu_pa: Gent shear modulus of the rubber [Pa]; None: the authors' (31.7 kPa).
        jm: Gent locking parameter J_m; None: the authors' (39.6).
        allow_outside_design_space: accept a design outside the product's space, up to the
            wider research range (the summary says so).
        progress: show a progress bar.

    Raises :class:`~mfdesign.errors.InputError` (one line) for a bad design or a
    non-positive or non-finite number.
    """
    from mfdesign.design import DesignError, check_design_space
    from mfdesign.errors import InputError

    defaults = SimParams()
    mu = float(defaults.mu_pa) if mu_pa is None else mu_pa
    j_m = float(defaults.jm) if jm is None else jm
    try:
        membrane = Membrane.from_key(design)
        widened = check_design_space(membrane, allow_outside_design_space)
    except DesignError as err:
        raise InputError(f"bad design {design!r}: {err}") from None
    for name, value in (("h-max-mm", h_max_mm), ("p-max-pa", p_max_pa), ("mu-pa", mu), ("jm", j_m)):
        if not (value > 0.0 and value < float("inf")):
            raise InputError(f"--{name} must be a positive finite number, got {value}")
    params = SimParams(mu_pa=mu, jm=j_m)
    table = simulate_plane(membrane, h_max_mm, p_max_pa, n_heights, n_pressures, params, progress=progress)
    note = (
        {"design_space": "widened (--allow-outside-design-space): outside the product's membranes"} if widened else {}
    )
    paths = write_plane(table, membrane, out, extra=note)
    return PlaneResult(membrane.key(), paths, bool(widened))
