"""Shooting for the membrane boundary-value problem (the engine behind :mod:`solve`).

Unknowns at the disk edge ``r0`` (where ``lambda2 = 1``, ``R = r0``, ``Z = h``):
``x = (a, phi0)`` with ``lambda1(r0) = 1 + exp(a)`` (the meridian is in tension at the
disk, so the parametrisation keeps iterates physical). Conditions at the clamp ``r_out``:
``lambda2 = s`` (clamp pre-stretch, 1 without) and ``Z = 0``. The ODE of :mod:`membrane`
is integrated with diffrax (Tsit5, PID step control, forward-mode autodiff) segment by
segment in one ``lax.scan``; at each ring edge ``lambda1`` jumps so that the meridional
force ``Q = r t W1`` is continuous (:func:`membrane.jump_lambda1`). Newton's method
from optimistix drives the two residuals to zero. The plate force then follows from the disk's
vertical balance, ``F = p pi r0^2 + 2 pi r0 t W1(lambda1(r0), 1) sin(phi0)``.

A "string" model gives the first guess: a strip of the annulus in plane strain under
constant tension is a circular arc of curvature ``p / T`` through the disk edge and the
clamp; its stretch solves ``arc length = lambda L`` (first sign change on a grid).
"""

from __future__ import annotations

import functools
from typing import Callable

import diffrax as dfx
import equinox as eqx
import jax
import jax.numpy as jnp
import numpy as np
import optimistix as optx

from mfdesign.design import MAX_RINGS, OUTER_RADIUS_MM, Membrane
from mfdesign.physics.membrane import Segment, jump_lambda1, rhs
from mfdesign.physics.params import SimParams
from mfdesign.units import PA_TO_MPA

# The integration's tolerances: at 1e-7 / 1e-8 a simulator plane solves 1.4-1.5x faster than
# at 1e-8 / 1e-9 (2.3-3.0 s -> 1.6-2.1 s a plane on one core; issue 40) and its forces move by
# at most 3.2e-5 N (experiments/bench_ode_tol.py measures both, JSON in experiments/out), a hundredth
# of the planes' interpolation error (~3e-3 N RMS) and far below any rig's noise. The
# convergence test |r| < 1e-7 (solve_force) is on the integrated map itself, which is
# deterministic, so it holds as before (no plane node changed its converged state).
RTOL_ODE = 1e-7
ATOL_ODE = 1e-8
# Termination: successive iterates and residuals agree to ~1e-8. Tighter (1e-10 / 1e-11)
# sits at the noise floor of the rtol-1e-9 integration, where the trust region keeps
# rejecting steps at an already converged point; convergence proper is the |r| < 1e-7
# check in solve_force, and near the root the last step is quadratically small.
SHOOTING_SOLVER = optx.LevenbergMarquardt(rtol=1e-8, atol=1e-9)
SHOOTING_MAX_STEPS = 25
MAX_ODE_STEPS = 1024
FAILED_RESIDUAL = 1e3


class Geometry(eqx.Module):
    """A design as arrays (mm) for jit/vmap, always with ``MAX_RINGS`` ring slots.

    ``ring_edges_mm`` = [in1, out1, in2, out2]; a slot without a ring has both edges at the
    clamp and ``ring_used`` False. Every design thus has the same array shapes, so each
    kernel compiles once for all ring counts (a compilation per ring count tripled a cold
    start), and an unused slot adds two zero-width segments that the integration passes
    through unchanged (diffrax takes no step on ``t0 == t1``, and the interface jump is
    skipped).
    """

    thickness_mm: jax.Array
    contact_mm: jax.Array
    outer_mm: jax.Array
    ring_edges_mm: jax.Array
    ring_used: jax.Array


