"""Issue 41 item 3 (slow): the demo's folder is a campaign that two more rounds continue.

``mfdesign demo --quick --physics standin --out D`` (the CLI, as the README runs it): the
stand-in demo lives in a world of its own, the bundled card's designs, hidden effect and
noise measured on the virtual rig over the stand-in, so its diagnosis must find the card's
effect. Then ``experiments/campaign_rounds.py``: each round asks for a membrane, "builds"
it on the same virtual rig, tells it and refits. Every round's model predicts two
membranes no round sees, against the rig's readings and against its noise-free truth.

What this world can show: the model class holds the truth, so round 0 already predicts
the unseen membranes at the sensor's noise (0.2 N); there is nothing left for more rounds
to learn, and a fall from round to round would be chance (measured: 0.025, 0.034, 0.036 N
against the truth). The test asserts what must hold: every round stays at the floor, its
intervals cover, and ``mfdesign status D`` lists the three rounds with the campaign's own
held-out error of rounds 1 and 2."""

from __future__ import annotations

import importlib.util
import json
import math
from pathlib import Path

import pytest
from typer.testing import CliRunner

from mfdesign.cli import app
from mfdesign.design import Membrane

ROOT = Path(__file__).resolve().parents[1]


@pytest.mark.slow
def test_the_demos_campaign_continues_two_rounds_on_the_virtual_rig(tmp_path, monkeypatch):
    runner = CliRunner()
    folder = tmp_path / "demo"
    r = runner.invoke(app, ["demo", "--quick", "--physics", "standin", "--out", str(folder)])
    assert r.exit_code == 0, r.output
    assert "mfdesign ask" in r.output  # the demo says how to continue

    monkeypatch.syspath_prepend(str(ROOT / "experiments"))
    spec = importlib.util.spec_from_file_location("campaign_rounds", ROOT / "experiments" / "campaign_rounds.py")
    mod = importlib.util.module_from_spec(spec)
    spec.loader.exec_module(mod)
    result = mod.main(["--campaign", str(folder), "--rounds", "2", "--q", "1", "--out", str(tmp_path / "r.json")])

    assert "pressure_sensor" in json.loads((folder / "summary.json").read_text())["diagnosis"]["found"]
    rounds = result["rounds"]
    assert [r["round"] for r in rounds] == [0, 1, 2]
    for r in rounds:
        # the model's own error on membranes no round saw: under half the 0.2 N sensor noise
        assert r["test_truth_rmse_n"] < 0.1, rounds
        # against the readings: the noise itself, and intervals that cover
        assert r["test_rmse_n"] < 0.3 and 0.8 <= r["test_coverage90"] <= 1.0, rounds
    for r in rounds[1:]:
        assert len(r["built"]) == 1 and math.isfinite(r["heldout_told"]["rmse_n"])

    status = runner.invoke(app, ["status", str(folder)])
    assert status.exit_code == 0, status.output
    lines = status.output.splitlines()
    table = [ln.split() for ln in lines if ln.strip()[:1].isdigit()]
    assert [row[0] for row in table] == ["0", "1", "2"]
    assert table[0][-1] == "-" and all(row[-2] != "-" for row in table[1:])  # held-out RMSE of rounds 1, 2


@pytest.mark.slow
def test_in_a_world_the_model_does_not_hold_the_heldout_error_falls_when_each_round_builds_every_kind(
    tmp_path, monkeypatch
):
    """Issue 41 item 3 where there is something to learn: the stiff-rings stand-in world
    (``StandinWorld``: each ring raises the contact pressure by 0.65 where the model says
    0.4, a misfit no effect of the library reaches). Round 0 is the full stand-in demo on the
    card's six designs measured there; each later round asks for one membrane of each ring
    count (``Campaign.ask(each_ring_count=True)``), "builds" them in the same world, tells
    and refits. Six test membranes no round sees, over the design space.

    Measured (session 31, docs/campaign.md): the error against the noise-free truth fell
    1.257 -> 0.991 -> 0.939 -> 0.465 N over three rounds (1.257 -> 0.990 -> 0.580 N over
    two after the discrepancy's members drew other random weights: the fall held, its size
    did not). A free batch of three did not fall
    every round (1.257 -> 1.441 -> 1.075 -> 0.791 N), nor did two (1.257 -> 1.445 -> 1.348 ->
    1.269 N): it builds where the force spread is largest, ringed membranes, and the
    calibration fitted mostly on them carries their misfit to ringless ones. Not robust to
    every setting: from the quick demo the same asks gave 0.642 -> 0.571 -> 1.740 N, when
    round 2's data moved the calibration to another compromise (J_m 29 instead of 39; 31
    log units higher on those data, so no failed search)."""
    monkeypatch.syspath_prepend(str(ROOT / "experiments"))
    spec = importlib.util.spec_from_file_location("campaign_rounds", ROOT / "experiments" / "campaign_rounds.py")
    mod = importlib.util.module_from_spec(spec)
    spec.loader.exec_module(mod)
    folder = tmp_path / "stiff"
    args = ["--campaign", str(folder), "--world", "stiff-rings", "--start", "--rounds", "2", "--q", "1"]
    result = mod.main([*args, "--each-ring-count", "--out", str(tmp_path / "r.json"), "--no-figure"])

    rounds = result["rounds"]
    assert [r["round"] for r in rounds] == [0, 1, 2]
    truth = [r["test_truth_rmse_n"] for r in rounds]
    assert truth[1] < truth[0] and truth[2] < truth[1], rounds
    for r in rounds:
        assert 0.8 <= r["test_coverage90"] <= 1.0, rounds
    for r in rounds[1:]:  # every kind of membrane built every round
        assert sorted(Membrane.from_key(k).n_rings for k in r["built"]) == [0, 1, 2], r["built"]
