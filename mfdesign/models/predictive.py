"""Predictive distribution of the multi-fidelity model: posterior theta x discrepancy ensemble.

For posterior draw s (physical theta_s, a latent thickness t_s per row: the membrane's own
if it was calibrated, else a draw from the population prior N(0, sigma_t,s)) and draw s of
the gated discrepancy (:class:`~mfdesign.models.discrepancy.Discrepancy`: ensemble member
s mod M near the training membranes, shrinking to zero with a growing spread away from
them)::

    F_s(x) = E(x; theta_s, t_s) + delta_s(x)             (x = design, h [mm], p [Pa])
    y_s    = F_s(x) + sigma_eps * e,  e ~ N(0, 1)

``sigma_eps`` [N] is the RMS of the training residuals after the discrepancy (fitted on
training rows only). Central intervals are Monte-Carlo quantiles of ``y``; ``predict``
returns ``F_s`` as ``[S, N]`` so that every consumer of the ``ForceModel`` protocol
(``models.cv``, ``models.trajectory``) can use the model.
"""

from __future__ import annotations

import equinox as eqx
import jax
import jax.numpy as jnp
import numpy as np
import pandas as pd

from mfdesign._padding import pad_last, padded_size
from mfdesign._x64 import enable_x64
from mfdesign.models.hierarchical import CalibrationData, HierarchicalModel
from mfdesign.models.predictor import AbstractPredictor
from mfdesign.physics._traces import stored_jit

__all__ = ["MultiFidelity", "MultiFidelityPredictor", "coverage"]


