"""A cheap, differentiable stand-in for the simulator (tests, CI, tutorials): no physics.

Same call signature as the emulator (``mfdesign.models.emulator``), so every calibration
code path runs in milliseconds::

    force_model(design [N, 6] mm, h_mm [N], p_pa [N], params: SimParams) -> F [N] N

with ``params`` fields scalar or ``[N]``. The force is shaped like the real planes (zero
until the membrane reaches the plate, then rising and stiffening with pressure)::

    s      = mu t tf / (31.7 kPa * 1 mm)                     membrane stiffness scale
    p_c    = 40 Pa/mm * s * h * (1 + 0.4 n_rings)            contact pressure [Pa]
    p_lock = 250 Pa * J_m * s                                Gent-like stiffening scale [Pa]
    F      = 1.6 pi (c + dc)^2 * w softplus((p - p_c) / w) * (1 + p / p_lock),  w = 50 Pa

(c the disk radius [m], dc the contact offset). It depends on J_m, so both Gent
constants are identifiable (mu through the height dependence, J_m through the curvature in
p).
:func:`standin_plane` wraps it as a ``simulator`` for :class:`~mfdesign.rig.virtual.VirtualRig`.
"""

from __future__ import annotations

import dataclasses

import jax
import jax.numpy as jnp
import numpy as np

from mfdesign._x64 import enable_x64
from mfdesign.models.force import ForceModel
from mfdesign.physics.params import SimParams
from mfdesign.physics.solve import SimResult
from mfdesign.physics.status import Status
from mfdesign.materials import ECOFLEX_MU_PA

__all__ = ["RING_COEFFICIENT", "StandinForceModel", "StandinWorld", "standin_force", "standin_plane"]

_W_PA = 50.0
# How much each fabric ring raises the contact pressure (module doc). The model's value;
# a world may differ (:class:`StandinWorld`), and no effect reaches it.
RING_COEFFICIENT = 0.4


def _formula(xp, softplus, design, h_mm, p_pa, params: SimParams, ring_coefficient: float = RING_COEFFICIENT):
    """The module doc's formula in the array namespace ``xp`` (jax.numpy or numpy)."""
    n_rings = (~xp.isnan(design[:, 2])).astype(float) + (~xp.isnan(design[:, 4])).astype(float)
    stiff = params.mu_pa * design[:, 0] * params.thickness_factor / ECOFLEX_MU_PA
    p_c = 40.0 * stiff * h_mm * (1.0 + ring_coefficient * n_rings)
    p_lock = 250.0 * params.jm * stiff
    r_m = (design[:, 1] + params.contact_offset_mm - params.fabric_inset_mm) * 1e-3
    push = _W_PA * softplus((p_pa - p_c) / _W_PA)
    return 1.6 * xp.pi * r_m**2 * push * (1.0 + p_pa / p_lock), p_lock


def standin_force(design, h_mm, p_pa, params: SimParams = SimParams()) -> jax.Array:
    """Stand-in force [N] at rows ``design`` [N, 6] (mm), ``h_mm`` [N], ``p_pa`` [N] (module doc)."""
    enable_x64()  # float64 physics: mfdesign._x64
    design, h_mm, p_pa = (jnp.asarray(a, float) for a in (design, h_mm, p_pa))
    return _formula(jnp, jax.nn.softplus, design, h_mm, p_pa, params)[0]


def standin_plane(design, h_grid, p_grid, params: SimParams = SimParams(), ring_coefficient: float = RING_COEFFICIENT):
    """:func:`standin_force` on ``h_grid x p_grid`` in the ``force_plane`` result layout
    (NumPy: the virtual rig calls it with many shapes, where JAX would compile each).

    Locking ``0.9 (p / 8 kPa)^1.5 / sqrt(s) (1 + 0.15 n_rings)`` reaches a burst threshold of
    ~0.9 only near the ringed membranes' pressure limits; ``rise = p / 250 - h / 2`` mm ends
    ringless force trials at the rig's contact limit. ``ring_coefficient``: each ring's
    rise of the contact pressure (the model's :data:`RING_COEFFICIENT`; a world of its own:
    :class:`StandinWorld`).
    """
    enable_x64()  # float64 physics: mfdesign._x64
    H, P = np.meshgrid(np.asarray(h_grid, float), np.asarray(p_grid, float), indexing="ij")
    d = np.broadcast_to(np.asarray(design.to_array(), float), (H.size, 6))
    params = jax.tree.map(lambda a: np.asarray(a, float), params)
    f, _ = _formula(np, lambda x: np.logaddexp(0.0, x), d, H.ravel(), P.ravel(), params, ring_coefficient)
    stiff = float(params.mu_pa) * design.thickness_mm * float(params.thickness_factor) / ECOFLEX_MU_PA
    locking = 0.9 * (P / 8000.0) ** 1.5 / stiff**0.5 * (1.0 + 0.15 * design.n_rings)
    status = np.full(H.shape, int(Status.OK), np.int8)
    return SimResult(
        force_n=f.reshape(H.shape),
        status=status,
        max_locking=locking.reshape(H.shape),
        max_rise_mm=P / 250.0 - H / 2.0,
        wrinkled=np.zeros(H.shape, bool),
    )


@dataclasses.dataclass(frozen=True)
class StandinWorld:
    """A stand-in world the stand-in model does not hold: its rings raise the contact
    pressure by ``ring_coefficient`` each, where the model says :data:`RING_COEFFICIENT`.
    No effect of the library reaches that coefficient, so a campaign in this world keeps a
    ring-dependent misfit: a test of whether its rounds learn what the physics cannot hold
    (``experiments/campaign_rounds.py --world stiff-rings``, issue 41; measured: they did not,
    the calibration carried part of the misfit to ringless membranes, docs/campaign.md). A
    plane solver for :class:`~mfdesign.rig.virtual.VirtualRig` (its repr is the rig's
    plane-cache key)."""

    ring_coefficient: float = 0.65

    def __repr__(self) -> str:
        return f"StandinWorld(ring_coefficient={self.ring_coefficient!r})"

    def __call__(self, design, h_grid, p_grid, params: SimParams = SimParams()):
        return standin_plane(design, h_grid, p_grid, params, self.ring_coefficient)


class StandinForceModel(ForceModel):
    """:func:`standin_force` behind the force-model interface (fast tests, no physics)."""

    name = "standin"

    def __call__(self, design, h_mm, p_pa, params: SimParams = SimParams()):
        return standin_force(design, h_mm, p_pa, params)
