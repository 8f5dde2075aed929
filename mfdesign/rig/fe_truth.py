"""The finite-element reference as the virtual rig's truth: ``VirtualRig(simulator=fe_plane())``.

Diagnosis runs on the shooting solver's planes (the exact model). A sweep whose truth is
the same solver proves only the logic; the FE reference (:mod:`mfdesign.physics.fe`)
discretises the energy instead of the equilibrium ODEs and shares no code with it, so
data made with it test the diagnosis on physics it did not make (the two agree to about
1e-3 N where both converge: docs/physics.md).

The adapter returns the :class:`~mfdesign.physics.solve.SimResult` the rig reads: the
force (0 and ``NO_CONTACT`` where the membrane does not reach the plate, NaN and
``NOT_CONVERGED`` where the FE minimiser did not converge, NaN and ``OUTSIDE_MODEL`` above
``p pi R^2`` as the simulator), the Gent locking measure
``(I1 - 3) / J_m`` of the most stretched rubber element (the rig's burst model) and the
membrane's rise above the plate ``max Z - h`` [mm] (the rig ends ringless force trials
at ``ringless_contact_rise_mm``).
"""

from __future__ import annotations

from dataclasses import dataclass

import numpy as np

from mfdesign.design import Membrane
from mfdesign.physics.params import SimParams
from mfdesign.physics.status import Status

__all__ = ["fe_plane"]


@dataclass(frozen=True)
class fe_plane:  # noqa: N801 -- used like a function: VirtualRig(simulator=fe_plane())
    """``(design, h_grid [mm], p_grid [Pa], params) -> SimResult`` by the FE reference.

    ``n_elements``: elements along r (300 agrees with 400 to ~1e-3 N on the rig's
    membranes and costs less); ``n_steps``: pressure increments of each point's path.
    The repr is the rig's plane-cache key, so it names every setting.
    """

    n_elements: int = 300
    n_steps: int = 8

    def __repr__(self) -> str:
        # "outside model": points above p pi R^2 are not readings (the cache key changes with it)
        return f"fe_plane(n_elements={self.n_elements}, n_steps={self.n_steps}, outside model)"

    def __call__(self, design: Membrane, h_grid, p_grid, params: SimParams = SimParams()):
        from mfdesign.physics.fe import fe_forces
        from mfdesign.physics.solve import SimResult

        H, P = np.meshgrid(np.asarray(h_grid, float), np.asarray(p_grid, float), indexing="ij")
        res = fe_forces([(design, params)], [H], [P], n_elements=self.n_elements, n_steps=self.n_steps)[0]
        f = np.asarray(res.force_n, float)
        conv = np.asarray(res.converged, bool) & np.isfinite(f)
        R, Z, r = (np.asarray(a, float) for a in (res.R_mm, res.Z_mm, res.r_mm))
        # Gent locking of the rubber: meridional stretch per element, hoop stretch at its
        # middle; the rings (fabric) burst nothing, so the rubber's J_m is the measure's scale.
        dr = np.diff(r, axis=-1)
        l1 = np.hypot(np.diff(R, axis=-1), np.diff(Z, axis=-1)) / dr
        l2 = 0.5 * (R[..., 1:] + R[..., :-1]) / (0.5 * (r[..., 1:] + r[..., :-1]))
        i1 = l1**2 + l2**2 + 1.0 / np.maximum(l1 * l2, 1e-12) ** 2
        locking = np.max((i1 - 3.0) / float(params.rubber.jm), axis=-1)
        rise = np.max(Z, axis=-1) - H
        status = np.where(conv, np.where(f < 0, int(Status.NO_CONTACT), int(Status.OK)), int(Status.NOT_CONVERGED))
        # as the simulator: a force above p pi R^2 (the membrane dips below the clamp plane)
        # is outside the physical model, never a reading (Status.OUTSIDE_MODEL)
        outside = conv & ~np.asarray(res.inside_model, bool) & (f >= 0)
        status = np.where(outside, int(Status.OUTSIDE_MODEL), status)
        conv = conv & ~outside
        return SimResult(
            force_n=np.where(conv, np.maximum(f, 0.0), np.nan),
            status=status.astype(np.int8),
            max_locking=np.where(conv, locking, np.nan),
            max_rise_mm=np.where(conv, rise, np.nan),
            wrinkled=np.zeros(H.shape, bool),
        )
