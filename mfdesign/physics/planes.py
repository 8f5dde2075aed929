"""Simulator planes in reduced units, on a lattice of the constants that change their shape.

The exact force model (:class:`mfdesign.models.exact.ExactForceModel`) reads these planes.
Two facts keep their number small:

* **Scaling.** The rubber's energy is ``mu w(lambda; J_m)`` per reference volume and the
  rings' ``mu_ring w(lambda; J_ring)``, both times the local thickness. Dividing the total
  energy ``int 2 pi r t W dr - p V + F h`` by ``s mu0`` with ``s = (mu / mu0) tf`` shows
  that, at fixed ring ratio ``rho = mu_ring / mu``,

      F(h, p; mu, tf) = s G(h, p / s)

  exactly, where ``G`` is the plane at the reference constants (``mu0``, ``tf = 1``). So mu,
  the thickness factor and every per-membrane thickness latent cost no plane at all.
  The rings break the scaling only through ``rho``: when mu moves at fixed ring
  modulus, ``rho`` moves with it (a 19 % stiffer ring changes the force of a two-ring
  membrane by 0.77 N RMS, 2.6 N at most over its plane), so ``rho`` is a lattice
  axis for ringed membranes (ring softening lives on the same axis).
* **Lattice.** Every other constant that changes the solution's shape is an axis with
  nodes ``c0 + k step`` of a coordinate (:data:`AXES`): ``log J_m``, ``log(rho / rho0)``,
  the thickness gradient, the clamp pre-stretch, the contact offset and the fabric inset. A plane is solved
  at each node that a fit needs (:func:`lattice_jobs`, :func:`solve_planes`), cached on disk.

Planes hold the *signed* force (:func:`~mfdesign.physics.solve.force_plane` with
``signed=True``) on heights ``0, 2.5, ... mm`` and reduced pressures ``0, 250, ... Pa``:
cubic interpolation (Keys 1981) of it is within ~0.003 N RMS of the simulator between
nodes (``experiments/bench_exact.py`` measures it), and the contact boundary, where the
clipped force has a kink, is a smooth zero crossing.
"""

from __future__ import annotations

import dataclasses
import functools
import hashlib
import json
import logging
import math
import os
import threading
from pathlib import Path
from typing import Callable, Iterable, Mapping, Sequence

import numpy as np

from mfdesign.design import Membrane
from mfdesign.physics.params import SimParams
from mfdesign.materials import ECOFLEX_JM

__all__ = [
    "AXES",
    "Axis",
    "H_STEP_MM",
    "P_STEP_PA",
    "PlaneGrid",
    "cache_dir",
    "lattice_jobs",
    "shipped_plane",
    "solve_planes",
]

log = logging.getLogger(__name__)

H_STEP_MM = 2.5
P_STEP_PA = 250.0
# bump when the plane content changes (solver, grid semantics): old cache files are ignored.
# 3: nodes the shooting solver cannot converge on are taken from the FE reference (_repair)
SCHEMA = 3


@dataclasses.dataclass(frozen=True)
class Axis:
    """A lattice axis: ``coord(params) -> c`` (JAX or NumPy), ``at(base, c) -> SimParams`` at
    a node, node spacing ``step`` and the coordinate's hard range ``[lo, hi]``;
    ``ringed_only``: the coordinate does not act on a ringless membrane."""

    name: str
    coord: Callable
    at: Callable
    step: float
    lo: float
    hi: float
    ringed_only: bool = False
    doc: str = ""


def _ring_coord(params: SimParams, base: SimParams):
    import jax.numpy as jnp

    return jnp.log((params.ring_mu_pa / params.mu_pa) / (base.ring_mu_pa / base.mu_pa))


def _jm_coord(params: SimParams, base: SimParams):
    import jax.numpy as jnp

    return jnp.log(params.jm / base.jm)


