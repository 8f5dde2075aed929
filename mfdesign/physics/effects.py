"""Physical effects that the plain membrane model lacks: the candidates for "what is missing".

An effect is a small class: a ``name``, a one-line physical ``story``, its ``parameters``
(each with a unit, a prior, the ``neutral`` value at which the effect does nothing and a
``typical`` realistic magnitude) and up to two hooks:

* ``sim_params(base, theta, context) -> SimParams``: effects on the *mechanics* act only
  through the simulator's inputs (:class:`~mfdesign.physics.params.SimParams`). Default:
  identity.
* ``observe(theta, sample, context) -> Sample``: effects of the *measurement chain*
  (sensors, rig, rate-dependence of the rubber) turn the true values of a
  :class:`Sample` into what the rig records. Default: identity.

``theta`` handed to a hook is the effect's own ``{parameter name: value}``; a missing
name means the neutral value. Across several effects, a flat dict with qualified names
``"effect.parameter"`` is used (see :func:`split_theta`).

Writing a new effect (see ``docs/effects.md``)::

    @register_effect
    @dataclass(frozen=True)
    class HeightSensorOffset(Effect):
        name = "height_offset"
        story = "the time-of-flight sensors read the lifted plate a fixed distance high"
        parameters = (Parameter("offset_mm", "mm", Normal(0.0, 2.0), 0.0, 1.5),)

        def observe(self, theta, sample, context):
            if context.experiment != "lift":
                return sample
            return sample.replace(height_mm=sample.height_mm + theta["offset_mm"])

Sign conventions: heights are of the plate above the membrane plane (mm), the membrane
pushes the plate *up* (positive force), the force falls with height at fixed pressure, so
``dF_dh`` (N/mm) is usually negative.
"""

from __future__ import annotations

import dataclasses
import math
from dataclasses import dataclass
from typing import Any, ClassVar, Iterable, Mapping

import equinox as _eqx
import jax as _jax
import jax.numpy as _jnp
import numpy as np

from mfdesign.physics.params import SimParams

__all__ = [
    "EFFECTS",
    "Context",
    "Effect",
    "LogNormal",
    "Normal",
    "Parameter",
    "Sample",
    "Uniform",
    "apply_observe",
    "apply_sim_params",
    "effect",
    "neutral_theta",
    "register_effect",
    "split_theta",
    "typical_theta",
]


# -- priors ---------------------------------------------------------------------------------
@dataclass(frozen=True)
class Uniform:
    """Uniform on ``[low, high]``."""

    low: float
    high: float

    def __post_init__(self):
        if not (math.isfinite(self.low) and math.isfinite(self.high) and self.low < self.high):
            raise ValueError(f"Uniform needs finite low < high, got {self.low}, {self.high}")

    @property
    def bounds(self) -> tuple[float, float]:
        return (self.low, self.high)

    def logpdf(self, x):
        x = np.asarray(x, float)
        inside = (x >= self.low) & (x <= self.high)
        return np.where(inside, -math.log(self.high - self.low), -np.inf)

    def sample(self, rng: np.random.Generator, size=None):
        return rng.uniform(self.low, self.high, size=size)

    def logpdf_jax(self, x):
        """JAX log-density (same maths as :meth:`logpdf`), for jitted log-posteriors."""
        inside = (x >= self.low) & (x <= self.high)
        return _jnp.where(inside, -math.log(self.high - self.low), -_jnp.inf)


@dataclass(frozen=True)
class Normal:
    """Normal ``N(mean, sd)``, optionally truncated to ``[low, high]`` (renormalised)."""

    mean: float
    sd: float
    low: float = -math.inf
    high: float = math.inf

    def __post_init__(self):
        if not (self.sd > 0 and self.low < self.high):
            raise ValueError(f"Normal needs sd > 0 and low < high, got sd={self.sd}, [{self.low}, {self.high}]")

    @property
    def bounds(self) -> tuple[float, float]:
        return (self.low, self.high)

    def _mass(self) -> float:
        cdf = lambda x: 0.5 * (1.0 + math.erf((x - self.mean) / (self.sd * math.sqrt(2.0))))
        return cdf(self.high) - cdf(self.low)

    def logpdf(self, x):
        x = np.asarray(x, float)
        z = (x - self.mean) / self.sd
        lp = -0.5 * z**2 - math.log(self.sd * math.sqrt(2.0 * math.pi)) - math.log(self._mass())
        return np.where((x >= self.low) & (x <= self.high), lp, -np.inf)

    def sample(self, rng: np.random.Generator, size=None):
        n = 1 if size is None else int(np.prod(size))
        out = np.empty(0)
        while out.size < n:  # rejection: fine for the mild truncations used here
            draw = rng.normal(self.mean, self.sd, size=2 * n + 8)
            out = np.concatenate([out, draw[(draw >= self.low) & (draw <= self.high)]])
        out = out[:n]
        return float(out[0]) if size is None else out.reshape(size)

    def logpdf_jax(self, x):
        """JAX log-density (same maths as :meth:`logpdf`), for jitted log-posteriors."""
        z = (x - self.mean) / self.sd
        lp = -0.5 * z**2 - math.log(self.sd * math.sqrt(2.0 * math.pi)) - math.log(self._mass())
        return _jnp.where((x >= self.low) & (x <= self.high), lp, -_jnp.inf)


