"""A report of titled sections (text, a table, pictures): the demo's report.

:meth:`Report.write` renders one ``index.html`` (template ``sections.html.j2``, through
:func:`mfdesign.report.render.write_html`) beside its PNGs, linked by relative path, and a
``report.json`` with the same content as data.
"""

from __future__ import annotations

import datetime as _dt
import json
import os
from dataclasses import dataclass, field
from pathlib import Path
from typing import Sequence

from mfdesign import outputs  # atomic writes: a reader never sees a torn file
from mfdesign.report.render import write_html

__all__ = ["Report", "Section"]


@dataclass
class Section:
    """One titled part of the report: paragraphs, an optional table, pictures (paths)."""

    title: str
    paragraphs: list[str] = field(default_factory=list)
    table: list[dict] | None = None
    images: list[tuple[str, str]] = field(default_factory=list)  # (path, caption)
    data: dict = field(default_factory=dict)


@dataclass
class Report:
    """Collects sections; :meth:`write` renders ``index.html`` and ``report.json``.

    ``banners``: warnings shown in red above everything else (a chain that has not
    converged, a model far above the noise floor): what a reader must know before
    trusting any number below."""

    title: str
    summary: list[str] = field(default_factory=list)
    sections: list[Section] = field(default_factory=list)
    meta: dict = field(default_factory=dict)
    banners: list[str] = field(default_factory=list)

    def add(
        self,
        title: str,
        paragraphs: Sequence[str] = (),
        table: list[dict] | None = None,
        images: Sequence[tuple[str | Path, str]] = (),
        data: dict | None = None,
    ) -> Section:
        missing = [str(p) for p, _ in images if not Path(p).is_file()]
        if missing:
            raise FileNotFoundError(f"report section {title!r}: picture(s) not found: {', '.join(missing)}")
        s = Section(title, list(paragraphs), table, [(str(p), c) for p, c in images], dict(data or {}))
        self.sections.append(s)
        return s

    def write(self, out: str | Path) -> dict[str, Path]:
        """Write ``out/index.html`` and ``out/report.json``; pictures must live under ``out``."""
        out = Path(out)
        out.mkdir(parents=True, exist_ok=True)
        stamp = _dt.datetime.now().isoformat(timespec="seconds")
        html_path = write_html(
            out / "index.html",
            "sections.html.j2",
            title=self.title,
            written=stamp,
            banners=self.banners,
            summary=self.summary,
            sections=self.sections,
            root=out,
        )
        data = {
            "title": self.title,
            "written": stamp,
            "banners": self.banners,
            "summary": self.summary,
            "meta": self.meta,
            "sections": [
                {
                    "title": s.title,
                    "paragraphs": s.paragraphs,
                    "table": s.table,
                    "images": [os.path.relpath(p, out) for p, _ in s.images],
                    "data": s.data,
                }
                for s in self.sections
            ],
        }
        json_path = out / "report.json"
        outputs.write_text(json_path, json.dumps(data, indent=2, default=_json_default))
        return {"html": html_path, "json": json_path}


def _json_default(o):
    try:
        import numpy as np

        if isinstance(o, np.generic):
            return o.item()
        if isinstance(o, np.ndarray):
            return o.tolist()
    except ImportError:  # pragma: no cover
        pass
    return str(o)
