"""A job killed mid-trial (SIGKILL of the host process) resumes without losing or
duplicating samples; the interrupted attempt stays in the journal but not in the
measurements."""

import json
import signal
import subprocess
import sys
import time
from pathlib import Path

from mfdesign.design import Membrane
from mfdesign.rig.procedures import iter_trial_events, membrane_plan, read_samples, run_job, to_measurements

from test_rig_support import RINGLESS, assert_no_lost_samples, emulator, fast_config

ROOT = Path(__file__).resolve().parents[2]


def _count_lines(path: Path) -> int:
    try:
        return path.read_bytes().count(b"\n")
    except FileNotFoundError:
        return 0


def _in_trial(job: Path) -> bool:
    try:
        lines = (job / "trials.jsonl").read_bytes().splitlines()
    except FileNotFoundError:
        return False
    return bool(lines) and b'"event": "start"' in lines[-1]


def test_killed_job_resumes_without_loss_or_duplicates(tmp_path):
    cfg = fast_config()
    cfg_path = tmp_path / "rig.json"
    cfg_path.write_text(json.dumps(cfg.to_dict()))
    job = tmp_path / "job"
    samples = job / "samples.csv"
    args = [
        "--design",
        RINGLESS,
        "--out",
        str(job),
        "--config",
        str(cfg_path),
        "--heights",
        "10",
        "--heights",
        "20",
        "--trials",
        "2",
        "--source",
        "virtual",
        "--no-progress",
    ]
    with emulator(config=cfg) as em:
        proc = subprocess.Popen(
            [sys.executable, "-m", "mfdesign.cli", "rig", "characterize", "--port", em.port, *args],
            cwd=ROOT,
            stdout=subprocess.PIPE,
            stderr=subprocess.STDOUT,
        )
        try:
            deadline = time.monotonic() + 60
            while _count_lines(samples) < 100 or not _in_trial(job):  # mid-trial, past the first
                assert proc.poll() is None, proc.stdout.read().decode()
                assert time.monotonic() < deadline, "job did not start"
                time.sleep(0.01)
            proc.send_signal(signal.SIGKILL)
            proc.wait(timeout=10)
        finally:
            if proc.poll() is None:
                proc.kill()
        before = samples.read_bytes()
        before = before[: before.rfind(b"\n") + 1]  # a line cut mid-write is not a recorded sample
        events = list(iter_trial_events(job))
        assert events[-1]["event"] == "start", "the kill should land mid-trial"
        cut_key = events[-1]["trial_key"]
        plan = membrane_plan(Membrane.from_key(RINGLESS), heights_mm=(10, 20), trials=2, source="virtual")
        res = run_job(em.port, job, plan, cfg, progress=False)  # resume (in this process)
    assert res.status == "complete"
    assert res.skipped + len(res.trials_run) == 4
    assert res.trials_run[0].key == cut_key and res.trials_run[0].attempt == 1
    after = samples.read_bytes()
    assert after.startswith(before), "samples recorded before the kill must be kept as they were"
    assert_no_lost_samples(em, job)  # also: seq 0..n-1, no duplicates, nothing invented
    raw = read_samples(job)
    ends = [e for e in iter_trial_events(job) if e["event"] == "end"]
    assert [e["status"] for e in ends if e["trial_key"] == cut_key] == ["aborted", "complete"]
    complete = {(e["trial_key"], e["attempt"]) for e in ends if e["status"] == "complete"}
    assert sorted(k for k, _ in complete) == sorted(t.key for t in plan.all_trials())  # each trial once
    df = to_measurements(job).df
    n_complete = sum(((raw["trial_key"] == k) & (raw["attempt"] == a)).sum() for k, a in complete)
    assert len(df) == n_complete < len(raw)
    assert sorted(df.groupby(["height_set_mm", "trial"]).groups) == [(10.0, 0), (10.0, 1), (20.0, 0), (20.0, 1)]
    assert "was cut off" in (job / "rig.log").read_text()
