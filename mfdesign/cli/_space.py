"""Design-space bounds from the command line, shared by ``propose`` and ``optimize``.

``--thickness-mm LO HI``, ``--contact-radius-mm LO HI`` and ``--half-width-mm LO HI``
(mm) narrow the product's design space; ``LO == HI`` fixes that feature (e.g. the lab
has only 2 mm sheet). Bounds outside the product's space are refused unless
``--allow-outside-design-space``, which allows the wider research range.
"""

from __future__ import annotations

import math
from typing import Any

import typer

# Declared once; both commands take them. None: the product's bounds.
THICKNESS = typer.Option(None, "--thickness-mm", help="Thickness bounds LO HI [mm] (LO = HI fixes it). Default: 1 3.")
CONTACT_RADIUS = typer.Option(
    None, "--contact-radius-mm", help="Contact-disk radius bounds LO HI [mm] (LO = HI fixes it). Default: 25.4 38.1."
)
HALF_WIDTH = typer.Option(
    None, "--half-width-mm", help="Ring half-width bounds LO HI [mm] (LO = HI fixes it). Default: 5 13."
)


def design_space(thickness, contact_radius, half_width, allow_outside: bool = False):
    """The :class:`~mfdesign.design.DesignSpace` the options describe; exits with one line
    (status 2) naming the option and the allowed range when a bound is bad."""
    from mfdesign.cli._app import fail
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
            fail(f"{option} takes LO HI with LO <= HI (LO = HI fixes it), got {lo:g} {hi:g}")
        if lo < a or hi > b:
            widen = "" if allow_outside else f" ({WIDEN_OPTION} widens it to {getattr(RESEARCH_SPACE, field)})"
            fail(f"{option} {lo:g} {hi:g} is outside the allowed {a:g}-{b:g} mm{widen}")
        bounds[field] = (lo, hi)
    try:
        return DesignSpace(**bounds)
    except DesignError as err:
        fail(f"the design-space bounds do not fit: {err}")
