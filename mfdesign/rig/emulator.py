"""A virtual rig controller on a pseudo-terminal, speaking the real controller's protocol.

:class:`RigEmulator` opens a pty (``os.openpty``), prints nothing, and serves from a thread:
it reads one-character commands, integrates a simple pneumatic chamber (pump fills at a
rate, the release valve vents), moves the plate with the linear actuators at a speed,
asks a pluggable :class:`Plant` for the force on the plate and whether the membrane
touches the rig (the limit switch), and streams telemetry lines at the rig's rate in real
or accelerated time (``time_scale``). Time-of-flight readings are made from the height
through the inverse of the rig config's affine maps, so a host with the same config reads
the heights back.

With ``payload_kg > 0`` the emulator is the mass-lift rig: the plate rides on the membrane
carrying the mass and settles where the plant's force equals its weight.

:class:`Fault` injects failures: garbled or partial lines, sensor dropout, a stalled
controller, a disconnect (pty closed), a burst, a pressure surge. Every command received
and every line sent is recorded (``received``, ``sent``, ``events``) for tests.

The emulated controller has the watchdog that docs/rig.md asks of the firmware: armed by
the first command, restarted by every command (the host's heartbeat ``p`` included), it
puts the rig safe by itself (pump off, valve open, actuators stopped) when no command
arrives for ``watchdog_s``, and reports it with ``#watchdog,tripped,<silent_s>``. Each
heartbeat is answered with ``#watchdog,armed,<watchdog_s>``. ``watchdog_s=0`` emulates
firmware without the feature (heartbeats ignored, never answered). The watchdog runs on the
wall clock, not rig time, because it watches the host, whose clock is the wall clock at any
``time_scale`` (as the host's ``telemetry_timeout_s`` does): at ``time_scale`` s the pump
runs ``s * watchdog_s`` rig seconds before it trips.

The control loop never waits on the physics: :meth:`RigEmulator.start` asks the plant once
before the port opens (a plant that compiles does it then), and a starved loop slows its
clock rather than leaping, so a loaded machine stretches the rig's time, never stalls it
(``tests/rig/test_rig_under_load.py`` runs the rig's scenarios beside a CPU hog).
"""

from __future__ import annotations

import logging
import math
import os
import select
import threading
import time
import tty
from dataclasses import dataclass, field
from typing import Literal, Protocol, runtime_checkable

import numpy as np

from mfdesign.rig.config import RigConfig
from mfdesign.rig.protocol import DEFAULT_WATCHDOG_S
from mfdesign.units import G_M_S2, LBF_TO_N, PSI_TO_PA

log = logging.getLogger("mfdesign.rig.emulator")

# the chamber model's defaults (RigEmulator arguments)
PUMP_RATE_PA_S = 1500.0
PUMP_MAX_PA = 30000.0
LEAK_TAU_S = 600.0
WORKING_PRESSURE_PA = 10000.0  # the most a procedure pumps to (procedures.RINGLESS_LIMIT_PA, lift)


def pump_time_s(
    from_pa: float,
    to_pa: float,
    *,
    pump_rate_pa_s: float = PUMP_RATE_PA_S,
    pump_max_pa: float = PUMP_MAX_PA,
    leak_tau_s: float = LEAK_TAU_S,
) -> float:
    """Rig seconds the pump needs, valve closed, to take the chamber from ``from_pa`` to
    ``to_pa`` (``inf`` if it never gets there): the closed form of the model that
    :meth:`RigEmulator._advance` integrates, ``dp/dt = rate (1 - p / max) - p / leak_tau``.

    With the defaults, 10 kPa -> 12 kPa takes 2.15 s: the budget of the controller watchdog."""
    decay_per_s = pump_rate_pa_s / pump_max_pa + 1.0 / leak_tau_s
    p_end = pump_rate_pa_s / decay_per_s  # where pumping and leaking balance
    if to_pa <= from_pa:
        return 0.0
    if to_pa >= p_end:
        return math.inf
    return math.log((p_end - from_pa) / (p_end - to_pa)) / decay_per_s


@runtime_checkable
class Plant(Protocol):
    """Physics behind the emulator: force on a plate held at a height, rig contact, burst."""

    burst_pressure_pa: float | None

    def force_n(self, height_mm: float, pressure_pa: float) -> float:
        """Force on the plate (N); 0 when the membrane does not touch it."""
        ...

    def touches_rig(self, height_mm: float, pressure_pa: float) -> bool:
        """Whether the membrane touches the rig frame (the limit switch trips)."""
        ...


