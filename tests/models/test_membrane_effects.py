"""Effect parameters that vary from membrane to membrane (a hierarchical random effect).

The data come from the virtual rig with each membrane's own fabric inset (the rig's
``membrane_theta``) on the stand-in simulator; the model is the stand-in too, so these
tests check the hierarchy's logic (layout, prior, per-row values, recovery, the new
membrane's draws, files), not the physics.
"""

from __future__ import annotations

import math

import jax
import jax.numpy as jnp
import numpy as np
import pytest

from mfdesign.calibration.mcmc import build_model, find_map
from mfdesign.calibration.posterior import Posterior, file_diagnostics
from mfdesign.models.hierarchical import CalibrationData, HierarchicalModel, membrane_block
from mfdesign.models.standin import standin_force

KEYS = (
    "[2.0, 25.4, nan, nan, nan, nan]",
    "[2.0, 31.92, 46.0, 5.0, 59.0, 5.0]",
    "[2.33, 29.63, 37.63, 5.0, 62.0, 5.0]",
    "[1.5, 28.0, nan, nan, nan, nan]",
)
INSETS = (0.2, 1.4, 0.7, 1.0)  # mm, the truth of each membrane
Q = "fabric_inset.inset_mm"


@pytest.fixture(scope="module")
def table():
    from mfdesign.design import Membrane
    from mfdesign.models.standin import standin_plane
    from mfdesign.physics.params import SimParams
    from mfdesign.rig.virtual import Protocol, VirtualRig

    rig = VirtualRig(
        effects=["fabric_inset"],
        theta={Q: 0.0},
        membrane_theta={k: {Q: v} for k, v in zip(KEYS, INSETS)},
        seed=1,
        protocol=Protocol(sample_hz=0.2, trials_per_height=1, heights_mm=(0.0, 20.0, 40.0, 60.0)),
        simulator=standin_plane,
        base_params=SimParams(mu_pa=34e3, jm=45.0),
    )
    return rig.run([Membrane.from_key(k) for k in KEYS], progress=False)


@pytest.fixture(scope="module")
def data(table):
    return CalibrationData.from_measurements(table, max_rows=400, seed=1)


@pytest.fixture(scope="module")
def model(data):
    return build_model(standin_force, data, ["fabric_inset"], membrane_effects=("fabric_inset",))


def test_layout_names_and_blocks(model, data):
    names = model.names
    assert model.membrane_params == (Q,)
    one = build_model(standin_force, data, ["fabric_inset"], membrane_effects="fabric_inset")
    assert one.membrane_effects == ("fabric_inset",) and one.names == names  # a bare name, not its letters
    assert [n for n in names if n.startswith(Q)] == [Q, Q + "_sd"] + [f"{Q}[{m}]" for m in range(4)]
    assert membrane_block(f"{Q}[3]") == (Q, 3) and membrane_block("thickness[0]") == ("thickness", 0)
    assert membrane_block(Q) is None and membrane_block("thickness_sd") is None


def test_unknown_parameter_is_refused(data):
    with pytest.raises(ValueError, match="not a parameter of the effects"):
        build_model(standin_force, data, ["fabric_inset"], membrane_effects=("contact_offset",))
    with pytest.raises(ValueError, match="need membranes"):
        HierarchicalModel(standin_force, ("fabric_inset",), n_membranes=0, membrane_effects=(Q,))


def test_prior_is_normal_in_the_unconstrained_coordinate(model):
    """log_prior_u changes with a membrane's value exactly as N(u_m; u_centre, sd) does."""
    u = np.asarray(model.to_unconstrained(model.initial_physical()), float)
    i, k, j = model.names.index(Q), model.names.index(f"{Q}[2]"), model.names.index(Q + "_sd")
    u[i], u[j] = 0.4, float(model.specs[j].to_unconstrained(0.7))
    sd = float(model.specs[j].to_physical(u[j]))
    assert sd == pytest.approx(0.7)
    a, b = u.copy(), u.copy()
    a[k], b[k] = 0.4 + 0.3, 0.4 - 1.1
    got = float(model.log_prior_u(jnp.asarray(a)) - model.log_prior_u(jnp.asarray(b)))
    want = -0.5 * (0.3 / sd) ** 2 + 0.5 * (1.1 / sd) ** 2
    assert got == pytest.approx(want, rel=1e-10)


def test_rows_get_their_membranes_value_and_new_ones_the_centre(model, data):
    x = np.asarray(model.initial_physical(), float)
    x[model.names.index(Q)] = 0.9
    for m, v in enumerate(INSETS):
        x[model.names.index(f"{Q}[{m}]")] = v
    theta = model.theta_rows(jnp.asarray(x), data)[Q]
    np.testing.assert_allclose(np.asarray(theta), np.asarray(INSETS)[np.asarray(data.rows.membrane)])
    # a row of a membrane the model was not calibrated on: the population centre
    import equinox as eqx

    rows = eqx.tree_at(lambda r: r.membrane, data.rows, jnp.full(len(data), 4))
    other = CalibrationData(data.design, rows, data.force_n, data.weight, KEYS + ("new",))
    np.testing.assert_allclose(np.asarray(model.theta_rows(jnp.asarray(x), other)[Q]), 0.9)


