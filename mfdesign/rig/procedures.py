"""Rig procedures: set height, characterisation and mass-lift trials, resumable jobs.

A *job* is a membrane's programme (a :class:`Plan`) run into a job directory:

- ``job.json``: the plan and the rig config (written once; a resume must match the plan);
- ``samples.csv``: every trial sample, appended and flushed as it arrives (fsync'ed right
  after by a background thread, so a slow disk never delays the control loop);
- ``trials.jsonl``: trial events (``start``, ``end`` with ``status`` complete / burst /
  aborted, ``end_reason``, ``burst`` flag), appended the same way;
- ``rig.log``: the rig log (faults, safe-state actions, bad lines, dropouts).

A killed job resumes where it stopped: finished trials are skipped, a trial that was cut
off is recorded as an aborted attempt (its samples stay in the journal, marked by their
``attempt``) and run again from the start, so nothing is lost and nothing is counted twice.
:func:`journal_frame` / :func:`to_measurements` turn the completed, unburst trials into the
Measurements table (burst and aborted trials stay in the journal only, as in the paper).
"""

from __future__ import annotations

import json
import logging
import math
import os
import threading
import time
from dataclasses import asdict, dataclass, field
from pathlib import Path
from typing import Iterator, Literal

import pandas as pd
from tqdm import tqdm

from mfdesign.data.measurements import COLUMNS
from mfdesign.rig.config import RigConfig
from mfdesign.rig.protocol import Command, RigConnection, RigFault, Sample
from mfdesign.units import G_M_S2

log = logging.getLogger("mfdesign.rig")

RINGED_LIMITS_PA = (4300.0, 6100.0)  # first pass, retest when the membrane did not burst
RINGLESS_LIMIT_PA = 10000.0  # ringless run until contact; this caps them
HEIGHTS_MM = tuple(float(h) for h in range(0, 71, 10))
MEASUREMENT_COLUMNS = list(COLUMNS)  # the Measurements schema (mfdesign.data.measurements)
SAMPLE_COLUMNS = [
    "seq",
    "trial_key",
    "attempt",
    "stage",
    "trial",
    "experiment",
    "phase",
    "height_set_mm",
    "rig_time_s",
    "time_s",
    "host_time_s",
    "height_mm",
    "left_mm",
    "right_mm",
    "height_held",
    "pressure_pa",
    "force_n",
    "flow",
    "contact",
]


class JobError(ValueError):
    """A job directory that cannot be (re)used as asked."""


class SensorDropout(RigFault):
    kind = "sensor_dropout"


class SetHeightError(RigFault):
    kind = "set_height"


class TrialTimeout(RigFault):
    kind = "trial_timeout"


class Burst(RigFault):
    kind = "burst"


# -- plans -------------------------------------------------------------------------------
@dataclass(frozen=True)
class TrialSpec:
    """One trial of a plan; ``key`` is unique within the job."""

    key: str
    experiment: Literal["force", "lift"]
    stage: int
    trial: int
    height_set_mm: float
    pressure_limit_pa: float
    mass_kg: float = 0.0


@dataclass(frozen=True)
class Plan:
    """A membrane's programme: stages (pressure limits) x heights x trials, or lift trials."""

    design_key: str
    experiment: Literal["force", "lift"]
    pressure_limits_pa: tuple[float, ...]
    heights_mm: tuple[float, ...] = ()
    trials: int = 3
    mass_kg: float = 0.0
    source: Literal["rig", "virtual"] = "rig"

    def __post_init__(self) -> None:
        if self.experiment not in ("force", "lift"):
            raise JobError(f"experiment must be 'force' or 'lift', got {self.experiment!r}")
        if not self.pressure_limits_pa or any(not (0 < p < 1e5) for p in self.pressure_limits_pa):
            raise JobError(f"pressure limits must be in (0, 100000) Pa, got {self.pressure_limits_pa}")
        if not (1 <= self.trials <= 100):
            raise JobError(f"trials must be 1..100, got {self.trials}")
        if self.experiment == "force" and not self.heights_mm:
            raise JobError("a force plan needs at least one height")
        if self.experiment == "lift" and not (0 < self.mass_kg <= 50):
            raise JobError(f"a lift plan needs a mass in (0, 50] kg, got {self.mass_kg}")
        if self.source not in ("rig", "virtual"):
            raise JobError(f"source must be 'rig' or 'virtual', got {self.source!r}")

    def stage_trials(self, stage: int) -> list[TrialSpec]:
        limit = self.pressure_limits_pa[stage]
        if self.experiment == "lift":
            return [
                TrialSpec(f"lift-s{stage}-t{k}", "lift", stage, stage * self.trials + k, math.nan, limit, self.mass_kg)
                for k in range(self.trials)
            ]
        return [
            TrialSpec(f"force-s{stage}-h{h:g}-t{k}", "force", stage, stage * self.trials + k, h, limit)
            for h in self.heights_mm
            for k in range(self.trials)
        ]

    def all_trials(self) -> list[TrialSpec]:
        return [t for s in range(len(self.pressure_limits_pa)) for t in self.stage_trials(s)]

    def to_dict(self) -> dict:
        return asdict(self)

    @classmethod
    def from_dict(cls, d: dict) -> "Plan":
        d = dict(d)
        d["pressure_limits_pa"] = tuple(d["pressure_limits_pa"])
        d["heights_mm"] = tuple(d["heights_mm"])
        return cls(**d)


