"""Independent reference: the membrane by finite elements along r and energy minimisation.

This module deliberately shares nothing with the shooting solver (``solve.py``,
``membrane.py``): it discretises the *energy* rather than the Euler-Lagrange ODEs, so the
two agree only if both are right (issue 2, verification items 5a and 5c).

Model (ARCHITECTURE.md, "The physics"). Reference: the flat annulus ``r0 <= r <= r_out``,
``r0 = contact radius + contact_offset_mm``. Deformed meridian ``(R(r), Z(r))``, piecewise
linear on nodes ``r_0 < ... < r_N`` (every ring edge is a node, so each element is one
material). On an element ``lambda1 = sqrt(dR^2 + dZ^2) / dr`` (constant) and the hoop
stretch ``lambda2 = R / r`` and the thickness are evaluated at the two Gauss points;
the elastic energy is ``sum_e int 2 pi r t(r) W(lambda1, lambda2) dr`` with 2-point
Gauss quadrature. The enclosed volume ``V = -int pi R^2 dZ`` along the meridian from the
disk edge to the clamp (the column under the disk included) is exact for linear
segments: ``-pi (Z_b - Z_a)(R_a^2 + R_a R_b + R_b^2) / 3``. Total potential
``Pi = U - p V``. Units: mm, MPa (= N/mm^2), N, N mm.

Boundary conditions: ``R(r0) = r0``, ``Z(r0) = h`` (rigid disk held by the plate),
``R(r_out) = s r_out`` (clamp pre-stretch ``s``), ``Z(r_out) = 0``.

Force on the plate. By the envelope theorem ``F = -dPi*/dh``: the partial derivative of
``Pi`` with respect to ``h`` at the optimal interior nodes (autodiff). Cross-check, the
vertical balance of the disk: ``F = p pi r0^2 + 2 pi r0 t(r0) W1(lambda1_first, 1) sin(phi)``
with ``phi`` the first element's angle above the horizontal going outward. The two
differ by O(first element length / r0); the mesh is graded towards the disk.

Minimiser. :class:`NewtonTrustRegion`, an ``optimistix`` minimiser (``optx.minimise``):
Newton steps on the exact Hessian (assembled from per-element autodiff Hessians; block
tridiagonal in the nodes, solved by block LDL^T in O(N)) with Levenberg-Marquardt
damping ``(H + lam D) d = -g`` (``D = diag|H|``), accepted when the energy decreases as
predicted. A trial with NaN energy (past the Gent extension limit, or R <= 0) is rejected
and the damping raised. At the end the undamped Hessian must be positive definite (all
Schur complements of the block LDL^T), i.e. the point is a stable equilibrium.

Initial guess / continuation. The plate-held membrane starts from ``R = r`` (linear
blend to the clamp pre-stretch) and ``Z = h ln(r_out / r) / ln(r_out / r0)`` (the
small-strain shape of an isotropically tensioned annulus) plus a parabolic bulge of
Hencky's small-strain height for the first pressure step (a flat start at ``h = 0`` has no
out-of-plane stiffness). The pressure is then raised from 0 in ``n_steps`` equal
increments, each minimisation warm-started from the previous one: quasi-static
inflation at fixed plate height, the rig's protocol. Were the state to jump (a limit
point in ``p`` at fixed ``h``), the damped Newton iteration would follow the jump to
another stable branch; on the ringless 2 mm design at h = 20 mm, F(p) is smooth from 0 to
10 kPa and 8 or 24 increments give identical forces. A point is ``converged`` only if
every step converged, the final out-of-balance force is below 1e-9 of the largest
element force, the Hessian is positive definite and the energy is finite (the unloaded
flat state, exact but with a singular Hessian, is accepted as such); otherwise its
forces and shape are NaN.
"""

from __future__ import annotations

import math
from typing import Callable

import equinox as eqx
import jax
import jax.numpy as jnp
import numpy as np
import optimistix as optx

from mfdesign._x64 import enable_x64
from mfdesign.design import Membrane
from mfdesign.materials import Gent
from mfdesign.physics.params import SimParams
from mfdesign.units import PA_TO_MPA

_GAUSS = (0.5 - 0.5 / math.sqrt(3.0), 0.5 + 0.5 / math.sqrt(3.0))


# ----------------------------------------------------------------------------------------
# Mesh
# ----------------------------------------------------------------------------------------
class Mesh(eqx.Module):
    """Reference nodes and per-element material/thickness data (all arrays)."""

    r: jax.Array  # [N + 1] mm
    mu: jax.Array  # [N] Pa
    jm: jax.Array  # [N]
    i2: jax.Array  # [N] the rubber's I2 share (mfdesign.materials.Gent), 0 on the rings
    t_gauss: jax.Array  # [N, 2] mm, reference thickness at the Gauss points
    r_out_def: jax.Array  # deformed clamp radius s * r_out
    plate_k: jax.Array  # plate-contact penalty [N/mm^3]; 0: the plate touches the disk only
    node_area: jax.Array  # [N + 1] mm^2, reference area each node stands for (2 pi r dr)