def test_map_recovers_each_membranes_inset_and_beats_a_shared_one(model, data):
    res = find_map(model, data, starts=8, seed=0)
    x = np.asarray(res.x)
    got = np.array([x[model.names.index(f"{Q}[{m}]")] for m in range(4)])
    assert np.max(np.abs(got - np.asarray(INSETS))) < 0.2, got
    shared = build_model(standin_force, data, ["fabric_inset"])
    res_shared = find_map(shared, data, starts=8, seed=0)
    ll = float(model.log_lik(res.x, data))
    ll_shared = float(shared.log_lik(res_shared.x, data))
    # 5 more parameters; the per-membrane fit must win by far more than BIC's 5 ln N / 2
    assert ll - ll_shared > 2.5 * 5 * math.log(len(data)), (ll, ll_shared)


def test_a_new_membrane_draws_from_the_population(model, data):
    """Rows of a membrane the model was not calibrated on (index >= n_membranes) draw their
    inset from the population: their forces spread across samples as the spread grows; a
    calibrated membrane's rows do not move."""
    rows = data.rows
    n = len(data)
    membrane = np.asarray(rows.membrane).copy()
    membrane[: n // 2] = 4  # the first half of the rows: a fifth, new membrane
    keys = KEYS + ("[2.0, 28.0, nan, nan, nan, nan]",)
    import equinox as eqx

    new_rows = eqx.tree_at(lambda r: r.membrane, rows, jnp.asarray(membrane))
    mixed = CalibrationData(data.design, new_rows, data.force_n, data.weight, keys)
    x = np.asarray(model.initial_physical(), float)
    x[model.names.index(Q)] = 0.8
    for m, v in enumerate(INSETS):
        x[model.names.index(f"{Q}[{m}]")] = v
    spreads = []
    for sd in (0.05, 1.0):
        xs = np.repeat(x[None], 64, 0)
        xs[:, model.names.index(Q + "_sd")] = sd
        xs[:, model.names.index("thickness_sd")] = 1e-6  # thickness draws out of the way
        f = np.asarray(model.sample_force(jnp.asarray(xs), mixed, jax.random.PRNGKey(3)))
        assert np.all(np.std(f[:, n // 2 :], axis=0) < 1e-9)  # calibrated membranes: their own value
        spreads.append(float(np.mean(np.std(f[:, : n // 2], axis=0))))
    assert spreads[0] > 0 and spreads[1] > 5 * spreads[0], spreads


def test_posterior_tables_and_arviz_group_the_membranes(model, data):
    rng = np.random.default_rng(0)
    dim = model.dim
    chain = rng.normal(size=(20, 6, dim)) * 0.01 + np.asarray(model.initial_physical())
    post = Posterior(
        model.names,
        tuple(s.unit for s in model.specs),
        chain.reshape(-1, dim),
        rng.normal(size=120),
        chain[0, 0],
        0.0,
        1.0,
        0.0,
        0.0,
        {},
        KEYS,
        ("fabric_inset",),
        chain,
        rng.normal(size=(20, 6)),
    )
    table = post.summary()
    assert [p for p in table.parameter if p.startswith(Q + " ")] == [f"{Q} {k}" for k in KEYS]
    assert set(table.unit[table.parameter.str.startswith(Q + " ")]) == {"mm"}
    assert not any(membrane_block(p) for p in table.parameter)
    idata = post.to_inference_data()
    var = idata.posterior["membrane." + Q]
    assert var.dims[-1] == "membrane" and var.shape[-1] == 4 and var.attrs["units"] == "mm"
    assert "thickness" in idata.posterior and Q in idata.posterior
    diag = file_diagnostics(idata, model.names)
    assert set(diag["rhat"]) == set(model.names)


def test_fit_mf_per_membrane_saves_and_reloads(table, tmp_path):
    """``mfdesign fit-mf --per-membrane``: the folder's mf.json names the per-membrane
    parameters, and the reloaded model has the posterior's layout (tiny chain: plumbing)."""
    from typer.testing import CliRunner

    from mfdesign.calibration.workflow import load_multi_fidelity
    from mfdesign.cli import app
    from mfdesign.data.store import write_parquet

    src = tmp_path / "rig.parquet"
    write_parquet(table, src)
    args = ["fit-mf", str(src), "--out", str(tmp_path / "fit"), "--physics", "standin", "--effects", "fabric_inset"]
    args += ["--mcmc-steps", "30", "--max-rows", "80", "--members", "2", "--delta-steps", "20"]
    r = CliRunner().invoke(app, args + ["--per-membrane", "fabric_inset"])
    assert r.exit_code == 0, r.output
    fit = load_multi_fidelity(tmp_path / "fit")
    assert fit.model.membrane_params == (Q,) and f"{Q}[3]" in fit.posterior.names
    design = np.array([[1.7, 31.0, np.nan, np.nan, np.nan, np.nan]] * 2)
    f = np.asarray(fit.mf.predict(design, np.array([10.0, 30.0]), np.array([4000.0, 6000.0])))
    assert np.all(np.isfinite(f))
    bad = CliRunner().invoke(app, args + ["--per-membrane", "contact_offset"])
    assert bad.exit_code == 2 and "--per-membrane" in bad.output and "allowed" in bad.output