def membrane_plan(
    design,
    *,
    heights_mm=HEIGHTS_MM,
    trials: int = 3,
    ringed_limits_pa=RINGED_LIMITS_PA,
    ringless_limit_pa: float = RINGLESS_LIMIT_PA,
    source: str = "rig",
) -> Plan:
    """The paper's programme: ringed to 4.3 kPa, retested to 6.1 kPa; ringless until contact."""
    limits = tuple(ringed_limits_pa) if design.n_rings else (ringless_limit_pa,)
    return Plan(design.key(), "force", limits, tuple(float(h) for h in heights_mm), trials, 0.0, source)


def lift_plan(
    design, mass_kg: float, *, trials: int = 3, pressure_limit_pa: float = 10000.0, source: str = "rig"
) -> Plan:
    return Plan(design.key(), "lift", (pressure_limit_pa,), (), trials, float(mass_kg), source)


# -- journal -----------------------------------------------------------------------------
def _fmt(v) -> str:
    if isinstance(v, bool):
        return "1" if v else "0"
    if isinstance(v, float):
        return repr(v)
    return str(v)


def _repair_tail(path: Path) -> None:
    """Cut a partial last line left by a crash mid-write (it was never a recorded sample)."""
    if not path.exists():
        return
    data = path.read_bytes()
    if data and not data.endswith(b"\n"):
        cut = data.rfind(b"\n") + 1
        with open(path, "r+b") as f:
            f.truncate(cut)
        log.warning("journal %s: dropped a partial last line (%d bytes) left by a crash", path.name, len(data) - cut)