def build_mesh(
    design: Membrane,
    params: SimParams = SimParams(),
    n_elements: int = 400,
    grading: float = 1.6,
    plate_contact_k: float = 0.0,
) -> Mesh:
    """Graded mesh: ring edges are nodes; the first segment is refined towards the disk.

    ``plate_contact_k`` [N/mm^3] > 0 lets the membrane touch the plate beyond the disk
    (:func:`fe_force`); 0 keeps the model of the shooting solver and the authors.

    Elements are shared among the segments (disk-ring-...-clamp) in proportion to their
    length (at least 4 per segment). In the first segment the nodes follow
    ``r0 + L x^grading`` (x uniform), so the element next to the disk is small (used by
    the disk-balance force); the other segments are uniform.
    """
    enable_x64()  # float64 physics: mfdesign._x64
    inset = float(params.fabric_inset_mm)
    r0 = float(design.contact_radius_mm) + float(params.contact_offset_mm) - inset
    r_out = float(design.outer_radius_mm)
    edges = [r0]
    for ring in design.rings:
        edges += [ring.inner_mm + inset, ring.outer_mm - inset]
    edges.append(r_out)
    edges = np.asarray(edges, dtype=np.float64)
    if np.any(np.diff(edges) <= 0):
        raise ValueError(f"contact offset / fabric inset put the disk edge {r0} mm beyond a ring edge, or close a ring")
    lengths = np.diff(edges)
    n_seg = len(lengths)
    counts = np.maximum(4, np.floor(n_elements * lengths / lengths.sum()).astype(int))
    # Fix the total exactly to n_elements (static shape for jit).
    while counts.sum() > n_elements:
        counts[np.argmax(counts)] -= 1
    while counts.sum() < n_elements:
        counts[np.argmax(lengths / counts)] += 1
    nodes = [np.array([r0])]
    is_ring = []
    for k in range(n_seg):
        x = np.linspace(0.0, 1.0, counts[k] + 1)[1:]
        if k == 0:
            x = x**grading
        nodes.append(edges[k] + lengths[k] * x)
        is_ring += [k % 2 == 1] * counts[k]  # segments alternate rubber / ring / rubber ...
    r = np.concatenate(nodes)
    r[-1] = r_out
    is_ring = np.asarray(is_ring)
    rubber, fabric = params.rubber, params.fabric
    mu = jnp.where(jnp.asarray(is_ring), fabric.mu_pa, rubber.mu_pa)
    jm = jnp.where(jnp.asarray(is_ring), fabric.jm, rubber.jm)
    i2 = jnp.where(jnp.asarray(is_ring), fabric.i2_share, rubber.i2_share)
    ra, dr = r[:-1], np.diff(r)
    rg = np.stack([ra + g * dr for g in _GAUSS], axis=-1)
    r_mid = 0.5 * (r0 + r_out)
    t_gauss = (
        design.thickness_mm
        * params.thickness_factor
        * (1.0 + params.thickness_gradient * (jnp.asarray(rg) - r_mid) / (r_out - r0))
    )
    half = np.concatenate([[0.0], 0.5 * dr]) + np.concatenate([0.5 * dr, [0.0]])
    return Mesh(
        r=jnp.asarray(r),
        mu=mu,
        jm=jm,
        i2=i2,
        t_gauss=t_gauss,
        r_out_def=jnp.asarray(params.clamp_prestretch * r_out),
        plate_k=jnp.asarray(float(plate_contact_k)),
        node_area=jnp.asarray(2.0 * np.pi * r * half),
    )


# ----------------------------------------------------------------------------------------
# Energy: a sum of element terms, each depending on its two end nodes only
# ----------------------------------------------------------------------------------------
def _element_potential(q, ra, rb, mu, jm, i2, tg, p_pa):
    """``Pi_e`` [N mm] of one element; ``q = (R_a, Z_a, R_b, Z_b)``.

    Elastic part by 2-point Gauss quadrature, pressure part exact for a linear segment.
    NaN past the Gent extension limit or for a non-positive stretch.
    """
    Ra, Za, Rb, Zb = q[0], q[1], q[2], q[3]
    dr = rb - ra
    l1 = jnp.sqrt((Rb - Ra) ** 2 + (Zb - Za) ** 2) / dr
    mat = Gent(mu_pa=mu, jm=jm, i2_share=i2)
    U = 0.0
    bad = l1 <= 0.0
    for k, g in enumerate(_GAUSS):
        rg = ra + g * dr
        l2 = (Ra + g * (Rb - Ra)) / rg
        bad = bad | (l2 <= 0.0)
        U = U + 0.5 * dr * 2.0 * jnp.pi * rg * tg[k] * mat.energy(l1, l2) * PA_TO_MPA
    V = -jnp.pi * (Zb - Za) * (Ra * Ra + Ra * Rb + Rb * Rb) / 3.0
    return jnp.where(bad, jnp.nan, U - p_pa * PA_TO_MPA * V)


def _element_value_grad_hess(q, *args):
    """``(H, (g, value))`` of one element by nested forward-mode autodiff (one pass)."""

    def value(z):
        v = _element_potential(z, *args)
        return v, v

    def grad(z):
        g, v = jax.jacfwd(value, has_aux=True)(z)
        return g, (g, v)

    return jax.jacfwd(grad, has_aux=True)(q)


