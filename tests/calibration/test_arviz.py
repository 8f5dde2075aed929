"""ArviZ output of a calibration: constrained values, chain x draw, pointwise groups, netCDF.

Stand-in force model and short chains: this checks the plumbing (physical units, walkers
as chains, log-likelihood terms that sum to the model's), not the posterior's quality.
"""

from __future__ import annotations

import json
import warnings

import arviz as az
import numpy as np
import pytest
from typer.testing import CliRunner

from mfdesign.calibration.mcmc import ConvergenceWarning, build_model, calibrate
from mfdesign.calibration.plots import pair_plot
from mfdesign.calibration.posterior import Posterior, convergence_rows, load_inference_data, save_inference_data
from mfdesign.models.standin import standin_force

GROUPS = {"posterior", "sample_stats", "log_likelihood", "posterior_predictive", "observed_data", "constant_data"}


@pytest.fixture(scope="module")
def fitted():
    from test_calibrate import virtual_data

    table, data = virtual_data(rows=120)
    model = build_model(standin_force, data, ["pressure_sensor"])
    with warnings.catch_warnings():
        warnings.simplefilter("ignore", ConvergenceWarning)
        post = calibrate(data, model, n_steps=200, progress=False, seed=0)
    return table, data, model, post


def test_posterior_keeps_the_physical_chain_and_arviz_diagnostics(fitted):
    _, _, model, post = fitted
    n_draw, n_walker, dim = post.chain.shape
    assert dim == model.dim and post.log_prob_chain.shape == (n_draw, n_walker)
    np.testing.assert_allclose(np.sort(post.chain.reshape(-1, dim), 0), np.sort(post.samples, 0))
    c = post.convergence
    for key in ("tau", "tau_max", "acceptance", "rhat", "ess_bulk", "ess_tail", "rhat_max", "ess_bulk_min"):
        assert key in c
    assert set(c["rhat"]) == set(model.names) and c["rhat_max"] >= 0.99 and c["ess_bulk_min"] > 0


def test_convergence_rows_put_emcee_tau_beside_arviz_rhat_and_ess(fitted):
    """One row per parameter, the numbers the chain's check computed (nothing recomputed):
    emcee's tau and ArviZ's R-hat / ESS (az.rhat / az.ess on the walkers as chains)."""
    _, _, model, post = fitted
    c = post.convergence
    rows = convergence_rows(c)
    assert [r["parameter"] for r in rows] == list(model.names)
    i = model.names.index("mu_pa")
    a = np.swapaxes(post.chain, 0, 1)[..., i]  # [chain = walker, draw]
    mu = rows[i]
    assert mu["tau [steps]"] == c["tau"]["mu_pa"] and mu["R-hat"] == float(az.rhat(a))
    assert (mu["ESS bulk"], mu["ESS tail"]) == (float(az.ess(a, method="bulk")), float(az.ess(a, method="tail")))
    assert max(r["R-hat"] for r in rows) == c["rhat_max"]
    old = convergence_rows({"tau": {"mu_pa": 3.0}})  # a posterior.json from before ArviZ
    assert old == [{"parameter": "mu_pa", "tau [steps]": 3.0, "R-hat": None, "ESS bulk": None, "ESS tail": None}]


