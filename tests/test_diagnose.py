"""Diagnosis: residual breakdowns, noise floor, effect screen and full check on hidden effects.

Fast versions on the analytic stand-in simulator (``mfdesign.rig.virtual.analytic_plane``):
4 membranes, 1 Hz sampling, deflation on. The full sweep is ``experiments/hidden_effects.py``.
"""

from __future__ import annotations

import json

import numpy as np
import pandas as pd
import pytest

from mfdesign.design import Membrane
from mfdesign.diagnose import PlaneSimulator, compute_residuals, noise_floor, worst_regions
from mfdesign.diagnose.pipeline import diagnose
from mfdesign.physics import effects as fx
from mfdesign.rig.virtual import Protocol, VirtualRig, analytic_plane

KEYS = ("[2.0, 25.4, nan, nan, nan, nan]", "[1.0, 38.1, nan, nan, nan, nan]",
        "[1.5, 30.0, 45.0, 6.0, nan, nan]", "[2.0, 38.1, 47.55, 6.45, 62.0, 5.0]")
_CACHE: dict = {}


def virtual(hidden=(), seed=3, theta=None):
    key = (tuple(hidden), seed, json.dumps(theta, sort_keys=True))
    if key not in _CACHE:
        rig = VirtualRig(effects=list(hidden), theta=theta if theta is not None else fx.typical_theta(hidden),
                         seed=seed, simulator=analytic_plane, protocol=Protocol(deflate=True, sample_hz=1.0))
        _CACHE[key] = rig.run([Membrane.from_key(k) for k in KEYS], progress=False)
    return _CACHE[key]


def sim():
    return PlaneSimulator(simulator=analytic_plane)


def test_neutral_effects_change_nothing():
    m = virtual()
    s = sim()
    plain = s.expected_force(m)
    names = ["pressure_sensor", "load_cell_offset", "hysteresis", "rig_compliance", "contact_offset"]
    np.testing.assert_array_equal(s.expected_force(m, names, fx.neutral_theta(names)), plain)


def test_expected_force_reproduces_the_hidden_truth():
    """With the hidden effect at its true value the residual falls to the noise floor."""
    m = virtual(["pressure_sensor"])
    s = sim()
    before = compute_residuals(m, s.predict)
    after = compute_residuals(m, s.expected_force(m, ["pressure_sensor"], fx.typical_theta(["pressure_sensor"])))
    assert before.rmse_n > 1.5 * before.noise_floor_n
    assert after.rmse_n < 1.1 * after.noise_floor_n


def test_noise_floor_recovers_white_noise_under_a_smooth_trend():
    rng = np.random.default_rng(0)
    n, sd = 4000, 0.37
    t = np.arange(n) * 0.1
    frame = pd.DataFrame({"design_key": "a", "trial": np.repeat(np.arange(4), n // 4), "time_s": t,
                          "residual_n": 3.0 * np.sin(t / 20.0) + sd * rng.standard_normal(n)})
    assert noise_floor(frame) == pytest.approx(sd, rel=0.06)
    assert noise_floor(frame, robust=False) == pytest.approx(sd, rel=0.06)


def test_breakdowns_and_words_locate_an_injected_error():
    """A model that over-predicts by 3 N above 6 kPa on the thin ringless membrane only."""
    m = virtual()
    s = sim()
    df = m.df
    pred = s.predict(m)
    bad = (df["design_key"] == KEYS[1]).to_numpy() & (df["pressure_pa"] > 6000).to_numpy()
    res = compute_residuals(m, pred + 3.0 * bad)
    worst = worst_regions(res)
    top = worst[0]
    assert top["n_rings"] == 0 and top["thickness_mm"] == 1.0
    assert top["mean_n"] == pytest.approx(-3.0, abs=0.3)
    assert top["pressure_kpa"][0] >= 6.0
    assert "over-predicts" in top["words"] and "ringless 1 mm" in top["words"]


@pytest.mark.parametrize("hidden", ["load_cell_offset", "pressure_sensor", "hysteresis"])
def test_hidden_effect_found_first_and_error_falls_to_noise(hidden):
    m = virtual([hidden])
    d = diagnose(m, sim(), check_top=2, max_steps=1)
    assert d.steps[0]["screen"][0].effect == hidden
    assert d.found == [hidden]
    best = d.steps[0]["checks"][0]
    assert best.effects == (hidden,)
    assert best.heldout_rmse_n <= 1.2 * d.before.noise_floor_n
    true = fx.typical_theta([hidden])
    for k, v in d.theta.items():
        assert v == pytest.approx(true[k], abs=max(0.1 * abs(true[k]), 3 * d.steps[0]["verdict"]["stderr"][k], 1e-3))


def test_clean_control_claims_nothing():
    for seed in (11,):
        d = diagnose(virtual(seed=seed), sim(), check_top=2, max_steps=1)
        assert d.found == []
        assert d.steps[0]["verdict"]["status"] == "at_noise_floor"


def test_two_hidden_effects_are_both_found():
    hidden = ["pressure_sensor", "load_cell_offset"]
    d = diagnose(virtual(hidden), sim(), check_top=2, max_steps=2)
    assert sorted(d.found) == sorted(hidden)
    assert d.after.rmse_n <= 1.2 * d.before.noise_floor_n


def test_unexplained_structure_is_not_attributed():
    """A residual no effect can make (a bump at mid pressure on one membrane) is reported
    as unexplained instead of being forced onto an effect."""
    m = virtual()
    s = sim()
    df = m.df
    p = df["pressure_pa"].to_numpy()
    one = (df["design_key"] == KEYS[2]).to_numpy()
    bump = 2.0 * np.exp(-(((p - 3000.0) / 600.0) ** 2)) * one * (df["height_set_mm"].to_numpy() % 20 == 0)
    d = diagnose(m, s, model=lambda mm: s.predict(mm) - bump, check_top=2, max_steps=1)
    v = d.steps[0]["verdict"]
    assert v["status"] == "unexplained", v["words"]
    assert d.found == []
