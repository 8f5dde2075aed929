"""Where lift plates stall, from the data alone: found where the pressure climbs with the
plate still, and classed by the other trials (repeated mid-travel, at the top, one-off)."""

import numpy as np
import pandas as pd

from mfdesign.data.lifts import stalls
from mfdesign.diagnosis.residuals import stall_words


def _trial(trial, force, stops, top_mm=40.0, key="[2.0, 38.1, 47.55, 6.45, 62.0, 5.0]"):
    """A plate rising 10 mm/kPa from 2 kPa, read in whole mm, with the pressure climbing
    ``kpa`` at each height of ``stops`` {height: kpa} and 1 kPa at its top (a hold)."""
    p, h, pa = [], [], 2000.0
    for mm in range(0, int(top_mm) + 1):
        n = 2 + int(20 * stops.get(mm, 0.0))  # 50 Pa a sample
        for _ in range(n):
            p.append(pa)
            h.append(float(mm))
            pa += 50.0
    p += list(pa + np.arange(1, 21) * 50.0)
    h += [top_mm] * 20
    return pd.DataFrame(dict(design_key=key, trial=trial, experiment="lift", height_mm=h, pressure_pa=p, force_n=force))


def test_stalls_are_found_and_classed_by_the_other_trials():
    df = pd.concat(
        [
            _trial(0, 14.7, {25: 0.8}),
            _trial(1, 14.7, {26: 0.6}),  # the same step 1 mm higher: repeated
            _trial(2, 24.5, {18: 0.9}),
            _trial(3, 24.5, {}),  # the replicate runs through: a one-off
            pd.DataFrame(
                dict(
                    design_key="x",
                    trial=9,
                    experiment="force",
                    height_mm=[10.0] * 50,
                    pressure_pa=np.arange(50) * 100.0,
                    force_n=5.0,
                )
            ),
        ],
        ignore_index=True,
    )
    s = stalls(df)
    got = {(r.trial, r.height_mm): (r.at_top, r.repeats) for r in s.itertuples()}
    assert got[(0, 25.0)] == (False, True) and got[(1, 26.0)] == (False, True)
    assert got[(2, 18.0)] == (False, False)
    assert all(got[(t, 40.0)] == (True, True) for t in range(4))  # every trial holds at its top
    assert set(got) == {(0, 25.0), (1, 26.0), (2, 18.0)} | {(t, 40.0) for t in range(4)}  # force rows ignored
    assert (s["spent_pa"] > 400).all()
    (line,) = stall_words(s)
    assert "repeated by another trial of the same mass" in line and "14.7 N: 25-26 mm" in line
    assert "not repeated by the other trial" in line and "24.5 N: 18 mm" in line


def test_a_steadily_rising_plate_has_no_stall():
    s = stalls(_trial(0, 14.7, {}, top_mm=40.0).iloc[:-20])  # no hold at the top either
    assert s.empty and list(s.columns)[:4] == ["design_key", "trial", "force_n", "height_mm"]
    assert stall_words(s) == []
