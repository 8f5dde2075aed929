"""Membrane designs, their validation, the public key format and the design space.

A membrane is a flat Ecoflex disc of outer radius ``R_out = 70 mm`` and thickness ``t``,
clamped at ``R_out``, with a rigid central contact disk of radius ``c`` and 0-2 stiff
fabric rings. A ring is the annulus ``[r - w, r + w]``: ``r`` the radius of its centre
line, ``w`` its half-width (outer - inner = 2 w). All lengths in millimetres.

The public key format (that of the authors' data files) is
``"[t, c, r1, w1, r2, w2]"`` with ``nan`` for an absent ring.
"""

from __future__ import annotations

import math
from typing import Sequence

import equinox as eqx
import jax.numpy as jnp
import numpy as np

from mfdesign.errors import InputError

OUTER_RADIUS_MM = 70.0
MIN_GAP_MM = 3.0  # fabric needs this much rubber between itself and the disk/clamp/other ring
MAX_RINGS = 2
_TOL = 1e-9


class DesignError(InputError):
    """A membrane design that cannot be built; the message names the field and the rule."""


def _check_number(name: str, value: float) -> float:
    try:
        value = float(value)
    except (TypeError, ValueError):
        raise DesignError(f"{name} must be a number in mm, got {value!r}") from None
    if not math.isfinite(value):
        raise DesignError(f"{name} must be finite, got {value}")
    if value <= 0.0:
        raise DesignError(f"{name} must be positive (mm), got {value}")
    return value


class Ring(eqx.Module):
    """A stiff fabric ring: the annulus ``[radius_mm - half_width_mm, radius_mm + half_width_mm]``.

    **Arguments:**

    - `radius_mm`: radius of the ring's centre line [mm].
    - `half_width_mm`: half the ring's radial width [mm].

    Raises :class:`DesignError` on a non-finite or non-positive number.
    """

    radius_mm: float
    half_width_mm: float

    def __init__(self, radius_mm: float, half_width_mm: float):
        self.radius_mm = _check_number("ring radius", radius_mm)
        self.half_width_mm = _check_number("ring half-width", half_width_mm)

    @property
    def inner_mm(self) -> float:
        return self.radius_mm - self.half_width_mm

    @property
    def outer_mm(self) -> float:
        return self.radius_mm + self.half_width_mm