def geometry_of(design: Membrane) -> Geometry:
    edges = [e for ring in design.rings for e in (ring.inner_mm, ring.outer_mm)]
    edges += [design.outer_radius_mm] * (2 * MAX_RINGS - len(edges))
    return Geometry(
        thickness_mm=jnp.asarray(design.thickness_mm, float),
        contact_mm=jnp.asarray(design.contact_radius_mm, float),
        outer_mm=jnp.asarray(design.outer_radius_mm, float),
        ring_edges_mm=jnp.asarray(edges, float),
        ring_used=jnp.arange(MAX_RINGS) < design.n_rings,
    )


def geometry_of_array(design, outer_radius_mm: float = OUTER_RADIUS_MM) -> Geometry:
    """:func:`geometry_of` of a design row ``[t, c, r1, w1, r2, w2]`` mm (NaN pairs: no
    ring), traceable: a search differentiates the simulator through it (forward mode).
    The NaN of an absent ring is replaced before any arithmetic, so that no NaN reaches a
    tangent through the unselected branch of a ``where``."""
    d = jnp.asarray(design, float)
    r, w = d[2::2], d[3::2]
    used = jnp.isfinite(r) & jnp.isfinite(w)
    r, w = jnp.where(used, r, 0.0), jnp.where(used, w, 0.0)
    R = jnp.asarray(outer_radius_mm, float)
    edges = jnp.stack([jnp.where(used, r - w, R), jnp.where(used, r + w, R)], axis=-1).reshape(-1)
    return Geometry(thickness_mm=d[0], contact_mm=d[1], outer_mm=R, ring_edges_mm=edges, ring_used=used)


class Segments(eqx.Module):
    """The material segments from the disk to the clamp, stacked: ``seg[k]`` lives on
    ``[bounds[k], bounds[k + 1]]``; even ``k`` rubber, odd ``k`` fabric."""

    seg: Segment  # fields with a leading axis of length n_segments
    bounds: jax.Array
    real: jax.Array  # False for the zero-width segments of an unused ring slot

    @property
    def r0(self):
        return self.bounds[0]

    @property
    def r_out(self):
        return self.bounds[-1]

    def first(self) -> Segment:
        return jax.tree.map(lambda a: a[0], self.seg)


