"""Diagnosis: residual breakdowns, noise floor, effect screen and full check on hidden effects.

Fast versions on the analytic stand-in simulator: the virtual rig measures with
``mfdesign.rig.virtual.standin_plane`` and diagnosis runs on its JAX twin
(``EmulatorForwardModel(StandinForceModel())``: autodiff screen, nonlinear refit); 4 membranes, 1 Hz sampling,
deflation on. One test runs the emulator back end on a small random emulator. The full
sweep is ``experiments/hidden_effects.py``.
"""

from __future__ import annotations

import json

import numpy as np
import pandas as pd
import pytest

from mfdesign.design import Membrane
from mfdesign.diagnosis import compute_residuals, noise_floor, worst_regions
from mfdesign.diagnosis.forward import EmulatorForwardModel, emulator_plane
from mfdesign.models.standin import StandinForceModel
from mfdesign.diagnosis.pipeline import diagnose
from mfdesign.physics import effects as fx
from mfdesign.models.standin import standin_plane
from mfdesign.rig.virtual import Protocol, VirtualRig

KEYS = (
    "[2.0, 25.4, nan, nan, nan, nan]",
    "[1.0, 38.1, nan, nan, nan, nan]",
    "[1.5, 30.0, 45.0, 6.0, nan, nan]",
    "[2.0, 38.1, 47.55, 6.45, 62.0, 5.0]",
)
_CACHE: dict = {}


def virtual(hidden=(), seed=3, theta=None):
    key = (tuple(hidden), seed, json.dumps(theta, sort_keys=True))
    if key not in _CACHE:
        rig = VirtualRig(
            effects=list(hidden),
            theta=theta if theta is not None else fx.typical_theta(hidden),
            seed=seed,
            simulator=standin_plane,
            protocol=Protocol(deflate=True, sample_hz=1.0),
        )
        _CACHE[key] = rig.run([Membrane.from_key(k) for k in KEYS], progress=False)
    return _CACHE[key]


_SIM: dict = {}


def sim():
    """The forward model on the analytic stand-in (one instance: compiled code is shared)."""
    if "s" not in _SIM:
        _SIM["s"] = EmulatorForwardModel(StandinForceModel())
    return _SIM["s"]


def test_nonlinear_check_finds_load_cell_offset():
    """The screen and the nonlinear check on the stand-in find a hidden load-cell offset."""
    m = virtual(["load_cell_offset"])
    d = diagnose(m, sim(), candidates=["load_cell_offset", "pressure_sensor"], check_top=2, max_steps=1)
    assert d.found == ["load_cell_offset"]
    assert d.theta["load_cell_offset.offset_n"] == pytest.approx(0.8, abs=0.08)


def _random_emulator_data():
    """A small random emulator as the rig's truth (pressure offset 150 Pa hidden) and as the model."""
    from mfdesign.models.emulator import EmulatorConfig, default_ranges, init_emulator

    if "emu" not in _SIM:
        emu = init_emulator(EmulatorConfig(n_members=2, width=16, depth=2), np.zeros(14), np.ones(14), default_ranges())
        rig = VirtualRig(
            effects=["pressure_sensor"],
            theta={"pressure_sensor.offset_pa": 150.0},
            seed=5,
            simulator=emulator_plane(emu),
            protocol=Protocol(sample_hz=0.5, height_step_mm=2.0, pressure_step_pa=50.0),
        )
        _SIM["emu"] = (EmulatorForwardModel(emu), rig.run([Membrane.from_key(k) for k in KEYS[:3]], progress=False))
    return _SIM["emu"]


