"""The simulator's public interface: force at a plate height, height under a load, shape.

Units: heights and radii in mm, pressures in Pa, forces in N.

* :func:`force_at` -- the rig's experiment: plate held at ``h``, chamber at ``p``.
* :func:`force_plane` -- the same on a height x pressure grid (the paper's figure).
* :func:`height_at` -- the mass-lift experiment: the plate carries a load ``F``.
* :func:`shape` -- the deformed meridian, stretches and stresses, for plots and checks.

Every point comes with a :class:`~mfdesign.physics.status.Status`. Solutions are found
by quasi-static inflation at fixed height: pressure rises from near zero to the target
in small steps, each shooting solve warm-started from the last (natural-parameter
continuation). A pressure limit point at fixed height (snap-through) shows up as a sign
change of the shooting Jacobian's determinant along the path; points beyond it are
``LIMIT_POINT``. Points below the pressure at which the membrane reaches the plate
(negative contact force) are ``NO_CONTACT`` with force 0, as the rig would measure.
"""

from __future__ import annotations

import collections
import dataclasses
import os
import threading
from concurrent.futures import ThreadPoolExecutor
from typing import Any, Callable, Sequence

import equinox as eqx
import jax
import jax.numpy as jnp
import numpy as np
import optimistix as optx

from mfdesign._x64 import enable_x64
from mfdesign.design import OUTER_RADIUS_MM, Membrane
from mfdesign.errors import InputError
from mfdesign.physics import _traces
from mfdesign.physics import shooting as sh
from mfdesign.physics.params import SimParams
from mfdesign.physics.status import SOLVER_FAILED, Status, force_bound_n
from mfdesign.units import PA_TO_MPA

WRINKLE_TOL = 1e-9  # MPa: a principal stress more negative than this is compression
PATH_STEPS = 8  # pressure steps from p / PATH_STEPS to p for a scattered point
# Below this plate height [mm] a point is reached by inflating at LOW_HEIGHT_MM and then
# lowering the plate at fixed pressure (force_at: DESCENT_STEPS steps; force_plane: one
# step per low grid row, row after row): beside a stiff ring the
# string model's first guess at h ~ 0 lies outside the physical region, so inflation at
# fixed low height never starts (and, under vmap, holds up every height of the batch).
LOW_HEIGHT_MM = 4.0
DESCENT_STEPS = 4


class SimResult(eqx.Module):
    """Per-point outputs (NumPy arrays of one shape).

    ``force_n`` [N] (0 for ``NO_CONTACT``, NaN where ``status`` is not usable),
    ``status`` (int codes of :class:`Status`), ``max_locking`` (``(I1 - 3) / J_m`` at
    the most stretched point: 1 is the Gent limit, a burst indicator), ``max_rise_mm``
    (how far the membrane rises above the plate beside the disk: the model has no
    contact beyond the disk, so large values flag where it is least trustworthy) and
    ``wrinkled`` (a principal stress is compressive somewhere: real membranes wrinkle
    there, which membrane theory ignores; the force is kept, flagged).
    """

    force_n: np.ndarray
    status: np.ndarray
    max_locking: np.ndarray
    max_rise_mm: np.ndarray
    wrinkled: np.ndarray

    @property
    def ok(self) -> np.ndarray:
        return np.isin(self.status, [Status.OK, Status.NO_CONTACT])


class PointSolution(eqx.Module):
    """What a kernel knows about each point it solved (arrays with the points' leading axes).

    ``converged``: the shooting converged at the point; ``passed``: a pressure limit point
    was passed on the way (a fold); ``force_n`` [N] (negative before contact); ``wrinkled``,
    ``locking``, ``rise_mm``, ``profile_ok``: the stress checks of the state (of the last
    converged one where the point failed); ``state``: the shooting unknowns ``x`` [..., 2].
    """

    converged: Any
    passed: Any
    force_n: Any
    wrinkled: Any
    locking: Any
    rise_mm: Any
    profile_ok: Any
    state: Any


def _exportable(cls: type, n_fields: int) -> None:
    """Let ``jax.export`` store and read kernels that return ``cls`` (:mod:`._traces`): an
    equinox Module's node data carries no value here (every field is an array), so nothing
    is written and the one it always has is read back."""
    from jax import export

    aux = jax.tree_util.tree_structure(cls(*range(n_fields))).node_data()[1]
    export.register_pytree_node_serialization(
        cls,
        serialized_name=f"{cls.__module__}.{cls.__qualname__}",
        serialize_auxdata=lambda _: b"",
        deserialize_auxdata=lambda _: aux,
    )


_exportable(PointSolution, len(dataclasses.fields(PointSolution)))


class KeptPrograms:
    """The plane solver's compiled programs, kept for the whole process.

    A long job drops JAX's caches between its stages (:func:`mfdesign._memory.release_memory`:
    the compiled programs of every stage held 4 GB), and each stage that solves planes or
    points then traced the solver's kernels again: ~10 s for the plane kernel (now the
    walk kernel), ~4 s for the points kernel, on 2 cores, in every stage that used them
    (41 s of a cold quick demo's 89 s of tracing, session 33). Here each kernel is traced and compiled once per
    argument signature (``jax.jit(...).lower(...).compile()``: ahead of time, so the
    program is held here, not in JAX's caches, and survives ``jax.clear_caches()``), at
    most ``size`` programs, the least recently used dropped; where the compilation cache
    is on, the traced kernel is stored for the next process too (:mod:`._traces`). The
    walk (a plane's rows and its descent), points and height kernels come through here. A
    first call from several threads compiles once. On several devices the kernel is called as it is (its
    arguments carry shardings a kept program would not match)."""

    def __init__(self, size: int = 8) -> None:
        self.size = size
        self._programs: collections.OrderedDict = collections.OrderedDict()
        # Held while a program compiles: the threads of one batched call all wait for the
        # same program, so one lock is enough (and two kernels never compile side by side).
        self._lock = threading.Lock()

    def __len__(self) -> int:
        return len(self._programs)

    @staticmethod
    def _signature(args) -> tuple:
        leaves, tree = jax.tree.flatten(args)
        leaves = [jnp.asarray(v) for v in leaves]
        return leaves, tree, tuple((v.shape, v.dtype, v.weak_type) for v in leaves)

    def holders(self, kernel: Callable, args: tuple, static: tuple = (), padded: tuple = ()) -> list[dict]:
        """The programs of ``kernel`` (same ``static``), kept here or stored on disk by an
        earlier process (:func:`._traces.stored_shapes`), that could take ``args`` with the
        arguments at the indices ``padded`` (arrays) padded: every other leaf of the same
        shape and type, each padded argument of the same rank and type and nowhere smaller.
        One ``{index: shape}`` of the padded arguments per program (the call's own shapes
        among them when its program is kept or stored). None on several devices, where
        nothing is kept (:meth:`__call__`)."""
        if len(jax.local_devices()) > 1:
            return []
        owner = [i for i, a in enumerate(args) for _ in jax.tree.leaves(a)]
        _, tree, sig = self._signature(args)
        with self._lock:
            candidates = [k_sig for k, st, tr, k_sig in self._programs if k is kernel and st == static and tr == tree]
        kinds = [kind for _, *kind in sig]
        candidates += [
            tuple((shape, *kind) for shape, kind in zip(shapes, kinds))
            for shapes in _traces.stored_shapes(kernel, static, tree, sig)
        ]
        found: list[dict] = []
        for k_sig in candidates:
            shapes: dict = {}
            for i, (s, *kind), (ks, *k_kind) in zip(owner, sig, k_sig):
                fits = kind == k_kind and len(s) == len(ks) and all(a <= b for a, b in zip(s, ks))
                if not fits or (i not in padded and s != ks):
                    break
                if i in padded:
                    shapes[i] = ks
            else:
                if shapes not in found:
                    found.append(shapes)
        return found

    def __call__(self, kernel: Callable, *args, static: tuple = ()):
        """``kernel(*args, *static)``: ``args`` a pytree of arrays, ``static`` hashable."""
        if len(jax.local_devices()) > 1:
            return kernel(*args, *static)
        leaves, tree, sig = self._signature(args)
        key = (kernel, static, tree, sig)
        with self._lock:
            program = self._programs.get(key)
            if program is None:

                def flat(*xs):
                    return kernel(*jax.tree.unflatten(tree, xs), *static)

                flat.__name__ = getattr(kernel, "__name__", "kernel")  # the program's name in logs
                program = self._programs[key] = _traces.compiled(kernel, flat, leaves, static, tree, sig)
                while len(self._programs) > self.size:
                    self._programs.popitem(last=False)
            else:
                self._programs.move_to_end(key)
        return program(*leaves)


KEPT = KeptPrograms()

