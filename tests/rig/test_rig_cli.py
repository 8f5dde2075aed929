"""The ``rig`` typer sub-app: characterize and lift against an emulator in a thread;
``emulate`` as a process that prints its device path and serves until Ctrl-C."""

import json
import signal
import subprocess
import sys
from pathlib import Path

import pandas as pd
from typer.testing import CliRunner

from mfdesign.units import G_M_S2
from mfdesign.cli.rig import rig_app

from test_rig_support import RINGLESS, emulator, fast_config

ROOT = Path(__file__).resolve().parents[2]
runner = CliRunner()


def _text(result) -> str:
    """Output with rich's box drawing and line wrapping undone."""
    return " ".join(result.output.replace("│", " ").split())


def _cfg_file(tmp_path) -> Path:
    p = tmp_path / "rig.json"
    p.write_text(json.dumps(fast_config().to_dict()))
    return p


def test_characterize_and_lift(tmp_path):
    cfg = _cfg_file(tmp_path)
    with emulator(config=fast_config()) as em:
        r = runner.invoke(
            rig_app,
            [
                "characterize",
                "--port",
                em.port,
                "--design",
                RINGLESS,
                "--out",
                str(tmp_path / "c"),
                "--config",
                str(cfg),
                "--heights",
                "10",
                "--heights",
                "20",
                "--trials",
                "1",
                "--source",
                "virtual",
                "--no-progress",
            ],
        )
    assert r.exit_code == 0, r.output
    assert "complete: 2 trials now, 0 before" in r.output
    df = pd.read_parquet(tmp_path / "c" / "measurements.parquet")
    assert set(df["height_set_mm"]) == {10.0, 20.0} and set(df["source"]) == {"virtual"}
    with emulator(config=fast_config(), payload_kg=1.5) as em:
        r = runner.invoke(
            rig_app,
            [
                "lift",
                "--port",
                em.port,
                "--design",
                RINGLESS,
                "--mass-kg",
                "1.5",
                "--out",
                str(tmp_path / "l"),
                "--config",
                str(cfg),
                "--trials",
                "1",
                "--pressure-limit-pa",
                "4000",
                "--source",
                "virtual",
                "--no-progress",
            ],
        )
    assert r.exit_code == 0, r.output
    df = pd.read_parquet(tmp_path / "l" / "measurements.parquet")
    assert (df["experiment"] == "lift").all() and df["force_n"].iloc[0] == 1.5 * G_M_S2


def test_bad_input_gets_a_clear_message(tmp_path):
    r = runner.invoke(
        rig_app,
        ["characterize", "--port", "/dev/null", "--design", "[2.0, 80.0, nan, nan, nan, nan]", "--out", str(tmp_path)],
    )
    assert r.exit_code == 2 and "contact radius 80.0 mm must be smaller" in _text(r)
    bad = tmp_path / "rig.toml"
    bad.write_text("telemetry_timeout_s = 0\n")
    r = runner.invoke(
        rig_app,
        [
            "lift",
            "--port",
            "/dev/null",
            "--design",
            RINGLESS,
            "--mass-kg",
            "1.5",
            "--out",
            str(tmp_path),
            "--config",
            str(bad),
        ],
    )
    assert r.exit_code == 2 and "telemetry_timeout_s must be a positive number" in _text(r)
    r = runner.invoke(
        rig_app,
        ["characterize", "--port", "/dev/null", "--design", RINGLESS, "--out", str(tmp_path), "--heights", "10,abc"],
    )
    assert r.exit_code == 2 and "comma-separated" in _text(r)
    r = runner.invoke(
        rig_app,
        [
            "characterize",
            "--port",
            str(tmp_path / "no-such-port"),
            "--design",
            RINGLESS,
            "--out",
            str(tmp_path / "j"),
            "--heights",
            "10",
            "--no-progress",
        ],
    )
    assert r.exit_code == 3 and "cannot open rig port" in _text(r)


def test_emulate_prints_port_and_serves_until_ctrl_c(tmp_path):
    proc = subprocess.Popen(
        [sys.executable, "-m", "mfdesign.cli", "rig", "emulate", "--time-scale", "25"],
        cwd=ROOT,
        stdout=subprocess.PIPE,
        stderr=subprocess.PIPE,
        text=True,
    )
    try:
        port = proc.stdout.readline().strip()
        assert port.startswith("/dev/pts/"), port
        r = runner.invoke(
            rig_app,
            [
                "characterize",
                "--port",
                port,
                "--design",
                RINGLESS,
                "--out",
                str(tmp_path / "c"),
                "--config",
                str(_cfg_file(tmp_path)),
                "--heights",
                "20",
                "--trials",
                "1",
                "--source",
                "virtual",
                "--no-progress",
            ],
        )
        assert r.exit_code == 0, r.output
        proc.send_signal(signal.SIGINT)
        assert proc.wait(timeout=10) == 0
        assert "emulator stopped" in proc.stderr.read()
    finally:
        if proc.poll() is None:
            proc.kill()


def test_characterize_survives_a_slow_host_before_the_pump(tmp_path, monkeypatch):
    """Issue 44, class 8: under load the host was slow (a journal fsync) just before
    switching the pump on; the samples queued meanwhile are older than the command, and at
    25x emulated time one wall second of them read as "pressure still 4 Pa after pumping
    15 s". The pressurise clock now starts at the first sample after the command. The
    stall is made deterministic here: the host sleeps 1.2 s (30 rig s) at every trial start."""
    import time

    from mfdesign.rig import procedures

    event = procedures.Journal.event

    def slow_event(self, **fields):
        out = event(self, **fields)
        if fields.get("event") == "start":
            time.sleep(1.2)
        return out

    monkeypatch.setattr(procedures.Journal, "event", slow_event)
    args = ["--design", RINGLESS, "--config", str(_cfg_file(tmp_path)), "--trials", "1", "--no-progress"]
    with emulator(config=fast_config()) as em:
        r = runner.invoke(
            rig_app, ["characterize", "--port", em.port, "--out", str(tmp_path / "c"), "--heights", "10", *args]
        )
    assert r.exit_code == 0, r.output
    assert "complete: 1 trials now" in r.output
