"""Simulator runs a proposal chose are made and reported: mfdesign.sim_runs and `propose`.

A stand-in simulator (an analytic plane with chosen statuses) keeps these fast; one slow
test runs the real shooting simulator on a tiny plane.
"""

from __future__ import annotations

import json

import jax.numpy as jnp
import numpy as np
import pytest
from typer.testing import CliRunner

from mfdesign import sim_runs
from mfdesign.acquire import FunctionPredictor, Run
from mfdesign.data.store import read_parquet
from mfdesign.design import Membrane
from mfdesign.physics.status import Status
from tiny_models import tiny_ensemble

runner = CliRunner()
SPEC = sim_runs.PlaneSpec(h_max_mm=40.0, p_max_pa=6000.0, n_heights=3, n_pressures=4)
OFFSETS = np.array([-1.0, 0.0, 1.0, 2.0])  # members = truth + offset: mean error 0.5 N, std sqrt(1.25) N


def truth(d, h, p):
    """The stand-in simulator's force [N]: linear in pressure, falling with height."""
    return d[..., 1] / 25.0 * p / 1000.0 - 0.05 * h


PRED = FunctionPredictor({"sim": lambda d, h, p: truth(d, h, p)[None] + jnp.asarray(OFFSETS)[:, None]})


def stand_in(bad_points=0, fail_design=None):
    """``simulate(designs, spec, params)`` returning ``truth`` planes, the first
    ``bad_points`` points NOT_CONVERGED (NaN), raising for ``fail_design``."""

    def simulate(designs, spec, params):
        out = []
        for d in designs:
            if fail_design is not None and d.key() == fail_design:
                raise RuntimeError("shooting blew up")
            H, P = np.meshgrid(spec.h_mm, spec.p_pa, indexing="ij")
            f = np.asarray(truth(d.to_array(), H, P), float)
            status = np.full(f.shape, int(Status.OK))
            status.ravel()[:bad_points] = int(Status.NOT_CONVERGED)
            f.ravel()[:bad_points] = np.nan
            out.append((f, status, np.zeros_like(f)))
        return out

    return simulate


def _run(rank, key):
    return Run(rank, Membrane.from_key(key), "sim", 1.0, 1.0, 0.01, "a reason")


A, B = "[2.0, 30.0, nan, nan, nan, nan]", "[1.5, 27.0, nan, nan, nan, nan]"


def test_made_run_reports_the_error_against_the_simulator_and_the_predicted_spread():
    (m,) = sim_runs.make([_run(1, A)], PRED, spec=SPEC, simulate=stand_in())
    assert m.state == "converged" and m.converged and m.points == m.usable_points == 12
    assert m.rmse_n == pytest.approx(0.5) and m.max_error_n == pytest.approx(0.5)
    assert m.predicted_std_n == pytest.approx(np.sqrt(1.25))
    assert "within the predicted spread" in m.taught()
    out = m.to_json()
    assert out["made"] and out["error_over_predicted"] == pytest.approx(0.5 / np.sqrt(1.25))
    assert m.surrogate_rmse_n is None  # no surrogate given
    data = sim_runs.as_measurements([m])
    assert len(data) == 12 and set(data.df["source"]) == {"simulated"} and set(data.df["design_key"]) == {A}
    (m,) = sim_runs.make(
        [_run(1, A)], PRED, spec=SPEC, simulate=stand_in(), surrogate=lambda d, h, p: truth(d, h, p) - 0.3
    )
    assert m.surrogate_rmse_n == pytest.approx(0.3) and "surrogate alone" in m.taught()


def test_unconverged_points_and_a_failing_design_are_reported_not_dropped():
    (m,) = sim_runs.make([_run(1, A)], PRED, spec=SPEC, simulate=stand_in(bad_points=5))
    assert m.state == "partly converged" and not m.converged
    assert m.failed_points == 5 and m.status == {"OK": 7, "NOT_CONVERGED": 5} and m.usable_points == 7
    (m,) = sim_runs.make([_run(1, A)], PRED, spec=SPEC, simulate=stand_in(bad_points=12))
    assert m.state == "not converged" and m.rmse_n is None and "nothing learned" in m.taught()
    assert sim_runs.as_measurements([m]) is None
    good, bad = sim_runs.make([_run(1, A), _run(2, B)], PRED, spec=SPEC, simulate=stand_in(fail_design=B))
    assert good.state == "converged" and good.rmse_n == pytest.approx(0.5)  # the batch retried one by one
    assert bad.state == "failed" and "shooting blew up" in bad.error and bad.table is None
    assert bad.to_json()["converged"] is False and "simulator failed" in bad.to_json()["taught"]