class Membrane(eqx.Module):
    """An axisymmetric membrane design (all lengths in mm).

    Rings are stored sorted by radius, so a design with its rings swapped is the same
    design (equal and with the same hash).

    **Arguments:**

    - `thickness_mm`: membrane thickness t [mm] (the paper's range 1-3 mm).
    - `contact_radius_mm`: radius c of the rigid contact disk [mm].
    - `rings`: up to two fabric rings, :class:`Ring` or `(radius_mm, half_width_mm)`.
    - `outer_radius_mm`: clamped outer radius [mm] (70 mm on the rig).

    ``Membrane.from_key("[t, c, r1, w1, r2, w2]")`` builds one from the public key (mm,
    `nan` for an absent ring) and ``key()`` writes it. Raises :class:`DesignError` on a
    design that does not fit (overlapping rings, a ring outside the clamp, ...).
    """

    thickness_mm: float
    contact_radius_mm: float
    rings: tuple[Ring, ...]
    outer_radius_mm: float = OUTER_RADIUS_MM

    def __init__(
        self,
        thickness_mm: float,
        contact_radius_mm: float,
        rings: Sequence[Ring | tuple[float, float]] = (),
        outer_radius_mm: float = OUTER_RADIUS_MM,
    ):
        self.thickness_mm = _check_number("thickness", thickness_mm)
        self.contact_radius_mm = _check_number("contact radius", contact_radius_mm)
        self.outer_radius_mm = _check_number("outer radius", outer_radius_mm)
        rings = [r if isinstance(r, Ring) else Ring(*r) for r in rings]
        if len(rings) > MAX_RINGS:
            raise DesignError(f"a membrane has at most {MAX_RINGS} rings, got {len(rings)}")
        self.rings = tuple(sorted(rings, key=lambda r: (r.radius_mm, r.half_width_mm)))
        self._validate()

    def _validate(self) -> None:
        c, out = self.contact_radius_mm, self.outer_radius_mm
        if c >= out:
            raise DesignError(f"contact radius {c} mm must be smaller than the outer radius {out} mm")
        edges = [("the contact disk", c)]
        for k, ring in enumerate(self.rings, start=1):
            lo_name, lo = edges[-1]
            if ring.inner_mm < lo + MIN_GAP_MM - _TOL:
                raise DesignError(
                    f"ring {k} (radius {ring.radius_mm}, half-width {ring.half_width_mm} mm) "
                    f"starts at {ring.inner_mm:g} mm, overlapping {lo_name} (ends at {lo:g} mm): "
                    f"allowed inner edge >= {lo + MIN_GAP_MM:g} mm ({MIN_GAP_MM:g} mm spacing)"
                )
            edges.append((f"ring {k}", ring.outer_mm))
        last_name, last = edges[-1]
        if self.rings and last > out - MIN_GAP_MM + _TOL:
            raise DesignError(
                f"{last_name} ends at {last:g} mm, overlapping the clamp at {out:g} mm: "
                f"allowed outer edge <= {out - MIN_GAP_MM:g} mm ({MIN_GAP_MM:g} mm spacing)"
            )

    # -- conversions ------------------------------------------------------------------
    @property
    def n_rings(self) -> int:
        return len(self.rings)

    def to_array(self) -> np.ndarray:
        """``[t, c, r1, w1, r2, w2]`` in mm, NaN for absent rings (the key's numbers)."""
        out = [self.thickness_mm, self.contact_radius_mm]
        for k in range(MAX_RINGS):
            if k < len(self.rings):
                out += [self.rings[k].radius_mm, self.rings[k].half_width_mm]
            else:
                out += [math.nan, math.nan]
        return np.asarray(out, dtype=np.float64)

    @classmethod
    def from_array(cls, values: Sequence[float]) -> "Membrane":
        """Inverse of :meth:`to_array`; NaN pairs mean "no ring"."""
        values = list(values)
        if len(values) != 2 + 2 * MAX_RINGS:
            raise DesignError(f"a design has {2 + 2 * MAX_RINGS} numbers [t, c, r1, w1, r2, w2], got {len(values)}")
        try:
            values = [float(v) for v in values]
        except (TypeError, ValueError):
            raise DesignError(f"design numbers must be numbers, got {values!r}") from None
        rings = []
        for k in range(MAX_RINGS):
            r, w = values[2 + 2 * k], values[3 + 2 * k]
            if math.isnan(r) and math.isnan(w):
                continue
            if math.isnan(w):
                raise DesignError(f"ring {k + 1} has a radius ({r} mm) but no half-width")
            if math.isnan(r):
                raise DesignError(f"ring {k + 1} has a half-width ({w} mm) but no radius")
            rings.append(Ring(r, w))
        return cls(values[0], values[1], rings)

    def key(self) -> str:
        """The public key ``"[t, c, r1, w1, r2, w2]"`` (as in the authors' data files)."""
        return "[" + ", ".join(repr(float(v)) for v in self.to_array()) + "]"

    @classmethod
    def from_key(cls, key: str) -> "Membrane":
        """Parse ``"[t, c, r1, w1, r2, w2]"`` (``nan`` for an absent ring)."""
        if not isinstance(key, str):
            raise DesignError(f"a design key is a string, got {type(key).__name__}")
        text = key.strip()
        if not (text.startswith("[") and text.endswith("]")):
            raise DesignError(f'a design key looks like "[2.0, 25.4, nan, nan, nan, nan]", got {key!r}')
        parts = [p.strip() for p in text[1:-1].split(",")]
        try:
            values = [float(p) for p in parts]
        except ValueError:
            raise DesignError(f"design key {key!r} holds something that is not a number") from None
        return cls.from_array(values)

    def __str__(self) -> str:
        return self.key()


# Where the ``2 + 2 n`` unit-cube coordinates of an n-ring design sit in the 6-d cube of
# :meth:`DesignSpace.decode_any`: (t, c, w1, w2, f1, f2).
_CUBE_SLOTS = {0: [0, 1], 1: [0, 1, 2, 4], 2: [0, 1, 2, 3, 4, 5]}


