"""Hierarchical multi-fidelity model of the plate force (Kennedy & O'Hagan 2001, modular).

For row i of membrane m(i), recorded at height h_i [mm] and pressure p_i [Pa]::

    F_i = E_i(theta_global, t_m(i)) + delta(design_i, h_i, p_i) + eps_i

* ``E_i``: the expected RECORDED force: the force model (emulator of the simulator, or
  any ``force_model(design [N, 6], h [N], p [N], SimParams) -> F [N]``) run with
  SimParams built from the global parameters and the row (mechanical effects), then passed
  through the measurement effects: :func:`~mfdesign.models.force.recorded_force`, the one
  place that applies the effects to a force (the diagnosis' forward model calls it too).
* ``theta_global``: ``mu_pa`` [Pa] (Gent shear modulus, prior log-normal around the
  paper's 31.7 kPa, sd 0.5 in log), ``jm`` [1] (Gent J_m, log-normal around 39.6, sd 0.6
  in log) and the active effects' parameters with the effects' own priors and units.
* ``theta_membrane``: per-membrane relative thickness ``t_m ~ N(0, sigma_t)`` with the
  population spread ``sigma_t`` [1] a hyper-parameter (log-normal prior, median 0.05):
  that is the hierarchy. The parameterisation is the centred one (``t_m`` sampled
  directly): every membrane has hundreds of rows that pin its ``t_m`` to about 1 %, the
  regime where the centred form mixes and the non-centred ``t_m = sigma_t z_m`` draws a
  curved ridge ``z_m ~ t_m / sigma_t`` (Papaspiliopoulos, Roberts & Skold 2007; measured:
  the non-centred chains' autocorrelation time was ~2x longer). The simulator sees ``thickness_factor * (1 + t_m)``; an
  active ``thickness_deviation`` effect then acts as the population mean.
* per-membrane effect parameters (``membrane_effects``, e.g. ``fabric_inset.inset_mm``): a
  hierarchical random effect like the thickness. Membrane m has its own value ``v_m``; in
  the parameter's unconstrained coordinate ``b^-1`` (the bijection of its prior's support)
  ``b^-1(v_m) ~ N(b^-1(c), s)``, with the population centre ``c`` the effect's global
  parameter (its own prior, physical units) and the spread ``s`` (``"<param>_sd"``,
  unconstrained units, log-normal prior) calibrated. A new membrane's prediction draws its
  ``v`` from that population (Gelman & Hill 2007, ch. 12-13: varying intercepts), so its
  interval widens by what the membranes disagree on. Centred, like the thickness.
* ``eps``: noise of scale ``noise_n`` [N] (fitted; Gaussian or Student-t with ``nu``).
* ``delta``: the discrepancy, an RPN ensemble (:mod:`mfdesign.models.ensemble`) fitted to
  the residuals ``F - E(theta_MAP)`` (:func:`fit_discrepancy`), gated so that it shrinks
  to zero, and its spread grows, away from the training membranes
  (:mod:`mfdesign.models.discrepancy`). Calibration of theta uses
  the likelihood without delta and delta is fitted afterwards: a modular ("cut")
  analysis (Liu, Bayarri & Berger 2009), which keeps the flexible ensemble from absorbing
  what the physical constants should explain.

Sampling happens in an unconstrained vector ``u`` (one entry per parameter): a
parameter whose prior has bounds ``[lo, hi]`` is ``lo + (hi - lo) sigmoid(u)``, one
with only ``lo`` is ``lo + exp(u)``, an unbounded one is ``u``; the log-Jacobian enters
the log-density so the posterior of the physical value is exact.
"""

from __future__ import annotations

import dataclasses
import math
from typing import Callable, Sequence

import equinox as eqx
import jax
import jax.numpy as jnp
import numpy as np
import pandas as pd

