"""Controller watchdog and host heartbeat (issue 22): a host that stops talking leaves a rig
that goes safe by itself, before the pump can take the chamber past the hard limit."""

import logging
import signal
import subprocess
import sys
import time
from pathlib import Path

import pytest
from typer.testing import CliRunner

from mfdesign.design import Membrane
from mfdesign.cli.rig import rig_app
from mfdesign.rig.config import RigConfig
from mfdesign.rig.emulator import WORKING_PRESSURE_PA, RigEmulator, pump_time_s
from mfdesign.rig.procedures import RINGLESS_LIMIT_PA, iter_trial_events, lift_plan, membrane_plan, run_job
from mfdesign.rig.protocol import (
    DEFAULT_WATCHDOG_S,
    PSI_TO_PA,
    Command,
    RigConnection,
    TelemetryError,
    WatchdogStatus,
    WatchdogTripped,
    parse_watchdog_status,
)

from test_rig_support import RINGLESS, emulator, fast_config, log_text

ROOT = Path(__file__).resolve().parents[2]

# The killed host: connects, closes the valve, starts the pump, then only reads (its reader
# and heartbeat threads run) until the test kills it.
HOST = """
import sys
from mfdesign.rig.config import RigConfig
from mfdesign.rig.protocol import Command, RigConnection
conn = RigConnection(sys.argv[1], RigConfig(heartbeat_interval_s=float(sys.argv[2])))
conn.send(Command.VALVE_CLOSE)
conn.send(Command.PUMP_ON)
while True:
    conn.next_sample()
"""


def _trips(em: RigEmulator) -> list[tuple[float, str]]:
    return [(w, e) for w, _, e in em.events if e.startswith("watchdog")]


def _wait(cond, timeout_s: float) -> bool:
    deadline = time.monotonic() + timeout_s
    while not cond():
        if time.monotonic() > deadline:
            return False
        time.sleep(0.01)
    return True


def test_default_watchdog_is_well_inside_the_pump_budget():
    budget_s = pump_time_s(WORKING_PRESSURE_PA, RigConfig().hard_pressure_limit_pa)
    assert budget_s == pytest.approx(2.149, abs=0.001)  # the number quoted in protocol.py and docs/rig.md
    assert DEFAULT_WATCHDOG_S <= budget_s / 2
    assert 5 * RigConfig().heartbeat_interval_s <= DEFAULT_WATCHDOG_S  # four beats may be late or lost
    assert WORKING_PRESSURE_PA == RINGLESS_LIMIT_PA == lift_plan(Membrane.from_key(RINGLESS), 1.0).pressure_limits_pa[0]
    # the closed form is the model the emulator integrates
    em = RigEmulator(noise=False)
    em.pressure, em.pump, em.valve_open = WORKING_PRESSURE_PA, True, False
    while em.pressure < 12000.0:
        em._advance(0.01)
    assert em.t == pytest.approx(budget_s, abs=0.02)


def test_status_lines_parse_strictly():
    assert parse_watchdog_status(b"#watchdog,armed,1.000") == WatchdogStatus("armed", 1.0)
    assert parse_watchdog_status(b"#watchdog,tripped,1.25\r") == WatchdogStatus("tripped", 1.25)
    for bad in (
        b"#watchdog,armed",
        b"#watchdog,asleep,1",
        b"#watchdog,armed,x",
        b"#watchdog,armed,1,2",
        b"#watchdog,tripped,-1",
        b"#watchdog,armed,nan",
    ):
        with pytest.raises(TelemetryError):
            parse_watchdog_status(bad)
    assert Command.HEARTBEAT == "p"
    assert len({c.value for c in Command}) == len(Command)  # a character of its own


def test_emulator_refuses_a_bad_watchdog_time():
    for bad in (-1.0, float("nan"), float("inf")):
        with pytest.raises(ValueError, match="watchdog_s"):
            RigEmulator(watchdog_s=bad)


