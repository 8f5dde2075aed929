"""Shortened characterisation and mass-lift jobs end to end through the pseudo-terminal."""

import numpy as np
import pytest

from mfdesign.units import G_M_S2
from mfdesign.data.measurements import Measurements
from mfdesign.design import Membrane
from mfdesign.rig.procedures import (
    JobError,
    iter_trial_events,
    lift_plan,
    membrane_plan,
    run_job,
    set_height,
    to_measurements,
)
from mfdesign.rig.protocol import RigConnection

from test_rig_support import (
    RINGED,
    RINGLESS,
    assert_no_lost_samples,
    emulator,
    fast_config,
    log_text,
)


def test_characterisation_ringed_end_to_end(tmp_path):
    cfg = fast_config()
    d = Membrane.from_key(RINGED)
    plan = membrane_plan(d, heights_mm=(0, 20), trials=2, source="virtual")
    with emulator(RINGED, config=cfg) as em:
        res = run_job(em.port, tmp_path, plan, cfg, progress=False)
    assert res.status == "complete" and len(res.trials_run) == 8  # 2 heights x 2 trials x 2 stages
    assert {r.end_reason for r in res.trials_run} == {"pressure_limit"}
    assert_no_lost_samples(em, tmp_path)
    m = to_measurements(tmp_path)
    assert isinstance(m, Measurements)
    df = m.df
    assert set(df["trial"]) == {0, 1, 2, 3}  # stage 0 (4.3 kPa): trials 0-1, retest (6.1 kPa): 2-3
    assert set(df["phase"]) == {"inflate", "deflate"} and set(df["source"]) == {"virtual"}
    assert (df["design_key"] == d.key()).all() and (df["experiment"] == "force").all()
    err = (df["height_mm"] - df["height_set_mm"]).abs()
    assert (err.groupby(df["trial"]).median() <= 1.0).all() and (err <= 1.5).all()  # 1 mm (+ sensor noise)
    peak = df.groupby("trial")["pressure_pa"].max()
    # overshoot past the limit is the host's reaction time x pump rate (x25 in accelerated time,
    # so a loaded machine can overshoot by kPa here; at real time it is a few Pa)
    assert (peak[[0, 1]] > 4300).all() and (peak[[2, 3]] > 6100).all()
    low = df[(df["height_set_mm"] == 0) & (df["trial"] == 2)]
    assert low["force_n"].max() > 20  # the plant pushes on a low plate
    assert (df.groupby("trial")["time_s"].min() == 0).all()
    log = log_text(tmp_path)
    assert "job complete: 8 trials" in log and "SAFE STATE (session end)" in log
    # run again: nothing left to do, nothing duplicated
    with emulator(RINGED, config=cfg) as em:
        res2 = run_job(em.port, tmp_path, plan, cfg, progress=False)
    assert res2.trials_run == [] and res2.skipped == 8 and len(to_measurements(tmp_path)) == len(m)


def test_ringless_until_contact(tmp_path):
    cfg = fast_config()
    plan = membrane_plan(Membrane.from_key(RINGLESS), heights_mm=(10,), trials=1, source="virtual")
    assert plan.pressure_limits_pa == (10000.0,)
    with emulator(RINGLESS, config=cfg) as em:
        res = run_job(em.port, tmp_path, plan, cfg, progress=False)
    assert [r.end_reason for r in res.trials_run] == ["contact"]
    assert res.trials_run[0].peak_pa < 5000


def test_mass_lift_job(tmp_path):
    cfg = fast_config()
    d = Membrane.from_key(RINGLESS)
    plan = lift_plan(d, 1.5, trials=1, pressure_limit_pa=4000, source="virtual")
    with emulator(RINGLESS, config=cfg, payload_kg=1.5) as em:
        res = run_job(em.port, tmp_path, plan, cfg, progress=False)
    assert res.status == "complete"
    df = to_measurements(tmp_path).df
    assert (df["experiment"] == "lift").all() and df["height_set_mm"].isna().all()
    assert np.allclose(df["force_n"], 1.5 * G_M_S2)
    inflate = df[df["phase"] == "inflate"]
    assert inflate["height_mm"].iloc[-1] > inflate["height_mm"].iloc[0] + 10  # the mass went up
    assert_no_lost_samples(em, tmp_path)


@pytest.mark.parametrize("push_lowers", [True, False])
def test_set_height_both_wirings(push_lowers):
    cfg = fast_config(push_lowers_plate=push_lowers)
    with emulator(config=cfg, start_height_mm=30.0) as em, RigConnection(em.port, cfg) as conn:
        for target in (12.0, 47.5):
            h = set_height(conn, target)
            assert abs(h - target) <= 1.0
            assert abs(em.pos["left"] - target) <= 1.0 and abs(em.pos["right"] - target) <= 1.0
        with pytest.raises(ValueError, match="outside the rig"):
            set_height(conn, 200.0)


def test_job_dir_with_another_plan_is_refused(tmp_path):
    cfg = fast_config()
    d = Membrane.from_key(RINGLESS)
    with emulator(config=cfg) as em:
        run_job(em.port, tmp_path, membrane_plan(d, heights_mm=(20,), trials=1, source="virtual"), cfg, progress=False)
    with pytest.raises(JobError, match="different job"):
        run_job(em.port, tmp_path, membrane_plan(d, heights_mm=(30,), trials=1), cfg, progress=False)
    with pytest.raises(JobError, match="hard limit"):
        run_job("/dev/null", tmp_path / "x", membrane_plan(d, ringless_limit_pa=20000.0), cfg)
    ends = [e for e in iter_trial_events(tmp_path) if e["event"] == "end"]
    assert len(ends) == 1 and ends[0]["status"] == "complete" and ends[0]["burst"] is False
