"""A virtual rig: the paper's protocol run on the simulator, with hidden effects and sensor noise.

Truth = simulator (mechanical effects applied through ``SimParams``) -> measurement-chain
effects (:mod:`mfdesign.physics.effects`) -> sensor noise and quantisation. The output is
a :class:`~mfdesign.data.measurements.Measurements` table with ``source = "virtual"``,
shaped like the real data.

Protocol (the paper's, see ``docs/rig.md``); every number is a field of :class:`Protocol`:

* **force characterisation**: plate held at 0, 10, ..., 70 mm, 3 trials per height (order:
  heights ascending, the 3 repeats back to back). The pressure ramps from 0 at
  ``ramp_pa_per_s`` (100 Pa/s) and the rig samples at ``sample_hz`` (10 Hz). Ringed
  membranes go to 4.3 kPa; when no trial burst the membrane, the whole programme runs
  again to 6.1 kPa. Ringless membranes inflate "until contact with the rig": the membrane
  beside the disk bulges above the plate and touches the plate's holder when it rises
  ``ringless_contact_rise_mm`` (20 mm, our choice: it makes the largest ringless forces
  ~100 N, as in the paper) above the plate; capped at ``ringless_limit_pa`` (10 kPa, the
  rig's cap).
* **mass lift**: 1.5, 2.5 and 4.0 kg on the free plate (load ``m g`` N, :data:`mfdesign.units.G_M_S2`), 2 trials per
  mass (as in the real file), inflation from 0 to ``lift_limit_pa`` (10 kPa) or until the
  plate reaches ``lift_height_max_mm`` (75 mm). Along the ramp the plate sits on the
  branch reached by quasi-static inflation from ``h = 0``: at each pressure, the first
  height where the force at fixed height falls to the load (as ``solve.height_at``).
* **deflation** (``deflate=True``; off by default): back down to 0 at the same rate.
* **bursts**: each membrane draws a burst threshold of the Gent locking measure
  ``(I1 - 3) / J_m`` (normal, ``burst_locking_mean`` +- ``burst_locking_sd``); the first
  sample beyond it bursts the membrane: that trial is dropped (as in the paper), the burst
  is logged in :attr:`VirtualRig.events`, and the membrane takes no further trials.

Recording: the rig's controller regulates on its own sensors, so a trial runs on
RECORDED set-points (the ramp is the pressure the transducer reads; a force trial holds
the plate where the height sensors read ``h_set``). The recorded force of a force trial is
:func:`~mfdesign.physics.effects.apply_expected_force` of the measurement effects at its
set-points, with the truth plane as ``force_fn``; the recorded height of a mass lift is
where that expected force equals the weight
(:func:`~mfdesign.physics.effects.recorded_lift_height`, from the truth's quasi-static
branch; the plate's support at 0 and the rig's top are stiff springs, so a resting or
pinned plate has a height too). The effects' one JAX hook thus records the data and
scores them in the likelihood. Physical events (contact, bursts, the top) are looked up on
the truth at the set-points: measurement effects change what is recorded, not the membrane.

Efficiency: per membrane and distinct ``SimParams`` the simulator runs once, one
:func:`~mfdesign.physics.solve.force_plane` on (heights x pressures): the set heights and
a lift grid (0-80 mm every ``height_step_mm``) x ``pressure_step_pa`` up to the highest
pressure of the programme. The rig reads it bilinearly (:meth:`TruthPlane.at`, JAX, so
that the effects' hooks can trace and differentiate it). Samples where the simulator has
no usable value (not converged, past a limit point) are omitted and counted in the
trial's event. Planes can be memoised on
disk (``cache_dir``), keyed by design, SimParams, grids and a hash of the simulator's
source, so a rerun after a simulator change never reads a stale plane.

Reproducibility: every (membrane, experiment) draws from its own generator seeded by
``(seed, crc32(design key), crc32(experiment))``, so a membrane's data do not depend on
which other membranes run or in what order; the same seed gives the same table, bit for bit.
"""

from __future__ import annotations

import dataclasses
import hashlib
import json
import logging
import os
import zlib
from dataclasses import dataclass
from pathlib import Path
from typing import Any, Callable, Iterable, Mapping, Sequence

import equinox as eqx
import jax
import jax.numpy as jnp
import numpy as np
import pandas as pd

from mfdesign._x64 import enable_x64
from mfdesign.data.measurements import COLUMNS, Measurements
from mfdesign.design import Membrane
from mfdesign.physics import effects as fx
from mfdesign.physics.params import SimParams
from mfdesign.physics.status import Status
from mfdesign.units import G_M_S2, PSI_TO_PA

log = logging.getLogger(__name__)

