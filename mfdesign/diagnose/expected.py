"""The expected observed force at the recorded (height, pressure) of every row, with effects.

This is the forward model that diagnosis compares with measurements: the simulator (or a
cheap stand-in) on one height x pressure plane per membrane and distinct
:class:`~mfdesign.physics.params.SimParams`, interpolated at each row, then the
measurement chain of the effects.

For a row recorded at ``(h_rec, p_rec)`` with effects ``theta``:

1. mechanics: ``params = apply_sim_params(effects, theta, base, Context(experiment, trial))``
   (per trial, so that e.g. stress softening acts on the first trial only);
2. inputs: the measurement effects move the recorded inputs away from the true ones,
   ``h_rec = h_true + dh``, ``p_rec = p_true + dp``. One fixed-point step inverts this:
   ``(dh, dp)`` are evaluated by ``observe`` at the recorded point and
   ``(h_true, p_true) = (h_rec - dh, p_rec - dp)`` (exact for offsets; first order in the
   effect for gains and height shifts);
3. output: ``F_expected = observe(F_sim(h_true, p_true; params)).force_n``.

Query heights: in a force trial the plate is held at ``height_set_mm`` (the recorded
height is a noisy reading of it), so the set-point is used where it is finite; in a lift
the recorded height. Lift rows where the plate rests on its stop (``h < resting_mm``) or
at the top of the rig carry no information on the membrane's push (the force column is
the weight) and are masked (:func:`usable_rows`).

Planes come from :meth:`mfdesign.rig.virtual.VirtualRig.truth_plane` (memoised in
memory and, with ``cache_dir``, on disk): heights every ``h_step_mm`` plus every set
height, pressures every ``p_step_pa`` (the virtual rig's grid, so that its data are
reproduced exactly by the neutral model).
"""

from __future__ import annotations

import dataclasses
import functools
import os
from dataclasses import dataclass, field
from typing import Any, Callable, Mapping, Sequence

import numpy as np
import pandas as pd

from mfdesign.data.measurements import Measurements
from mfdesign.design import Membrane
from mfdesign.physics import effects as fx
from mfdesign.physics.params import SimParams

__all__ = ["PlaneSimulator", "query_heights", "trial_order", "usable_rows"]

RESTING_MM = 1.5  # a lifted plate below this rests on its stop (the sensor reads 0 or 1 mm there)
JUMP_MM = 2.0  # a lifted plate moving more than this between samples is not in equilibrium


def query_heights(meas: Measurements) -> np.ndarray:
    """Plate height [mm] at which the model is asked: set-point in force trials, else recorded."""
    df = meas._df
    hs = df["height_set_mm"].to_numpy(float)
    h = df["height_mm"].to_numpy(float)
    force = (df["experiment"] == "force").to_numpy()
    return np.where(force & np.isfinite(hs), hs, h)


def usable_rows(meas: Measurements, resting_mm: float = RESTING_MM, top_mm: float | None = None,
                jump_mm: float = JUMP_MM) -> np.ndarray:
    """Rows whose force column says something about the membrane's push (bool mask).

    Excludes lift rows with the plate on its stop (``h < resting_mm``), at the rig's top
    (``h >= top_mm``, default: the largest lift height recorded minus 0.5 mm, when several
    rows sit there) or jumping (snap-through: the height changes by more than ``jump_mm``
    from a neighbouring sample of the trial, so the plate is not in equilibrium)."""
    df = meas._df
    lift = (df["experiment"] == "lift").to_numpy()
    h = df["height_mm"].to_numpy(float)
    bad = lift & (h < resting_mm)
    tid = df["design_key"].to_numpy(object).astype(str) + "|" + df["trial"].to_numpy().astype(str)
    same = tid[1:] == tid[:-1]
    dh = np.abs(np.diff(h)) > jump_mm
    jump = np.zeros(len(h), bool)
    jump[1:] |= same & dh
    jump[:-1] |= same & dh
    bad |= lift & jump
    if top_mm is None and lift.any():
        top = float(np.max(h[lift]))
        if np.sum(lift & (h >= top - 0.5)) > 5:
            top_mm = top - 0.5
    if top_mm is not None:
        bad |= lift & (h >= top_mm)
    return ~bad


def trial_order(meas: Measurements) -> np.ndarray:
    """Order of each row's trial in its membrane's life (0 = first trial), int64."""
    df = meas._df
    return df.groupby("design_key", sort=False)["trial"].rank(method="dense").to_numpy(np.int64) - 1


@functools.lru_cache(maxsize=4096)
def _membrane(key: str) -> Membrane:
    return Membrane.from_key(key)


def _params_key(params: SimParams) -> tuple:
    return tuple(float(getattr(params, f.name)) for f in dataclasses.fields(params))