@dataclass(frozen=True)
class LogNormal:
    """``log x ~ N(log median, sigma)``, optionally truncated to ``[low, high]`` (x > 0)."""

    median: float
    sigma: float
    low: float = 0.0
    high: float = math.inf

    def __post_init__(self):
        if not (self.median > 0 and self.sigma > 0 and 0 <= self.low < self.high):
            raise ValueError("LogNormal needs median > 0, sigma > 0 and 0 <= low < high")

    @property
    def bounds(self) -> tuple[float, float]:
        return (self.low, self.high)

    def _log_normal(self) -> Normal:
        lo = math.log(self.low) if self.low > 0 else -math.inf
        hi = math.log(self.high) if math.isfinite(self.high) else math.inf
        return Normal(math.log(self.median), self.sigma, lo, hi)

    def logpdf(self, x):
        x = np.asarray(x, float)
        with np.errstate(divide="ignore", invalid="ignore"):
            lx = np.log(np.where(x > 0, x, np.nan))
            lp = self._log_normal().logpdf(lx) - lx
        return np.where(x > 0, lp, -np.inf)

    def sample(self, rng: np.random.Generator, size=None):
        return np.exp(self._log_normal().sample(rng, size))

    def logpdf_jax(self, x):
        """JAX log-density (same maths as :meth:`logpdf`), for jitted log-posteriors."""
        pos = x > 0
        lx = _jnp.log(_jnp.where(pos, x, 1.0))
        lp = self._log_normal().logpdf_jax(lx) - lx
        return _jnp.where(pos, lp, -_jnp.inf)


# -- parameters, samples, context -------------------------------------------------------------
@dataclass(frozen=True)
class Parameter:
    """One named parameter of an effect: unit, prior, value that switches it off, realistic size."""

    name: str
    unit: str
    prior: Any  # Uniform | Normal | LogNormal | anything with logpdf / sample / bounds
    neutral: float
    typical: float
    doc: str = ""


@dataclass(frozen=True)
class Sample:
    """Arrays of one shape: plate height [mm], gauge pressure [Pa], force on the plate [N].

    True values go into :meth:`Effect.observe`, observed values come out.
    """

    height_mm: np.ndarray
    pressure_pa: np.ndarray
    force_n: np.ndarray

    def replace(self, **changes) -> "Sample":
        return dataclasses.replace(self, **changes)


@dataclass(frozen=True)
class Context:
    """What an effect may need to know about the samples (arrays broadcast with the sample).

    * ``experiment``: ``"force"`` (plate held at a set height) or ``"lift"`` (mass on a free
      plate; ``force_n`` is then the weight of the mass, not a load-cell reading).
    * ``trial_index``: order of the trial within the membrane's life (0 = first inflation).
    * ``phase``: ``"inflate"`` / ``"deflate"`` per sample (``is_deflate`` as a bool mask).
    * ``time_s``: time since the trial started.
    * ``dF_dh``: slope of the true force with plate height at fixed pressure [N/mm] (from
      the simulator; usually negative), for effects that move the plate.
    * ``design``: the :class:`~mfdesign.design.Membrane`, ``rng``: a NumPy Generator for
      effects with their own randomness (the virtual rig passes a seeded one).
    """

    experiment: str = "force"
    trial_index: Any = 0
    phase: Any = "inflate"
    time_s: Any = None
    dF_dh: Any = None
    design: Any = None
    rng: Any = None

    @property
    def is_deflate(self) -> np.ndarray:
        return np.asarray(self.phase) == "deflate"


