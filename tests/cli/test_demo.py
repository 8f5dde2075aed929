"""The README's main job end to end (slow): the quick demo writes a report whose pictures
all load in headless Chromium and whose numbers, read off the rendered page, are those of
its sub-reports (summary.json, posterior.json, diagnosis.json). The fast version renders
the report from a stored quick demo's JSON (tests/cli/demo_report/) with stand-in pictures.

``MFDESIGN_UPDATE_SCREENSHOTS=1 pytest -m slow tests/cli/test_demo.py`` also writes the
screenshot of the whole page to docs/img/demo_report.png (the README shows it)."""

import json
import os
import shutil
from pathlib import Path

import numpy as np
import pytest

from browser import check_page, chromium_path

FIXTURE = Path(__file__).parent / "demo_report"
SCREENSHOT = Path(__file__).parents[2] / "docs" / "img" / "demo_report.png"


def assert_page_shows_the_numbers(lines: list[str], out: Path) -> None:
    """Every headline number of the demo, as the sub-reports in ``out`` hold it, is on the
    page ``lines`` (``browser.rendered_lines``), formatted as the page formats it: posterior
    medians and 90 % intervals, convergence (tau, R-hat, ESS), RMSE before / after and the
    noise floor, the verdict, the effects found and each round's screen, truths, proposals."""
    from mfdesign.calibration.posterior import convergence_rows
    from mfdesign.workflows.demo import _display_rows, _optimum_headline, _short, _truth_table
    from mfdesign.report.render import cell

    summary = json.loads((out / "summary.json").read_text())
    diagnosis = json.loads((out / "diagnose" / "diagnosis.json").read_text())
    text = "\n".join(lines)

    def row(*cells) -> str:
        return " | ".join(cell(c) for c in cells)

    # The summary repeats the sub-reports (no number of its own) ...
    d = summary["diagnosis"]
    assert d["rmse_before_n"] == diagnosis["before"]["summary"]["rmse_n"]
    assert d["noise_floor_n"] == diagnosis["before"]["summary"]["noise_floor_n"]
    assert d["found"] == diagnosis["found"] == diagnosis["effects_added"]
    if diagnosis["after"] is not None:
        assert d["rmse_after_n"] == diagnosis["after"]["summary"]["rmse_n"]
    # ... and the page shows them: RMSE before / after, noise floor, one verdict, effects.
    b, floor = d["rmse_before_n"], d["noise_floor_n"]
    assert f"{b:.2f} N" in d["verdict"] and f"{floor:.2f} N" in d["verdict"]
    hidden = summary.get("hidden_effect")
    assert d["verdict"] in lines  # the diagnosis section's, and the summary box's:
    assert d["verdict"] + (f" (Hidden truth: {hidden}.)" if hidden else "") in lines
    if d["rmse_after_n"] is not None:
        assert f"Residual RMSE {b:.2f} N before, {d['rmse_after_n']:.2f} N after; noise floor {floor:.2f} N." in lines
    assert f"After adding {', '.join(d['found']) if d['found'] else 'nothing'}" in lines
    for i, step in enumerate(diagnosis["search"]):
        assert f"Round {i + 1}'s verdict: {step['verdict']['words']}" in lines
        for r in step["screen"][:6]:
            assert row(r["effect"], float(r["explained_fraction"])) in lines
    for w in diagnosis["before"]["worst_regions"][:4]:
        assert w["words"] in lines
    first = f"{summary['rows']} rows of {summary['membranes']} membranes from {Path(summary['data']).name}."
    for banner in summary.get("banners") or []:
        assert lines.index(banner) < lines.index(first)  # the warnings come before any number
    # Posterior medians and 90 % intervals: the summary's rows are posterior.json's, rounded.
    for tag in ("plain", "with_effects"):
        if f"posterior_{tag}" not in summary:  # the plain model is calibrated with --calibrate-plain only
            assert tag == "plain" and not (out / tag).exists()
            continue
        rows = summary[f"posterior_{tag}"]
        for r, shown in zip(rows, _display_rows(rows)):  # the page shows Pa as kPa
            assert row(r["parameter"], shown["unit"], shown["median"], shown["q05"], shown["q95"]) in lines
        stored = out / tag / "posterior.json"
        if not stored.is_file():
            continue
        post = json.loads(stored.read_text())
        by_name = {p["parameter"]: p for p in post["parameters"]}
        for r in rows:
            for k in ("median", "q05", "q95"):
                assert r[k] == round(by_name[r["parameter"]][k], 4)
        # Convergence: emcee's tau and ArviZ's R-hat / ESS per parameter, as posterior.json has them.
        conv = summary["convergence"][tag]
        assert conv["parameters"] == convergence_rows(post["convergence"])
        assert conv["rhat_max"] == post["convergence"]["rhat_max"]
        for r in conv["parameters"]:
            assert row(tag.replace("_", " "), *r.values()) in lines
        assert (
            f"{tag.replace('_', ' ')}: {conv['steps_over_tau']:.1f} tau long, acceptance {conv['acceptance']:.2f}, "
            f"R-hat max {conv['rhat_max']:.3f}" in text
        )
    for r in _truth_table(summary.get("truth_check") or {}, summary["posterior_with_effects"]):
        assert r["90 % interval"] in text and r["parameter"] in text
    for p in summary["proposals"]:  # membranes to build, each with why
        assert f"{_short(p['design'])}: {p['fidelity']}" in lines
        assert f"because it {p['reason']} (cost {p['cost']:g})" in lines
    for p in summary.get("simulator_runs") or []:  # the tool's own runs: made, and what each taught
        made = f"; made, {p['state']}: {p['taught']}" if p.get("made") else "; not made"
        assert f"{_short(p['design'])}: {p['fidelity']} (because it {p['reason']} (cost {p['cost']:g})){made}" in lines
    if summary.get("discrepancy_gate"):
        assert f"The multi-fidelity model's {summary['discrepancy_gate']}." in lines
    for why in summary["optimum"].get("limits") or []:
        assert f"At a limit: {why}" in lines
    assert _optimum_headline(summary["optimum"]) in lines
    assert ", ".join(f"{n} {c:.2f}" for n, c in summary["coverage_90"].items()) in text


