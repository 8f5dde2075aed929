"""The CLI contract itself: bugs give one line naming a log (exit 1); two runs on one --out
cannot mix files (the second fails at once); a killed run's lock does not stick."""

from __future__ import annotations

import json
import os
import signal
import subprocess
import sys
import time
from pathlib import Path

from typer.testing import CliRunner

from mfdesign.cli import app
from mfdesign.outputs import OutputLock

runner = CliRunner()
ROOT = Path(__file__).resolve().parents[2]


def _lines(r):
    return [ln for ln in r.output.splitlines() if ln.strip()]


def test_a_bug_prints_one_line_with_a_log_in_the_out_folder(tmp_path, monkeypatch):
    import mfdesign.workflows.data as commands

    def broken(*a, **k):
        raise ZeroDivisionError("deliberate")

    monkeypatch.setattr(commands, "cv", broken)
    r = runner.invoke(app, ["cv", "mass-lift", "--out", str(tmp_path / "cv.json")])
    assert r.exit_code == 1 and len(_lines(r)) == 1, r.output
    log = Path(_lines(r)[0].split("traceback in ")[1])
    assert log.parent == tmp_path and "ZeroDivisionError: deliberate" in log.read_text()
    assert "Traceback" not in r.output


def test_a_held_lock_refuses_a_second_run_at_once(tmp_path):
    out = tmp_path / "o"
    out.mkdir()
    with OutputLock(out):
        t0 = time.perf_counter()
        r = runner.invoke(app, ["simulate", "--out", str(out)])
        assert time.perf_counter() - t0 < 5
    assert r.exit_code == 2 and "in use by another mfdesign run" in r.output and len(_lines(r)) == 1
    assert [p.name for p in out.iterdir()] == []  # the held lock is released: no lock file stays behind


def _holder(out: Path) -> subprocess.Popen:
    """A real second process that holds the lock on ``out`` the way a running command does."""
    code = (
        "import sys, time; from mfdesign.outputs import OutputLock; "
        "lock = OutputLock(sys.argv[1]).acquire(); print('locked', flush=True); time.sleep(60)"
    )
    proc = subprocess.Popen(
        [sys.executable, "-c", code, str(out)],
        stdout=subprocess.PIPE,
        text=True,
        env={**os.environ, "PYTHONPATH": str(ROOT)},
    )
    assert proc.stdout.readline().strip() == "locked"
    return proc


def test_two_runs_at_once_and_a_killed_runs_lock(tmp_path):
    from mfdesign.design import Membrane
    from mfdesign.models.standin import standin_plane
    from mfdesign.rig.virtual import Protocol, VirtualRig

    data = tmp_path / "m.parquet"
    VirtualRig(seed=1, simulator=standin_plane, protocol=Protocol(sample_hz=0.5)).run(
        [Membrane.from_key("[2.0, 25.4, nan, nan, nan, nan]")], progress=False
    ).to_parquet(data)
    out = tmp_path / "rep"
    out.mkdir()
    args = ["diagnose", str(data), "--physics", "standin", "--no-search", "--out", str(out)]
    first = _holder(out)
    try:
        second = runner.invoke(app, args)
        assert second.exit_code == 2 and "in use" in second.output and str(first.pid) in second.output
        assert not (out / "diagnosis.json").exists()
    finally:
        first.send_signal(signal.SIGKILL)  # killed while holding the lock: the OS drops the flock
        first.wait()
    third = runner.invoke(app, args)
    assert third.exit_code == 0, third.output
    json.loads((out / "diagnosis.json").read_text())
    assert not [p for p in out.iterdir() if p.name.endswith(".tmp")]


def test_two_real_processes_on_one_out(tmp_path):
    """Both processes run the command; exactly the ones that got the lock write."""
    out = tmp_path / "sim"
    cmd = [
        sys.executable,
        "-m",
        "mfdesign.cli",
        "simulate",
        "--out",
        str(out),
        "--n-heights",
        "2",
        "--n-pressures",
        "2",
    ]
    env = {**os.environ, "PYTHONPATH": str(ROOT)}
    procs = [
        subprocess.Popen(cmd, env=env, stdout=subprocess.PIPE, stderr=subprocess.PIPE, text=True) for _ in range(2)
    ]
    results = [p.communicate(timeout=300) + (p.returncode,) for p in procs]
    codes = sorted(rc for *_, rc in results)
    assert codes in ([0, 0], [0, 2]), results  # sequential by chance, or one refused at once
    for o, e, rc in results:
        assert "Traceback" not in e
        if rc == 2:
            assert "in use by another mfdesign run" in e
    assert json.loads((out / "summary.json").read_text())["points"] == 4


def test_widened_design_space_is_said(tmp_path):
    key = "[5.0, 25.4, nan, nan, nan, nan]"
    r = runner.invoke(app, ["simulate", "--design", key, "--out", str(tmp_path)])
    assert r.exit_code == 2 and "allowed: thickness 1-3 mm" in r.output and "--allow-outside-design-space" in r.output


def test_the_exact_models_lattice_growth_is_said_on_stderr(capsys):
    """A calibration on exact physics can solve planes for an hour: the CLI shows the exact
    model's one line per lattice growth (once, however often the app is set up)."""
    import logging

    from mfdesign.cli._app import show_lattice_growth

    show_lattice_growth()
    show_lattice_growth()
    logging.getLogger("mfdesign.models.exact").info("exact planes: lattice grows to jm 0..1 (test)")
    captured = capsys.readouterr()
    assert captured.err.count("exact planes: lattice grows to jm 0..1 (test)") == 1
    assert "lattice grows" not in captured.out  # stderr: stdout stays the command's output
