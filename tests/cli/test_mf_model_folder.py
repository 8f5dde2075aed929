"""A multi-fidelity fit saved by `mfdesign fit-mf` is a model folder for propose and optimize.

Analytic stand-in force model, two bundled membranes, tiny chains: this checks the
plumbing (save -> load -> traceable members -> acquisition), not the fit's quality.
"""

import jax
import jax.numpy as jnp
import numpy as np
import pytest
from typer.testing import CliRunner

from mfdesign.acquire import Grid
from mfdesign.calibration.workflow import load_multi_fidelity
from mfdesign.cli import app
from mfdesign.workflows.models import load_model
from mfdesign.workflows.models import load_predictor
from mfdesign.data.store import read_parquet, write_parquet
from mfdesign.workflows.demo import BUNDLED

runner = CliRunner()


@pytest.fixture(scope="module")
def folder(tmp_path_factory):
    tmp = tmp_path_factory.mktemp("mf")
    meas = read_parquet(BUNDLED)
    data = tmp / "two.parquet"
    write_parquet(meas.subset(meas.design_keys[:2]), data)
    out = tmp / "fit"
    r = runner.invoke(
        app,
        [
            "fit-mf",
            str(data),
            "--out",
            str(out),
            "--physics",
            "standin",
            "--mcmc-steps",
            "30",
            "--walkers",
            "16",
            "--max-rows",
            "60",
            "--members",
            "2",
            "--delta-steps",
            "20",
            "--effects",
            "pressure_sensor",
        ],
    )
    assert r.exit_code == 0, r.output
    return out


def test_loaded_fit_members_equal_its_predictions_and_are_differentiable(folder):
    fit = load_multi_fidelity(folder)
    assert fit.model.effects == ("pressure_sensor",) and len(fit.design_keys) == 2
    design = np.array([[1.7, 31.0, np.nan, np.nan, np.nan, np.nan]] * 3)
    h, p = np.array([0.0, 20.0, 40.0]), np.array([3000.0, 5000.0, 7000.0])
    traced = np.asarray(
        jax.jit(lambda d, hh, pp: fit.mf.members(d, hh, pp))(jnp.asarray(design), jnp.asarray(h), jnp.asarray(p))
    )
    np.testing.assert_allclose(traced, np.asarray(fit.mf.predict(design, h, p)), rtol=1e-10)
    g = jax.grad(lambda d: fit.mf.members(d, jnp.asarray(h), jnp.asarray(p)).mean())(jnp.asarray(design))
    assert np.all(np.isfinite(np.asarray(g)[:, :2])) and float(jnp.abs(g[:, 1]).sum()) > 0


def test_propose_and_optimize_read_the_folder(folder):
    pred = load_predictor(folder)
    assert pred.fidelities == ("rig", "sim")
    design = jnp.asarray([[2.0, 30.0, np.nan, np.nan, np.nan, np.nan]])
    rig, sim = (np.asarray(pred.grid_members(f, design, Grid())) for f in ("rig", "sim"))
    assert rig.shape == sim.shape == (16, 1, Grid().size)
    assert not np.allclose(rig, sim)  # rig members carry the discrepancy, sim members do not
    model = load_model(folder)  # optimize's predictor: the same 16 posterior draws, rig and sim
    assert model.fidelities == ("rig", "sim")
    assert model.members("rig", design, jnp.zeros(1), jnp.full(1, 5000.0)).shape == (16, 1)


def test_a_folder_without_the_discrepancy_is_refused(folder, tmp_path):
    import shutil

    broken = tmp_path / "broken"
    shutil.copytree(folder, broken)
    shutil.rmtree(broken / "delta")
    with pytest.raises(ValueError, match="missing"):
        load_multi_fidelity(broken)
    r = runner.invoke(
        app, ["propose", "--model", str(broken), "--q", "1", "--restarts", "2", "--out", str(tmp_path / "p")]
    )
    assert r.exit_code == 2 and "delta" in r.output