def _plate_contact(X, mesh: Mesh):
    """Penalty ``sum_i k A_i max(Z_i - Z_0, 0)^2 / 2`` [N mm] of nodes above the plate.

    The plate is the plane through the disk (``Z_0 = h``); a frictionless stiff contact
    (``k`` [N/mm^3], a contact pressure ``k`` x penetration) stands in for the constraint
    ``Z <= h``. Returns the value, its nodal gradient [N+1, 2] and Hessian diagonal
    [N+1, 2] (the disk node's coupling to the others is dropped: it is a fixed dof).
    The gradient's disk entry is the plate's contact reaction, so ``-dPi/dh`` includes it.
    """
    gap = jnp.maximum(X[1:, 1] - X[0, 1], 0.0)
    kA = mesh.plate_k * mesh.node_area[1:]
    value = 0.5 * jnp.sum(kA * gap**2)
    gz = jnp.concatenate([-jnp.sum(kA * gap)[None], kA * gap])
    hz = jnp.concatenate([jnp.zeros(1), jnp.where(gap > 0.0, kA, 0.0)])
    zero = jnp.zeros_like(gz)
    return value, jnp.stack([zero, gz], -1), jnp.stack([zero, hz], -1)


def _element_args(mesh: Mesh):
    return mesh.r[:-1], mesh.r[1:], mesh.mu, mesh.jm, mesh.i2, mesh.t_gauss


def potential_nodes(X, p_pa, mesh: Mesh):
    """Total potential ``Pi = U - p V`` [N mm] of the node array ``X = [[R_i, Z_i]]``."""
    q = jnp.concatenate([X[:-1], X[1:]], axis=1)
    pe = jax.vmap(_element_potential, in_axes=(0, 0, 0, 0, 0, 0, 0, None))(q, *_element_args(mesh), p_pa)
    return jnp.sum(pe) + _plate_contact(X, mesh)[0]


def enclosed_volume(X):
    """``-int pi R^2 dZ`` from the disk edge to the clamp, exact for linear segments."""
    R, Z = X[:, 0], X[:, 1]
    Ra, Rb = R[:-1], R[1:]
    return -jnp.sum(jnp.pi * jnp.diff(Z) * (Ra * Ra + Ra * Rb + Rb * Rb) / 3.0)


def _local_model(X, p_pa, mesh: Mesh):
    """Energy, full nodal gradient [N+1, 2] and the block-tridiagonal Hessian.

    ``D[i]`` is the 2x2 diagonal block of node ``i``, ``B[e]`` the block coupling node
    ``e`` to node ``e + 1``. Assembled from element values, gradients and Hessians.
    """
    q = jnp.concatenate([X[:-1], X[1:]], axis=1)
    ax = (0, 0, 0, 0, 0, 0, 0, None)
    args = (*_element_args(mesh), p_pa)
    He, (ge, pe) = jax.vmap(_element_value_grad_hess, in_axes=ax)(q, *args)
    n = X.shape[0]
    g = jnp.zeros((n, 2)).at[:-1].add(ge[:, :2]).at[1:].add(ge[:, 2:])
    D = jnp.zeros((n, 2, 2)).at[:-1].add(He[:, :2, :2]).at[1:].add(He[:, 2:, 2:])
    B = He[:, :2, 2:]
    pc, gc, hc = _plate_contact(X, mesh)
    g = g + gc
    D = D + jax.vmap(jnp.diag)(hc)
    # Scales for round-off-aware tests: sum |Pi_e| and the largest element force.
    return jnp.sum(pe) + pc, g, D, B, jnp.sum(jnp.abs(pe)) + pc, jnp.max(jnp.abs(ge))


def _masked_model(X, args):
    """Restrict the model to the free degrees of freedom (``mask`` 1 free, 0 fixed)."""
    p_pa, mesh, mask = args
    f, g, D, B, fabs, gabs = _local_model(X, p_pa, mesh)
    g, D, B = _apply_mask(g, D, B, mask)
    return f, g, D, B, fabs, gabs


def _apply_mask(g, D, B, mask):
    g = g * mask
    D = mask[:, :, None] * D * mask[:, None, :] + jax.vmap(jnp.diag)(1.0 - mask)
    B = mask[:-1, :, None] * B * mask[1:, None, :]
    return g, D, B


def _inv2(S):
    det = S[..., 0, 0] * S[..., 1, 1] - S[..., 0, 1] * S[..., 1, 0]
    inv = jnp.stack([jnp.stack([S[..., 1, 1], -S[..., 0, 1]], -1), jnp.stack([-S[..., 1, 0], S[..., 0, 0]], -1)], -2)
    return inv / det[..., None, None], det


def block_tridiag_solve(D, B, b):
    """Solve ``H x = b`` for symmetric block-tridiagonal ``H`` (2x2 blocks) by block LDL^T.

    Returns ``(x, pd)``: ``pd`` is True iff every Schur complement is positive definite,
    i.e. iff ``H`` is positive definite.
    """

    # scan with B_{i-1} supplied per step: prepend a zero block for node 0
    Bp = jnp.concatenate([jnp.zeros((1, 2, 2)), B], axis=0)

    def fwd2(carry, inp):
        S_prev_inv, c_prev, pd = carry
        Di, bi, Bi = inp
        S = Di - Bi.T @ S_prev_inv @ Bi
        c = bi - Bi.T @ S_prev_inv @ c_prev
        S_inv, det = _inv2(S)
        pd = pd & (S[0, 0] > 0) & (det > 0)
        return (S_inv, c, pd), (S_inv, c)

    init = (jnp.zeros((2, 2)), jnp.zeros(2), jnp.asarray(True))
    (_, _, pd), (S_inv, c) = jax.lax.scan(fwd2, init, (D, b, Bp))
    Bn = jnp.concatenate([B, jnp.zeros((1, 2, 2))], axis=0)  # B_i couples i to i+1

    def bwd(x_next, inp):
        Si, ci, Bi = inp
        x = Si @ (ci - Bi @ x_next)
        return x, x

    _, x = jax.lax.scan(bwd, jnp.zeros(2), (S_inv, c, Bn), reverse=True)
    return x, pd