# -- the effect base class and the registry -----------------------------------------------------
class Effect:
    """Base class of an effect; subclasses set ``name``, ``story``, ``parameters`` and
    override one or both hooks. Instances carry no state (use frozen dataclasses)."""

    name: ClassVar[str] = ""
    story: ClassVar[str] = ""
    parameters: ClassVar[tuple[Parameter, ...]] = ()

    # -- hooks ----------------------------------------------------------------------------
    def sim_params(self, base: SimParams, theta: Mapping[str, float], context: Context | None = None) -> SimParams:
        return base

    def observe(self, theta: Mapping[str, float], sample: Sample, context: Context) -> Sample:
        return sample

    # -- helpers --------------------------------------------------------------------------
    @property
    def acts_on_mechanics(self) -> bool:
        return type(self).sim_params is not Effect.sim_params

    @property
    def acts_on_measurement(self) -> bool:
        return type(self).observe is not Effect.observe

    @property
    def parameter_names(self) -> tuple[str, ...]:
        return tuple(p.name for p in self.parameters)

    def qualified(self, pname: str) -> str:
        return f"{self.name}.{pname}"

    def full_theta(self, theta: Mapping[str, float] | None = None) -> dict[str, float]:
        """The effect's own theta with every parameter present (missing -> neutral)."""
        theta = dict(theta or {})
        unknown = set(theta) - set(self.parameter_names)
        if unknown:
            raise KeyError(
                f"effect {self.name!r} has no parameter(s) {sorted(unknown)}; "
                f"its parameters: {list(self.parameter_names)}"
            )
        return {p.name: theta.get(p.name, p.neutral) for p in self.parameters}

    def neutral(self) -> dict[str, float]:
        return {p.name: p.neutral for p in self.parameters}

    def typical(self) -> dict[str, float]:
        return {p.name: p.typical for p in self.parameters}

    def log_prior(self, theta: Mapping[str, float]) -> float:
        th = self.full_theta(theta)
        return float(sum(np.sum(p.prior.logpdf(th[p.name])) for p in self.parameters))

    def sample_prior(self, rng: np.random.Generator) -> dict[str, float]:
        return {p.name: float(p.prior.sample(rng)) for p in self.parameters}

    def describe(self) -> str:
        pars = ", ".join(f"{p.name} [{p.unit}] (neutral {p.neutral:g}, typical {p.typical:g})" for p in self.parameters)
        return f"{self.name}: {self.story} -- {pars}"

    def __repr__(self) -> str:
        return f"{type(self).__name__}()"

    # -- the likelihood side (JAX): every effect inside a jitted log-likelihood ------------------
    # The hooks above turn true values into recorded ones (NumPy, for the virtual rig); these
    # give, for a recorded row, the EXPECTED recorded force at the row's RECORDED height and
    # pressure as a pure JAX function of theta (traced), so that emcee / optimistix can
    # differentiate and vectorise it.
    def row_sim_params(self, base: SimParams, theta, rows: "Rows") -> SimParams:
        """Row-wise simulator inputs (fields scalar or ``[N]``); default: ``sim_params`` without
        a context. Override when the mechanics depend on the row (trial, phase)."""
        return self.sim_params(base, theta, None)

    def observed_force_fn(self, theta, force_fn, rows: "Rows"):
        """Map ``force_fn(h_rec, p_rec) -> F`` (the expected recorded force of the effects applied
        so far) to the same with this effect applied; default: identity (no measurement effect).

        ``force_fn`` is element-wise over the rows (row i depends on ``h[i], p[i]`` only), which
        lets effects take ``dF/dh`` with one ``jax.jvp``.
        """
        return force_fn

    def expected_force(self, theta, force_fn, rows: "Rows"):
        """Expected recorded force [N] of every row at its recorded (h, p) with this effect alone."""
        return self.observed_force_fn(theta, force_fn, rows)(rows.h_mm, rows.p_pa)

    @property
    def has_likelihood(self) -> bool:
        """False for a measurement effect without a JAX likelihood hook (calibration refuses it)."""
        return (not self.acts_on_measurement) or type(self).observed_force_fn is not Effect.observed_force_fn


EFFECTS: dict[str, type[Effect]] = {}


