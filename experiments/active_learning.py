"""Active-learning loop against the virtual rig (issue 7, item 2; issue 19, item 3): learning curves by arm.

Truth (``--truth``): ``offset``: the bundled dataset's virtual rig (authors' simulator
constants, sensor noise, one hidden effect: pressure-sensor offset 150 Pa). ``hard``
(issue 19): the same offset plus an effect from OUTSIDE the effects library, defined here
(``MouldingSkinFray``, not registered, so no model can name it): moulding adds a 0.25 mm
skin to every membrane (relative thickness ``1 + 0.25 / t``: thin membranes most) and the
fabric rings' cut edges do not bond over 3 mm (ring stiffness ``1 - 3 / w``: narrow rings
most); the nominal simulator is then 6.08 N RMS off on the held-out rows (10.7-12.0 N on
the two ringless membranes, 1.1-2.5 N on the ringed ones), against 1.94 N on ``offset``.
Held-out: the six bundled designs, run on the same virtual rig (fixed across seeds and arms). Every arm starts from the same three
membranes (one per ring count, Latin hypercube in the unit cube, per seed), then runs
``--iters`` rounds of a batch of ``q = 2`` and refits after each:

* ``random``: Latin-hypercube designs, ring count uniform in {0, 1, 2}; fabricated.
* ``rig``: the paper's acquisition (``mfdesign.acquire.propose``, rig fidelity only) on an
  RPN ensemble fitted to the rig data.
* ``fidelity``: acquisition over {rig, sim} with costs {1, ``--cost-sim``} on a
  :class:`~mfdesign.acquire.SplitPredictor`: an RPN ensemble fitted to simulator planes
  (``sim``) plus an RPN ensemble fitted to the rig data minus the sim ensemble's mean
  (``discrepancy``); prediction = sim mean + discrepancy mean. A rig choice fabricates the
  membrane *and* simulates it; a sim choice only simulates. Before round 1 the arm
  simulates ``--warm-sims`` Latin-hypercube designs (cost 0.01 each). Simulator runs
  inform this model directly: the split F = F_sim + delta, with no calibration of theta.
* ``mf-rig``: the paper's acquisition (rig only) on the calibrated multi-fidelity model of
  issue 5 (``mfdesign.calibration.workflow.fit_multi_fidelity``: emcee calibration of mu,
  J_m, the thickness hierarchy and the ``--mf-effects`` through the simulator's emulator,
  or, with ``--simulator simulator``, through the exact force model (simulator planes of the
  fabricated and held-out membranes; the acquisition then searches on the emulator), then
  an RPN discrepancy on the residuals). Default effect: ``pressure_sensor``, the one
  ``mfdesign diagnose`` names on this rig's data (the demo finds it); ``--mf-effects``
  with no name runs the bare model. Its simulator fidelity is the pre-trained emulator, so
  sim runs would add nothing: rig only. Its acquisition runs on a 4 x 4 grid and refines
  ``--mf-refine`` batches (each evaluation runs the emulator for every posterior draw).
* ``mf-random``: the same model on the random arm's kind of designs: the control that
  separates what the physics prior buys from what the acquisition buys.
* ``disc-random`` / ``disc-rig``: the nominal simulator (its emulator, no calibration) + an
  RPN discrepancy ensemble fitted to rig minus simulator; random fabrication (the random
  arm's very designs) / the paper's acquisition on the discrepancy's members (the physics
  is one function for all of them). A cheap stand-in for the mf arms (no MCMC): the
  physics-informed model class, 5 seeds in minutes. Needs ``--simulator emulator``.
* ``rig-protocol`` / ``disc-rig-protocol``: the acquisition of ``rig`` / ``disc-rig`` on
  a predictor whose spread counts only where the rig measures a design (force trials to
  6.1 kPa with rings, 10 kPa without; grid 1-10 kPa): the one change tried after the
  diagnosis (``--diagnose``) of why acquisition did not beat random.

Comparison (issue 19): per model class, random vs acquisition, the membranes each run needs
to reach a target held-out RMSE, fixed before the runs as the mean over seeds of the random
arm's RMSE at its last budget (and ``--target-n``); ratio = random / acquisition per seed,
its median, min-max and IQR over the seeds. A run that never reaches the target within its
budget is censored (count "> last"): the ratio is then an interval, reported as such.
``--diagnose`` refits every acquisition round's model and measures where its members'
spread lies (the share above the design's measured pressures, on proposed / random /
held-out designs), how often proposals sit on the design space's bounds, and the model's
error on its own training rows against the held-out error.

Cost axis: rig membranes count 1, simulator planes ``--cost-sim``. Metric: force RMSE [N]
on the held-out rows that measure F(h, p) (mean prediction): force characterisation and
lifted mass-lift rows; training sees the same kinds of rows
(``mfdesign.calibration.workflow.lifted_rows``, the calibration's rule: a lift row below
2 mm records the mass's weight, not F; kept, such rows put a floor of 4.95 N under the
held-out RMSE of the nominal simulator itself, 1.94 N without them). The plot
also shows the nominal simulator alone (no data). Small ensembles (8 members, 1,500
steps) on a fixed-size resample of the training rows (one compilation for all fits); acquisition
screens 1,000 random batches per ring count and refines the best 32 by 15 L-BFGS
iterations. ``--quick`` swaps the simulator for the analytic stand-in
(``mfdesign.rig.virtual.standin_plane``), fewer steps: a smoke run, not a result.
``--simulator emulator`` (default): the truth rig and the sim fidelity run on the
simulator's emulator (0.5 % of the force range from the simulator, held out; planes in
milliseconds instead of minutes), as the hidden-effect sweep does; ``--simulator simulator``
runs the shooting simulator itself (planes cached in ``$MFDESIGN_CACHE_DIR/rig_planes``).
A checkpoint per (seed, arm) after every iteration (``experiments/out/active_learning_runs/``)
lets a killed run resume (same command), and lets arms run in parallel processes.

    python experiments/active_learning.py [--quick | --simulator emulator] [--seeds 0 1 2] [--iters 6]

The published curves: ``--arms random rig fidelity --iters 6`` (~15 min on the 2-core CPU)
and ``--arms mf-random mf-rig --iters 2`` (~40 min; each fit calibrates by MCMC), one per
core in parallel; then ``--report-only`` writes the JSON/PNG of every run on disk. The mf
arms calibrate through the emulator, so ``--quick`` (analytic truth) is meant for the
other three.

Issue 19 (``--truth hard``, 5 seeds, one process, load 7-11 on the 2 cores):
``--seeds 0 1 2 3 4 --arms random rig disc-random disc-rig --iters 6`` (792 s), then
``--arms rig disc-rig --report-only --diagnose`` (183 s), then the same seeds with
``--arms ... rig-protocol disc-rig-protocol`` (447 s). Target = random's mean final RMSE.
Data-only: 5.97 N; membranes random/acquisition per seed 11/15, >15/11, 13/13, 9/15,
>15/13: ratio median 1.0 (min 0.6). Physics + discrepancy: 2.01 N; 9/9, >15/11, 5/13,
9/5, >15/11: median in [1.45, 1.8] (censored seeds), min 0.38. Diagnosis: in a batch of
ringed proposals 60-79 % of the members' squared spread lies above 6.1 kPa (the grid's 7
and 8 kPa rows), where the rig never holds a ringed membrane's plate: the acquisition
buys membranes for extrapolation that no membrane reduces; 79-82 % of its proposed
unit-cube coordinates sit within 1 % of a bound. The data-only model fits its own rows
2-3x better than the held-out ones (4-5 N vs 7-15 N: it generalises badly from few
membranes); the discrepancy model fits its own rows to 1.2-1.4 N in every round and its
held-out error closes on that (1.70 N at 13 membranes): a floor no design choice lowers.
Spread vs error on held-out rows: Spearman 0.38-0.58, error^2 / spread^2 4-11 (the
ensembles are overconfident). The change (``disc-rig-protocol``): 9/7, >15/5, 5/7, 9/5, >15/9,
median ratio in [1.78, 1.8], min 0.71, IQR from [1.29, 1.29] to [1.8, unbounded]; 1.80 N
at 7 membranes (mean) against 2.50 N for random. The data-only ``rig-protocol`` arm falls
faster (8.9 N at 5 membranes, random 13.7) but stalls at 6-6.4 N and re-proposes built
designs (12-14 membranes fabricated): median in [1.29, 1.86] at 5.97 N.
The mf pair (``--arms mf-random mf-rig --iters 2``, 3,176 s, load 2-10): random fabrication
makes the calibrated model WORSE on this truth (mean 6.22 N at 3 membranes, 7.18 N at 7:
the global calibration bends to the ringed membranes' design-dependent misfit, and the
held-out ringless [2.0, 25.4] membrane goes to 12-21 N); the acquisition picks ringless
membranes with small disks (c = 25.4-26.6 mm) and falls to 3.49 N at 7 (final RMSE ratio
median 2.16, 0.92-5.76 over seeds). Random's rising curve makes the random-final target
degenerate (both reach it with the first 3 membranes on 3 seeds: median 1.0); at the fixed
4 N (``--target-n``, the default before issue 19): >7/5, >7/5, >7/5, 5/5, >7/>7, median
>= 1.6. Its posterior spread tracks its error (Spearman 0.80-0.86 against 0.38-0.58 for the
ensembles; error^2 / spread^2 1.3 for mf-rig).

Writes ``experiments/out/active_learning[_hard][_quick].json`` and ``.png``.
"""