def _block_matvec(D, B, d):
    out = jnp.einsum("nij,nj->ni", D, d)
    out = out.at[:-1].add(jnp.einsum("nij,nj->ni", B, d[1:]))
    out = out.at[1:].add(jnp.einsum("nji,nj->ni", B, d[:-1]))
    return out


# ----------------------------------------------------------------------------------------
# An optimistix minimiser: damped Newton on the exact (block-tridiagonal) Hessian
# ----------------------------------------------------------------------------------------
class _NTRState(eqx.Module):
    f: jax.Array
    fabs: jax.Array
    gabs: jax.Array
    grad: jax.Array
    D: jax.Array
    B: jax.Array
    lam: jax.Array
    terminate: jax.Array
    gnorm: jax.Array
    first: jax.Array


class NewtonTrustRegion(optx.AbstractMinimiser):
    """Newton's method with Levenberg-Marquardt damping, for ``optx.minimise``.

    ``model(y, args) -> (f, grad, D, B, fabs, gabs)`` supplies the energy, its gradient,
    the block-tridiagonal Hessian (autodiff per element) and two scales: ``sum |Pi_e|``
    and the largest element force. A step solves ``(H + lam diag|H|) d = -g`` by block
    LDL^T. It is accepted when the energy falls by at least 1e-4 of the quadratic
    model's prediction or, once the predicted change is below ``ftol_rel sum|Pi_e|``
    (round-off level), when the gradient does not grow more than tenfold (noise).
    Rejected (and ``lam`` x8): NaN energy (past the Gent limit, or R <= 0), a damped
    Hessian that is not positive definite, or too little decrease; ``lam`` /4 after a
    step that matched the model well. Stops (with ``lam < 1e-2``) when the gradient
    max-norm is below ``gtol_rel`` x the largest element force, or when in the round-off
    regime an accepted step is below ``atol + rtol |y|`` (Newton's quadratic convergence
    leaves an error of order ``rtol^2``), or at once when the gradient is below
    ``gexact`` newtons. The first step is a zero step that evaluates the model at ``y0``
    (so the compiled loop holds one copy of the model).
    """

    model: Callable = eqx.field(static=True)
    rtol: float = 1e-8
    atol: float = 1e-10
    gtol_rel: float = 1e-12
    ftol_rel: float = 1e-11
    gexact: float = 1e-12
    lam0: float = 1e-3
    norm: Callable = eqx.field(static=True, default=optx.max_norm)

    def init(self, fn, y, args, options, f_struct, aux_struct, tags):
        # The model is evaluated in `step` only (one copy in the compiled loop): the first
        # step is a zero step that just evaluates it at y0 and is always accepted.
        f, g, D, B, fabs, gabs = jax.tree_util.tree_map(
            lambda s: jnp.full(s.shape, jnp.inf, s.dtype), jax.eval_shape(self.model, y, args)
        )
        return _NTRState(
            f=f,
            fabs=fabs,
            gabs=gabs,
            grad=g,
            D=D,
            B=B,
            lam=jnp.asarray(self.lam0),
            terminate=jnp.asarray(False),
            gnorm=jnp.asarray(jnp.inf),
            first=jnp.asarray(True),
        )

    def step(self, fn, y, args, options, state, tags):
        D, B, g, lam = state.D, state.B, state.grad, state.lam
        diag = jnp.abs(jnp.diagonal(D, axis1=1, axis2=2))
        diag = jnp.maximum(diag, 1e-12 * jnp.max(diag))
        Dd = D + lam * jax.vmap(jnp.diag)(diag)
        d, ok = block_tridiag_solve(Dd, B, -g)
        ok = (ok & jnp.all(jnp.isfinite(d))) | state.first
        d = jnp.where(ok & ~state.first, d, 0.0)
        y_try = y + d
        f_try, g_try, D_try, B_try, fabs_try, gabs_try = self.model(y_try, args)
        pred = jnp.sum(g * d) + 0.5 * jnp.sum(d * _block_matvec(D, B, d))
        actual = f_try - state.f
        # Below this the energy difference is round-off: judge by the gradient instead.
        tiny = jnp.abs(pred) <= self.ftol_rel * state.fabs
        finite = jnp.isfinite(f_try) & jnp.all(jnp.isfinite(g_try))
        gmax_try = jnp.max(jnp.abs(g_try))
        accept = state.first | (
            ok & finite & (((actual <= 1e-4 * pred) & ~tiny) | (tiny & (gmax_try <= 10.0 * state.gnorm)))
        )
        ratio = jnp.where(pred < 0, actual / jnp.where(pred < 0, pred, -1.0), 0.0)
        good = tiny | (ratio > 0.5)
        lam_new = jnp.where(accept, jnp.where(good, lam / 4.0, lam), lam * 8.0)
        lam_new = jnp.where(state.first, lam, jnp.clip(lam_new, 1e-14, 1e14))
        # In the round-off regime Newton converges quadratically: a step of relative size
        # `rtol` leaves an error of order rtol^2.
        step_small = self.norm(d) <= self.atol + self.rtol * self.norm(y)
        grad_small = gmax_try <= self.gtol_rel * state.gabs
        # Balanced to `gexact` newtons (round-off of the element forces is ~1e-14 N):
        # nothing left to do. The unloaded flat state, whose Hessian is singular, would
        # otherwise never pass the step test.
        exact = accept & (gmax_try <= self.gexact)
        terminate = exact | (accept & ~state.first & (lam_new < 1e-2) & (grad_small | (tiny & step_small)))
        sel = lambda a, b: jnp.where(accept, a, b)  # noqa: E731
        new = _NTRState(
            f=sel(f_try, state.f),
            fabs=sel(fabs_try, state.fabs),
            gabs=sel(gabs_try, state.gabs),
            grad=sel(g_try, g),
            D=sel(D_try, D),
            B=sel(B_try, B),
            lam=lam_new,
            terminate=terminate,
            gnorm=sel(gmax_try, state.gnorm),
            first=jnp.asarray(False),
        )
        return sel(y_try, y), new, None

    def terminate(self, fn, y, args, options, state, tags):
        return state.terminate, optx.RESULTS.successful

    def postprocess(self, fn, y, aux, args, options, state, tags, result):
        return y, aux, {"gnorm": state.gnorm, "lam": state.lam}


