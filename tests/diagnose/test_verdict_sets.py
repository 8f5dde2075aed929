"""The verdict over sets of different sizes and over ties (no physics: CheckResults by hand).

* a pair is claimed only where it beats the best single effect by the claim's margins;
* two sets the data cannot tell apart are both named, never one silently;
* a candidate without model values on its rows is "not evaluated" with the rows named.
"""

from __future__ import annotations

import numpy as np
import pandas as pd

from mfdesign.diagnosis.check import verdict
from mfdesign.diagnosis.refit import CheckResult, _undefined_words
from mfdesign.diagnosis.residuals import Residuals


def _res(rms: float = 2.0, floor: float = 0.3) -> Residuals:
    class R:  # the verdict reads only these two numbers (and the shape on "unexplained")
        noise_floor_n = floor
        rmse_n = rms

    return R()  # type: ignore[return-value]


def _check(effects, heldout, dbic, base=2.0, floor=0.3, theta=None, undefined=""):
    return CheckResult(
        effects=tuple(effects),
        theta=theta or {f"{e}.x": 1.0 for e in effects},
        stderr={f"{e}.x": 0.1 for e in effects},
        rmse_n=heldout,
        heldout_rmse_n=heldout,
        heldout_rmse_base_n=base,
        delta_bic=dbic,
        n_eff=500.0,
        noise_floor_n=floor,
        undefined=undefined,
    )


def test_a_pair_must_beat_the_best_single_by_the_margins():
    single = _check(["a"], 0.34, -900.0)
    small_gain = _check(["a", "b"], 0.33, -905.0)  # 3 % and 5 BIC better: not worth a second effect
    v = verdict(_res(), [single, small_gain])
    assert v["effects"] == ["a"]
    big_gain = _check(["a", "b"], 0.30, -1400.0)
    v = verdict(_res(), [single, big_gain])
    assert v["effects"] == ["a", "b"]
    assert v["status"] == "explained"


def test_a_pair_found_when_every_single_explains_little():
    # two effects together: each alone leaves 2.5x the floor; the pair reaches it
    v = verdict(_res(), [_check(["c"], 0.80, -300.0), _check(["a"], 0.78, -320.0), _check(["a", "b"], 0.32, -1500.0)])
    assert v["effects"] == ["a", "b"]


def test_ties_are_named_both():
    a = _check(["thickness_deviation"], 0.320, -1000.0)
    b = _check(["pressure_sensor"], 0.325, -995.0)
    c = _check(["load_cell_offset"], 0.500, -600.0)
    v = verdict(_res(), [a, b, c])
    assert v["effects"] == ["thickness_deviation"]
    assert [alt["effects"] for alt in v["alternatives"]] == [["pressure_sensor"]]
    assert "cannot tell it from pressure_sensor" in v["words"]
    # a clear winner names no alternative
    v = verdict(_res(), [a, _check(["pressure_sensor"], 0.40, -800.0)])
    assert v["alternatives"] == []


def test_not_evaluated_names_the_rows():
    frame = pd.DataFrame(
        {
            "design_key": ["[2.0, 25.4, nan, nan, nan, nan]"] * 4,
            "height_mm": [10.0, 20.0, 60.0, 70.0],
            "pressure_pa": [2000.0, 3000.0, 9000.0, 9500.0],
        }
    )
    words = _undefined_words(frame, np.array([False, False, True, True]))
    assert words.startswith("2 of 4 rows")
    assert "60-70 mm, 9.0-9.5 kPa" in words
    nan = float("nan")
    failed = _check(["x"], nan, nan, undefined=words)
    v = verdict(_res(), [failed, _check(["a"], 0.33, -900.0)])
    assert v["not_evaluated"] == [["x"]]
    assert "x at 2 of 4 rows" in v["words"]
    assert v["effects"] == ["a"]
