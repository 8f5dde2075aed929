"""A search on the simulator itself near a model's optimum (issue 43): the simulator's
force as a pure JAX function of the design, its forward-mode derivative, and the few
projected-Adam steps ``optimize`` takes where its simulator check disagrees with the model.

The truth is the simulator proper (``force_at``, ``height_at``), not the refine's own
code path: the traced force must equal ``force_at``'s signed force, and its derivative
the finite differences of ``force_at``."""

import jax
import jax.numpy as jnp
import numpy as np
import pytest

from mfdesign._x64 import enable_x64
from mfdesign.design import Membrane
from mfdesign.optimization import CHECK_H_MAX_MM, CHECK_N_HEIGHTS, HeightTargets, _disagrees
from mfdesign.physics.params import SimParams
from mfdesign.physics.solve import PATH_STEPS, force_at, point_force, traced_params

enable_x64()

RINGED = [2.0, 24.0, 33.0, 5.0, 46.4, 5.0]  # near the authors' task-A design, gaps > 3 mm (room to differentiate)


def test_point_force_is_the_simulators_signed_force_and_its_derivative_is_the_simulators():
    h = np.array([2.0, 30.0, 55.0])  # one point below LOW_HEIGHT_MM: the plate is lowered
    p = np.array([5000.0, 6895.0, 6895.0])
    params = traced_params(SimParams())
    f = jax.jit(jax.vmap(lambda d, hh, pp: point_force(d, hh, pp, params, PATH_STEPS), (None, 0, 0)))
    d = jnp.asarray(RINGED)
    want = force_at(Membrane.from_array(RINGED), h, p, signed=True).force_n
    np.testing.assert_allclose(np.asarray(f(d, h, p)), want, rtol=1e-6, atol=1e-6)
    # d F / d (thickness, contact radius, ring-1 radius) against central differences of the
    # simulator proper
    jac = np.asarray(jax.jit(jax.jacfwd(lambda dd: f(dd, h, p)))(d))
    for k, step in ((0, 1e-3), (1, 1e-2), (2, 1e-2)):
        up, down = list(RINGED), list(RINGED)
        up[k] += step
        down[k] -= step
        fd = (
            force_at(Membrane.from_array(up), h, p, signed=True).force_n
            - force_at(Membrane.from_array(down), h, p, signed=True).force_n
        ) / (2 * step)
        np.testing.assert_allclose(jac[:, k], fd, rtol=2e-3, atol=2e-3 * np.abs(fd).max())


def test_an_absent_rings_nan_does_not_reach_the_derivative():
    params = traced_params(SimParams())
    d = jnp.asarray([1.5, 25.0, np.nan, np.nan, np.nan, np.nan])
    g = jax.jit(jax.jacfwd(lambda dd: point_force(dd, 30.0, 6000.0, params, PATH_STEPS)))(d)
    assert np.isfinite(np.asarray(g[:2])).all() and np.all(np.asarray(g[2:]) == 0.0)


def _check(sim, model):
    return {"h_sim_mm": sim, "h_model_mm": model}


def test_the_refine_starts_only_where_the_check_disagrees_within_the_losss_grid():
    assert not _disagrees(_check([30.0, 41.0], [31.0, 40.0]), tol_mm=2.0)
    assert _disagrees(_check([30.0, 45.0], [31.0, 40.0]), tol_mm=2.0)
    assert _disagrees(_check([None, 40.0], [31.0, 40.0]), tol_mm=2.0)  # a target it could not check
    # both above the loss's 80 mm grid: every height scores the same, no disagreement
    assert not _disagrees(_check([105.2, 114.9], [80.0, 80.0]), tol_mm=2.0)
    assert _disagrees(_check([105.2, 114.9], [80.0, 80.0]), tol_mm=2.0, top_mm=None)
    # past the check's own grid (BEYOND_GRID): above the loss's grid too
    beyond = {"h_sim_mm": [None, None], "h_model_mm": [80.0, 80.0], "status": ["BEYOND_GRID"] * 2, "h_max_mm": 120.0}
    assert not _disagrees(beyond, tol_mm=2.0)
    assert _disagrees(beyond | {"h_model_mm": [80.0, 50.0]}, tol_mm=2.0)
    assert _disagrees(beyond | {"status": ["NOT_CONVERGED", "BEYOND_GRID"]}, tol_mm=2.0)


@pytest.mark.slow
def test_optimize_refines_on_the_simulator_where_the_model_is_wrong():
    """A closed-form model that is not the simulator: its optimum's check disagrees, the
    refine runs from the winner, never raises the simulator's loss, and its design's
    heights come from the simulator proper (height_at). ~2 minutes on 2 cores (compiles)."""
    from mfdesign.models.predictor import AbstractPredictor
    from mfdesign.optimization import optimize

    class Linear(AbstractPredictor):
        @property
        def fidelities(self):
            return ("rig",)

        def members(self, fidelity, d, h, p):
            rings = jnp.nan_to_num(d[:, 3]) + jnp.nan_to_num(d[:, 5])
            return ((d[:, 1] / 25.0) * p / 100.0 - (2.0 * d[:, 0] + 0.3 + 0.02 * rings) * h)[None]

    problem = HeightTargets((14.715, 24.525), (5516.0, 5516.0))
    res = optimize(
        Linear(),
        problem,
        rings=(2,),
        n_starts=4,
        steps=1,
        n_refine=1,
        check=True,
        progress=False,
        sim_refine_steps=3,
    )
    ref = res.simulator_refined
    assert ref is not None and "disagrees" in ref["why"]
    assert ref["loss_sim"] <= ref["loss_sim_start"]
    assert ref["start_design_key"] == res.design_key
    design = Membrane.from_key(ref["design_key"])  # a valid design (the key parses and checks)
    assert design.n_rings == 2
    from mfdesign.physics.solve import height_at

    h, _ = height_at(design, problem.force_n, problem.p_pa, h_max_mm=CHECK_H_MAX_MM, n_heights=CHECK_N_HEIGHTS)
    np.testing.assert_allclose(
        np.asarray([np.nan if v is None else v for v in ref["check"]["h_sim_mm"]]), h, equal_nan=True
    )
    assert res.to_json()["simulator_refined"]["design_key"] == ref["design_key"]


def test_heights_above_the_rigs_travel_are_limits():
    from mfdesign.optimization import _check_flags

    check = {
        "force_n": [14.7, 24.5, 39.2],
        "p_pa": [6895.0] * 3,
        "h_sim_mm": [99.5, None, 40.0],
        "status": ["OK", "BEYOND_GRID", "OK"],
        "h_max_mm": 120.0,
    }
    flags = _check_flags(check)
    assert len(flags) == 2 and "to 99.5 mm" in flags[0] and "past 120 mm" in flags[1]
    assert _check_flags(None) == []