# A kept program with larger batch axes serves a call whose own program is not compiled,
# its arguments padded, while its work (the product of the padded axes) is at most this
# many times the call's: compiling the walk kernel costs ~20 s of XLA and tracing on 2
# cores, a made simulator plane on the data planes' program a few seconds more computing
# (issue 40: the demo's made run on 15 heights x 17 pressures compiled its programs
# again, beside the data planes' 31 x 83).
PAD_WORK_LIMIT = 10.0
# ... or while that work is at most this (lanes x (steps + reported points)): a plane's
# descent (17 pressures x one low height) runs on its rows' program (15 x 35 x 17) for
# a fraction of a second, where a program of its own took ~20 s to compile on 2 cores.
PAD_WORK_FLOOR = 1024


def _edge(a, shape):
    """``a`` padded to ``shape`` by repeating its last entries (real points: no new failures)."""
    a = np.asarray(a)
    return np.pad(a, [(0, n - m) for m, n in zip(a.shape, shape)], mode="edge")


def _filled(value):
    def pad(a, shape):
        a = np.asarray(a)
        return np.pad(a, [(0, n - m) for m, n in zip(a.shape, shape)], constant_values=value)

    return pad


def _kept_call(
    kernel, args: tuple, pads: dict[int, Callable], work: Callable[[dict], float], lead: Callable[[dict], tuple]
):
    """``KEPT(kernel, *args)``, or a kept program of ``kernel`` with larger batch axes
    (:meth:`KeptPrograms.holders`) fed ``args`` padded (``pads[i](arg, shape)`` for the
    arguments that may grow), when its ``work(shapes)`` is at most :data:`PAD_WORK_LIMIT`
    times the call's; every output is cut back to the call's leading axes (``lead(shapes)``
    of the arguments' shapes). A padded lane never changes a real one: lanes are
    independent, and padded path steps come after every reported one. The results equal
    the call's own program's to rounding only (XLA vectorises another batch size
    otherwise: up to ~1e-12 N on a plane), so they may depend in the last bits on what
    the process compiled before."""
    own = {i: np.shape(args[i]) for i in pads}
    fits = [
        s
        for s in KEPT.holders(kernel, args, padded=tuple(pads))
        if work(s) <= max(PAD_WORK_LIMIT * work(own), PAD_WORK_FLOOR)
    ]
    best = min(fits, key=work, default=own)
    if best == own:
        return KEPT(kernel, *args)
    out = KEPT(kernel, *(pads[i](a, best[i]) if i in pads else a for i, a in enumerate(args)))
    cut = tuple(slice(0, n) for n in lead(own))
    return jax.tree.map(lambda o: np.asarray(o)[cut], out)


# --------------------------------------------------------------------------------------
# jitted kernels (one design; vmapped over points)


class _Walk(eqx.Module):
    """A continuation's state between steps (:func:`_step`): the last two converged states
    ``x1``, ``x2`` [unknowns] and their pressures ``p1``, ``p2`` [MPa], how many converged
    (``n_have``), the shooting Jacobian's determinant at the first (``det0``), whether a
    limit point was passed, whether the last step converged, and whether the walk goes on
    (``alive``: a walk without restarts stops at its first failure)."""

    x1: Any
    p1: Any
    x2: Any
    p2: Any
    n_have: Any
    det0: Any
    passed: Any
    last_ok: Any
    alive: Any


def _start(x0, p0, have, alive=True) -> _Walk:
    """A walk from the state ``x0`` (solved at pressure ``p0`` [MPa]) where ``have``, else
    from nothing (its first step starts from the string model); none at all where not
    ``alive``."""
    have = jnp.asarray(have)
    return _Walk(x0, p0, x0, p0, have.astype(int), jnp.asarray(1.0), jnp.asarray(False), have, jnp.asarray(alive))


def _step(walk: _Walk, hp, geom, params, secant=True, restart=True):
    """One continuation step to the point ``hp = (h [mm], p [MPa])``.

    Predictor: with ``secant``, extrapolation in pressure from the last two solutions (the
    last one alone after the first success; without, the last solution: a plate lowered at
    fixed pressure); the string model when the walk has no solution yet or the previous
    step failed (across a stiff ring at low tension the shooting is very sensitive, and a
    restart from the string model recovers). Without ``restart`` a failed step ends the
    walk instead (a lowered plate is not picked up again). Corrector: one
    Levenberg-Marquardt solve; one solve per step, because under ``vmap`` both branches of
    a conditional would run. A sign change of the shooting Jacobian's determinant marks a
    passed pressure limit point. A NaN pressure is a padded step (:func:`_kept_call`):
    skipped, at the cost of one residual evaluation.
    """
    h, p_mpa = hp
    w = walk
    live = jnp.isfinite(p_mpa) & w.alive
    p_mpa = jnp.where(live, p_mpa, w.p1)
    slope = jnp.where(secant & (w.n_have >= 2), (w.x1 - w.x2) / jnp.where(w.p1 != w.p2, w.p1 - w.p2, 1.0), 0.0)
    predicted = w.x1 + slope * (p_mpa - w.p1)
    cold = sh.string_guess(geom, params, h, p_mpa)
    have = w.n_have > 0
    x, conv, det = sh.solve_force(jnp.where(have & w.last_ok, predicted, cold), geom, params, h, p_mpa, active=live)
    det0 = jnp.where(have, w.det0, det)
    passed = w.passed | (conv & have & (jnp.sign(det) != jnp.sign(det0)))
    walk = _Walk(
        jnp.where(conv, x, w.x1),
        jnp.where(conv, p_mpa, w.p1),
        jnp.where(conv, w.x1, w.x2),
        jnp.where(conv, w.p1, w.p2),
        w.n_have + conv.astype(int),
        det0,
        passed,
        conv,
        w.alive & (restart | conv),
    )
    return walk, (x, conv, passed)


def _path(geom, params, h, p_path_mpa):
    """Continuation along an increasing pressure path at fixed height."""
    hs = jnp.broadcast_to(h, p_path_mpa.shape)
    init = _start(jnp.zeros(2), jnp.asarray(0.0), False)
    _, (xs, conv, passed) = jax.lax.scan(lambda w, hp: _step(w, hp, geom, params), init, (hs, p_path_mpa))
    return xs, conv, passed


def _descend(x, geom, params, h_from, h_to, p_mpa, n_steps: int = DESCENT_STEPS, active=True):
    """Height continuation at fixed pressure: the plate moves from ``h_from`` to ``h_to``
    in ``n_steps`` equal steps, each shooting solve warm-started by secant extrapolation in
    ``h`` from the last two converged states; after a failed step the point is dropped
    (``active`` off). Returns ``(x, converged_at_h_to)``."""
    hs = h_from + (h_to - h_from) * jnp.arange(1, n_steps + 1) / n_steps

    def step(carry, hh):
        x1, h1, x2, h2, ok = carry
        dh = jnp.where(h1 != h2, h1 - h2, 1.0)
        predicted = x1 + jnp.where(h1 != h2, (x1 - x2) / dh, 0.0) * (hh - h1)
        x, conv, _ = sh.solve_force(predicted, geom, params, hh, p_mpa, active=ok)
        return (
            jnp.where(conv, x, x1),
            jnp.where(conv, hh, h1),
            jnp.where(conv, x1, x2),
            jnp.where(conv, h1, h2),
            conv,
        ), None

    h_from = jnp.asarray(h_from, float)
    init = (x, h_from, x, h_from, jnp.asarray(active))
    (x, _, _, _, conv), _ = jax.lax.scan(step, init, hs)
    return x, conv


def _last_good(xs, conv, path):
    """The last converged solution on a path and its pressure (the end when it converged):
    checks of a failed point (e.g. how close to the Gent limit) use the last good state."""
    idx = jnp.max(jnp.where(conv, jnp.arange(conv.shape[0]), 0))
    idx = jnp.where(conv[-1], conv.shape[0] - 1, idx)
    return xs[idx], path[idx]


def _point_outputs(x, geom, params, h, p_at, p_mpa):
    """Force at ``p_mpa`` and the stress checks of the state ``x`` solved at ``p_at``."""
    segs = sh.segments(geom, params)
    force = sh.disk_force(segs, p_mpa, 1.0 + jnp.exp(x[0]), x[1])
    x_safe = jnp.where(jnp.all(jnp.isfinite(x)), x, jnp.array([-1.0, 0.0]))
    _, y, w1, w2, locking, ok_prof = sh.profile(x_safe, geom, params, h, p_at, n_save=24)
    wrinkled = (jnp.min(w1) < -WRINKLE_TOL) | (jnp.min(w2) < -WRINKLE_TOL)
    rise = jnp.max(y[:, 3]) - h
    return force, wrinkled, jnp.max(locking), rise, ok_prof


