"""mfdesign.discriminate and ``mfdesign discriminate`` (issue 42 item 4).

Stand-in physics, virtual-rig data of one membrane at three heights and tiny chains (as
tests/test_campaign.py's ``rig_data``): these check the criterion's bookkeeping and
behaviour (deterministic, zero between equal predictives, larger where the hypotheses
part), the input checks and the command's exit codes, not the fits' quality.
"""

from __future__ import annotations

import json

import numpy as np
import pytest
from typer.testing import CliRunner

from mfdesign.cli import app
from mfdesign.discriminate import (
    BOX_HILL_1967,
    Experiment,
    Hypothesis,
    candidate_experiments,
    hypothesis_probabilities,
    outside_rig,
    parse_hypotheses,
    rank_experiments,
)
from mfdesign.errors import InputError

runner = CliRunner()
KEY = "[2.0, 25.4, nan, nan, nan, nan]"
NEW = "[2.0, 15.0, nan, nan, nan, nan]"
RINGLESS = tuple(float(v) for v in (2.0, 25.4, "nan", "nan", "nan", "nan"))


def rig_data(seed: int = 1):
    """Force trials of one membrane on the virtual rig (stand-in simulator, a hidden 1.2 mm
    fabric inset) at 3 heights, 0.2 samples a second."""
    from mfdesign.design import Membrane
    from mfdesign.models.standin import standin_plane
    from mfdesign.physics.params import SimParams
    from mfdesign.rig.virtual import Protocol, VirtualRig

    rig = VirtualRig(
        effects=["fabric_inset"],
        theta={"fabric_inset.inset_mm": 1.2},
        seed=seed,
        protocol=Protocol(sample_hz=0.2, trials_per_height=1, heights_mm=(0.0, 20.0, 40.0)),
        simulator=standin_plane,
        base_params=SimParams(mu_pa=34e3, jm=45.0),
    )
    return rig.run([Membrane.from_key(KEY)], lift=False, progress=False)


@pytest.fixture(scope="module")
def fits():
    from mfdesign.calibration.workflow import fit_multi_fidelity
    from mfdesign.models.ensemble import EnsembleConfig

    table = rig_data()
    out = {}
    for name, effects in (("fabric_inset", ["fabric_inset"]), ("none", [])):
        out[name] = fit_multi_fidelity(
            table,
            "standin",
            effects,
            n_steps=40,
            n_walkers=16,
            max_rows=60,
            ensemble_config=EnsembleConfig(n_members=2, steps=20, monotone=False),
            progress=False,
            stop_when_converged=False,
        )
    return table, out


def test_ranking_is_deterministic_and_says_what_each_hypothesis_predicts(fits):
    _, f = fits
    cands = candidate_experiments([KEY], [NEW], height_sets_mm=((0.0,), (0.0, 40.0)), masses_kg=(2.5,))
    a = rank_experiments(f, cands, n_draws=8, n_pressures=4, seed=3)
    b = rank_experiments(f, cands, n_draws=8, n_pressures=4, seed=3)
    assert np.array_equal(a.order, b.order) and np.array_equal(a.score, b.score)
    assert a.hypotheses == ("fabric_inset", "none") and "Box" in a.method == BOX_HILL_1967
    entry = a.entry(a.top(1)[0])
    for h in ("fabric_inset", "none"):
        p = entry["predictions"]["by_hypothesis"][h]
        assert len(p["mean"]) == len(entry["predictions"]["rows"]) and np.all(np.array(p["lo"]) <= np.array(p["hi"]))
    assert entry["predictions"]["level"] == 0.9 and 0.0 <= entry["expected_p_truth"] <= 1.0
    assert len(a.lines(3)) == 3 * 3  # a line per experiment, one per hypothesis under it


def test_equal_predictives_score_zero_and_a_parting_candidate_beats_a_silent_one(fits):
    _, f = fits
    silent = Experiment(RINGLESS, "force", 60.0, (60.0,), cost=1.0)  # 60 Pa at 60 mm: no contact, 0 N
    parting = Experiment((2.0, 15.0, np.nan, np.nan, np.nan, np.nan), "force", 6000.0, (0.0, 20.0), True, cost=5.0)
    r = rank_experiments(f, [silent, parting], n_draws=8, n_pressures=5, seed=0)
    assert r.score[1] > r.score[0] + 0.5 and list(r.order) == [1, 0]
    same = rank_experiments({"a": f["none"], "b": f["none"]}, [silent, parting], n_draws=8, n_pressures=5)
    assert np.all(np.abs(same.score) < 0.05), same.score  # the same predictive: nothing to learn
    assert np.allclose(same.p_truth, 0.5, atol=0.02)


class _NanAbove:
    """A predictive with no number above ``h_max`` mm (as the exact model outside the physical
    model or off its planes): the rows there must not count, a candidate with no other row
    must not be scored."""

    def __init__(self, inner, h_max):
        self._inner, self.h_max = inner, h_max

    def thinned(self, n):
        return _NanAbove(self._inner.thinned(n), self.h_max)

    def __getattr__(self, name):
        return getattr(self._inner, name)

    def sample_data(self, data, key):
        f = np.asarray(self._inner.sample_data(data, key))
        return np.where(np.asarray(data.rows.h_mm)[None, :] > self.h_max, np.nan, f)


