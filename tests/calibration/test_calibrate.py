"""Calibration with emcee: truth recovered, reports, resume after a real kill, pool, plots."""

from __future__ import annotations

import inspect
import os
import signal
import subprocess
import sys
import textwrap
import warnings
from multiprocessing.pool import ThreadPool

import h5py
import jax
import jax.numpy as jnp
import numpy as np
import pytest

from mfdesign.calibration.mcmc import ConvergenceWarning, LogPosterior, build_model, calibrate, find_map
from mfdesign.calibration.plots import corner_plot
from mfdesign.calibration.posterior import Posterior
from mfdesign.models.standin import standin_force
from mfdesign.models.hierarchical import CalibrationData

TRUTH = {"mu_pa": 34e3, "jm": 45.0, "pressure_sensor.offset_pa": 150.0}


def virtual_data(seed: int = 1, rows: int = 240):
    """Virtual-rig data of 3 membranes on the stand-in simulator, hidden pressure offset 150 Pa."""
    from mfdesign.models.standin import standin_plane
    from mfdesign.design import Membrane
    from mfdesign.models.hierarchical import CalibrationData
    from mfdesign.physics.params import SimParams
    from mfdesign.rig.virtual import Protocol, VirtualRig

    designs = [
        Membrane.from_key(k)
        for k in (
            "[2.0, 25.4, nan, nan, nan, nan]",
            "[2.0, 31.92, 46.0, 5.0, 59.0, 5.0]",
            "[2.33, 29.63, 37.63, 5.0, 62.0, 5.0]",
        )
    ]
    proto = Protocol(sample_hz=0.2, trials_per_height=1, heights_mm=(0.0, 20.0, 40.0, 60.0))
    rig = VirtualRig(
        effects=["pressure_sensor"],
        theta={"pressure_sensor.offset_pa": 150.0},
        seed=seed,
        protocol=proto,
        simulator=standin_plane,
        base_params=SimParams(mu_pa=34e3, jm=45.0),
    )
    table = rig.run(designs, progress=False)
    return table, CalibrationData.from_measurements(table, max_rows=rows - 20, seed=seed).padded(rows)


@pytest.fixture(scope="module")
def setup():
    table, data = virtual_data()
    model = build_model(standin_force, data, ["pressure_sensor"])
    return table, data, model


def test_transforms_roundtrip_and_jacobian(setup):
    _, _, model = setup
    x = model.initial_physical()
    np.testing.assert_allclose(np.asarray(model.to_physical(model.to_unconstrained(x))), x, rtol=1e-9)
    u = model.to_unconstrained(x) + 0.3
    for i, s in enumerate(model.specs):
        slope = jax.grad(lambda v: s.to_physical(v))(u[i])
        np.testing.assert_allclose(float(s.log_jacobian(u[i])), np.log(abs(float(slope))), rtol=1e-8, atol=1e-10)


def test_padding_and_weights(setup):
    table, data, model = setup
    x = jnp.asarray(model.initial_physical())
    small = CalibrationData.from_measurements(table, max_rows=220, seed=1)
    assert len(data) == 240 and len(small) < 240
    np.testing.assert_allclose(float(model.log_lik(x, data)), float(model.log_lik(x, small)), rtol=1e-12)
    assert float(np.asarray(data.rows.h_mm)[np.asarray(~data.rows.is_force)].min()) >= 2.0  # unlifted rows dropped


def test_calibration_recovers_truth_and_reports(setup, tmp_path):
    _, data, model = setup
    with warnings.catch_warnings():
        warnings.simplefilter("ignore", ConvergenceWarning)
        post = calibrate(data, model, n_steps=1500, progress=False, seed=0)
    for name, truth in TRUTH.items():
        lo, hi = post.interval(name, 0.99)
        assert lo < truth < hi, (name, lo, hi)
    # the interval is informative: much narrower than the prior
    lo, hi = post.interval("mu_pa", 0.95)
    assert hi - lo < 0.2 * 34e3
    table = post.summary()
    assert {"parameter", "unit", "median", "q05", "q95", "map"} <= set(table.columns)
    assert table.set_index("parameter").loc["mu_pa", "unit"] == "Pa"
    assert np.isfinite(post.bic) and np.isfinite(post.log_evidence_laplace)
    c = post.convergence
    assert set(c["tau"]) == set(model.names) and 0 < c["acceptance"] < 1 and c["n_steps"] == 1500
    back = Posterior.load(post.save(tmp_path / "post"))
    np.testing.assert_array_equal(back.samples, post.samples)
    assert back.summary().equals(post.summary())
    png = corner_plot(post.samples[:, :4], post.names[:4], tmp_path / "corner.png", truths=[34e3, 45.0, 150.0, 1.0])
    assert png.stat().st_size > 10_000