from mfdesign._x64 import enable_x64
from mfdesign.data.lifts import floating_rows
from mfdesign.physics import effects as fx
from mfdesign.physics.effects import LogNormal, Normal, Rows
from mfdesign.physics.params import SimParams
from mfdesign.models.force import recorded_force, row_sim_params
from mfdesign.materials import ECOFLEX_JM, ECOFLEX_MU_PA

__all__ = [
    "LATENT",
    "SPREAD",
    "CalibrationData",
    "HierarchicalModel",
    "ParamSpec",
    "fit_discrepancy",
    "membrane_block",
    "membrane_parameters",
]

ForceFn = Callable[..., jax.Array]  # force_model(design [N, 6], h [N], p [N], SimParams) -> [N] N
LATENT = "thickness["  # name prefix of the per-membrane thickness latents
SPREAD = "_sd"  # suffix of a per-membrane effect parameter's population spread


def membrane_block(name: str) -> tuple[str, int] | None:
    """``(variable, membrane index)`` of a per-membrane parameter name (``"thickness[3]"`` ->
    ``("thickness", 3)``, ``"fabric_inset.inset_mm[0]"`` -> ``("fabric_inset.inset_mm", 0)``),
    else ``None``: how files and tables group one value per membrane."""
    if not name.endswith("]") or "[" not in name:
        return None
    var, _, idx = name[:-1].rpartition("[")
    return (var, int(idx)) if idx.isdigit() else None


@dataclasses.dataclass(frozen=True)
class ParamSpec:
    """One sampled parameter: ``name``, ``unit``, ``prior`` (effects' prior classes), ``doc``.

    The map between the sampler's unconstrained ``u`` and the physical value is the
    prior's support's :func:`~mfdesign.physics.effects.bijection` (one implementation)."""

    name: str
    unit: str
    prior: object
    doc: str = ""

    @property
    def bijection(self) -> fx.Bijection:
        return fx.bijection(self.prior.bounds)

    def to_physical(self, u):
        return self.bijection.to_physical(u)

    def log_jacobian(self, u):
        return self.bijection.log_jacobian(u)

    def to_unconstrained(self, x):
        return self.bijection.to_unconstrained(x)


