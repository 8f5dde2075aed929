"""The residual's shape in words: which part of the mean square is per membrane, per lift,
or a trend with height or pressure (what the diagnosis says when no effect explains it)."""

import numpy as np
import pandas as pd
import pytest

from mfdesign.diagnosis.residuals import Residuals, residual_shape, shape_words


def _res(residual_of):
    rng = np.random.default_rng(0)
    rows = []
    for m, (key, rings) in enumerate([("a", 0), ("b", 1), ("c", 2), ("d", 2)]):
        for trial in range(3):
            h = np.linspace(5, 50, 40)
            p = 2000 + 60 * h
            rows.append(pd.DataFrame(dict(design_key=key, n_rings=rings, trial=trial, height_mm=h, pressure_pa=p, m=m)))
    f = pd.concat(rows, ignore_index=True)
    f["residual_n"] = residual_of(f) + 0.05 * rng.standard_normal(len(f))
    return Residuals(f, noise_floor_n=0.05)


def _share(res, name):
    return {s["shape"]: s["share"] for s in residual_shape(res)}[name]


def test_shares_sum_to_one_and_find_the_shape_that_was_put_in():
    per_membrane = _res(lambda f: np.array([3.0, -2.0, 1.0, -4.0])[f["m"]] + 0.5)
    shares = residual_shape(per_membrane)
    assert sum(s["share"] for s in shares) == pytest.approx(1.0)
    # rings 2 hold c and d (+1, -4): their mean -1.5 is "per ring count", the rest "per membrane"
    assert _share(per_membrane, "per membrane") > 0.4 and _share(per_membrane, "grows with height") < 0.01
    height = _res(lambda f: 0.1 * (f["height_mm"] - 27.5))
    assert _share(height, "grows with height") > 0.95
    per_lift = _res(lambda f: np.where(f["trial"] == 1, 2.0, -1.0) * np.where(f["m"] % 2 == 0, 1, -1))
    assert _share(per_lift, "per lift") > 0.9
    assert shape_words(height).startswith("grows with height")


def test_a_refit_with_non_finite_forces_is_named_not_ranked():
    from mfdesign.diagnosis.check import CheckResult, verdict

    res = _res(lambda f: np.array([3.0, -2.0, 1.0, -4.0])[f["m"]])

    def check(name, heldout, bic):
        return CheckResult((name,), {}, {}, 1.0, heldout, 2.5, bic, 100.0, 0.05)

    # the NaN refit would win a min() over held-out errors (NaN compares False)
    v = verdict(res, [check("ring_stiffening", float("nan"), 2e13), check("contact_offset", 2.4, 5.0)])
    assert v["status"] == "unexplained" and v["not_evaluated"] == [["ring_stiffening"]]
    assert "the best candidate, contact_offset" in v["words"] and "not evaluated" in v["words"]
    assert "ring_stiffening" in v["words"].split("not evaluated")[1]
    v = verdict(res, [check("contact_offset", 1.0, -50.0), check("ring_stiffening", float("nan"), float("nan"))])
    assert v["effects"] == ["contact_offset"] and "not evaluated" in v["words"]
    assert verdict(res, [check("contact_offset", 1.0, -50.0)])["not_evaluated"] == []