def _split_folder(path):
    import mfdesign

    mfdesign.enable_x64()
    tiny_ensemble(seed=0).save(path / "sim")
    tiny_ensemble(seed=1).save(path / "discrepancy")
    return path


ARGS = ["--rings", "0", "--thickness-mm", "2", "2", "--restarts", "4", "--refine", "2", "--opt-steps", "2"]


def test_cli_makes_the_sim_run_writes_it_and_reports_it(tmp_path, monkeypatch):
    from mfdesign.cli import app

    seen = {}

    def simulate(designs, spec, params):
        seen["params"] = params
        return stand_in(bad_points=2)(designs, spec, params)

    monkeypatch.setattr(sim_runs, "simulate_planes", simulate)
    model = _split_folder(tmp_path / "split")
    out = tmp_path / "o"
    r = runner.invoke(app, ["propose", "--model", str(model), "--sim-runs", "1", *ARGS, "--out", str(out)])
    assert r.exit_code == 0, r.output
    assert seen["params"].mu_pa == 31.7e3  # a split model (no fit): the authors' constants
    report = json.loads((out / "proposal.json").read_text())
    (entry,) = report["simulate"]
    assert entry["made"] and entry["state"] == "partly converged" and entry["failed_points"] == 2
    assert entry["status"] == {"OK": 253, "NOT_CONVERGED": 2} and entry["points"] == 15 * 17
    assert entry["rmse_n"] > 0 and entry["predicted_std_n"] > 0 and entry["seconds"] >= 0
    assert entry["constants"]["constants"] == "authors"
    plane = out / "sim_runs" / "run1" / "plane.parquet"
    assert entry["plane"] == str(plane) and plane.is_file() and (out / "sim_runs" / "run1" / "summary.json").is_file()
    data = read_parquet(out / "sim_runs.parquet")
    assert len(data) == 253 and data.design_keys == [entry["design"]]
    assert report["sim_runs"]["made"] and report["sim_runs"]["plane"]["n_heights"] == 15
    assert "simulator runs (made by the tool at the authors' constants: mu 31.7 kPa, J_m 39.6)" in r.output
    assert "made: partly converged (OK 253, NOT_CONVERGED 2)" in r.output and "N RMS" in r.output
    assert "warning: simulator run 1" in r.output  # a failure is never silent


def test_cli_no_simulate_only_lists_and_bad_plane_is_one_line(tmp_path, monkeypatch):
    from mfdesign.cli import app

    def never(*a):
        raise AssertionError("--no-simulate ran the simulator")

    monkeypatch.setattr(sim_runs, "simulate_planes", never)
    model = _split_folder(tmp_path / "split")
    out = tmp_path / "o"
    args = ["propose", "--model", str(model), "--membranes", "1", "--sim-runs", "1", *ARGS]
    r = runner.invoke(app, [*args, "--no-simulate", "--out", str(out)])
    assert r.exit_code == 0, r.output
    (entry,) = json.loads((out / "proposal.json").read_text())["simulate"]
    assert entry["made"] is False and entry["why_not_made"] == "--no-simulate"
    assert "simulator runs (listed, not made: --no-simulate):" in r.output
    assert not (out / "sim_runs").exists()
    # the membrane to fabricate is not checked either, and says why (never a silent null)
    report = json.loads((out / "proposal.json").read_text())
    (fab,) = report["fabricate"]
    assert fab["simulator_check"] == {"checked": False, "why_not_checked": "--no-simulate: the simulator was not run"}
    assert any("not checked by the simulator: --no-simulate" in b for b in report["banners"])
    assert "simulator check: none (--no-simulate: the simulator was not run)" in r.output
    assert f"BANNER: membrane(s) to fabricate {fab['rank']} not checked by the simulator" in r.output
    r = runner.invoke(app, [*args, "--sim-heights", "1", "--out", str(out)])
    text = r.output.strip()
    assert r.exit_code == 2 and "--sim-heights" in text and len(text.splitlines()) == 1, text


@pytest.mark.slow
def test_the_real_simulator_makes_a_tiny_plane():
    spec = sim_runs.PlaneSpec(h_max_mm=30.0, p_max_pa=6000.0, n_heights=2, n_pressures=3)
    (m,) = sim_runs.make([_run(1, "[2.0, 25.4, nan, nan, nan, nan]")], PRED, spec=spec)
    assert m.error is None and m.points == 6 and sum(m.status.values()) == 6
    assert m.table["force_n"].notna().sum() == m.usable_points
    assert m.usable_points > 0 and np.isfinite(m.rmse_n)


