"""The HTML report renders, and headless Chromium sees every picture (or flags a broken one)."""

import json

import matplotlib

matplotlib.use("Agg")
import matplotlib.pyplot as plt
import pytest

from browser import check_page, chromium_path
from mfdesign.report import Report


def _png(path):
    fig, ax = plt.subplots(figsize=(3, 2))
    ax.plot([0, 1], [0, 1])
    fig.savefig(path)
    plt.close(fig)
    return path


def test_report_writes_html_and_json(tmp_path):
    rep = Report("demo", summary=["one line"])
    rep.add(
        "plane", ["text <b>escaped</b>"], table=[{"a": 1.23456, "b": "x"}], images=[(_png(tmp_path / "a.png"), "cap")]
    )
    paths = rep.write(tmp_path)
    page = paths["html"].read_text()
    assert 'src="a.png"' in page and "&lt;b&gt;" in page and "1.235" in page
    data = json.loads(paths["json"].read_text())
    assert data["sections"][0]["images"] == ["a.png"]


def test_report_refuses_missing_picture(tmp_path):
    with pytest.raises(FileNotFoundError, match="nope.png"):
        Report("x").add("s", images=[(tmp_path / "nope.png", "c")])


@pytest.mark.skipif(chromium_path() is None, reason="no Chromium installed (Debian package 'chromium')")
def test_headless_chromium_sees_pictures_and_broken_ones(tmp_path):
    rep = Report("demo")
    rep.add("ok", images=[(_png(tmp_path / "a.png"), "fine")])
    bad = _png(tmp_path / "b.png")
    rep.add("will break", images=[(bad, "deleted after writing")])
    paths = rep.write(tmp_path)
    good = check_page(paths["html"], tmp_path / "shot1.png")
    assert (good.images, good.broken_images) == (2, 0)
    assert good.screenshot.stat().st_size > 1000
    bad.unlink()
    broken = check_page(paths["html"], tmp_path / "shot2.png")
    assert broken.broken_images == 1


def test_banners_come_first_and_pictures_open_full_size(tmp_path):
    rep = Report("demo", summary=["one line"], banners=["chain <not> converged"])
    rep.add("plane", images=[(_png(tmp_path / "a.png"), "cap")])
    paths = rep.write(tmp_path)
    page = paths["html"].read_text()
    assert page.index('class="banner"') < page.index("one line")
    assert "chain &lt;not&gt; converged" in page
    assert '<a href="a.png" target="_blank"><img src="a.png"' in page
    assert "520px" not in page
    assert json.loads(paths["json"].read_text())["banners"] == ["chain <not> converged"]