class Journal:
    """Append-only job journal (see module doc); every write is flushed and fsync'ed."""

    def __init__(self, job_dir: str | Path, plan: Plan, config: RigConfig):
        self.dir = Path(job_dir)
        self.dir.mkdir(parents=True, exist_ok=True)
        self.config = config
        meta = self.dir / "job.json"
        if meta.exists():
            try:
                saved = json.loads(meta.read_text())
                saved_plan = Plan.from_dict(saved["plan"])
            except (ValueError, KeyError, TypeError) as exc:
                raise JobError(f"{meta} is not a job file: {exc}") from None
            if saved_plan != plan:
                raise JobError(f"{self.dir} holds a different job ({saved_plan}); use another --out to run {plan}")
            if saved.get("config") != config.to_dict():
                log.warning("rig config differs from the one this job started with; using the new one")
        else:
            tmp = meta.with_suffix(".tmp")
            tmp.write_text(json.dumps({"plan": plan.to_dict(), "config": config.to_dict()}, indent=1))
            os.replace(tmp, meta)
        self.plan = plan
        self.samples_path = self.dir / "samples.csv"
        self.events_path = self.dir / "trials.jsonl"
        for p in (self.samples_path, self.events_path):
            _repair_tail(p)
        new = not self.samples_path.exists() or self.samples_path.stat().st_size == 0
        self._dirty = threading.Event()
        self._closing = False
        self._sync_error: OSError | None = None
        self._syncer = threading.Thread(target=self._sync_loop, name="journal-fsync", daemon=True)
        self._samples = open(self.samples_path, "a", encoding="utf-8")
        self._events = open(self.events_path, "a", encoding="utf-8")
        if new:
            self._write(self._samples, ",".join(SAMPLE_COLUMNS) + "\n", force_sync=True)
        self.next_seq = self._last_seq() + 1
        self._syncer.start()

    def _last_seq(self) -> int:
        with open(self.samples_path, "rb") as f:
            f.seek(0, 2)
            f.seek(max(0, f.tell() - 4096))
            lines = f.read().splitlines()
        for line in reversed(lines):
            head = line.split(b",", 1)[0]
            if head.isdigit():
                return int(head)
        return -1

    def _write(self, f, text: str, force_sync: bool = False) -> None:
        """Write and flush now (in the OS: survives a crash of this process); fsync at once
        when ``force_sync``, else in the background thread, so a slow disk never delays the
        control loop (a pump-off) while the data still reaches the disk within milliseconds."""
        if self._sync_error is not None:
            raise self._sync_error
        f.write(text)
        f.flush()
        if force_sync:
            os.fsync(f.fileno())
        else:
            self._dirty.set()

    def _sync_loop(self) -> None:
        while True:
            self._dirty.wait()
            if self._closing:
                return
            self._dirty.clear()
            try:
                for f in (self._samples, self._events):
                    os.fsync(f.fileno())
            except OSError as exc:
                log.error("journal fsync failed: %s", exc)
                self._sync_error = exc
                return
            if self.config.fsync_interval_s:
                time.sleep(self.config.fsync_interval_s)

    def samples(self, spec: TrialSpec, attempt: int, t0: float, rows: list[tuple[str, Sample, float, bool]]) -> None:
        """Append ``(phase, sample, height_mm, height_held)`` rows; one flush (+ fsync)."""
        lines = []
        for phase, s, height_mm, held in rows:
            row = [
                self.next_seq + len(lines),
                spec.key,
                attempt,
                spec.stage,
                spec.trial,
                spec.experiment,
                phase,
                spec.height_set_mm,
                s.rig_time_s,
                s.rig_time_s - t0,
                time.time(),
                height_mm,
                s.left_mm,
                s.right_mm,
                held,
                s.pressure_pa,
                s.force_n,
                s.flow,
                s.contact,
            ]
            lines.append(",".join(_fmt(v) for v in row) + "\n")
        self._write(self._samples, "".join(lines))
        self.next_seq += len(lines)

    def event(self, **fields) -> None:
        fields.setdefault("wall_time", time.time())
        self._write(self._events, json.dumps(fields) + "\n", force_sync=True)

    def events(self) -> list[dict]:
        out = []
        with open(self.events_path, encoding="utf-8") as f:
            for n, line in enumerate(f, 1):
                try:
                    out.append(json.loads(line))
                except json.JSONDecodeError:
                    log.error("trials.jsonl line %d is unreadable; ignored", n)
        return out

    def sync(self) -> None:
        for f in (self._samples, self._events):
            f.flush()
            os.fsync(f.fileno())

    def close(self) -> None:
        self._closing = True
        self._dirty.set()
        self._syncer.join(timeout=10)
        for f in (self._samples, self._events):
            if not f.closed:
                f.flush()
                os.fsync(f.fileno())
                f.close()


@dataclass
class JobState:
    """What a journal says about a job: finished trials and attempts so far."""

    finished: dict[str, str] = field(default_factory=dict)  # key -> status (complete / burst)
    attempts: dict[str, int] = field(default_factory=dict)  # key -> attempts started
    open_attempts: list[tuple[str, int]] = field(default_factory=list)  # started, never ended

    @property
    def burst(self) -> bool:
        return "burst" in self.finished.values()


def job_state(events: list[dict]) -> JobState:
    st = JobState()
    open_: dict[tuple[str, int], bool] = {}
    for e in events:
        key, att = e.get("trial_key"), e.get("attempt")
        if e.get("event") == "start":
            st.attempts[key] = max(st.attempts.get(key, 0), att + 1)
            open_[(key, att)] = True
        elif e.get("event") == "end":
            open_.pop((key, att), None)
            if e.get("status") in ("complete", "burst"):
                st.finished[key] = e["status"]
    st.open_attempts = list(open_)
    return st


# -- procedures --------------------------------------------------------------------------
def _why(exc: BaseException) -> str:
    return type(exc).__name__ + (f": {exc}" if str(exc) else "")