class CalibrationData(eqx.Module):
    """Rows a likelihood sees: ``design`` [N, 6] mm, ``rows`` (:class:`Rows`: recorded h
    [mm], p [Pa], kinds), ``force_n`` [N] recorded force (or lifted weight), ``weight`` [N]
    (normalised to mean 1). ``design_keys`` (static) names the membranes ``rows.membrane``
    indexes."""

    design: jax.Array
    rows: Rows
    force_n: jax.Array
    weight: jax.Array
    design_keys: tuple[str, ...] = eqx.field(static=True)

    @classmethod
    def from_measurements(
        cls,
        table,
        max_rows: int | None = 3000,
        seed: int = 0,
        design_keys: Sequence[str] | None = None,
        min_lift_height_mm: float = 2.0,
    ) -> "CalibrationData":
        """From a Measurements table; at most ``max_rows`` rows, drawn evenly within each
        trial (the ramps are densely sampled: neighbouring rows carry little new information).

        Lift rows where the plate does not float are dropped
        (:func:`~mfdesign.data.lifts.floating_rows`, with ``min_lift_height_mm`` its resting
        floor): resting on its support or pinned, the membrane's force is only bounded by W,
        not equal to it.
        """
        enable_x64()  # float64 physics: mfdesign._x64
        df = table if isinstance(table, pd.DataFrame) else table.df
        df = df[floating_rows(df, resting_mm=min_lift_height_mm)]
        if len(df) == 0:
            raise ValueError("calibration data: no usable rows (empty table, or only unlifted lift rows)")
        if max_rows is not None and len(df) > max_rows:
            if max_rows < 10:
                raise ValueError(f"max_rows must be >= 10, got {max_rows}")
            rng = np.random.default_rng(seed)
            # every trial keeps its share of rows, evenly spaced along the ramp (random phase)
            keep = []
            frac = max_rows / len(df)
            for _, idx in df.groupby(["design_key", "trial"], sort=False).indices.items():
                k = max(1, int(round(frac * len(idx))))
                pos = (rng.uniform() + np.arange(k)) * len(idx) / k
                keep.append(idx[np.minimum(pos.astype(int), len(idx) - 1)])
            df = df.iloc[np.sort(np.concatenate(keep))]
        keys = tuple(design_keys) if design_keys is not None else tuple(dict.fromkeys(df["design_key"]))
        from mfdesign.design import Membrane

        table_keys = {k: Membrane.from_key(k).to_array() for k in keys}
        design = np.stack([table_keys[k] for k in df["design_key"]])
        w = df["weight"].to_numpy(float)
        if not w.sum() > 0:  # was silently replaced by ones: refuse, the data say "ignore every row"
            raise ValueError(f"all {len(w)} sample weights are 0; allowed: weights >= 0 with a positive sum")
        w = w / w.mean()
        return cls(
            jnp.asarray(design),
            Rows.from_measurements(df, keys),
            jnp.asarray(df["force_n"].to_numpy(float)),
            jnp.asarray(w),
            keys,
        )

    def __len__(self) -> int:
        return int(self.force_n.shape[0])

    def padded(self, n: int) -> "CalibrationData":
        """The same data padded to ``n`` rows with weight-0 copies of row 0 (equal shapes
        across data sets share one compiled likelihood)."""
        extra = n - len(self)
        if extra < 0:
            raise ValueError(f"cannot pad {len(self)} rows down to {n}")
        idx = jnp.concatenate([jnp.arange(len(self)), jnp.zeros(extra, int)])
        w = jnp.concatenate([self.weight, jnp.zeros(extra)])
        return CalibrationData(self.design[idx], self.rows.take(idx), self.force_n[idx], w, self.design_keys)


SAMPLE_BATCH = 4  # posterior draws evaluated at once by sample_force (memory bound)


def membrane_parameters(effects, names) -> tuple[str, ...]:
    """The qualified parameters (``"effect.param"``) of ``effects`` that ``names`` select (a
    parameter's own name, or an effect's name for all of its parameters); ``ValueError``
    naming one that selects nothing, with the allowed names."""
    allowed = list(fx.neutral_theta(effects))
    out: list[str] = []
    for name in names:
        got = [q for q in allowed if q == name or q.split(".")[0] == name]
        if not got:
            raise ValueError(
                f"per-membrane parameter {name!r} is not a parameter of the effects in the model; "
                f"allowed: {allowed or 'none (no effects)'}"
            )
        out += [q for q in got if q not in out]
    return tuple(out)


def _names(names) -> tuple[str, ...]:
    """A name or names as a tuple (``tuple("fabric_inset")`` would be its letters)."""
    return (names,) if isinstance(names, str) else tuple(names)


def _effect_names(effects) -> tuple[str, ...]:
    return tuple(fx.effect(e).name for e in effects)


