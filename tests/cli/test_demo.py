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