AXES: dict[str, Axis] = {
    a.name: a
    for a in (
        Axis(
            "jm",
            _jm_coord,
            lambda b, c: dataclasses.replace(b, jm=b.jm * math.exp(c)),
            step=math.log(2.0) / 8,
            lo=math.log(10.0 / ECOFLEX_JM),
            hi=math.log(400.0 / ECOFLEX_JM),
            doc="log(J_m / J_m0): Gent locking of the rubber",
        ),
        Axis(
            "ring",
            _ring_coord,
            lambda b, c: dataclasses.replace(b, ring_mu_pa=b.ring_mu_pa * math.exp(c)),
            step=math.log(2.0) / 4,
            lo=math.log(0.005),
            hi=math.log(20.0),
            ringed_only=True,
            doc="log(rho / rho0), rho = ring modulus / rubber modulus",
        ),
        Axis(
            "gradient",
            lambda p, b: p.thickness_gradient - b.thickness_gradient,
            lambda b, c: dataclasses.replace(b, thickness_gradient=b.thickness_gradient + c),
            step=0.05,
            lo=-0.6,
            hi=0.6,
            doc="relative thickness change disk edge -> clamp",
        ),
        Axis(
            "prestretch",
            lambda p, b: p.clamp_prestretch - b.clamp_prestretch,
            lambda b, c: dataclasses.replace(b, clamp_prestretch=b.clamp_prestretch + c),
            step=0.005,
            lo=0.0,
            hi=0.1,
            doc="hoop stretch at the clamp - 1",
        ),
        Axis(
            "offset",
            lambda p, b: p.contact_offset_mm - b.contact_offset_mm,
            lambda b, c: dataclasses.replace(b, contact_offset_mm=b.contact_offset_mm + c),
            step=0.5,
            lo=-8.0,
            hi=8.0,
            doc="effective - nominal contact radius [mm]",
        ),
        Axis(
            "inset",
            lambda p, b: p.fabric_inset_mm - b.fabric_inset_mm,
            lambda b, c: dataclasses.replace(b, fabric_inset_mm=b.fabric_inset_mm + c),
            step=0.25,
            lo=0.0,
            hi=2.5,
            doc="fabric edges' effective inset [mm]",
        ),
        Axis(
            "i2",
            lambda p, b: p.i2_share - b.i2_share,
            lambda b, c: dataclasses.replace(b, i2_share=b.i2_share + c),
            step=0.05,
            lo=0.0,
            hi=0.9,
            doc="share of the rubber's modulus in a Mooney-Rivlin I2 term",
        ),
    )
}


@dataclasses.dataclass(frozen=True)
class PlaneGrid:
    """Heights ``0 .. h_top_mm`` every ``H_STEP_MM`` and reduced pressures ``0 .. p_top_pa``
    every ``P_STEP_PA`` (reduced: ``p / s``, see the module doc)."""

    h_top_mm: float = 80.0
    p_top_pa: float = 16_000.0
    # reduced pressures reach 2 x the data's: membranes down to s = mu tf / mu0 = 0.5 (the
    # real membranes' thickness latents spread +-20 % around a rubber ~18 % softer than the
    # coupons': 1.6 x capped the population's thickness spread at 5 %)
    P_MARGIN = 2.0

    @classmethod
    def covering(cls, h_max_mm: float, p_max_pa: float, p_margin: float | None = None) -> "PlaneGrid":
        """The smallest grid holding heights up to ``h_max_mm`` and pressures up to
        ``p_margin x p_max_pa`` (default :attr:`P_MARGIN`; room for a softer or thinner
        membrane: ``p / s`` grows as ``s`` falls; rows beyond the top are NaN, never
        extrapolated)."""
        p_margin = cls.P_MARGIN if p_margin is None else p_margin
        h_top = H_STEP_MM * math.ceil(max(h_max_mm, H_STEP_MM) / H_STEP_MM + 1e-9)
        p_top = P_STEP_PA * math.ceil(max(p_margin * p_max_pa, 4 * P_STEP_PA) / P_STEP_PA + 1e-9)
        return cls(float(h_top), float(p_top))

    @property
    def h(self) -> np.ndarray:
        return np.arange(0.0, self.h_top_mm + 0.5 * H_STEP_MM, H_STEP_MM)

    @property
    def p(self) -> np.ndarray:
        return np.arange(0.0, self.p_top_pa + 0.5 * P_STEP_PA, P_STEP_PA)