# ----------------------------------------------------------------------------------------
# Results
# ----------------------------------------------------------------------------------------
class FEResult(eqx.Module):
    """One (or a batch of) finite-element equilibria. NaN where not converged."""

    force_n: jax.Array  # envelope force -dPi*/dh  [N]
    force_disk_n: jax.Array  # disk balance p pi r0^2 + 2 pi r0 t W1 sin(phi)  [N]
    h_mm: jax.Array
    p_pa: jax.Array
    r_mm: jax.Array  # reference nodes
    R_mm: jax.Array
    Z_mm: jax.Array
    energy: jax.Array  # Pi* [N mm]
    converged: jax.Array
    residual: jax.Array  # max |dPi/dy| over free dofs / largest element force
    n_iterations: jax.Array  # Newton iterations over the whole continuation

    @property
    def inside_model(self) -> jax.Array:
        """Converged and inside the physical model: the membrane stays on the plate's side
        of the clamp plane and the force is at most ``p pi R^2``
        (:func:`mfdesign.physics.status.force_bound_n`); the FE counterpart of the
        simulator's ``Status.OUTSIDE_MODEL``. The two go together: by the first integral at
        the clamp, ``F = p pi R^2 + 2 pi R T sin(phi)``, so a force above the bound means the
        membrane leaves the clamp heading down (seen: 164 N against 161 N at 40 mm, 8 kPa,
        the membrane 1.2 mm below the clamp). The radius alone is no criterion: an inflated
        membrane bulges past the clamp radius at ordinary points (84 mm at 20 mm, 5 kPa, a
        point the rig holds), so it is not checked."""
        clamp_r, clamp_z = self.R_mm[..., -1], self.Z_mm[..., -1]
        above = jnp.min(self.Z_mm, axis=-1) >= clamp_z - 1e-6 * clamp_r  # rounding only
        bound = self.p_pa * PA_TO_MPA * jnp.pi * clamp_r**2
        return self.converged & above & (self.force_n <= bound * (1 + 1e-6))


def _objective(X, args):
    p_pa, mesh, _ = args
    return potential_nodes(X, p_pa, mesh), None


def _minimise(X0, args, max_steps):
    solver = NewtonTrustRegion(model=_masked_model)
    sol = optx.minimise(_objective, solver, X0, args, has_aux=True, max_steps=max_steps, throw=False)
    return sol.value, sol.result == optx.RESULTS.successful, sol.stats["num_steps"]


