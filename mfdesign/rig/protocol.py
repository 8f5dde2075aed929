"""The rig controller's serial protocol over pyserial: commands, strict telemetry, safety.

The controller (an ESP32 at 115200 baud) takes one character plus a newline per command
(:class:`Command`) and streams telemetry lines ``time,force_lbf,pressure_psi,left_tof,
right_tof,flow,limit_switch``. This module converts lbf and psi to N and Pa and time-of-flight
to height (through :class:`~mfdesign.rig.config.RigConfig`), so everything past it speaks mm,
Pa and N.

:class:`RigConnection` owns the one serial connection of a session. A reader thread parses
every line (bad lines are counted and logged, never raised), watches for telemetry silence,
pressure over the hard limit and a lost port, and on any of them puts the rig safe
(:data:`SAFE_SEQUENCE`: pump off, valve open, actuators stopped) at once, without waiting
for the caller. Used as a context manager, any exception in the caller (Ctrl-C included)
also ends in the safe state and a closed port.

Host heartbeat (issue 22): a host killed outright (SIGKILL, PC power loss) sends nothing,
and a controller that keeps its last state keeps pumping. So the connection sends
:attr:`Command.HEARTBEAT` every ``heartbeat_interval_s`` from its own thread, and a
controller with a watchdog goes safe by itself when no command arrives for its timeout
(:data:`DEFAULT_WATCHDOG_S`). The controller answers each heartbeat with a status line
``#watchdog,armed,<timeout_s>`` and reports a trip with ``#watchdog,tripped,<silent_s>``;
these lines are not telemetry. A controller that never answers has no watchdog: the
connection logs a warning (``controller_watchdog_s`` stays ``None``).
"""

from __future__ import annotations

import enum
import logging
import math
import queue
import threading
import time
from dataclasses import dataclass

import serial

from mfdesign.rig.config import TOF_DROPOUT, RigConfig
from mfdesign.units import LBF_TO_N, PSI_TO_PA

N_FIELDS = 7
MAX_LINE_BYTES = 256
_LOG_FIRST_BAD = 20  # log this many bad lines verbatim, then every 100th

log = logging.getLogger("mfdesign.rig")


class Command(str, enum.Enum):
    """Controller commands (one character each; sent with a trailing newline)."""

    PUMP_ON = "w"
    PUMP_OFF = "s"
    VALVE_OPEN = "q"
    VALVE_CLOSE = "a"
    LEFT_PUSH = "u"
    LEFT_PULL = "i"
    LEFT_STOP = "o"
    RIGHT_PUSH = "j"
    RIGHT_PULL = "k"
    RIGHT_STOP = "l"
    BOTH_PUSH = "y"
    BOTH_STOP = "h"
    BOTH_PULL = "n"
    RESET = "m"
    SENSORS_ON = "9"
    SENSORS_OFF = "0"
    HEARTBEAT = "p"  # "the host is alive": feeds the controller's watchdog, changes nothing else


# The controller's watchdog timeout (wall-clock s) asked of the firmware (docs/rig.md) and the
# emulator's default. From the highest working pressure (10 kPa: ringless cap, lift default)
# the emulated pump needs 2.15 s, valve closed, to reach the 12 kPa hard limit
# (emulator.pump_time_s; tests/rig/test_rig_watchdog.py keeps this number honest): after 1 s of
# silence it has added about 0.95 kPa, leaving > 1 kPa and > 1.1 s of margin. Shorter would
# trip on a host descheduled for a few hundred ms (seen: 0.45 s on a loaded 2-core machine).
DEFAULT_WATCHDOG_S = 1.0
WATCHDOG_STATUS_PREFIX = b"#watchdog,"


SAFE_SEQUENCE = (Command.PUMP_OFF, Command.VALVE_OPEN, Command.BOTH_STOP)
# commands that cannot add energy: allowed after a fault, and do not leave the safe state
_SAFE_CHARS = {c.value for c in SAFE_SEQUENCE} | {
    Command.LEFT_STOP.value,
    Command.RIGHT_STOP.value,
    Command.SENSORS_ON.value,
    Command.SENSORS_OFF.value,
    Command.HEARTBEAT.value,
}


class TelemetryError(ValueError):
    """A telemetry line that does not follow the format; the message says why."""


class RigFault(RuntimeError):
    """A fault that ended the session in the safe state; ``kind`` names it."""

    kind = "fault"