@pytest.mark.slow
def test_quick_demo_writes_a_report_chromium_can_show(tmp_path):
    from mfdesign.workflows.demo import DemoSettings, run_demo

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
    # The optimum shown is the simulator's check of the emulator's answer, never its word alone.
    optimum = json.loads((tmp_path / "optimize" / "optimize.json").read_text())
    assert optimum["simulator"] is not None and summary["optimum"]["simulator"] is not None
    assert "the simulator (calibrated constants) lifts the loads to" in report["summary"][3]
    assert all(p["fidelity"] == "rig" and p["reason"] for p in summary["proposals"])  # to build, with why
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
    assert_page_shows_the_numbers(page.lines, tmp_path)
    if os.environ.get("MFDESIGN_UPDATE_SCREENSHOTS") == "1":
        shutil.copyfile(page.screenshot, SCREENSHOT)


def _stand_in_pictures(out: Path) -> None:
    """A small PNG wherever the demo's stages draw one (the fast test has their JSON only)."""
    import matplotlib

    matplotlib.use("Agg")
    import matplotlib.pyplot as plt

    names = ["figures/planes.png", "figures/predictive_check.png", "plain/corner.png", "with_effects/corner.png"]
    names += [f"diagnose/{k}.png" for k in ("maps_before", "maps_after", "parity", "breakdown", "screen_1", "screen_2")]
    names += ["propose/proposal.png", "optimize/optimize.png"]
    for name in names:
        path = out / name
        path.parent.mkdir(parents=True, exist_ok=True)
        fig, ax = plt.subplots(figsize=(3, 2))
        ax.set_title(name, fontsize=7)
        fig.savefig(path, dpi=60)
        plt.close(fig)