def _model_plus(model, offset_n, seen):
    """A stand-in simulator that returns the model's own mean (sim fidelity where it has
    one, else rig) plus ``offset_n`` (so the check's error is exactly ``offset_n``),
    recording each call."""
    from mfdesign.workflows.models import load_predictor

    pred = load_predictor(model)
    fidelity = "sim" if "sim" in pred.fidelities else "rig"

    def simulate(designs, spec, params):
        seen.append((type(spec).__name__, [d.key() for d in designs], params))
        H, P = (a.ravel() for a in np.meshgrid(spec.h_mm, spec.p_pa, indexing="ij"))
        out = []
        for d in designs:
            rows = jnp.asarray(np.tile(d.to_array(), (H.size, 1)))
            f = np.asarray(pred.members(fidelity, rows, jnp.asarray(H), jnp.asarray(P))).mean(axis=0) + offset_n
            f = f.reshape(len(spec.h_mm), len(spec.p_pa))
            out.append((f, np.full(f.shape, int(Status.OK)), np.zeros_like(f)))
        return out

    return simulate


def test_cli_checks_every_membrane_to_fabricate_with_the_simulator(tmp_path, monkeypatch):
    """Issue 43: each membrane to fabricate is re-computed with the simulator (one batched
    call over the membranes, on the acquisition grid, at the model's constants) and
    proposal.json records the simulator's forces, the model's and its error there; an
    error beyond the predicted spread is a banner on the console and in proposal.json."""
    from mfdesign.acquire import Grid
    from mfdesign.cli import app

    model = _split_folder(tmp_path / "split")
    for offset, understated in ((0.0, False), (500.0, True)):
        seen = []
        monkeypatch.setattr(sim_runs, "simulate_planes", _model_plus(model, offset, seen))
        out = tmp_path / f"o{offset:g}"
        r = runner.invoke(app, ["propose", "--model", str(model), "--membranes", "2", *ARGS, "--out", str(out)])
        assert r.exit_code == 0, r.output
        report = json.loads((out / "proposal.json").read_text())
        assert [(kind, len(keys)) for kind, keys, _ in seen] == [("GridSpec", 2)]  # one batched call
        assert seen[0][2].mu_pa == 31.7e3  # a split model: the authors' constants
        for entry in report["fabricate"]:
            check = entry["simulator_check"]
            assert check["checked"] and check["compared_fidelity"] == "sim" and check["state"] == "converged"
            assert check["constants"]["constants"] == "authors"
            h, p = Grid().points()
            assert check["h_mm"] == h.tolist() and check["p_pa"] == p.tolist() and check["points"] == Grid().size
            sim, model_n = np.array(check["simulator_n"], float), np.array(check["model_n"], float)
            np.testing.assert_allclose(sim - model_n, offset, atol=1e-6)
            assert check["rmse_n"] == pytest.approx(offset, abs=1e-6)
            assert check["max_error_n"] == pytest.approx(offset, abs=1e-6)
            assert check["predicted_std_n"] > 0 and len(check["prediction_rig_n"]) == Grid().size
            assert check["understated"] is understated
        assert report["simulator_check"]["checked"] and report["simulator_check"]["seconds"] >= 0
        assert r.output.count("simulator check (sim fidelity vs simulator, 64 of 64 points)") == 2
        banner = [b for b in report["banners"] if "more than its predicted spread" in b]
        assert bool(banner) is understated
        assert ("BANNER: the model is off the simulator by more than its predicted spread" in r.output) is understated
        assert (out / "proposal.png").is_file()
    # a rig-only ensemble (`mfdesign fit`): its rig prediction is what the simulator checks
    rig_only = tmp_path / "rig_only"
    tiny_ensemble().save(rig_only)
    seen = []
    monkeypatch.setattr(sim_runs, "simulate_planes", _model_plus(rig_only, 0.0, seen))
    r = runner.invoke(app, ["propose", "--model", str(rig_only), "--q", "1", *ARGS, "--out", str(tmp_path / "r")])
    assert r.exit_code == 0, r.output
    (entry,) = json.loads((tmp_path / "r" / "proposal.json").read_text())["fabricate"]
    check = entry["simulator_check"]
    assert check["checked"] and check["compared_fidelity"] == "rig" and "prediction_rig_n" not in check
    assert "no separate simulator part" in check["compared"] and check["rmse_n"] == pytest.approx(0.0, abs=1e-6)
    assert len(seen) == 1 and "simulator check (rig fidelity vs simulator" in r.output