def cache_dir() -> Path:
    """``$MFDESIGN_CACHE_DIR/planes`` or ``~/.cache/mfdesign/planes``."""
    root = os.environ.get("MFDESIGN_CACHE_DIR")
    return (Path(root) if root else Path.home() / ".cache" / "mfdesign") / "planes"


# SimParams fields added after SCHEMA 2 enter a plane's key only when they leave their
# default, so adding a field does not orphan every cached plane
_KEYED_WHEN_SET = {"fabric_inset_mm": 0.0, "i2_share": 0.0}


def _params_tuple(params: SimParams) -> tuple[float, ...]:
    values = ((f.name, round(float(getattr(params, f.name)), 12)) for f in dataclasses.fields(params))
    return tuple(v for name, v in values if name not in _KEYED_WHEN_SET or v != _KEYED_WHEN_SET[name])


# The planes the demo asks of the bundled dataset's six membranes (full and --quick), solved
# once by ``python -m tools.ship_planes`` and shipped in the package: a lab's first demo
# reads them where it solved 72 planes (~190 s of a cold demo on 2 cores, issue 40). Keyed
# like the cache (schema, design, constants, grid), so a request that changed is solved,
# and read only where the disk cache is (``cache`` not False). "0" here solves them.
SHIPPED_ENV = "MFDESIGN_SHIPPED_PLANES"
SHIPPED_NAME = "planes.npz"


@functools.cache
def _shipped_pack() -> Mapping[str, np.ndarray]:
    """The shipped planes (key -> signed plane), read whole once (1.7 MB in memory); empty where the
    file is missing or unreadable (then every plane is solved, as before they shipped)."""
    from mfdesign.data.shipped import shipped_path

    try:
        with np.load(shipped_path(SHIPPED_NAME), allow_pickle=False) as pack:
            return {k: np.asarray(pack[k], float) for k in pack.files}
    except (OSError, ValueError) as err:
        log.warning("shipped planes unreadable (%s): every plane is solved", err)
        return {}


def shipped_plane(key: str) -> np.ndarray | None:
    """The shipped plane of cache key ``key``, or None (not shipped, or ``$MFDESIGN_SHIPPED_PLANES=0``)."""
    if os.environ.get(SHIPPED_ENV, "1").strip() == "0":
        return None
    return _shipped_pack().get(key)


def _job_key(design: Membrane, params: SimParams, grid: PlaneGrid) -> str:
    from mfdesign.physics.solve import fine_path

    key = {
        "schema": SCHEMA,
        "design": design.key(),
        "params": _params_tuple(params),
        "grid": [grid.h_top_mm, grid.p_top_pa, H_STEP_MM, P_STEP_PA],
    }
    if fine_path(params):  # solved on a finer path than planes cached before it existed
        key["path"] = "fine"
    blob = json.dumps(key)
    return hashlib.sha256(blob.encode()).hexdigest()[:24]


def _fill_zero_pressure(f: np.ndarray) -> np.ndarray:
    """Column p = 0 of a signed plane: linear extrapolation from the next two (the signed
    force is smooth in p; the continuation path starts above 0)."""
    f = f.copy()
    f[:, 0] = 2.0 * f[:, 1] - f[:, 2]
    return f


def _fill_above_no_contact(f: np.ndarray) -> np.ndarray:
    """Unsolved nodes straight above a no-contact node (negative signed force) in the same
    pressure column: there the membrane does not reach the plate either (it reaches less
    high at the same pressure), so the recorded force is 0. The signed force needs a
    number for the interpolation; it continues the column's descent (never rises), so it
    stays negative and clips to 0. Seen at 75-77.5 mm on a two-ring membrane whose
    shooting cannot pull it that high at any pressure: left NaN, these nodes blanked the
    rows at 70 mm of that membrane as soon as a lattice coordinate moved off a node."""
    f = f.copy()
    for i in range(2, f.shape[0]):
        below, below2 = f[i - 1], f[i - 2]
        fill = ~np.isfinite(f[i]) & np.isfinite(below) & (below < 0)
        step = np.where(np.isfinite(below2), np.minimum(below - below2, 0.0), 0.0)
        f[i] = np.where(fill, below + step, f[i])
    return f


