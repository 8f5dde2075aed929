"""Corner plots with partial truths; PIT and coverage of a posterior predictive."""

import arviz as az
import numpy as np
import pytest

from mfdesign.calibration.plots import corner_plot, pit, pit_coverage, predictive_check_plot


def test_corner_plot_takes_unknown_truths_and_reaches_a_far_truth(tmp_path):
    x = np.random.default_rng(0).normal(size=(500, 3))
    png = corner_plot(x, ["a", "b", "c"], tmp_path / "c.png", truths=[0.0, None, 25.0])
    assert png.stat().st_size > 1000
    fig = corner_plot(x, ["a", "b", "c"], None, truths=[0.0, None, 25.0])
    assert fig.axes and all(ax.get_xlim()[1] > 25.0 for ax in fig.axes if ax.get_xlabel() == "c")
    with pytest.raises(ValueError, match="2 truths for 3"):
        corner_plot(x, ["a", "b", "c"], tmp_path / "d.png", truths=[0.0, 1.0])


def _overlaps(fig) -> list[tuple[str, str]]:
    """Pairs of visible tick labels on one axis whose boxes overlap once drawn."""
    fig.canvas.draw()
    renderer = fig.canvas.get_renderer()
    bad = []
    for ax in fig.axes:
        for labels in (ax.get_xticklabels(), ax.get_yticklabels()):
            shown = [t for t in labels if t.get_visible() and t.get_text()]
            boxes = [t.get_window_extent(renderer) for t in shown]
            for a in range(len(shown)):
                for b in range(a + 1, len(shown)):
                    if boxes[a].overlaps(boxes[b]):
                        bad.append((shown[a].get_text(), shown[b].get_text()))
    return bad


def test_corner_plot_shows_kpa_with_units_and_tick_labels_that_do_not_overlap():
    """The demo's corner plot once labelled mu_pa in Pa: x ticks 32000 32500 33000 ran into
    one another and the labels had no units. mu is shown in kPa, every label with its unit."""
    rng = np.random.default_rng(0)
    x = np.column_stack([rng.normal(32500, 300, 800), rng.normal(40, 1, 800), rng.normal(150, 5, 800)])
    fig = corner_plot(
        x, ["mu_pa", "jm", "pressure_sensor.offset_pa"], None, truths=[31700, 39.6, None], units=["Pa", "1", "Pa"]
    )
    labels = {ax.get_xlabel() for ax in fig.axes} | {ax.get_ylabel() for ax in fig.axes}
    assert {"mu [kPa]", "jm", "pressure_sensor.offset [kPa]"} <= labels
    mu_axis = next(ax for ax in fig.axes if ax.get_xlabel() == "mu [kPa]")
    assert 30 < mu_axis.get_xlim()[0] < mu_axis.get_xlim()[1] < 35  # kPa, not Pa
    assert _overlaps(fig) == []


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
