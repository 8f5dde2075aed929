"""A small, dependency-free HTML report: sections of text, tables and pictures.

The report is one ``index.html`` beside its PNGs (referenced by relative paths, so the
folder can be zipped, mailed or served) and a ``report.json`` with the same content as
data. The page carries a three-line script that counts images that failed to load into
``<body data-broken-images="n">``: a headless browser test reads it back (``--dump-dom``)
to prove that no picture is broken.
"""

from __future__ import annotations

import datetime as _dt
import html
import json
import os
from dataclasses import dataclass, field
from pathlib import Path
from typing import Any, Sequence

from mfdesign import outputs  # atomic writes: a reader never sees a torn file

__all__ = ["Report", "Section"]

_STYLE = """
body { font-family: system-ui, sans-serif; max-width: 1100px; margin: 2em auto; color: #222; line-height: 1.45; }
h1 { border-bottom: 2px solid #446; } h2 { margin-top: 2em; border-bottom: 1px solid #ccc; }
figure { display: inline-block; margin: 0.5em; vertical-align: top; }
figure img { max-width: 520px; border: 1px solid #ddd; }
figcaption { font-size: 0.85em; color: #555; max-width: 520px; }
table { border-collapse: collapse; margin: 0.8em 0; font-size: 0.9em; }
td, th { border: 1px solid #ccc; padding: 0.25em 0.6em; text-align: right; }
th { background: #eef; } td:first-child, th:first-child { text-align: left; }
.note { background: #f6f6fa; border-left: 4px solid #88a; padding: 0.5em 1em; }
.meta { color: #666; font-size: 0.85em; }
"""

_CHECK_IMAGES = """
<script>
window.addEventListener('load', function () {
  var bad = Array.from(document.images).filter(function (i) { return !(i.complete && i.naturalWidth > 0); });
  document.body.setAttribute('data-broken-images', String(bad.length));
  document.body.setAttribute('data-images', String(document.images.length));
});
</script>
"""


def _cell(v: Any) -> str:
    if isinstance(v, float):
        return f"{v:.4g}"
    return html.escape(str(v))


@dataclass
class Section:
    """One titled part of the report: paragraphs, an optional table, pictures (paths)."""

    title: str
    paragraphs: list[str] = field(default_factory=list)
    table: list[dict] | None = None
    images: list[tuple[str, str]] = field(default_factory=list)  # (path, caption)
    data: dict = field(default_factory=dict)

    def html(self, root: Path) -> str:
        parts = [f"<h2>{html.escape(self.title)}</h2>"]
        parts += [f"<p>{html.escape(p)}</p>" for p in self.paragraphs]
        if self.table:
            cols = list(self.table[0])
            parts.append("<table><tr>" + "".join(f"<th>{html.escape(c)}</th>" for c in cols) + "</tr>")
            parts += [
                "<tr>" + "".join(f"<td>{_cell(row.get(c, ''))}</td>" for c in cols) + "</tr>" for row in self.table
            ]
            parts.append("</table>")
        for path, caption in self.images:
            rel = os.path.relpath(path, root)
            parts.append(
                f'<figure><img src="{html.escape(rel)}" alt="{html.escape(caption)}">'
                f"<figcaption>{html.escape(caption)}</figcaption></figure>"
            )
        return "\n".join(parts)


@dataclass
class Report:
    """Collects sections; :meth:`write` renders ``index.html`` and ``report.json``."""

    title: str
    summary: list[str] = field(default_factory=list)
    sections: list[Section] = field(default_factory=list)
    meta: dict = field(default_factory=dict)

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
        body = [f"<h1>{html.escape(self.title)}</h1>", f'<p class="meta">written {stamp}</p>']
        if self.summary:
            body.append('<div class="note">' + "".join(f"<p>{html.escape(s)}</p>" for s in self.summary) + "</div>")
        body += [s.html(out) for s in self.sections]
        page = (
            f"<!doctype html><html><head><meta charset='utf-8'><title>{html.escape(self.title)}</title>"
            f"<style>{_STYLE}</style>{_CHECK_IMAGES}</head><body>" + "\n".join(body) + "</body></html>"
        )
        html_path = out / "index.html"
        outputs.write_text(html_path, page)
        data = {
            "title": self.title,
            "written": stamp,
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