from __future__ import annotations

import json
import zlib

import numpy as np

from _common import Timing, command, parser, timed, write_json  # experiments/ is on a script's path

# after _common, which turns JAX's float64 on
import equinox as eqx  # noqa: E402
import jax.numpy as jnp  # noqa: E402

from mfdesign.models.predictor import AbstractPredictor  # noqa: E402

HIDDEN = ("pressure_sensor", {"pressure_sensor.offset_pa": 150.0, "pressure_sensor.gain": 1.0})


def _moulding_effect():
    """The ``--truth hard`` effect from outside the library (built on first use: importing
    the effects package belongs after ``enable_x64``)."""
    import dataclasses

    from mfdesign.physics.effects import MechanicalEffect, Parameter, Uniform
    from mfdesign.physics.params import SimParams

    class MouldingSkinFray(MechanicalEffect):
        """Gravity moulding leaves a skin of fixed thickness on every membrane, and the cut
        edges of a fabric ring fray and do not bond.

        * ``skin_mm``: the meniscus and the last pour layer add about the same thickness to
          every membrane, so the actual thickness is ``t + skin``: a relative change
          ``skin / t`` that a thin membrane feels most (the library's
          ``thickness_deviation`` is one relative factor for all designs);
        * ``fray_mm``: a band this wide at each cut edge of a ring (half-width ``w``) does
          not bond to the rubber, so the ring carries ``1 - fray / w`` of the fabric's
          stiffness (the mean over a membrane's rings: the simulator has one ring modulus);
          narrow rings lose most (the library's ``ring_softening`` is one factor for all).

        Not registered: the model's effects library cannot name it, so the models must learn
        it from data. It needs the design (``context.design``): the virtual rig passes it.
        """

        name = "moulding_skin_fray"
        story = "moulding adds a fixed skin to every membrane and leaves the fabric rings' cut edges unbonded"
        parameters = (
            Parameter("skin_mm", "mm", Uniform(0.0, 0.6), 0.0, 0.25, "thickness added to every membrane"),
            Parameter("fray_mm", "mm", Uniform(0.0, 4.5), 0.0, 3.0, "unbonded band at each ring edge"),
        )

        def sim_params(self, base: SimParams, theta, context=None) -> SimParams:
            if context is None or context.design is None:
                raise ValueError(f"{self.name} depends on the design: call it with a Context holding one")
            d = np.asarray(context.design.to_array(), float)
            w = d[[3, 5]][np.isfinite(d[[3, 5]])]  # ring half-widths [mm]
            ring = float(np.mean(np.clip(1.0 - theta["fray_mm"] / w, 0.05, 1.0))) if w.size else 1.0
            return dataclasses.replace(
                base,
                thickness_factor=base.thickness_factor * (1.0 + theta["skin_mm"] / d[0]),
                ring_mu_pa=base.ring_mu_pa * ring,
            )

    return MouldingSkinFray()


