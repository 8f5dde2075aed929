"""The one HTML writer: Jinja templates (package data under ``mfdesign/report/templates``).

Every page extends ``base.html.j2`` (the page shell, the style sheet and the picture check
below) and fills its ``body`` block; ``_macros.html.j2`` draws tables and pictures the same
way on every page. Autoescaping is always on, so text from data (effect names, design keys,
words a diagnosis writes) cannot break the page, and undefined names are errors, so a
template that asks for something its caller did not pass fails loudly instead of leaving a
hole.

Pictures are PNG files beside the page, linked by relative path (the folder can be zipped,
mailed or served). ``base.html.j2`` carries a three-line script that counts images that
failed to load into ``<body data-broken-images="n" data-images="m">``: a headless browser
test reads it back (``--dump-dom``) to prove that no picture is broken.
"""

from __future__ import annotations

import functools
import os
from pathlib import Path
from typing import Any

import jinja2

from mfdesign import outputs  # atomic writes: a reader never sees a torn file

__all__ = ["cell", "environment", "render", "write_html"]


def cell(v: Any) -> str:
    """A value as a table cell or in a sentence: floats to 4 significant digits, dicts as
    ``k = v, ...``, sequences comma-separated, None empty (escaping is the template's job)."""
    if isinstance(v, float):
        return f"{v:.4g}"
    if isinstance(v, dict):
        return ", ".join(f"{k} = {cell(x)}" for k, x in v.items())
    if isinstance(v, (list, tuple)):
        return ", ".join(cell(x) for x in v)
    return "" if v is None else str(v)


@functools.cache
def environment() -> jinja2.Environment:
    """The templates' environment (built once: Jinja caches compiled templates in it)."""
    env = jinja2.Environment(
        loader=jinja2.PackageLoader("mfdesign.report", "templates"),
        autoescape=True,
        undefined=jinja2.StrictUndefined,
        trim_blocks=True,
        lstrip_blocks=True,
        keep_trailing_newline=True,
    )
    env.filters["cell"] = cell
    env.filters["relpath"] = os.path.relpath  # pictures are linked relative to the page
    return env


def render(template: str, **context: Any) -> str:
    """The page ``template`` (a file name under ``templates/``) filled with ``context``."""
    return environment().get_template(template).render(**context)


def write_html(path: str | os.PathLike, template: str, **context: Any) -> Path:
    """Render ``template`` with ``context`` and write it atomically to ``path``; returns the path."""
    path = Path(path)
    outputs.write_text(path, render(template, **context))
    return path