__all__ = ["Noise", "Protocol", "TruthPlane", "VirtualRig", "simulator_fingerprint"]


@dataclass(frozen=True)
class Noise:
    """Sensor noise (Gaussian standard deviations) and quantisation steps; 0 switches off."""

    force_sd_n: float = 0.2
    pressure_sd_pa: float = 10.0
    height_sd_mm: float = 0.3
    force_step_n: float = 0.01  # load-cell resolution
    pressure_step_pa: float = (
        1e-4 * PSI_TO_PA
    )  # 0.69 Pa: the real sensor reads in steps of 1e-4 psi, as in the real mass-lift file
    height_step_mm: float = 1.0  # time-of-flight sensors read whole millimetres

    @classmethod
    def none(cls) -> "Noise":
        return cls(0.0, 0.0, 0.0, 0.0, 0.0, 0.0)


@dataclass(frozen=True)
class Protocol:
    """The experiment programme and the rig's sampling (mm, Pa, s, kg)."""

    heights_mm: tuple[float, ...] = (0.0, 10.0, 20.0, 30.0, 40.0, 50.0, 60.0, 70.0)
    trials_per_height: int = 3
    ringed_limits_pa: tuple[float, ...] = (4300.0, 6100.0)
    ringless_limit_pa: float = 10000.0
    ringless_contact_rise_mm: float = 20.0
    ramp_pa_per_s: float = 100.0
    sample_hz: float = 10.0
    deflate: bool = False
    lift_masses_kg: tuple[float, ...] = (1.5, 2.5, 4.0)
    lift_trials: int = 2
    lift_limit_pa: float = 10000.0
    lift_height_max_mm: float = 75.0
    # Lift height grid of the simulator plane (0 .. lift max + step). Lifted heights are
    # interpolated linearly between its rows: at 10 mm that put the virtual "truth" up to
    # ~1 N off the simulator (a misfit no calibration can remove); at 2.5 mm the force
    # behind a lift row is within ~0.06 N RMS of the simulator's.
    height_step_mm: float = 2.5
    pressure_step_pa: float = 250.0  # pressure grid of the simulator plane
    burst_locking_mean: float = 0.92
    burst_locking_sd: float = 0.03

    def __post_init__(self):
        if self.ramp_pa_per_s <= 0 or self.sample_hz <= 0:
            raise ValueError("ramp_pa_per_s and sample_hz must be positive")
        if self.pressure_step_pa <= 0 or self.height_step_mm <= 0:
            raise ValueError("grid steps must be positive")
        if min(self.heights_mm, default=0.0) < 0:
            raise ValueError("plate heights must be >= 0 mm")

    def force_limits(self, design: Membrane) -> tuple[float, ...]:
        return tuple(self.ringed_limits_pa) if design.n_rings else (self.ringless_limit_pa,)

    def grids(self, design: Membrane) -> tuple[np.ndarray, np.ndarray]:
        """(heights, pressures) of the one simulator plane a membrane needs."""
        p_top = max(max(self.force_limits(design)), self.lift_limit_pa)
        n = int(np.ceil(p_top / self.pressure_step_pa - 1e-9))
        p_grid = self.pressure_step_pa * np.arange(1, n + 1)
        top = self.lift_height_max_mm + self.height_step_mm
        hs = {float(h) for h in self.heights_mm}
        hs |= {float(h) for h in np.arange(0.0, top + 1e-9, self.height_step_mm)}
        return np.array(sorted(hs)), p_grid


# -- truth on a grid -----------------------------------------------------------------------
# The plate's support (h = 0) and the rig's top stop, as springs for the lift solve: stiff
# enough that a resting plate sits within ~1e-4 mm of its support under 100 N, soft enough
# that the root find's residual (1e-7 N) is not lost to rounding (K * ulp(75 mm) ~ 1e-8 N).
STOP_N_PER_MM = 1e6


def _cell(grid, x):
    """Cell ``i`` of ``x`` on a sorted ``grid`` (``grid[i] <= x < grid[i + 1]``, the end
    cells extended) and the fraction ``(x - grid[i]) / (grid[i + 1] - grid[i])``."""
    i = jnp.clip(jnp.searchsorted(grid, x, side="right") - 1, 0, grid.shape[0] - 2)
    return i, (x - grid[i]) / (grid[i + 1] - grid[i])


def _mix(a, b, t):
    """``(1 - t) a + t b``; at a node only that node counts (an unsolved NaN neighbour does not)."""
    return jnp.where(t == 0, a, jnp.where(t == 1, b, (1.0 - t) * a + t * b))