def _finish(X, p, mesh: Mesh, mask, ok_steps, nsteps):
    f, g_full, D, B, _, gabs = _local_model(X, p, mesh)
    g, Dm, Bm = _apply_mask(g_full, D, B, mask)
    _, pd = block_tridiag_solve(Dm, Bm, jnp.zeros_like(g))
    # Out-of-balance nodal force relative to the largest element force (N-independent).
    residual = jnp.max(jnp.abs(g)) / gabs
    F_env = -g_full[0, 1]  # -dPi/dh at the optimal interior nodes (envelope theorem)
    # Disk balance on the first element.
    r0, dr0 = mesh.r[0], mesh.r[1] - mesh.r[0]
    dR, dZ = X[1, 0] - X[0, 0], X[1, 1] - X[0, 1]
    ds = jnp.sqrt(dR**2 + dZ**2)
    tg = mesh.t_gauss[0]
    t0 = tg[0] - (tg[1] - tg[0]) * _GAUSS[0] / (_GAUSS[1] - _GAUSS[0])  # extrapolate to r0
    W1 = jax.grad(Gent(mu_pa=mesh.mu[0], jm=mesh.jm[0], i2_share=mesh.i2[0]).energy)(ds / dr0, jnp.asarray(1.0))
    F_disk = p * PA_TO_MPA * jnp.pi * r0**2 + 2.0 * jnp.pi * r0 * t0 * W1 * PA_TO_MPA * dZ / ds
    # The unloaded flat state (p = 0, h = 0, no clamp pre-stretch) is exact but has no
    # out-of-plane stiffness (semi-definite Hessian): accept it when exactly in balance.
    trivial = (p == 0.0) & (jnp.abs(X[0, 1]) == 0.0) & (jnp.max(jnp.abs(g)) <= 1e-12)
    residual = jnp.where(trivial, 0.0, residual)
    conv = ok_steps & jnp.isfinite(f) & (((residual < 1e-9) & pd) | trivial)
    nan = jnp.nan
    return FEResult(
        force_n=jnp.where(conv, F_env, nan),
        force_disk_n=jnp.where(conv, F_disk, nan),
        h_mm=jnp.where(conv, X[0, 1], nan),
        p_pa=p,
        r_mm=mesh.r,
        R_mm=jnp.where(conv, X[:, 0], nan),
        Z_mm=jnp.where(conv, X[:, 1], nan),
        energy=jnp.where(conv, f, nan),
        converged=conv,
        residual=residual,
        n_iterations=nsteps,
    )


@eqx.filter_jit
def _continuation(X0, p_from, p_to, mesh: Mesh, mask, n_steps: int, max_steps: int):
    """Raise the pressure from ``p_from`` to ``p_to`` in ``n_steps``, warm-starting each."""

    def body(carry, k):
        X, ok, ns = carry
        pk = p_from + (p_to - p_from) * (k + 1) / n_steps
        X_new, ok_k, n_k = _minimise(X, (pk, mesh, mask), max_steps)
        return (X_new, ok & ok_k, ns + n_k), None

    (X, ok, ns), _ = jax.lax.scan(body, (X0, jnp.asarray(True), jnp.asarray(0)), jnp.arange(n_steps))
    return _finish(X, p_to, mesh, mask, ok, ns)


def _plate_mask(n_nodes):
    m = jnp.ones((n_nodes, 2))
    return m.at[0].set(0.0).at[-1].set(0.0)


def _initial_nodes(h, mesh: Mesh, p1=0.0):
    """Logarithmic cone through the disk edge and the clamp, plus a bulge for pressure.

    The bulge ``b 4 x (1 - x)`` (``x`` the reference position across the annulus of
    width ``L``) has Hencky's small-strain height for a membrane of span ``L``,
    ``b = 0.6 (L/2) (p1 (L/2) / (3 mu t))^(1/3)`` at the first pressure step ``p1``:
    starting flat at ``h = 0`` would leave the Newton iteration with a singular
    out-of-plane stiffness.
    """
    r = mesh.r
    r0, r_out = r[0], r[-1]
    x = (r - r0) / (r_out - r0)
    R = r + x * (mesh.r_out_def - r_out)
    half = 0.5 * (r_out - r0)
    mu_t = mesh.mu[-1] * PA_TO_MPA * mesh.t_gauss[-1, -1]
    b = 0.6 * half * (p1 * PA_TO_MPA * half / (3.0 * mu_t)) ** (1.0 / 3.0)
    Z = h * jnp.log(r_out / r) / jnp.log(r_out / r0) + b * 4.0 * x * (1.0 - x)
    return jnp.stack([R, Z], axis=-1)


def _tree_reshape(res, shape):
    size = int(np.prod(shape))
    return jax.tree_util.tree_map(
        lambda a: a.reshape(shape + a.shape[1:]) if a.ndim >= 1 and a.shape[0] == size else a, res
    )


def _point(mesh: Mesh, hh, pp, n_steps: int, max_steps: int):
    """One plate-held equilibrium (see :func:`fe_force` for the start and the path)."""
    mask = _plate_mask(mesh.r.shape[0])
    X0 = _initial_nodes(hh, mesh, pp / n_steps)
    return _continuation(X0, jnp.asarray(0.0), pp, mesh, mask, n_steps, max_steps)


@eqx.filter_jit
def _points(meshes: Mesh, which, h, p, n_steps: int, max_steps: int):
    """Every point at once: point ``i`` on mesh ``which[i]`` of the stacked ``meshes``."""

    def one(i, hh, pp):
        return _point(jax.tree_util.tree_map(lambda a: a[i], meshes), hh, pp, n_steps, max_steps)

    return jax.vmap(one)(which, h, p)


def _row(mesh: Mesh, hh, ps, n_steps: int, max_steps: int):
    """One height's equilibria at increasing pressures ``ps``: a point's path to ``ps[0]``
    (:func:`_point`: ``n_steps`` increments from 0), then one increment to each next
    pressure from the equilibrium before; one scan over that schedule. A failed increment
    fails the rest of the row (its start would be no equilibrium)."""
    mask = _plate_mask(mesh.r.shape[0])
    schedule = jnp.concatenate([ps[0] * (jnp.arange(n_steps) + 1) / n_steps, ps[1:]])

    def step(carry, pp):
        X, ok, ns = carry
        X, ok_k, n_k = _minimise(X, (pp, mesh, mask), max_steps)
        ok, ns = ok & ok_k, ns + n_k
        return (X, ok, ns), _finish(X, pp, mesh, mask, ok, ns)

    start = (_initial_nodes(hh, mesh, ps[0] / n_steps), jnp.asarray(True), jnp.asarray(0))
    _, res = jax.lax.scan(step, start, schedule)
    return jax.tree_util.tree_map(lambda a: a[n_steps - 1 :], res)