@pytest.mark.skipif(chromium_path() is None, reason="no Chromium installed (Debian package 'chromium')")
def test_the_report_shows_the_sub_reports_numbers(tmp_path):
    """The demo's page rendered from a stored quick demo's JSON (summary.json, posterior.json,
    diagnosis.json: tests/cli/demo_report/), read back from headless Chromium: every
    headline number is the one those files hold."""
    from mfdesign.workflows.demo import demo_report

    shutil.copytree(FIXTURE, tmp_path, dirs_exist_ok=True)
    _stand_in_pictures(tmp_path)
    summary = json.loads((tmp_path / "summary.json").read_text())
    demo_report(tmp_path, summary).write(tmp_path)
    page = check_page(tmp_path / "index.html", tmp_path / "screenshot.png")
    assert page.broken_images == 0 and page.images >= 10
    assert_page_shows_the_numbers(page.lines, tmp_path)
    titles = [line for line in page.lines if line.startswith("Convergence of the chains")]
    assert len(titles) == 1


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
    from mfdesign.workflows.demo import _banners, _verdict

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
    from mfdesign.workflows.demo import _truth_table

    check = {
        "mu_pa": {"truth": 31700.0, "q05": 31597.0, "q95": 31818.0, "inside": True},
        "jm": {"truth": 39.6, "q05": 39.5, "q95": 39.67, "inside": True},
    }
    table = [{"parameter": "mu_pa", "unit": "Pa", "median": 31700.4}, {"parameter": "jm", "unit": "1", "median": 40.0}]
    rows = _truth_table(check, table)
    # one format per row: the truth, the median and the interval all in kPa (the page once
    # showed "3.17e+04" beside "31597 to 31818")
    assert rows[0] == {
        "parameter": "mu_pa",
        "unit": "kPa",
        "truth": 31.7,
        "median": 31.7,
        "90 % interval": "31.6 to 31.82",
        "inside": "yes",
    }
    assert rows[1]["unit"] == "1" and rows[1]["90 % interval"] == "39.5 to 39.67"


def test_posterior_tables_show_pascals_as_kilopascals():
    from mfdesign.workflows.demo import _display_rows

    rows = [{"parameter": "mu_pa", "unit": "Pa", "median": 33640.0, "q05": 33100.0, "q95": 34210.5}]
    assert _display_rows(rows) == [{"parameter": "mu_pa", "unit": "kPa", "median": 33.64, "q05": 33.1, "q95": 34.21}]
    assert _display_rows([{"parameter": "jm", "unit": "1", "median": 39.6}])[0]["median"] == 39.6


def test_calibrate_draws_truth_lines_only_for_the_bundled_dataset():
    from pathlib import Path

    from mfdesign.cli.calibrate import _bundled_truths
    from mfdesign.data.shipped import bundled_path

    truths = _bundled_truths([Path("bundled")])
    assert truths["mu_pa"] == 31700.0 and truths["pressure_sensor.offset_pa"] == 150.0
    assert _bundled_truths([bundled_path()]) == truths
    assert _bundled_truths([Path("mine.parquet")]) == {} and _bundled_truths([Path("bundled")] * 2) == {}


def _optimum(**kw):
    """An optimum as summary.json holds it (numbers made up for the test)."""
    opt = {
        "design": "[1.5, 26.5, nan, nan, nan, nan]",
        "task": "A",
        "limits": [],
        "alternatives": [],
        "alternatives_gap_pct": [],
        "tie_tol_pct": 2.0,
        "force_n": [9.81, 14.7, 19.6],
        "p_pa": [6900.0, 6900.0, 8300.0],
        "h_model_mm": [60.0, 50.0, 40.0],
        "simulator": {
            "h_sim_mm": [61.0, 49.5, 40.2],
            "status": ["OK"] * 3,
            "model_error_mm": [-1.0, 0.5, -0.2],
            "mae_mm": 0.57,
            "constants": {"constants": "calibrated"},
        },
        "unchecked": None,
    }
    return opt | kw