def register_effect(cls: type[Effect]) -> type[Effect]:
    """Class decorator: add an effect class to :data:`EFFECTS` under its ``name``."""
    if not (isinstance(cls, type) and issubclass(cls, Effect)):
        raise TypeError(f"register_effect takes a subclass of Effect, got {cls!r}")
    if not cls.name or not cls.story:
        raise ValueError(f"effect {cls.__name__} needs a non-empty name and story")
    names = [p.name for p in cls.parameters]
    if len(set(names)) != len(names):
        raise ValueError(f"effect {cls.name!r}: duplicate parameter names {names}")
    for p in cls.parameters:
        lo, hi = p.prior.bounds
        if not (lo <= p.typical <= hi):
            raise ValueError(f"effect {cls.name!r}: typical {p.name} = {p.typical} outside the prior {p.prior}")
    other = EFFECTS.get(cls.name)
    if other is not None and other.__qualname__ != cls.__qualname__:
        raise ValueError(f"an effect named {cls.name!r} is already registered ({other.__qualname__})")
    EFFECTS[cls.name] = cls
    return cls


def effect(name_or_effect: str | Effect) -> Effect:
    """An effect instance from its registered name (or the instance itself)."""
    if isinstance(name_or_effect, Effect):
        return name_or_effect
    try:
        return EFFECTS[name_or_effect]()
    except KeyError:
        raise KeyError(f"no effect named {name_or_effect!r}; registered: {sorted(EFFECTS)}") from None


def _as_effects(effects: Iterable[str | Effect]) -> list[Effect]:
    out = [effect(e) for e in effects]
    names = [e.name for e in out]
    if len(set(names)) != len(names):
        raise ValueError(f"an effect appears twice: {names}")
    return out


def split_theta(effects: Iterable[str | Effect], theta: Mapping[str, Any] | None) -> dict[str, dict[str, float]]:
    """Per-effect thetas from a flat ``{"effect.param": value}`` or a nested
    ``{"effect": {"param": value}}`` dict; missing parameters take their neutral value;
    a name that belongs to no listed effect is an error (a typo must not pass silently)."""
    effects = _as_effects(effects)
    theta = dict(theta or {})
    per: dict[str, dict[str, float]] = {e.name: {} for e in effects}
    for key, value in theta.items():
        if isinstance(value, Mapping):
            if key not in per:
                raise KeyError(f"theta names effect {key!r}, not among {list(per)}")
            per[key].update(value)
            continue
        name, _, pname = key.partition(".")
        if name not in per or not pname:
            raise KeyError(f"theta key {key!r}: expected 'effect.parameter' with effect among {list(per)}")
        per[name][pname] = value
    return {e.name: e.full_theta(per[e.name]) for e in effects}


def neutral_theta(effects: Iterable[str | Effect]) -> dict[str, float]:
    """Flat theta that switches every listed effect off."""
    return {e.qualified(p.name): p.neutral for e in _as_effects(effects) for p in e.parameters}


def typical_theta(effects: Iterable[str | Effect]) -> dict[str, float]:
    """Flat theta with every listed effect at its realistic magnitude."""
    return {e.qualified(p.name): p.typical for e in _as_effects(effects) for p in e.parameters}


def apply_sim_params(
    effects: Iterable[str | Effect],
    theta: Mapping[str, Any] | None,
    base: SimParams = SimParams(),
    context: Context | None = None,
) -> SimParams:
    """The simulator inputs with every mechanical effect applied, in list order."""
    effects = _as_effects(effects)
    per = split_theta(effects, theta)
    params = base
    for e in effects:
        params = e.sim_params(params, per[e.name], context)
        if not isinstance(params, SimParams):
            raise TypeError(f"effect {e.name!r}.sim_params returned {type(params).__name__}, not SimParams")
    return params


def apply_observe(
    effects: Iterable[str | Effect],
    theta: Mapping[str, Any] | None,
    sample: Sample,
    context: Context,
) -> Sample:
    """True values -> observed values through every measurement effect, in list order."""
    effects = _as_effects(effects)
    per = split_theta(effects, theta)
    for e in effects:
        sample = e.observe(per[e.name], sample, context)
        if not isinstance(sample, Sample):
            raise TypeError(f"effect {e.name!r}.observe returned {type(sample).__name__}, not Sample")
    return sample


def _replace(params: SimParams, **changes) -> SimParams:
    return dataclasses.replace(params, **changes)


