"""Curve-fit baseline, cross-validation by membrane, metrics and the trajectory inversion."""

import dataclasses

import numpy as np
import pandas as pd
import pytest

from mfdesign.data.measurements import Measurements
from mfdesign.design import Membrane
from mfdesign.models.baselines import CurveFitConfig, monomials
from mfdesign.models.cv import ForceModelSpec, cross_validate, metrics
from mfdesign.models.predictor import AbstractPredictor
from mfdesign.models.trajectory import crossing_or_nan as first_crossing, model_pressure, trajectory_errors

NAN = np.nan
DESIGNS = [
    [2.0, 25.4, NAN, NAN, NAN, NAN],
    [1.5, 38.1, NAN, NAN, NAN, NAN],
    [2.0, 30.0, 40.0, 5.0, NAN, NAN],
    [1.5, 28.0, 38.0, 5.0, 55.0, 6.0],
    [2.5, 26.0, 40.0, 6.0, 56.0, 5.0],
]


def truth(d, h, p):
    """A known polynomial of degree 2 (ring numbers enter only for ringed membranes)."""
    r = np.nan_to_num(d[:, 2])
    return 1.0 + 2.0 * d[:, 0] + 1e-3 * p * (1 + d[:, 0]) - 0.1 * h + 1e-6 * p * h * 30 + 0.05 * r


def table(n_per=40, seed=0):
    rng = np.random.default_rng(seed)
    frames = []
    for d in DESIGNS:
        key = Membrane.from_array(d).key()
        h, p = rng.uniform(0, 50, n_per), rng.uniform(0, 10_000, n_per)
        arr = np.tile(d, (n_per, 1))
        frames.append(
            pd.DataFrame(
                dict(
                    design_key=key,
                    trial=0,
                    experiment="force",
                    phase="inflate",
                    time_s=np.arange(n_per, dtype=float),
                    height_set_mm=h,
                    height_mm=h,
                    pressure_pa=p,
                    force_n=truth(arr, h, p),
                    weight=1.0,
                    source="virtual",
                )
            )
        )
    return Measurements(pd.concat(frames, ignore_index=True))


def test_monomials_count():
    assert len(monomials(4, 2)) == 15  # C(4 + 2, 2)
    assert tuple(monomials(3, 1)[0]) == (0, 0, 0)


def test_curve_fit_recovers_known_polynomial():
    a = table().arrays()
    model = CurveFitConfig(degree=2, ridge=0.0).fit(a["design"], a["height_mm"], a["pressure_pa"], a["force_n"])
    b = table(seed=1).arrays()
    pred = np.asarray(model.members("rig", b["design"], b["height_mm"], b["pressure_pa"]))
    assert pred.shape == (1, len(b["force_n"]))
    np.testing.assert_allclose(pred[0], b["force_n"], atol=1e-6)
    assert model.fallback == ()


def test_curve_fit_pooled_fallback_for_empty_group():
    a = table().subset([Membrane.from_array(d).key() for d in DESIGNS[2:]]).arrays()
    model = CurveFitConfig(degree=1).fit(a["design"], a["height_mm"], a["pressure_pa"], a["force_n"])
    assert model.fallback == ("ringless",)
    out = model.members("rig", np.array([DESIGNS[0]]), np.array([10.0]), np.array([1e3]))
    assert np.all(np.isfinite(out))


class ConstModel(AbstractPredictor):
    """Toy fitted model: the training mean, with a fixed member spread."""

    value: float
    spread: float

    @property
    def fidelities(self):
        return ("rig",)

    def members(self, fidelity, design, h_mm, p_pa):
        self.check_fidelity(fidelity)
        n = len(h_mm)
        return np.stack([np.full(n, self.value - self.spread), np.full(n, self.value + self.spread)])


@dataclasses.dataclass(frozen=True)
class ConstSpec:
    spread: float = 1.0
    seen: list = dataclasses.field(default_factory=list)

    def fit(self, design, h_mm, p_pa, force_n, weight=None, *, key=None, progress=False):
        self.seen.append({tuple(np.nan_to_num(r)) for r in design})
        return ConstModel(float(np.average(force_n, weights=weight)), self.spread)


def test_protocols():
    assert isinstance(ConstSpec(), ForceModelSpec)
    assert isinstance(ConstModel(0.0, 1.0), AbstractPredictor)
    assert isinstance(CurveFitConfig(), ForceModelSpec)