@eqx.filter_jit
def _rows(mesh: Mesh, h, ps, n_steps: int, max_steps: int):
    return jax.vmap(lambda hh: _row(mesh, hh, ps, n_steps, max_steps))(h)


def fe_rows(
    design: Membrane,
    params: SimParams,
    h_mm,
    p_pa,
    n_elements: int = 400,
    n_steps: int = 8,
    max_steps: int = 200,
) -> FEResult:
    """Plate-held equilibria on a grid: every height of ``h_mm`` [R] at every pressure of
    ``p_pa`` [P] (increasing, > 0), as :func:`fe_forces` solves them but along each height's
    quasi-static inflation: the first pressure from ``p = 0`` in ``n_steps`` increments,
    each next one a single increment from the equilibrium before (the same path, walked
    once instead of once a point). Whole rows of a simulator plane the shooting cannot
    solve (plate heights near the membrane's reach beside a wide outer ring) cost a point
    path each otherwise: 8 increments a node, 45 of the ~190 thread-seconds that 30 planes
    of the bundled membranes took (issue 40). A failed increment leaves the rest of its
    row NaN (the caller solves those nodes one by one).

    Returns an :class:`FEResult` whose fields are shaped [R, P] (plus the node axis)."""
    from mfdesign.physics.solve import in_batches, n_workers

    enable_x64()  # float64 physics: mfdesign._x64
    ps = np.asarray(p_pa, np.float64)
    if ps.ndim != 1 or ps.size < 1 or not np.all(np.diff(ps) > 0) or not ps[0] > 0:
        raise ValueError("fe_rows: p_pa must be increasing pressures above 0 Pa")
    mesh = build_mesh(design, params, n_elements)
    h = np.atleast_1d(np.asarray(h_mm, np.float64))
    # two rows a batch: one program for any number of rows, both lanes busy from three rows
    # on (5 rows of 82 pressures: 2.5 s one a batch, 1.3-1.9 s two or more, 2-core CPU)
    return in_batches(
        lambda hh: _rows(mesh, jnp.asarray(hh), jnp.asarray(ps), n_steps, max_steps), h, size=2, lanes=n_workers()
    )


