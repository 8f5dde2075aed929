"""Per-point outcome of a simulation: every number the simulator returns comes with one.

A point that is not ``OK`` or ``NO_CONTACT`` carries NaN: the simulator never returns a
number it could not vouch for.
"""

from __future__ import annotations

import enum

import numpy as np


class Status(enum.IntEnum):
    OK = 0  # converged, membrane pushes the plate
    NO_CONTACT = 1  # the inflating membrane has not reached the plate: F = 0
    NOT_CONVERGED = 2  # shooting did not converge
    EXTENSION_LIMIT = 3  # the Gent chains lock (I1 - 3 -> J_m): the membrane bursts first
    LIMIT_POINT = 4  # past a pressure limit point at this height (snap-through)
    ODE_FAILURE = 5  # the ODE could not be integrated (non-physical state)
    INVALID_INPUT = 7  # negative or non-finite height or pressure
    NOT_LIFTED = 8  # mass-lift: the membrane's force at h = 0 is below the load, h = 0
    SNAP_THROUGH = 9  # mass-lift: the quasi-static branch jumped over a fold to reach h
    BEYOND_GRID = 10  # mass-lift: force above the load at every height up to h_max: h > h_max
    OUTSIDE_MODEL = 11  # converged, but F > p pi R^2: the membrane dips below the clamp plane

    @property
    def reason(self) -> str:
        return _REASONS[self]


# The simulator failed at a point that has a solution (the others that are not usable,
# EXTENSION_LIMIT and LIMIT_POINT, are the physics saying "no such state"): what a
# caller may solve again another way.
SOLVER_FAILED = (Status.NOT_CONVERGED, Status.ODE_FAILURE)

_REASONS = {
    Status.OK: "converged",
    Status.NO_CONTACT: "membrane below the plate: no contact, force 0",
    Status.NOT_CONVERGED: "shooting did not converge",
    Status.EXTENSION_LIMIT: "Gent extension limit reached (the membrane would burst)",
    Status.LIMIT_POINT: "beyond a pressure limit point at this height (snap-through)",
    Status.ODE_FAILURE: "the equilibrium ODE could not be integrated",
    Status.INVALID_INPUT: "height and pressure must be finite and >= 0",
    Status.NOT_LIFTED: "the membrane cannot lift the load at this pressure: h = 0",
    Status.SNAP_THROUGH: "reached by snap-through over a fold of the p-h curve",
    Status.BEYOND_GRID: "the membrane carries the load past the highest height solved (h > h_max_mm)",
    Status.OUTSIDE_MODEL: (
        "force above p pi R^2 (R the clamp radius): the membrane leaves the clamp heading "
        "below the clamp plane, outside the physical model"
    ),
}


def force_bound_n(p_pa, outer_radius_mm: float):
    """The most force a membrane clamped at ``outer_radius_mm`` can put on the plate at
    gauge pressure ``p_pa``: ``p pi R^2`` [N].

    Why it bounds: the plate and the membrane enclose the air; the plate's force is the
    pressure on the area the membrane covers, less the membrane's pull. While the membrane
    stays inside the clamp radius and above the clamp plane that area is at most pi R^2, so
    a larger force means a state the rig cannot hold (seen: 208 N against 154 N at 10 kPa,
    the membrane ballooning to R ~ 119 mm)."""
    return np.asarray(p_pa, float) * 1e-6 * np.pi * float(outer_radius_mm) ** 2


VALID = (Status.OK, Status.NO_CONTACT, Status.NOT_LIFTED, Status.SNAP_THROUGH)


def is_valid(status) -> np.ndarray:
    """Boolean mask of points whose value can be used."""
    s = np.asarray(status)
    return np.isin(s, [int(v) for v in VALID])


def summarize(status) -> dict[str, int]:
    """Count of each status name in an array of codes."""
    s = np.asarray(status).ravel()
    return {Status(int(k)).name: int((s == k).sum()) for k in np.unique(s)}