# The truths (``--truth``): effects (library names or instances) and their parameters.
# ``offset``: the bundled dataset's one library effect. ``hard`` (issue 19): the same
# pressure offset plus the outside effect above (skin 0.25 mm, fray 3 mm): the nominal
# simulator is 10.7-12.0 N RMS off on the two held-out ringless membranes (the thinner the
# worse), 1.1-2.5 N on the four ringed ones (the narrower the rings the worse).
TRUTHS = {
    "offset": (lambda: [HIDDEN[0]], HIDDEN[1]),
    "hard": (
        lambda: [HIDDEN[0], _moulding_effect()],
        {**HIDDEN[1], "moulding_skin_fray.skin_mm": 0.25, "moulding_skin_fray.fray_mm": 3.0},
    ),
}
HELD_OUT = (
    "[2.0, 25.4, nan, nan, nan, nan]",
    "[1.0, 38.1, nan, nan, nan, nan]",
    "[1.5, 30.0, 45.0, 6.0, nan, nan]",
    "[2.0, 25.4, 33.4, 5.0, 46.4, 5.0]",
    "[2.33, 29.63, 37.63, 5.0, 62.0, 5.0]",
    "[2.0, 38.1, 47.55, 6.45, 62.0, 5.0]",
)
ARMS = (
    "random",
    "rig",
    "fidelity",
    "mf-random",
    "mf-rig",
    "disc-random",
    "disc-rig",
    "rig-protocol",
    "disc-rig-protocol",
)
# Arm pairs on one model class: (random fabrication, acquisition).
PAIRS = {
    "data-only": ("random", "rig"),
    "physics + discrepancy": ("disc-random", "disc-rig"),
    "mf": ("mf-random", "mf-rig"),
    "data-only, protocol-aware acquisition": ("random", "rig-protocol"),
    "physics + discrepancy, protocol-aware acquisition": ("disc-random", "disc-rig-protocol"),
}
# The protocol-aware arms' grid: the rig's set heights x 1-10 kPa (a ringless membrane's
# force trials reach the rig's 10 kPa cap; the default grid stops at 8 kPa).
PROTOCOL_GRID_P = tuple(float(p) for p in range(1000, 10001, 1000))
# Options a run's checkpoint must share with the command that resumes it.
SETTINGS = (
    "simulator",
    "q",
    "restarts",
    "refine",
    "lbfgs_steps",
    "members",
    "steps",
    "cost_sim",
    "warm_sims",
    "mcmc_steps",
    "walkers",
    "mf_rows",
    "mf_draws",
    "mf_effects",
    "mf_refine",
)
# The mf arms' acquisition grid: heights 0-60 mm x 2-8 kPa, 4 x 4 (the default 8 x 8 grid
# through 8 posterior draws of the emulator took over 13 minutes per proposal).
MF_GRID_H, MF_GRID_P = (0.0, 20.0, 40.0, 60.0), (2000.0, 4000.0, 6000.0, 8000.0)
_POINT = ("design", "height_mm", "pressure_pa")  # a point's inputs in the row dicts
ROWS_PER_MEMBRANE = 400  # rig rows kept per membrane (the ramps are ~20k samples)
TRAIN_ROWS = 6000  # fixed-size resample: every fit has the same shapes (one compilation)


class Lab:
    """Truth rig, nominal simulator and the held-out set for one experiment."""

    def __init__(self, simulator: str, truth: str = "offset"):
        from mfdesign.design import Membrane
        from mfdesign.models.standin import standin_plane
        from mfdesign.rig.virtual import VirtualRig

        if simulator == "emulator":
            from mfdesign.diagnosis.forward import emulator_plane
            from mfdesign.models.emulator import load_default

            sim = emulator_plane(load_default())
        else:
            sim = standin_plane if simulator == "analytic" else None
        from mfdesign.physics.planes import cache_dir

        cache = cache_dir().parent / "rig_planes" if simulator == "simulator" else None  # $MFDESIGN_CACHE_DIR
        self.simulator = simulator
        effects, theta = TRUTHS[truth]
        self.truth = VirtualRig(effects=effects(), theta=theta, seed=777, simulator=sim, cache_dir=cache)
        self.nominal = VirtualRig(simulator=sim, cache_dir=cache)
        from mfdesign.calibration.workflow import lifted_rows

        held = lifted_rows(self.truth.run([Membrane.from_key(k) for k in HELD_OUT], progress=False)).arrays()
        self._rows: dict = {}
        self.held = {k: v[::5] for k, v in held.items() if k in ("design", "height_mm", "pressure_pa", "force_n")}

    def nominal_force(self, design, h_mm, p_pa) -> np.ndarray:
        """The nominal simulator's force [N] at points, through its emulator (the disc arms'
        physics; it needs ``--simulator emulator``: the truth's own physics, pointwise)."""
        import jax.numpy as jnp

        from mfdesign.models.emulator import load_default

        if self.simulator != "emulator":
            raise SystemExit("the disc arms need --simulator emulator (a pointwise nominal simulator)")
        f = load_default()(jnp.asarray(design), jnp.asarray(h_mm), jnp.asarray(p_pa), self.nominal.base_params)
        return np.asarray(f)

    def simulator_rmse(self) -> float | None:
        """Held-out RMSE [N] of the nominal simulator alone (the truth's physics at the
        truth's constants, no data, no discrepancy): the zero-membrane reference of a physics
        model. None for the analytic stand-in."""
        h = self.held
        if self.simulator == "simulator":
            # The exact force model (simulator planes of the held-out membranes, within
            # 0.01 N of direct calls): one plane per membrane instead of a shooting solve
            # per row (force_at on every held-out row took > 12 min).
            import jax.numpy as jnp

            from mfdesign.design import Membrane
            from mfdesign.models.backends import force_model_for

            keys = tuple(dict.fromkeys(Membrane.from_array(d).key() for d in h["design"]))
            fm = force_model_for(
                "exact",
                keys,
                h_max_mm=float(np.max(h["height_mm"])),
                p_max_pa=float(np.max(h["pressure_pa"])),
                base=self.nominal.base_params,
            )
            f = np.asarray(
                fm(
                    jnp.asarray(h["design"]),
                    jnp.asarray(h["height_mm"]),
                    jnp.asarray(h["pressure_pa"]),
                    self.nominal.base_params,
                )
            )
            return float(np.sqrt(np.nanmean((f - h["force_n"]) ** 2)))
        if self.simulator != "emulator":
            return None
        import jax.numpy as jnp

        from mfdesign.models.emulator import load_default

        f = load_default()(
            jnp.asarray(h["design"]),
            jnp.asarray(h["height_mm"]),
            jnp.asarray(h["pressure_pa"]),
            self.nominal.base_params,
        )
        return float(np.sqrt(np.mean((np.asarray(f) - h["force_n"]) ** 2)))

    def fabricate(self, design, seed: int) -> dict:
        """Rig rows of one membrane (force characterisation + mass lifts), subsampled."""
        a = self.table(design, seed).arrays()
        out = {k: a[k] for k in ("design", "height_mm", "pressure_pa", "force_n")}
        # Sensor noise (10 Pa) puts a few readings at the start of a ramp below zero gauge;
        # the monotone head needs p >= 0, and nothing acts below zero: read them as 0.
        out["pressure_pa"] = np.maximum(out["pressure_pa"], 0.0)
        return out

    def table(self, design, seed: int):
        """The same rows as a Measurements table (what the multi-fidelity fit reads)."""
        from mfdesign.data.measurements import Measurements

        memo = (design.key(), seed)
        if memo not in self._rows:
            self.truth.seed = 1000 + seed
            from mfdesign.calibration.workflow import lifted_rows

            m = lifted_rows(self.truth.run([design], progress=False))
            rng = np.random.default_rng([seed, zlib.crc32(design.key().encode())])
            keep = np.sort(rng.choice(len(m), size=min(ROWS_PER_MEMBRANE, len(m)), replace=False))
            self._rows[memo] = Measurements(m.df.iloc[keep].reset_index(drop=True))
        return self._rows[memo]

    def simulate(self, design) -> dict:
        """Simulator plane of one membrane: converged points up to the rig's pressure limit."""
        plane = self.nominal.truth_plane(design)
        p_top = max(self.nominal.protocol.force_limits(design))
        H, P = np.meshgrid(plane.h_grid, plane.p_grid, indexing="ij")
        ok = np.isfinite(plane.force_n) & (P <= p_top + 1e-9)
        n = int(ok.sum())
        return {
            "design": np.repeat(design.to_array()[None], n, 0),
            "height_mm": H[ok],
            "pressure_pa": P[ok],
            "force_n": plane.force_n[ok],
        }


