"""run.log beside every command's outputs (version, command, settings, records, exit
status); --verbose / --quiet; bad input leaves no log (bad input writes nothing)."""

from __future__ import annotations

import json
from importlib.metadata import version

from typer.testing import CliRunner

from mfdesign.cli import app

runner = CliRunner()


def _settings(text: str) -> dict:
    line = next(ln for ln in text.splitlines() if " settings: " in ln)
    return json.loads(line.split(" settings: ", 1)[1])


def test_a_folder_command_writes_run_log_with_version_settings_and_status(tmp_path):
    out = tmp_path / "sim"
    args = ["simulate", "--out", str(out), "--n-heights", "2", "--n-pressures", "2", "--h-max-mm", "10"]
    r = runner.invoke(app, args)
    assert r.exit_code == 0, r.output
    text = (out / "run.log").read_text()
    assert f"mfdesign {version('mfdesign')}: " in text
    settings = _settings(text)
    assert settings["n_heights"] == 2 and settings["h_max_mm"] == 10.0 and settings["out"] == str(out)
    assert settings["design"] == "[2.0, 25.4, nan, nan, nan, nan]"  # defaults recorded too
    assert text.rstrip().splitlines()[-1].endswith(" s") and "finished: exit status 0 after" in text
    assert not [p for p in out.iterdir() if p.name.endswith(".part") or p.name == ".mfdesign.lock"]


def test_a_file_command_writes_its_log_beside_the_file(tmp_path):
    target = tmp_path / "m.parquet"
    r = runner.invoke(app, ["import", "bundled", "--out", str(target)])
    assert r.exit_code == 0, r.output
    text = (tmp_path / "m.parquet.run.log").read_text()
    assert _settings(text)["out"] == str(target) and "finished: exit status 0" in text


def test_bad_input_leaves_no_log_and_verbose_with_quiet_is_refused(tmp_path):
    out = tmp_path / "bad"
    r = runner.invoke(app, ["simulate", "--design", "[9, 9]", "--out", str(out)])
    assert r.exit_code == 2 and not (out / "run.log").exists()
    assert not [p for p in out.iterdir() if p.name.endswith(".part")]
    r = runner.invoke(app, ["--verbose", "--quiet", "simulate", "--out", str(out)])
    assert r.exit_code == 2 and "--verbose and --quiet exclude each other" in r.output
    assert len([ln for ln in r.output.splitlines() if ln.strip()]) == 1