class HierarchicalModel(eqx.Module):
    """The parameter layout, priors, transforms and log-density of the model (module doc).

    ``force_model``: the fidelity-"sim" force model (emulator / stand-in; a function or an
    ``eqx.Module``, whose arrays are then traced, not baked into compiled code);
    ``effects``: names of the active effects; ``n_membranes``: how many membranes the data
    hold (one latent thickness each; 0 or ``membrane_latents=False``: none);
    ``likelihood``: ``"gaussian"`` or ``"student_t"`` (``nu`` degrees of freedom);
    ``base``: SimParams of everything not sampled (ring constants, ...);
    ``membrane_effects``: parameters of ``effects`` (``"effect.param"``, or an effect's name
    for all of its parameters) that vary from membrane to membrane around the population
    centre (module doc), with ``effect_sd_prior`` the prior of their spread (unconstrained
    units: near the middle of a ``[0, 2]`` mm support one unit is about 0.5 mm).
    """

    force_model: ForceFn
    effects: tuple[str, ...] = eqx.field(default=(), converter=_effect_names, static=True)
    n_membranes: int = eqx.field(default=0, static=True)
    membrane_latents: bool = eqx.field(default=True, static=True)
    likelihood: str = eqx.field(default="gaussian", static=True)
    nu: float = eqx.field(default=4.0, static=True)
    mu_prior: object = eqx.field(default=LogNormal(ECOFLEX_MU_PA, 0.5, 3e3, 300e3), static=True)
    jm_prior: object = eqx.field(default=LogNormal(ECOFLEX_JM, 0.6, 2.0, 1000.0), static=True)
    noise_prior: object = eqx.field(default=LogNormal(1.0, 1.5, 1e-4, 1e3), static=True)
    thickness_sd_prior: object = eqx.field(default=LogNormal(0.05, 0.8, 1e-3, 0.5), static=True)
    base: SimParams = SimParams()
    membrane_effects: tuple[str, ...] = eqx.field(default=(), converter=_names, static=True)
    effect_sd_prior: object = eqx.field(default=LogNormal(1.0, 1.0, 1e-2, 10.0), static=True)

    def __check_init__(self):
        if self.likelihood not in ("gaussian", "student_t"):
            raise ValueError(f"likelihood must be 'gaussian' or 'student_t', got {self.likelihood!r}")
        if not (isinstance(self.n_membranes, (int, np.integer)) and self.n_membranes >= 0):
            raise ValueError(f"n_membranes must be an integer >= 0, got {self.n_membranes!r}")
        if self.membrane_effects and self.n_membranes < 1:
            raise ValueError("per-membrane effect parameters need membranes (n_membranes >= 1)")
        self.membrane_params  # noqa: B018 -- validates the names

    # -- layout -----------------------------------------------------------------------------
    @property
    def membrane_params(self) -> tuple[str, ...]:
        """The qualified effect parameters (``"effect.param"``) that vary per membrane."""
        return membrane_parameters(self.effects, self.membrane_effects)

    @property
    def uses_latents(self) -> bool:
        return self.membrane_latents and self.n_membranes > 0

    @property
    def specs(self) -> tuple[ParamSpec, ...]:
        out = [
            ParamSpec("mu_pa", "Pa", self.mu_prior, "Gent shear modulus of the rubber"),
            ParamSpec("jm", "1", self.jm_prior, "Gent locking parameter J_m"),
        ]
        for name in self.effects:
            e = fx.effect(name)
            out += [ParamSpec(e.qualified(p.name), p.unit, p.prior, p.doc) for p in e.parameters]
        out.append(ParamSpec("noise_n", "N", self.noise_prior, "noise scale of a recorded force"))
        if self.uses_latents:
            out.append(
                ParamSpec(
                    "thickness_sd",
                    "1",
                    self.thickness_sd_prior,
                    "population spread of the membranes' relative thickness",
                )
            )
            # The prior N(0, thickness_sd) depends on another parameter: log_prior_u
            # replaces this spec's placeholder prior by it.
            out += [
                ParamSpec(
                    f"{LATENT}{m}]",
                    "1",
                    Normal(0.0, 1.0),
                    "relative thickness latent t_m of membrane m, prior N(0, thickness_sd)",
                )
                for m in range(self.n_membranes)
            ]
        by_name = {sp.name: sp for sp in out}
        for q in self.membrane_params:
            centre = by_name[q]
            out.append(
                ParamSpec(q + SPREAD, "1", self.effect_sd_prior, f"population spread of {q} (unconstrained units)")
            )
            # The prior N(b^-1(centre), spread) in the unconstrained coordinate replaces this
            # spec's (log_prior_u); the spec keeps the effect's prior for its support.
            out += [
                ParamSpec(f"{q}[{m}]", centre.unit, centre.prior, f"{q} of membrane m, around the population centre")
                for m in range(self.n_membranes)
            ]
        return tuple(out)

    @property
    def names(self) -> tuple[str, ...]:
        return tuple(s.name for s in self.specs)

    @property
    def dim(self) -> int:
        return len(self.specs)

    def to_physical(self, u) -> jax.Array:
        """``u`` [..., dim] unconstrained -> physical values [..., dim]."""
        u = jnp.asarray(u)
        return jnp.stack([s.to_physical(u[..., i]) for i, s in enumerate(self.specs)], -1)

    def to_unconstrained(self, x) -> np.ndarray:
        x = np.asarray(x, float)
        return np.stack([s.to_unconstrained(x[..., i]) for i, s in enumerate(self.specs)], -1)

    def initial_physical(self) -> np.ndarray:
        """A sensible starting point: prior medians (mu, J_m, noise, sigma_t), effects neutral, z = 0."""
        start = {
            "mu_pa": self.mu_prior.center,
            "jm": self.jm_prior.center,
            "noise_n": self.noise_prior.center,
            "thickness_sd": self.thickness_sd_prior.center,
        }
        start.update(fx.neutral_theta(self.effects))
        for q in self.membrane_params:
            start.update({f"{q}[{m}]": start[q] for m in range(self.n_membranes)})
            start[q + SPREAD] = self.effect_sd_prior.center
        x = []
        for s in self.specs:
            v = start.get(s.name, 0.0)
            lo, hi = s.prior.bounds
            span = (hi - lo) if math.isfinite(hi - lo) else 1.0
            x.append(float(np.clip(v, lo + 1e-3 * span, hi - 1e-3 * span)))  # inside, not on, a bound
        return np.asarray(x)

    def unpack(self, x) -> dict[str, jax.Array]:
        """Physical vector [dim] -> ``{name: value}`` (``thickness`` and each per-membrane
        effect parameter ``"effect.param[]"`` as one [M] array)."""
        out = {s.name: x[i] for i, s in enumerate(self.specs) if membrane_block(s.name) is None}
        if self.uses_latents:
            k = self.names.index(f"{LATENT}0]")
            out["thickness"] = x[k : k + self.n_membranes]
        for q in self.membrane_params:
            k = self.names.index(f"{q}[0]")
            out[q + "[]"] = x[k : k + self.n_membranes]
        return out

    def _membrane_prior_u(self, u) -> jax.Array:
        """log density of the per-membrane effect values in the sampler's coordinate:
        ``u_m ~ N(u_centre, spread)`` (the bijection's Jacobian of ``v_m`` cancels there)."""
        terms = []
        for q in self.membrane_params:
            i, k = self.names.index(q), self.names.index(f"{q}[0]")
            sd = self.specs[self.names.index(q + SPREAD)].to_physical(u[self.names.index(q + SPREAD)])
            z = (u[k : k + self.n_membranes] - u[i]) / sd
            terms.append(jnp.sum(-0.5 * z**2 - jnp.log(sd)) - 0.5 * self.n_membranes * math.log(2 * math.pi))
        return jnp.sum(jnp.stack(terms)) if terms else jnp.asarray(0.0)

    # -- densities --------------------------------------------------------------------------
    def log_prior_u(self, u) -> jax.Array:
        """log p(x(u)) + log |dx/du| for one unconstrained vector ``u`` [dim]."""
        x = self.to_physical(u)
        terms = [
            s.prior.logpdf(x[i]) + s.log_jacobian(u[i])
            for i, s in enumerate(self.specs)
            if membrane_block(s.name) is None
        ]
        terms.append(self._membrane_prior_u(u))
        if self.uses_latents:  # t_m ~ N(0, thickness_sd): the hierarchy
            v = self.unpack(x)
            sd = v["thickness_sd"]
            terms.append(
                jnp.sum(-0.5 * (v["thickness"] / sd) ** 2 - jnp.log(sd))
                - 0.5 * self.n_membranes * math.log(2 * math.pi)
            )
        return jnp.sum(jnp.stack(terms))

    def theta_rows(self, x, data: CalibrationData, effect_rows=None) -> dict[str, jax.Array]:
        """The effects' parameters at physical ``x`` (``{"effect.param": value}``): scalars,
        and [N] per row for a per-membrane parameter (the row's membrane's own value; a row of
        a membrane the model was not calibrated on gets the population centre). ``effect_rows``
        (``{"effect.param": [N]}``) overrides them, e.g. draws for a new membrane."""
        v = self.unpack(x)
        theta = {k: v[k] for k in fx.neutral_theta(self.effects)}
        if self.membrane_params:
            m = data.rows.membrane
            known = m < self.n_membranes
            for q in self.membrane_params:
                own = v[q + "[]"][jnp.clip(m, 0, self.n_membranes - 1)]
                theta[q] = jnp.where(known, own, v[q])
        theta.update(effect_rows or {})
        return theta

    def _row_inputs(self, x, data: CalibrationData, thickness_rel=None, effect_rows=None):
        """``(theta, base, thickness_rel)`` of every row at physical ``x``: the effects'
        parameters (:meth:`theta_rows`), the base constants with the sampled material, and
        the rows' relative thickness (the membranes' latents unless ``thickness_rel`` is given)."""
        v = self.unpack(x)
        base = dataclasses.replace(self.base, mu_pa=v["mu_pa"], jm=v["jm"])
        if thickness_rel is None and self.uses_latents:
            thickness_rel = v["thickness"][data.rows.membrane]
        return self.theta_rows(x, data, effect_rows), base, thickness_rel

    def sim_params(self, x, data: CalibrationData, thickness_rel=None, effect_rows=None) -> SimParams:
        """Row-wise SimParams at physical ``x``: mechanical effects, then the latent thickness
        (``thickness_rel`` [N] overrides the membranes' latents, e.g. for a new membrane;
        ``effect_rows`` the per-membrane effect values, :meth:`theta_rows`)."""
        theta_fx, base, t = self._row_inputs(x, data, thickness_rel, effect_rows)
        return row_sim_params(self.effects, theta_fx, base, data.rows, t)

    def expected_force(
        self, x, data: CalibrationData, thickness_rel=None, marked: bool = False, effect_rows=None
    ) -> jax.Array:
        """Expected recorded force [N] of every row at physical ``x`` (fidelity "sim" + effects:
        :func:`~mfdesign.models.force.recorded_force`, the one place that applies them).
        ``marked``: rows outside the physical model read ``+inf`` (``ForceModel.marking``),
        else NaN (or, for a model held at its lattice's edge, the plane's number).
        ``thickness_rel`` / ``effect_rows``: as in :meth:`sim_params`."""
        theta_fx, base, t = self._row_inputs(x, data, thickness_rel, effect_rows)
        fm = self.force_model
        if marked and hasattr(fm, "marking"):
            fm = fm.marking(True)
        return recorded_force(fm, data.design, data.rows, self.effects, theta_fx, base, t)

    def outside_rows(self, x, data: CalibrationData) -> jax.Array:
        """Rows [N] bool that are outside the physical model at physical ``x`` (the force
        model's ``outside_model``: a force above ``p pi R^2``); the likelihood leaves them out."""
        return jnp.isposinf(self.expected_force(x, data, marked=True))

    def pointwise_log_lik(self, x, data: CalibrationData) -> jax.Array:
        """log p(F_i | x) [N] (unweighted).

        A row outside the physical model at ``x`` (the force model says so: a force above
        ``p pi R^2``, ``Status.OUTSIDE_MODEL``) is left out: its measurement does not enter.
        It counts as a row at the noise level (the expected log density of a row the model
        fits, ``E[log p(eps)]``), not as 0: the rows the noise scale's ``-log sigma`` term
        sees then do not change with ``x``, and a parameter that puts a well-fitted row
        outside gains nothing. Any other NaN (off the lattice, an unsolved node) is "very
        unlikely" (-1e10), the support's edge."""
        sigma = self.unpack(x)["noise_n"]
        f = self.expected_force(x, data, marked=True)
        outside = jnp.isposinf(f)
        # Double where: a NaN force (outside the force model's support) must not reach the
        # arithmetic, or its NaN partials times the zero cotangent poison every gradient.
        good = jnp.isfinite(f)
        r = jnp.where(good, data.force_n - f, 0.0) / sigma
        if self.likelihood == "gaussian":
            ll = -0.5 * r**2 - jnp.log(sigma) - 0.5 * math.log(2 * math.pi)
            typical = -0.5 - jnp.log(sigma) - 0.5 * math.log(2 * math.pi)
        else:
            from scipy.special import digamma

            nu = self.nu
            c = math.lgamma((nu + 1) / 2) - math.lgamma(nu / 2) - 0.5 * math.log(nu * math.pi)
            ll = c - jnp.log(sigma) - 0.5 * (nu + 1) * jnp.log1p(r**2 / nu)
            # E[log(1 + T^2 / nu)] = psi((nu + 1) / 2) - psi(nu / 2) for T ~ t_nu
            typical = c - jnp.log(sigma) - 0.5 * (nu + 1) * float(digamma((nu + 1) / 2) - digamma(nu / 2))
        # a NaN force (outside the model's support) is "very unlikely"
        return jnp.where(good & jnp.isfinite(ll), ll, jnp.where(outside, typical, -1e10))

    def log_lik(self, x, data: CalibrationData) -> jax.Array:
        return jnp.sum(data.weight * self.pointwise_log_lik(x, data))

    def log_posterior_u(self, u, data: CalibrationData) -> jax.Array:
        """Unnormalised log posterior at one unconstrained vector ``u`` [dim]."""
        lp = self.log_prior_u(u)
        ll = self.log_lik(self.to_physical(u), data)
        out = lp + ll
        return jnp.where(jnp.isfinite(out), out, -jnp.inf)

    # -- prediction -------------------------------------------------------------------------
    def thickness_for(self, x_samples, data: CalibrationData, key=None) -> jax.Array:
        """Relative thickness [S, N] of each row for each posterior sample: the membrane's own
        latent where the row's design key was calibrated, else a draw from the population
        prior N(0, sigma_t) (a new membrane)."""
        x_samples = jnp.atleast_2d(x_samples)
        S, N = x_samples.shape[0], len(data)
        if not self.uses_latents:
            return jnp.zeros((S, N))
        sd = x_samples[:, self.names.index("thickness_sd")]
        k = self.names.index(f"{LATENT}0]")
        t = x_samples[:, k : k + self.n_membranes]
        known = t[:, jnp.clip(data.rows.membrane, 0, self.n_membranes - 1)]
        key = jax.random.PRNGKey(0) if key is None else key
        n_keys = len(data.design_keys)
        fresh = sd[:, None] * jax.random.normal(key, (S, n_keys))[:, data.rows.membrane]
        return jnp.where((data.rows.membrane < self.n_membranes)[None, :], known, fresh)

    def effects_for(self, x_samples, data: CalibrationData, key=None) -> dict[str, jax.Array]:
        """Per-membrane effect values [S, N] of each row for each posterior sample
        (``{"effect.param": ...}``, :attr:`membrane_params`): the membrane's own where it was
        calibrated, else a draw from the population (``b^-1(v) ~ N(b^-1(c), spread)``: a new
        membrane), independent of :meth:`thickness_for`'s draws."""
        x_samples = jnp.atleast_2d(x_samples)
        S = x_samples.shape[0]
        m = data.rows.membrane
        known = (m < self.n_membranes)[None, :]
        key = jax.random.PRNGKey(1) if key is None else jax.random.fold_in(key, 1)
        out = {}
        for j, q in enumerate(self.membrane_params):
            spec = self.specs[self.names.index(q)]
            k = self.names.index(f"{q}[0]")
            own = x_samples[:, k : k + self.n_membranes][:, jnp.clip(m, 0, self.n_membranes - 1)]
            u_c = spec.to_unconstrained(x_samples[:, self.names.index(q)])
            sd = x_samples[:, self.names.index(q + SPREAD)]
            eps = jax.random.normal(jax.random.fold_in(key, j), (S, len(data.design_keys)))[:, m]
            fresh = spec.to_physical(u_c[:, None] + sd[:, None] * eps)
            out[q] = jnp.where(known, own, fresh)
        return out

    def sample_force(self, x_samples, data: CalibrationData, key=None) -> jax.Array:
        """Expected recorded force [S, N] for posterior samples ``x_samples`` [S, dim]
        (``data.rows.membrane`` indexes the calibrated membranes first; higher indices are
        new membranes whose thickness and per-membrane effect values come from the
        population)."""
        t = self.thickness_for(x_samples, data, key)
        e = self.effects_for(x_samples, data, key)
        # lax.map in small batches, not one vmap: S draws x N rows x the emulator's hidden
        # width at once runs to tens of GB on a trajectory grid.
        return jax.lax.map(
            lambda a: self.expected_force(a[0], data, a[1], effect_rows=a[2]),
            (jnp.atleast_2d(x_samples), t, e),
            batch_size=SAMPLE_BATCH,
        )