def _moves(cfg: RigConfig) -> dict[str, dict[int, Command]]:
    """Per side: +1 (plate up), -1 (down), 0 (stop) -> command."""
    up_l, down_l = (
        (Command.LEFT_PULL, Command.LEFT_PUSH) if cfg.push_lowers_plate else (Command.LEFT_PUSH, Command.LEFT_PULL)
    )
    up_r, down_r = (
        (Command.RIGHT_PULL, Command.RIGHT_PUSH) if cfg.push_lowers_plate else (Command.RIGHT_PUSH, Command.RIGHT_PULL)
    )
    return {"left": {1: up_l, -1: down_l, 0: Command.LEFT_STOP}, "right": {1: up_r, -1: down_r, 0: Command.RIGHT_STOP}}


def set_height(conn: RigConnection, target_mm: float, config: RigConfig | None = None) -> float:
    """Move the plate to ``target_mm`` (each side on its own sensor) within the tolerance.

    Returns the settled height. A sensor that drops out borrows the other side's reading;
    both out longer than ``sensor_dropout_timeout_s`` is a :class:`SensorDropout` fault.
    """
    cfg = config or conn.config
    if not (cfg.height_min_mm <= target_mm <= cfg.height_max_mm):
        raise ValueError(f"height {target_mm} mm outside the rig's [{cfg.height_min_mm}, {cfg.height_max_mm}] mm")
    tol = cfg.height_tolerance_mm
    cmds = _moves(cfg)
    state = {"left": 0, "right": 0}
    settled, start, last_seen = 0, None, None
    while True:
        s = conn.next_sample()
        backlog = conn.drain()  # steer on the newest reading, not on a queue of stale ones
        s = backlog[-1] if backlog else s
        start = s.rig_time_s if start is None else start
        if s.rig_time_s - start > cfg.set_height_timeout_s:
            raise conn.fail(
                SetHeightError(
                    f"plate did not reach {target_mm:g} mm within "
                    f"{cfg.set_height_timeout_s:g} s (at {s.height_mm:.1f} mm)"
                )
            )
        h = {"left": s.left_mm, "right": s.right_mm}
        if math.isnan(h["left"]) and math.isnan(h["right"]):
            if any(state.values()):
                conn.send(Command.BOTH_STOP)
                state = {"left": 0, "right": 0}
            last_seen = s.rig_time_s if last_seen is None else last_seen
            if s.rig_time_s - last_seen > cfg.sensor_dropout_timeout_s:
                raise conn.fail(
                    SensorDropout(
                        f"both height sensors out for {s.rig_time_s - last_seen:.1f} s while setting the height"
                    )
                )
            continue
        last_seen = None
        for side, other in (("left", "right"), ("right", "left")):
            if math.isnan(h[side]):
                h[side] = h[other]
        if abs(h["left"] - h["right"]) > cfg.max_tilt_mm:
            log.warning("plate tilted: left %.1f mm, right %.1f mm", h["left"], h["right"])
        for side in ("left", "right"):
            err = target_mm - h[side]
            want = state[side]
            if state[side] == 0 and abs(err) > 0.4 * tol:  # aim well inside the tolerance:
                want = 1 if err > 0 else -1  # sensor noise must not carry samples outside it
            elif state[side] != 0 and (abs(err) < 0.15 * tol or err * state[side] < 0):
                want = 0
            if want != state[side]:
                conn.send(cmds[side][want])
                state[side] = want
        ok = all(abs(target_mm - h[x]) <= tol for x in h) and not any(state.values())
        settled = settled + 1 if ok else 0
        if settled >= 3:
            return 0.5 * (h["left"] + h["right"])


def wait_deflated(conn: RigConnection, config: RigConfig | None = None) -> None:
    """Pump off, valve open, wait until the chamber pressure is below ``zero_pressure_pa``."""
    cfg = config or conn.config
    conn.send(Command.PUMP_OFF)
    conn.send(Command.VALVE_OPEN)
    start = None
    while True:
        s = conn.next_sample()
        start = s.rig_time_s if start is None else start
        if s.pressure_pa < cfg.zero_pressure_pa:
            return
        if s.rig_time_s - start > cfg.trial_timeout_s:
            raise conn.fail(
                TrialTimeout(
                    f"chamber still at {s.pressure_pa:.0f} Pa after {cfg.trial_timeout_s:g} s with the valve open"
                )
            )


