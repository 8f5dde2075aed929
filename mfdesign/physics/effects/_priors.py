"""Priors of effect parameters: ``logpdf`` (NumPy, for reports and the virtual rig),
``logpdf_jax`` (inside a jitted log-posterior), ``sample`` and the support ``bounds``."""

from __future__ import annotations

import math
from dataclasses import dataclass

import jax.numpy as jnp
import numpy as np

__all__ = ["LogNormal", "Normal", "Uniform"]


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

    @property
    def center(self) -> float:
        """A starting point inside the support: the midpoint."""
        return 0.5 * (self.low + self.high)

    def logpdf(self, x):
        x = np.asarray(x, float)
        inside = (x >= self.low) & (x <= self.high)
        return np.where(inside, -math.log(self.high - self.low), -np.inf)

    def sample(self, rng: np.random.Generator, size=None):
        return rng.uniform(self.low, self.high, size=size)

    def logpdf_jax(self, x):
        """JAX log-density (same maths as :meth:`logpdf`), for jitted log-posteriors."""
        inside = (x >= self.low) & (x <= self.high)
        return jnp.where(inside, -math.log(self.high - self.low), -jnp.inf)


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

    @property
    def center(self) -> float:
        """A starting point inside the support: the mean, clipped to the bounds."""
        return min(max(self.mean, self.low), self.high)

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
        return jnp.where((x >= self.low) & (x <= self.high), lp, -jnp.inf)


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

    @property
    def center(self) -> float:
        """A starting point inside the support: the median, clipped to the bounds."""
        return min(max(self.median, self.low), self.high)

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
        lx = jnp.log(jnp.where(pos, x, 1.0))
        lp = self._log_normal().logpdf_jax(lx) - lx
        return jnp.where(pos, lp, -jnp.inf)
