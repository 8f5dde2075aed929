"""The README's main job end to end (slow): the quick demo writes a report whose pictures
all load in headless Chromium."""

import json

import numpy as np
import pytest

from browser import check_page, chromium_path


@pytest.mark.slow
def test_quick_demo_writes_a_report_chromium_can_show(tmp_path):
    from mfdesign.cli._demo import DemoSettings, run_demo

    summary = run_demo(tmp_path, DemoSettings.quick(), echo=lambda *_: None, progress=False)
    report = json.loads((tmp_path / "report.json").read_text())
    titles = [s["title"] for s in report["sections"]]
    assert titles[0] == "Data and model" and any(t.startswith("Diagnosis") for t in titles)
    assert len(summary["proposals"]) == 2
    # One verdict: the summary box and the diagnosis section say the same; every round shown.
    diagnosis = next(s for s in report["sections"] if s["title"].startswith("Diagnosis:"))
    assert diagnosis["paragraphs"][-1] in report["summary"][1]
    assert sum(t.startswith("Diagnosis round") for t in titles) >= 1
    if "truth_check" in summary:
        truths = next(s for s in report["sections"] if s["title"].startswith("Truths"))
        assert [r["parameter"] for r in truths["table"]] == list(summary["truth_check"])
    if not all(c["converged"] for c in summary["convergence"].values()):
        assert any("has not converged" in b for b in report["banners"])
    assert all(p["fidelity"] in ("rig", "sim") for p in summary["proposals"])
    # Both fits reach ArviZ and Posterior.load in physical units (mu in Pa, J_m > 1).
    import arviz as az

    from mfdesign.calibration.posterior import Posterior

    for tag in ("plain", "with_effects"):
        if not (tmp_path / tag).is_dir():
            continue
        idata = az.from_netcdf(str(tmp_path / tag / "posterior.nc"), engine="h5netcdf")
        assert idata.posterior["mu_pa"].dims == ("chain", "draw")
        assert 15e3 < float(idata.posterior["mu_pa"].mean()) < 60e3
        assert float(idata.posterior["jm"].min()) > 1.0
        post = Posterior.load(tmp_path / tag / "posterior")
        mu = post.samples[:, post.names.index("mu_pa")]
        assert float(idata.posterior["mu_pa"].median()) == pytest.approx(float(np.median(mu)), rel=5e-3)
    if chromium_path() is None:
        pytest.skip("no Chromium installed (Debian package 'chromium')")
    page = check_page(tmp_path / "index.html", tmp_path / "screenshot.png")
    assert page.images >= 6 and page.broken_images == 0


def _diag(before, after, floor, found, last_status):
    from types import SimpleNamespace as NS

    return NS(
        before=NS(rmse_n=before, noise_floor_n=floor),
        after=None if after is None else NS(rmse_n=after, noise_floor_n=floor),
        found=found,
        effects=found,
        steps=[{"verdict": {"status": "partly_explained"}}, {"verdict": {"status": last_status}}],
    )


def test_one_verdict_from_every_round_and_banners_that_say_what_is_wrong():
    """A first round that found an effect and a last one that found nothing more give one
    sentence (the summary and the diagnosis section print it), and the banners flag the
    model above 1.2x the noise floor and a chain that has not converged."""
    from mfdesign.cli._demo import _banners, _verdict

    partial = _diag(17.4, 11.56, 0.23, ["thickness_deviation"], "unexplained")
    words = _verdict(partial)
    assert "17.40 N to 11.56 N" in words and "50.3x the noise floor" in words
    assert "explains only part" in words and "no further candidate" in words
    conv = {"plain": {"converged": False, "problems": ["16 tau long"]}, "with_effects": {"converged": True}}
    banners = _banners(partial, conv)
    assert len(banners) == 2 and "plain model's chain has not converged (16 tau long)" in banners[0]
    assert "50.3x the noise floor" in banners[1]
    good = _diag(1.53, 0.32, 0.283, ["pressure_sensor"], "explained")
    assert "1.13x the noise floor" in _verdict(good) and "explains the misfit" in _verdict(good)
    assert _banners(good, {"with_effects": {"converged": True}}) == []
    nothing = _diag(1.4, None, 0.29, [], "unexplained")
    assert "no candidate effect explains" in _verdict(nothing) and len(_banners(nothing, {})) == 1


def test_truth_table_puts_each_truth_beside_the_posterior():
    from mfdesign.cli._demo import _truth_table

    check = {"mu_pa": {"truth": 31700.0, "q05": 30000.0, "q95": 33000.0, "inside": True}}
    rows = _truth_table(check, [{"parameter": "mu_pa", "median": 31500.0}, {"parameter": "jm", "median": 40.0}])
    assert rows == [
        {
            "parameter": "mu_pa",
            "truth": 31700.0,
            "median": 31500.0,
            "90 % interval": "30000 to 33000",
            "inside": "yes",
        }
    ]


def test_calibrate_draws_truth_lines_only_for_the_bundled_dataset():
    from pathlib import Path

    from mfdesign.cli.calibrate import _bundled_truths
    from mfdesign.data.shipped import bundled_path

    truths = _bundled_truths([Path("bundled")])
    assert truths["mu_pa"] == 31700.0 and truths["pressure_sensor.offset_pa"] == 150.0
    assert _bundled_truths([bundled_path()]) == truths
    assert _bundled_truths([Path("mine.parquet")]) == {} and _bundled_truths([Path("bundled")] * 2) == {}