# -- mechanics: effects through SimParams ------------------------------------------------------
@register_effect
@dataclass(frozen=True)
class ThicknessDeviation(Effect):
    name = "thickness_deviation"
    story = "gravity moulding leaves a membrane thicker or thinner than its nominal thickness"
    parameters = (Parameter("relative", "1", Normal(0.0, 0.1, -0.5, 0.5), 0.0, 0.08, "actual / nominal thickness - 1"),)

    def sim_params(self, base, theta, context=None):
        return _replace(base, thickness_factor=base.thickness_factor * (1.0 + theta["relative"]))


@register_effect
@dataclass(frozen=True)
class ThicknessGradient(Effect):
    name = "thickness_gradient"
    story = "the uncured rubber flows outwards in the mould: the membrane thins (or thickens) towards the clamp"
    parameters = (
        Parameter(
            "gradient",
            "1",
            Normal(0.0, 0.15, -0.6, 0.6),
            0.0,
            -0.15,
            "relative thickness change from the disk edge to the clamp (zero-mean)",
        ),
    )

    def sim_params(self, base, theta, context=None):
        return _replace(base, thickness_gradient=base.thickness_gradient + theta["gradient"])


@register_effect
@dataclass(frozen=True)
class ClampPrestretch(Effect):
    name = "clamp_prestretch"
    story = "clamping the membrane stretches it radially before inflation"
    parameters = (Parameter("strain", "1", Uniform(0.0, 0.08), 0.0, 0.02, "hoop stretch at the clamp - 1"),)

    def sim_params(self, base, theta, context=None):
        return _replace(base, clamp_prestretch=base.clamp_prestretch * (1.0 + theta["strain"]))


@register_effect
@dataclass(frozen=True)
class RingSoftening(Effect):
    name = "ring_softening"
    story = "the fabric rings partly delaminate from the rubber, so they are less stiff than assumed"
    parameters = (
        Parameter("factor", "1", LogNormal(0.5, 1.0, 0.01, 1.0), 1.0, 0.3, "effective / assumed ring shear modulus"),
    )

    def sim_params(self, base, theta, context=None):
        return _replace(base, ring_mu_pa=base.ring_mu_pa * theta["factor"])


@register_effect
@dataclass(frozen=True)
class ContactOffset(Effect):
    name = "contact_offset"
    story = "the membrane sticks to the plate beyond the rigid disk, so the effective contact radius is larger"
    parameters = (Parameter("offset_mm", "mm", Uniform(0.0, 6.0), 0.0, 2.0, "effective - nominal contact radius"),)

    def sim_params(self, base, theta, context=None):
        return _replace(base, contact_offset_mm=base.contact_offset_mm + theta["offset_mm"])


@register_effect
@dataclass(frozen=True)
class StressSoftening(Effect):
    name = "stress_softening"
    story = "Mullins effect: the virgin rubber of the first inflation is stiffer than in every later trial"
    parameters = (
        Parameter(
            "stiffening",
            "1",
            Uniform(0.0, 0.5),
            0.0,
            0.15,
            "relative increase of the rubber's shear modulus on the membrane's first trial",
        ),
    )

    def sim_params(self, base, theta, context=None):
        first = context is not None and int(np.min(context.trial_index)) == 0
        if not first:
            return base
        return _replace(base, mu_pa=base.mu_pa * (1.0 + theta["stiffening"]))

    def row_sim_params(self, base, theta, rows):
        factor = 1.0 + theta["stiffening"] * rows.is_first_trial.astype(float)
        return _replace(base, mu_pa=base.mu_pa * factor)


# -- measurement chain --------------------------------------------------------------------
@register_effect
@dataclass(frozen=True)
class PressureSensor(Effect):
    name = "pressure_sensor"
    story = "the pressure transducer has a zero offset and a gain error"
    parameters = (
        Parameter("offset_pa", "Pa", Normal(0.0, 150.0), 0.0, 150.0, "reading at zero gauge pressure"),
        Parameter("gain", "1", Normal(1.0, 0.03, 0.8, 1.2), 1.0, 1.0, "reading / true pressure"),
    )

    def observe(self, theta, sample, context):
        return sample.replace(pressure_pa=theta["gain"] * sample.pressure_pa + theta["offset_pa"])

    def observed_force_fn(self, theta, force_fn, rows):
        # recorded p = gain * p_true + offset  =>  p_true = (p - offset) / gain
        return lambda h, p: force_fn(h, (p - theta["offset_pa"]) / theta["gain"])


