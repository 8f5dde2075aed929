"""A diagnosis's page: every number, word and table of ``Diagnosis.to_json()`` reaches
``index.html``, escaped, with its pictures (the whole command: tests/cli/test_diagnose_cli.py)."""

import copy

import matplotlib

matplotlib.use("Agg")
import matplotlib.pyplot as plt
import pytest

from browser import check_page, chromium_path
from mfdesign.report.render import write_html

SUMMARY = {
    "n": 4805,
    "rmse_n": 0.8118,
    "bias_n": 0.7694,
    "noise_floor_n": 0.2016,
    "rmse_over_noise": 4.0266,
    "membranes": 2,
    "dropped": {"lift_plate_resting_or_at_top": 381},
}
DATA = {
    "model": "plain <simulator>",
    "effects_added": ["load_cell_offset"],
    "theta": {"load_cell_offset.offset_n": 0.803017},
    "before": {
        "summary": SUMMARY,
        "worst_regions": [{"words": "below 6 kPa the model under-predicts"}],
        "trends": ["by experiment: RMS 0.83 N at force"],
    },
    "after": {
        "summary": {**SUMMARY, "rmse_n": 0.1969, "noise_floor_n": 0.2016},
        "worst_regions": [{"words": "at 6-8 kPa the model over-predicts"}],
    },
    "search": [
        {
            "base_effects": [],
            "screen": [
                {
                    "effect": "load_cell_offset",
                    "explained_fraction": 0.93981,
                    "structure_explained_fraction": 1.0,
                    "theta": {"load_cell_offset.offset_n": 0.8047},
                    "stderr": {"load_cell_offset.offset_n": 0.0029},
                    "delta_bic": -13490.0,
                }
            ],
            "checks": [
                {
                    "effects": ["load_cell_offset"],
                    "theta": {"load_cell_offset.offset_n": 0.803},
                    "stderr": {"load_cell_offset.offset_n": 0.0064},
                    "rmse_n": 0.1968,
                    "heldout_rmse_base_n": 0.8095,
                    "heldout_rmse_n": 0.1969,
                    "heldout_over_noise": 3.2,
                    "delta_bic": -2822.0,
                }
            ],
            "verdict": {"words": "nothing explains it: held-out RMSE 3.2x the noise floor & <more>"},
        }
    ],
    "found": ["load_cell_offset"],
}


def _png(path):
    fig, ax = plt.subplots(figsize=(3, 2))
    ax.plot([0, 1], [0, 1])
    fig.savefig(path)
    plt.close(fig)
    return path


def _page(tmp_path, data, names=("maps_before", "parity", "screen_1", "maps_after")):
    images = {k: _png(tmp_path / f"{k}.png").name for k in names}
    return write_html(
        tmp_path / "index.html", "diagnosis.html.j2", title="mfdesign diagnosis", data=data, images=images
    )


def test_numbers_words_and_tables_reach_the_page(tmp_path):
    page = _page(tmp_path, DATA).read_text()
    assert "<h1>Diagnosis of the plain &lt;simulator&gt;</h1>" in page
    assert "4805 usable rows of 2 membranes; RMSE 0.812 N, bias +0.769 N, noise floor 0.202 N (ratio 4.027)" in page
    assert "left out: lift_plate_resting_or_at_top = 381." in page
    assert "<li>below 6 kPa the model under-predicts</li>" in page and "<li>by experiment: RMS 0.83 N" in page
    assert "Which effect is missing (round 1)" in page and "<td>0.9398</td>" in page and "<td>-1.349e+04</td>" in page
    assert "<h3>Full check</h3>" in page and "<th>heldout_over_noise</th>" in page and "<td>3.2</td>" in page
    assert "<b>nothing explains it: held-out RMSE 3.2x the noise floor &amp; &lt;more&gt;</b>" in page
    assert "<h2>After adding load_cell_offset</h2>" in page
    assert "theta: load_cell_offset.offset_n = 0.803; RMSE 0.812 &rarr; 0.197 N (noise floor 0.202 N)" in page
    for png in ("maps_before.png", "parity.png", "screen_1.png", "maps_after.png"):
        assert f'src="{png}"' in page
    assert 'src="breakdown.png"' not in page  # a picture not drawn is not linked


def test_without_effects_or_search_the_page_has_no_after_or_rounds(tmp_path):
    data = copy.deepcopy(DATA) | {"after": None, "search": [], "effects_added": []}
    page = _page(tmp_path, data, names=("maps_before",)).read_text()
    assert "After adding" not in page and "Which effect is missing" not in page
    assert "RMSE 0.812 N" in page


@pytest.mark.skipif(chromium_path() is None, reason="no Chromium installed (Debian package 'chromium')")
def test_headless_chromium_sees_every_picture(tmp_path):
    page = check_page(_page(tmp_path, DATA), tmp_path / "shot.png")
    assert (page.images, page.broken_images) == (4, 0)


def test_a_model_above_the_noise_floor_gets_a_banner(tmp_path):
    from types import SimpleNamespace as NS

    from mfdesign.report.diagnosis import floor_banner

    diag = NS(before=NS(rmse_n=0.812, noise_floor_n=0.202), after=NS(rmse_n=0.4), effects=["load_cell_offset"])
    words = floor_banner(diag)
    assert "after adding load_cell_offset still sits at 2.0x the noise floor" in words
    assert floor_banner(NS(before=diag.before, after=NS(rmse_n=0.22), effects=["x"])) is None
    page = write_html(
        tmp_path / "r.html", "diagnosis.html.j2", title="t", data=DATA, images={}, banners=[words]
    ).read_text()
    assert page.index('class="banner"') < page.index("Where it fails")


