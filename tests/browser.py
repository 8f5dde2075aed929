"""Open an HTML page in headless Chromium: screenshot, a check that every picture loaded,
and the text the browser rendered.

Uses the system's ``chromium`` (Debian package ``chromium``) through its command line:
``--dump-dom`` prints the page after its scripts ran, where :mod:`mfdesign.report` pages
(template ``base.html.j2``) record ``data-broken-images``; ``--screenshot`` writes a PNG.
:func:`rendered_lines` turns that DOM into the lines a reader sees (one per paragraph,
heading, list item or table row; a row's cells joined by ``" | "``), so that a test can
compare the numbers on the page with the JSON they came from.
"""

from __future__ import annotations

import re
import shutil
import subprocess
from dataclasses import dataclass
from html.parser import HTMLParser
from pathlib import Path

__all__ = ["PageCheck", "chromium_path", "check_page", "rendered_lines"]

_FLAGS = [
    "--headless",
    "--no-sandbox",
    "--disable-gpu",
    "--hide-scrollbars",
    "--allow-file-access-from-files",
    "--virtual-time-budget=10000",
]


def chromium_path() -> str | None:
    """The Chromium executable, or None when none is installed."""
    for name in ("chromium", "chromium-browser", "google-chrome", "chrome"):
        found = shutil.which(name)
        if found:
            return found
    return None


@dataclass(frozen=True)
class PageCheck:
    """What Chromium saw: pictures (all, broken), the screenshot written and the page's
    DOM after its scripts ran (``rendered_lines(dom)``: its text)."""

    images: int
    broken_images: int
    screenshot: Path
    dom: str

    @property
    def lines(self) -> list[str]:
        return rendered_lines(self.dom)


# Elements that end a line of text; a table cell ends a cell (joined by " | ").
_BLOCKS = {"p", "h1", "h2", "h3", "h4", "li", "tr", "div", "figcaption", "title", "br"}
_HIDDEN = {"script", "style", "head"}


class _Text(HTMLParser):
    def __init__(self):
        super().__init__(convert_charrefs=True)
        self.lines: list[str] = []
        self.cells: list[str] = []
        self.words: list[str] = []
        self.hidden = 0

    def _flush_cell(self):
        self.cells.append(" ".join(" ".join(self.words).split()))
        self.words = []

    def _flush_line(self):
        if self.cells:
            if self.words:
                self._flush_cell()
            line = " | ".join(self.cells)
        else:
            line = " ".join(" ".join(self.words).split())
        self.cells, self.words = [], []
        if line.strip():
            self.lines.append(line)

    def handle_starttag(self, tag, attrs):
        if tag in _HIDDEN:
            self.hidden += 1
        elif tag in _BLOCKS:
            self._flush_line()

    def handle_endtag(self, tag):
        if tag in _HIDDEN:
            self.hidden -= 1
        elif tag in ("td", "th"):
            self._flush_cell()
        elif tag in _BLOCKS:
            self._flush_line()

    def handle_data(self, data):
        if not self.hidden:
            self.words.append(data)


def rendered_lines(dom: str) -> list[str]:
    """The visible text of ``dom`` (HTML) as lines: one per paragraph, heading, list item,
    caption or banner, one per table row with its cells joined by ``" | "``; whitespace
    collapsed, scripts and styles left out."""
    parser = _Text()
    parser.feed(dom)
    parser.close()
    parser._flush_line()
    return parser.lines


def check_page(
    page: str | Path, screenshot: str | Path, width: int = 1200, height: int | None = None, timeout_s: float = 120.0
) -> PageCheck:
    """Load ``page`` headless at ``width`` px; count its (broken) images, keep its DOM and
    write a screenshot PNG of the whole page (``height``: cut at that many px instead;
    mfdesign report pages record their height in ``data-height``, capped at 20000 px)."""
    exe = chromium_path()
    if exe is None:
        raise FileNotFoundError("no Chromium found (install the Debian package 'chromium')")
    url = Path(page).resolve().as_uri()
    dom = subprocess.run(
        [exe, *_FLAGS, f"--window-size={width},1000", "--dump-dom", url],
        capture_output=True,
        text=True,
        timeout=timeout_s,
        check=True,
    ).stdout
    m_bad = re.search(r'data-broken-images="(\d+)"', dom)
    m_all = re.search(r'data-images="(\d+)"', dom)
    if m_bad is None or m_all is None:
        raise RuntimeError(f"{page}: the page's image check did not run (not an mfdesign report?)")
    if height is None:
        m_height = re.search(r'data-height="(\d+)"', dom)
        height = min(int(m_height.group(1)), 20000) if m_height else 4000
    shot = Path(screenshot).resolve()
    shot.parent.mkdir(parents=True, exist_ok=True)
    subprocess.run(
        [exe, *_FLAGS, f"--screenshot={shot}", f"--window-size={width},{height}", url],
        capture_output=True,
        text=True,
        timeout=timeout_s,
        check=True,
    )
    if not shot.is_file():
        raise RuntimeError(f"Chromium wrote no screenshot for {page}")
    return PageCheck(images=int(m_all.group(1)), broken_images=int(m_bad.group(1)), screenshot=shot, dom=dom)