@dataclass
class TrialResult:
    key: str
    attempt: int
    status: str  # complete | burst
    end_reason: str  # pressure_limit | contact | height_limit | burst
    n_samples: int
    peak_pa: float


@dataclass
class _TrialState:
    """What a running trial has seen, and its decision on each new sample (the state
    machine of :func:`run_trial`: inflate until a limit, then deflate to zero)."""

    spec: TrialSpec
    cfg: RigConfig
    status: str = "complete"
    reason: str = ""
    peak: float = 0.0
    phase: str = "inflate"
    t0: float | None = None
    t_rise: float | None = None
    t_deflate: float = math.nan
    held: float = math.nan
    # host clock (time.monotonic) when the pump was switched on, and the rig time of the
    # first sample received after it: the timeouts count from there. Why not from the first
    # sample (t0): samples queued while the host was busy before switching the pump on (a
    # slow fsync of the journal on a loaded machine) are older than the command, and at 25x
    # emulated time one second of such a backlog read as "15 s pumping, still 4 Pa".
    pump_sent: float = -math.inf
    t_pump: float | None = None

    def see(self, smp: Sample) -> tuple[tuple, str | None, RigFault | None, bool]:
        """``(journal row, action, fault, done)`` for one sample; action is ``"burst"``,
        ``"deflate"`` or None; a fault or ``done`` ends the batch."""
        self.t0 = smp.rig_time_s if self.t0 is None else self.t0
        h, is_held = smp.height_mm, False
        if self.spec.experiment == "force":  # the plate is fixed: hold the last height over dropouts
            if math.isnan(h) and not math.isnan(self.held):
                h, is_held = self.held, True
            self.held = h
        row = (self.phase, smp, h, is_held)
        if self.phase == "inflate":
            return (row, *self._inflating(smp))
        fault, done = self._deflating(smp)
        return row, None, fault, done

    def _inflating(self, smp: Sample) -> tuple[str | None, RigFault | None, bool]:
        cfg, spec, p, t = self.cfg, self.spec, smp.pressure_pa, smp.rig_time_s
        if self.t_pump is None and smp.host_time >= self.pump_sent:
            self.t_pump = t
        pumping = t - self.t_pump if self.t_pump is not None else 0.0
        self.peak = max(self.peak, p)
        if self.t_rise is None and p > cfg.burst_min_peak_pa:
            self.t_rise = t
        if self.peak > cfg.burst_min_peak_pa and p < (1 - cfg.burst_drop_fraction) * self.peak:
            self.status = self.reason = "burst"
            log.error("BURST in trial %s: pressure fell from %.0f Pa to %.0f Pa while pumping", spec.key, self.peak, p)
            return "burst", None, True
        if p >= spec.pressure_limit_pa:
            self.reason = "pressure_limit"
        elif smp.contact:
            self.reason = "contact"
        elif spec.experiment == "lift" and smp.height_mm >= cfg.height_max_mm:
            self.reason = "height_limit"
        elif self.t_rise is None and pumping > cfg.pressurise_timeout_s:
            why = f"pressure still {p:.0f} Pa after pumping {cfg.pressurise_timeout_s:g} s (leak, pump failure or burst membrane)"
            return None, TrialTimeout(f"trial {spec.key}: {why}"), False
        elif pumping > cfg.trial_timeout_s:
            why = f"{spec.pressure_limit_pa:.0f} Pa not reached in {cfg.trial_timeout_s:g} s (at {p:.0f} Pa)"
            return None, TrialTimeout(f"trial {spec.key}: {why}"), False
        if not self.reason:
            return None, None, False
        self.phase, self.t_deflate = "deflate", t
        log.info("trial %s: %s at %.0f Pa; deflating", spec.key, self.reason, p)
        return "deflate", None, False

    def _deflating(self, smp: Sample) -> tuple[RigFault | None, bool]:
        if smp.pressure_pa < self.cfg.zero_pressure_pa:
            return None, True
        if smp.rig_time_s - self.t_deflate > self.cfg.trial_timeout_s:
            return TrialTimeout(f"trial {self.spec.key}: not deflated in {self.cfg.trial_timeout_s:g} s"), False
        return None, False


def _act(conn: RigConnection, action: str | None, fault: RigFault | None) -> None:
    """Drive the rig on a batch's decision: safe state first on a fault or a burst."""
    if fault is not None:
        conn.fail(fault)
    elif action == "burst":
        conn.safe_state("burst")
    elif action == "deflate":
        conn.send(Command.PUMP_OFF)
        conn.send(Command.VALVE_OPEN)