def _figure_of(draw, monkeypatch, *args):
    """The matplotlib figure ``draw(*args, path)`` makes (its writer captured, not saved)."""
    from mfdesign.report import diagnosis

    seen = {}
    monkeypatch.setattr(diagnosis, "_save", lambda fig, path: seen.setdefault("fig", fig))
    draw(*args)
    return seen["fig"]


@pytest.fixture(scope="module")
def small_residuals():
    import numpy as np

    from mfdesign.workflows.demo import BUNDLED
    from mfdesign.data.store import read_parquet
    from mfdesign.diagnosis.residuals import compute_residuals

    meas = read_parquet(BUNDLED)
    meas = meas.subset(meas.design_keys[:2])
    observed = meas.df["force_n"].to_numpy(float)
    wrong = observed + 1.5 * np.sin(meas.df["pressure_pa"].to_numpy(float) / 1e3)  # a ~1.5 N misfit
    return compute_residuals(meas, wrong)


def test_parity_shows_the_residuals_on_their_own_scale(small_residuals, monkeypatch, tmp_path):
    """On the parity plot's 0-200 N axes a 1.5 N residual is invisible: a second panel
    shows observed - model against the model force, in N, with the noise floor."""
    from mfdesign.report.diagnosis import parity

    fig = _figure_of(parity, monkeypatch, small_residuals, tmp_path / "p.png")
    resid = next(ax for ax in fig.axes if ax.get_ylabel() == "residual: observed - model [N]")
    lo, hi = resid.get_ylim()
    assert hi - lo < 10.0  # its own scale: a few N, not the forces' 0-200 N
    assert resid.get_xlabel() == "model force [N]"


def test_breakdown_bars_have_readable_ticks_and_newtons(small_residuals, monkeypatch, tmp_path):
    from mfdesign.report.diagnosis import breakdown_plot

    fig = _figure_of(breakdown_plot, monkeypatch, small_residuals, tmp_path / "b.png")
    fig.canvas.draw()
    for ax in fig.axes:
        assert ax.get_ylabel() == "RMS residual [N]"
        assert all(t.get_fontsize() >= 8 for t in ax.get_xticklabels())
    plt.close(fig)


def test_indistinguishable_sets_are_named_with_the_trial_that_separates_them_and_their_joint_posterior(tmp_path):
    from mfdesign.report.diagnosis import joint_plot

    data = copy.deepcopy(DATA)
    alt = {
        "effects": ["pressure_sensor"],
        "theta": {"pressure_sensor.offset_pa": -50.0, "pressure_sensor.gain": 0.94},
        "separated_by": {
            "words": "a force trial of [2.0, 25.4, nan, nan, nan, nan] at h = 70 mm up to 10.0 kPa separates"
        },
        "joint": {
            "effects": ["thickness_deviation", "pressure_sensor"],
            "theta": {
                "thickness_deviation.relative": -0.1,
                "pressure_sensor.offset_pa": -10.0,
                "pressure_sensor.gain": 0.99,
            },
            "stderr": {
                "thickness_deviation.relative": 0.02,
                "pressure_sensor.offset_pa": 20.0,
                "pressure_sensor.gain": 0.01,
            },
            "correlation": [[1.0, -0.9, 0.5], [-0.9, 1.0, -0.3], [0.5, -0.3, 1.0]],
            "method": "Laplace approximation",
        },
    }
    v = {
        "effects": ["thickness_deviation"],
        "theta": {"thickness_deviation.relative": -0.12},
        "words": "w",
        "alternatives": [alt],
    }
    data["search"][0]["verdict"] = v
    data["search"][0]["pair_screen"] = [
        {"effect": "a+b", "explained_fraction": 0.97, "theta": {"a.x": 1.0, "b.y": 2.0}, "delta_bic": -5000.0}
    ]
    joint_plot(v, alt, tmp_path / "joint_1_1.png")
    assert (tmp_path / "joint_1_1.png").stat().st_size > 1000
    page = _page(tmp_path, data, names=("maps_before", "joint_1_1")).read_text()
    assert "Indistinguishable on these data: thickness_deviation and pressure_sensor" in page
    assert "at h = 70 mm up to 10.0 kPa separates" in page
    assert "Laplace approximation" in page and 'src="joint_1_1.png"' in page
    assert "<h3>Pairs fitted jointly (first order)</h3>" in page and "<td>a+b</td>" in page


def test_ties_and_unevaluated_candidates_are_banners_above_the_verdict():
    """A tie between effect sets and a candidate no solver could evaluate limit what the
    verdict shows: each is said at the top of the page, not only inside the verdict's words."""
    from types import SimpleNamespace as NS

    from mfdesign.report.diagnosis import limit_banners

    before = NS(rmse_n=0.5, noise_floor_n=0.2)
    tie = {"effects": ["ring_stiffening"], "alternatives": [{"effects": ["fabric_inset", "ring_stiffening"]}]}
    gap = {"effects": [], "not_evaluated": [["contact_offset"]]}
    diag = NS(before=before, after=NS(rmse_n=0.21), effects=["ring_stiffening"], steps=[{"verdict": tie}])
    words = limit_banners(diag)
    assert words == [
        "Round 1: the data cannot tell ring_stiffening from fabric_inset+ring_stiffening: both are named, neither "
        "is preferred (the diagnosis section gives the trial that would separate them)."
    ]
    diag = NS(before=before, after=None, effects=[], steps=[{"verdict": tie}, {"verdict": gap}])
    words = limit_banners(diag)
    assert len(words) == 3 and "still sits at 2.5x the noise floor" in words[0]
    assert words[2].startswith("Round 2: candidate(s) not evaluated (contact_offset)")
    clean = NS(before=before, after=NS(rmse_n=0.21), effects=["x"], steps=[{"verdict": {"effects": ["x"]}}])
    assert limit_banners(clean) == []