def _mf_grid():
    from mfdesign.acquire import Grid

    return Grid(h_mm=MF_GRID_H, p_pa=MF_GRID_P)


def _cat(parts: list[dict]) -> dict:
    return {k: np.concatenate([p[k] for p in parts]) for k in parts[0]}


def _resample(data: dict, rng) -> dict:
    idx = rng.choice(len(data["force_n"]), size=TRAIN_ROWS, replace=True)
    return {k: v[idx] for k, v in data.items()}


def _fit(cfg, data, seed):
    from mfdesign.models.ensemble import fit_ensemble

    d = _resample(data, np.random.default_rng(seed))
    return fit_ensemble(cfg, d["design"], d["height_mm"], d["pressure_pa"], d["force_n"], key=seed, progress=False)


class Model:
    """The arm's model: rig ensemble, sim ensemble + discrepancy ensemble, or (``mf*`` arms)
    the calibrated multi-fidelity model of issue 5."""

    def __init__(self, arm, rig_data, sim_data, cfgs, seed, tables=None, args=None, lab=None):
        import jax.numpy as jnp

        from mfdesign.acquire import EnsemblePredictor, SplitPredictor

        self.arm = arm
        if arm.startswith("mf"):
            from mfdesign.calibration.workflow import fit_multi_fidelity, force_model_named
            from mfdesign.data.measurements import Measurements

            table = Measurements.concat(tables)
            if args.simulator == "simulator":
                # Truth on simulator planes: calibrate on exact physics, whose planes cover the
                # fabricated membranes and the held-out ones (the metric); the acquisition
                # searches new designs on the emulator (``for_search``), the CLI's split.
                from mfdesign.calibration.workflow import for_search
                from mfdesign.models.backends import force_model_for

                h_held, p_held = args.held_ranges
                keys = tuple(dict.fromkeys([*table.df["design_key"], *HELD_OUT]))
                fm = force_model_for(
                    "exact",
                    keys,
                    h_max_mm=max(float(table.df["height_mm"].max()), h_held),
                    p_max_pa=max(float(table.df["pressure_pa"].max()), p_held),
                )
            else:
                fm = force_model_named("emulator")
            fit = fit_multi_fidelity(
                table,
                fm,
                tuple(args.mf_effects),
                n_steps=args.mcmc_steps,
                n_walkers=args.walkers,
                max_rows=args.mf_rows,
                ensemble_config=cfgs["disc"],
                seed=seed,
                progress=False,
            )
            self.mf = fit.mf
            search = for_search(fit) if args.simulator == "simulator" else fit.mf
            self.predictor = search.predictor(n_draws=args.mf_draws)
            # 32 draws: the mean over them is what the metric needs, at a quarter of the cost.
            self.members = lambda d, h, p: np.asarray(self.mf.thinned(32).predict(d, h, p))
            return
        if arm.startswith("disc"):
            # The nominal simulator (no calibration) + an RPN discrepancy fitted to rig minus
            # simulator: the physics is one function for every member, so the members'
            # spread, what the acquisition reads, is the discrepancy ensemble's.
            nominal = lab.nominal_force
            resid = dict(rig_data, force_n=rig_data["force_n"] - nominal(*(rig_data[k] for k in _POINT)))
            self.disc = _fit(cfgs["disc"], resid, seed)
            self.predictor = EnsemblePredictor(self.disc)
            self.members = lambda d, h, p: nominal(d, h, p)[None] + np.asarray(self.disc.predict(jnp.asarray(d), h, p))
            return
        if arm != "fidelity":
            self.ens = _fit(cfgs["rig"], rig_data, seed)
            self.predictor = EnsemblePredictor(self.ens)
            self.members = lambda d, h, p: np.asarray(self.ens.predict(jnp.asarray(d), h, p))
            return
        self.sim = _fit(cfgs["rig"], sim_data, seed)
        s = np.asarray(
            self.sim.predict(jnp.asarray(rig_data["design"]), rig_data["height_mm"], rig_data["pressure_pa"]).mean(0)
        )
        resid = dict(rig_data, force_n=rig_data["force_n"] - s)
        self.disc = _fit(cfgs["disc"], resid, seed + 1)
        self.predictor = SplitPredictor(self.sim, self.disc)
        self.members = lambda d, h, p: np.asarray(self.predictor.members("rig", jnp.asarray(d), h, p))

    def predict(self, d, h, p) -> np.ndarray:
        """Mean prediction [N] at points."""
        return self.members(d, h, p).mean(0)


class ProtocolPredictor(AbstractPredictor):
    """The arm's predictor scored only where the rig measures a design: its force trials
    run to ``ringed_p_max_pa`` (a ringed membrane) or ``ringless_p_max_pa`` [Pa]; beyond,
    every member is set to 0, so the members agree there and the point adds no deviation.
    The acquisition then stops buying membranes for a spread that their data cannot reduce
    (a ringed membrane's forces above 6.1 kPa are never measured, only extrapolated)."""

    inner: AbstractPredictor
    ringed_p_max_pa: float = eqx.field(static=True)
    ringless_p_max_pa: float = eqx.field(static=True)

    @classmethod
    def of(cls, inner, lab):
        pr = lab.truth.protocol
        return cls(inner, float(max(pr.ringed_limits_pa)), float(pr.ringless_limit_pa))

    @property
    def fidelities(self):
        return self.inner.fidelities

    def _limit(self, design):
        return jnp.where(jnp.isfinite(design[..., 2]), self.ringed_p_max_pa, self.ringless_p_max_pa)

    def members(self, fidelity, design, h_mm, p_pa):
        m = self.inner.members(fidelity, design, h_mm, p_pa)
        return jnp.where(jnp.asarray(p_pa) <= self._limit(design), m, 0.0)

    def grid_members(self, fidelity, design, grid):
        m = self.inner.grid_members(fidelity, design, grid)  # [M, B, G]
        p = jnp.asarray(grid.points()[1])
        return jnp.where(p[None, :] <= self._limit(design)[:, None], m, 0.0)


def _lhs(rng, n, dim):
    from scipy.stats import qmc

    return qmc.LatinHypercube(d=dim, seed=rng).random(n)


def warm_sims(seed, n):
    """``n`` Latin-hypercube designs (ring counts in turn) for the fidelity arm's first sims."""
    from mfdesign.design import DesignSpace

    space, rng = DesignSpace(), np.random.default_rng(20_000 + seed)
    return [space.decode(_lhs(rng, 1, space.dim(i % 3))[0], i % 3) for i in range(n)]


def initial_designs(seed):
    from mfdesign.design import DesignSpace

    space, rng = DesignSpace(), np.random.default_rng(10_000 + seed)
    return [space.decode(_lhs(rng, 1, space.dim(n))[0], n) for n in (0, 1, 2)]