@register_effect
@dataclass(frozen=True)
class LoadCellOffset(Effect):
    name = "load_cell_offset"
    story = "the load cell was tared with a different preload: every force reading is shifted"
    parameters = (Parameter("offset_n", "N", Normal(0.0, 1.0), 0.0, 0.8, "reading at zero force"),)

    def observe(self, theta, sample, context):
        if context.experiment != "force":
            return sample  # in a mass lift the force column is the known weight
        return sample.replace(force_n=sample.force_n + theta["offset_n"])

    def observed_force_fn(self, theta, force_fn, rows):
        return lambda h, p: force_fn(h, p) + _jnp.where(rows.is_force, theta["offset_n"], 0.0)


@register_effect
@dataclass(frozen=True)
class RigCompliance(Effect):
    """The frame that holds the plate at its set height is a spring of stiffness ``k``.

    The membrane pushes the plate up with the force ``F_obs`` the load cell reads; the
    frame yields by ``F_obs / k``, so the true plate height is ``h_set + F_obs / k`` while
    the height sensors, mounted on the same frame, still read ``h_set``. Self-consistency:
    ``F_obs = F(h_set + F_obs / k)``; to first order ``F_obs = F + dF_dh F_obs / k``, so
    ``F_obs = F / (1 - dF_dh / k)``. With ``dF_dh < 0`` (force falls with height) the rig
    reads less than the stiff-rig force. Parameterised by the compliance ``1 / k`` so that
    0 is the neutral value.
    """

    name = "rig_compliance"
    story = "the rig's frame yields under the membrane's push: the plate sits higher than its set-point"
    parameters = (
        Parameter("compliance_mm_per_n", "mm/N", Uniform(0.0, 0.1), 0.0, 0.02, "1 / k, plate displacement per newton"),
    )

    def observe(self, theta, sample, context):
        c = theta["compliance_mm_per_n"]
        if context.experiment != "force" or c == 0.0:
            return sample
        if context.dF_dh is None:
            raise ValueError("rig_compliance needs context.dF_dh (N/mm) from the simulator")
        slope = np.nan_to_num(np.asarray(context.dF_dh, float), nan=0.0)
        denom = np.maximum(1.0 - slope * c, 0.2)  # guard a rising F(h): never amplify > 5x
        return sample.replace(force_n=sample.force_n / denom)

    def observed_force_fn(self, theta, force_fn, rows):
        c = theta["compliance_mm_per_n"]

        def fn(h, p):
            f, slope = _jax.jvp(lambda hh: force_fn(hh, p), (h,), (_jnp.ones_like(h),))
            slope = _jnp.nan_to_num(slope, nan=0.0)
            denom = _jnp.maximum(1.0 - slope * c, 0.2)
            return _jnp.where(rows.is_force, f / denom, f)

        return fn


@register_effect
@dataclass(frozen=True)
class Hysteresis(Effect):
    """Viscoelastic loss: on deflation the rubber carries a fraction ``loss`` less force.

    In a force trial the load cell reads ``(1 - loss) F``. In a mass lift the plate then
    sinks until ``(1 - loss) F(h) = W``: to first order ``dh = loss W / dF_dh`` (< 0).
    """

    name = "hysteresis"
    story = "viscoelastic losses: the membrane pushes less on deflation than on inflation"
    parameters = (Parameter("loss", "1", Uniform(0.0, 0.3), 0.0, 0.08, "fractional force deficit on deflation"),)

    def observe(self, theta, sample, context):
        loss = theta["loss"]
        down = context.is_deflate
        if loss == 0.0 or not np.any(down):
            return sample
        if context.experiment == "force":
            return sample.replace(force_n=np.where(down, (1.0 - loss) * sample.force_n, sample.force_n))
        if context.dF_dh is None:
            raise ValueError("hysteresis in a mass lift needs context.dF_dh (N/mm)")
        slope = np.asarray(context.dF_dh, float)
        ok = np.isfinite(slope) & (slope < -1e-6)
        dh = np.where(ok, loss * sample.force_n / np.where(ok, slope, -1.0), 0.0)
        return sample.replace(height_mm=np.where(down, np.maximum(sample.height_mm + dh, 0.0), sample.height_mm))

    def observed_force_fn(self, theta, force_fn, rows):
        # Force rows: the load cell reads (1 - loss) F. Lift rows: the plate settles where
        # (1 - loss) F(h, p) = W at the recorded h, so the expected "force" sample is the same
        # (1 - loss) F (the forward model moves the height to first order instead).
        loss = theta["loss"]
        return lambda h, p: _jnp.where(rows.is_deflate, (1.0 - loss) * force_fn(h, p), force_fn(h, p))