DISCREPANCY_ROWS = 20_000  # rows the discrepancy is fitted and scored on (fit_discrepancy)


def fit_discrepancy(
    model: HierarchicalModel, x_ref, table, design_keys: Sequence[str], config, *, key=0, progress=False
):
    """The discrepancy delta: a gated RPN ensemble (:mod:`mfdesign.models.discrepancy`)
    fitted to ``F - E(x_ref)`` over the rows of ``table`` that calibration uses
    (Measurements of the calibrated membranes, as measured: the floating-lift rule needs
    whole trials; ``design_keys`` in the calibration's order, so that each row gets its
    membrane's latent thickness), with ``x_ref`` the MAP or posterior median (physical).
    Use a non-monotone ``config``: residuals need not grow with pressure. The gate's
    length scale and prior spread come from leave-one-membrane-out on these rows. Returns
    the fitted :class:`~mfdesign.models.discrepancy.Discrepancy`."""
    enable_x64()  # float64 physics: mfdesign._x64
    from mfdesign.models.discrepancy import fit_gated

    # the rows are the calibration's own (floating lift rows: the rule runs once, on whole
    # trials), at most DISCREPANCY_ROWS of them evenly along every trial: the ensemble trains
    # on minibatches, but its leave-one-membrane-out scores predict every row with K x M
    # members (on the bundled 150,503 rows: 48 members x 32 float32 activations, ~0.9 GB a
    # hidden layer; with 20,000 rows the fit still adds ~0.7 GB to the demo's RSS, issue 40);
    # the 2 Hz ramps carry little new information row to row
    data = CalibrationData.from_measurements(
        table, max_rows=DISCREPANCY_ROWS, design_keys=design_keys, seed=key if isinstance(key, int) else 0
    )
    resid = np.asarray(data.force_n - model.expected_force(jnp.asarray(x_ref), data))
    ok = np.isfinite(resid)
    return fit_gated(
        config,
        np.asarray(data.design)[ok],
        np.asarray(data.rows.h_mm)[ok],
        np.asarray(data.rows.p_pa)[ok],
        resid[ok],
        np.asarray(data.weight)[ok],
        np.asarray(data.rows.membrane)[ok],
        key=key,
        progress=progress,
    )