def _unmeasured_share(predictor, designs, limit, grid) -> np.ndarray:
    """Per design [B]: the share of the members' squared deviation on ``grid`` (what the
    acquisition scores) that lies above the design's force-trial pressure limit [Pa],
    where the rig never holds the plate: spread a fabricated membrane cannot reduce."""
    from mfdesign.acquire import _grid_members

    d = jnp.asarray(np.stack([m.to_array() for m in designs]))
    m = np.asarray(_grid_members(predictor, "rig", d, grid))  # [M, B, G]
    dev2 = (m - m.mean(0, keepdims=True)) ** 2
    lim = np.array([limit(x) for x in designs])[:, None]
    above = grid.points()[1][None, :] > lim
    return (dev2 * above[None]).sum((0, 2)) / dev2.sum((0, 2))


def diagnose(lab, results, args, cfgs, arms=("rig", "disc-rig"), n_random=120) -> dict:
    """Why the acquisition does or does not beat random (refits each acquisition round's
    model, as the run did: same seeds, same rows): per round, the unmeasured share
    (:func:`_unmeasured_share`) of the designs it proposed, of random designs and of the
    held-out designs; and how often a proposed coordinate sits on the design space's
    bounds (uncertainty sampling's pull to the box's faces)."""
    from mfdesign.acquire import Grid
    from mfdesign.design import DesignSpace, Membrane

    space, grid, pr = DesignSpace(), Grid(), lab.truth.protocol
    limit = lambda m: max(pr.force_limits(m))  # noqa: E731
    rng = np.random.default_rng(0)
    rand = [space.decode(_lhs(rng, 1, space.dim(n))[0], n) for n in rng.integers(0, 3, size=n_random)]
    held = [Membrane.from_key(k) for k in HELD_OUT]
    out: dict = {}
    for arm in arms:
        rows = []
        for seed in sorted(results):
            curve = results[seed].get(arm, {}).get("curve", [])
            keys = results[seed][arm]["rig"] if curve else []
            for pt in curve:
                if not pt.get("proposed"):
                    continue
                it, n = pt["iteration"], pt["membranes"]
                rig_data = _cat([lab.fabricate(Membrane.from_key(k), seed) for k in keys[:n]])
                model = Model(arm, rig_data, None, cfgs, seed * 100 + it, None, args, lab)
                prop = [Membrane.from_key(k) for k, _ in pt["proposed"]]
                fit_err = model.predict(*(rig_data[k] for k in _POINT)) - rig_data["force_n"]
                h = lab.held
                held_err = model.predict(h["design"], h["height_mm"], h["pressure_pa"]) - h["force_n"]
                u = np.concatenate([space.encode(m) for m in prop])  # unit-cube coordinates
                rows.append(
                    {
                        "seed": seed,
                        "membranes": n,
                        "proposed": float(_unmeasured_share(model.predictor, prop, limit, grid).mean()),
                        "random": float(_unmeasured_share(model.predictor, rand, limit, grid).mean()),
                        "held_out": float(_unmeasured_share(model.predictor, held, limit, grid).mean()),
                        "proposed_rings": [m.n_rings for m in prop],
                        # the fabricated rows' own RMSE [N]: near the held-out one, the model
                        # is limited by its fit, not by which membranes it saw
                        "train_rmse_n": float(np.sqrt(np.mean(fit_err**2))),
                        "held_out_rmse_n": float(np.sqrt(np.mean(held_err**2))),
                        "held_out_rmse_n_run": pt["rmse_n"],
                        "proposed_at_bounds": float(np.mean((u < 0.01) | (u > 0.99))) if u.size else None,
                    }
                )
                print(f"diagnose {arm} seed {seed} n {n}: {rows[-1]}", flush=True)
        out[arm] = {
            "rounds": rows,
            "unmeasured_share_mean": {
                k: float(np.mean([r[k] for r in rows])) for k in ("proposed", "random", "held_out")
            },
            "ringless_share_proposed": float(np.mean([r == 0 for x in rows for r in x["proposed_rings"]])),
            "train_over_held_out_rmse_mean": float(np.mean([r["train_rmse_n"] / r["held_out_rmse_n"] for r in rows])),
        }
    return out


def run_arm(lab, arm, seed, args, cfgs, state) -> dict:
    """Run (or resume) one arm for one seed; ``state`` is the checkpoint dict of this run."""
    from mfdesign.acquire import Grid, propose
    from mfdesign.design import DesignSpace, Membrane

    space = DesignSpace()
    # disc-random fabricates the random arm's designs: one model class apart, same membranes.
    rng = np.random.default_rng([seed, ARMS.index("random" if arm == "disc-random" else arm)])
    rig_keys = state.setdefault("rig", [d.key() for d in initial_designs(seed)])
    # The fidelity arm simulates its membranes and --warm-sims Latin-hypercube designs first
    # (cost 0.01 each): a sim ensemble fitted to three planes cannot tell designs apart.
    sim_keys = state.setdefault(
        "sim", list(rig_keys) + [d.key() for d in warm_sims(seed, args.warm_sims)] if arm == "fidelity" else []
    )
    curve = state.setdefault("curve", [])
    costs = {"rig": 1.0, "sim": args.cost_sim}
    while True:
        it = len(curve)
        mf = arm.startswith("mf")  # the mf arms read Measurements tables, not arrays
        rig_data = None if mf else _cat([lab.fabricate(Membrane.from_key(k), seed) for k in rig_keys])
        sim_data = _cat([lab.simulate(Membrane.from_key(k)) for k in sim_keys]) if sim_keys else None
        with timed() as t:
            tables = [lab.table(Membrane.from_key(k), seed) for k in rig_keys] if mf else None
            model = Model(arm, rig_data, sim_data, cfgs, seed * 100 + it, tables, args, lab)
        fit_s = t["wall_s"]
        h = lab.held
        members = model.members(h["design"], h["height_mm"], h["pressure_pa"])
        err = members.mean(0) - h["force_n"]
        rmse = float(np.sqrt(np.mean(err**2)))
        cost = len(rig_keys) + args.cost_sim * len(sim_keys)
        if len(curve) == it:
            curve.append(
                {
                    "iteration": it,
                    "membranes": len(rig_keys),
                    "sims": len(sim_keys),
                    "cost": cost,
                    "rmse_n": rmse,
                    "fit_s": fit_s,
                    **uncertainty_vs_error(members, h),
                }
            )
        print(
            f"seed {seed} {arm:8s} it {it}: {len(rig_keys)} membranes, {len(sim_keys)} sims, cost {cost:.2f}: "
            f"held-out RMSE {rmse:.2f} N (fit {fit_s:.1f} s)",
            flush=True,
        )
        if it >= args.iters:
            return state
        with timed() as t:
            if arm in ("random", "mf-random", "disc-random"):
                new = [(space.decode(_lhs(rng, 1, space.dim(n))[0], n), "rig") for n in rng.integers(0, 3, size=args.q)]
            else:
                fids = ("rig", "sim") if arm == "fidelity" else ("rig",)
                cheap = arm.startswith("mf")  # every evaluation runs the emulator for each posterior draw
                protocol = arm.endswith("-protocol")
                prop = propose(
                    ProtocolPredictor.of(model.predictor, lab) if protocol else model.predictor,
                    args.q,
                    fidelities=fids,
                    costs=costs,
                    n_restarts=args.restarts,
                    n_refine=args.mf_refine if cheap else args.refine,
                    n_steps=args.lbfgs_steps,
                    grid=_mf_grid() if cheap else (Grid(p_pa=PROTOCOL_GRID_P) if protocol else Grid()),
                    key=seed * 1000 + it,
                )
                new = list(zip(prop.designs, prop.fidelities))
        curve[-1]["propose_s"] = t["wall_s"]
        curve[-1]["proposed"] = [[d.key(), f] for d, f in new]
        for d, f in new:
            if f == "rig" and d.key() not in rig_keys:
                rig_keys.append(d.key())
            if arm == "fidelity" and d.key() not in sim_keys:
                sim_keys.append(d.key())  # a fabricated membrane is simulated too
        args.save()  # checkpoint after each iteration


