"""Issue 41 item 3 (slow): the demo's folder is a campaign that two more rounds continue.

``mfdesign demo --quick --physics standin --out D`` (the CLI, as the README runs it), then
``experiments/campaign_rounds.py``: each round asks for a membrane, "builds" it on the
virtual rig (the bundled dataset's truth and hidden effect), tells it and refits. Every
round's model predicts two membranes measured on the same rig that no round sees; that
held-out error must fall from round to round, and ``mfdesign status D`` must list the
three rounds with the campaign's own held-out error of rounds 1 and 2."""

from __future__ import annotations

import importlib.util
import math
from pathlib import Path

import pytest
from typer.testing import CliRunner

from mfdesign.cli import app

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

    rounds = result["rounds"]
    assert [r["round"] for r in rounds] == [0, 1, 2]
    rmse = [r["test_rmse_n"] for r in rounds]
    assert all(math.isfinite(x) for x in rmse)
    assert rmse[2] < rmse[1] < rmse[0], rmse  # held-out error on membranes no round saw
    for r in rounds[1:]:
        assert len(r["built"]) == 1 and math.isfinite(r["heldout_told"]["rmse_n"])

    status = runner.invoke(app, ["status", str(folder)])
    assert status.exit_code == 0, status.output
    lines = status.output.splitlines()
    table = [ln.split() for ln in lines if ln.strip()[:1].isdigit()]
    assert [row[0] for row in table] == ["0", "1", "2"]
    assert table[0][-1] == "-" and all(row[-2] != "-" for row in table[1:])  # held-out RMSE of rounds 1, 2
