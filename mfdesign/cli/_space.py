"""Design-space bounds from the command line, shared by ``propose`` and ``optimize``.

``--thickness-mm LO HI``, ``--contact-radius-mm LO HI`` and ``--half-width-mm LO HI``
(mm) narrow the product's design space; ``LO == HI`` fixes that feature (e.g. the lab
has only 2 mm sheet). Bounds outside the product's space are refused unless
``--allow-outside-design-space``, which allows the wider research range
(:func:`mfdesign.workflows.space.design_space` checks them).
"""

from __future__ import annotations

import typer

# Declared once; both commands take them. None: the product's bounds.
THICKNESS = typer.Option(None, "--thickness-mm", help="Thickness bounds LO HI [mm] (LO = HI fixes it). Default: 1 3.")
CONTACT_RADIUS = typer.Option(
    None, "--contact-radius-mm", help="Contact-disk radius bounds LO HI [mm] (LO = HI fixes it). Default: 25.4 38.1."
)
HALF_WIDTH = typer.Option(
    None, "--half-width-mm", help="Ring half-width bounds LO HI [mm] (LO = HI fixes it). Default: 5 13."
)
