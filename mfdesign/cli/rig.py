"""``mfdesign rig ...``: emulate a rig, characterise a membrane, run mass-lift trials.

``rig_app`` is a typer sub-app, registered as ``rig`` (:func:`register`). Jobs write into
``--out`` (journal, rig log, ``measurements.parquet``); run the same command again to
resume an interrupted job. SIGTERM is treated like Ctrl-C (rig safe, port closed).
"""

from __future__ import annotations

import logging
import math
import signal
import sys
from pathlib import Path
from typing import TYPE_CHECKING, Optional

import typer

if TYPE_CHECKING:  # imported on use: --help stays fast
    from mfdesign.design import Membrane

from mfdesign.cli._contract import item_parser
from mfdesign.rig.config import ConfigError, RigConfig
from mfdesign.rig.protocol import DEFAULT_WATCHDOG_S, RigFault

rig_app = typer.Typer(help="Drive the membrane test rig (or its emulator) over a serial port.", no_args_is_help=True)


def _config(path: Optional[Path]) -> RigConfig:
    try:
        return RigConfig.load(path) if path else RigConfig()
    except ConfigError as exc:
        raise typer.BadParameter(str(exc), param_hint="--config") from None


def _design(key: str) -> Membrane:
    from mfdesign.design import DesignError, Membrane

    try:
        return Membrane.from_key(key)
    except DesignError as exc:
        raise typer.BadParameter(str(exc), param_hint="--design") from None


def _heights(values) -> tuple[float, ...]:
    hs = tuple(float(x) for x in values or ())
    if not hs or any(not math.isfinite(h) for h in hs):
        raise typer.BadParameter(f"need at least one finite height, got {list(hs)}", param_hint="--heights")
    return hs


def _signals_as_interrupt() -> None:
    """SIGTERM and SIGINT stop a rig command as Ctrl-C does (rig put safe, job resumable).
    SIGINT too, explicitly: a shell without job control starts background jobs with SIGINT
    ignored, and ``kill -INT`` (or a test) must still stop the emulator or a job."""

    def handler(signum, frame):
        raise KeyboardInterrupt(f"signal {signum}")

    try:
        signal.signal(signal.SIGTERM, handler)
        signal.signal(signal.SIGINT, signal.default_int_handler)
    except ValueError:  # not the main thread (e.g. under a test runner): leave it
        pass


# pyserial URL schemes that can reach a rig; loop:// is pyserial's loopback, which only
# echoes the host's own commands (no rig is ever behind it).
_PORT_SCHEMES = ("socket", "rfc2217", "spy", "alt", "hwgrep")


def check_port(port: str) -> str:
    """Refuse a ``--port`` that cannot be a rig controller (a bad argument, exit 2), before
    the job folder is touched: a regular file, a folder, loop://. A device path that does
    not exist stays a rig fault (an unplugged USB cable: plug it in and resume)."""
    import os
    import stat

    from mfdesign.errors import InputError

    allowed = f"allowed: a serial device (e.g. /dev/ttyUSB0) or a pyserial URL ({', '.join(s + '://' for s in _PORT_SCHEMES)})"
    if "://" in port:
        scheme = port.split("://", 1)[0].lower()
        if scheme not in _PORT_SCHEMES:
            why = (
                " (pyserial's loopback: it echoes the host's own commands, no rig is behind it)"
                if scheme == "loop"
                else ""
            )
            raise InputError(f"--port {port!r}: the URL scheme {scheme!r} reaches no rig{why}; {allowed}")
        return port
    try:
        mode = os.stat(port).st_mode
    except FileNotFoundError:
        return port
    except OSError as err:
        raise InputError(f"--port {port!r}: cannot inspect it ({err.strerror or err}); {allowed}") from None
    if not stat.S_ISCHR(mode):
        kind = (
            "a folder" if stat.S_ISDIR(mode) else "a regular file" if stat.S_ISREG(mode) else "not a character device"
        )
        raise InputError(f"--port {port!r} is {kind}, not a serial device; {allowed}")
    return port