@pytest.mark.filterwarnings("ignore:Estimated shape parameter of Pareto")  # tiny chain: PSIS k is high
def test_netcdf_roundtrip_gives_constrained_values_and_groups(fitted, tmp_path):
    _, data, model, post = fitted
    path = save_inference_data(post, tmp_path, model, data, max_draws=None)
    assert path == tmp_path / "posterior.nc"
    idata = az.from_netcdf(path)
    assert GROUPS <= set(idata.groups())
    mu = idata.posterior["mu_pa"]
    x_file, _ = post.file_chains()  # every walker's kept draws, one per autocorrelation time
    assert mu.dims == ("chain", "draw") and mu.shape == x_file.shape[:2]
    assert 20e3 < float(mu.mean()) < 50e3 and mu.attrs["units"] == "Pa"  # physical, not log(mu / prior) ~ 0.16
    np.testing.assert_allclose(mu.values, x_file[..., model.names.index("mu_pa")])
    assert idata.posterior["thickness"].dims == ("chain", "draw", "membrane")
    assert list(idata.posterior["membrane"].values) == list(post.design_keys)
    off = idata.posterior["pressure_sensor.offset_pa"]
    assert 50 < float(off.mean()) < 300  # the hidden offset of the virtual rig, 150 Pa
    # log-likelihood: one weighted term per row, summing to the model's log-likelihood
    ll = idata.log_likelihood["force_n"]
    n_rows = int((np.asarray(data.weight) > 0).sum())
    assert ll.dims == ("chain", "draw", "row") and ll.shape[2] == n_rows
    x0 = np.array(
        [float(idata.posterior[n][0, 0]) for n in model.names if not n.startswith("thickness[")]
        + list(idata.posterior["thickness"][0, 0].values)
    )
    order = [n for n in model.names if not n.startswith("thickness[")] + [
        n for n in model.names if n.startswith("thickness[")
    ]
    x0 = x0[[order.index(n) for n in model.names]]
    np.testing.assert_allclose(float(ll[0, 0].sum()), float(model.log_lik(x0, data)), rtol=1e-8)
    assert idata.posterior_predictive["force_n"].shape == ll.shape
    assert idata.observed_data["force_n"].shape == (n_rows,)
    loo = az.loo(idata)
    assert np.isfinite(loo.elpd_loo)
    # the one-line reload
    again = load_inference_data(tmp_path)
    np.testing.assert_allclose(again.posterior["jm"].values, idata.posterior["jm"].values)


@pytest.mark.filterwarnings("ignore:Estimated shape parameter of Pareto")
def test_the_file_keeps_every_kept_draw_and_the_report_its_arviz_numbers(fitted, tmp_path):
    """posterior.nc holds every walker's kept draws one autocorrelation time apart (the demo
    once thinned them to 7 per walker: az.summary then gave R-hat up to 1.096 and ESS 438
    for every parameter while the report said 770), and the R-hat / ESS that posterior.json
    reports are exactly az.summary's on that file; the rule is stated with them."""
    import copy

    _, data, model, post = fitted
    post = copy.deepcopy(post)  # save_inference_data updates the convergence report in place
    save_inference_data(post, tmp_path, model, data)
    post.save(tmp_path / "posterior")
    idata = az.from_netcdf(tmp_path / "posterior.nc")
    n_draw, n_walker, _ = post.chain.shape
    step = post.tau_step()
    assert step == int(np.ceil(post.convergence["tau_max"] / post.convergence["thin"])) >= 1
    assert idata.posterior.sizes["chain"] == n_walker
    assert idata.posterior.sizes["draw"] == len(range(0, n_draw, step))
    stored = json.loads((tmp_path / "posterior.json").read_text())["convergence"]
    assert stored["draws_in_file"] == {"file": "posterior.nc", "chains": n_walker, "draws": len(range(0, n_draw, step))}
    table = az.summary(idata, var_names=["mu_pa", "jm", "noise_n", "thickness"], kind="diagnostics")
    for name in ("mu_pa", "jm", "noise_n"):
        assert stored["rhat"][name] == pytest.approx(table.loc[name, "r_hat"], abs=0.006)  # az.summary rounds
        assert stored["ess_bulk"][name] == pytest.approx(table.loc[name, "ess_bulk"], abs=0.6)
        assert stored["ess_tail"][name] == pytest.approx(table.loc[name, "ess_tail"], abs=0.6)
    k = post.design_keys[0]
    assert stored["rhat"]["thickness[0]"] == pytest.approx(table.loc[f"thickness[{k}]", "r_hat"], abs=0.006)
    assert stored["rhat_max"] == max(stored["rhat"].values())
    assert "50 times its longest integrated autocorrelation time" in stored["rule"]