@eqx.filter_jit
def _points_kernel(geom, params, h, p_mpa, n_steps: int):
    """Scattered points: each gets its own path ``p * k / n_steps``, k = 1..n_steps; a point
    below ``LOW_HEIGHT_MM`` runs its path there and the plate is then lowered to ``h``.

    One kernel for both kinds (the descent is masked off above ``LOW_HEIGHT_MM``, at the
    cost of ``DESCENT_STEPS`` residual evaluations): a kernel per kind compiled twice,
    ~4 s each, most of a cold plane repair. Like every kernel here it serves all ring
    counts (:class:`~mfdesign.physics.shooting.Geometry` pads the ring slots)."""

    def one(hh, pp):
        x, conv_end, passed, seen, h_at, p_at = _point_state(geom, params, hh, pp, n_steps)
        force, wrinkled, locking, rise, ok_prof = _point_outputs(x, geom, params, h_at, p_at, pp)
        # No converged state on the whole path: nothing is known about locking.
        locking = jnp.where(seen, locking, jnp.nan)
        return PointSolution(conv_end, passed, force, wrinkled, locking, rise, ok_prof, x)

    return jax.vmap(one)(h, p_mpa)


# point_force's last solve, from a converged state: Newton (a root finder proper, so its
# implicit derivative is first order), a few steps at most.
POLISH_SOLVER = optx.Newton(rtol=1e-8, atol=1e-9)
POLISH_STEPS = 8


def _point_state(geom, params, hh, pp, n_steps: int):
    """One scattered point (:func:`_points_kernel`): the path ``pp * k / n_steps`` at
    ``max(hh, LOW_HEIGHT_MM)``, then the plate lowered to ``hh`` when it lies below.
    Returns ``(x, converged, passed a limit point, any state converged, h_at, p_at)``:
    the state and the height / pressure it was solved at (the last good one on a failed
    path)."""
    path = pp * jnp.arange(1, n_steps + 1) / n_steps
    low = hh < LOW_HEIGHT_MM
    h_path = jnp.maximum(hh, LOW_HEIGHT_MM)
    xs, conv, passed = _path(geom, params, h_path, path)
    x, p_at = _last_good(xs, conv, path)
    conv_end = conv[-1]
    x_low, conv_low = _descend(x, geom, params, h_path, hh, pp, active=conv_end & low)
    down = low & conv_end & conv_low
    x = jnp.where(down, x_low, x)
    h_at = jnp.where(down, hh, h_path)
    conv_end = jnp.where(low, down, conv_end)
    return x, conv_end, passed[-1], jnp.any(conv), h_at, p_at


def point_force(design, h_mm, p_pa, params: SimParams, path_steps: int = PATH_STEPS):
    """The simulator's signed plate force [N] at one point, as a pure JAX function of the
    design row ``[t, c, r1, w1, r2, w2]`` mm, the height [mm] and the pressure [Pa]: the
    same path as :func:`force_at` (``path_steps`` pressure steps, the plate lowered below
    ``LOW_HEIGHT_MM``), NaN where it does not converge or passes a pressure limit point.

    For searches that differentiate the simulator itself (forward mode: ``jax.jacfwd``
    or ``jax.jvp`` in the design; the shooting solves are differentiated implicitly), e.g.
    :func:`mfdesign.optimization.simulator_refine`. It skips :func:`force_at`'s stress checks
    (wrinkling, Gent locking): a result it leads to is checked by the simulator proper.
    ``params`` fields must be arrays (:func:`traced_params`), and the caller picks the path
    (:func:`fine_path`: ``STIFF_RING_PATH_REFINE`` times the steps for stiff rings)."""
    geom = sh.geometry_of_array(design)
    p_mpa = jnp.asarray(p_pa, float) * PA_TO_MPA
    h_mm = jnp.asarray(h_mm, float)
    # The path only finds the state: no derivative flows through it. The derivative comes
    # from one Newton solve at the found state (implicit differentiation of a root find
    # needs first derivatives of the residual only; the least-squares solve's own adjoint
    # differentiates the residual twice, which diffrax's step control does not allow).
    x, conv, passed, _, _, _ = _point_state(*jax.lax.stop_gradient((geom, params, h_mm, p_mpa)), path_steps)
    sol = optx.root_find(
        sh.shooting_residual,
        POLISH_SOLVER,
        x,
        (geom, params, h_mm, p_mpa, jnp.asarray(True)),
        max_steps=POLISH_STEPS,
        throw=False,
    )
    x = sol.value
    force = sh.disk_force(sh.segments(geom, params), p_mpa, 1.0 + jnp.exp(x[0]), x[1])
    return jnp.where(conv & ~passed & (sol.result == optx.RESULTS.successful), force, jnp.nan)


@eqx.filter_jit
def _walk_kernel(geom, params, h_mm, p_mpa, x_start, start_ok, restart, secant, report_idx):
    """Continuation walks (:func:`_step`), one per lane (vmapped), through the points
    ``(h_mm, p_mpa)`` ``[lane, step]``, each from ``x_start`` where ``start_ok`` (else from
    the string model), with per-lane ``restart`` and ``secant`` (:func:`_step`); outputs
    at the steps ``report_idx`` ``[lane, report]``.

    One program for a plane's rows (a pressure path at fixed height, restarts and secant
    on) and for its low rows' descent (the plate lowered at fixed pressure from the anchor
    row's states, neither): two kernels compiled ~20 s each on 2 cores in every process
    that solved a plane (issue 40). A failed point is checked at the last converged state
    before it (at that state's height and pressure); where none converged its locking is
    NaN (unknown)."""

    def one(hs, ps, x0, ok0, rs, sc):
        # a descent from no state (its anchor failed) takes no step
        init = _start(x0, jnp.where(ok0, ps[0], 0.0), ok0, ok0 | rs)
        _, (xs, conv, passed) = jax.lax.scan(lambda w, hp: _step(w, hp, geom, params, sc, rs), init, (hs, ps))
        idx = jnp.arange(conv.shape[0])
        last = jax.lax.cummax(jnp.where(conv, idx, 0))[report_idx]
        seen = jax.lax.cummax(conv.astype(int))[report_idx] > 0
        force, wrinkled, locking, rise, ok_prof = jax.vmap(
            lambda x, hh, pa, pp: _point_outputs(x, geom, params, hh, pa, pp)
        )(xs[last], hs[last], ps[last], ps[report_idx])
        locking = jnp.where(seen, locking, jnp.nan)
        return PointSolution(conv[report_idx], passed[report_idx], force, wrinkled, locking, rise, ok_prof, xs[last])

    return jax.vmap(one)(h_mm, p_mpa, x_start, start_ok, restart, secant)


def _lanes_then(value):
    """Pad ``[lane, step]`` arrays: lanes by repeating the last (real points: no new
    failures), steps with ``value`` (NaN pressure: a skipped step)."""

    def pad(a, shape):
        a = np.asarray(a)
        a = np.pad(a, [(0, shape[0] - a.shape[0]), (0, 0)], mode="edge")
        return np.pad(a, [(0, 0), (0, shape[1] - a.shape[1])], constant_values=value)

    return pad


def _walks(geom, params, h_mm, p_mpa, x_start, start_ok, restart: bool, secant: bool, report, parts, most=None):
    """:func:`_walk_kernel` on ``[lane, step]`` points, the lanes split like a plane's rows
    (:func:`_in_parts`, at most ``most`` lanes a call) and each part run on a kept program
    where one fits (:func:`_kept_call`); outputs ``[lane, report]``."""
    n = h_mm.shape[0]
    flags = np.full(n, restart), np.full(n, secant)
    return _in_parts(
        lambda *lanes: _kept_call(
            _walk_kernel,
            (geom, params, *lanes, report),
            {2: _lanes_then(np.nan), 3: _lanes_then(np.nan), 4: _edge, 5: _edge, 6: _edge, 7: _edge, 8: _edge},
            work=lambda s: s[2][0] * (s[2][1] + s[8][0]),
            lead=lambda s: (s[2][0], s[8][0]),
        ),
        h_mm,
        p_mpa,
        x_start,
        start_ok,
        *flags,
        parts=parts,
        most=most,
    )


def _descent_starts(anchor):
    """Start states of the descent, one per grid pressure, from the anchor row (solved at
    ``LOW_HEIGHT_MM``). Where the anchor did not converge (low tension at the lowest
    pressures makes the shooting touchy), its nearest converged state at a higher pressure."""
    conv_a, locking_a, x_a = (np.asarray(o) for o in (anchor.converged, anchor.locking, anchor.state))
    n_p = conv_a.shape[0]
    idx = np.where(conv_a, np.arange(n_p), n_p)
    nxt = np.flip(np.minimum.accumulate(np.flip(idx)))
    return x_a[np.minimum(nxt, n_p - 1)], nxt < n_p, locking_a


# Relative slack of the force bound p pi R^2 (status.force_bound_n): rounding only.
FORCE_BOUND_RTOL = 1e-6