def _finish(job_dir: Path, run) -> None:
    from mfdesign.outputs import prepare_out_dir
    from mfdesign.rig.procedures import JobError, to_measurements

    prepare_out_dir(job_dir)  # an existing file or a read-only folder: one line, before the rig is touched

    logging.basicConfig(level=logging.WARNING, format="%(levelname)s %(name)s: %(message)s")
    _signals_as_interrupt()
    try:
        result = run()
    except JobError as exc:
        typer.echo(f"error: {exc}", err=True)
        raise typer.Exit(2) from None
    except RigFault as exc:
        typer.echo(
            f"rig fault ({exc.kind}): {exc}. The rig was put safe (pump off, valve open, "
            f"actuators stopped); see {job_dir / 'rig.log'}. Run the same command to resume.",
            err=True,
        )
        raise typer.Exit(3) from None
    except KeyboardInterrupt:
        typer.echo(f"interrupted: rig put safe; run the same command to resume ({job_dir}).", err=True)
        raise typer.Exit(130) from None
    m = to_measurements(job_dir)
    out = job_dir / "measurements.parquet"
    m.to_parquet(out)
    n_done = sum(1 for t in result.trials_run if t.status == "complete")
    typer.echo(f"{result.status}: {n_done} trials now, {result.skipped} before; {len(m)} samples -> {out}")
    if result.status == "burst":
        typer.echo("the membrane burst: that trial is in the journal (trials.jsonl) but not in the measurements")


@rig_app.command()
def emulate(
    design: str = typer.Option("[2.0, 25.4, nan, nan, nan, nan]", help="membrane for the analytic plant"),
    time_scale: float = typer.Option(1.0, min=0.01, max=1000.0, help="rig seconds per wall second"),
    rate_hz: float = typer.Option(20.0, min=1.0, max=1000.0, help="telemetry lines per rig second"),
    mass_kg: float = typer.Option(0.0, min=0.0, max=50.0, help="> 0: mass-lift rig carrying this mass"),
    burst_pa: Optional[float] = typer.Option(None, min=1.0, help="membrane bursts at this pressure"),
    config: Optional[Path] = typer.Option(None, help="rig config (.toml/.json) for the ToF maps"),
    seed: int = typer.Option(0, help="sensor-noise seed"),
    watchdog_s: float = typer.Option(
        DEFAULT_WATCHDOG_S,
        help="wall-clock seconds without a command (heartbeat included) after which the "
        "controller goes safe by itself; 0: off, like firmware without the watchdog",
    ),
) -> None:
    """Serve a virtual rig controller on a pseudo-terminal; prints its device path."""
    from mfdesign.rig.emulator import WORKING_PRESSURE_PA, AnalyticPlant, RigEmulator

    if not (math.isfinite(watchdog_s) and watchdog_s >= 0):
        typer.echo(f"error: --watchdog-s must be a number of seconds >= 0 (0: off), got {watchdog_s:g}", err=True)
        raise typer.Exit(2)
    cfg = _config(config)
    plant = AnalyticPlant.from_design(_design(design), burst_pressure_pa=burst_pa)
    em = RigEmulator(
        plant, cfg, time_scale=time_scale, rate_hz=rate_hz, payload_kg=mass_kg, seed=seed, watchdog_s=watchdog_s
    )
    budget_s = em.time_to_pressure_s(WORKING_PRESSURE_PA, cfg.hard_pressure_limit_pa)
    if watchdog_s == 0:
        typer.echo("note: watchdog off (firmware without it): a killed host leaves the pump running", err=True)
    elif watchdog_s * time_scale > budget_s:  # the watchdog is wall clock; the pump runs on rig time
        typer.echo(
            f"note: at time scale {time_scale:g} the {watchdog_s:g} s watchdog lets the pump run "
            f"{watchdog_s * time_scale:g} rig s after the host's last command; from "
            f"{WORKING_PRESSURE_PA:g} Pa it reaches the {cfg.hard_pressure_limit_pa:g} Pa hard limit "
            f"in {budget_s:.2f} rig s",
            err=True,
        )
    port = em.start()
    typer.echo(port)
    sys.stdout.flush()
    typer.echo("emulated rig running; Ctrl-C to stop", err=True)
    _signals_as_interrupt()
    try:
        em.serve_forever()
    except KeyboardInterrupt:
        typer.echo("emulator stopped", err=True)


