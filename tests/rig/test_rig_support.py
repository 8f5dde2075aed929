"""Shared helpers for the rig tests (emulator on a pty, journal checks); no tests here."""

from __future__ import annotations

import contextlib
from pathlib import Path

import pandas as pd

from mfdesign.design import Membrane
from mfdesign.rig.config import RigConfig
from mfdesign.rig.emulator import AnalyticPlant, RigEmulator
from mfdesign.rig.procedures import read_samples

RINGLESS = "[2.0, 25.4, nan, nan, nan, nan]"
RINGED = "[2.0, 25.4, 33.4, 5.0, 46.4, 5.0]"
SCALE = 25.0  # rig seconds per wall second in the tests


def fast_config(**kw) -> RigConfig:
    # generous timeout and hard limit: accelerated time on a loaded CI machine stretches the
    # host's reaction (x SCALE in rig seconds); the fault tests set their own where it matters
    base = dict(telemetry_timeout_s=2.0, hard_pressure_limit_pa=20000.0)
    base.update(kw)
    return RigConfig(**base)


@contextlib.contextmanager
def emulator(key: str = RINGLESS, faults=(), config: RigConfig | None = None, burst_pa=None, **kw):
    plant = AnalyticPlant.from_design(Membrane.from_key(key), burst_pressure_pa=burst_pa)
    em = RigEmulator(plant, config or fast_config(), time_scale=kw.pop("time_scale", SCALE), faults=list(faults), **kw)
    em.start()
    try:
        yield em
    finally:
        em.stop()


def log_text(job_dir) -> str:
    return (Path(job_dir) / "rig.log").read_text()


def assert_safe_after(em: RigEmulator, wall: float) -> float:
    """The emulator received s, q, h (in that order) after ``wall``; returns when 'h' came."""
    seq = [(w, c) for w, _, c in em.received if w >= wall]
    want = ["s", "q", "h"]
    for w, c in seq:
        if want and c == want[0]:
            want.pop(0)
            if not want:
                return w
    raise AssertionError(f"emulator did not receive s, q, h after the fault; got {[c for _, c in seq]}")


def assert_journal_consistent(job_dir) -> pd.DataFrame:
    df = read_samples(job_dir)
    assert list(df["seq"]) == list(range(len(df))), "journal seq must be 0..n-1, no gaps, no duplicates"
    return df


def assert_no_lost_samples(em: RigEmulator, job_dir) -> int:
    """Every valid line the emulator sent during a journaled trial attempt is in the journal,
    once, and the journal holds nothing the emulator did not send as a valid line."""
    df = assert_journal_consistent(job_dir)
    valid = [round(t, 3) for _, t, kind, _ in em.sent if kind in ("ok", "dropout")]
    valid_set = set(valid)
    n = 0
    for (_, _), g in df.groupby(["trial_key", "attempt"]):
        times = [round(t, 3) for t in g["rig_time_s"]]
        assert len(times) == len(set(times)), "a sample was recorded twice"
        assert set(times) <= valid_set, "journal holds a sample the emulator never sent validly"
        lo, hi = min(times), max(times)
        expected = [t for t in valid if lo <= t <= hi]
        missing = sorted(set(expected) - set(times))
        assert not missing, f"samples sent but not recorded: {missing[:5]}"
        n += len(times)
    return n
