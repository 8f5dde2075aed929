"""The virtual rig: protocol, effects as hidden truth, bursts, reproducibility (same seed, same bytes).

Fast tests use the analytic stand-in simulator (``standin_plane``); one test runs the real
simulator on a small grid; the bit-for-bit regeneration of the bundled dataset is ``slow``.
"""

from __future__ import annotations

import hashlib
import importlib.util
import json
from pathlib import Path

import numpy as np
import pytest

from mfdesign.data.measurements import Measurements
from mfdesign.design import Membrane
from mfdesign.models.standin import standin_plane
from mfdesign.rig.virtual import Noise, Protocol, TruthPlane, VirtualRig
from mfdesign.units import G_M_S2 as G

ROOT = Path(__file__).resolve().parents[2]
RINGLESS = Membrane(2.0, 25.4)
RINGED = Membrane.from_key("[2.0, 25.4, 33.4, 5.0, 46.4, 5.0]")
SMALL = Protocol(heights_mm=(0.0, 30.0), trials_per_height=2, lift_trials=1, sample_hz=2.0)


def _rig(**kw):
    base = dict(seed=7, simulator=standin_plane, protocol=SMALL)
    base.update(kw)
    return VirtualRig(**base)


def _sha(path: Path) -> str:
    return hashlib.sha256(path.read_bytes()).hexdigest()


def test_protocol_shape():
    rig = _rig(protocol=Protocol(lift_trials=2))
    m = rig.run([RINGLESS, RINGED], progress=False)
    df = m.df
    assert set(df["source"]) == {"virtual"}
    f = df[df["experiment"] == "force"]
    # ringless: 8 heights x 3 trials, one pass; ringed: two passes (4.3 then 6.1 kPa) unless burst
    n_ringless = f[f["design_key"] == RINGLESS.key()]["trial"].nunique()
    assert n_ringless == 24
    ringed = f[f["design_key"] == RINGED.key()]
    burst = [e for e in rig.events if e["status"] == "burst" and e["design_key"] == RINGED.key()]
    assert ringed["trial"].nunique() == (48 if not burst else burst[0]["trial"])
    assert ringed["pressure_pa"].max() < 6100 + 100
    assert sorted(f["height_set_mm"].unique()) == [0, 10, 20, 30, 40, 50, 60, 70]
    # samples at 10 Hz on a 100 Pa/s ramp: time steps 0.1 s, time from 0 within a trial
    t = f[(f["design_key"] == RINGED.key()) & (f["trial"] == 0)]["time_s"].to_numpy()
    np.testing.assert_allclose(np.diff(t), 0.1)
    assert t[0] == 0.0 and t[-1] == pytest.approx(43.0)
    # lifts: 3 masses x 2 trials, trial ids after the force trials, force = m g
    lift = df[(df["experiment"] == "lift") & (df["design_key"] == RINGLESS.key())]
    assert sorted(lift["force_n"].unique()) == pytest.approx([1.5 * G, 2.5 * G, 4.0 * G])
    assert lift["trial"].min() == 24 and lift["trial"].nunique() == 6
    assert lift["height_set_mm"].isna().all()
    assert lift["height_mm"].max() <= 75 + 2


def test_ringless_stops_at_contact_ringed_at_limits():
    rig = _rig(protocol=Protocol(heights_mm=(30.0,), trials_per_height=1, lift_masses_kg=()), noise=Noise.none())
    rig.run([RINGLESS, RINGED], progress=False)
    ev = {(e["design_key"], e["trial"]): e for e in rig.events}
    e0 = ev[(RINGLESS.key(), 0)]
    # analytic rise = p / 250 - h / 2 reaches 20 mm at p = 250 * (20 + 15) = 8750 Pa
    assert e0["end_reason"] == "contact" and e0["peak_pa"] == pytest.approx(8750, abs=15)
    peaks = [
        ev[(RINGED.key(), k)]["peak_pa"]
        for k in (0, 1)
        if (RINGED.key(), k) in ev and ev[(RINGED.key(), k)]["status"] == "complete"
    ]
    assert peaks[0] == pytest.approx(4300)