def test_the_headline_gives_the_simulators_heights_and_the_emulators_error():
    from mfdesign.workflows.demo import _optimum_headline, _optimum_table

    words = _optimum_headline(_optimum())
    assert words.startswith("Optimised for lift task A: [1.50, 26.50, nan, nan, nan, nan]")
    assert "the simulator (calibrated constants) lifts the loads to 61.0, 49.5, 40.2 mm" in words
    assert "the emulator's error there (emulator minus simulator): -1.0 to +0.5 mm" in words
    unchecked = _optimum_headline(_optimum(simulator=None, unchecked="stand-in physics"))
    assert "not checked by the simulator (stand-in physics): the heights are the model's word alone" in unchecked
    rows = _optimum_table(_optimum())
    assert [r["simulator height [mm]"] for r in rows] == [61.0, 49.5, 40.2]
    assert list(rows[0]) == [
        "load [N]",
        "pressure [kPa]",
        "emulator height [mm]",
        "simulator height [mm]",
        "emulator error [mm]",
    ]


def test_banners_state_the_limits_of_the_optimum_and_of_the_spread():
    """What the headline must not hide: an optimum at the grid's top and above the rig's
    travel, a near-tie, a simulator run far off the predicted spread, an unchecked optimum,
    and a simulator that puts the optimum elsewhere; none of them for a clean one."""
    from mfdesign.workflows.demo import _banners

    good = _diag(1.53, 0.32, 0.283, ["pressure_sensor"], "explained")
    conv = {"with_effects": {"converged": True}}
    assert (
        _banners(
            good, conv, _optimum(), [{"design": "[2, 30, nan, nan, nan, nan]", "rmse_n": 0.5, "predicted_std_n": 0.4}]
        )
        == []
    )
    top = "lift height of 9.81 N at 6.9 kPa is at the 80 mm top of the height grid"
    bad = _optimum(
        limits=[top, "thickness 1 mm is at the design space's lower bound 1 mm"],
        alternatives=["[1.6, 27.0, nan, nan, nan, nan]", "[1.4, 26.0, nan, nan, nan, nan]"],
        simulator=_optimum()["simulator"] | {"h_sim_mm": [None, 45.0, 40.2], "model_error_mm": [None, 5.0, -0.2]},
    )
    run = {"design": "[1.5, 30.0, nan, nan, nan, nan]", "rmse_n": 4.39, "predicted_std_n": 0.295}
    banners = _banners(good, conv, bad, [run])
    assert len(banners) == 4, banners
    spread, limit, tie, sim = banners
    assert "understated" in spread and "4.39 N RMS" in spread and "0.295 N RMS (15x)" in spread
    assert limit.startswith(f"The optimum for lift task A sits at a limit: {top}") and "1 more limit" in limit
    assert "near-tie: 2 other design(s) come within 2 % of its loss" in tie
    assert "simulator beyond the grid, 45.0, 40.2 mm against the emulator's 60.0, 50.0, 40.0 mm" in sim
    alone = _banners(good, conv, _optimum(simulator=None, unchecked="stand-in physics"))
    assert alone == ["The optimum for lift task A is the model's answer alone: stand-in physics."]
    # a membrane to build whose simulator check is far off its predicted spread is said too
    # (the check is a MadeRun's JSON: no design key of its own; the demo's first full run
    # fell over on that, KeyError 'design', after 514 s)
    check = {k: v for k, v in run.items() if k != "design"}
    proposed = {"design": "[2.0, 26.0, nan, nan, nan, nan]", "simulator_check": check}
    (said,) = _banners(good, conv, _optimum(), [], [proposed, {"design": "[1.0, 30.0, nan, nan, nan, nan]"}])
    assert said.startswith("The predicted spread is understated: at the proposed membrane") and "15x" in said


