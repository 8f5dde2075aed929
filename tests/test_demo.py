"""The README's main job end to end (slow): the quick demo writes a report whose pictures
all load in headless Chromium."""

import json

import pytest

from mfdesign.browser import check_page, chromium_path


@pytest.mark.slow
def test_quick_demo_writes_a_report_chromium_can_show(tmp_path):
    from mfdesign.demo import DemoSettings, run_demo

    summary = run_demo(tmp_path, DemoSettings.quick(), echo=lambda *_: None, progress=False)
    report = json.loads((tmp_path / "report.json").read_text())
    titles = [s["title"] for s in report["sections"]]
    assert titles[0] == "Data and model" and any(t.startswith("Diagnosis") for t in titles)
    assert len(summary["proposals"]) == 2
    assert all(p["fidelity"] in ("rig", "sim") for p in summary["proposals"])
    if chromium_path() is None:
        pytest.skip("no Chromium installed (Debian package 'chromium')")
    page = check_page(tmp_path / "index.html", tmp_path / "screenshot.png")
    assert page.images >= 6 and page.broken_images == 0
