"""Corner plots with partial truths; PIT and coverage of a posterior predictive."""

import arviz as az
import numpy as np
import pytest

from mfdesign.calibration.plots import corner_plot, pit, pit_coverage, predictive_check_plot


def test_corner_plot_takes_unknown_truths_and_reaches_a_far_truth(tmp_path):
    x = np.random.default_rng(0).normal(size=(500, 3))
    png = corner_plot(x, ["a", "b", "c"], tmp_path / "c.png", truths=[0.0, None, 25.0])
    assert png.stat().st_size > 1000
    with pytest.raises(ValueError, match="2 truths for 3"):
        corner_plot(x, ["a", "b", "c"], tmp_path / "d.png", truths=[0.0, 1.0])


def _idata(scale_rep: float, n_rows: int = 4000):
    rng = np.random.default_rng(1)
    mean = rng.uniform(0, 50, n_rows)
    rep = mean + scale_rep * rng.standard_normal((2, 200, n_rows))  # chain x draw x row
    obs = mean + rng.standard_normal(n_rows)
    return az.from_dict(posterior_predictive={"force_n": rep}, observed_data={"force_n": obs})


def test_pit_is_uniform_and_coverage_nominal_for_a_calibrated_predictive(tmp_path):
    u = pit(_idata(1.0))
    assert u.shape == (4000,) and 0.0 <= u.min() and u.max() <= 1.0
    cov = pit_coverage(u)
    for level, share in cov.items():
        assert share == pytest.approx(level, abs=0.03)
    # intervals twice too narrow: the observations fall outside far more often than nominal
    assert pit_coverage(pit(_idata(0.5)))[0.9] < 0.7
    png = predictive_check_plot({"ok": u, "narrow": pit(_idata(0.5))}, tmp_path / "pc.png")
    assert png.stat().st_size > 1000