def _classify(h, p, sol: PointSolution, signed: bool = False, outer_radius_mm: float = OUTER_RADIUS_MM) -> SimResult:
    """Status codes and the reported force of every point from what its kernel found."""
    conv, passed, force, wrinkled = sol.converged, sol.passed, sol.force_n, sol.wrinkled
    locking, rise, ok_prof = sol.locking, sol.rise_mm, sol.profile_ok
    h, p = np.broadcast_arrays(np.asarray(h, float), np.asarray(p, float))
    conv, passed, wrinkled, ok_prof = (np.asarray(a, bool) for a in (conv, passed, wrinkled, ok_prof))
    force = np.asarray(force, float).copy()
    locking = np.asarray(locking, float)
    status = np.full(h.shape, int(Status.OK), dtype=np.int8)
    status[~conv] = Status.NOT_CONVERGED
    # The last converged state before the failure was close to locking: the membrane
    # runs into the Gent limit (it would burst) rather than the solver failing.
    status[~conv & np.isfinite(locking) & (locking > 0.9)] = Status.EXTENSION_LIMIT
    status[conv & ~ok_prof] = Status.ODE_FAILURE
    status[passed] = Status.LIMIT_POINT
    # Converged, but more force than p pi R^2: outside the physical model (status.py says
    # why). Never OK, so never a data point of a fit. A signed plane keeps the number (its
    # interpolation needs a smooth surface); its status says the node is outside.
    outside = (status == Status.OK) & (force > force_bound_n(p, outer_radius_mm) * (1 + FORCE_BOUND_RTOL))
    status[outside] = Status.OUTSIDE_MODEL
    usable = status == Status.OK
    no_contact = usable & (force < 0)
    status[no_contact] = Status.NO_CONTACT
    # ``signed``: keep the (negative) force that would hold the plate down at h before the
    # membrane reaches it; unlike the clipped force it is smooth across the contact
    # boundary, so planes of it interpolate to simulator accuracy (clip after interpolating).
    force[no_contact] = force[no_contact] if signed else 0.0
    force[~usable & ~(signed & outside)] = np.nan
    zero_p = np.isfinite(p) & (p == 0) & np.isfinite(h) & (h >= 0)
    status[zero_p] = Status.NO_CONTACT  # no pressure: the membrane lies still
    force[zero_p] = np.nan if signed else 0.0  # signed: unknown (the path starts above 0)
    bad = ~np.isfinite(h) | ~np.isfinite(p) | (h < 0) | (p < 0)
    status[bad] = Status.INVALID_INPUT
    force[bad] = np.nan
    converged = usable & ~zero_p
    return SimResult(
        force_n=force,
        status=status,
        max_locking=np.where(conv | ~converged, locking, np.nan),
        max_rise_mm=np.where(converged, np.asarray(rise, float), np.nan),
        wrinkled=converged & wrinkled,
    )


def _sanitize(h, p):
    """Inputs the kernels can run on (invalid points are classified afterwards)."""
    h = np.asarray(h, float)
    p = np.asarray(p, float)
    ok = np.isfinite(h) & np.isfinite(p) & (h >= 0) & (p > 0)
    return np.where(ok, h, 10.0), np.where(ok, p, 1000.0)


def force_at(
    design: Membrane,
    h_mm,
    p_pa,
    params: SimParams = SimParams(),
    path_steps: int = PATH_STEPS,
    signed: bool = False,
) -> SimResult:
    """Force on a plate held at height ``h_mm`` [mm] with gauge pressure ``p_pa`` [Pa].

    Every point is solved independently by quasi-static inflation in ``path_steps``
    pressure steps at its height (points below 4 mm: inflation at 4 mm, then the plate is
    lowered), all points in one vmapped kernel.

    **Arguments:**

    - `design`: the membrane (:class:`~mfdesign.design.Membrane`).
    - `h_mm`: plate heights [mm], any shape broadcasting with `p_pa`.
    - `p_pa`: gauge pressures [Pa].
    - `params`: simulator constants (:class:`~mfdesign.physics.params.SimParams`; default the
      authors' Ecoflex 00-30).
    - `path_steps`: pressure steps from `p / path_steps` to `p` of each point's path.
    - `signed`: keep the negative force of `NO_CONTACT` points (smooth across the contact
      boundary, for interpolation; see :func:`force_plane`).

    **Returns:**

    A :class:`SimResult` of the broadcast shape: force [N] (NaN where the status is not
    usable, never a silent number), status codes, locking, rise and wrinkling checks.
    """
    enable_x64()  # float64 physics: mfdesign._x64
    return _force_and_state(design, h_mm, p_pa, params, path_steps, signed)[0]


def _force_and_state(
    design: Membrane, h_mm, p_pa, params: SimParams, path_steps: int = PATH_STEPS, signed: bool = False
) -> tuple[SimResult, np.ndarray]:
    """:func:`force_at`'s result and each point's first shooting unknown ``a = log(lambda1 - 1)``
    at the state its path ended in (the last converged one on a failed path; NaN where none):
    :func:`height_at` starts its fixed-force solves from these instead of solving a path again."""
    h, p = np.broadcast_arrays(np.asarray(h_mm, float), np.asarray(p_pa, float))
    shape_ = h.shape
    hs, ps = _sanitize(h.ravel(), p.ravel())
    if hs.size == 0:
        empty = np.zeros(shape_)
        return SimResult(empty, empty.astype(np.int8), empty, empty, empty.astype(bool)), np.full(shape_, np.nan)
    out = _solve_points(design, hs, ps, params, path_steps)
    res = _classify(h.ravel(), p.ravel(), out, signed=signed, outer_radius_mm=design.outer_radius_mm)
    a = np.asarray(out.state, float)[:, 0]
    return jax.tree.map(lambda v: v.reshape(shape_), res), np.where(np.isfinite(a), a, np.nan).reshape(shape_)