def test_npz_roundtrip_keeps_the_chain_and_max_draws_thins(fitted, tmp_path):
    _, data, model, post = fitted
    post.save(tmp_path / "posterior", seeds={"seed": 0})
    back = Posterior.load(tmp_path / "posterior")
    np.testing.assert_array_equal(back.chain, post.chain)
    # provenance (issue 41): version, call (a Python call's name under pytest), seed, machine
    js = json.loads((tmp_path / "posterior.json").read_text())
    prov = js.pop("provenance")
    assert prov["mfdesign_version"] and prov["call"] == "Posterior.save()" and prov["seeds"] == {"seed": 0}
    assert prov["machine"]["cores"] >= 1 and prov["time"]
    # a posterior.json written before provenance still loads
    (tmp_path / "posterior.json").write_text(json.dumps(js))
    np.testing.assert_array_equal(Posterior.load(tmp_path / "posterior").samples, post.samples)
    idata = back.to_inference_data(model, data, max_draws=100)
    n_chain, n_draw = idata.posterior.sizes["chain"], idata.posterior.sizes["draw"]
    assert n_chain == post.chain.shape[1] and n_chain * n_draw <= 100 + n_chain
    plain = back.to_inference_data()  # without model and data: posterior and sample_stats only
    assert set(plain.groups()) == {"posterior", "sample_stats"}


def test_pair_plot_with_truths(fitted, tmp_path):
    *_, post = fitted
    path = pair_plot(post, tmp_path / "pair.png", truths={"mu_pa": 34e3, "jm": 45.0}, names=["mu_pa", "jm", "noise_n"])
    assert path.stat().st_size > 10_000
    with pytest.raises(KeyError):
        pair_plot(post, tmp_path / "x.png", names=["nope"])


def test_calibrate_command_writes_posterior_nc(tmp_path):
    from mfdesign.cli import app
    from mfdesign.data.store import read_parquet, write_parquet
    from mfdesign.workflows.demo import BUNDLED

    meas = read_parquet(BUNDLED)
    data = tmp_path / "two.parquet"
    write_parquet(meas.subset(meas.design_keys[:2]), data)
    out = tmp_path / "cal"
    r = CliRunner().invoke(
        app,
        [
            "calibrate",
            str(data),
            "--out",
            str(out),
            "--physics",
            "standin",
            "--mcmc-steps",
            "40",
            "--walkers",
            "16",
            "--max-rows",
            "60",
        ],
    )
    assert r.exit_code == 0, r.output
    # the terminal line carries ArviZ's diagnostics, as posterior.json holds them
    conv = json.loads((out / "posterior.json").read_text())["convergence"]
    assert (
        f"R-hat max {conv['rhat_max']:.3f}, ESS bulk min {conv['ess_bulk_min']:.0f}, "
        f"tail min {conv['ess_tail_min']:.0f} (ArviZ)" in r.output
    )
    idata = az.from_netcdf(out / "posterior.nc")
    assert GROUPS <= set(idata.groups())
    assert idata.posterior["mu_pa"].dims == ("chain", "draw") and idata.posterior.sizes["chain"] == 16
    assert 10e3 < float(idata.posterior["mu_pa"].mean()) < 100e3  # pascals (bundled truth 31.7e3), not ~0.16


def test_calibrate_prints_convergence_warnings_not_library_notices(tmp_path, monkeypatch):
    """A cold `demo --quick` printed ArviZ's import-time FutureWarning ("ArviZ is undergoing
    a major refactor ...") as a "warning:" line: only the chain's own warnings are the user's."""
    import mfdesign.workflows.calibrate as wc
    from mfdesign.cli import app
    from mfdesign.data.store import read_parquet, write_parquet
    from mfdesign.workflows.demo import BUNDLED

    real = wc._sample

    def noisy(*args, **kwargs):
        warnings.warn("a library's notice about its next release", FutureWarning, stacklevel=1)
        return real(*args, **kwargs)

    monkeypatch.setattr(wc, "_sample", noisy)
    meas = read_parquet(BUNDLED)
    data = tmp_path / "one.parquet"
    write_parquet(meas.subset(meas.design_keys[:1]), data)
    args = ["calibrate", str(data), "--out", str(tmp_path / "cal"), "--physics", "standin"]
    r = CliRunner().invoke(app, [*args, "--mcmc-steps", "40", "--walkers", "16", "--max-rows", "60"])
    assert r.exit_code == 0, r.output
    assert "next release" not in r.output
    assert "warning: chain of 40 steps" in r.output  # 40 steps never converge: that one is said