def test_optimize_checks_a_fit_with_its_calibrated_constants(folder, tmp_path, monkeypatch):
    """The simulator check of a fit-mf model runs at the fit's posterior median, and the
    output says so; a plain ensemble folder is checked at the authors' constants."""
    import importlib
    import json

    from mfdesign.calibration.workflow import calibrated_sim_params
    from mfdesign.workflows.models import simulator_constants
    from tiny_models import tiny_ensemble

    fit = load_multi_fidelity(folder)
    params, desc = calibrated_sim_params(fit)
    names = list(fit.posterior.names)
    median = np.median(fit.posterior.samples, axis=0)
    assert params.mu_pa == pytest.approx(median[names.index("mu_pa")], rel=1e-12)
    assert params.jm == pytest.approx(median[names.index("jm")], rel=1e-12)
    assert params.thickness_factor == 1.0  # a new membrane: the population's centre
    assert desc["constants"] == "calibrated" and desc["mu_pa"] == params.mu_pa
    tiny_ensemble().save(tmp_path / "ens")
    authors, adesc = simulator_constants(tmp_path / "ens")
    assert adesc["constants"] == "authors" and authors.mu_pa == 31.7e3 and authors.mu_pa != params.mu_pa

    seen = {}

    def fake_check(design, force_n, p_pa, predicted_h_mm, params=None, **kw):
        seen["params"] = params
        n = len(force_n)
        return dict(
            force_n=list(force_n),
            p_pa=list(p_pa),
            h_sim_mm=[10.0] * n,
            h_model_mm=list(predicted_h_mm),
            status=["OK"] * n,
            mae_mm=1.0,
        )

    monkeypatch.setattr(importlib.import_module("mfdesign.optimization"), "check_with_simulator", fake_check)
    out = tmp_path / "o"
    args = ["optimize", "--model", str(folder), "--target-set", "A", "--rings", "0", "--starts", "4"]
    # the fake check disagrees with the model: no simulator search here (tests/test_simulator_refine.py)
    r = runner.invoke(
        app, [*args, "--refine", "2", "--opt-steps", "2", "--check", "--sim-refine-steps", "0", "--out", str(out)]
    )
    assert r.exit_code == 0, r.output
    assert seen["params"].mu_pa == params.mu_pa and seen["params"].jm == params.jm
    sim = json.loads((out / "optimize.json").read_text())["simulator"]
    assert sim["constants"]["constants"] == "calibrated" and sim["constants"]["model"] == str(folder)
    assert f"simulator check at calibrated constants (posterior median of {folder})" in r.output


def test_propose_lists_but_does_not_make_sim_runs_of_a_standin_fit(folder, tmp_path):
    """A stand-in fit has no simulator behind it: its sim runs are listed, and its membranes
    to fabricate left unchecked, each with the reason (issue 43: never a silent null)."""
    import json

    out = tmp_path / "p"
    args = ["propose", "--model", str(folder), "--membranes", "1", "--sim-runs", "1", "--rings", "0"]
    r = runner.invoke(app, [*args, "--restarts", "4", "--refine", "2", "--opt-steps", "2", "--out", str(out)])
    assert r.exit_code == 0, r.output
    doc = json.loads((out / "proposal.json").read_text())
    (entry,) = doc["simulate"]
    assert entry["made"] is False and "standin" in entry["why_not_made"]
    (fab,) = doc["fabricate"]
    assert fab["simulator_check"]["checked"] is False and "standin" in fab["simulator_check"]["why_not_checked"]
    assert any("not checked by the simulator: the model was fitted with --physics standin" in b for b in doc["banners"])
    assert "simulator check: none (the model was fitted with --physics standin" in r.output
    # provenance (issue 41 item 6): version, call, seed, the model's files hashed, machine
    prov = doc["provenance"]
    assert prov["seeds"] == {"seed": 0} and prov["machine"]["cores"] >= 1 and prov["mfdesign_version"]
    assert any(k.endswith("mf.json") and len(v) == 64 for k, v in prov["inputs_sha256"].items())
    assert "simulator runs (listed, not made: the model was fitted with --physics standin" in r.output


def test_a_fit_with_the_coupons_rubber_and_no_latents_reloads_as_fitted(tmp_path):
    """`fit-mf --material coupons --no-latents`: mu and J_m stay in the coupons' held ranges,
    no thickness latents, and the folder reloads into the same layout (mf.json records it)."""
    import json

    meas = read_parquet(BUNDLED)
    data = tmp_path / "two.parquet"
    write_parquet(meas.subset(meas.design_keys[:2]), data)
    out = tmp_path / "fit"
    args = ["fit-mf", str(data), "--out", str(out), "--physics", "standin", "--mcmc-steps", "30", "--walkers", "16"]
    args += ["--max-rows", "60", "--members", "2", "--delta-steps", "20", "--material", "coupons", "--no-latents"]
    r = runner.invoke(app, args)
    assert r.exit_code == 0, r.output
    meta = json.loads((out / "mf.json").read_text())
    assert meta["material"] == "coupons" and meta["membrane_latents"] is False
    fit = load_multi_fidelity(out)
    names = list(fit.posterior.names)
    assert not any(n.startswith("thickness") for n in names) and not fit.model.uses_latents
    mu = np.asarray(fit.posterior.samples[:, names.index("mu_pa")])
    jm = np.asarray(fit.posterior.samples[:, names.index("jm")])
    assert 31.3e3 <= mu.min() and mu.max() <= 31.7e3 and 39.4 <= jm.min() and jm.max() <= 39.8


def test_an_unknown_material_is_one_line_and_exit_2(tmp_path):
    meas = read_parquet(BUNDLED)
    data = tmp_path / "two.parquet"
    write_parquet(meas.subset(meas.design_keys[:2]), data)
    r = runner.invoke(app, ["fit-mf", str(data), "--out", str(tmp_path / "o"), "--material", "rubbery"])
    assert r.exit_code == 2
    assert "--material must be one of free, coupons, coupons-jm" in r.output and "Traceback" not in r.output