def uncertainty_vs_error(members, held) -> dict:
    """Does the members' spread track the mean's error on the held-out rows? The
    acquisition fabricates where members disagree; that buys accuracy only where the
    disagreement is where the error is. Per held-out membrane: RMSE [N] and RMS member
    std [N]; over the rows: Spearman rank correlation of |error| and std, and
    ``z2 = mean(error^2) / mean(std^2)`` (1 for a calibrated spread, >> 1 overconfident)."""
    from scipy.stats import spearmanr

    err = members.mean(0) - held["force_n"]
    std = members.std(0)
    keys = [json.dumps([None if np.isnan(x) else round(float(x), 4) for x in d]) for d in held["design"]]
    by = {}
    for k in dict.fromkeys(keys):
        sel = np.array([kk == k for kk in keys])
        by[k] = {"rmse_n": float(np.sqrt(np.mean(err[sel] ** 2))), "std_n": float(np.sqrt(np.mean(std[sel] ** 2)))}
    return {
        "by_design": by,
        "spearman_abs_err_std": float(spearmanr(np.abs(err), std).statistic) if std.max() > 0 else None,
        "z2": float(np.mean(err**2) / max(np.mean(std**2), 1e-30)),
    }


def summarise(results, args) -> dict:
    target = args.target_n
    summary = {}
    for arm in ARMS:
        runs = [results[s][arm]["curve"] for s in results if arm in results[s] and results[s][arm].get("curve")]
        if not runs:
            continue
        first = []
        for c in runs:
            hit = [p for p in c if p["rmse_n"] <= target]
            first.append(hit[0]["membranes"] if hit else None)
        finals = [c[-1]["rmse_n"] for c in runs]
        by_n: dict = {}
        for c in runs:
            for pt in c:
                by_n.setdefault(pt["membranes"], []).append(pt["rmse_n"])
        summary[arm] = {
            "seeds": len(runs),
            "final_rmse_n_mean": float(np.mean(finals)),
            "final_membranes": [c[-1]["membranes"] for c in runs],
            "rmse_n_by_membranes": {
                str(n): {"mean": float(np.mean(v)), "runs": len(v)} for n, v in sorted(by_n.items())
            },
            "final_rmse_n": finals,
            "membranes_to_target": first,
            "final_cost_mean": float(np.mean([c[-1]["cost"] for c in runs])),
            # does the members' spread track the error on held-out rows (every fit of every seed)?
            "spearman_abs_err_std_mean": _mean_of(runs, "spearman_abs_err_std"),
            "z2_median": _median_of(runs, "z2"),
        }
    return summary


def _mean_of(runs, key):
    v = [p[key] for c in runs for p in c if p.get(key) is not None]
    return float(np.mean(v)) if v else None


def _median_of(runs, key):
    v = [p[key] for c in runs for p in c if p.get(key) is not None]
    return float(np.median(v)) if v else None


def _needed(curve, target) -> tuple[int, float]:
    """Membranes a run needs to reach ``target`` [N]: (n, n) at its first checkpoint at or
    below it; (last + 1, inf) when it never does within its budget (censored: more than it
    fabricated, not a number)."""
    hit = [p["membranes"] for p in curve if p["rmse_n"] <= target]
    return (hit[0], hit[0]) if hit else (curve[-1]["membranes"] + 1, np.inf)


def compare(results, args) -> dict:
    """Per model class, random vs acquisition: membranes to the target on each seed and
    their ratio random / acquisition (ratio > 1: the acquisition needs fewer).

    Targets: ``random-final`` (fixed before the runs): the mean over seeds of the random
    arm's held-out RMSE at its last budget -- what random fabrication reaches, on average,
    with all its membranes; and the fixed ``--target-n``. A run that never reaches a target
    is censored: its count is only a lower bound, so a seed's ratio is an interval
    ``[lo, hi]`` and the median over seeds too (lo = hi where nothing is censored)."""
    out = {}
    for name, (rand, acq) in PAIRS.items():
        seeds = sorted(
            s for s in results if results[s].get(rand, {}).get("curve") and results[s].get(acq, {}).get("curve")
        )
        if not seeds:
            continue
        curves = {a: {s: results[s][a]["curve"] for s in seeds} for a in (rand, acq)}
        final = float(np.mean([curves[rand][s][-1]["rmse_n"] for s in seeds]))
        pair = {"random_arm": rand, "acquisition_arm": acq, "seeds": seeds}
        # At each run's last budget, per seed: random's RMSE / the acquisition's (> 1: the
        # acquisition is better); what to read where a curve is not monotone (the mf arms).
        # An arm that re-proposed a built design fabricated fewer ("final_membranes").
        fr = [curves[rand][s][-1]["rmse_n"] / curves[acq][s][-1]["rmse_n"] for s in seeds]
        pair["final_rmse_ratio"] = {
            "per_seed": dict(zip(map(str, seeds), fr)),
            "median": float(np.median(fr)),
            "min_max": [float(min(fr)), float(max(fr))],
        }
        for rule, target in (("random-final", final), ("fixed", args.target_n)):
            per, lo, hi = {}, [], []
            for s in seeds:
                (r_lo, r_hi), (a_lo, a_hi) = (_needed(curves[a][s], target) for a in (rand, acq))
                lo.append(r_lo / a_hi)
                hi.append(r_hi / a_lo)
                per[str(s)] = {
                    "random_membranes": r_lo if np.isfinite(r_hi) else f">{r_lo - 1}",
                    "acquisition_membranes": a_lo if np.isfinite(a_hi) else f">{a_lo - 1}",
                    "ratio": [lo[-1], hi[-1] if np.isfinite(hi[-1]) else None],
                }
            lo_a, hi_a = np.asarray(lo), np.asarray(hi)
            pair[rule] = {
                "target_n": target,
                "per_seed": per,
                "ratio_median": [float(np.median(lo_a)), _finite(np.median(hi_a))],
                "ratio_min_max": [float(lo_a.min()), _finite(hi_a.max())],
                # "nearest": no interpolation across unbounded (inf) upper bounds; with 5 seeds
                # the quartiles are order statistics 2 and 4 either way.
                "ratio_iqr": {
                    q: [
                        float(np.percentile(lo_a, q, method="nearest")),
                        _finite(np.percentile(hi_a, q, method="nearest")),
                    ]
                    for q in (25, 75)
                },
                "censored_runs": int(np.sum(~np.isfinite(hi_a))) + int(np.sum(lo_a == 0)),
            }
        out[name] = pair
    return out