def test_noise_and_quantisation():
    m = _rig().characterise(RINGLESS).df
    q = m["pressure_pa"] / (1e-4 * 6894.757293168)
    np.testing.assert_allclose(q, np.round(q), atol=1e-6)
    np.testing.assert_allclose(m["force_n"] * 100, np.round(m["force_n"] * 100), atol=1e-6)
    assert np.all(m["height_mm"] == np.round(m["height_mm"]))
    # no contact at p = 0: force readings are pure noise, ~0.2 N
    z = m[m["time_s"] == 0.0]["force_n"]
    assert abs(z.mean()) < 0.3


def test_hidden_effects_act():
    clean = dict(noise=Noise.none())
    plain = _rig(**clean).characterise(RINGLESS).df
    off = (
        _rig(effects=["pressure_sensor"], theta={"pressure_sensor.offset_pa": 150.0}, **clean).characterise(RINGLESS).df
    )
    # The rig ramps the pressure its transducer reads, so the offset shows as the recorded
    # force-pressure curve moved 150 Pa to the right (each reading 150 Pa above the truth).
    assert len(off) == len(plain)
    for trial, got in off.groupby("trial"):
        ref = plain[plain["trial"] == trial]
        moved = np.interp(got["pressure_pa"] - 150.0, ref["pressure_pa"], ref["force_n"], left=0.0)
        np.testing.assert_allclose(got["force_n"], moved, atol=1e-9)
    thick = (
        _rig(effects=["thickness_deviation"], theta={"thickness_deviation.relative": 0.2}, **clean)
        .characterise(RINGLESS)
        .df
    )
    assert len(thick) == len(plain)
    hi = plain["force_n"] > 1
    assert np.all(thick["force_n"][hi] <= plain["force_n"][hi] + 1e-9)  # stiffer: contacts later
    assert np.any(thick["force_n"][hi] < plain["force_n"][hi] - 0.1)
    # per-membrane override
    per = (
        _rig(
            effects=["thickness_deviation"],
            membrane_theta={RINGLESS.key(): {"thickness_deviation.relative": 0.2}},
            **clean,
        )
        .characterise(RINGLESS)
        .df
    )
    np.testing.assert_array_equal(per["force_n"], thick["force_n"])
    # Mullins: only trial 0 differs
    at30 = Protocol(heights_mm=(30.0, 0.0), trials_per_height=2, lift_trials=1, sample_hz=2.0)
    plain30 = _rig(protocol=at30, **clean).characterise(RINGLESS).df
    soft = (
        _rig(effects=["stress_softening"], theta={"stress_softening.stiffening": 0.3}, protocol=at30, **clean)
        .characterise(RINGLESS)
        .df
    )
    diff = soft["force_n"].to_numpy() != plain30["force_n"].to_numpy()
    assert set(plain30["trial"][diff]) == {0}


def test_bursts_drop_the_trial_and_end_the_membrane():
    # a low threshold: the first trial bursts at the threshold; nothing is recorded
    proto = Protocol(heights_mm=(0.0, 30.0), trials_per_height=2, burst_locking_mean=0.3, burst_locking_sd=0.0)
    rig = _rig(protocol=proto)
    m = rig.run([RINGED], progress=False)
    assert len(m.df) == 0
    (ev,) = rig.events
    assert ev["status"] == "burst" and ev["trial"] == 0 and ev["burst_locking"] > 0.3


def test_lift_trajectory_follows_the_plane():
    rig = _rig(noise=Noise.none(), protocol=Protocol(lift_trials=1))
    m = rig.mass_lift(RINGLESS, 1.5).df
    plane = rig.truth_plane(RINGLESS)
    # at every sample the plane's force at (h, p) equals the load where the plate is lifted
    lifted = (m["height_mm"] > 0.5) & (m["height_mm"] < 74)
    f = plane.at(plane.force_n, m["height_mm"][lifted].to_numpy(), m["pressure_pa"][lifted].to_numpy())
    np.testing.assert_allclose(f, 1.5 * G, rtol=0.05)
    assert np.all(np.diff(m["height_mm"].to_numpy()) >= -1e-9)  # analytic plane: monotone lift