def _solve_points(
    design: Membrane, hs: np.ndarray, ps_pa: np.ndarray, params: SimParams, path_steps: int
) -> PointSolution:
    """``_points_kernel`` at sanitised points (NumPy) in batches of :data:`POINTS_BATCH`,
    :func:`n_workers` batches at a time on threads.

    One batch size serves every caller, so a plane's repair (eight nodes) and the lift
    check (63 points) share one compiled program: padded to a power of two, the check
    compiled a 64-lane program of its own (14 s of XLA in a cold quick demo on 2 cores,
    session 33). Small batches also run faster: under ``vmap`` every lane iterates as long
    as the slowest of its batch, and a single call ran on one core (63 points: 1.79 s as
    one call, 0.80 s in batches of eight on two threads)."""
    geom, params_ = sh.geometry_of(design), traced_params(params)
    # as force_plane's path
    n_steps = path_steps * (STIFF_RING_PATH_REFINE if fine_path(params) else 1)

    def kernel(h, p):
        return KEPT(_points_kernel, geom, params_, jnp.asarray(h), jnp.asarray(p) * PA_TO_MPA, static=(n_steps,))

    n = hs.size
    # padded here: for fewer points than a batch in_batches would compile a smaller program
    m = -(-n // POINTS_BATCH) * POINTS_BATCH
    hs, ps_pa = (np.concatenate([a, np.repeat(a[-1:], m - n)]) for a in (hs, ps_pa))
    out = in_batches(kernel, hs, ps_pa, size=POINTS_BATCH, lanes=n_workers())
    return jax.tree.map(lambda o: o[:n], out)


def traced_params(params: SimParams) -> SimParams:
    """``params`` with every field a float64 array: under ``eqx.filter_jit`` a Python float is
    static, so each new value of a constant would compile the kernels again (~10 s each)."""
    return jax.tree.map(lambda a: jnp.asarray(a, float), params)


POINTS_BATCH = 8  # scattered points per compiled call (_solve_points)


def _pad(values: np.ndarray, n: int) -> np.ndarray:
    """Pad a batch to the next power of two (>= 8) by repeating its last entry: each
    batch size is a separate compilation, so a few sizes serve every call."""
    size = max(8, 1 << (n - 1).bit_length())
    return np.concatenate([values, np.repeat(values[-1:], size - n, axis=0)])


# Widest pressure step of a plane's continuation path [Pa]: on a 12 x 12 grid (909 Pa
# steps) thin small-disk membranes lost whole rows above ~4 kPa (the force rises by
# ~30 N per step there); 250 Pa leaves the 50 x 50 grid (204 Pa) as it was.
MAX_PATH_STEP_PA = 250.0
# Rings stiffer than STIFF_RING_RATIO x the modelled ring-to-rubber modulus ratio (the
# authors' 1 MPa over 31.7 kPa) change the solution fast along the path: at 3x, 250 Pa
# steps left 3.6 % of a plane's nodes above 1 kPa unconverged, in a band through the real
# lifts' operating region ([2.0, 25.4, 33.4, 5, 46.4, 5]); a 4x finer path left 0.1 %. The
# band starts below 2x (a diagnosis refit at 1.89x met it), so the lattice's ring nodes
# from 2^(3/4) = 1.68x up take the finer path; those up to 2^(2/4) = 1.41x, which the real
# lifts' calibrations use, keep theirs.
STIFF_RING_RATIO = 1.5
STIFF_RING_PATH_REFINE = 4


def fine_path(params: SimParams) -> bool:
    """Whether a plane of ``params`` is solved on the finer continuation path (stiff rings:
    :data:`STIFF_RING_RATIO`); part of a cached plane's identity (``planes._job_key``)."""
    ref = SimParams()
    return float(params.ring_mu_pa) / float(params.mu_pa) > STIFF_RING_RATIO * ref.ring_mu_pa / ref.mu_pa


PARALLEL_MIN_ROWS = 16  # below this a plane is one batch (splitting would not pay)


def n_workers() -> int:
    """Parallel lanes for plane work: every local JAX device, or every CPU core on a
    single-device CPU (XLA runs one vmapped while-loop on one core, so independent
    batches on several threads use several cores; the GIL is released inside XLA)."""
    devices = jax.local_devices()
    if len(devices) > 1:
        return len(devices)
    return max(1, os.cpu_count() or 1)


def _shard_rows(a: np.ndarray):
    """``a`` on the local devices, split along its leading axis (``jax.sharding``): a jitted
    kernel vmapped over that axis then runs partitioned, one slice per device. On one
    device, the array as it is."""
    devices = jax.local_devices()
    if len(devices) < 2 or a.shape[0] % len(devices):
        return jnp.asarray(a)
    from jax.sharding import Mesh, NamedSharding, PartitionSpec

    mesh = Mesh(np.asarray(devices), ("rows",))
    return jax.device_put(a, NamedSharding(mesh, PartitionSpec("rows")))


def _part_size(n: int, parts: int | None = None) -> int:
    """Lanes of each call :func:`_in_parts` makes for a batch of ``n`` on one CPU device
    (``parts`` slices, default :func:`n_workers`, none below :data:`PARALLEL_MIN_ROWS`)."""
    parts = n_workers() if parts is None else max(1, int(parts))
    parts = min(parts, max(1, n // (PARALLEL_MIN_ROWS // 2)))
    return n if n < PARALLEL_MIN_ROWS or parts < 2 else -(-n // parts)


def _in_parts(kernel, *batch: np.ndarray, parts: int | None = None, most: int | None = None) -> list[np.ndarray]:
    """``kernel(*batch)`` with the batch (leading axis) split over the local devices.

    Several devices: one call, the batch sharded across them (:func:`_shard_rows`). One
    CPU device: ``parts`` slices (default :func:`n_workers`) on as many threads, each of
    at most ``most`` lanes where given (more slices then: a plane's descent runs on its
    rows' program). Every output has the batch's leading axis, and the result equals one
    call on the whole batch. The slices are padded to one length (one compilation)."""
    n = batch[0].shape[0]
    devices = jax.local_devices()
    if len(devices) > 1:
        size = -(-n // len(devices)) * len(devices)
        padded = [np.concatenate([a, np.repeat(a[-1:], size - n, axis=0)]) for a in batch]
        return jax.tree.map(lambda o: np.asarray(o)[:n], kernel(*(_shard_rows(a) for a in padded)))
    size = min(_part_size(n, parts), most or n)
    if size >= n:
        return jax.tree.map(np.asarray, kernel(*batch))
    lanes = n_workers() if parts is None else max(1, int(parts))
    return in_batches(kernel, *batch, size=size, lanes=min(lanes, -(-n // size)))


def in_batches(kernel, *batch: np.ndarray, size: int, lanes: int, bar=None):
    """``kernel(*batch)`` in batches of ``size`` along the leading axis, ``lanes`` at a time
    on threads (XLA releases the GIL). The last batch is padded by repeating the last row,
    so that one compilation serves all; every output is cut back to the batch's length.
    ``bar``: a tqdm bar advanced once a batch."""
    n = batch[0].shape[0]
    size = max(1, min(int(size), n))
    count = -(-n // size)
    padded = [np.concatenate([a, np.repeat(a[-1:], size * count - n, axis=0)]) for a in batch]

    def run(k):
        sl = slice(k * size, (k + 1) * size)
        out = jax.tree.map(np.asarray, kernel(*(a[sl] for a in padded)))
        if bar is not None:
            bar.update(1)
        return out

    lanes = max(1, min(int(lanes), count))
    if lanes == 1:
        chunks = [run(k) for k in range(count)]
    else:
        with ThreadPoolExecutor(lanes) as pool:
            chunks = list(pool.map(run, range(count)))
    return jax.tree.map(lambda *outs: np.concatenate(outs)[:n], *chunks)


def _checked_grid(values, name: str, what: str) -> np.ndarray:
    """A grid argument as a non-empty 1-D float array, else InputError (an empty grid
    reached JAX as a zero-size reduction: a traceback, not a message)."""
    try:
        grid = np.asarray(values, float).ravel()
    except (TypeError, ValueError):
        raise InputError(f"force_plane: {name} is not a list of numbers; allowed: {what}") from None
    if grid.size == 0:
        raise InputError(f"force_plane: {name} is empty; allowed: at least one value ({what})")
    return grid


def force_plane(
    design: Membrane,
    h_grid_mm: Sequence[float],
    p_grid_pa: Sequence[float],
    params: SimParams = SimParams(),
    substeps: int = 1,
    signed: bool = False,
    parts: int | None = None,
) -> SimResult:
    """Force on a ``len(h_grid) x len(p_grid)`` grid of plate heights and pressures.

    Each height is one continuation path through all the pressures (vmapped over heights,
    split over every core or device); heights below 4 mm are reached by lowering the plate
    from 4 mm at each pressure.

    **Arguments:**

    - `design`: the membrane (:class:`~mfdesign.design.Membrane`).
    - `h_grid_mm`: plate heights [mm], any order.
    - `p_grid_pa`: gauge pressures [Pa], strictly increasing.
    - `params`: simulator constants (default the authors' Ecoflex 00-30).
    - `substeps`: continuation steps per grid interval (more where an interval is wider
      than `MAX_PATH_STEP_PA`, a quarter of it for stiff rings: :func:`fine_path`).
    - `signed`: `NO_CONTACT` points keep the negative force that would hold the plate at `h`
      (smooth across the contact boundary, for interpolation; p = 0 is then NaN).
    - `parts`: slices the heights are split into (default: every core or device,
      :func:`n_workers`).

    **Returns:**

    A :class:`SimResult` of shape `(len(h_grid), len(p_grid))`: force [N] (NaN where not
    usable), status codes, locking, rise and wrinkling checks.
    """
    enable_x64()  # float64 physics: mfdesign._x64
    if not isinstance(design, Membrane):
        raise InputError(f"force_plane: design is a {type(design).__name__}; allowed: a Membrane")
    h_grid = _checked_grid(h_grid_mm, "h_grid_mm", "plate heights [mm]")
    p_grid = _checked_grid(p_grid_pa, "p_grid_pa", "gauge pressures [Pa], strictly increasing")
    if p_grid.size and np.any(np.diff(p_grid) <= 0):
        raise InputError("force_plane needs strictly increasing pressures; allowed: p_grid_pa sorted, no repeats")
    path, report = _plane_path(p_grid, substeps, params)
    out = _solve_plane(design, h_grid, path, report, params, parts)
    H, P = np.meshgrid(h_grid, p_grid, indexing="ij")
    return _classify(H, P, out, signed=signed, outer_radius_mm=design.outer_radius_mm)


def _plane_path(p_grid: np.ndarray, substeps: int, params: SimParams) -> tuple[list, list]:
    """:func:`force_plane`'s continuation path [Pa] and the indices on it of the grid's
    pressures: from the first positive pressure / 4 up through every grid pressure with
    ``substeps`` in between, at least enough that no step exceeds :data:`MAX_PATH_STEP_PA`
    (the continuation is a property of the physics, not of how coarse a grid the caller
    asked for). Part of every cached plane's values: a change here changes the planes."""
    p_pos = np.where(p_grid > 0, p_grid, np.nan)
    first = np.nanmin(p_pos) if np.any(p_grid > 0) else 1000.0
    knots = np.concatenate([[first / 4.0], np.where(p_grid > 0, p_grid, first / 4.0)])
    knots = np.maximum.accumulate(knots)
    widest = float(np.max(np.diff(knots))) if knots.size > 1 else 0.0
    max_step = MAX_PATH_STEP_PA / (STIFF_RING_PATH_REFINE if fine_path(params) else 1)
    substeps = max(int(substeps), int(np.ceil(widest / max_step)))
    path, report = [knots[0]], []
    for k in range(1, len(knots)):
        for s in range(1, substeps + 1):
            path.append(knots[k - 1] + (knots[k] - knots[k - 1]) * s / substeps)
        report.append(len(path) - 1)
    return path, report


def _solve_plane(design: Membrane, h_grid: np.ndarray, path_pa, report, params: SimParams, parts) -> PointSolution:
    """The walk kernel's plane rows (and descent below :data:`LOW_HEIGHT_MM`) on the heights
    ``h_grid`` [mm] along the pressure path ``path_pa`` [Pa], reported at the path's indices
    ``report``: a :class:`PointSolution` of shape ``(len(h_grid), len(report))``."""
    hs, _ = _sanitize(h_grid, np.ones_like(h_grid))
    geom = sh.geometry_of(design)
    params = traced_params(params)
    path_mpa, report = jnp.asarray(path_pa, float) * PA_TO_MPA, jnp.asarray(report)
    low = hs < LOW_HEIGHT_MM
    # Rows below LOW_HEIGHT_MM: inflation at LOW_HEIGHT_MM (an extra anchor row), then the
    # plate is lowered at each pressure; they leave the main batch, whose heights then all
    # start from a usable first guess (module constants explain why).
    rows = np.concatenate([hs[~low], [LOW_HEIGHT_MM]]) if low.any() else hs
    n_path = path_mpa.shape[0]
    out = _walks(
        geom,
        params,
        np.repeat(rows[:, None], n_path, axis=1),
        np.broadcast_to(np.asarray(path_mpa), (rows.size, n_path)),
        np.zeros((rows.size, 2)),
        np.zeros(rows.size, bool),
        True,
        True,
        report,
        parts,
    )
    if low.any():
        x_start, start_ok, locking_start = _descent_starts(jax.tree.map(lambda o: o[-1], out))
        p_rep = np.asarray(path_mpa[report])
        low_idx = np.nonzero(low)[0]
        order = low_idx[np.argsort(-hs[low_idx], kind="stable")]  # the plate goes down
        n_low = order.size
        # One lane per pressure (independent: split like the rows, no more lanes a call
        # than the rows' program has), the plate lowered through the low heights from the
        # anchor's state.
        down = _walks(
            geom,
            params,
            np.broadcast_to(hs[order], (p_rep.size, n_low)),
            np.repeat(p_rep[:, None], n_low, axis=1),
            x_start,
            start_ok,
            False,
            False,
            jnp.arange(n_low),
            parts,
            most=_part_size(rows.size, parts),
        )
        # Unsolved: the anchor's state says whether the Gent limit was near.
        locking = np.where(np.asarray(down.converged), np.asarray(down.locking), locking_start[:, None])
        down = dataclasses.replace(down, locking=locking)
        down = jax.tree.map(lambda o: np.swapaxes(o, 0, 1), down)  # (pressure, height) -> (height, pressure)
        down = dataclasses.replace(down, passed=np.broadcast_to(out.passed[-1], down.converged.shape))  # the anchor's

        def merge(o_main, o_low):
            arr = np.empty((hs.size,) + o_main.shape[1:], o_main.dtype)
            arr[~low], arr[order] = o_main[:-1], o_low
            return arr

        out = jax.tree.map(merge, out, down)
    return out


def force_planes(
    jobs: Sequence[tuple[Membrane, SimParams]],
    h_grid_mm: Sequence[float],
    p_grid_pa: Sequence[float],
    signed: bool = False,
    progress: bool = False,
    then: Callable[[tuple[Membrane, SimParams], SimResult], Any] | None = None,
    scheduler: Any = None,
) -> list:
    """:func:`force_plane` of many ``(design, params)`` jobs on one grid, using every local
    core or device (:func:`n_workers`), or the workers of a Dask cluster.

    Arguments:
        jobs: the planes to solve, each a membrane and its simulator constants.
        h_grid_mm: plate heights [mm] (any order).
        p_grid_pa: gauge pressures [Pa], strictly increasing.
        signed: keep the negative force of ``NO_CONTACT`` points (see :func:`force_plane`).
        progress: a tqdm bar over the jobs.
        then: run on each ``(job, SimResult)`` in the same worker as its plane, its value
            returned in the result's place (post-processing such as re-solving unconverged
            nodes: its own compilations then overlap with other workers' planes). On a
            cluster it must pickle (a module-level function or a ``functools.partial`` of one).
        scheduler: a Dask scheduler's address (or a ``distributed.Client``); None: the
            CLI's ``--scheduler``, else ``$MFDESIGN_SCHEDULER``, else this machine; False:
            this machine (:mod:`mfdesign.physics.cluster`).

    Returns one :class:`SimResult` (or ``then``'s value) per job, in order. On a single-device CPU the jobs run
    on one thread per core (each plane in one piece); with several devices each plane's
    heights are sharded across them (``jax.sharding``). On a cluster each task solves
    :data:`~mfdesign.physics.cluster.PLANES_PER_TASK` planes on one core of a worker, with
    the same function as here (``then`` included), and the results come back in order.
    """
    enable_x64()  # float64 physics: mfdesign._x64
    jobs = list(jobs)
    from mfdesign.physics import cluster

    where = cluster.scheduler_from(scheduler)
    if where is not None and jobs:
        task = cluster.on_worker(
            _planes_here, h_grid_mm=h_grid_mm, p_grid_pa=p_grid_pa, signed=signed, then=then, lanes=1
        )
        return cluster.map_chunks(
            where, task, jobs, per_task=cluster.PLANES_PER_TASK, progress=progress, desc="simulator planes"
        )
    return _planes_here(jobs, h_grid_mm, p_grid_pa, signed, progress, then)


def _planes_here(
    jobs: list,
    h_grid_mm: Sequence[float],
    p_grid_pa: Sequence[float],
    signed: bool = False,
    progress: bool = False,
    then: Callable | None = None,
    lanes: int | None = None,
) -> list:
    """:func:`force_planes` on this machine, ``lanes`` planes at a time (default
    :func:`n_workers`); a cluster task runs it on its chunk with one lane."""
    enable_x64()  # float64 physics: mfdesign._x64 (also in a Dask worker)
    workers = n_workers() if lanes is None else max(1, int(lanes))
    if len(jax.local_devices()) > 1 or workers < 2 or len(jobs) < 2:
        it = jobs
        if progress:
            from tqdm.auto import tqdm

            it = tqdm(jobs, desc="simulator planes", unit="plane")
        # ``then`` right after each plane: a caller that stores planes loses none on a crash
        out = []
        for job in it:
            res = force_plane(job[0], h_grid_mm, p_grid_pa, job[1], signed=signed, parts=lanes)
            out.append(res if then is None else then(job, res))
        return out
    bar = None
    if progress:
        from tqdm.auto import tqdm

        bar = tqdm(total=len(jobs), desc="simulator planes", unit="plane")

    def run(job):
        d, prm = job
        res = force_plane(d, h_grid_mm, p_grid_pa, prm, signed=signed, parts=1)
        if then is not None:
            res = then(job, res)
        if bar is not None:
            bar.update(1)
        return res

    with ThreadPoolExecutor(workers) as pool:
        out = list(pool.map(run, jobs))
    if bar is not None:
        bar.close()
    return out


# --------------------------------------------------------------------------------------
# mass lift: height under a load


def _height_residual(a, args):
    """1-D shooting at fixed force: ``phi0`` from the disk balance, ``lambda2(r_out) = s``."""
    geom, params, F, p_mpa = args
    segs = sh.segments(geom, params)
    seg0, r0 = segs.first(), segs.r0
    l1 = 1.0 + jnp.exp(a)
    t0, _ = seg0.thickness(r0)
    sin_phi = (F - p_mpa * jnp.pi * r0**2) / (2.0 * jnp.pi * r0 * t0 * seg0.w1(l1, 1.0))
    ok_sin = jnp.abs(sin_phi) < 1.0
    phi0 = jnp.arcsin(jnp.clip(sin_phi, -0.999999, 0.999999))
    y0 = jnp.stack([l1, 1.0, phi0, 0.0])
    y, ok, _ = sh.integrate(segs, p_mpa, y0)
    res = y[1] - params.clamp_prestretch
    return jnp.where(ok & ok_sin & jnp.isfinite(res), res, sh.FAILED_RESIDUAL), -y[3]


def _height_only(a, args):
    return _height_residual(a, args)[0]


# The fixed-force residual as the root finder sees it: its derivative materialised once
# per iteration (sh.with_materialised_jacobian says why).
_HEIGHT_SHOOTING = sh.with_materialised_jacobian(_height_only)


@eqx.filter_jit
def _height_kernel(geom, params, F, p_mpa, a0):
    def one(ff, pp, aa):
        sol = optx.root_find(
            _HEIGHT_SHOOTING,
            sh.SHOOTING_SOLVER,
            aa,
            (geom, params, ff, pp),
            max_steps=sh.SHOOTING_MAX_STEPS,
            throw=False,
        )
        res, h = _height_residual(sol.value, (geom, params, ff, pp))
        conv = (sol.result == optx.RESULTS.successful) & (jnp.abs(res) < 1e-7)
        return jnp.where(conv, h, jnp.nan), conv

    return jax.vmap(one)(F, p_mpa, a0)


def _lift_forces(res: SimResult, p_pa, outer_radius_mm: float) -> np.ndarray:
    """Forces [N] of ``res`` for a mass lift's crossing: an ``OUTSIDE_MODEL`` node counts
    as ``p pi R^2`` (:func:`~mfdesign.physics.status.force_bound_n`), not as unknown. There
    the converged state pushes harder than that bound (a membrane ballooning past the
    clamp), so the plate is certainly pushed up by any load below the bound. Left NaN,
    such nodes made a gap below the crossing: a thin, large-disk membrane that lifts its
    loads past 100 mm at 6.9 kPa was NOT_CONVERGED at every load (issue 43's paper-design
    optimum)."""
    f = np.asarray(res.force_n, float)
    outside = np.asarray(res.status) == Status.OUTSIDE_MODEL
    return np.where(outside, force_bound_n(p_pa, outer_radius_mm), f)


def _first_crossing(F, p, Fh):
    """Where each load ``F[i]`` is first crossed from above along its row ``Fh[i]`` of
    forces on the height grid (NaN = unsolved). Vectorised bookkeeping for :func:`height_at`.

    Returns ``(height, status, lo_idx, refine)``: ``refine[i]`` when the crossing lies in
    ``[hg[lo_idx], hg[lo_idx + 1]]`` with every height from the first solved one up to it
    solved; ``NOT_LIFTED`` (height 0) when the force at ``h = 0`` is below the load;
    ``INVALID_INPUT`` for a non-finite or negative load or pressure; ``BEYOND_GRID`` (NaN)
    when the force exceeds the load at every height from the first solved one to the top
    of the grid (the plate rises past ``h_max``); ``NOT_CONVERGED`` otherwise. When the lowest heights did not converge (narrow rubber gaps beside stiff
    rings near the Gent limit at h ~ 0), a force above the load at the first solved height
    still shows that the plate is lifted past it.
    """
    n_q, n_h = Fh.shape
    valid = np.isfinite(F) & np.isfinite(p) & (p >= 0) & (F >= 0)
    row_ok = np.isfinite(Fh)
    above = Fh >= F[:, None]
    has_ok = row_ok.any(1)
    start = np.argmax(row_ok, axis=1)
    rows = np.arange(n_q)
    above_start = above[rows, start]
    cols = np.arange(n_h)[None, :]
    below = ~above & row_ok & (cols >= start[:, None])
    has_below = below.any(1)
    j = np.argmax(below, axis=1)
    # Unsolved heights between the first solved one and the crossing: a gap, unknown.
    gaps = np.cumsum(~row_ok, axis=1)
    gap = (gaps[rows, j] - gaps[rows, start]) > 0
    not_lifted = valid & has_ok & ~above_start & (start == 0)
    refine = valid & has_ok & above_start & has_below & ~gap
    # Solved and above the load at every height from the first solved one to the top.
    beyond = valid & has_ok & above_start & ~has_below & (gaps[:, -1] == gaps[rows, start])
    height = np.where(not_lifted, 0.0, np.nan)
    status = np.full(n_q, int(Status.NOT_CONVERGED), dtype=np.int8)
    status[not_lifted] = Status.NOT_LIFTED
    status[beyond] = Status.BEYOND_GRID
    status[refine] = Status.OK
    status[~valid] = Status.INVALID_INPUT
    return height, status, np.where(refine, j - 1, 0), refine


def height_at(
    design: Membrane,
    force_n,
    p_pa,
    params: SimParams = SimParams(),
    h_max_mm: float = 100.0,
    n_heights: int = 41,
) -> tuple[np.ndarray, np.ndarray]:
    """Plate height [mm] when the plate carries ``force_n`` [N] at pressure ``p_pa`` [Pa].

    The branch reached by quasi-static inflation from ``h = 0``: at pressure ``p`` the
    plate rises until the membrane's force at fixed height falls to the load, i.e. the
    first height where ``F(h, p)`` crosses the load from above (found on a height grid,
    one plane at the loads' pressures, then refined by shooting at fixed force). Folds along a pressure
    sweep are reported by :func:`lift_curve`.

    **Arguments:**

    - `design`: the membrane.
    - `force_n`: loads [N] (the lifted weight, plate included), broadcasting with `p_pa`.
    - `p_pa`: gauge pressures [Pa].
    - `params`: simulator constants (default the authors').
    - `h_max_mm`: top of the height grid [mm]; a plate that rises past it is `BEYOND_GRID`.
    - `n_heights`: points of the height grid the crossing is bracketed on.

    **Returns:**

    `(height_mm, status)`: heights [mm] (0 with `NOT_LIFTED` where the force at `h = 0` is
    below the load; NaN with `BEYOND_GRID` past `h_max_mm` or where the solve failed) and
    status codes (:class:`~mfdesign.physics.status.Status`).
    """
    enable_x64()  # float64 physics: mfdesign._x64
    F, p = np.broadcast_arrays(np.asarray(force_n, float), np.asarray(p_pa, float))
    shape_ = F.shape
    F, p = F.ravel(), p.ravel()
    hg = np.linspace(0.0, h_max_mm, n_heights)
    Fh, a_grid = _lift_grid(design, hg, p, params)
    height, status, lo_idx, for_refine = _first_crossing(F, p, Fh)
    _refine_crossings(design, params, F, p, Fh, hg, lo_idx, for_refine, height, status, a_grid)
    return height.reshape(shape_), status.reshape(shape_)


def _lift_path(p_pa: np.ndarray, params: SimParams) -> tuple[np.ndarray, np.ndarray]:
    """:func:`height_at`'s continuation path [Pa] through the pressures ``p_pa`` (positive,
    sorted, unique) and their indices on it: equal steps of at most
    :data:`MAX_PATH_STEP_PA` (a quarter of it for stiff rings, :func:`fine_path`) and at
    most ``p_max / PATH_STEPS``, the pressures merged in. Unlike :func:`_plane_path` the
    step does not grow with the gap below the first pressure: one load pressure of
    6.9 kPa made 22 steps that way, 28 here, which fit the demo's made plane's program
    (35 steps) while the three pressures of a waypoint task would not have."""
    top = float(p_pa[-1])
    step = min(MAX_PATH_STEP_PA / (STIFF_RING_PATH_REFINE if fine_path(params) else 1), top / PATH_STEPS)
    n = int(np.ceil(top / step - 1e-9))
    path = np.union1d(top * np.arange(1, n + 1) / n, p_pa)
    return path, np.searchsorted(path, p_pa)


def _lift_grid(design: Membrane, hg: np.ndarray, p: np.ndarray, params: SimParams) -> tuple[np.ndarray, np.ndarray]:
    """Forces [N] for a mass lift (:func:`_lift_forces`) and first shooting unknowns
    ``a = log(lambda1 - 1)`` (NaN where none) of every query pressure ``p`` [Pa] at every
    height ``hg`` [mm], each ``(p.size, hg.size)``.

    The heights are one plane at the distinct pressures (:func:`_solve_plane`, one
    continuation per height), not a path per (load, height) point: the lift check then
    runs on the walk program a made simulator plane compiled, padded (:func:`_kept_call`),
    instead of compiling the points kernel (~10 s of tracing and XLA on 2 cores in the
    demo's optimum check, issue 40). Nodes the continuation did not converge on are solved
    again point by point (:func:`force_at`'s paths), as a plane's repair does. A
    pressure of 0 is no force (``NO_CONTACT``); a negative or non-finite one NaN."""
    Fh = np.where((p == 0)[:, None] & (hg >= 0)[None, :], 0.0, np.nan)
    a_grid = np.full(Fh.shape, np.nan)
    live = np.isfinite(p) & (p > 0)
    if not live.any():
        return Fh, a_grid
    pu, col = np.unique(p[live], return_inverse=True)
    path, report = _lift_path(pu, params)
    sol = _solve_plane(design, hg, path, report, params, None)
    H, P = np.meshgrid(hg, pu, indexing="ij")
    res = _classify(H, P, sol, outer_radius_mm=design.outer_radius_mm)
    force = _lift_forces(res, P, design.outer_radius_mm)
    a = np.asarray(sol.state, float)[..., 0]
    again = np.isin(res.status, SOLVER_FAILED)
    if again.any():
        res_pt, a_pt = _force_and_state(design, H[again], P[again], params)
        force[again] = _lift_forces(res_pt, P[again], design.outer_radius_mm)
        a[again] = a_pt
    Fh[live], a_grid[live] = force.T[col], np.where(np.isfinite(a), a, np.nan).T[col]
    return Fh, a_grid


def _refine_crossings(design, params, F, p, Fh, hg, lo_idx, refine, height, status, a_grid=None):
    """Crossings bracketed on the height grid: linear interpolation, then shooting at fixed
    force (one batched solve). Writes ``height`` and ``status`` in place.

    The solve starts from the grid states' unknown ``a_grid`` interpolated like the height
    (the bracket's two nodes were solved on the way there). A path solved at the guessed
    height for the start compiled a program of its own for this alone (~18 s of XLA and
    ~4 s of tracing on 2 cores, session 32); it remains for a bracket without states (and for
    ``a_grid`` None: :func:`lift_curve`'s plane keeps none)."""
    idx = np.nonzero(refine)[0]
    if not idx.size:
        return
    j = lo_idx[idx]
    f0, f1 = Fh[idx, j], Fh[idx, j + 1]
    w = (f0 - F[idx]) / np.where(f0 != f1, f0 - f1, 1.0)
    h_guess = hg[j] + w * (hg[j + 1] - hg[j])
    a_grid = np.full(Fh.shape, np.nan) if a_grid is None else a_grid  # a plane keeps no states (lift_curve)
    a_lo, a_hi = a_grid[idx, j], a_grid[idx, j + 1]
    a0 = np.where(
        np.isfinite(a_lo) & np.isfinite(a_hi), a_lo + w * (a_hi - a_lo), np.where(np.isfinite(a_lo), a_lo, a_hi)
    )
    lost = ~np.isfinite(a0)
    if lost.any():
        a0[lost] = _a_guess(design, params, h_guess[lost], p[idx][lost])
    geom = sh.geometry_of(design)
    params = traced_params(params)
    m = idx.size
    h_ref, conv = KEPT(
        _height_kernel,
        geom,
        params,
        jnp.asarray(_pad(F[idx], m)),
        jnp.asarray(_pad(p[idx], m)) * PA_TO_MPA,
        jnp.asarray(_pad(a0, m)),
    )
    h_ref, conv = np.asarray(h_ref)[:m], np.asarray(conv)[:m]
    good = conv & (np.abs(h_ref - h_guess) < 2.0 * (hg[1] - hg[0]))
    height[idx] = np.where(good, h_ref, np.nan)
    status[idx] = np.where(good, status[idx], Status.NOT_CONVERGED)


def lift_curve(
    design: Membrane,
    force_n: float,
    p_grid_pa: Sequence[float],
    params: SimParams = SimParams(),
    h_max_mm: float = 100.0,
    n_heights: int = 41,
) -> tuple[np.ndarray, np.ndarray]:
    """Lift height [mm] of a plate carrying ``force_n`` [N] along increasing pressures
    ``p_grid_pa`` [Pa] (the mass-lift experiment), with snap-through flagged.

    The plane ``F(h, p)`` on ``n_heights`` heights is solved by continuation
    (:func:`force_plane`); at each pressure the plate sits at the first crossing of the
    load from above (as in :func:`height_at`), refined by shooting at fixed force. A fold
    of the ``p``-``h`` relation at fixed load shows in the plane as a row that, beyond the
    first crossing, rises above the load again: a slightly higher pressure pushes the first
    crossing past the dip and the plate jumps to the far branch. The pressure where the
    quasi-statically followed height jumps across such a dip gets ``SNAP_THROUGH`` (its
    height is the far branch's). Returns ``(height_mm, status)`` per pressure.
    """
    enable_x64()  # float64 physics: mfdesign._x64
    p = np.asarray(p_grid_pa, float).ravel()
    if not (np.isfinite(force_n) and force_n >= 0):
        raise ValueError(f"force_n must be a finite load >= 0 N, got {force_n}")
    hg = np.linspace(0.0, h_max_mm, n_heights)
    P = np.broadcast_to(p[None, :], (hg.size, p.size))
    Fh = _lift_forces(force_plane(design, hg, p, params), P, design.outer_radius_mm).T  # [pressures, heights]
    F = np.full(p.size, float(force_n))
    height, status, lo_idx, refine = _first_crossing(F, p, Fh)
    _refine_crossings(design, params, F, p, Fh, hg, lo_idx, refine, height, status)
    # Rows whose force re-rises above the load after the first crossing (a dip): the
    # plate there sits on the near branch; when at the next pressure it sits beyond the
    # dip's far end, it snapped through.
    above = Fh >= F[:, None]
    cols = np.arange(hg.size)[None, :]
    past_first = cols > lo_idx[:, None] + 1
    re_rise = refine & (above & past_first & np.isfinite(Fh)).any(1)
    far_end = np.where(re_rise, hg[np.argmax(above & past_first, axis=1)], np.inf)
    snapped = np.zeros(p.size, bool)
    snapped[1:] = re_rise[:-1] & (status[1:] == Status.OK) & (height[1:] >= far_end[:-1])
    status[snapped] = Status.SNAP_THROUGH
    return height, status


def _final_state(geom, params, h, p_mpa):
    """Shooting unknowns at ``(h, p)`` after quasi-static inflation in ``PATH_STEPS``
    steps (the warm start for the fixed-force solve and the state :func:`shape` draws);
    below ``LOW_HEIGHT_MM`` inflation at that height, then the plate is lowered (for
    ``h >= LOW_HEIGHT_MM`` the descent has zero length and returns the state unchanged)."""
    path = p_mpa * jnp.arange(1, PATH_STEPS + 1) / PATH_STEPS
    h_path = jnp.maximum(h, LOW_HEIGHT_MM)
    xs, _, _ = _path(geom, params, h_path, path)
    x, conv = _descend(xs[-1], geom, params, h_path, h, p_mpa)
    return jnp.where(conv, x, xs[-1])


@eqx.filter_jit
def _profiles(states, geom, params, h, p_mpa, n_save: int):
    """:func:`~mfdesign.physics.shooting.profile` of every point in one vmapped program
    (``n_save`` is static: the saved points per segment fix the output's shape)."""
    return jax.vmap(lambda x, hh, pp: sh.profile(x, geom, params, hh, pp, n_save=n_save))(states, h, p_mpa)


@eqx.filter_jit
def _a_kernel(geom, params, h, p_mpa):
    return jax.vmap(lambda hh, pp: _final_state(geom, params, hh, pp)[0])(h, p_mpa)


def _a_guess(design, params, h, p):
    geom = sh.geometry_of(design)
    params = traced_params(params)
    n = np.size(h)
    h, p = _pad(np.asarray(h, float), n), _pad(np.asarray(p, float), n)
    a = np.asarray(_a_kernel(geom, params, jnp.asarray(h), jnp.asarray(p) * PA_TO_MPA))[:n]
    return np.where(np.isfinite(a), a, 0.0)


# --------------------------------------------------------------------------------------
# shape


class Shape(eqx.Module):
    """Deformed meridian of one solution: reference radius ``r_mm`` -> ``R_mm``, ``Z_mm``,
    stretches, the meridian's angle above the horizontal ``phi_rad`` and the principal
    tensions per unit deformed length [N/mm]."""

    r_mm: np.ndarray
    R_mm: np.ndarray
    Z_mm: np.ndarray
    lambda1: np.ndarray
    lambda2: np.ndarray
    phi_rad: np.ndarray
    tension1_n_per_mm: np.ndarray
    tension2_n_per_mm: np.ndarray
    force_n: float | np.ndarray
    status: int | np.ndarray


def shape(design: Membrane, h_mm, p_pa, params: SimParams = SimParams(), n_per_segment: int = 64) -> Shape:
    """The deformed membrane at plate height ``h_mm`` [mm] and pressure ``p_pa`` [Pa].

    Scalars give one profile. Arrays (broadcast together) give one profile per point, all
    solved and integrated in one vmapped call: every field then gains the points' leading
    axes (``force_n`` and ``status`` become arrays of the points' shape).
    """
    enable_x64()  # float64 physics: mfdesign._x64
    h, p = np.broadcast_arrays(np.asarray(h_mm, float), np.asarray(p_pa, float))
    hf, pf = h.ravel(), p.ravel()
    k = hf.size
    # The scattered-point kernel gives the state too: one compiled program, shared with
    # force_at and the plane repairs (a separate state kernel cost a cold
    # diagnosis two more compilations).
    out = _solve_points(design, *_sanitize(hf, pf), params, PATH_STEPS)
    res = _classify(hf, pf, out)
    geom = sh.geometry_of(design)
    traced = traced_params(params)
    r, y, w1, w2, _, _ = _profiles(
        jnp.asarray(_pad(out.state, k)),
        geom,
        traced,
        jnp.asarray(_pad(hf, k)),
        jnp.asarray(_pad(pf, k)) * PA_TO_MPA,
        n_per_segment,
    )
    segs = sh.segments(geom, traced)
    t = np.asarray(jnp.repeat(segs.seg.t_mm, n_per_segment))
    n = sh.n_segments(design.n_rings) * n_per_segment  # unused ring slots: repeats at the clamp
    t = t[:n]
    lead = h.shape  # the points' shape: () for one point
    # the k points of the padded batch, their n saved points, then the points' shape
    r, y, w1, w2 = (np.asarray(a)[:k, :n].reshape(lead + (n,) + a.shape[2:]) for a in (r, y, w1, w2))
    return Shape(
        r_mm=r,
        R_mm=r * y[..., 1],
        Z_mm=y[..., 3],
        lambda1=y[..., 0],
        lambda2=y[..., 1],
        phi_rad=y[..., 2],
        tension1_n_per_mm=t * w1 / y[..., 1],
        tension2_n_per_mm=t * w2 / y[..., 0],
        force_n=float(res.force_n[0]) if h.ndim == 0 else np.asarray(res.force_n).reshape(lead),
        status=int(res.status[0]) if h.ndim == 0 else np.asarray(res.status).reshape(lead),
    )