# -- the likelihood side: the rows a jitted log-likelihood sees (JAX) -------------------------


class Rows(_eqx.Module):
    """Observation context of N recorded rows for a jitted likelihood (all arrays ``[N]``).

    * ``h_mm``, ``p_pa``: the RECORDED plate height [mm] and gauge pressure [Pa];
    * ``is_force``: True for a force trial (the force column is a load-cell reading),
      False for a mass lift (the force column is the known weight ``m g`` [N]);
    * ``is_deflate``: the row was recorded while deflating;
    * ``is_first_trial``: the row belongs to the membrane's first trial (trial id 0);
    * ``membrane``: int index of the row's membrane (into a list of design keys).

    Mass-lift rows enter the likelihood as force samples, as the paper does: the plate is
    in equilibrium at the recorded ``(h, p)``, so the membrane's force there equals the
    weight ``W``; ``expected force = W`` is the observation. Per effect: pressure_sensor
    acts on both kinds (the same transducer); load_cell_offset and rig_compliance only on
    force rows (a lift reads no load cell, and the free plate does not load the frame);
    hysteresis on deflating rows of both kinds (see :class:`Hysteresis`).
    """

    h_mm: _jax.Array
    p_pa: _jax.Array
    is_force: _jax.Array
    is_deflate: _jax.Array
    is_first_trial: _jax.Array
    membrane: _jax.Array

    @classmethod
    def from_measurements(cls, table, design_keys=None) -> "Rows":
        """Rows of a :class:`~mfdesign.data.measurements.Measurements` (membrane index into
        ``design_keys``, default the table's own order)."""
        df = table.df if hasattr(table, "df") else table
        keys = list(design_keys) if design_keys is not None else list(dict.fromkeys(df["design_key"]))
        index = {k: i for i, k in enumerate(keys)}
        missing = sorted(set(df["design_key"]) - set(index))
        if missing:
            raise KeyError(f"Rows: membranes {missing} not among design_keys {keys}")
        return cls(
            h_mm=_jnp.asarray(df["height_mm"].to_numpy(float)),
            p_pa=_jnp.asarray(df["pressure_pa"].to_numpy(float)),
            is_force=_jnp.asarray(df["experiment"].to_numpy() == "force"),
            is_deflate=_jnp.asarray(df["phase"].to_numpy() == "deflate"),
            is_first_trial=_jnp.asarray(df["trial"].to_numpy() == 0),
            membrane=_jnp.asarray(df["design_key"].map(index).to_numpy(np.int32)),
        )

    def __len__(self) -> int:
        return int(self.h_mm.shape[0])

    def take(self, idx) -> "Rows":
        """The rows at integer positions ``idx``."""
        return _jax.tree.map(lambda a: a[idx], self)


def apply_row_sim_params(effects, theta, base: SimParams, rows: Rows) -> SimParams:
    """Row-wise simulator inputs with every mechanical effect applied, in list order (JAX)."""
    effects = _as_effects(effects)
    per = split_theta(effects, theta)
    params = base
    for e in effects:
        params = e.row_sim_params(params, per[e.name], rows)
    return params


def observed_force_fn(effects, theta, force_fn, rows: Rows):
    """``force_fn`` wrapped by every measurement effect in list order (as ``apply_observe``)."""
    effects = _as_effects(effects)
    per = split_theta(effects, theta)
    for e in effects:
        if not e.has_likelihood:
            raise NotImplementedError(
                f"effect {e.name!r} changes measurements (observe) but has no likelihood hook "
                "observed_force_fn(theta, force_fn, rows); add one to use it in calibration"
            )
        force_fn = e.observed_force_fn(per[e.name], force_fn, rows)
    return force_fn


def apply_expected_force(effects, theta, force_fn, rows: Rows):
    """Expected recorded force [N] of every row at its recorded (h, p), all effects applied."""
    return observed_force_fn(effects, theta, force_fn, rows)(rows.h_mm, rows.p_pa)


__all__ += ["Rows", "apply_expected_force", "apply_row_sim_params", "observed_force_fn"]