def test_heartbeats_keep_it_fed_and_it_trips_after_the_host_stops():
    cfg = fast_config()
    with emulator(config=cfg) as em:
        with RigConnection(em.port, cfg) as conn:
            assert _wait(lambda: conn.controller_watchdog_s is not None, 2.0), "no answer to the heartbeat"
            assert conn.controller_watchdog_s == DEFAULT_WATCHDOG_S
            time.sleep(DEFAULT_WATCHDOG_S + 0.3)  # longer than the watchdog: only heartbeats feed it
            assert _trips(em) == [] and conn.fault is None
            assert sum(c == "p" for _, _, c in em.received) >= 4
            assert "p" not in {c for _, c, _ in conn.sent}  # heartbeats stay out of the command record

        # The trip after the host's last command. Not simply the first trip: a host starved
        # for over a second while it closed (a loaded CI machine) tripped the watchdog then,
        # its next heartbeat re-armed it ("#watchdog,armed" last), and the test read that
        # earlier, legitimate trip (session 38).
        def tripped_after_last_command() -> bool:
            return bool(em.watchdog_trips) and em.watchdog_trips[-1][0] > max(w for w, _, _ in em.received)

        assert _wait(tripped_after_last_command, DEFAULT_WATCHDOG_S + 1.0)
        trip_wall, _, silent_s, _ = em.watchdog_trips[-1]
        last_command = max(w for w, _, _ in em.received if w < trip_wall)
        assert silent_s == pytest.approx(trip_wall - last_command)
        assert DEFAULT_WATCHDOG_S < silent_s < DEFAULT_WATCHDOG_S + 0.5  # + slack for a starved emulator
        assert not em.pump and em.valve_open and em.motion == {"left": 0, "right": 0}
        # the status line goes out at the next line boundary, after the trip
        assert _wait(lambda: em.status_sent and em.status_sent[-1][2].startswith("#watchdog,tripped,"), 1.0)


def test_a_controller_without_the_watchdog_is_reported(caplog):
    cfg = fast_config(heartbeat_interval_s=0.1)
    with caplog.at_level(logging.WARNING, logger="mfdesign.rig"):
        with emulator(config=cfg, watchdog_s=0) as em, RigConnection(em.port, cfg) as conn:
            assert _wait(lambda: "did not answer" in caplog.text, 2.5)
            assert conn.controller_watchdog_s is None and em.status_sent == [] and _trips(em) == []
    assert "its firmware has no watchdog" in caplog.text


def test_a_trip_while_pumping_is_a_fault_not_a_burst(tmp_path, monkeypatch):
    """A host stalled past the watchdog (here: heartbeats lost) finds the rig vented under it:
    the trial is aborted (resumable), never marked burst, though the pressure fell while pumping."""
    monkeypatch.setattr(RigConnection, "_beat", lambda self: True)  # beats "sent", none arrive
    cfg = fast_config()
    plan = membrane_plan(Membrane.from_key(RINGLESS), heights_mm=(20,), trials=1, source="virtual")
    with emulator(config=cfg, time_scale=2.0, start_height_mm=20.0) as em:
        with pytest.raises(WatchdogTripped, match="went safe by itself"):
            run_job(em.port, tmp_path, plan, cfg, progress=False)
    assert len(_trips(em)) >= 1
    end = [e for e in iter_trial_events(tmp_path) if e["event"] == "end"][-1]
    assert end["status"] == "aborted" and end["burst"] is False
    log = log_text(tmp_path)
    assert "FAULT watchdog" in log and "BURST" not in log


SCALE = 4.0  # real time compressed 4x, watchdog and heartbeat with it (see the test below)