@jax.custom_jvp
def _bilinear(table, h_grid, p_grid, h, p):
    """Bilinear interpolation of ``table[h_grid, p_grid]`` at points ``(h, p)``."""
    i, w = _cell(h_grid, h)
    j, u = _cell(p_grid, p)
    return _mix(_mix(table[i, j], table[i, j + 1], u), _mix(table[i + 1, j], table[i + 1, j + 1], u), w)


@_bilinear.defjvp
def _bilinear_jvp(primals, tangents):
    # The slopes of the cell the point lies in: the difference quotients of the table (a
    # node takes the cell above it), NaN where a corner is unsolved. Autodiff of
    # ``_mix`` would drop the zero-weight corner's slope at a node, where the force trials
    # sit. The grids are constants (their tangents are ignored).
    table, h_grid, p_grid, h, p = primals
    d_table, _, _, dh, dp = tangents
    i, w = _cell(h_grid, h)
    j, u = _cell(p_grid, p)
    dfdh = (_mix(table[i + 1, j], table[i + 1, j + 1], u) - _mix(table[i, j], table[i, j + 1], u)) / (
        h_grid[i + 1] - h_grid[i]
    )
    dfdp = (_mix(table[i, j + 1], table[i + 1, j + 1], w) - _mix(table[i, j], table[i + 1, j], w)) / (
        p_grid[j + 1] - p_grid[j]
    )
    value = _bilinear(table, h_grid, p_grid, h, p)
    return value, dfdh * dh + dfdp * dp + _bilinear(d_table, h_grid, p_grid, h, p)


_PLANE_FIELDS = ("h_grid", "p_grid", "force_n", "locking", "rise_mm", "status")


def _as_float(a) -> jax.Array:
    return jnp.asarray(a, float)


class TruthPlane(eqx.Module):
    """Simulator output on ``h_grid`` [mm] x ``p_grid`` [Pa]; ``p_grid[0] = 0`` (no pressure,
    no force): ``force_n`` [N], ``locking`` [1], ``rise_mm`` [mm], ``status`` (codes)."""

    h_grid: jax.Array = eqx.field(converter=_as_float)
    p_grid: jax.Array = eqx.field(converter=_as_float)
    force_n: jax.Array = eqx.field(converter=_as_float)
    locking: jax.Array = eqx.field(converter=_as_float)
    rise_mm: jax.Array = eqx.field(converter=_as_float)
    status: jax.Array = eqx.field(converter=jnp.asarray)

    def along_p(self, values, p) -> jax.Array:
        """Linear interpolation in pressure ``p`` [Pa] of ``values`` on ``p_grid``."""
        j, u = _cell(self.p_grid, jnp.asarray(p, float))
        values = jnp.asarray(values, float)
        return _mix(values[..., j], values[..., j + 1], u)

    def at(self, values, h, p) -> jax.Array:
        """Bilinear interpolation of a plane of ``values`` at heights ``h`` [mm] and pressures
        ``p`` [Pa] (NaN where h is NaN or a weighted corner is unsolved; a pressure below the
        grid reads the zero-pressure column: nothing acts below zero gauge pressure)."""
        h, p = jnp.broadcast_arrays(jnp.asarray(h, float), jnp.asarray(p, float))
        ok = jnp.isfinite(h)
        v = _bilinear(
            jnp.asarray(values, float),
            self.h_grid,
            self.p_grid,
            jnp.where(ok, h, self.h_grid[0]),
            jnp.maximum(p, self.p_grid[0]),
        )
        return jnp.where(ok, v, jnp.nan)

    def force(self, h, p) -> jax.Array:
        """The true force [N] at true height ``h`` [mm] and pressure ``p`` [Pa] (the effects' ``force_fn``)."""
        return self.at(self.force_n, h, p)

    def lift_force(self, h, p, top_mm: float) -> jax.Array:
        """Upward force [N] on a free plate at true height ``h`` [mm]: the membrane's, with the
        plate between its support (0) and the rig's top ``top_mm``, plus the reaction of
        either (stiff springs, :data:`STOP_N_PER_MM`) when ``h`` is pushed past it."""
        stops = STOP_N_PER_MM * (jnp.maximum(-h, 0.0) - jnp.maximum(h - top_mm, 0.0))
        return self.force(jnp.clip(h, 0.0, top_mm), p) + stops

    def lift_height(self, load_n: float) -> np.ndarray:
        """Plate height at each grid pressure under ``load_n``: the first crossing of
        ``F(h, p) = load`` going up from ``h = 0``, linear in h between grid heights.

        Heights where the simulator has no value at this pressure are skipped (the crossing
        is interpolated across them). ``0`` where the lowest height cannot carry the load
        (not lifted); the top of the grid where every height carries it (the plate flies up
        to the rig's top: a snap-through); NaN where the lowest usable height is not 0 and
        already below the load (unknown).
        """
        F, hg = np.asarray(self.force_n), np.asarray(self.h_grid)
        out = np.full(F.shape[1], np.nan)
        for j in range(F.shape[1]):
            col = F[:, j]
            rows = np.nonzero(np.isfinite(col))[0]
            if rows.size == 0:
                continue
            f0 = rows[0]
            if col[f0] < load_n:
                if f0 == 0:
                    out[j] = 0.0  # not lifted
                continue
            cand = rows[col[rows] < load_n]
            if cand.size == 0:
                if rows[-1] == len(hg) - 1:
                    out[j] = hg[-1]  # carries the load everywhere: up to the top
                continue
            b = cand[0]
            a = rows[rows < b][-1]
            w = (col[a] - load_n) / (col[a] - col[b])
            out[j] = hg[a] + w * (hg[b] - hg[a])
        return out

    # -- storage -------------------------------------------------------------------------
    def to_npz(self, path: Path) -> None:
        tmp = path.with_name(path.name + ".tmp.npz")
        np.savez(tmp, **{k: np.asarray(getattr(self, k)) for k in _PLANE_FIELDS})
        os.replace(tmp, path)

    @classmethod
    def from_npz(cls, path: Path) -> "TruthPlane":
        with np.load(path) as z:
            return cls(**{k: z[k] for k in _PLANE_FIELDS})


