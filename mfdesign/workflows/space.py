"""Design-space bounds as the commands take them (``propose``, ``optimize``).

``thickness_mm``, ``contact_radius_mm`` and ``half_width_mm`` (each ``(LO, HI)`` in mm, or
None for the product's bounds) narrow the product's design space; ``LO == HI`` fixes that
feature (e.g. the lab has only 2 mm sheet). Bounds outside the product's space are refused
unless ``allow_outside``, which allows the wider research range.
"""

from __future__ import annotations

import math
from typing import Any

from mfdesign.errors import InputError

__all__ = ["design_space"]


def design_space(
    thickness: tuple[float, float] | None,
    contact_radius: tuple[float, float] | None,
    half_width: tuple[float, float] | None,
    allow_outside: bool = False,
) -> Any:
    """The :class:`~mfdesign.design.DesignSpace` the bounds describe.

    Arguments:
        thickness: thickness bounds ``(LO, HI)`` [mm]; None: the product's (1-3 mm).
        contact_radius: contact-disk radius bounds [mm]; None: the product's (25.4-38.1 mm).
        half_width: ring half-width bounds [mm]; None: the product's (5-13 mm).
        allow_outside: allow bounds up to the wider research range.

    Raises :class:`~mfdesign.errors.InputError` (one line naming the option and the
    allowed range) when a bound is bad."""
    from mfdesign.design import PRODUCT_SPACE, RESEARCH_SPACE, WIDEN_OPTION, DesignError, DesignSpace

    outer = RESEARCH_SPACE if allow_outside else PRODUCT_SPACE
    bounds: dict[str, Any] = {}
    for option, field, given in (
        ("--thickness-mm", "thickness_mm", thickness),
        ("--contact-radius-mm", "contact_radius_mm", contact_radius),
        ("--half-width-mm", "half_width_mm", half_width),
    ):
        if given is None:
            continue
        lo, hi = (float(v) for v in given)
        a, b = getattr(outer, field)
        if not (math.isfinite(lo) and math.isfinite(hi)) or lo > hi:
            raise InputError(f"{option} takes LO HI with LO <= HI (LO = HI fixes it), got {lo:g} {hi:g}")
        if lo < a or hi > b:
            widen = "" if allow_outside else f" ({WIDEN_OPTION} widens it to {getattr(RESEARCH_SPACE, field)})"
            raise InputError(f"{option} {lo:g} {hi:g} is outside the allowed {a:g}-{b:g} mm{widen}")
        bounds[field] = (lo, hi)
    try:
        return DesignSpace(**bounds)
    except DesignError as err:
        raise InputError(f"the design-space bounds do not fit: {err}") from None