_MEMO: dict[str, np.ndarray] = {}
REPAIR_BATCH = 8  # unconverged plane nodes re-solved per call: force_at's smallest size, shared with other callers
REPAIR_POINTS = 64  # more unconverged nodes than this in a plane: a region the shooting cannot solve (FE only)


FE_ELEMENTS = 300  # the FE reference's mesh for nodes the shooting cannot solve (agrees with 400 to ~1e-3 N)


def _repair(design: Membrane, params: SimParams, grid: PlaneGrid, f: np.ndarray, status: np.ndarray) -> None:
    """Re-solve a plane's unconverged nodes (in place): first by the shooting solver one
    point at a time, then by the FE reference.

    Along a plane's continuation path a step can fail where a point's own path, from
    p / 8 (:func:`~mfdesign.physics.solve.force_at`), converges: at low tension beside a
    stiff ring the shooting is touchy. Left NaN, such a node would blank the
    interpolation cells around it (rows the simulator can solve).

    Where the shooting fails on its own path too (a rubber gap of a few tenths of a mm
    between the disk and a ring: a contact offset or a fabric inset closing it; whole rows
    near the membrane's reach), the node comes from the FE reference
    (:func:`~mfdesign.physics.fe.fe_rows` for a height whose failed nodes are many, its
    inflation walked once; :func:`~mfdesign.physics.fe.fe_forces` for the rest): the same physics (energy, Gent
    rubber and rings, clamp) discretised by finite elements and minimised, which agrees
    with the shooting solver to ~1e-3 N where both converge (docs/physics.md). Chosen over
    a finer shooting path because the FE minimiser does not integrate across the gap at
    all (a short, stiff segment is one more element), so it converges where shooting
    cannot, and it is already the project's independent check. Nodes past the Gent limit
    or a limit point stay NaN: there the membrane has no such state (and the FE minimiser
    would jump to another branch)."""
    from mfdesign.physics.solve import force_at
    from mfdesign.physics.status import Status

    H, P = np.meshgrid(grid.h, grid.p[1:], indexing="ij")
    status = status.ravel().reshape(f.shape)
    idx = np.flatnonzero(~np.isfinite(f) & (status == Status.NOT_CONVERGED))
    # point paths mend sporadic failures; where whole regions fail (a narrow gap) they
    # fail too, eight points at a time: those go to the FE reference at once
    idx = idx if idx.size <= REPAIR_POINTS else idx[:0]
    for a in range(0, idx.size, REPAIR_BATCH):
        part = idx[a : a + REPAIR_BATCH]
        pad = np.concatenate([part, np.full(REPAIR_BATCH - part.size, part[-1])])
        res = force_at(design, H.ravel()[pad], P.ravel()[pad], params, signed=True)
        f.ravel()[part] = np.asarray(res.force_n, float)[: part.size]
    solver_failed = np.isin(status, [int(Status.NOT_CONVERGED), int(Status.ODE_FAILURE)])
    failed = ~np.isfinite(f) & solver_failed
    if not failed.any():
        return
    from mfdesign.physics.fe import fe_forces, fe_rows

    # A height whose failed nodes cost more increments one by one (8 a node) than a walk of
    # its whole row (fe_rows: 8 to the first pressure, then one a node; one compiled program
    # per plane grid) is walked: whole rows near the membrane's reach fail at once (the
    # bundled two-ring membrane with a wide outer ring, h >= 70 mm: 1,645 nodes, 45 s of FE
    # in a 30-plane lattice, issue 40).
    n_steps = 8
    walked = np.flatnonzero(n_steps + f.shape[1] - 1 < n_steps * failed.sum(axis=1))
    try:
        if walked.size:
            fe = fe_rows(design, params, grid.h[walked], grid.p[1:], n_elements=FE_ELEMENTS, n_steps=n_steps)
            got = np.where(np.asarray(fe.converged, bool), np.asarray(fe.force_n, float), np.nan)
            f[walked] = np.where(failed[walked], got, f[walked])
        idx = np.flatnonzero(~np.isfinite(f) & solver_failed)
        if idx.size:
            fe = fe_forces(
                [(design, params)], [H.ravel()[idx]], [P.ravel()[idx]], n_elements=FE_ELEMENTS, n_steps=n_steps
            )[0]
            f.ravel()[idx] = np.where(np.asarray(fe.converged, bool), np.asarray(fe.force_n, float), np.nan)
    except ValueError:  # no such membrane: the offset or inset closes the gap to a ring (build_mesh)
        return