class TelemetrySilence(RigFault):
    kind = "telemetry_silence"


class OverPressure(RigFault):
    kind = "over_pressure"


class RigDisconnected(RigFault):
    kind = "disconnected"


class WatchdogTripped(RigFault):
    """The controller went safe by itself (no command for its watchdog time) while this
    host believed the rig energised: the host stalled, or its heartbeats were lost."""

    kind = "watchdog"


@dataclass(frozen=True)
class Sample:
    """One telemetry line in physical units (mm, Pa, N, s)."""

    rig_time_s: float
    force_n: float
    pressure_pa: float
    left_tof: float
    right_tof: float
    flow: float
    contact: bool  # limit switch reads 0: the membrane touched the rig
    left_mm: float  # NaN: sensor dropout
    right_mm: float
    host_time: float  # time.monotonic() at receipt

    @property
    def height_mm(self) -> float:
        """Mean of the valid sensors' heights; NaN when both dropped out."""
        vals = [v for v in (self.left_mm, self.right_mm) if not math.isnan(v)]
        return sum(vals) / len(vals) if vals else math.nan


def _field(name: str, text: str, lo: float, hi: float) -> float:
    try:
        v = float(text)
    except ValueError:
        raise TelemetryError(f"{name} {text!r} is not a number") from None
    if not math.isfinite(v) or not (lo <= v <= hi):
        raise TelemetryError(f"{name} {text!r} outside [{lo:g}, {hi:g}]")
    return v


def parse_telemetry(line: bytes | str, config: RigConfig, host_time: float | None = None) -> Sample:
    """Parse one line strictly (no newline), converting units; raise :class:`TelemetryError`."""
    if isinstance(line, bytes):
        try:
            line = line.decode("ascii")
        except UnicodeDecodeError:
            raise TelemetryError("line is not ASCII") from None
    line = line.rstrip("\r")
    parts = line.split(",")
    if len(parts) != N_FIELDS:
        raise TelemetryError(f"expected {N_FIELDS} comma-separated fields, got {len(parts)}")
    if any(p.strip() != p or p == "" for p in parts):
        raise TelemetryError("empty field or stray whitespace")
    t = _field("time", parts[0], 0.0, 1e9) * config.time_unit_s
    force = _field("force_lbf", parts[1], -1000.0, 1000.0) * LBF_TO_N
    pressure = _field("pressure_psi", parts[2], -20.0, 200.0) * PSI_TO_PA
    ltof = _field("left_tof", parts[3], 0.0, 1e6)
    rtof = _field("right_tof", parts[4], 0.0, 1e6)
    flow = _field("flow", parts[5], -1e6, 1e6)
    if parts[6] not in ("0", "1"):
        raise TelemetryError(f"limit_switch {parts[6]!r} is not 0 or 1")
    lmm, rmm = config.height_mm(ltof, rtof)
    return Sample(
        rig_time_s=t,
        force_n=force,
        pressure_pa=pressure,
        left_tof=ltof,
        right_tof=rtof,
        flow=flow,
        contact=parts[6] == "0",
        left_mm=lmm,
        right_mm=rmm,
        host_time=time.monotonic() if host_time is None else host_time,
    )


@dataclass(frozen=True)
class WatchdogStatus:
    """A controller status line ``#watchdog,<state>,<seconds>`` (not telemetry).

    ``armed``: the answer to a heartbeat; ``seconds`` is the controller's timeout.
    ``tripped``: the controller went safe; ``seconds`` is how long it heard no command."""

    state: str
    seconds: float


def parse_watchdog_status(line: bytes) -> WatchdogStatus:
    """Parse a line starting with ``#watchdog,`` strictly; raise :class:`TelemetryError`."""
    parts = line.rstrip(b"\r").split(b",")
    if len(parts) != 3 or parts[1] not in (b"armed", b"tripped"):
        raise TelemetryError("watchdog status is not '#watchdog,armed|tripped,<seconds>'")
    seconds = _field("watchdog seconds", parts[2].decode("ascii", "replace"), 0.0, 1e6)
    return WatchdogStatus(parts[1].decode("ascii"), seconds)