def test_same_seed_same_bytes(tmp_path):
    paths = []
    for k, seed in enumerate((11, 11, 12)):
        m = _rig(
            seed=seed,
            effects=["pressure_sensor", "hysteresis"],
            theta={"pressure_sensor.offset_pa": 150.0, "hysteresis.loss": 0.05},
            protocol=Protocol(heights_mm=(0.0, 30.0), trials_per_height=2, deflate=True, sample_hz=2.0, lift_trials=1),
        ).run([RINGLESS, RINGED], progress=False)
        p = tmp_path / f"run{k}.parquet"
        m.to_parquet(p)
        paths.append(p)
    assert _sha(paths[0]) == _sha(paths[1])
    assert _sha(paths[0]) != _sha(paths[2])
    back = Measurements.from_parquet(paths[0])
    assert (back.df["phase"] == "deflate").any()
    # a membrane's data do not depend on which other membranes run
    alone = (
        _rig(
            seed=11,
            effects=["pressure_sensor", "hysteresis"],
            theta={"pressure_sensor.offset_pa": 150.0, "hysteresis.loss": 0.05},
            protocol=Protocol(heights_mm=(0.0, 30.0), trials_per_height=2, deflate=True, sample_hz=2.0, lift_trials=1),
        )
        .run([RINGED], progress=False)
        .df
    )
    both = back.df[back.df["design_key"] == RINGED.key()].reset_index(drop=True)
    assert alone.equals(both)


def test_plane_cache(tmp_path):
    rig = _rig(cache_dir=tmp_path)
    a = rig.truth_plane(RINGED)
    files = list(tmp_path.glob("plane_*.npz"))
    assert len(files) == 1
    b = TruthPlane.from_npz(files[0])
    np.testing.assert_array_equal(a.force_n, b.force_n)
    again = _rig(cache_dir=tmp_path).characterise(RINGED).df
    np.testing.assert_array_equal(again["force_n"], rig.characterise(RINGED).df["force_n"])


def _load_script(monkeypatch):
    """The bundling script as a module. It imports ``_common`` from its own folder, which
    ``python experiments/make_bundled_dataset.py`` puts first on the path; so does this
    (for the one test only)."""
    monkeypatch.syspath_prepend(str(ROOT / "experiments"))
    spec = importlib.util.spec_from_file_location(
        "make_bundled_dataset", ROOT / "experiments" / "make_bundled_dataset.py"
    )
    mod = importlib.util.module_from_spec(spec)
    spec.loader.exec_module(mod)
    return mod


def test_dataset_script_is_reproducible_tiny(tmp_path, monkeypatch):
    """The bundling script's code path, bit for bit, on a tiny run with the analytic simulator."""
    mod = _load_script(monkeypatch)
    kw = dict(designs=[RINGLESS, RINGED], simulator=standin_plane, protocol=SMALL, cache_dir=None)
    a = mod.build(tmp_path / "a", **kw)
    b = mod.build(tmp_path / "b", **kw)
    assert _sha(a["parquet"]) == _sha(b["parquet"])
    card = json.loads(Path(a["card"]).read_text())
    assert card["seed"] == mod.SEED and card["hidden_effect"]["name"] == mod.HIDDEN_EFFECT
    assert card["sha256"] == _sha(a["parquet"])


def test_bundled_dataset_is_valid():
    card_path = ROOT / "mfdesign" / "data" / "files" / "bundled_card.json"
    if not card_path.is_file():
        pytest.skip("bundled dataset not generated yet (python experiments/make_bundled_dataset.py)")
    card = json.loads(card_path.read_text())
    pq = card_path.parent / card["file"]
    assert pq.stat().st_size <= 5 * 1024 * 1024
    assert _sha(pq) == card["sha256"]
    m = Measurements.from_parquet(pq)
    assert len(m.df) == card["n_rows"]
    assert set(m.df["source"]) == {"virtual"}


