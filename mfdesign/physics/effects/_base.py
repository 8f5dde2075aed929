"""The effect base classes, their parameters and the registry (see the package doc)."""

from __future__ import annotations

import abc
import dataclasses
import inspect
from dataclasses import dataclass
from typing import Any, Callable, ClassVar, Iterable, Mapping

import equinox as eqx
import jax
import jax.numpy as jnp
import numpy as np
import optimistix as optx

from mfdesign.physics.effects._rows import Rows
from mfdesign.physics.params import SimParams

__all__ = [
    "EFFECTS",
    "Context",
    "Effect",
    "MeasurementEffect",
    "MechanicalEffect",
    "Parameter",
    "apply_expected_force",
    "apply_row_sim_params",
    "apply_sim_params",
    "effect",
    "neutral_theta",
    "observed_force_fn",
    "recorded_lift_height",
    "register_effect",
    "split_theta",
    "typical_theta",
]

ForceFn = Callable[[jax.Array, jax.Array], jax.Array]


# -- parameters and context ---------------------------------------------------------------------
@dataclass(frozen=True)
class Parameter:
    """One named parameter of an effect: unit, prior, value that switches it off, realistic size."""

    name: str
    unit: str
    prior: Any  # a Prior (Uniform | Normal | LogNormal) or anything with logpdf / sample / bounds
    neutral: float
    typical: float
    doc: str = ""


@dataclass(frozen=True)
class Context:
    """What a mechanical effect's :meth:`Effect.sim_params` may need to know about a trial.

    * ``experiment``: ``"force"`` (plate held at a set height) or ``"lift"`` (mass on a free plate);
    * ``trial_index``: order of the trial within the membrane's life (0 = first inflation);
    * ``design``: the :class:`~mfdesign.design.Membrane`.
    """

    experiment: str = "force"
    trial_index: Any = 0
    design: Any = None


# -- the effect base classes -------------------------------------------------------------------
class Effect(eqx.Module):
    """An effect: class-level ``name``, ``story`` and ``parameters``, and two hooks declared
    abstract here (the interface, as diffrax's ``AbstractSolver`` declares its own).
    Subclass :class:`MechanicalEffect` (it implements ``sim_params``) or
    :class:`MeasurementEffect` (``observed_force_fn``); the other hook is then the identity.
    An effect is a frozen module without fields: everything it knows is its class."""

    name: ClassVar[str] = ""
    story: ClassVar[str] = ""
    parameters: ClassVar[tuple[Parameter, ...]] = ()
    # how a lab measures the effect itself, not through the force (what a diagnosis
    # recommends when force data cannot tell this effect from another)
    direct_check: ClassVar[str] = ""

    # -- hooks ----------------------------------------------------------------------------
    @abc.abstractmethod
    def sim_params(self, base: SimParams, theta: Mapping[str, Any], context: Context | None = None) -> SimParams:
        """Simulator inputs with the effect on the mechanics (``dataclasses.replace(base, ...)``)."""

    @abc.abstractmethod
    def observed_force_fn(self, theta: Mapping[str, Any], force_fn: ForceFn, rows: Rows) -> ForceFn:
        """Map ``force_fn(h, p) -> F`` (the expected recorded force [N] at recorded height h
        [mm] and pressure p [Pa], with the effects applied so far) to the same with this
        effect applied. JAX, traceable in ``theta``.

        ``force_fn`` is element-wise over the rows (row i depends on ``h[i], p[i]`` only), which
        lets an effect take ``dF/dh`` with one ``jax.jvp``. The likelihood evaluates the result
        at the recorded ``(h, p)``; the virtual rig uses the same function to record (a force
        trial: at its set-points; a mass lift: where it equals the weight).
        """

    def row_sim_params(self, base: SimParams, theta: Mapping[str, Any], rows: Rows) -> SimParams:
        """Row-wise simulator inputs (fields scalar or ``[N]``) for a jitted likelihood; default:
        ``sim_params`` without a context. Override when the mechanics depend on the row."""
        return self.sim_params(base, theta, None)

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

    def full_theta(self, theta: Mapping[str, Any] | None = None) -> dict[str, Any]:
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
        return float(sum(np.sum(np.asarray(p.prior.logpdf(th[p.name]))) for p in self.parameters))

    def sample_prior(self, rng: np.random.Generator) -> dict[str, float]:
        return {p.name: float(p.prior.sample(rng)) for p in self.parameters}

    def describe(self) -> str:
        pars = ", ".join(f"{p.name} [{p.unit}] (neutral {p.neutral:g}, typical {p.typical:g})" for p in self.parameters)
        return f"{self.name}: {self.story} -- {pars}"

    def expected_force(self, theta: Mapping[str, Any], force_fn: ForceFn, rows: Rows) -> jax.Array:
        """Expected recorded force [N] of every row at its recorded (h, p) with this effect alone."""
        return self.observed_force_fn(theta, force_fn, rows)(rows.h_mm, rows.p_pa)