def segments(geom: Geometry, params: SimParams) -> Segments:
    inset = params.fabric_inset_mm
    r0 = geom.contact_mm + params.contact_offset_mm - inset
    r_out = geom.outer_mm
    # a used ring's inner edge moves out and its outer edge in (unused slots sit at the clamp)
    inward = jnp.tile(jnp.array([1.0, -1.0]), geom.ring_edges_mm.shape[0] // 2)
    edges = geom.ring_edges_mm + inset * inward * jnp.repeat(geom.ring_used, 2)
    bounds = jnp.concatenate([jnp.stack([r0]), edges, jnp.stack([r_out])])
    n = bounds.shape[0] - 1
    real = jnp.concatenate([jnp.array([True]), jnp.repeat(geom.ring_used, 2)])
    # An unused slot is rubber: its (repeated) profile points then carry the last real
    # segment's stresses, harmless to the checks' minima and maxima.
    is_fabric = ((jnp.arange(n) % 2) == 1) & real
    ones = jnp.ones(n)
    seg = Segment(
        mu_mpa=jnp.where(is_fabric, params.ring_mu_pa, params.mu_pa) * PA_TO_MPA,
        jm=jnp.where(is_fabric, params.ring_jm, params.jm) * ones,
        i2_share=jnp.where(is_fabric, 0.0, params.i2_share) * ones,  # a rubber property
        t_mm=geom.thickness_mm * params.thickness_factor * ones,
        gradient=params.thickness_gradient * ones,
        r_mid=0.5 * (r0 + r_out) * ones,
        span=(r_out - r0) * ones,
    )
    return Segments(seg=seg, bounds=bounds, real=real)


def _nonphysical(t, y, args, **kwargs):
    """Stop integrating once the state has left the physical region (a diffrax event):
    a state past the Gent limit has no energy, and integrating on would only shrink the
    step until ``max_steps``, holding up every point of a vmapped batch."""
    seg, _ = args
    l1, l2 = y[0], y[1]
    locking = seg.locking(l1, l2)
    bad = (locking > 0.9995) | (l1 < 0.2) | (l2 < 0.05) | (l2 > 20.0)
    return bad | ~jnp.all(jnp.isfinite(y))


_EVENT = dfx.Event(_nonphysical)


def integrate(segs: Segments, p_mpa, y0, save_per_segment: int = 0):
    """Integrate ``(lambda1, lambda2, phi, Z)`` from the disk to the clamp.

    One ``lax.scan`` over the segments, so the traced program does not grow with the
    number of rings. Returns ``(y_end, ok, profile)``, ``profile`` = ``(r, y)`` sampled at
    ``save_per_segment`` points per segment (``None`` when 0).
    """
    n = segs.bounds.shape[0] - 1
    prev = jax.tree.map(lambda a: jnp.concatenate([a[:1], a[:-1]]), segs.seg)
    xs = (segs.seg, prev, segs.bounds[:-1], segs.bounds[1:], segs.real)

    def step(carry, x):
        y, ok = carry
        seg, seg_prev, a, b, real = x
        # Segment 0 "jumps" from itself: the identity, solved exactly. An unused ring
        # slot has no interface: no jump.
        l1, ok_jump = jump_lambda1(seg_prev, seg, a, y[0], y[1], valid=ok)
        y = y.at[0].set(jnp.where(real, l1, y[0]))
        ok_jump = ok_jump | ~real
        if save_per_segment:
            ts = a + (b - a) * jnp.linspace(0.0, 1.0, save_per_segment)
            saveat = dfx.SaveAt(ts=ts)
        else:
            ts = None
            saveat = dfx.SaveAt(t1=True)
        sol = dfx.diffeqsolve(
            dfx.ODETerm(rhs),
            dfx.Tsit5(),
            t0=a,
            t1=b,
            dt0=(b - a) / 16.0,
            y0=y,
            args=(seg, p_mpa),
            saveat=saveat,
            stepsize_controller=dfx.PIDController(rtol=RTOL_ODE, atol=ATOL_ODE),
            adjoint=dfx.ForwardMode(),
            event=_EVENT,
            max_steps=MAX_ODE_STEPS,
            throw=False,
        )
        ok = ok & ok_jump & (sol.result == dfx.RESULTS.successful)
        out = (ts, sol.ys) if save_per_segment else None
        return (sol.ys[-1], ok), out

    (y, ok), out = jax.lax.scan(step, (y0, jnp.asarray(True)), xs, length=n)
    prof = (out[0].reshape(-1), out[1].reshape(-1, 4)) if save_per_segment else None
    return y, ok & jnp.all(jnp.isfinite(y)), prof


def disk_force(segs, p_mpa, l1_0, phi0):
    # Q at the disk edge (lambda2 = 1) times the meridian's vertical direction.
    """Force on the plate [N] from the disk's vertical balance (unknowns -> force)."""
    seg, r0 = segs.first(), segs.r0
    t0, _ = seg.thickness(r0)
    return p_mpa * jnp.pi * r0**2 + 2.0 * jnp.pi * r0 * t0 * seg.w1(l1_0, 1.0) * jnp.sin(phi0)


def start_state(x, h):
    """State ``(lambda1, lambda2, phi, Z)`` at the disk edge from the unknowns ``x``."""
    return jnp.stack([1.0 + jnp.exp(x[0]), jnp.ones_like(h), x[1], h])


def force_residual(x, args):
    """Shooting residual at fixed height: ``(lambda2(r_out) - s, Z(r_out) / L)``.

    ``args = (geom, params, h, p_mpa, active)``: an inactive point (a lane of a vmapped
    batch with nothing left to solve) has residual 0, so the solver stops at once instead
    of iterating in lockstep with the rest of the batch."""
    geom, params, h, p_mpa, active = args
    segs = segments(geom, params)
    y, ok, _ = integrate(segs, p_mpa, start_state(x, h))
    span = segs.r_out - segs.r0
    res = jnp.stack([y[1] - params.clamp_prestretch, y[3] / span])
    # Outside the physical region the residual is large but finite: the trust region
    # rejects such a step (a NaN would reach, and abort, the linear solves).
    res = jnp.where(ok & jnp.all(jnp.isfinite(res)), res, FAILED_RESIDUAL)
    return jnp.where(active, res, 0.0)


def residual_and_jacobian(x, args, residual=force_residual):
    """``(r(x), dr/dx)`` from one forward-mode integration: the primal state and the
    tangent columns ride in the same ODE loop (``jacfwd`` batches only the tangents)."""
    jac, res = jax.jacfwd(lambda xx: (residual(xx, args),) * 2, has_aux=True)(x)
    return res, jac


def with_materialised_jacobian(residual: Callable) -> Callable:
    """``residual(x, args)`` with a JVP rule that materialises its Jacobian once.

    The solvers linearise the residual and then apply the linear map several times per
    iteration (materialising it for the least-squares solve, predicting the trust
    region's reduction). The plain linearisation of an ODE ``while_loop`` re-runs the
    whole integration at every application, so each application is a full integration,
    and each is traced and compiled again (the fixed-force height solve compiled ~27 s
    that way against ~10 s for a whole path of force solves on 2 cores, issue 40). Here
    the tangent map is ``J dx`` with ``J`` computed once, in the same pass as the
    residual (and transposable, unlike the loop). Tangents of ``args`` (implicit
    differentiation with respect to the design or the parameters) get their own JVP.
    ``x`` may be a scalar or a vector.
    """

    @jax.custom_jvp
    def wrapped(x, args):
        return residual(x, args)

    @functools.partial(wrapped.defjvp, symbolic_zeros=True)
    def _jvp(primals, tangents):
        x, args = primals
        dx, dargs = tangents
        res, jac = residual_and_jacobian(x, args, residual)
        out = jnp.zeros_like(res) if _is_zero(dx) else jnp.tensordot(jac, dx, axes=jnp.ndim(dx))
        if not all(_is_zero(t) for t in jax.tree.leaves(dargs, is_leaf=_is_zero)):
            dargs = jax.tree.map(lambda t, a: _zero_tangent(a) if _is_zero(t) else t, dargs, args, is_leaf=_is_zero)
            out = out + jax.jvp(lambda a: residual(x, a), (args,), (dargs,))[1]
        return res, out

    return wrapped


# The force shooting's residual as the solvers see it (with_materialised_jacobian).
shooting_residual = with_materialised_jacobian(force_residual)


def _is_zero(t):
    return isinstance(t, jax.custom_derivatives.SymbolicZero)


def _zero_tangent(a):
    """A zero tangent for ``a``: float0 for a bool or integer leaf (e.g. ``ring_used``)."""
    if jnp.issubdtype(jnp.result_type(a), jnp.inexact):
        return jnp.zeros_like(a)
    return np.zeros(jnp.shape(a), dtype=jax.dtypes.float0)


def solve_force(x0, geom: Geometry, params: SimParams, h_mm, p_mpa, active=True):
    """Shooting solve from ``x0``. Returns ``(x, converged, det_jacobian)``.

    ``active = False`` skips the point (``x0`` back, not converged) at the cost of one
    residual evaluation: under ``vmap`` every lane runs as many iterations as the slowest.
    Converged means the solver's own test passed and ``|r(x)| < 1e-7``. The residual and
    Jacobian at the returned ``x`` (the last accepted iterate) are the ones the solver
    already computed there (``sol.state.f_info``): re-evaluating them would cost another
    integration per continuation step.
    """
    args = (geom, params, h_mm, p_mpa, jnp.asarray(active))
    sol = optx.least_squares(shooting_residual, SHOOTING_SOLVER, x0, args, max_steps=SHOOTING_MAX_STEPS, throw=False)
    x = sol.value
    res = sol.state.f_info.residual
    jac = sol.state.f_info.jac.as_matrix()
    converged = (
        jnp.asarray(active)
        & (sol.result == optx.RESULTS.successful)
        & jnp.all(jnp.isfinite(x))
        & jnp.all(jnp.abs(res) < 1e-7)
    )
    return x, converged, jnp.linalg.det(jac)


def string_guess(geom: Geometry, params: SimParams, h_mm, p_mpa):
    """First guess ``x = (a, phi0)`` from the circular-arc strip model (see module doc)."""
    segs = segments(geom, params)
    rubber, r0 = segs.first(), segs.r0
    lengths = jnp.diff(segs.bounds)
    L_rubber = jnp.sum(lengths[0::2])
    L_ring = jnp.sum(lengths[1::2])
    horiz = params.clamp_prestretch * segs.r_out - r0
    chord = jnp.sqrt(horiz**2 + h_mm**2)
    t = rubber.t_mm

    def half_angle(lam):
        tension = t * rubber.w1(lam, 1.0)  # N/mm
        return jnp.clip(p_mpa * chord / (2.0 * tension), 0.0, 1.0)

    def mismatch(lam, _):
        u = half_angle(lam)
        ratio = jnp.where(u < 1e-4, 1.0 + u**2 / 6.0, jnp.arcsin(u) / jnp.maximum(u, 1e-4))
        return chord * ratio - (lam * L_rubber + L_ring)

    lam_lo = jnp.maximum((chord - L_ring) / L_rubber, 1.0 + 1e-9)
    c = 2.0 + 0.9 * rubber.jm
    lam_hi = jnp.maximum(jnp.sqrt(0.5 * (c + jnp.sqrt(c**2 - 4.0))), lam_lo + 1e-6)
    # A first guess only: the first sign change of the (decreasing) mismatch on a grid,
    # linearly interpolated. Never raises, whatever the bracket (a bisection would
    # abort the batch when the root lies outside [lo, hi]).
    grid = lam_lo + (lam_hi - lam_lo) * jnp.linspace(0.0, 1.0, 129) ** 2
    g = jax.vmap(lambda lam: mismatch(lam, None))(grid)
    g = jnp.where(jnp.isfinite(g), g, -1.0)
    k = jnp.argmax(g <= 0.0)  # 0 when even lam_lo overshoots (or no crossing at all)
    k = jnp.where(jnp.any(g <= 0.0), k, grid.shape[0] - 1)
    k0 = jnp.maximum(k - 1, 0)
    w = jnp.where(g[k0] != g[k], g[k0] / (g[k0] - g[k]), 0.0)
    lam = grid[k0] + jnp.clip(w, 0.0, 1.0) * (grid[k] - grid[k0])
    lam = jnp.clip(lam, lam_lo, lam_hi)
    phi0 = jnp.arctan2(-h_mm, horiz) + jnp.arcsin(half_angle(lam))
    return jnp.stack([jnp.log(jnp.maximum(lam - 1.0, 1e-12)), phi0])


def profile(x, geom: Geometry, params: SimParams, h_mm, p_mpa, n_save: int = 48):
    """The solution along r: ``r``, ``(lambda1, lambda2, phi, Z)``, and stress checks."""
    segs = segments(geom, params)
    _, ok, (r, y) = integrate(segs, p_mpa, start_state(x, h_mm), save_per_segment=n_save)
    # Which segment each saved point belongs to (static: n_save points per segment).
    seg_of_point = jax.tree.map(lambda a: jnp.repeat(a, n_save), segs.seg)
    stress = jax.vmap(lambda sg, l1, l2: (sg.w1(l1, l2), sg.w2(l1, l2), sg.locking(l1, l2)))
    w1, w2, locking = stress(seg_of_point, y[:, 0], y[:, 1])
    return r, y, w1, w2, locking, ok


def n_segments(n_rings: int) -> int:
    return 2 * n_rings + 1


__all__ = [
    "Geometry",
    "geometry_of",
    "segments",
    "integrate",
    "disk_force",
    "force_residual",
    "solve_force",
    "shooting_residual",
    "residual_and_jacobian",
    "with_materialised_jacobian",
    "string_guess",
    "start_state",
    "profile",
]