def _force_plane(design, h_grid, p_grid, params):
    """``force_plane``; if the simulator raises (it should return statuses, but a solver
    error inside JIT can escape), retry height by height and mark the failing heights
    ``NOT_CONVERGED`` (NaN) instead of losing the whole membrane."""
    from mfdesign.physics.solve import SimResult, force_plane

    try:
        return force_plane(design, h_grid, p_grid, params)
    except Exception as err:  # noqa: BLE001 -- any solver failure: degrade to per-height
        log.warning(
            "force_plane failed for %s (%s: %s); retrying height by height",
            design.key(),
            type(err).__name__,
            str(err).splitlines()[0] if str(err) else "",
        )
    shape = (len(h_grid), len(p_grid))
    out = SimResult(
        force_n=np.full(shape, np.nan),
        status=np.full(shape, int(Status.NOT_CONVERGED), np.int8),
        max_locking=np.full(shape, np.nan),
        max_rise_mm=np.full(shape, np.nan),
        wrinkled=np.zeros(shape, bool),
    )
    for i, h in enumerate(h_grid):
        try:
            r = force_plane(design, [h], p_grid, params)
        except Exception as err:  # noqa: BLE001
            log.warning("force_plane failed for %s at h = %g mm: %s", design.key(), h, type(err).__name__)
            continue
        out.force_n[i], out.status[i] = r.force_n[0], r.status[0]
        out.max_locking[i], out.max_rise_mm[i] = r.max_locking[0], r.max_rise_mm[0]
    return out


def simulator_fingerprint() -> str:
    """Hash of the simulator's source: every module of ``mfdesign/physics`` except the
    effects library, plus ``materials.py`` and ``design.py``; part of every plane-cache key
    and of the bundled dataset's card."""
    pkg = Path(__file__).resolve().parents[1]
    files = sorted(f for f in (pkg / "physics").glob("*.py") if f.name != "effects.py")
    files += [pkg / "materials.py", pkg / "design.py"]
    h = hashlib.sha256()
    for f in files:
        if f.is_file():
            h.update(f.name.encode() + b"\0" + f.read_bytes())
    return h.hexdigest()[:16]


def _params_dict(params: SimParams) -> dict:
    return {f.name: float(getattr(params, f.name)) for f in dataclasses.fields(params)}


def _quantise(x: np.ndarray, step: float) -> np.ndarray:
    return np.round(x / step) * step + 0.0 if step > 0 else x + 0.0


# -- recording through the effects' hooks (jitted; every trial padded to one length, so that
# a rig compiles once per list of measurement effects) ----------------------------------------
@eqx.filter_jit
def _plane_at(plane: TruthPlane, values: jax.Array, h: jax.Array, p: jax.Array) -> jax.Array:
    """The plane of ``values`` at set-points ``(h, p)``."""
    return plane.at(values, h, p)


@eqx.filter_jit
def _recorded_force(effects: tuple, theta: dict, plane: TruthPlane, rows: fx.Rows) -> jax.Array:
    """Recorded force [N] of a force trial at its set-points ``rows`` (before sensor noise)."""
    return fx.apply_expected_force(effects, theta, plane.force, rows)


@eqx.filter_jit
def _recorded_height(effects: tuple, theta: dict, plane: TruthPlane, rows: fx.Rows, weight, start, top_mm: float):
    """Recorded plate height [mm] of a lift at its pressure set-points ``rows.p_pa``."""
    force_fn = lambda h, p: plane.lift_force(h, p, top_mm)  # noqa: E731
    return fx.recorded_lift_height(effects, theta, force_fn, rows, weight, start)