def test_short_chain_warns(setup):
    _, data, model = setup
    with pytest.warns(ConvergenceWarning, match="tau"):
        post = calibrate(data, model, n_steps=40, progress=False)
    assert not post.convergence["converged"] and post.convergence["problems"]


def test_pool_gives_same_log_posterior(setup):
    _, data, model = setup
    u = model.to_unconstrained(model.initial_physical()) + 0.01 * np.random.default_rng(0).standard_normal(
        (8, model.dim)
    )
    plain = LogPosterior(model, data)(u)
    with ThreadPool(2) as pool:
        pooled = LogPosterior(model, data, pool=pool)(u)
    np.testing.assert_allclose(pooled, plain, rtol=1e-12)
    assert np.all(np.isfinite(plain))


def test_log_posterior_batches_of_any_size_share_one_program(setup):
    """emcee asks for the whole ensemble, its halves and smaller sets; every size runs as
    chunks of WALKER_CHUNK points (issue 40: one compilation, not one per size), each point's
    value that of the point alone."""
    from mfdesign.calibration import mcmc

    _, data, model = setup
    rng = np.random.default_rng(1)
    u = model.to_unconstrained(model.initial_physical()) + 0.01 * rng.standard_normal(
        (2 * mcmc.WALKER_CHUNK + 3, model.dim)
    )
    lp = LogPosterior(model, data)
    before = mcmc._batch_log_post._cached._cache_size()
    whole = lp(u)
    parts = np.concatenate([lp(u[:5]), lp(u[5 : 5 + mcmc.WALKER_CHUNK]), lp(u[5 + mcmc.WALKER_CHUNK :])])
    assert mcmc._batch_log_post._cached._cache_size() - before <= 1
    assert whole.shape == (len(u),) and np.all(np.isfinite(whole))
    np.testing.assert_allclose(parts, whole, rtol=1e-12)
    np.testing.assert_allclose(lp(u[7:8]), whole[7:8], rtol=1e-12)


def test_evidence_prefers_the_hidden_effect(setup):
    """Laplace evidence / BIC: the data (150 Pa sensor offset) favour the model that has it."""
    _, data, model = setup
    bare = build_model(standin_force, data, [])
    with_fx, without = find_map(model, data), find_map(bare, data)
    assert float(with_fx.log_post) > float(without.log_post)


KILL_SCRIPT = """
import os, signal, sys
sys.path.insert(0, {tests!r})
{source}
from mfdesign.calibration.mcmc import build_model, calibrate
from mfdesign.models.standin import standin_force
table, data = virtual_data()
model = build_model(standin_force, data, ["pressure_sensor"])

def stop(it):
    if it == 30:
        os.kill(os.getpid(), signal.SIGKILL)  # a real kill: no clean-up, no flush

calibrate(data, model, n_steps=200, chain_path={path!r}, progress=False, callback=stop, n_walkers=24)
"""


def test_resume_after_kill(tmp_path):
    path = str(tmp_path / "chain.h5")
    script = KILL_SCRIPT.format(
        tests=os.path.dirname(__file__), path=path, source=textwrap.dedent(inspect.getsource(virtual_data))
    )
    env = dict(os.environ, JAX_PLATFORMS="cpu")
    proc = subprocess.run([sys.executable, "-c", script], env=env, capture_output=True, text=True, timeout=900)
    assert proc.returncode == -signal.SIGKILL, proc.stderr[-2000:]
    with h5py.File(path, "r") as f:
        assert int(f["mcmc"].attrs["iteration"]) == 30
        before = np.asarray(f["mcmc"]["chain"][:30])
    table, data = virtual_data()
    model = build_model(standin_force, data, ["pressure_sensor"])
    with warnings.catch_warnings():
        warnings.simplefilter("ignore", ConvergenceWarning)
        post = calibrate(data, model, n_steps=60, chain_path=path, progress=False, n_walkers=24)
    assert post.convergence["resumed_from"] == 30 and post.convergence["n_steps"] == 60
    with h5py.File(path, "r") as f:
        chain = np.asarray(f["mcmc"]["chain"])
        assert int(f["mcmc"].attrs["iteration"]) == 60
    np.testing.assert_array_equal(chain[:30], before)  # the stored part is untouched
    assert np.all(chain[30:60] != 0) and not np.allclose(chain[30], chain[29])  # and the chain went on
    # another model on the same file is refused, not silently mixed
    other = build_model(standin_force, data, [])
    with pytest.raises(ValueError, match="another model"):
        calibrate(data, other, n_steps=70, chain_path=path, progress=False)