def test_cv_splits_by_membrane_and_metrics_are_correct():
    data = table()
    spec = ConstSpec(spread=2.0)
    folds = data.kfold(5, seed=0)
    res = cross_validate(spec, folds, progress=False)
    assert len(res.folds) == 5 and len(spec.seen) == 5
    for fold, seen, (train, test) in zip(res.folds, spec.seen, folds):
        test_designs = {tuple(np.nan_to_num(d)) for d in test.arrays()["design"]}
        assert not (seen & test_designs)  # no held-out membrane in training
        a, b = train.arrays(), test.arrays()
        err = b["force_n"] - a["force_n"].mean()
        assert fold["rmse_n"] == pytest.approx(np.sqrt(np.mean(err**2)))
        assert fold["median_abs_n"] == pytest.approx(np.median(np.abs(err)))
        assert fold["coverage95_epistemic"] == pytest.approx(np.mean(np.abs(err) <= 1.959963985 * 2.0))
    assert res.overall["n"] == len(data)
    assert res.overall["rmse_n"] == pytest.approx(
        np.sqrt(np.mean((res.predictions["force"] - res.predictions["mean"]) ** 2))
    )


def test_metrics_coverage_with_noise_term():
    f = np.array([0.0, 1.0, 2.0, 3.0])
    m = metrics(f, np.zeros(4), np.zeros(4), noise_sd=1.5)
    assert m["coverage68_epistemic"] == 0.25  # only the exact hit
    assert m["coverage68_total"] == 0.5  # |e| <= 0.9945 * 1.5
    assert m["coverage95_total"] == 0.75  # |e| <= 2.94
    with pytest.raises(ValueError):
        metrics(f, np.zeros(3), np.zeros(4))


class LinearForce(AbstractPredictor):
    """F = (p - 1000) / 100 + 0.1 h: invertible by hand."""

    @property
    def fidelities(self):
        return ("rig",)

    def members(self, fidelity, design, h_mm, p_pa):
        self.check_fidelity(fidelity)
        return ((np.asarray(p_pa) - 1000) / 100 + 0.1 * np.asarray(h_mm))[None]


def test_first_crossing_and_model_pressure_invert_a_known_model():
    x = np.linspace(0, 10, 11)
    np.testing.assert_allclose(first_crossing(x, np.stack([x, 2 * x]), [2.5, 30.0]), [2.5, np.nan])
    p = model_pressure(LinearForce(), DESIGNS[0], np.array([10.0, 20.0]), np.array([5.0, 40.0]))
    np.testing.assert_allclose(p, [1000 + 100 * (10 - 0.5), 1000 + 100 * (20 - 4.0)], rtol=1e-9)


def test_trajectory_error_is_zero_for_an_exact_model():
    key = Membrane.from_array(DESIGNS[0]).key()
    h = np.array([5.0, 40.0, 50.0])
    wp = pd.DataFrame(dict(design_key=key, trial=0, force_n=14.715, h_mm=h, p_pa=1000 + 100 * (14.715 - 0.1 * h)))
    table_, summary = trajectory_errors(LinearForce(), wp)
    assert summary[key]["traj_rmse_p"] < 1e-9
    assert summary[key]["traj_rmse_dist"] < 1e-9


def test_measured_waypoint_is_the_last_crossing_before_the_top_not_a_resting_spike():
    from mfdesign.models.trajectory import measured_waypoints

    # resting plate (1-3 mm) with one 6 mm spike at 2.0 kPa, lift-off at 4 kPa, top at 60 mm;
    # stored top-down as the real files store some trials
    p = np.array([1000, 1500, 2000, 2500, 3000, 4000, 4100, 4200, 4300], float)
    h = np.array([1.0, 2.0, 6.0, 2.0, 3.0, 4.0, 20.0, 45.0, 60.0])
    df = pd.DataFrame(
        dict(design_key="k", trial=0, experiment="lift", force_n=14.715, height_mm=h[::-1], pressure_pa=p[::-1])
    )
    wp = measured_waypoints(df, heights=(5.0, 40.0, 70.0))
    np.testing.assert_allclose(wp["p_pa"].to_numpy()[:2], [4000 + 100 / 16, 4100 + 100 * 20 / 25])
    assert np.isnan(wp["p_pa"].iloc[2])  # never reached