def fe_forces(
    jobs,
    h_mm,
    p_pa,
    n_elements: int = 400,
    n_steps: int = 8,
    max_steps: int = 200,
    plate_contact_k=0.0,
    batch: int = 16,
    progress: bool = False,
) -> list[FEResult]:
    """:func:`fe_force` of many membranes and constants at once, each with its own points.

    Every job's mesh has ``n_elements`` elements, so the meshes stack into one array and
    the points, in batches of ``batch``, are solved by one vmapped kernel compiled once;
    the batches run one a core on threads (XLA releases the GIL) or device.

    Arguments:
        jobs: ``(design, params)`` pairs (a :class:`~mfdesign.design.Membrane` and its
            :class:`~mfdesign.physics.params.SimParams`).
        h_mm: per job, plate heights [mm] (an array or a scalar).
        p_pa: per job, gauge pressures [Pa], broadcast with that job's heights.
        n_elements: finite elements along ``r`` (as :func:`build_mesh`).
        n_steps: pressure increments of the quasi-static path from ``p = 0``.
        max_steps: Newton steps allowed per increment.
        plate_contact_k: plate-contact penalty [N/mm^3], one for every job or one per job
            (0: the plate touches the disk only; see :func:`fe_force`).
        batch: points a vmapped batch. A batch's Newton loops run as long as its slowest
            point's, so on a CPU small batches waste less on points that need every step:
            192 points of the real lifts in one batch took 2.0x the CPU of batches of 16,
            64 took 1.44x, 8 1.05x, 1 1.26x (``experiments/bench_fe_batch.py``, 2-core
            CPU, load 3-4). A GPU wants large batches.
        progress: a tqdm bar over the batches.

    Returns one :class:`FEResult` per job, its fields shaped like the job's broadcast
    points (plus the node axis for ``r_mm``, ``R_mm``, ``Z_mm``).
    """
    # batching and worker count only: nothing of the shooting solver's physics is shared
    from mfdesign.physics.solve import in_batches, n_workers

    enable_x64()  # float64 physics: mfdesign._x64
    jobs = list(jobs)
    if not (len(jobs) == len(h_mm) == len(p_pa)):
        raise ValueError(f"fe_forces: {len(jobs)} jobs but {len(h_mm)} height and {len(p_pa)} pressure arrays")
    ks = np.broadcast_to(np.asarray(plate_contact_k, dtype=np.float64), (len(jobs),))
    meshes = [build_mesh(d, prm, n_elements, plate_contact_k=float(k)) for (d, prm), k in zip(jobs, ks)]
    stacked = jax.tree_util.tree_map(lambda *a: jnp.stack(a), *meshes)
    pts = [np.broadcast_arrays(np.asarray(h, np.float64), np.asarray(p, np.float64)) for h, p in zip(h_mm, p_pa)]
    shapes = [h.shape for h, _ in pts]
    which = np.concatenate([np.full(h.size, j) for j, (h, _) in enumerate(pts)]).astype(np.int32)
    h_all = np.concatenate([h.ravel() for h, _ in pts])
    p_all = np.concatenate([p.ravel() for _, p in pts])
    n = h_all.size
    bar = None
    if progress:
        from tqdm.auto import tqdm

        bar = tqdm(total=-(-n // max(1, min(int(batch), n))), desc="FE batches", unit="batch")
    res = in_batches(
        lambda w, hh, pp: _points(stacked, jnp.asarray(w), jnp.asarray(hh), jnp.asarray(pp), n_steps, max_steps),
        which,
        h_all,
        p_all,
        size=batch,
        lanes=n_workers(),
        bar=bar,
    )
    if bar is not None:
        bar.close()
    ends = np.cumsum([int(np.prod(s)) for s in shapes])

    def job(j):  # job j's slice of the points, in its own shape
        lo, shape = ends[j] - int(np.prod(shapes[j])), shapes[j]
        return jax.tree_util.tree_map(lambda a: jnp.asarray(a[lo : ends[j]].reshape(shape + a.shape[1:])), res)

    return [job(j) for j in range(len(jobs))]


def fe_force(
    design: Membrane,
    h_mm,
    p_pa,
    params: SimParams = SimParams(),
    n_elements: int = 400,
    n_steps: int = 8,
    max_steps: int = 200,
    plate_contact_k: float = 0.0,
) -> FEResult:
    """Force [N] on the plate held at height ``h_mm`` [mm] at pressure ``p_pa`` [Pa].

    ``plate_contact_k`` [N/mm^3]: 0 (the default, the shooting solver's and the authors'
    model) lets the membrane beside the disk rise through the plate; > 0 makes the plate
    a frictionless penalty contact (pressure ``k`` x penetration) that the membrane lies
    against, and the force then includes its reaction.

    ``h_mm`` and ``p_pa`` may be arrays (broadcast together; solved in parallel with
    ``vmap``; :func:`fe_forces` takes many designs and constants at once). Each point
    follows quasi-static inflation at fixed ``h`` from ``p = 0`` in ``n_steps`` equal
    pressure increments, starting from the logarithmic cone
    ``Z = h ln(r_out/r)/ln(r_out/r0)``, ``R = r``, plus a small-strain bulge for the first
    pressure step (see :func:`_initial_nodes`). Unconverged points (extension limit,
    minimiser failure, unstable state) have ``converged = False`` and NaN forces and
    shapes.
    """
    return fe_forces([(design, params)], [h_mm], [p_pa], n_elements, n_steps, max_steps, plate_contact_k)[0]


def fe_free_inflation(
    design: Membrane,
    p_pa,
    params: SimParams = SimParams(),
    n_elements: int = 400,
    n_steps: int = 8,
    max_steps: int = 200,
    h_guess_mm=None,
) -> FEResult:
    """Free inflation (no plate, ``F = 0``): the disk height ``h_mm`` is an unknown too.

    Starts from the paraboloid ``Z = h_g (1 - (r/a)^2) / (1 - (r0/a)^2)`` with ``h_g``
    Hencky's small-strain estimate ``0.6 a (p1 a / (3 mu t))^(1/3)`` at the first
    pressure step ``p1 = p / n_steps`` (or ``h_guess_mm``), then raises the pressure in
    ``n_steps`` increments. ``force_n`` of the result is ``-dPi/dh`` ~ 0 (a check).
    """
    enable_x64()  # float64 physics: mfdesign._x64
    mesh = build_mesh(design, params, n_elements)
    p = jnp.asarray(p_pa, dtype=jnp.float64)
    a = float(design.outer_radius_mm)
    t = float(design.thickness_mm) * params.thickness_factor
    mask = _plate_mask(mesh.r.shape[0]).at[0, 1].set(1.0)  # the disk moves vertically

    def one(pp):
        if h_guess_mm is None:
            p1 = pp / n_steps * PA_TO_MPA
            hg = 0.6 * a * (p1 * a / (3.0 * params.mu_pa * PA_TO_MPA * t)) ** (1.0 / 3.0)
        else:
            hg = jnp.asarray(h_guess_mm, dtype=jnp.float64)
        r = mesh.r
        R = r + (r - r[0]) / (r[-1] - r[0]) * (mesh.r_out_def - r[-1])
        Z = hg * (1.0 - (r / r[-1]) ** 2) / (1.0 - (r[0] / r[-1]) ** 2)
        return _continuation(jnp.stack([R, Z], -1), jnp.asarray(0.0), pp, mesh, mask, n_steps, max_steps)

    if p.ndim == 0:
        return one(p)
    return _tree_reshape(jax.vmap(one)(p.ravel()), p.shape)


__all__ = [
    "FEResult",
    "Mesh",
    "NewtonTrustRegion",
    "block_tridiag_solve",
    "build_mesh",
    "enclosed_volume",
    "fe_force",
    "fe_forces",
    "fe_free_inflation",
    "fe_rows",
    "potential_nodes",
]
