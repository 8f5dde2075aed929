"""The effect base class, its parameters and the registry (see the package doc)."""

from __future__ import annotations

import abc
import dataclasses
import inspect
from dataclasses import dataclass
from typing import Any, ClassVar, Iterable, Mapping

import numpy as np

from mfdesign.physics.effects._rows import Rows
from mfdesign.physics.params import SimParams

__all__ = [
    "EFFECTS",
    "Context",
    "Effect",
    "Parameter",
    "Sample",
    "apply_observe",
    "apply_sim_params",
    "effect",
    "neutral_theta",
    "register_effect",
    "split_theta",
    "typical_theta",
    "apply_row_sim_params",
    "observed_force_fn",
    "apply_expected_force",
]


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
class Effect(abc.ABC):
    """An effect: ``name``, ``story``, ``parameters`` and two hooks (the interface, as
    diffrax's ``AbstractSolver`` declares its own). Subclass :class:`MechanicalEffect` (it
    implements ``sim_params``) or :class:`MeasurementEffect` (``observe``); the other hook
    is then the identity. Instances carry no state (use frozen dataclasses)."""

    name: ClassVar[str] = ""
    story: ClassVar[str] = ""
    parameters: ClassVar[tuple[Parameter, ...]] = ()

    # -- hooks ----------------------------------------------------------------------------
    @abc.abstractmethod
    def sim_params(self, base: SimParams, theta: Mapping[str, float], context: Context | None = None) -> SimParams:
        """Simulator inputs with the effect on the mechanics (``dataclasses.replace(base, ...)``)."""

    @abc.abstractmethod
    def observe(self, theta: Mapping[str, float], sample: Sample, context: Context) -> Sample:
        """True height, pressure and force arrays -> what the rig records (the virtual rig)."""

    # -- helpers --------------------------------------------------------------------------
    @property
    def acts_on_mechanics(self) -> bool:
        return isinstance(self, MechanicalEffect)

    @property
    def acts_on_measurement(self) -> bool:
        return isinstance(self, MeasurementEffect)

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


class MechanicalEffect(Effect):
    """An effect on the mechanics: it acts only through the simulator's inputs
    (:class:`~mfdesign.physics.params.SimParams`); the likelihood gets it for free."""

    @abc.abstractmethod
    def sim_params(self, base: SimParams, theta: Mapping[str, float], context: Context | None = None) -> SimParams:
        """Simulator inputs with the effect (``dataclasses.replace(base, ...)``)."""

    def observe(self, theta: Mapping[str, float], sample: Sample, context: Context) -> Sample:
        return sample


class MeasurementEffect(Effect):
    """An effect of the measurement chain (sensors, rig, rate-dependence): ``observe`` for
    the virtual rig and, for calibration and diagnosis, ``observed_force_fn`` (without it the
    effect works as hidden truth only, ``has_likelihood`` False)."""

    def sim_params(self, base: SimParams, theta: Mapping[str, float], context: Context | None = None) -> SimParams:
        return base

    @abc.abstractmethod
    def observe(self, theta: Mapping[str, float], sample: Sample, context: Context) -> Sample:
        """True height, pressure and force arrays -> what the rig records."""


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
    if inspect.isabstract(cls):
        missing = sorted(getattr(cls, "__abstractmethods__", ()))
        raise TypeError(
            f"effect {cls.__name__} does not implement {missing}: subclass MechanicalEffect "
            "(implement sim_params) or MeasurementEffect (implement observe)"
        )
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


# -- the likelihood side: every effect on the rows of a jitted log-likelihood ---------------
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