class MultiFidelity(eqx.Module):
    """Posterior draws ``theta`` [S, dim] (physical) of ``model``, discrepancy ``delta``
    (a :class:`~mfdesign.models.discrepancy.Discrepancy` or None), residual noise ``noise_n`` [N]; ``design_keys`` are the
    calibrated membranes in latent order."""

    model: HierarchicalModel
    theta: jax.Array
    delta: object
    noise_n: float = eqx.field(static=True)
    design_keys: tuple[str, ...] = eqx.field(static=True)

    @classmethod
    def from_posterior(
        cls, model, posterior, delta=None, noise_n: float | None = None, max_draws: int = 128, seed: int = 0
    ) -> "MultiFidelity":
        """Thin the posterior to at most ``max_draws`` draws (``noise_n`` default: the
        posterior median noise scale)."""
        enable_x64()  # float64 physics: mfdesign._x64
        idx = np.random.default_rng(seed).permutation(len(posterior.samples))[:max_draws]
        noise = float(np.median(posterior.samples[:, posterior.names.index("noise_n")])) if noise_n is None else noise_n
        return cls(model, jnp.asarray(posterior.samples[idx]), delta, float(noise), tuple(posterior.design_keys))

    def data_for(self, design, h_mm, p_pa, table=None, min_lift_height_mm: float = 2.0) -> CalibrationData:
        """Rows to predict: from a Measurements ``table`` (its kinds of rows; unlifted lift
        rows dropped as in calibration), or plain force rows at ``design`` [N, 6], ``h_mm``
        [N], ``p_pa`` [N]."""
        if table is not None:
            keys = list(self.design_keys) + [
                k for k in dict.fromkeys(table.df["design_key"]) if k not in self.design_keys
            ]
            return CalibrationData.from_measurements(
                table, max_rows=None, design_keys=keys, min_lift_height_mm=min_lift_height_mm
            )
        from mfdesign.design import Membrane
        from mfdesign.physics.effects import Rows

        design = np.atleast_2d(np.asarray(design, float))
        h_mm, p_pa = (np.broadcast_to(np.asarray(a, float), (len(design),)) for a in (h_mm, p_pa))
        row_keys = [Membrane.from_array(d).key() for d in design]
        keys = list(self.design_keys) + [k for k in dict.fromkeys(row_keys) if k not in self.design_keys]
        index = {k: i for i, k in enumerate(keys)}
        n = len(design)
        rows = Rows(
            jnp.asarray(h_mm),
            jnp.asarray(p_pa),
            jnp.ones(n, bool),
            jnp.zeros(n, bool),
            jnp.zeros(n, bool),
            jnp.asarray([index[k] for k in row_keys], dtype=jnp.int32),
        )
        return CalibrationData(jnp.asarray(design), rows, jnp.zeros(n), jnp.ones(n), tuple(keys))

    def sample_data(self, data: CalibrationData, key=0, discrepancy=True) -> jax.Array:
        """``F_s`` [S, N] at the rows of ``data`` (module doc). ``discrepancy``: add the
        discrepancy draws (True), or not (False: the physics alone, the ``sim`` fidelity);
        a traced boolean chooses at run time (one compiled program serves both)."""
        key = jax.random.PRNGKey(key) if isinstance(key, int) else key
        f = _sim_draws(self.model, self.theta, data, key)
        if self.delta is None or discrepancy is False:
            return f

        inputs = (data.design, data.rows.h_mm, data.rows.p_pa)
        if discrepancy is not True:
            # Traced: the draws are computed either way and selected, and where they are
            # not wanted their inputs carry no gradient (the gate's sqrt(1 - g^2) has an
            # infinite slope on a training membrane: 0 x inf would be NaN). A select, not a
            # lax.cond: under the acquisition's vmap x grad x L-BFGS a cond compiled slower
            # (14 s) than the two programs it replaced together (8 + 4 s).
            inputs = tuple(jnp.where(discrepancy, a, jax.lax.stop_gradient(a)) for a in inputs)
        # its own stream: the physics draws stay what they were without a discrepancy
        k_delta = jax.random.fold_in(key, 1)
        g = f + _delta_draws(self.delta, *inputs, f.shape[0], k_delta)
        return g if discrepancy is True else jnp.where(discrepancy, g, f)

    def predict(self, design, h_mm, p_pa):
        """``ForceModel`` protocol: draws ``F_s`` [S, N] N at force rows (new designs draw
        their thickness from the population). Rows are padded to a power of two (>= 256)
        so that a few compiled shapes serve every call (trajectory grids vary in size)."""
        design = np.atleast_2d(np.asarray(design, float))
        h_mm, p_pa = (np.broadcast_to(np.asarray(a, float), (len(design),)) for a in (h_mm, p_pa))
        n = len(design)
        if n == 0:
            return np.zeros((self.theta.shape[0], 0))
        size = padded_size(n, 256)
        return self.sample_data(self.data_for(*(pad_last(a, size) for a in (design, h_mm, p_pa))))[:, :n]

    def members(self, design, h_mm, p_pa, key=0, discrepancy=True) -> jax.Array:
        """Traceable ``F_s`` [S, N] N at force rows ``design`` [N, 6] mm, ``h_mm`` [N],
        ``p_pa`` [N]: a row of a calibrated membrane (the same design to 1e-6 mm) takes that
        membrane's own latent thickness, as :meth:`predict` does; any other design draws its
        thickness from the population prior. Unlike :meth:`predict` nothing leaves JAX, so
        acquisition and design optimisation can differentiate through it (their
        ``members`` protocol). ``discrepancy``: as in :meth:`sample_data`."""
        from mfdesign.design import Membrane
        from mfdesign.physics.effects import Rows

        n = design.shape[0]
        k = len(self.design_keys)
        known = jnp.asarray(np.array([Membrane.from_key(x).to_array() for x in self.design_keys]).reshape(k, 6))
        d, c = design[:, None, :], known[None, :, :]
        same = jnp.all(jnp.where(jnp.isnan(d) | jnp.isnan(c), jnp.isnan(d) & jnp.isnan(c), jnp.abs(d - c) < 1e-6), -1)
        rows = Rows(
            h_mm,
            p_pa,
            jnp.ones(n, bool),
            jnp.zeros(n, bool),
            jnp.zeros(n, bool),
            jnp.where(same.any(1), jnp.argmax(same, 1), k).astype(jnp.int32),
        )
        data = CalibrationData(design, rows, jnp.zeros(n), jnp.ones(n), self.design_keys + ("<new membrane>",))
        return self.sample_data(data, key, discrepancy)

    def thinned(self, n_draws: int) -> "MultiFidelity":
        """The first ``n_draws`` posterior draws (already a random permutation): searches that
        differentiate through every draw pay for each one."""
        return MultiFidelity(self.model, self.theta[:n_draws], self.delta, self.noise_n, self.design_keys)

    def predictor(self, n_draws: int = 16) -> "MultiFidelityPredictor":
        """A :class:`MultiFidelityPredictor` of the first ``n_draws`` draws, with two
        fidelities: ``rig`` (physics draws + discrepancy members) and ``sim`` (physics draws
        only: what a simulator run informs, never the sim-to-real discrepancy)."""
        return MultiFidelityPredictor(self.thinned(n_draws))

    def interval(self, data: CalibrationData, level: float = 0.9, n_noise: int = 8, key=0):
        """Mean [N] and central ``level`` interval ``(lo, hi)`` [N] of the observation ``y``."""
        if not 0 < level < 1:
            raise ValueError(f"level must be in (0, 1), got {level}")
        f = np.asarray(self.sample_data(data, key))
        rng = np.random.default_rng(0 if not isinstance(key, int) else key)
        y = f[None] + self.noise_n * rng.standard_normal((n_noise,) + f.shape)
        y = y.reshape(-1, f.shape[1])
        a = (1 - level) / 2
        lo, hi = np.quantile(y, [a, 1 - a], axis=0)
        return f.mean(0), lo, hi