def test_the_page_puts_every_banner_above_the_first_number(tmp_path):
    """Without a browser: the stored quick demo's page (tests/cli/demo_report) carries its
    banners (chains, the understated spread, the optimum's limit, near-tie, no check) in
    the red box above the summary, and the headline says the optimum was not checked."""
    from markupsafe import escape  # Jinja's own escaping, as the page was written

    from mfdesign.workflows.demo import _optimum_headline, demo_report

    shutil.copytree(FIXTURE, tmp_path, dirs_exist_ok=True)
    _stand_in_pictures(tmp_path)
    # the stored diagnosis.json predates provenance (issue 41): readers need none
    assert "provenance" not in json.loads((tmp_path / "diagnose" / "diagnosis.json").read_text())
    summary = json.loads((tmp_path / "summary.json").read_text())
    demo_report(tmp_path, summary).write(tmp_path)
    page = (tmp_path / "index.html").read_text()
    first = page.index(escape(f"{summary['rows']} rows of {summary['membranes']} membranes"))
    kinds = ("has not converged", "spread is understated", "sits at a limit", "near-tie", "answer alone")
    for kind in kinds:
        banner = next(b for b in summary["banners"] if kind in b)
        assert 0 <= page.index(escape(banner)) < first, kind
    assert escape(_optimum_headline(summary["optimum"])) in page
    # One convergence rule, stated once (the page once wanted R-hat < 1.01 while summary.json
    # called a chain with R-hat 1.038 converged).
    from mfdesign.calibration.posterior import convergence_rule

    assert page.count(str(escape("Rule: " + convergence_rule()))) == 1 and "want &lt; 1.01" not in page


def test_planes_figure_shows_every_measured_membrane_with_a_height_key(tmp_path, monkeypatch):
    """The demo's planes figure once showed 4 of the 6 bundled membranes, with no key for
    the colours of the plate heights."""
    from types import SimpleNamespace

    from mfdesign.workflows import demo as _demo
    from mfdesign.data.store import read_parquet

    meas = read_parquet(_demo.BUNDLED)
    flat = SimpleNamespace(predict=lambda design, h, p: np.zeros((2, len(h))), noise_n=0.2)
    drawn = {}
    monkeypatch.setattr(_demo.outputs, "savefig", lambda fig, path, **kw: drawn.setdefault("fig", fig))
    _demo._plane_figure(meas, {"plain": flat, "with effects": flat}, tmp_path / "planes.png")
    fig = drawn["fig"]
    titles = [ax.get_title() for ax in fig.axes if ax.get_title()]
    assert len(titles) == len(meas.design_keys) == 6
    assert {_demo._short(k) + " mm" for k in meas.design_keys} == set(titles)
    assert any(ax.get_ylabel() == "plate height [mm]" for ax in fig.axes)  # the colour bar
    assert all(
        ax.get_xlabel() == "pressure [kPa]" and ax.get_ylabel() == "force [N]" for ax in fig.axes if ax.get_title()
    )


def test_the_page_gives_each_proposed_membranes_simulator_check(tmp_path):
    """Issue 43: a membrane the demo proposes to build is re-computed by the simulator before
    the page shows it; its section gives that check beside the proposal."""
    from markupsafe import escape

    from mfdesign.workflows.demo import demo_report

    shutil.copytree(FIXTURE, tmp_path, dirs_exist_ok=True)
    _stand_in_pictures(tmp_path)
    summary = json.loads((tmp_path / "summary.json").read_text())
    assert summary["proposals"], "the stored quick demo proposes membranes"
    taught = "model (sim fidelity) vs simulator 0.812 N RMS (max 2.1 N) over 255 points; predicted spread 0.5 N RMS"
    summary["proposals"][0]["simulator_check"] = {"state": "converged", "taught": taught, "checked": True}
    demo_report(tmp_path, summary).write(tmp_path)
    page = (tmp_path / "index.html").read_text()
    assert str(escape(f"simulator check (converged): {taught}")) in page