class DesignSpace(eqx.Module):
    """Bounds of the designs an optimiser may propose, and a decoding from the unit cube.

    The paper's bounds: thickness 1-3 mm, contact radius 25.4-38.1 mm, ring half-width
    >= 5 mm; every gap (disk-ring, ring-ring, ring-clamp) >= 3 mm. A point of the unit
    cube ``[0, 1]^(2 + 2 n_rings)`` decodes to ``(t, c, w_1.., slack fractions..)``:
    widths first (each between ``half_width_min`` and what still fits), then the free
    radial slack is shared among the ``n_rings + 1`` gaps. Every point of the cube gives
    a valid design, and the map is piecewise linear in ``u``.

    **Arguments:**

    - `thickness_mm`: `(low, high)` thickness bounds [mm].
    - `contact_radius_mm`: `(low, high)` contact-disk radius bounds [mm].
    - `half_width_mm`: `(low, high)` ring half-width bounds [mm].
    - `outer_radius_mm`: clamped outer radius [mm].
    - `gap_mm`: the least gap between disk, rings and clamp [mm].
    """

    thickness_mm: tuple[float, float] = (1.0, 3.0)
    contact_radius_mm: tuple[float, float] = (25.4, 38.1)
    half_width_mm: tuple[float, float] = (5.0, 13.0)
    outer_radius_mm: float = OUTER_RADIUS_MM
    gap_mm: float = MIN_GAP_MM

    def __check_init__(self):
        for name in ("thickness_mm", "contact_radius_mm", "half_width_mm"):
            lo, hi = getattr(self, name)
            if not (math.isfinite(lo) and math.isfinite(hi) and 0 < lo <= hi):
                raise DesignError(f"DesignSpace.{name} must be 0 < low <= high, got {(lo, hi)}")
        # Two rings of minimum width must fit beside the largest disk.
        need = self.contact_radius_mm[1] + 3 * self.gap_mm + 4 * self.half_width_mm[0]
        if need > self.outer_radius_mm:
            raise DesignError(
                f"two rings of half-width {self.half_width_mm[0]} mm do not fit beside a "
                f"{self.contact_radius_mm[1]} mm disk inside {self.outer_radius_mm} mm"
            )

    def dim(self, n_rings: int) -> int:
        if n_rings not in (0, 1, 2):
            raise DesignError(f"n_rings must be 0, 1 or 2, got {n_rings}")
        return 2 + 2 * n_rings

    def decode_unit(self, u, n_rings: int):
        """Unit-cube points ``[..., 2 + 2 n_rings]`` -> design arrays ``[..., 6]`` mm (JAX).

        ``u`` is clipped to the cube. ``t`` and ``c`` are linear in ``u[0]``, ``u[1]``; then
        the ring half-widths, each between ``half_width_min`` and what the earlier rings
        left over; then the radial slack ``span - 2 sum(w)`` (``span`` = room between the
        disk and the clamp less the ``n_rings + 1`` gaps) is shared among the gaps by the
        fractions ``u[2 + n_rings + k]``. Piecewise linear, so differentiable almost
        everywhere: optimisers follow it (jit/vmap/grad). NaN fills the absent ring slots.
        """
        u = jnp.asarray(u, dtype=jnp.float64)
        if u.shape[-1] != self.dim(n_rings):
            raise DesignError(f"expected {self.dim(n_rings)} unit-cube coordinates, got {u.shape[-1]}")
        # One implementation: place the coordinates where decode_any reads them.
        u6 = jnp.zeros(u.shape[:-1] + (6,)).at[..., _CUBE_SLOTS[n_rings]].set(u)
        return self.decode_any(u6, n_rings)

    def decode_any(self, u6, n_rings):
        """:meth:`decode_unit` with the ring count as data (traceable, vmappable over it).

        ``u6`` ``[..., 6]`` = ``(t, c, w1, w2, f1, f2)``; ``n_rings`` 0, 1 or 2 (an array
        broadcasting with ``u6[..., 0]``). Equals ``decode_unit(cube_of(u6, n), n)``: the
        coordinates a design with ``n`` rings does not have are ignored. One compiled
        search then serves every ring count.
        """
        u = jnp.clip(jnp.asarray(u6, dtype=jnp.float64), 0.0, 1.0)
        if u.shape[-1] != 6:
            raise DesignError(f"decode_any expects 6 unit-cube coordinates, got {u.shape[-1]}")
        n = jnp.asarray(n_rings)
        (t_lo, t_hi), (c_lo, c_hi), (w_lo, w_hi) = self.thickness_mm, self.contact_radius_mm, self.half_width_mm
        t = t_lo + (t_hi - t_lo) * u[..., 0]
        c = c_lo + (c_hi - c_lo) * u[..., 1]
        gap, R = self.gap_mm, self.outer_radius_mm
        span = R - c - (n + 1) * gap
        room = span - 2 * n * w_lo
        has = [n >= 1, n >= 2]
        widths = []
        for k in range(2):
            w = jnp.where(has[k], w_lo + u[..., 2 + k] * jnp.minimum(w_hi - w_lo, room / 2.0), 0.0)
            room = room - 2.0 * jnp.where(has[k], w - w_lo, 0.0)
            widths.append(w)
        left = span - 2.0 * (widths[0] + widths[1])
        edge = c + gap
        cols = [t, c]
        for k in range(2):
            take = jnp.where(has[k], left * u[..., 4 + k], 0.0)
            left = left - take
            inner = edge + take
            nan = jnp.full_like(t, jnp.nan)
            cols += [jnp.where(has[k], inner + widths[k], nan), jnp.where(has[k], widths[k], nan)]
            edge = inner + 2 * widths[k] + gap
        return jnp.stack(cols, axis=-1)

    @staticmethod
    def cube_of(u6, n_rings: int):
        """The ``2 + 2 n_rings`` coordinates of a 6-d point that :meth:`decode_unit` reads."""
        return np.asarray(u6, float)[..., _CUBE_SLOTS[int(n_rings)]]

    def encode(self, design: Membrane) -> np.ndarray:
        """Inverse of :meth:`decode_unit`: the ``2 + 2 n_rings`` unit-cube coordinates of
        ``design`` (NumPy). A design outside the bounds gets coordinates outside ``[0, 1]``;
        a coordinate whose range is empty (a fixed feature, ``low == high``) is 0."""

        def frac(x, lo, width):
            return (x - lo) / width if width > _TOL else 0.0

        n = design.n_rings
        (t_lo, t_hi), (c_lo, c_hi), (w_lo, w_hi) = self.thickness_mm, self.contact_radius_mm, self.half_width_mm
        c = design.contact_radius_mm
        u6 = np.zeros(6)
        u6[0] = frac(design.thickness_mm, t_lo, t_hi - t_lo)
        u6[1] = frac(c, c_lo, c_hi - c_lo)
        # The same walk as decode_any: widths against the room left, then the slack shares.
        span = self.outer_radius_mm - c - (n + 1) * self.gap_mm
        room = span - 2 * n * w_lo
        for k, ring in enumerate(design.rings):
            u6[2 + k] = frac(ring.half_width_mm, w_lo, min(w_hi - w_lo, room / 2.0))
            room -= 2.0 * (ring.half_width_mm - w_lo)
        left = span - 2.0 * sum(r.half_width_mm for r in design.rings)
        edge = c + self.gap_mm
        for k, ring in enumerate(design.rings):
            take = ring.inner_mm - edge
            u6[4 + k] = frac(take, 0.0, left)
            left -= take
            edge = ring.outer_mm + self.gap_mm
        return self.cube_of(u6, n)

    def decode_array(self, u, n_rings: int) -> np.ndarray:
        """:meth:`decode_unit` as a NumPy array (batches of unit-cube points)."""
        return np.asarray(self.decode_unit(u, n_rings))

    def decode(self, u, n_rings: int) -> Membrane:
        """One unit-cube point -> a valid :class:`Membrane`."""
        arr = self.decode_array(np.asarray(u, dtype=np.float64), n_rings)
        if arr.ndim != 1:
            raise DesignError("decode takes one point; use decode_array for batches")
        return Membrane.from_array(arr)

    def contains(self, design: Membrane) -> bool:
        """Whether a design lies inside the bounds (validity is checked by Membrane itself)."""
        ok = self.thickness_mm[0] - _TOL <= design.thickness_mm <= self.thickness_mm[1] + _TOL
        ok &= self.contact_radius_mm[0] - _TOL <= design.contact_radius_mm <= self.contact_radius_mm[1] + _TOL
        for ring in design.rings:
            ok &= self.half_width_mm[0] - _TOL <= ring.half_width_mm <= self.half_width_mm[1] + _TOL
        return bool(ok)

    def describe(self) -> str:
        """The bounds in words (for error messages)."""
        (t0, t1), (c0, c1), (w0, w1) = self.thickness_mm, self.contact_radius_mm, self.half_width_mm
        return (
            f"thickness {t0:g}-{t1:g} mm, contact radius {c0:g}-{c1:g} mm, ring half-width {w0:g}-{w1:g} mm, "
            f"0-{MAX_RINGS} rings with gaps >= {self.gap_mm:g} mm inside {self.outer_radius_mm:g} mm"
        )

    def check(self, design: Membrane, what: str = "design") -> Membrane:
        """``design`` if it lies in this space, else :class:`DesignError` naming the
        offending numbers and the allowed ranges."""
        if self.contains(design):
            return design
        bad = []
        if not self.thickness_mm[0] - _TOL <= design.thickness_mm <= self.thickness_mm[1] + _TOL:
            bad.append(f"thickness {design.thickness_mm:g} mm")
        if not self.contact_radius_mm[0] - _TOL <= design.contact_radius_mm <= self.contact_radius_mm[1] + _TOL:
            bad.append(f"contact radius {design.contact_radius_mm:g} mm")
        for k, ring in enumerate(design.rings, start=1):
            if not self.half_width_mm[0] - _TOL <= ring.half_width_mm <= self.half_width_mm[1] + _TOL:
                bad.append(f"ring {k} half-width {ring.half_width_mm:g} mm")
        raise DesignError(
            f"{what} {design.key()}: {', '.join(bad)} outside the design space; allowed: {self.describe()}"
        )

    def sample(self, rng: np.random.Generator, n: int, n_rings: int) -> list[Membrane]:
        """``n`` designs drawn uniformly in the unit cube (seeded by ``rng``)."""
        return [self.decode(u, n_rings) for u in rng.uniform(size=(n, self.dim(n_rings)))]