@dataclass
class AnalyticPlant:
    """A smooth, plausible stand-in for the simulator (for tests and demos, not for science).

    The membrane's free reach grows like ``p^(1/3)`` (thinner and ringless reach further);
    once it passes the plate, the force is the pressure on an effective contact radius
    that grows from the disk radius towards the clamp with the overlap: about 100 N at
    10 kPa on a low plate, falling with height. The membrane touches the rig when the
    overlap exceeds ``rig_overlap_mm``.
    """

    thickness_mm: float = 2.0
    contact_radius_mm: float = 25.4
    n_rings: int = 0
    burst_pressure_pa: float | None = None
    outer_radius_mm: float = 70.0
    reach_ref_mm: float = 80.0  # reach of a ringless 2 mm membrane at 10 kPa
    rig_overlap_mm: float = 45.0

    @classmethod
    def from_design(cls, design, burst_pressure_pa: float | None = None) -> "AnalyticPlant":
        return cls(
            design.thickness_mm, design.contact_radius_mm, design.n_rings, burst_pressure_pa, design.outer_radius_mm
        )

    def reach_mm(self, pressure_pa: float) -> float:
        if pressure_pa <= 0:
            return 0.0
        return (
            self.reach_ref_mm
            * (pressure_pa / 1e4) ** (1 / 3)
            * (2.0 / self.thickness_mm) ** (1 / 3)
            * 0.6**self.n_rings
        )

    def force_n(self, height_mm: float, pressure_pa: float) -> float:
        overlap = self.reach_mm(pressure_pa) - height_mm
        if overlap <= 0:
            return 0.0
        c, r_out = self.contact_radius_mm, self.outer_radius_mm
        r_eff = c + (r_out - c) * (1 - math.exp(-overlap / 40.0))
        return pressure_pa * math.pi * r_eff**2 * 1e-6 * (1 - math.exp(-overlap / 5.0))

    def touches_rig(self, height_mm: float, pressure_pa: float) -> bool:
        return self.reach_mm(pressure_pa) - height_mm > self.rig_overlap_mm


FaultKind = Literal["garble", "partial", "dropout", "stall", "disconnect", "burst", "surge"]


@dataclass
class Fault:
    """One injected fault. It arms at rig time ``at_s`` and/or when the chamber pressure
    first exceeds ``after_pressure_pa`` (both, when both are given), then acts for
    ``duration_s`` rig seconds (``None``: for good). ``every``: garble/partial every n-th
    line; ``side``: dropout side (left/right/both); ``pressure_pa``: surge target."""

    kind: FaultKind
    at_s: float | None = None
    after_pressure_pa: float | None = None
    duration_s: float | None = None
    every: int = 3
    side: Literal["left", "right", "both"] = "left"
    pressure_pa: float = 20000.0
    started_s: float | None = field(default=None, init=False)
    started_wall: float | None = field(default=None, init=False)
    _seen_pressure: bool = field(default=False, init=False)

    def __post_init__(self) -> None:
        if self.kind not in FaultKind.__args__:  # type: ignore[attr-defined]
            raise ValueError(f"unknown fault kind {self.kind!r}; known: {FaultKind.__args__}")  # type: ignore[attr-defined]
        if self.every < 1:
            raise ValueError("Fault.every must be >= 1")

    def active(self, t: float) -> bool:
        if self.started_s is None:
            return False
        return self.duration_s is None or t < self.started_s + self.duration_s


