"""Priors of effect and model parameters, and the bijections that sampling uses.

A prior (:class:`Prior`) has ONE log-density, :meth:`Prior.logpdf`, written in JAX: a
jitted log-posterior traces it, and a NumPy caller converts the result (``float(...)``,
``np.asarray(...)``). ``sample`` draws with a NumPy Generator, ``bounds`` is the support
and ``center`` a starting point inside it.

Samplers work in an unconstrained coordinate ``u``: :func:`bijection` maps a support
``(lo, hi)`` to the transform (:class:`Interval`: ``lo + (hi - lo) sigmoid(u)``,
:class:`LowerBound`: ``lo + exp(u)``, :class:`UpperBound`: ``hi - exp(u)``,
:class:`Unbounded`: ``u``), each with ``to_physical``, ``log_jacobian`` (``log |dx/du|``)
and ``to_unconstrained``. It is keyed on the bounds alone, so any prior with ``bounds``
works (``models.hierarchical.ParamSpec`` delegates to it).
"""

from __future__ import annotations

import abc
import math

import equinox as eqx
import jax
import jax.numpy as jnp
import numpy as np

__all__ = [
    "Bijection",
    "Interval",
    "LogNormal",
    "LowerBound",
    "Normal",
    "Prior",
    "Unbounded",
    "Uniform",
    "UpperBound",
    "bijection",
]


# -- bijections: unconstrained u <-> physical x ------------------------------------------------
class Bijection(eqx.Module):
    """A smooth map from the real line onto a prior's support."""

    @abc.abstractmethod
    def to_physical(self, u):
        """Unconstrained ``u`` -> physical value inside the support."""

    @abc.abstractmethod
    def log_jacobian(self, u):
        """``log |dx/du|`` at ``u`` (enters a log-density sampled in ``u``)."""

    @abc.abstractmethod
    def to_unconstrained(self, x):
        """Physical ``x`` -> ``u`` (values on or outside a bound are pulled just inside)."""


class Interval(Bijection):
    """``[lo, hi]``: ``x = lo + (hi - lo) sigmoid(u)``."""

    lo: float
    hi: float

    def to_physical(self, u):
        return self.lo + (self.hi - self.lo) * jax.nn.sigmoid(u)

    def log_jacobian(self, u):
        return math.log(self.hi - self.lo) + jax.nn.log_sigmoid(u) + jax.nn.log_sigmoid(-u)

    def to_unconstrained(self, x):
        q = jnp.clip((jnp.asarray(x, float) - self.lo) / (self.hi - self.lo), 1e-12, 1 - 1e-12)
        return jnp.log(q) - jnp.log1p(-q)


class LowerBound(Bijection):
    """``[lo, inf)``: ``x = lo + exp(u)``."""

    lo: float

    def to_physical(self, u):
        return self.lo + jnp.exp(u)

    def log_jacobian(self, u):
        return jnp.asarray(u, float)

    def to_unconstrained(self, x):
        return jnp.log(jnp.maximum(jnp.asarray(x, float) - self.lo, 1e-300))


class UpperBound(Bijection):
    """``(-inf, hi]``: ``x = hi - exp(u)``."""

    hi: float

    def to_physical(self, u):
        return self.hi - jnp.exp(u)

    def log_jacobian(self, u):
        return jnp.asarray(u, float)

    def to_unconstrained(self, x):
        return jnp.log(jnp.maximum(self.hi - jnp.asarray(x, float), 1e-300))


class Unbounded(Bijection):
    """The real line: ``x = u``."""

    def to_physical(self, u):
        return jnp.asarray(u, float)

    def log_jacobian(self, u):
        return jnp.zeros_like(jnp.asarray(u, float))

    def to_unconstrained(self, x):
        return jnp.asarray(x, float)


def bijection(bounds: tuple[float, float]) -> Bijection:
    """The transform onto the support ``bounds = (lo, hi)`` (infinite ends allowed)."""
    lo, hi = bounds
    if math.isfinite(lo) and math.isfinite(hi):
        return Interval(lo, hi)
    if math.isfinite(lo):
        return LowerBound(lo)
    if math.isfinite(hi):
        return UpperBound(hi)
    return Unbounded()


# -- priors ---------------------------------------------------------------------------------------
class Prior(eqx.Module):
    """A prior: JAX ``logpdf``, NumPy ``sample``, support ``bounds``, a ``center`` inside it."""

    @abc.abstractmethod
    def logpdf(self, x):
        """Log-density at ``x`` (any shape; -inf outside the support), a JAX array."""

    @abc.abstractmethod
    def sample(self, rng: np.random.Generator, size=None):
        """Draws (a float when ``size`` is None)."""

    @property
    @abc.abstractmethod
    def bounds(self) -> tuple[float, float]:
        """The support ``(lo, hi)``."""

    @property
    @abc.abstractmethod
    def center(self) -> float:
        """A starting point inside the support."""

    @property
    @abc.abstractmethod
    def scale(self) -> float:
        """A typical spread of the prior (the unit a parameter is screened and stepped in)."""