def test_rows_without_a_number_are_left_out_and_a_candidate_without_any_is_not_scored(fits):
    _, f = fits
    nan_fit = {"fabric_inset": _NanAbove(f["fabric_inset"].mf, 30.0), "none": f["none"]}
    high = Experiment(RINGLESS, "force", 6000.0, (40.0,), cost=1.0)  # every row above 30 mm: no number
    mixed = Experiment(RINGLESS, "force", 6000.0, (0.0, 40.0), cost=1.0)
    low = Experiment(RINGLESS, "force", 6000.0, (0.0,), cost=1.0)
    r = rank_experiments(nan_fit, [high, mixed, low], n_draws=8, n_pressures=4, seed=0)
    assert r.unscored == (0,) and sorted(r.order) == [1, 2] and np.all(np.isfinite(r.score[[1, 2]]))
    counted = r.predictions[1]["counted"]
    assert counted == [True] * 4 + [False] * 4  # h = 0 counted, h = 40 mm not
    # what each hypothesis predicts there is said as it is: no number (NaN), not a zero
    mean = np.asarray(r.predictions[1]["by_hypothesis"]["fabric_inset"]["mean"], float)
    assert np.all(np.isfinite(mean[:4])) and np.all(np.isnan(mean[4:]))
    with pytest.raises(InputError, match="no finite prediction for any"):
        rank_experiments(nan_fit, [high], n_draws=8, n_pressures=4, seed=0)


def test_bad_input_fails_in_one_line():
    with pytest.raises(InputError, match="unknown effect 'fabric_insert'") as e:
        parse_hypotheses(["fabric_inset", "fabric_insert"])
    assert "\n" not in str(e.value)
    with pytest.raises(InputError, match="at least two"):
        parse_hypotheses(["fabric_inset"])
    with pytest.raises(InputError, match="same model"):
        parse_hypotheses(["fabric_inset+ring_stiffening", "ring_stiffening+fabric_inset"])
    with pytest.raises(InputError, match="material"):
        Hypothesis.parse("none:steel")
    with pytest.raises(InputError, match="kind"):
        Experiment(RINGLESS, "burst", 100.0)
    with pytest.raises(InputError, match="load"):
        Experiment(RINGLESS, "lift", 100.0)
    with pytest.raises(InputError, match="design"):
        candidate_experiments(["[2.0, nope]"])
    assert (
        Hypothesis.parse("none").effects == ()
        and Hypothesis.parse("a:coupons".replace("a", "none")).material == "coupons"
    )
    with pytest.raises(InputError, match="option 'latents'.*no-latents"):
        Hypothesis.parse("fabric_inset:coupons,latents")


def test_hypothesis_options_per_membrane_and_latents():
    h = Hypothesis.parse("fabric_inset[m]+ring_stiffening:coupons,no-latents")
    assert h.effects == ("fabric_inset", "ring_stiffening") and h.per_membrane == ("fabric_inset",)
    assert h.material == "coupons" and h.latents is False
    shared = Hypothesis.parse("fabric_inset+ring_stiffening:coupons,no-latents")
    assert shared.per_membrane == () and shared.key != h.key
    pairs = outside_rig([shared, h])
    assert "differ from one to the next" in pairs[0]["measurements"]["fabric_inset"]
    with pytest.raises(InputError, match="unknown effect 'fabric_insert'"):
        Hypothesis.parse("fabric_insert[m]")


def test_probabilities_and_outside_measurements():
    p = hypothesis_probabilities([100.0, 100.0 + 2 * np.log(19.0)])
    assert np.allclose(p, [0.95, 0.05])
    pairs = outside_rig(parse_hypotheses(["fabric_inset", "fabric_inset+ring_stiffening", "thickness_deviation"]))
    assert pairs[0]["pair"] == ["fabric_inset", "fabric_inset+ring_stiffening"]
    assert "hoop" in pairs[0]["measurements"]["ring_stiffening"]
    assert "thickness" in pairs[1]["measurements"]["thickness_deviation"]


def test_cli_ranks_and_bad_hypothesis_exits_2(tmp_path):
    from mfdesign.data.store import write_parquet

    data = write_parquet(rig_data(), tmp_path / "d.parquet")
    r = runner.invoke(
        app,
        [
            "discriminate",
            str(data),
            "--hypotheses",
            "fabric_inset",
            "bogus",
            "--physics",
            "standin",
            "--out",
            str(tmp_path / "x"),
        ],
    )
    assert r.exit_code == 2 and "unknown effect 'bogus'" in r.output and len(r.output.strip().splitlines()) == 1, (
        r.output
    )
    r = runner.invoke(
        app,
        [
            "discriminate",
            str(data),
            "--hypotheses",
            "fabric_inset",
            "none",
            "--physics",
            "emulator",
            "--out",
            str(tmp_path / "e"),
        ],
    )  # the emulator holds the fabric inset at 0: refused before any fit, not a NaN fit
    assert r.exit_code == 2 and "fabric_inset_mm" in r.output and len(r.output.strip().splitlines()) == 1, r.output
    out = tmp_path / "o"
    args = [
        "discriminate",
        str(data),
        "--hypotheses",
        "fabric_inset",
        "none",
        "--physics",
        "standin",
        "--out",
        str(out),
    ]
    r = runner.invoke(app, args + ["--mcmc-steps", "40", "--max-rows", "60", "--new-design", NEW, "--top", "2"])
    assert r.exit_code == 0, r.output
    doc = json.loads((out / "discriminate.json").read_text())
    assert doc["ranked"][0]["rank"] == 1 and {h["name"] for h in doc["hypotheses"]} == {"fabric_inset", "none"}
    assert (out / "discriminate.png").is_file() and "1. " in r.output and "Box & Hill" in r.output