class RigConnection:
    """The session's one serial connection to the rig controller (see module doc).

    ``port`` is a device path or any pyserial URL (``serial_for_url``).
    """

    def __init__(self, port: str, config: RigConfig | None = None, *, logger: logging.Logger | None = None):
        self.config = config or RigConfig()
        self.log = logger or log
        self.port = port
        try:
            self.ser = serial.serial_for_url(
                port, baudrate=self.config.port_baudrate, timeout=0.02, write_timeout=1.0
            )  # pyserial reports a write timeout when the thread was merely descheduled past
            # it, even though the bytes went out: long enough not to mistake load for a fault
        except (serial.SerialException, ValueError) as exc:
            raise RigDisconnected(f"cannot open rig port {port!r}: {exc}") from None
        self.ser.reset_input_buffer()
        self.bad_lines = 0
        self.good_lines = 0
        self.fault: RigFault | None = None
        self.sent: list[tuple[float, str, bool]] = []  # (monotonic time, char, written ok)
        self._queue: queue.Queue = queue.Queue()
        self._write_lock = threading.Lock()
        self._stop = threading.Event()
        self._safe = False
        self._closed = False
        self._last_time = -math.inf
        self._last_good = time.monotonic()
        self._dropout = {"left": False, "right": False}
        self._over_warned = 0.0
        self._handled: BaseException | None = None
        self._heard = False  # a good telemetry line arrived: the reader (safety monitor) works
        self.heartbeats_sent = 0
        self.controller_watchdog_s: float | None = None  # from its answer; None: none (yet)
        self._reader = threading.Thread(target=self._read_loop, name="rig-reader", daemon=True)
        self._heart = threading.Thread(target=self._heartbeat_loop, name="rig-heartbeat", daemon=True)
        self.log.info("connected to rig on %s at %d baud", port, self.config.port_baudrate)
        self.safe_state("connect")  # the rig's state is unknown (a killed host may have left it pumping)
        self._reader.start()
        self._heart.start()

    # -- commands ------------------------------------------------------------------------
    def send(self, cmd: Command) -> None:
        """Send one command; after a fault only safe commands go out (others raise it)."""
        cmd = Command(cmd)
        if self.fault is not None and cmd.value not in _SAFE_CHARS:
            raise self.fault
        if not self._write(cmd):
            self.fail(RigDisconnected(f"could not send {cmd.name} ({cmd.value!r}): port lost"))
            raise self.fault  # type: ignore[misc]
        if cmd.value not in _SAFE_CHARS:
            self._safe = False
        if cmd == Command.RESET:
            self._last_time = -math.inf  # the controller's clock restarts

    def _write(self, cmd: Command) -> bool:
        with self._write_lock:
            ok = True
            try:
                self.ser.write(f"{cmd.value}\n".encode("ascii"))
            except (serial.SerialException, OSError, AttributeError, TypeError) as exc:
                ok = False
                self.log.error("write %s (%r) failed: %s", cmd.name, cmd.value, exc)
            self.sent.append((time.monotonic(), cmd.value, ok))
            self.log.debug("sent %s (%r)", cmd.name, cmd.value)
            return ok

    # -- heartbeat -----------------------------------------------------------------------
    def _heartbeat_loop(self) -> None:
        """Send HEARTBEAT every ``heartbeat_interval_s`` while the reader hears the controller.

        A beat says more than "the process lives": it goes out only while the reader thread
        (which enforces the hard limit) is alive and receiving telemetry, so a host whose
        monitor died or went deaf lets the controller's watchdog put the rig safe."""
        interval = self.config.heartbeat_interval_s
        answer_wait_s = max(1.0, 5 * interval)  # several beats: one lost line is no verdict
        first_beat: float | None = None
        warned = False
        while not self._stop.wait(interval):
            now = time.monotonic()
            if not (
                self._reader.is_alive() and self._heard and now - self._last_good <= self.config.telemetry_timeout_s
            ):
                continue
            if not self._beat():
                return
            if first_beat is None:
                first_beat = now
            if not warned and self.controller_watchdog_s is None and now - first_beat > answer_wait_s:
                warned = True
                self.log.warning(
                    "the controller did not answer %d heartbeats in %.1f s: its firmware has no "
                    "watchdog, so a host killed mid-trial leaves the pump running (docs/rig.md, "
                    "'Controller watchdog')",
                    self.heartbeats_sent,
                    now - first_beat,
                )

    def _beat(self) -> bool:
        """Write one heartbeat (not logged or listed in ``sent``: five a second would bury the
        commands); False once the port is lost or closing."""
        with self._write_lock:
            try:
                self.ser.write(f"{Command.HEARTBEAT.value}\n".encode("ascii"))
                self.heartbeats_sent += 1
                return True
            except (serial.SerialException, OSError, AttributeError, TypeError) as exc:
                error = exc
        if not self._stop.is_set():  # outside the lock: fail() writes the safe sequence
            self.fail(RigDisconnected(f"serial port lost: heartbeat not sent ({error})"))
        return False

    def _handle_status(self, raw: bytes) -> None:
        try:
            st = parse_watchdog_status(raw)
        except TelemetryError as exc:
            self._bad(raw, str(exc))
            return
        if st.state == "armed":
            if self.controller_watchdog_s != st.seconds:
                self.controller_watchdog_s = st.seconds
                self.log.info(
                    "controller watchdog: safe after %.3f s without a command (heartbeat every %.3f s)",
                    st.seconds,
                    self.config.heartbeat_interval_s,
                )
                if st.seconds < 2 * self.config.heartbeat_interval_s:
                    self.log.warning(
                        "the controller's %.3f s watchdog is under two heartbeat intervals "
                        "(%.3f s): one late beat will put the rig safe",
                        st.seconds,
                        self.config.heartbeat_interval_s,
                    )
            return
        if self._safe or self.fault is not None:
            # nothing of ours was undone (e.g. the trip of a previous session reaching a fresh one)
            self.log.warning(
                "controller watchdog went safe after %.3f s without a command (the rig was already safe)", st.seconds
            )
            return
        # Faulting here also keeps the vent that follows from being read as a burst: this line
        # precedes, in the stream, every sample that shows the pressure falling.
        self.fail(
            WatchdogTripped(
                f"the controller went safe by itself after {st.seconds:.3f} s without a command "
                f"(host stalled, or heartbeats lost?)"
            )
        )

    def safe_state(self, reason: str) -> bool:
        """Pump off, valve open, actuators stopped; log each action. True if all were sent."""
        t0 = time.monotonic()
        results = [(c, self._write(c)) for c in SAFE_SEQUENCE]
        dt_ms = (time.monotonic() - t0) * 1e3
        summary = ", ".join(f"{c.name} {c.value!r} {'sent' if ok else 'FAILED'}" for c, ok in results)
        all_ok = all(ok for _, ok in results)
        level = logging.WARNING if all_ok else logging.ERROR
        self.log.log(level, "SAFE STATE (%s): %s in %.1f ms", reason, summary, dt_ms)
        if dt_ms > self.config.safe_state_deadline_s * 1e3:
            self.log.error(
                "safe state took %.1f ms, over the %.0f ms budget", dt_ms, self.config.safe_state_deadline_s * 1e3
            )
        self._safe = True
        return all_ok

    def fail(self, fault: RigFault) -> RigFault:
        """Record a fault (the first one wins), log it, go safe at once; returns the fault."""
        if self.fault is not None:
            self.log.error("further fault after %s: %s", self.fault.kind, fault)
            return self.fault
        self.fault = fault
        self.log.error("FAULT %s: %s", fault.kind, fault)
        self.safe_state(f"fault {fault.kind}")
        self._queue.put(fault)
        return fault

    # -- telemetry -------------------------------------------------------------------------
    def next_sample(self, timeout: float | None = None) -> Sample:
        """The next good sample in arrival order; raises the fault once the queue reaches it."""
        if timeout is None:
            timeout = self.config.telemetry_timeout_s + 0.5
        try:
            item = self._queue.get(timeout=timeout)
        except queue.Empty:
            if self.fault is None:
                self.fail(TelemetrySilence(f"no telemetry for {timeout:.2f} s (reader stuck?)"))
            raise self.fault from None  # type: ignore[misc]
        if isinstance(item, RigFault):
            self._queue.put(item)  # keep raising it on later calls
            raise item
        return item

    def drain(self) -> list[Sample]:
        """Samples already received and not yet consumed (without waiting)."""
        out: list[Sample] = []
        while True:
            try:
                item = self._queue.get_nowait()
            except queue.Empty:
                return out
            if isinstance(item, RigFault):
                self._queue.put(item)
                return out
            out.append(item)

    def _read_loop(self) -> None:
        buf = b""
        synced = False  # the first bytes after opening may start mid-line
        while not self._stop.is_set():
            try:
                chunk = self.ser.read(self.ser.in_waiting or 1)
            except (serial.SerialException, OSError, TypeError, AttributeError) as exc:
                if not self._stop.is_set():
                    self.fail(RigDisconnected(f"serial port lost: {exc}"))
                return
            now = time.monotonic()
            if chunk:
                buf += chunk
                *lines, buf = buf.split(b"\n")
                for raw in lines:
                    if not synced:
                        synced = True
                        if raw:
                            self.log.debug("skipped partial first line %r", raw[:80])
                            continue
                    self._handle_line(raw, now)
                if len(buf) > MAX_LINE_BYTES:
                    self._bad(buf[:80], f"no newline within {MAX_LINE_BYTES} bytes")
                    buf = b""
            silent = now - self._last_good
            if silent > self.config.telemetry_timeout_s and self.fault is None:
                self.fail(
                    TelemetrySilence(
                        f"no valid telemetry for {silent:.2f} s (timeout {self.config.telemetry_timeout_s:.2f} s)"
                    )
                )

    def _bad(self, raw: bytes, why: str) -> None:
        self.bad_lines += 1
        if self.bad_lines <= _LOG_FIRST_BAD or self.bad_lines % 100 == 0:
            self.log.warning("bad telemetry line #%d (%s): %r", self.bad_lines, why, raw[:120])

    def _handle_line(self, raw: bytes, now: float) -> None:
        if not raw.strip():
            return
        if raw.startswith(WATCHDOG_STATUS_PREFIX):
            self._handle_status(raw)
            return
        try:
            s = parse_telemetry(raw, self.config, host_time=now)
        except TelemetryError as exc:
            self._bad(raw, str(exc))
            return
        if s.rig_time_s <= self._last_time:
            self._bad(raw, f"time {s.rig_time_s:g} s not after {self._last_time:g} s")
            return
        self._last_time = s.rig_time_s
        self._last_good = now
        self._heard = True
        self.good_lines += 1
        for side, tof in (("left", s.left_tof), ("right", s.right_tof)):
            dropped = tof >= TOF_DROPOUT
            if dropped != self._dropout[side]:
                self._dropout[side] = dropped
                if dropped:
                    self.log.warning(
                        "%s time-of-flight dropout (reading %g >= %g) at rig t=%.2f s",
                        side,
                        tof,
                        TOF_DROPOUT,
                        s.rig_time_s,
                    )
                else:
                    self.log.info("%s time-of-flight back (reading %g) at rig t=%.2f s", side, tof, s.rig_time_s)
        self._queue.put(s)
        if s.pressure_pa <= self.config.hard_pressure_limit_pa or self.fault is not None:
            return
        if self._safe:
            if now - self._over_warned > 1.0:  # already venting: nothing more to command
                self._over_warned = now
                self.log.warning("pressure %.0f Pa over the hard limit while the rig is safe (venting)", s.pressure_pa)
        else:
            self.fail(
                OverPressure(
                    f"pressure {s.pressure_pa:.0f} Pa over the hard limit {self.config.hard_pressure_limit_pa:.0f} Pa"
                )
            )

    # -- lifetime --------------------------------------------------------------------------
    def close(self, reason: str = "session end") -> None:
        """Safe state (unless already safe), stop the reader, close the port. Idempotent."""
        if self._closed:
            return
        if not self._safe:
            self.safe_state(reason)
        self._closed = True
        self._stop.set()  # heartbeats stop: a controller with a watchdog trips harmlessly, already safe
        for t in (self._reader, self._heart):
            if t is not threading.current_thread() and t.is_alive():
                t.join(timeout=1.0)
        try:
            self.ser.close()
        except (serial.SerialException, OSError) as exc:
            self.log.error("closing port: %s", exc)
        self.log.info("port %s closed (%d good lines, %d bad lines)", self.port, self.good_lines, self.bad_lines)

    def __enter__(self) -> "RigConnection":
        return self

    def on_exception(self, exc: BaseException) -> None:
        """Log an exception of the caller and go safe at once (once per exception)."""
        if isinstance(exc, RigFault) or exc is self._handled:
            return
        self._handled = exc
        name = "Ctrl-C" if isinstance(exc, KeyboardInterrupt) else type(exc).__name__
        self.log.error("FAULT exception: %s%s", name, f": {exc}" if str(exc) else "")
        self.safe_state(f"exception {name}")

    def __exit__(self, exc_type, exc, tb) -> None:
        if exc is not None:
            self.on_exception(exc)
        self.close()