def run_trial(conn: RigConnection, journal: Journal, spec: TrialSpec, attempt: int) -> TrialResult:
    """One characterisation (plate held at ``height_set_mm``) or mass-lift trial.

    Inflate (valve closed, pump on) until the pressure limit, contact (limit switch) or, for
    lift, the height limit; then deflate to zero. A pressure collapse while pumping is a
    burst: safe state at once, trial ended and marked ``burst``. Each sample is journaled
    on arrival.
    """
    cfg = journal.config
    wait_deflated(conn, cfg)
    if spec.experiment == "force":
        set_height(conn, spec.height_set_mm, cfg)
    journal.event(event="start", trial_key=spec.key, attempt=attempt, **asdict(spec))
    log.info("trial %s attempt %d: inflate to %.0f Pa", spec.key, attempt, spec.pressure_limit_pa)
    state, n = _TrialState(spec, cfg), 0
    try:
        conn.send(Command.VALVE_CLOSE)
        conn.send(Command.PUMP_ON)
        state.pump_sent = time.monotonic()
        done = False
        while not done:
            # Everything received so far: decide on the newest data first, then journal it all
            # (one flush + fsync per batch; a batch is one sample when the host keeps up).
            rows, action, fault = [], None, None
            for smp in [conn.next_sample()] + conn.drain():
                row, act, fault, done = state.see(smp)
                rows.append(row)
                action = act or action
                if fault is not None or done:
                    break
            _act(conn, action, fault)
            journal.samples(spec, attempt, state.t0, rows)
            n += len(rows)
            if fault is not None:
                raise fault
    except BaseException as exc:
        conn.on_exception(exc)  # safe state first, then the bookkeeping
        journal.event(
            event="end",
            trial_key=spec.key,
            attempt=attempt,
            status="aborted",
            end_reason=_why(exc),
            burst=False,
            n_samples=n,
        )
        log.error("trial %s attempt %d aborted after %d samples: %s", spec.key, attempt, n, _why(exc))
        raise
    journal.event(
        event="end",
        trial_key=spec.key,
        attempt=attempt,
        status=state.status,
        end_reason=state.reason,
        burst=state.status == "burst",
        n_samples=n,
        peak_pa=state.peak,
    )
    return TrialResult(spec.key, attempt, state.status, state.reason, n, state.peak)


# -- jobs --------------------------------------------------------------------------------
@dataclass
class JobResult:
    job_dir: Path
    status: str  # complete | burst
    trials_run: list[TrialResult]
    skipped: int  # finished before this run (resume)


class _JobLog:
    """Attach ``rig.log`` in the job directory to the rig loggers for the job's duration."""

    def __init__(self, job_dir: Path):
        self.handler = logging.FileHandler(job_dir / "rig.log", encoding="utf-8")
        self.handler.setFormatter(
            logging.Formatter(
                "%(asctime)s.%(msecs)03d %(levelname)s [%(threadName)s] %(name)s: %(message)s", "%Y-%m-%d %H:%M:%S"
            )
        )
        self.handler.setLevel(logging.INFO)
        self.loggers = [logging.getLogger("mfdesign.rig")]

    def __enter__(self):
        for lg in self.loggers:
            lg.addHandler(self.handler)
            if lg.getEffectiveLevel() > logging.INFO:
                lg.setLevel(logging.INFO)
        return self

    def __exit__(self, *exc):
        for lg in self.loggers:
            lg.removeHandler(self.handler)
        self.handler.close()


def run_job(
    port: str, job_dir: str | Path, plan: Plan, config: RigConfig | None = None, *, progress: bool = True
) -> JobResult:
    """Run (or resume) a plan on the rig at ``port``, journaling into ``job_dir``.

    Any fault or exception leaves the rig safe and the port closed, and propagates; run
    it again with the same arguments to resume.
    """
    cfg = config or RigConfig()
    if max(plan.pressure_limits_pa) >= cfg.hard_pressure_limit_pa:
        raise JobError(
            f"plan pressure limits {plan.pressure_limits_pa} Pa must stay below the rig's "
            f"hard limit {cfg.hard_pressure_limit_pa:g} Pa"
        )
    job_dir = Path(job_dir)
    journal = Journal(job_dir, plan, cfg)
    with _JobLog(job_dir):
        try:
            return _run(port, journal, plan, cfg, progress)
        except BaseException as exc:
            log.error("job stopped: %s (resume by running it again)", _why(exc))
            raise
        finally:
            journal.close()