# The product's membranes (the paper's bounds), and the wider range that
# ``--allow-outside-design-space`` opens for research: still physical (a membrane thinner
# than 0.2 mm tears, one thicker than 10 mm is a plate, not a membrane).
PRODUCT_SPACE = DesignSpace()
RESEARCH_SPACE = DesignSpace(thickness_mm=(0.2, 10.0), contact_radius_mm=(5.0, 55.0), half_width_mm=(1.0, 30.0))
WIDEN_OPTION = "--allow-outside-design-space"


def check_design_space(design: Membrane, allow_outside: bool = False, what: str = "design") -> bool:
    """Refuse a design outside the product's space (or, with ``allow_outside``, outside
    :data:`RESEARCH_SPACE`); return whether it lies outside the product's space."""
    if PRODUCT_SPACE.contains(design):
        return False
    if not allow_outside:
        try:
            PRODUCT_SPACE.check(design, what)
        except DesignError as err:
            raise DesignError(f"{err} ({WIDEN_OPTION} widens this to {RESEARCH_SPACE.describe()})") from None
    RESEARCH_SPACE.check(design, what)
    return True


# Scales of the geometry features: the product space's extents (thickness 1-3 mm, disk
# 25.4-38.1 mm, a ring's centre anywhere from the disk to the clamp, half-width 5-13 mm),
# so that one unit is "the whole range" of each feature.
_FEATURE_SCALE_MM = (2.0, 12.7, 44.6, 8.0)


def membrane_features(design):
    """Geometry features [..., 8] of design arrays [..., 6] (mm, NaN = no ring; JAX,
    traceable): thickness and disk radius over their product ranges, then per ring slot its
    presence (0 or 1) and, when present, its centre radius and half-width over their
    ranges. The Euclidean distance between two membranes' features is how far apart the
    lab would call them: 1 is a ring more or less, or a feature moved over its whole range.
    """
    d = jnp.asarray(design, dtype=jnp.float64)
    st, sc, sr, sw = _FEATURE_SCALE_MM
    cols = [d[..., 0] / st, d[..., 1] / sc]
    for k in range(MAX_RINGS):
        r, w = d[..., 2 + 2 * k], d[..., 3 + 2 * k]
        present = ~(jnp.isnan(r) | jnp.isnan(w))
        cols += [
            present.astype(d.dtype),
            jnp.where(present, r, 0.0) / sr,
            jnp.where(present, w, 0.0) / sw,
        ]
    return jnp.stack(cols, axis=-1)