def _write_plane(folder: Path, key: str, f: np.ndarray) -> None:
    """Store a plane in the cache folder atomically: a reader never sees half a plane."""
    folder.mkdir(parents=True, exist_ok=True)
    tmp = folder / f".{key}.{os.getpid()}.{threading.get_ident()}.npy"
    np.save(tmp, f, allow_pickle=False)
    os.replace(tmp, folder / f"{key}.npy")


def _finish_plane(grid: PlaneGrid, folder: Path | None, job: tuple[Membrane, SimParams], res) -> np.ndarray:
    """A solved plane as cached: unconverged nodes repaired (:func:`_repair`), the p = 0
    column filled, stored in ``folder`` (None: not stored). ``force_planes``' ``then``: it
    runs in the plane's own worker (a thread here, a task on a Dask cluster), so each plane
    is stored as soon as it is solved: a run stopped half-way, or a second process solving
    the same lattice, loses none of them."""
    f = np.asarray(res.force_n, float)
    _repair(*job, grid, f, np.asarray(res.status))
    f = _fill_zero_pressure(np.concatenate([np.full((grid.h.size, 1), np.nan), f], axis=1))
    if folder is not None:
        _write_plane(folder, _job_key(job[0], job[1], grid), f)
    return f


def solve_planes(
    jobs: Sequence[tuple[Membrane, SimParams]],
    grid: PlaneGrid,
    cache: Path | None | bool = None,
    progress: bool = False,
    scheduler=None,
) -> list[np.ndarray]:
    """Signed force planes ``[len(grid.h), len(grid.p)]`` [N] of ``(design, params)`` jobs,
    from memory, the disk cache (``cache``: a folder, ``None`` for :func:`cache_dir`, ``False``
    for none), the planes shipped with the package (the bundled membranes': :func:`shipped_plane`;
    not where ``cache`` is False) or the simulator (all missing ones in one :func:`force_planes` call, on this
    machine or on the Dask ``scheduler``: None means the CLI's ``--scheduler``, else
    ``$MFDESIGN_SCHEDULER``, else this machine; :mod:`mfdesign.physics.cluster`)."""
    from mfdesign.physics import cluster
    from mfdesign.physics.solve import force_planes

    folder = None if cache is False else Path(cache) if cache else cache_dir()
    keys = [_job_key(d, prm, grid) for d, prm in jobs]
    todo: dict[str, tuple[Membrane, SimParams]] = {}
    shipped = 0
    for k, job in zip(keys, jobs):
        if k in _MEMO or k in todo:
            continue
        arr, where_from = _stored_plane(folder, k, (grid.h.size, grid.p.size))
        if arr is None:
            todo[k] = job
            continue
        _MEMO[k] = _fill_above_no_contact(arr)
        shipped += where_from == "shipped"
    if shipped:
        log.info(
            "exact planes: %d read from the planes shipped with mfdesign (the bundled membranes; %s=0 solves them)",
            shipped,
            SHIPPED_ENV,
        )
    if todo:
        finish = functools.partial(_finish_plane, grid, folder)
        where = cluster.scheduler_from(scheduler)
        results = force_planes(
            list(todo.values()),
            grid.h,
            grid.p[1:],
            signed=True,
            progress=progress,
            then=finish,
            scheduler=False if where is None else where,
        )
        if where is not None and folder is not None:
            _store_missing(folder, dict(zip(todo, results)))
        for k, f in zip(todo, results):
            _MEMO[k] = _fill_above_no_contact(f)
    return [_MEMO[k] for k in keys]