class RigEmulator:
    """Virtual controller on a pty; ``start()``, then connect a host to ``port``."""

    _KNOWN = frozenset("wsqauiojklyhnm90p")  # command characters; others are ignored, feed nothing

    def __init__(
        self,
        plant: Plant | None = None,
        config: RigConfig | None = None,
        *,
        time_scale: float = 1.0,
        rate_hz: float = 20.0,
        faults: list[Fault] | None = None,
        payload_kg: float = 0.0,
        start_height_mm: float = 40.0,
        actuator_speed_mm_s: float = 5.0,
        travel_mm: float = 80.0,
        pump_rate_pa_s: float = PUMP_RATE_PA_S,
        pump_max_pa: float = PUMP_MAX_PA,
        valve_tau_s: float = 0.5,
        leak_tau_s: float = LEAK_TAU_S,
        noise: bool = True,
        seed: int = 0,
        watchdog_s: float = DEFAULT_WATCHDOG_S,
    ):
        if not (time_scale > 0 and rate_hz > 0 and payload_kg >= 0):
            raise ValueError("time_scale and rate_hz must be positive, payload_kg >= 0")
        if not (math.isfinite(watchdog_s) and watchdog_s >= 0):
            raise ValueError(f"watchdog_s must be a finite number of seconds >= 0 (0: off), got {watchdog_s}")
        self.plant = plant or AnalyticPlant()
        if not isinstance(self.plant, Plant):
            raise TypeError("plant must implement force_n, touches_rig and burst_pressure_pa")
        self.config = config or RigConfig()
        self.time_scale, self.rate_hz = float(time_scale), float(rate_hz)
        self.faults = list(faults or [])
        self.payload_kg = float(payload_kg)
        self.speed, self.travel = actuator_speed_mm_s, travel_mm
        self.pump_rate, self.pump_max = pump_rate_pa_s, pump_max_pa
        self.valve_tau, self.leak_tau = valve_tau_s, leak_tau_s
        self.noise = noise
        self.watchdog_s = float(watchdog_s)
        self.rng = np.random.default_rng(seed)
        # state
        self.t = 0.0
        self.pressure = 0.0
        self.pump = False
        self.valve_open = True
        self.pos = {"left": start_height_mm, "right": start_height_mm}
        self.motion = {"left": 0, "right": 0}  # +1 plate up, -1 down
        self.sensors_on = True
        self.burst = False
        self.lift_height = 0.0
        # records for tests: (wall monotonic, rig t, ...)
        self.received: list[tuple[float, float, str]] = []
        self.sent: list[tuple[float, float, str, str]] = []  # (wall, rig t, kind, line)
        self.events: list[tuple[float, float, str]] = []
        self.status_sent: list[tuple[float, float, str, bool]] = []  # (wall, rig t, line, written)
        self.watchdog_trips: list[tuple[float, float, float, float]] = []  # (wall, rig t, silent s, Pa)
        self.lines_dropped = 0
        self._fed_wall: float | None = None  # last command (wall); None: watchdog not armed
        self._status_out: list[str] = []  # status lines waiting for a line boundary
        self._master = self._slave = -1
        self.port = ""
        self._stop = threading.Event()
        self._thread: threading.Thread | None = None
        self.closed = False
        self._line_no = 0
        self._after_partial = False

    # -- lifetime --------------------------------------------------------------------------
    def start(self) -> str:
        """Open the pty and serve from a daemon thread; returns the device path.

        The plant is asked once before the port opens: a plant whose first answer is slow
        (a simulator compiling) costs that time here, never in the control loop, where it
        would stall the pump, the telemetry and the watchdog while a host is connected."""
        h0 = self.heights()[0]
        self.plant.force_n(h0, 0.0)
        self.plant.touches_rig(h0, 0.0)
        self._master, self._slave = os.openpty()
        tty.setraw(self._slave)  # no echo, no line editing, before any client opens it
        os.set_blocking(self._master, False)
        self.port = os.ttyname(self._slave)
        self._thread = threading.Thread(target=self._serve, name="rig-emulator", daemon=True)
        self._thread.start()
        log.info("emulated rig on %s (time scale %g, %g Hz)", self.port, self.time_scale, self.rate_hz)
        return self.port

    def stop(self) -> None:
        self._stop.set()
        if self._thread is not None and self._thread is not threading.current_thread():
            self._thread.join(timeout=2.0)
        self._close_pty()

    def __enter__(self) -> "RigEmulator":
        self.start()
        return self

    def __exit__(self, *exc) -> None:
        self.stop()

    def _close_pty(self) -> None:
        for fd in (self._master, self._slave):
            if fd >= 0:
                try:
                    os.close(fd)
                except OSError:
                    pass
        self._master = self._slave = -1
        self.closed = True

    def _event(self, what: str) -> None:
        self.events.append((time.monotonic(), self.t, what))
        log.info("emulator t=%.2f: %s", self.t, what)

    # -- queries for tests -----------------------------------------------------------------
    def commands_after(self, wall: float) -> str:
        return "".join(c for w, _, c in self.received if w >= wall)

    def fault_started(self, kind: str) -> Fault | None:
        return next((f for f in self.faults if f.kind == kind and f.started_s is not None), None)

    def time_to_pressure_s(self, from_pa: float, to_pa: float) -> float:
        """Rig seconds this emulator's pump needs from ``from_pa`` to ``to_pa`` (valve closed)."""
        return pump_time_s(
            from_pa, to_pa, pump_rate_pa_s=self.pump_rate, pump_max_pa=self.pump_max, leak_tau_s=self.leak_tau
        )

    # -- serving ---------------------------------------------------------------------------
    def _serve(self) -> None:
        period = 1.0 / self.rate_hz
        next_emit = 0.0
        last_wall = time.monotonic()
        inbox = b""
        try:
            while not self._stop.is_set() and not self.closed:
                wait = max(0.0, min((next_emit - self.t) / self.time_scale, 0.005))
                r, _, _ = select.select([self._master], [], [], wait)
                now = time.monotonic()
                # a starved emulator slows its clock rather than leaping (no jumps between lines)
                self._advance(min((now - last_wall) * self.time_scale, 2 * period))
                last_wall = now
                if r:
                    try:
                        data = os.read(self._master, 4096)
                    except (BlockingIOError, InterruptedError):
                        data = b""
                    except OSError:
                        data = b""  # no client on the slave side
                    inbox += data
                    *cmds, inbox = inbox.split(b"\n")
                    for c in cmds:
                        self._command(c.strip(b"\r "), now)
                self._check_watchdog(now)  # after reading: commands that waited in the pty count
                if self.closed:
                    break
                if self.t >= next_emit:
                    next_emit = max(next_emit + period, self.t)
                    self._emit(now)
        except Exception:  # a bug in the emulator must not hang the host: close the pty
            log.exception("emulator crashed; closing the pty")
            self._close_pty()

    def _command(self, c: bytes, wall: float) -> None:
        ch = c.decode("ascii", "replace")
        self.received.append((wall, self.t, ch))
        if ch == "p" and not self.watchdog_s:
            return  # firmware without the feature: the heartbeat is an unknown command, ignored
        if ch in self._KNOWN and self.watchdog_s:
            self._fed_wall = wall  # arms the watchdog, or restarts it
        if ch == "p":
            self._status(f"#watchdog,armed,{self.watchdog_s:.3f}")
            return
        push = -1 if self.config.push_lowers_plate else 1  # height direction of "push"
        moves = {
            "u": ("left", push),
            "i": ("left", -push),
            "o": ("left", 0),
            "j": ("right", push),
            "k": ("right", -push),
            "l": ("right", 0),
        }
        if ch == "w":
            self.pump = True
        elif ch == "s":
            self.pump = False
        elif ch == "q":
            self.valve_open = True
        elif ch == "a":
            self.valve_open = False
        elif ch in moves:
            side, d = moves[ch]
            self.motion[side] = d
        elif ch in ("y", "n", "h"):
            d = {"y": push, "n": -push, "h": 0}[ch]
            self.motion = {"left": d, "right": d}
        elif ch == "m":
            self.t, self.pump, self.valve_open = 0.0, False, True
            self.motion = {"left": 0, "right": 0}
            self._event("controller reset")
        elif ch == "9":
            self.sensors_on = True
        elif ch == "0":
            self.sensors_on = False
        else:
            self._event(f"unknown command {ch!r} ignored")

    def _check_watchdog(self, wall: float) -> None:
        if self._fed_wall is None or wall - self._fed_wall <= self.watchdog_s:
            return
        silent_s = wall - self._fed_wall
        self._fed_wall = None  # disarmed (nothing left to time) until the next command
        # the pressure as the pump stops: the most a silent host's last command can have reached
        self.watchdog_trips.append((wall, self.t, silent_s, self.pressure))
        self.pump, self.valve_open = False, True  # what the host's s, q, h would do
        self.motion = {"left": 0, "right": 0}
        self._event(
            f"watchdog: no command for {silent_s:.3f} s at {self.pressure:.0f} Pa: "
            f"pump off, valve open, actuators stopped"
        )
        self._status(f"#watchdog,tripped,{silent_s:.3f}")

    def _status(self, line: str) -> None:
        self._status_out.append(line)

    def _flush_status(self, wall: float) -> None:
        """Write the waiting status lines. Only at a line boundary (never right after a
        partial line): a status line must not merge with telemetry."""
        while self._status_out:
            line = self._status_out.pop(0)
            try:
                os.write(self._master, line.encode("ascii") + b"\n")
                ok = True
            except (BlockingIOError, OSError):
                ok = False  # nobody reading: dropped, like telemetry
            self.status_sent.append((wall, self.t, line, ok))

    def _arm_faults(self, wall: float) -> None:
        for f in self.faults:
            if f.started_s is not None:
                continue
            if f.after_pressure_pa is not None and self.pressure > f.after_pressure_pa:
                f._seen_pressure = True
            if (f.after_pressure_pa is None or f._seen_pressure) and (f.at_s is None or self.t >= f.at_s):
                f.started_s, f.started_wall = self.t, wall
                self._event(f"fault {f.kind} started")
                if f.kind == "burst":
                    self._burst()
                elif f.kind == "surge":
                    self.pressure = f.pressure_pa

    def _burst(self) -> None:
        if not self.burst:
            self.burst = True
            self._event(f"membrane burst at {self.pressure:.0f} Pa")

    def _advance(self, dt: float) -> None:
        while dt > 1e-12:
            h = min(dt, 0.01)
            dt -= h
            self.t += h
            p = self.pressure
            if self.burst:
                dp = -p / 0.05
            else:
                dp = self.pump_rate * max(0.0, 1 - p / self.pump_max) if self.pump else 0.0
                dp -= p / self.valve_tau if self.valve_open else 0.0
                dp -= p / self.leak_tau
            self.pressure = max(0.0, p + dp * h)
            burst_at = self.plant.burst_pressure_pa
            if burst_at is not None and self.pressure >= burst_at:
                self._burst()
            for side in ("left", "right"):
                self.pos[side] = min(max(self.pos[side] + self.motion[side] * self.speed * h, 0.0), self.travel)
            if self.payload_kg > 0:
                excess = self.plant.force_n(self.lift_height, self.pressure) - self.payload_kg * G_M_S2
                v = max(-50.0, min(50.0, 10.0 * excess))  # plate settles within ~0.1 s
                self.lift_height = min(max(self.lift_height + v * h, 0.0), self.travel)
        self._arm_faults(time.monotonic())

    def heights(self) -> tuple[float, float]:
        if self.payload_kg > 0:
            return self.lift_height, self.lift_height
        return self.pos["left"], self.pos["right"]

    def telemetry_line(self) -> str:
        """The current state as a telemetry line (with sensor noise)."""
        hl, hr = self.heights()
        h = 0.5 * (hl + hr)
        force = 0.0 if self.burst else self.plant.force_n(h, self.pressure)
        contact = (not self.burst) and self.plant.touches_rig(h, self.pressure)
        n = self.rng.normal(size=4) if self.noise else np.zeros(4)
        ltof = self.config.tof_left.tof(hl) + 0.2 * n[0]
        rtof = self.config.tof_right.tof(hr) + 0.2 * n[1]
        drop = {"left": not self.sensors_on, "right": not self.sensors_on}
        for f in self.faults:
            if f.kind == "dropout" and f.active(self.t):
                for side in ("left", "right"):
                    drop[side] |= f.side in (side, "both")
        ltof = 8190.0 if drop["left"] else max(0.0, ltof)
        rtof = 8190.0 if drop["right"] else max(0.0, rtof)
        flow = (0.8 if self.pump else 0.0) + (0.01 * n[3] if self.noise else 0.0)
        return (
            f"{self.t:.3f},{(force + 0.05 * n[2]) / LBF_TO_N:.4f},"
            f"{(self.pressure + 5.0 * n[3]) / PSI_TO_PA:.5f},{ltof:.1f},{rtof:.1f},"
            f"{flow:.3f},{0 if contact else 1}"
        )

    def _emit(self, wall: float) -> None:
        for f in self.faults:
            if f.kind == "disconnect" and f.active(self.t):
                self._event("disconnect: pty closed")
                self._close_pty()
                return
            if f.kind == "stall" and f.active(self.t):
                return
        if not self._after_partial:
            self._flush_status(wall)
        line = self.telemetry_line()
        kind = "merged" if self._after_partial else "ok"  # merged: runs on from a partial line
        self._after_partial = False
        self._line_no += 1
        for f in self.faults:
            if f.kind in ("garble", "partial") and f.active(self.t) and self._line_no % f.every == 0:
                kind = f.kind
        if kind == "garble":
            b = bytearray(line.encode())
            for i in self.rng.integers(0, len(b), size=3):
                b[int(i)] = int(self.rng.choice(list(b"#x;\xff")))  # never valid: always caught
            data = bytes(b) + b"\n"
        elif kind == "partial":
            data = line.encode()[: len(line) // 2]  # cut short; the next line runs on
            self._after_partial = True
        else:
            if kind == "ok" and (
                not self.sensors_on or any(f.kind == "dropout" and f.active(self.t) for f in self.faults)
            ):
                kind = "dropout"
            data = line.encode() + b"\n"
        self.sent.append((wall, self.t, kind, line))
        try:
            os.write(self._master, data)
        except (BlockingIOError, OSError):
            self.lines_dropped += 1  # nobody reading: a real UART drops bytes too
            self.sent[-1] = (wall, self.t, "unsent", line)
        if not self._after_partial:
            self._flush_status(wall)

    def serve_forever(self) -> None:
        """Serve until Ctrl-C (used by ``mfdesign rig emulate``)."""
        if self._thread is None:
            self.start()
        try:
            while self._thread is not None and self._thread.is_alive():
                self._thread.join(timeout=0.2)
        finally:
            self.stop()