def _pad(a, size: int, dtype=float) -> jax.Array:
    """``a`` (or a scalar, broadcast) padded to ``size`` by repeating its last value."""
    a = np.atleast_1d(np.asarray(a))
    return jnp.asarray(np.pad(a, (0, size - len(a)), mode="edge"), dtype)


# -- the rig ---------------------------------------------------------------------------------
class VirtualRig:
    """The paper's rig in software: :meth:`characterise`, :meth:`mass_lift`, :meth:`run`.

    ``effects``: hidden truth effects (registered names or instances); ``theta``: their
    parameters (flat ``{"effect.param": value}`` or nested; missing = neutral);
    ``membrane_theta``: per-design overrides ``{design key: theta}`` (e.g. each membrane's
    own thickness deviation); ``base_params``: the simulator constants of the truth;
    ``simulator``: ``(design, h_grid, p_grid, params) -> SimResult`` (default
    :func:`~mfdesign.physics.solve.force_plane`; tests plug in a cheap analytic one);
    ``cache_dir``: optional folder memoising simulator planes.
    """

    def __init__(
        self,
        effects: Iterable[str | fx.Effect] = (),
        theta: Mapping[str, Any] | None = None,
        seed: int = 0,
        noise: Noise = Noise(),
        protocol: Protocol = Protocol(),
        base_params: SimParams = SimParams(),
        membrane_theta: Mapping[str, Mapping[str, Any]] | None = None,
        simulator: Callable | None = None,
        cache_dir: str | os.PathLike | None = None,
    ):
        self.effects = [fx.effect(e) for e in effects]
        self.theta = dict(theta or {})
        fx.split_theta(self.effects, self.theta)  # fail now on a typo, not mid-run
        self.membrane_theta = {Membrane.from_key(k).key(): dict(v) for k, v in (membrane_theta or {}).items()}
        for v in self.membrane_theta.values():
            fx.split_theta(self.effects, v)
        self.seed = int(seed)
        self.noise = noise
        self.protocol = protocol
        self.base_params = base_params
        self.simulator = simulator or _force_plane
        self.cache_dir = Path(cache_dir) if cache_dir is not None else None
        self.events: list[dict] = []
        self._planes: dict[str, TruthPlane] = {}
        # every trial's arrays are padded to the longest ramp of the programme (one compile)
        top = max(*protocol.ringed_limits_pa, protocol.ringless_limit_pa, protocol.lift_limit_pa)
        self._size = len(self._ramp(top)[0])

    @classmethod
    def from_card(
        cls,
        card: Mapping[str, Any],
        simulator: Callable | None = None,
        seed: int | None = None,
        noise: Noise | None = None,
        **protocol: Any,
    ) -> "VirtualRig":
        """The rig a dataset's card (``bundled_card.json``, read as a dict) describes: its
        hidden effect, seed, noise and protocol, the authors' simulator constants.

        Arguments:
            card: the card (``hidden_effect``, ``seed``, ``noise``, ``protocol``).
            simulator: the truth's plane solver (default the simulator; the stand-in demo
                passes :func:`~mfdesign.models.standin.standin_plane`, a world of its own).
            seed: the rig's noise seed (default the card's: the card's own measurements).
            noise: the sensors (default the card's; ``Noise.none()`` records the truth itself).
            **protocol: fields of :class:`Protocol` to change (e.g. ``sample_hz=2.0``).
        """

        def fields(kind, given):
            names = {f.name for f in dataclasses.fields(kind)}
            return {k: tuple(v) if isinstance(v, list) else v for k, v in given.items() if k in names}

        hidden = card["hidden_effect"]
        return cls(
            effects=[hidden["name"]],
            theta=hidden["theta"],
            seed=int(card.get("seed", 0)) if seed is None else int(seed),
            noise=Noise(**fields(Noise, card.get("noise", {}))) if noise is None else noise,
            protocol=Protocol(**(fields(Protocol, card.get("protocol", {})) | protocol)),
            simulator=simulator,
        )

    # -- truth -------------------------------------------------------------------------------
    def _theta(self, design: Membrane) -> dict:
        theta = dict(self.theta)
        theta.update(self.membrane_theta.get(design.key(), {}))
        return theta

    def sim_params(self, design: Membrane, experiment: str = "force", trial_index: int = 0) -> SimParams:
        """The truth's simulator inputs for one trial (mechanical effects applied)."""
        ctx = fx.Context(experiment=experiment, trial_index=trial_index, design=design)
        return fx.apply_sim_params(self.effects, self._theta(design), self.base_params, ctx)

    def truth_plane(self, design: Membrane, params: SimParams | None = None) -> TruthPlane:
        """The simulator plane of a membrane under ``params`` (memoised, optionally on disk)."""
        params = self.sim_params(design) if params is None else params
        h_grid, p_grid = self.protocol.grids(design)
        ident = json.dumps(
            {
                "design": design.key(),
                "params": _params_dict(params),
                "h": h_grid.tolist(),
                "p": p_grid.tolist(),
                "format": 2,
                "sim": simulator_fingerprint() if self.simulator is _force_plane else repr(self.simulator),
            },
            sort_keys=True,
        )
        key = hashlib.sha256(ident.encode()).hexdigest()[:24]
        if key in self._planes:
            return self._planes[key]
        path = self.cache_dir / f"plane_{key}.npz" if self.cache_dir is not None else None
        if path is not None and path.is_file():
            plane = TruthPlane.from_npz(path)
        else:
            res = self.simulator(design, h_grid, p_grid, params)
            zero = np.zeros((len(h_grid), 1))
            plane = TruthPlane(
                h_grid=h_grid,
                p_grid=np.concatenate([[0.0], p_grid]),
                force_n=np.concatenate([zero, np.asarray(res.force_n, float)], axis=1),
                locking=np.concatenate([zero, np.asarray(res.max_locking, float)], axis=1),
                rise_mm=np.concatenate([zero, np.asarray(res.max_rise_mm, float)], axis=1),
                status=np.concatenate(
                    [zero.astype(np.int8) + int(Status.NO_CONTACT), np.asarray(res.status, np.int8)], axis=1
                ),
            )
            if path is not None:
                path.parent.mkdir(parents=True, exist_ok=True)
                plane.to_npz(path)
        self._planes[key] = plane
        return plane

    # -- sampling ----------------------------------------------------------------------------
    def _rng(self, design: Membrane, experiment: str) -> np.random.Generator:
        words = [self.seed, zlib.crc32(design.key().encode()), zlib.crc32(experiment.encode())]
        return np.random.default_rng(np.random.SeedSequence(words))

    def _ramp(self, p_end: float) -> tuple[np.ndarray, np.ndarray, np.ndarray]:
        """(time, pressure set-point, deflating?) of one inflation (and deflation) to ``p_end`` [Pa]."""
        pr = self.protocol
        dt = 1.0 / pr.sample_hz
        n_up = int(np.floor(p_end / pr.ramp_pa_per_s * pr.sample_hz + 1e-9)) + 1
        t = np.arange(n_up) * dt
        p = np.minimum(pr.ramp_pa_per_s * t, p_end)
        down = np.zeros(n_up, bool)
        if pr.deflate:
            td = np.arange(1, n_up) * dt
            t = np.concatenate([t, t[-1] + td])
            p = np.concatenate([p, np.maximum(p[-1] - pr.ramp_pa_per_s * td, 0.0)])
            down = np.concatenate([down, np.ones(len(td), bool)])
        return t, p, down

    def _measurement(self, design: Membrane) -> tuple[tuple, dict]:
        """The measurement effects (static for JIT) and their theta as JAX scalars (traced)."""
        per = fx.split_theta(self.effects, self._theta(design))
        effects = tuple(e for e in self.effects if e.acts_on_measurement)
        theta = {e.name: {k: jnp.asarray(v, float) for k, v in per[e.name].items()} for e in effects}
        return effects, theta

    def _lookup(self, plane: TruthPlane, values, h, p) -> np.ndarray:
        """``values`` of the truth plane at set-points ``(h, p)`` (NumPy)."""
        n, size = len(p), self._size
        return np.asarray(_plane_at(plane, values, _pad(np.broadcast_to(h, (n,)), size), _pad(p, size)))[:n]

    def _branch(self, plane: TruthPlane, h_star: np.ndarray, p) -> np.ndarray:
        """Height [mm] of the truth's quasi-static lift branch at pressures ``p`` (from ``h_star``
        on the plane's pressures, :meth:`TruthPlane.lift_height`)."""
        return np.asarray(plane.along_p(h_star, _pad(p, self._size)))[: len(p)]

    def _rows(self, experiment: str, trial: int, h, p, down) -> fx.Rows:
        """Set-point rows of one trial, padded to the rig's one length."""
        n, size = len(p), self._size
        return fx.Rows(
            h_mm=_pad(np.broadcast_to(h, (n,)), size),
            p_pa=_pad(p, size),
            is_force=jnp.full(size, experiment == "force"),
            is_deflate=_pad(down, size, bool),
            is_first_trial=jnp.full(size, trial == 0),
            membrane=jnp.zeros(size, jnp.int32),
        )

    def _record_force(self, design, trial, plane, h_set, p_set, down) -> np.ndarray:
        effects, theta = self._measurement(design)
        f = _recorded_force(effects, theta, plane, self._rows("force", trial, h_set, p_set, down))
        return np.asarray(f)[: len(p_set)]

    def _record_lift(self, design, trial, plane, load, h_branch, p_set, down) -> np.ndarray:
        # Start each root find on the truth's branch; a resting (pinned) plate starts 1 mm
        # into its support (top stop), where the spring, not a flat force, sets the slope.
        top = float(self.protocol.lift_height_max_mm)
        start = np.where(h_branch <= 0.0, -1.0, np.where(h_branch >= top, top + 1.0, h_branch))
        effects, theta = self._measurement(design)
        rows = self._rows("lift", trial, start, p_set, down)
        h = _recorded_height(effects, theta, plane, rows, jnp.asarray(load, float), rows.h_mm, top)
        return np.asarray(h)[: len(p_set)]

    def _noisy(self, experiment, h, p, f, rng) -> tuple[np.ndarray, np.ndarray, np.ndarray]:
        """Sensor noise and quantisation on the recorded values (a lift's force is the known
        weight of the mass, not a reading)."""
        nz, n = self.noise, len(p)
        h = _quantise(h + nz.height_sd_mm * rng.standard_normal(n), nz.height_step_mm)
        p = _quantise(p + nz.pressure_sd_pa * rng.standard_normal(n), nz.pressure_step_pa)
        if experiment == "force":
            f = _quantise(f + nz.force_sd_n * rng.standard_normal(n), nz.force_step_n)
        return h, p, np.asarray(f, float)

    @staticmethod
    def _frame(design, trial, experiment, t, h_set, h, p, f, down) -> pd.DataFrame:
        n = len(t)
        return pd.DataFrame(
            {
                "design_key": design.key(),
                "trial": np.full(n, trial, dtype=np.int64),
                "experiment": experiment,
                "phase": np.where(down, "deflate", "inflate"),
                "time_s": t,
                "height_set_mm": np.full(n, h_set, float),
                "height_mm": h,
                "pressure_pa": p,
                "force_n": f,
                "weight": np.ones(n),
                "source": "virtual",
            }
        )

    @staticmethod
    def _measurements(frames: list[pd.DataFrame]) -> Measurements:
        if not frames:
            empty = {c: pd.Series(dtype=float) for c in COLUMNS}
            for c in ("design_key", "experiment", "phase", "source"):
                empty[c] = pd.Series(dtype=object)
            empty["trial"] = pd.Series(dtype=np.int64)
            return Measurements(pd.DataFrame(empty))
        return Measurements(pd.concat(frames, ignore_index=True))

    def _threshold(self, design: Membrane) -> float:
        """The membrane's burst threshold (one per membrane, from its own stream)."""
        pr = self.protocol
        return float(pr.burst_locking_mean + pr.burst_locking_sd * self._rng(design, "burst").standard_normal())

    def _burst(self, event, lock, p, threshold) -> bool:
        # Only a usable locking value bursts a membrane; a non-finite one (the simulator
        # failed at that point) is unknown, not a burst.
        lock = np.asarray(lock)
        over = np.nonzero(np.isfinite(lock) & (lock > threshold))[0]
        if not over.size:
            return False
        event.update(
            status="burst", burst_pressure_pa=float(p[over[0]]), burst_locking=float(lock[over[0]]), threshold=threshold
        )
        self.events.append(event)
        log.info(
            "virtual rig: %s burst at %.0f Pa (%s trial %d)",
            event["design_key"],
            p[over[0]],
            event["experiment"],
            event["trial"],
        )
        return True

    def _complete(self, frames, event, end, p_set, keep, frame_args) -> None:
        """Log a trial that ran to its end and keep its usable samples (``frame_args``:
        design, trial, experiment, t, h_set, h, p, f, down)."""
        event.update(
            status="complete",
            end_reason=end,
            n_samples=int(keep.sum()),
            n_omitted=int((~keep).sum()),
            peak_pa=float(np.max(p_set)),
        )
        self.events.append(event)
        if keep.any():
            design, trial, experiment, t, h_set, *arrays = frame_args
            frames.append(self._frame(design, trial, experiment, t[keep], h_set, *(a[keep] for a in arrays)))

    # -- experiments -------------------------------------------------------------------------
    def characterise(self, design: Membrane, first_trial: int = 0) -> Measurements:
        """The force characterisation of one membrane (see the module doc)."""
        enable_x64()  # float64 physics: mfdesign._x64
        return self._characterise(design, first_trial)[0]

    def _characterise(self, design: Membrane, first_trial: int = 0):
        pr = self.protocol
        rng = self._rng(design, "force")
        threshold = self._threshold(design)
        frames, trial = [], first_trial
        for k, p_limit in enumerate(pr.force_limits(design)):
            for h_set in pr.heights_mm:
                for _ in range(pr.trials_per_height):
                    plane = self.truth_plane(design, self.sim_params(design, "force", trial))
                    t, p_set, down = self._ramp(p_limit)
                    end = "pressure_limit"
                    if not design.n_rings:  # ringless: until contact with the rig
                        rise = self._lookup(plane, plane.rise_mm, h_set, p_set)
                        hit = np.nonzero(~down & (rise >= pr.ringless_contact_rise_mm))[0]
                        if hit.size:
                            end = "contact"
                            t, p_set, down = self._ramp(float(p_set[hit[0]]))
                    event = dict(
                        design_key=design.key(),
                        experiment="force",
                        trial=trial,
                        height_set_mm=float(h_set),
                        pressure_limit_pa=float(p_limit),
                        pass_index=k,
                    )
                    if self._burst(event, self._lookup(plane, plane.locking, h_set, p_set), p_set, threshold):
                        return self._measurements(frames), {"next_trial": trial + 1, "burst": True}
                    f = self._record_force(design, trial, plane, float(h_set), p_set, down)
                    h, p, f = self._noisy("force", np.full(len(t), float(h_set)), p_set, f, rng)
                    keep = np.isfinite(f)
                    self._complete(frames, event, end, p_set, keep, (design, trial, "force", t, h_set, h, p, f, down))
                    trial += 1
        return self._measurements(frames), {"next_trial": trial, "burst": False}

    def mass_lift(
        self, design: Membrane, mass_kg: float | Sequence[float] | None = None, first_trial: int = 0
    ) -> Measurements:
        """Mass-lift trials, ``lift_trials`` per mass (default masses: the protocol's)."""
        enable_x64()  # float64 physics: mfdesign._x64
        return self._mass_lift(design, mass_kg, first_trial)[0]

    def _mass_lift(self, design: Membrane, mass_kg=None, first_trial: int = 0):
        pr = self.protocol
        masses = pr.lift_masses_kg if mass_kg is None else [float(m) for m in np.atleast_1d(mass_kg)]
        rng = self._rng(design, "lift")
        threshold = self._threshold(design)
        frames, trial = [], first_trial
        for mass in masses:
            load = float(mass) * G_M_S2
            for _ in range(pr.lift_trials):
                plane = self.truth_plane(design, self.sim_params(design, "lift", trial))
                h_star = plane.lift_height(load)
                t, p_set, down = self._ramp(pr.lift_limit_pa)
                h_branch = self._branch(plane, h_star, p_set)
                end = "pressure_limit"
                top = np.nonzero(~down & (h_branch >= pr.lift_height_max_mm))[0]
                if top.size:  # the plate reached the top of the rig
                    end = "height_limit"
                    t, p_set, down = self._ramp(float(p_set[top[0]]))
                    h_branch = self._branch(plane, h_star, p_set)
                event = dict(design_key=design.key(), experiment="lift", trial=trial, mass_kg=float(mass))
                lock = self._lookup(plane, plane.locking, np.minimum(h_branch, pr.lift_height_max_mm), p_set)
                if self._burst(event, lock, p_set, threshold):
                    return self._measurements(frames), {"next_trial": trial + 1, "burst": True}
                h = self._record_lift(design, trial, plane, load, h_branch, p_set, down)
                h, p, f = self._noisy("lift", h, p_set, np.full(len(t), load), rng)
                keep = np.isfinite(h) & np.isfinite(p)
                self._complete(frames, event, end, p_set, keep, (design, trial, "lift", t, np.nan, h, p, f, down))
                trial += 1
        return self._measurements(frames), {"next_trial": trial, "burst": False}

    def run(
        self, designs: Iterable[Membrane], characterise: bool = True, lift: bool = True, progress: bool = True
    ) -> Measurements:
        """Each membrane: the force characterisation, then (if it did not burst) the mass lifts;
        trial ids continue across the two, so ``trial`` is the order in the membrane's life."""
        enable_x64()  # float64 physics: mfdesign._x64
        from tqdm.auto import tqdm

        frames = []
        for design in tqdm(list(designs), desc="virtual rig", unit="membrane", disable=not progress):
            nxt, burst = 0, False
            if characterise:
                m, info = self._characterise(design, 0)
                frames.append(m.df)
                nxt, burst = info["next_trial"], info["burst"]
            if lift and not burst:
                frames.append(self._mass_lift(design, None, nxt)[0].df)
        frames = [f for f in frames if len(f)]
        return self._measurements(frames)