def _stored_plane(folder: Path | None, key: str, shape: tuple[int, int]) -> tuple[np.ndarray | None, str]:
    """A plane already solved: from the disk cache ``folder`` (``"cache"``), else the
    shipped planes (``"shipped"``; only where there is a disk cache), else ``(None, "")``.
    A stored array of another shape, or a torn or foreign file, counts as missing (then
    solved again and overwritten)."""
    if folder is None:
        return None, ""
    path = folder / f"{key}.npy"
    if path.is_file():
        try:
            arr = np.load(path, allow_pickle=False)
            if arr.shape == shape:
                return arr, "cache"
        except (OSError, ValueError):
            pass
    arr = shipped_plane(key)
    return (arr, "shipped") if arr is not None and arr.shape == shape else (None, "")


def _store_missing(folder: Path, planes: Mapping[str, np.ndarray]) -> None:
    """After a cluster solve: store here the planes the workers did not leave in ``folder``
    (they do not see it: MFDESIGN_CACHE_DIR must be a folder every worker sees)."""
    missing = [k for k in planes if not (folder / f"{k}.npy").is_file()]
    for k in missing:
        _write_plane(folder, k, planes[k])
    if missing:
        log.warning(
            "%d of %d planes solved on the Dask cluster were not in %s: the workers do not see this folder "
            "(MFDESIGN_CACHE_DIR must be a folder every worker sees); stored from here",
            len(missing),
            len(planes),
            folder,
        )


def node_range(axis: Axis, lo: float, hi: float) -> tuple[int, int]:
    """Node indices ``k0 <= k1`` whose coordinates ``k step`` cover ``[lo, hi]`` (clipped to
    the axis' hard range)."""
    lo, hi = max(lo, axis.lo), min(hi, axis.hi)
    k0 = math.floor(lo / axis.step + 1e-9)
    k1 = math.ceil(hi / axis.step - 1e-9)
    k0 = max(k0, math.ceil(axis.lo / axis.step - 1e-9))
    k1 = min(k1, math.floor(axis.hi / axis.step + 1e-9))
    return k0, max(k0, k1)


def lattice_jobs(designs: Sequence[Membrane], base: SimParams, nodes: Mapping[str, tuple[int, int]]):
    """The ``(design, params)`` jobs of the planes on the tensor lattice of ``nodes`` (axis
    name -> inclusive node index range), reference constants ``base`` with ``mu`` as given
    and ``tf = 1``, and a function that stacks their solved planes (:func:`solve_planes`)
    into ``[M, n_1, ..., n_D, len(grid.h), len(grid.p)]``. A ringless membrane's ring axis
    repeats one plane."""
    names = list(nodes)
    axes = [AXES[n] for n in names]
    ranges = [range(nodes[n][0], nodes[n][1] + 1) for n in names]
    shape = [len(r) for r in ranges]
    jobs, where = [], []
    for m, d in enumerate(designs):
        for idx in np.ndindex(*shape) if shape else [()]:
            params = dataclasses.replace(base, thickness_factor=1.0)
            for a, r, i in zip(axes, ranges, idx):
                k = r[i] if not (a.ringed_only and d.n_rings == 0) else 0
                params = a.at(params, k * a.step)
            jobs.append((d, params))
            where.append((m, *idx))

    def stack(planes: Sequence[np.ndarray]) -> np.ndarray:
        out = np.empty((len(designs), *shape, *planes[0].shape))
        for w, f in zip(where, planes):
            out[w] = f
        return out

    return jobs, stack


def designs_of(keys: Iterable[str]) -> list[Membrane]:
    return [Membrane.from_key(k) for k in keys]