@dataclass
class PlaneSimulator:
    """Expected observed force from simulator planes (see the module doc).

    ``simulator``: ``(design, h_grid, p_grid, params) -> SimResult``-like (``None``: the real
    :func:`~mfdesign.physics.solve.force_plane`; tests pass
    :func:`~mfdesign.rig.virtual.analytic_plane`); ``base_params``: the simulator constants
    of the plain model; ``h_step_mm`` / ``p_step_pa``: plane grid steps; ``cache_dir``:
    optional on-disk memo of planes.
    """

    simulator: Callable | None = None
    base_params: SimParams = field(default_factory=SimParams)
    h_step_mm: float = 10.0
    p_step_pa: float = 250.0
    cache_dir: str | os.PathLike | None = None
    progress: bool = False
    _rigs: dict = field(default_factory=dict, repr=False)
    _n_planes: int = field(default=0, repr=False)

    def _rig(self, meas: Measurements):
        """A VirtualRig whose protocol grid covers the data (memoised by grid)."""
        from mfdesign.rig.virtual import Protocol, VirtualRig

        memo = self._rigs.get(("table", id(meas)))
        if memo is not None and memo[0] is meas:
            return memo[1]
        df = meas._df
        hs = df["height_set_mm"].to_numpy(float)
        sets = tuple(sorted({float(v) for v in hs[np.isfinite(hs)]}))
        h_top = float(np.nanmax(df["height_mm"].to_numpy(float))) + 2.0 if len(df) else 80.0
        p_top = float(np.nanmax(df["pressure_pa"].to_numpy(float))) + 2.0 * self.p_step_pa if len(df) else 1e4
        p_top = self.p_step_pa * np.ceil(p_top / self.p_step_pa)
        key = (sets, np.ceil(h_top / self.h_step_mm), p_top)
        if key not in self._rigs:
            proto = Protocol(heights_mm=sets or (0.0,), ringed_limits_pa=(p_top,), ringless_limit_pa=p_top,
                             lift_limit_pa=p_top, lift_height_max_mm=max(h_top, max(sets, default=0.0)),
                             height_step_mm=self.h_step_mm, pressure_step_pa=self.p_step_pa)
            self._rigs[key] = VirtualRig(protocol=proto, base_params=self.base_params,
                                         simulator=self.simulator, cache_dir=self.cache_dir)
        self._rigs[("table", id(meas))] = (meas, self._rigs[key])
        return self._rigs[key]

    def _trials(self, meas: Measurements) -> dict:
        """Row indices per (design, experiment, trial) and trial order (memoised per table)."""
        memo = self._rigs.get(("trials", id(meas)))
        if memo is not None and memo[0] is meas:
            return memo[1]
        df = meas._df
        val = {"groups": df.groupby(["design_key", "experiment", "trial"], sort=False).indices,
               "order": trial_order(meas), "h": query_heights(meas)}
        self._rigs[("trials", id(meas))] = (meas, val)
        return val

    def plane(self, meas: Measurements, design: Membrane, params: SimParams):
        return self._rig(meas).truth_plane(design, params)

    # -- the forward model ---------------------------------------------------------------
    def expected_force(self, meas: Measurements, effects: Sequence[str | fx.Effect] = (),
                       theta: Mapping[str, Any] | None = None) -> np.ndarray:
        """Expected observed force [N] per row of ``meas`` (NaN where the simulator has none)."""
        effects = [fx.effect(e) for e in effects]
        per_effect = fx.split_theta(effects, theta)  # validates names early
        flat = {f"{k}.{p}": v for k, d in per_effect.items() for p, v in d.items()}
        df = meas._df
        out = np.full(len(df), np.nan)
        tr = self._trials(meas)
        h_q, order = tr["h"], tr["order"]
        p_rec = df["pressure_pa"].to_numpy(float)
        keys = df["design_key"].to_numpy(object)
        exp = df["experiment"].to_numpy(object)
        # trial -> SimParams, then one vectorised pass per (design, experiment, params)
        groups: dict[tuple, list[np.ndarray]] = {}
        params_of: dict[tuple, SimParams] = {}
        for (key, experiment, trial), idx in tr["groups"].items():
            ctx = fx.Context(experiment=experiment, trial_index=int(order[idx[0]]), design=_membrane(key))
            params = fx.apply_sim_params(effects, flat, self.base_params, ctx)
            gk = (key, experiment, _params_key(params))
            params_of[gk] = params
            groups.setdefault(gk, []).append(idx)
        items = list(groups.items())
        if self.progress:
            from tqdm.auto import tqdm

            items = tqdm(items, desc="model planes", unit="group")
        for (key, experiment, _), idx_list in items:
            idx = np.concatenate(idx_list)
            plane = self.plane(meas, _membrane(key), params_of[(key, experiment, _)])
            h, p = h_q[idx], p_rec[idx]
            phase = df["phase"].to_numpy(object)[idx]
            t = df["time_s"].to_numpy(float)[idx]

            def ctx_at(hh, pp):
                return fx.Context(experiment=experiment, trial_index=order[idx], phase=phase, time_s=t,
                                  dF_dh=plane.at(plane.dF_dh, hh, pp), design=_membrane(key))

            if any(e.acts_on_measurement for e in effects):
                f0 = plane.at(plane.force_n, h, p)
                s = fx.apply_observe(effects, flat, fx.Sample(h.copy(), p.copy(), f0), ctx_at(h, p))
                h_t = h - (np.asarray(s.height_mm, float) - h)
                p_t = p - (np.asarray(s.pressure_pa, float) - p)
                h_t = np.clip(h_t, plane.h_grid[0], plane.h_grid[-1])
                p_t = np.clip(p_t, 0.0, plane.p_grid[-1])
                f_t = plane.at(plane.force_n, h_t, p_t)
                s = fx.apply_observe(effects, flat, fx.Sample(h_t, p_t, f_t), ctx_at(h_t, p_t))
                out[idx] = np.asarray(s.force_n, float)
            else:
                pc = np.clip(p, 0.0, plane.p_grid[-1])
                out[idx] = plane.at(plane.force_n, np.clip(h, plane.h_grid[0], plane.h_grid[-1]), pc)
        return out

    def predict(self, meas: Measurements) -> np.ndarray:
        """The plain model (no effects): ``expected_force(meas)``."""
        return self.expected_force(meas)