def _finite(x):
    return float(x) if np.isfinite(x) else None


def plot(results, summary, pairs, args, path):
    """Learning curves: one panel per model class (mean over seeds, band min-max), the
    targets, the nominal simulator alone; plus the fidelity arm on the data-only panel."""
    import matplotlib

    matplotlib.use("Agg")
    import matplotlib.pyplot as plt

    colours = {
        "random": "tab:gray",
        "rig": "tab:blue",
        "fidelity": "tab:orange",
        "mf-random": "tab:olive",
        "mf-rig": "tab:red",
        "disc-random": "tab:brown",
        "disc-rig": "tab:purple",
        "rig-protocol": "tab:cyan",
        "disc-rig-protocol": "tab:pink",
    }
    # One panel per model class: its random arm, its acquisition arms, its pairs' ratios.
    classes = {
        "data-only": ("random", "rig", "rig-protocol", "fidelity"),
        "physics + discrepancy": ("disc-random", "disc-rig", "disc-rig-protocol"),
        "mf": ("mf-random", "mf-rig"),
    }
    panels = [(n, arms) for n, arms in classes.items() if any(a in summary for a in arms)]
    fig, axes = plt.subplots(1, len(panels), figsize=(5.5 * len(panels), 4.8), squeeze=False)
    for ax, (name, arms) in zip(axes[0], panels):
        for arm in arms:
            curves = [results[s][arm]["curve"] for s in results if results[s].get(arm, {}).get("curve")]
            if not curves:
                continue
            by_n: dict = {}
            for c in curves:
                for pt in c:
                    by_n.setdefault(pt["membranes"], []).append(pt["rmse_n"])
            n = sorted(by_n)
            v = [np.asarray(by_n[k]) for k in n]
            ax.plot(n, [x.mean() for x in v], "o-", color=colours[arm], ms=3, label=f"{arm} ({len(curves)} seeds)")
            ax.fill_between(n, [x.min() for x in v], [x.max() for x in v], color=colours[arm], alpha=0.2)
        for pname, pair in pairs.items():
            if pair["random_arm"] not in arms or pair["acquisition_arm"] not in arms:
                continue
            t = pair["random-final"]["target_n"]
            med = pair["random-final"]["ratio_median"]
            first = not any(line.get_linestyle() == "--" and line.get_alpha() == 1.0 for line in ax.get_lines())
            ax.axhline(
                t,
                color="k",
                ls="--",
                lw=1,
                label=(f"target {t:.2f} N (random's final mean); " if first else "")
                + f"ratio {pair['acquisition_arm']}: median "
                + (
                    f"{med[0]:.2f}"
                    if med[0] == med[1]
                    else f"[{med[0]:.2f}, {'inf' if med[1] is None else f'{med[1]:.2f}'}]"
                ),
                alpha=1.0 if first else 0.0,
            )
        base = pairs.get(name)
        if base:  # the fixed target and its ratio (what to read where random's curve rises: mf)
            med = base["fixed"]["ratio_median"]
            ax.axhline(
                args.target_n,
                color="0.4",
                ls="-.",
                lw=1,
                label=f"fixed target {args.target_n:g} N; ratio {base['acquisition_arm']}: median "
                + (
                    f"{med[0]:.2f}"
                    if med[0] == med[1]
                    else f"[{med[0]:.2f}, {'inf' if med[1] is None else f'{med[1]:.2f}'}]"
                ),
            )
        if args.simulator_rmse is not None:
            ax.axhline(
                args.simulator_rmse,
                color="tab:green",
                ls=":",
                lw=1.5,
                label=f"nominal simulator, no data: {args.simulator_rmse:.2f} N",
            )
        ax.set_title(name)
        ax.set_xlabel("membranes fabricated")
        ax.set_ylabel("held-out force RMSE [N]")
        ax.set_yscale("log")
        ax.grid(alpha=0.3)
        ax.legend(fontsize=7)
    fig.suptitle(
        f"Active learning on the virtual rig ({args.simulator}{', quick' if args.quick else ''}, truth {args.truth}; "
        f"q = {args.q}; mean over seeds, band min-max)"
    )
    fig.tight_layout()
    fig.savefig(path, dpi=120)