@pytest.mark.slow
def test_real_simulator_small_plane():
    """The rig on the real simulator: a small plane of a ringless membrane (compiles: ~1-2 min)."""
    proto = Protocol(
        heights_mm=(30.0,),
        trials_per_height=1,
        ringless_limit_pa=2000.0,
        lift_masses_kg=(),
        lift_limit_pa=2000.0,
        lift_height_max_mm=0.0,
        height_step_mm=40.0,
        pressure_step_pa=500.0,
    )
    rig = VirtualRig(seed=0, protocol=proto)
    plane = rig.truth_plane(RINGLESS)
    assert plane.force_n.shape == (len(plane.h_grid), 5)  # pressures {0 (added), 500, .., 2000}
    assert 30.0 in plane.h_grid
    m = rig.characterise(RINGLESS).df
    assert len(m) > 0 and m["force_n"].max() > 1.0


@pytest.mark.slow
def test_bundled_dataset_regenerates_bit_for_bit(tmp_path, monkeypatch):
    card_path = ROOT / "mfdesign" / "data" / "files" / "bundled_card.json"
    if not card_path.is_file():
        pytest.skip("bundled dataset not generated yet")
    card = json.loads(card_path.read_text())
    from mfdesign.rig.virtual import simulator_fingerprint

    if card["simulator_fingerprint"] != simulator_fingerprint():
        pytest.skip("the simulator's source changed since the dataset was made: regenerate it")
    out = _load_script(monkeypatch).build(tmp_path, cache_dir=None)
    assert _sha(Path(out["parquet"])) == card["sha256"]


def test_a_rig_from_the_bundled_card_is_the_rig_the_card_describes():
    """``VirtualRig.from_card``: the card's hidden effect, seed, noise and protocol (the
    stand-in demo measures its world with it); overrides change only what they name."""
    from mfdesign.data.shipped import bundled_card_path

    card = json.loads(bundled_card_path().read_text())
    rig = VirtualRig.from_card(card, simulator=standin_plane)
    assert [e.name for e in rig.effects] == [card["hidden_effect"]["name"]]
    assert rig.theta == card["hidden_effect"]["theta"] and rig.seed == card["seed"]
    assert rig.noise.force_sd_n == card["noise"]["force_sd_n"] > 0
    assert list(rig.protocol.heights_mm) == card["protocol"]["heights_mm"]
    assert rig.protocol.sample_hz == card["protocol"]["sample_hz"]
    quiet = VirtualRig.from_card(card, simulator=standin_plane, seed=7, noise=Noise.none(), sample_hz=2.0)
    assert quiet.seed == 7 and quiet.noise == Noise.none() and quiet.protocol.sample_hz == 2.0
    assert quiet.protocol.heights_mm == rig.protocol.heights_mm
    # the truth itself: a noise-free trial reads the hidden offset on an exact plane
    one = quiet.run([Membrane.from_key(card["designs"][1])], lift=False, progress=False).df
    assert len(one) > 10 and np.all(np.isfinite(one["force_n"]))


def test_the_stiff_rings_world_differs_from_the_standin_only_on_ringed_membranes():
    """``StandinWorld`` (issue 41's world the model does not hold): a ringless membrane's
    plane is the stand-in's; a ringed one needs more pressure to reach the plate, so it
    pushes less; its repr (the rig's plane-cache key) names the coefficient."""
    from mfdesign.design import Membrane
    from mfdesign.models.standin import RING_COEFFICIENT, StandinWorld, standin_plane

    h, p = [10.0, 30.0, 50.0], [2000.0, 4000.0, 6000.0]
    ringless, ringed = Membrane(2.0, 25.4), Membrane.from_key("[2.0, 25.4, 33.4, 5.0, 46.4, 5.0]")
    world = StandinWorld(0.65)
    assert np.array_equal(world(ringless, h, p).force_n, standin_plane(ringless, h, p).force_n)
    assert np.all(world(ringed, h, p).force_n < standin_plane(ringed, h, p).force_n)
    assert StandinWorld(RING_COEFFICIENT)(ringed, h, p).force_n == pytest.approx(standin_plane(ringed, h, p).force_n)
    assert repr(world) == "StandinWorld(ring_coefficient=0.65)"