class Uniform(Prior):
    """Uniform on ``[low, high]``."""

    low: float
    high: float

    def __check_init__(self):
        if not (math.isfinite(self.low) and math.isfinite(self.high) and self.low < self.high):
            raise ValueError(f"Uniform needs finite low < high, got {self.low}, {self.high}")

    @property
    def bounds(self) -> tuple[float, float]:
        return (self.low, self.high)

    @property
    def center(self) -> float:
        """The midpoint."""
        return 0.5 * (self.low + self.high)

    @property
    def scale(self) -> float:
        """The standard deviation, ``(high - low) / sqrt(12)``."""
        return (self.high - self.low) / math.sqrt(12.0)

    def logpdf(self, x):
        x = jnp.asarray(x, float)
        inside = (x >= self.low) & (x <= self.high)
        return jnp.where(inside, -math.log(self.high - self.low), -jnp.inf)

    def sample(self, rng: np.random.Generator, size=None):
        return rng.uniform(self.low, self.high, size=size)


class Normal(Prior):
    """Normal ``N(mean, sd)``, optionally truncated to ``[low, high]`` (renormalised)."""

    mean: float
    sd: float
    low: float = -math.inf
    high: float = math.inf

    def __check_init__(self):
        if not (self.sd > 0 and self.low < self.high):
            raise ValueError(f"Normal needs sd > 0 and low < high, got sd={self.sd}, [{self.low}, {self.high}]")

    @property
    def bounds(self) -> tuple[float, float]:
        return (self.low, self.high)

    @property
    def center(self) -> float:
        """The mean, clipped to the bounds."""
        return min(max(self.mean, self.low), self.high)

    @property
    def scale(self) -> float:
        """``sd`` (of the untruncated normal)."""
        return float(self.sd)

    def _log_mass(self) -> float:
        """log of the probability mass inside ``[low, high]`` (a Python float: a constant)."""
        cdf = lambda x: 0.5 * (1.0 + math.erf((x - self.mean) / (self.sd * math.sqrt(2.0))))  # noqa: E731
        return math.log(cdf(self.high) - cdf(self.low))

    def logpdf(self, x):
        x = jnp.asarray(x, float)
        z = (x - self.mean) / self.sd
        lp = -0.5 * z**2 - math.log(self.sd * math.sqrt(2.0 * math.pi)) - self._log_mass()
        return jnp.where((x >= self.low) & (x <= self.high), lp, -jnp.inf)

    def sample(self, rng: np.random.Generator, size=None):
        n = 1 if size is None else int(np.prod(size))
        out = np.empty(0)
        while out.size < n:  # rejection: fine for the mild truncations used here
            draw = rng.normal(self.mean, self.sd, size=2 * n + 8)
            out = np.concatenate([out, draw[(draw >= self.low) & (draw <= self.high)]])
        out = out[:n]
        return float(out[0]) if size is None else out.reshape(size)


class LogNormal(Prior):
    """``log x ~ N(log median, sigma)``, optionally truncated to ``[low, high]`` (x > 0)."""

    median: float
    sigma: float
    low: float = 0.0
    high: float = math.inf

    def __check_init__(self):
        if not (self.median > 0 and self.sigma > 0 and 0 <= self.low < self.high):
            raise ValueError("LogNormal needs median > 0, sigma > 0 and 0 <= low < high")

    @property
    def bounds(self) -> tuple[float, float]:
        return (self.low, self.high)

    @property
    def center(self) -> float:
        """The median, clipped to the bounds."""
        return min(max(self.median, self.low), self.high)

    @property
    def scale(self) -> float:
        """``sigma x median``: the spread of x near its median."""
        return float(self.sigma * self.median)

    def _log_normal(self) -> Normal:
        lo = math.log(self.low) if self.low > 0 else -math.inf
        hi = math.log(self.high) if math.isfinite(self.high) else math.inf
        return Normal(math.log(self.median), self.sigma, lo, hi)

    def logpdf(self, x):
        x = jnp.asarray(x, float)
        pos = x > 0
        lx = jnp.log(jnp.where(pos, x, 1.0))  # a safe log: x <= 0 is masked below
        return jnp.where(pos, self._log_normal().logpdf(lx) - lx, -jnp.inf)

    def sample(self, rng: np.random.Generator, size=None):
        return np.exp(self._log_normal().sample(rng, size))