def _kill_pumping_host(watchdog_s: float) -> dict:
    """Run the host in a subprocess until the emulated chamber reaches the working pressure,
    SIGKILL it, watch for twice the time the pump alone needs to reach the hard limit; return
    what the emulator recorded."""
    hard_pa = RigConfig().hard_pressure_limit_pa
    with emulator(config=RigConfig(), time_scale=SCALE, watchdog_s=watchdog_s) as em:
        host = subprocess.Popen(
            [sys.executable, "-c", HOST, em.port, str(RigConfig().heartbeat_interval_s / SCALE)],
            cwd=ROOT,
            stdout=subprocess.PIPE,
            stderr=subprocess.STDOUT,
        )
        try:
            deadline = time.monotonic() + 30
            while em.pressure < WORKING_PRESSURE_PA:
                assert host.poll() is None, host.stdout.read().decode()
                assert not _trips(em), "the watchdog tripped while the host was alive (heartbeat late?)"
                assert time.monotonic() < deadline, "the host never got the pump to the working pressure"
                time.sleep(0.005)
            assert em.pump and not em.valve_open
            p_kill_pa = em.pressure
            host.send_signal(signal.SIGKILL)
            killed = time.monotonic()
            host.wait(timeout=10)
        finally:
            if host.poll() is None:
                host.kill()
        budget_s = em.time_to_pressure_s(p_kill_pa, hard_pa)
        assert budget_s < 2.5  # without a watchdog the limit falls inside the window
        time.sleep(max(0.0, killed + 2 * budget_s / SCALE - time.monotonic()))
        # the emulator's exact pressure when its pump stopped, and every line it sent after the kill
        sent_pa = [float(line.split(",")[2]) * PSI_TO_PA for w, _, _, line in em.sent if w >= killed]
        peak_pa = max(sent_pa + [t[3] for t in em.watchdog_trips] + [em.pressure])
        return dict(
            p_kill_pa=p_kill_pa,
            killed=killed,
            peak_pa=peak_pa,
            hard_pa=hard_pa,
            trips=_trips(em),
            pump=em.pump,
            valve_open=em.valve_open,
            motion=dict(em.motion),
        )


def test_killed_host_leaves_the_pressure_under_the_hard_limit():
    """SIGKILL of a host pumping at the working pressure: the emulated controller goes safe on
    its own and the chamber never passes the 12 kPa hard limit.

    Real time compressed 4x so the test takes seconds: the emulator runs at time scale 4 with
    the default watchdog and heartbeat also divided by 4 (0.25 s and 0.05 s of wall clock), so
    the pump gets the same 1 rig second as on the real rig with the defaults."""
    r = _kill_pumping_host(DEFAULT_WATCHDOG_S / SCALE)
    ((trip_wall, what),) = r["trips"]
    print(
        f"killed at {r['p_kill_pa']:.0f} Pa; watchdog {trip_wall - r['killed']:.3f} s later; "
        f"peak {r['peak_pa']:.0f} Pa (hard limit {r['hard_pa']:.0f} Pa); {what}"
    )
    assert r["peak_pa"] < r["hard_pa"]
    assert not r["pump"] and r["valve_open"] and r["motion"] == {"left": 0, "right": 0}
    assert trip_wall - r["killed"] < 2 * DEFAULT_WATCHDOG_S / SCALE + 0.5  # + slack for a loaded machine


@pytest.mark.slow
def test_killed_host_without_watchdog_passes_the_hard_limit():
    """The problem of issue 22, for contrast: firmware without the watchdog keeps pumping."""
    r = _kill_pumping_host(0.0)
    print(f"no watchdog: killed at {r['p_kill_pa']:.0f} Pa; peak {r['peak_pa']:.0f} Pa")
    assert r["trips"] == [] and r["pump"] and r["peak_pa"] > r["hard_pa"]


def test_cli_watchdog_option():
    runner = CliRunner()
    for bad in ("-1", "nan", "inf"):
        r = runner.invoke(rig_app, ["emulate", "--watchdog-s", bad])
        assert r.exit_code == 2, r.output
        lines = r.output.strip().splitlines()
        assert lines == [f"error: --watchdog-s must be a number of seconds >= 0 (0: off), got {bad}"], r.output