def main() -> None:
    ap = parser(__doc__)
    ap.add_argument("--quick", action="store_true", help="analytic stand-in simulator, short fits")
    ap.add_argument(
        "--simulator",
        choices=("simulator", "emulator", "analytic"),
        default="emulator",
        help="what the virtual rig's truth and the 'sim' fidelity run on (--quick: analytic)",
    )
    ap.add_argument("--seeds", type=int, nargs="+", default=[0, 1, 2])
    ap.add_argument("--arms", nargs="+", default=list(ARMS), choices=ARMS)
    ap.add_argument("--iters", type=int, default=6, help="acquisition rounds after the 3 initial membranes")
    ap.add_argument("--q", type=int, default=2)
    ap.add_argument("--restarts", type=int, default=1000, help="random batches screened per ring count")
    ap.add_argument("--refine", type=int, default=32, help="screened batches refined by L-BFGS")
    ap.add_argument("--warm-sims", type=int, default=12, help="fidelity arm: Latin-hypercube sims before round 1")
    ap.add_argument(
        "--mcmc-steps", type=int, default=200, help="mf arms: most emcee steps per fit (the chain stops once converged)"
    )
    ap.add_argument("--walkers", type=int, default=28, help="mf arms: emcee walkers")
    ap.add_argument("--mf-rows", type=int, default=800, help="mf arms: rows the calibration sees")
    ap.add_argument(
        "--mf-effects",
        nargs="*",
        default=["pressure_sensor"],
        help="mf arms: effects calibrated (default: the one `mfdesign diagnose` names on this rig's "
        "data; pass none for the bare model)",
    )
    ap.add_argument("--mf-refine", type=int, default=8, help="mf arms: screened batches refined by L-BFGS")
    ap.add_argument("--mf-draws", type=int, default=8, help="mf arms: posterior draws the acquisition compares")
    ap.add_argument("--lbfgs-steps", type=int, default=15)
    ap.add_argument("--members", type=int, default=8)
    ap.add_argument("--steps", type=int, default=1500)
    ap.add_argument("--cost-sim", type=float, default=0.01)
    ap.add_argument("--target-n", type=float, default=4.0, help="fixed target [N] (beside random's final mean)")
    ap.add_argument(
        "--truth",
        choices=tuple(TRUTHS),
        default="offset",
        help="the virtual rig's hidden effects: 'offset' (pressure offset 150 Pa) or 'hard' (the offset plus "
        "an effect outside the library, moulding skin + ring fray; writes active_learning_hard*)",
    )
    ap.add_argument("--report-only", action="store_true", help="write JSON/PNG from the checkpoint, run nothing")
    ap.add_argument(
        "--diagnose",
        action="store_true",
        help="refit the rig / disc-rig arms' models of every round and measure where their spread lies "
        "(runs_dir/diagnosis.json, read by every later report)",
    )
    args = ap.parse_args()
    if args.quick:
        args.steps = min(args.steps, 600)
        args.simulator = "analytic"

    import jax

    from mfdesign._cache import enable_compilation_cache
    from mfdesign.physics.effects import EFFECTS
    from mfdesign.models.ensemble import EnsembleConfig

    enable_compilation_cache()
    jax.config.update("jax_platforms", "cpu")
    tag = "_quick" if args.quick else ("" if args.simulator == "emulator" else f"_{args.simulator}")
    tag = ("_hard" if args.truth == "hard" else "") + tag
    # One checkpoint file per (seed, arm): runs of different arms can go on in parallel
    # processes (e.g. one per core) without overwriting each other.
    runs_dir = args.out / f"active_learning{tag}_runs"
    runs_dir.mkdir(parents=True, exist_ok=True)
    results: dict = {}
    for f in sorted(runs_dir.glob("seed*_*.json")):
        seed_s, arm = f.stem[4:].split("_", 1)
        results.setdefault(int(seed_s), {})[arm] = json.loads(f.read_text())

    def saver(seed, arm):
        def save():
            write_json(runs_dir / f"seed{seed}_{arm}.json", results[seed][arm], indent=1)

        return save

    common = dict(n_members=args.members, steps=args.steps, chunk=min(500, args.steps), batch=100)
    cfgs = {"rig": EnsembleConfig(monotone=True, **common), "disc": EnsembleConfig(monotone=False, **common)}
    clock = Timing()
    lab = Lab(args.simulator, args.truth)
    args.held_ranges = (float(lab.held["height_mm"].max()), float(lab.held["pressure_pa"].max()))
    args.simulator_rmse = lab.simulator_rmse()
    print(f"nominal simulator alone: held-out RMSE {args.simulator_rmse} N", flush=True)
    print(
        f"held-out: {len(lab.held['force_n'])} rows of {len(HELD_OUT)} membranes ({clock.elapsed():.0f} s)",
        flush=True,
    )
    for seed in [] if args.report_only else args.seeds:
        for arm in args.arms:
            state = results.setdefault(seed, {}).setdefault(arm, {})
            if state.get("curve") and len(state["curve"]) > args.iters:
                continue
            settings = {k: getattr(args, k) for k in SETTINGS}
            if state.setdefault("settings", settings) != settings:
                raise SystemExit(
                    f"seed {seed} arm {arm}: its checkpoint in {runs_dir} was made with "
                    f"{state['settings']}, not {settings}; delete it or pass the same options"
                )
            args.save = saver(seed, arm)
            run_arm(lab, arm, seed, args, cfgs, state)
            args.save()
    diag_path = runs_dir / "diagnosis.json"
    if args.diagnose:
        with timed() as t:
            diag = diagnose(lab, results, args, cfgs, arms=[a for a in ("rig", "disc-rig") if a in args.arms])
        diag["wall_s"] = t["wall_s"]
        write_json(diag_path, diag, indent=1)
    diagnosis = json.loads(diag_path.read_text()) if diag_path.is_file() else None
    summary = summarise(results, args)
    for arm, s in summary.items():
        print(
            f"{arm:8s}: final RMSE {s['final_rmse_n_mean']:.2f} N (mean of {s['seeds']} seeds), "
            f"membranes to {args.target_n} N: {s['membranes_to_target']}",
            flush=True,
        )
    if "random" in summary and "rig" in summary:
        r, a = summary["random"]["final_rmse_n_mean"], summary["rig"]["final_rmse_n_mean"]
        print(f"ratio final RMSE random / rig acquisition: {r / a:.2f}", flush=True)
    pairs = compare(results, args)
    for name, pair in pairs.items():
        for rule in ("random-final", "fixed"):
            c = pair[rule]
            per = ", ".join(
                f"{s}: {v['random_membranes']}/{v['acquisition_membranes']}" for s, v in c["per_seed"].items()
            )
            print(
                f"{name}: target {c['target_n']:.2f} N ({rule}); membranes random/acquisition per seed {per}; "
                f"ratio median {c['ratio_median']}, min-max {c['ratio_min_max']}, IQR {c['ratio_iqr']}",
                flush=True,
            )
    out = {
        "command": command(__file__, args, skip=("out", "save", "simulator_rmse", "held_ranges")),
        "quick": args.quick,
        "simulator": args.simulator,
        "truth": args.truth,
        "hidden_effects": [
            {"name": e.name, "story": e.story, "in_library": e.name in EFFECTS} for e in lab.truth.effects
        ],
        "hidden_theta": TRUTHS[args.truth][1],
        "pairs": pairs,
        # where the metric's rows lie against the default acquisition grid (1-8 kPa)
        "held_out_rows_above_8kpa": float(np.mean(lab.held["pressure_pa"] > 8000.0)),
        "diagnosis": diagnosis,
        "held_out": list(HELD_OUT),
        # --report-only: complete when every (seed, arm) has a curve (arms may have run for
        # different --iters: the mf arms for 2, the others for 6).
        "complete": all(
            len(results.get(s, {}).get(a, {}).get("curve", [])) > (0 if args.report_only else args.iters)
            for s in args.seeds
            for a in args.arms
        ),
        "target_n": args.target_n,
        "cost_sim": args.cost_sim,
        "simulator_alone_rmse_n": args.simulator_rmse,
        "summary": summary,
        "runs": {str(k): v for k, v in results.items()},
        "wall_s": clock.elapsed(),
        "note": (
            "fidelity arm: SplitPredictor (sim ensemble + discrepancy ensemble, warm-started with "
            "--warm-sims simulator planes); mf-* arms: the issue-5 multi-fidelity model (emcee calibration "
            + (
                "on the exact force model (simulator planes), the acquisition searching on the emulator"
                if args.simulator == "simulator"
                else "through the emulator"
            )
            + " + RPN discrepancy)"
        ),
    }
    path = write_json(args.out / f"active_learning{tag}.json", out)
    plot(results, summary, pairs, args, path.with_suffix(".png"))
    print(f"wrote {path} and .png", flush=True)


if __name__ == "__main__":
    main()