class MechanicalEffect(Effect):
    """An effect on the mechanics: it acts only through the simulator's inputs
    (:class:`~mfdesign.physics.params.SimParams`); the recording is the identity."""

    @abc.abstractmethod
    def sim_params(self, base: SimParams, theta: Mapping[str, Any], context: Context | None = None) -> SimParams:
        """Simulator inputs with the effect (``dataclasses.replace(base, ...)``)."""

    def observed_force_fn(self, theta: Mapping[str, Any], force_fn: ForceFn, rows: Rows) -> ForceFn:
        return force_fn


class MeasurementEffect(Effect):
    """An effect of the measurement chain (sensors, rig, rate-dependence): one JAX hook,
    ``observed_force_fn``, for the virtual rig and the likelihood alike."""

    def sim_params(self, base: SimParams, theta: Mapping[str, Any], context: Context | None = None) -> SimParams:
        return base

    @abc.abstractmethod
    def observed_force_fn(self, theta: Mapping[str, Any], force_fn: ForceFn, rows: Rows) -> ForceFn:
        """``force_fn`` with the effect applied (see :meth:`Effect.observed_force_fn`)."""


# -- the registry -----------------------------------------------------------------------------
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
        hint = (
            "it has no likelihood hook: implement observed_force_fn(theta, force_fn, rows) (docs/effects.md)"
            if "observed_force_fn" in missing and issubclass(cls, MeasurementEffect)
            else "subclass MechanicalEffect (implement sim_params) or MeasurementEffect (implement observed_force_fn)"
        )
        raise TypeError(f"effect {cls.__name__} does not implement {missing}: {hint}")
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


def split_theta(effects: Iterable[str | Effect], theta: Mapping[str, Any] | None) -> dict[str, dict[str, Any]]:
    """Per-effect thetas from a flat ``{"effect.param": value}`` or a nested
    ``{"effect": {"param": value}}`` dict; missing parameters take their neutral value;
    a name that belongs to no listed effect is an error (a typo must not pass silently)."""
    effects = _as_effects(effects)
    theta = dict(theta or {})
    per: dict[str, dict[str, Any]] = {e.name: {} for e in effects}
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


def _replace(params: SimParams, **changes) -> SimParams:
    return dataclasses.replace(params, **changes)


# -- composition ------------------------------------------------------------------------------
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


def apply_row_sim_params(effects, theta, base: SimParams, rows: Rows) -> SimParams:
    """Row-wise simulator inputs with every mechanical effect applied, in list order (JAX)."""
    effects = _as_effects(effects)
    per = split_theta(effects, theta)
    params = base
    for e in effects:
        params = e.row_sim_params(params, per[e.name], rows)
    return params


def observed_force_fn(effects, theta, force_fn: ForceFn, rows: Rows) -> ForceFn:
    """``force_fn`` wrapped by every effect's ``observed_force_fn`` in list order (JAX)."""
    effects = _as_effects(effects)
    per = split_theta(effects, theta)
    for e in effects:
        force_fn = e.observed_force_fn(per[e.name], force_fn, rows)
    return force_fn


def apply_expected_force(effects, theta, force_fn: ForceFn, rows: Rows) -> jax.Array:
    """Expected recorded force [N] of every row at its recorded (h, p), all effects applied.

    The likelihood's mean; the virtual rig records a force trial with it (``force_fn`` the
    truth, ``rows`` the rig's set-points)."""
    return observed_force_fn(effects, theta, force_fn, rows)(rows.h_mm, rows.p_pa)


def recorded_lift_height(
    effects,
    theta,
    force_fn: ForceFn,
    rows: Rows,
    weight_n,
    start_mm,
    atol: float = 1e-7,
    max_steps: int = 64,
) -> jax.Array:
    """Recorded plate height [mm] of each mass-lift row: where the expected recorded force at
    the row's recorded pressure equals the weight, ``F_obs(h, p) = W`` (JAX).

    The inverse of what the likelihood assumes for a lift row (its expected "force" at the
    recorded (h, p) is W), so a virtual lift is recorded by the same hooks. One Newton root
    find per row (``optimistix``, vmapped), from ``start_mm`` (the branch the plate is on):
    exact, where the first-order shift ``dh = (W - F_obs) / dF_dh`` of a single step is not.
    NaN where it does not converge. ``force_fn`` should be defined below and above the
    plate's range (the virtual rig adds its support and top stop as stiff springs).
    """
    effects = _as_effects(effects)
    solver: optx.AbstractRootFinder = optx.Newton(rtol=1e-12, atol=atol)

    def one(row: Rows, weight, start):
        fn = observed_force_fn(effects, theta, force_fn, row)
        sol: optx.Solution = optx.root_find(
            lambda h, _: fn(h, row.p_pa) - weight, solver, start, max_steps=max_steps, throw=False
        )
        return jnp.where(sol.result == optx.RESULTS.successful, sol.value, jnp.nan)

    n = rows.h_mm.shape[0]
    weight_n = jnp.broadcast_to(jnp.asarray(weight_n, float), (n,))
    start_mm = jnp.broadcast_to(jnp.asarray(start_mm, float), (n,))
    return jax.vmap(one)(rows, weight_n, start_mm)