def test_emulator_backend_screen_ranks_a_hidden_pressure_offset_first():
    """Emulator back end, exact autodiff screen: pressure_sensor first, offset near 150 Pa."""
    from mfdesign.diagnosis.screen import screen

    model, m = _random_emulator_data()
    res = compute_residuals(m, model.predict)
    ranked = screen(res, m, model, ["pressure_sensor", "load_cell_offset", "contact_offset", "hysteresis"])
    assert ranked[0].effect == "pressure_sensor"
    assert ranked[0].structure_explained_fraction > 0.8  # of the residual above the noise floor
    se = ranked[0].stderr["pressure_sensor.offset_pa"]
    assert ranked[0].theta["pressure_sensor.offset_pa"] == pytest.approx(150.0, abs=max(45.0, 3 * se))


@pytest.mark.slow
def test_emulator_backend_finds_a_hidden_pressure_offset():
    """The whole search on the emulator back end (nonlinear refit: one slow compile)."""
    model, m = _random_emulator_data()
    d = diagnose(
        m, model, candidates=["pressure_sensor", "load_cell_offset", "contact_offset"], check_top=2, max_steps=1
    )
    assert d.found == ["pressure_sensor"], d.steps[0]["verdict"]["words"]
    se = d.steps[0]["verdict"]["stderr"]["pressure_sensor.offset_pa"]
    assert d.theta["pressure_sensor.offset_pa"] == pytest.approx(150.0, abs=max(15.0, 3 * se))


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
    frame = pd.DataFrame(
        {
            "design_key": "a",
            "trial": np.repeat(np.arange(4), n // 4),
            "time_s": t,
            "residual_n": 3.0 * np.sin(t / 20.0) + sd * rng.standard_normal(n),
        }
    )
    assert noise_floor(frame) == pytest.approx(sd, rel=0.06)
    assert noise_floor(frame, robust=False) == pytest.approx(sd, rel=0.06)


def test_noise_floor_is_right_for_rare_large_jumps():
    """Height read in whole mm times a steep dF/dh: mostly small noise, now and then a
    +-3 N jump. The default (mean-square) floor is the noise RMSE; the median-based one
    falls well short (what made held-out RMSE look 1.3x above the floor on clean data)."""
    rng = np.random.default_rng(1)
    n = 20000
    jumps = 3.0 * rng.choice([-1.0, 0.0, 1.0], size=n, p=[0.02, 0.96, 0.02])
    noise = 0.2 * rng.standard_normal(n) + jumps
    frame = pd.DataFrame(
        {
            "design_key": "a",
            "trial": np.repeat(np.arange(10), n // 10),
            "phase": np.tile(np.repeat(["inflate", "deflate"], n // 20), 10),
            "time_s": np.arange(n) * 0.1,
            "residual_n": noise + np.repeat(rng.normal(0, 5, 20), n // 20),
        }
    )
    rms = float(np.sqrt(np.mean(noise**2)))
    assert noise_floor(frame) == pytest.approx(rms, rel=0.05)
    assert noise_floor(frame, robust=True) < 0.6 * rms


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


@pytest.mark.parametrize(
    "hidden",
    [
        "pressure_sensor",
        pytest.param("load_cell_offset", marks=pytest.mark.slow),
        pytest.param("hysteresis", marks=pytest.mark.slow),
    ],
)
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


@pytest.mark.slow
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


def test_an_effect_the_force_model_cannot_represent_is_named_not_screened():
    """The emulator was never trained on a fabric inset: screened, the inset would read as
    'explains nothing'; it is named as not screened instead, with the reason."""
    import types

    from mfdesign.diagnosis.pipeline import unmodelled
    from mfdesign.models.emulator import load_default
    from mfdesign.models.standin import StandinForceModel

    names = ["fabric_inset", "contact_offset", "lift_preload", "thickness_deviation", "rubber_i2"]
    out = unmodelled(names, types.SimpleNamespace(force_model=load_default()))
    assert list(out) == ["fabric_inset", "rubber_i2"] and "fabric_inset_mm" in out["fabric_inset"]
    assert "i2_share" in out["rubber_i2"]
    assert unmodelled(names, types.SimpleNamespace(force_model=StandinForceModel())) == {}