@rig_app.command()
def characterize(
    port: str = typer.Option(..., help="serial device or pyserial URL of the rig controller"),
    design: str = typer.Option(..., help='design key, e.g. "[2.0, 25.4, nan, nan, nan, nan]"'),
    out: Path = typer.Option(..., help="job directory (created; reused to resume)"),
    config: Optional[Path] = typer.Option(None, help="rig config (.toml/.json)"),
    heights: list[float] = typer.Option(
        [0.0, 10.0, 20.0, 30.0, 40.0, 50.0, 60.0, 70.0],
        parser=item_parser(float, "a height in mm"),
        help="plate height, mm (repeat for several)",
    ),
    trials: int = typer.Option(3, min=1, max=100),
    source: str = typer.Option("rig", help="'rig' (real rig) or 'virtual' (emulator)"),
    progress: bool = typer.Option(True, help="progress bar"),
) -> None:
    """A membrane's force programme: heights x trials; ringed to 4.3 kPa, retest to 6.1 kPa."""
    from mfdesign.rig.procedures import membrane_plan, run_job

    cfg, d, hs = _config(config), _design(design), _heights(heights)
    if source not in ("rig", "virtual"):
        raise typer.BadParameter("must be 'rig' or 'virtual'", param_hint="--source")
    bad = [h for h in hs if not (cfg.height_min_mm <= h <= cfg.height_max_mm)]
    if bad:
        raise typer.BadParameter(
            f"heights {bad} outside the rig's [{cfg.height_min_mm:g}, {cfg.height_max_mm:g}] mm", param_hint="--heights"
        )
    plan = membrane_plan(d, heights_mm=hs, trials=trials, source=source)
    check_port(port)
    _finish(out, lambda: run_job(port, out, plan, cfg, progress=progress))


@rig_app.command()
def lift(
    port: str = typer.Option(..., help="serial device or pyserial URL of the rig controller"),
    design: str = typer.Option(..., help="design key"),
    mass_kg: float = typer.Option(..., min=0.01, max=50.0, help="mass on the plate (mount it first)"),
    out: Path = typer.Option(..., help="job directory (created; reused to resume)"),
    config: Optional[Path] = typer.Option(None, help="rig config (.toml/.json)"),
    trials: int = typer.Option(3, min=1, max=100),
    pressure_limit_pa: float = typer.Option(10000.0, min=100.0, max=99000.0),
    source: str = typer.Option("rig", help="'rig' or 'virtual'"),
    progress: bool = typer.Option(True, help="progress bar"),
) -> None:
    """Mass-lift trials: inflate under a mass until the pressure or height limit; deflate."""
    from mfdesign.rig.procedures import lift_plan, run_job

    cfg, d = _config(config), _design(design)
    if source not in ("rig", "virtual"):
        raise typer.BadParameter("must be 'rig' or 'virtual'", param_hint="--source")
    if pressure_limit_pa >= cfg.hard_pressure_limit_pa:
        raise typer.BadParameter(
            f"must be below the hard limit {cfg.hard_pressure_limit_pa:g} Pa", param_hint="--pressure-limit-pa"
        )
    plan = lift_plan(d, mass_kg, trials=trials, pressure_limit_pa=pressure_limit_pa, source=source)
    check_port(port)
    _finish(out, lambda: run_job(port, out, plan, cfg, progress=progress))


def register(app: typer.Typer) -> None:
    app.add_typer(rig_app, name="rig", help="Drive the test rig (or its emulator) over a serial port.")