class MultiFidelityPredictor(AbstractPredictor):
    """The acquisition's and design search's predictor of a :class:`MultiFidelity` ``mf``
    (:meth:`MultiFidelity.predictor`): ``rig`` members are the physics draws plus the
    discrepancy, ``sim`` members the physics draws alone (paired: draw ``s`` of both is
    one hypothesis).

    The fidelity may be data (``fidelity_as_data``): :meth:`members` takes a name or an
    integer index into :attr:`fidelities`, traced or not, so one compiled program serves
    both (acquisition's L-BFGS compiled once per fidelity, ~9 s each on a cold demo,
    issue 40). ``mf`` is a pytree leaf, not a closure: programs compiled for one fit are
    reused by another of the same structure (a campaign's next round)."""

    mf: MultiFidelity
    fidelity_as_data = True

    @property
    def fidelities(self) -> tuple[str, ...]:
        return ("rig", "sim")

    def members(self, fidelity, design, h_mm, p_pa):
        if isinstance(fidelity, str):
            self.check_fidelity(fidelity)
            rig = fidelity == "rig"
        else:
            rig = jnp.asarray(fidelity) == self.fidelities.index("rig")
        args = (design, h_mm, p_pa)
        if any(isinstance(a, jax.core.Tracer) for a in args + (rig,)) or np.ndim(h_mm) != 1 or len(h_mm) == 0:
            return self.mf.members(*args, discrepancy=rig)  # traced: compiled into the caller's shapes
        # Called eagerly (a simulated plane's rows, a sanity probe): rows padded to a power of
        # two (>= 256, as :meth:`MultiFidelity.predict`) so that a few compiled shapes serve
        # every table (a plane of 255 and one of 211 rows were two compiles); the draws are
        # per membrane, not per row, so the padding changes no number.
        n = len(h_mm)
        size = padded_size(n, 256)
        return self.mf.members(*(jnp.asarray(pad_last(np.asarray(a, float), size)) for a in args), discrepancy=rig)[
            :, :n
        ]


@stored_jit
def _delta_draws(delta, design, h_mm, p_pa, n_draws: int, key):
    # one compiled program: op by op, the ensemble's forward pass and the prior draws were
    # ~70 small compilations (23 s of a 37 s coverage figure, issue 40)
    return delta.draws(design, h_mm, p_pa, n_draws, key)


@stored_jit(fast_compile=True)
def _sim_draws(model: HierarchicalModel, theta, data: CalibrationData, key):
    return model.sample_force(theta, data, key)


COVERAGE_ROWS = 20_000


def coverage(mf: MultiFidelity, table, level: float = 0.9, key=0, max_rows: int = COVERAGE_ROWS) -> dict:
    """RMSE [N] of the mean and the fraction of rows of ``table`` (Measurements) inside the
    central ``level`` interval, overall and per membrane; on at most ``max_rows`` rows,
    evenly spaced through the table (the bundled data's 150k rows took 90 s of posterior
    draws for a figure that 20k rows give to within 1 %)."""
    if len(table) > max_rows:
        from mfdesign.data.measurements import Measurements

        step = -(-len(table) // max_rows)
        table = Measurements(table.df.iloc[::step].reset_index(drop=True))
    data = mf.data_for(None, None, None, table=table)
    mean, lo, hi = mf.interval(data, level, key=key)
    f = np.asarray(data.force_n)
    # rows the model has no number for (outside the physical model, off the planes) are
    # left out and counted: a NaN mean made the whole RMSE NaN, and a NaN interval counted
    # the row as outside it
    ok = np.isfinite(mean) & np.isfinite(lo) & np.isfinite(hi) & np.isfinite(f)
    keys = np.asarray(data.design_keys, dtype=object)[np.asarray(data.rows.membrane)]
    f, mean, lo, hi, keys = f[ok], mean[ok], lo[ok], hi[ok], keys[ok]
    inside = (f >= lo) & (f <= hi)
    per = pd.DataFrame({"k": keys, "in": inside, "e2": (f - mean) ** 2}).groupby("k", sort=False).mean()
    return {
        "level": level,
        "coverage": float(inside.mean()) if ok.any() else float("nan"),
        "rmse_n": float(np.sqrt(np.mean((f - mean) ** 2))) if ok.any() else float("nan"),
        "per_membrane": {k: {"coverage": float(r["in"]), "rmse_n": float(np.sqrt(r["e2"]))} for k, r in per.iterrows()},
        "mean_width_n": float(np.mean(hi - lo)) if ok.any() else float("nan"),
        "rows_without_value": int((~ok).sum()),
    }