def _run(port: str, journal: Journal, plan: Plan, cfg: RigConfig, progress: bool) -> JobResult:
    st = job_state(journal.events())
    for key, att in st.open_attempts:
        journal.event(
            event="end",
            trial_key=key,
            attempt=att,
            status="aborted",
            end_reason="interrupted (found on resume)",
            burst=False,
        )
        log.warning(
            "resume: trial %s attempt %d was cut off; its samples stay in the journal, the trial runs again", key, att
        )
    todo = [t for t in plan.all_trials() if t.key not in st.finished]
    skipped = len(plan.all_trials()) - len(todo)
    log.info(
        "job %s: %s %s, %d trials to run, %d done before",
        journal.dir,
        plan.experiment,
        plan.design_key,
        len(todo),
        skipped,
    )
    if st.burst:
        log.warning("the membrane burst in an earlier run; nothing left to do")
        return JobResult(journal.dir, "burst", [], skipped)
    results: list[TrialResult] = []
    with (
        RigConnection(port, cfg) as conn,
        tqdm(total=len(todo), desc="trials", unit="trial", disable=not progress) as bar,
    ):
        conn.send(Command.SENSORS_ON)
        conn.safe_state("start of job")
        for spec in todo:
            r = run_trial(conn, journal, spec, st.attempts.get(spec.key, 0))
            results.append(r)
            bar.update(1)
            if r.status == "burst":
                log.error(
                    "membrane burst in %s; job ends (the trial is kept in the journal, dropped from the measurements)",
                    spec.key,
                )
                return JobResult(journal.dir, "burst", results, skipped)
        conn.send(Command.BOTH_STOP)
    log.info("job complete: %d trials run now, %d before", len(results), skipped)
    return JobResult(journal.dir, "complete", results, skipped)


# -- output ------------------------------------------------------------------------------
def read_samples(job_dir: str | Path) -> pd.DataFrame:
    """The raw journal (every sample of every attempt)."""
    return pd.read_csv(Path(job_dir) / "samples.csv", dtype={"trial_key": str, "phase": str})


def journal_frame(job_dir: str | Path) -> pd.DataFrame:
    """Samples of completed, unburst trials with exactly the Measurements columns."""
    job_dir = Path(job_dir)
    meta = json.loads((job_dir / "job.json").read_text())
    plan = Plan.from_dict(meta["plan"])
    events = []
    with open(job_dir / "trials.jsonl", encoding="utf-8") as f:
        for line in f:
            try:
                events.append(json.loads(line))
            except json.JSONDecodeError:
                continue
    good = {(e["trial_key"], e["attempt"]) for e in events if e.get("event") == "end" and e.get("status") == "complete"}
    df = read_samples(job_dir)
    keep = [(k, a) in good for k, a in zip(df["trial_key"], df["attempt"])]
    df = df[keep]
    missing = df["height_mm"].isna()
    if missing.any():
        log.warning("%d samples without a height (both sensors out) left out of the measurements", int(missing.sum()))
        df = df[~missing]
    out = pd.DataFrame(
        {
            "design_key": plan.design_key,
            "trial": df["trial"].astype(int),
            "experiment": df["experiment"].astype(str),
            "phase": df["phase"].astype(str),
            "time_s": df["time_s"].astype(float),
            "height_set_mm": df["height_set_mm"].astype(float),
            "height_mm": df["height_mm"].astype(float),
            "pressure_pa": df["pressure_pa"].astype(float),
            "force_n": df["force_n"].astype(float) if plan.experiment == "force" else float(plan.mass_kg * G_M_S2),
            "weight": 1.0,
            "source": plan.source,
        },
        columns=MEASUREMENT_COLUMNS,
    )
    return out.reset_index(drop=True)


def to_measurements(job_dir: str | Path):
    """The job's Measurements (``mfdesign.data.measurements.Measurements``)."""
    from mfdesign.data.measurements import Measurements

    return Measurements(journal_frame(job_dir))


def iter_trial_events(job_dir: str | Path) -> Iterator[dict]:
    with open(Path(job_dir) / "trials.jsonl", encoding="utf-8") as f:
        for line in f:
            yield json.loads(line)
