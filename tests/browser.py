"""Open an HTML page in headless Chromium: screenshot and a check that every picture loaded.

Uses the system's ``chromium`` (Debian package ``chromium``) through its command line:
``--dump-dom`` prints the page after its scripts ran, where :mod:`mfdesign.report` pages
(template ``base.html.j2``) record ``data-broken-images``; ``--screenshot`` writes a PNG.
"""

from __future__ import annotations

import re
import shutil
import subprocess
from dataclasses import dataclass
from pathlib import Path

__all__ = ["PageCheck", "chromium_path", "check_page"]

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
    images: int
    broken_images: int
    screenshot: Path


def check_page(
    page: str | Path, screenshot: str | Path, width: int = 1200, height: int = 4000, timeout_s: float = 120.0
) -> PageCheck:
    """Load ``page`` headless; count its (broken) images and write a screenshot PNG."""
    exe = chromium_path()
    if exe is None:
        raise FileNotFoundError("no Chromium found (install the Debian package 'chromium')")
    url = Path(page).resolve().as_uri()
    dom = subprocess.run(
        [exe, *_FLAGS, "--dump-dom", url], capture_output=True, text=True, timeout=timeout_s, check=True
    ).stdout
    m_bad = re.search(r'data-broken-images="(\d+)"', dom)
    m_all = re.search(r'data-images="(\d+)"', dom)
    if m_bad is None or m_all is None:
        raise RuntimeError(f"{page}: the page's image check did not run (not an mfdesign report?)")
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
    return PageCheck(images=int(m_all.group(1)), broken_images=int(m_bad.group(1)), screenshot=shot)
