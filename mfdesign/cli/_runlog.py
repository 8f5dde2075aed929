"""``run.log``: what a command did, beside its outputs (every command with ``--out``).

The log starts with the mfdesign version, the command line, every setting the command ran
with (its parameters, defaults included) and the Python / platform, then holds the
package's log records (``logging.getLogger("mfdesign...")``: INFO, DEBUG with
``--verbose``) and ends with the exit status and the wall time. A folder output gets
``OUT/run.log``; a file output (``import``, ``cv``) gets ``<file>.run.log`` beside it.

Why a temporary file renamed at the end, as every other output: a reader never sees a
half-written log of a finished run. A run refused for bad input (exit status 2) leaves no
log (bad input writes nothing); a crash keeps it (with the one-line error).

The console: ``--quiet`` shows warnings and errors only, ``--verbose`` every record at
DEBUG; by default the lines the commands already print (the exact model's lattice growth).
"""

from __future__ import annotations

import contextlib
import datetime
import json
import logging
import os
import platform
import time
from pathlib import Path
from typing import Any, Iterator

from mfdesign.errors import InputError


# Where the group callback leaves --verbose / --quiet for the command's run log.
VERBOSITY_KEY = "mfdesign.verbosity"


class _EchoHandler(logging.Handler):
    """Log records as lines on stderr, resolved at each call (a test runner swaps stderr)."""

    def emit(self, record: logging.LogRecord) -> None:
        import typer

        typer.echo(self.format(record), err=True)


__all__ = ["LOG_NAME", "console", "log_path", "run_log"]

LOG_NAME = "run.log"
_FORMAT = "%(asctime)s %(levelname)s %(name)s: %(message)s"


def _plain(value: Any) -> Any:
    if isinstance(value, Path):
        return str(value)
    if isinstance(value, (list, tuple)):
        return [_plain(v) for v in value]
    return value


def log_path(out: Path, is_file: bool) -> Path:
    """Where a command's log goes: ``OUT/run.log``, or ``<file>.run.log`` beside a file output."""
    return out.parent / f"{out.name}.{LOG_NAME}" if is_file else out / LOG_NAME


@contextlib.contextmanager
def run_log(path: Path, command: str, params: dict, verbose: bool = False) -> Iterator[logging.Handler]:
    """Log the run into ``path`` (module doc); renamed into place when the block ends,
    removed when it ends in bad input (``typer.Exit(2)``)."""
    from importlib.metadata import PackageNotFoundError, version

    import typer

    try:
        mine = version("mfdesign")
    except PackageNotFoundError:  # pragma: no cover -- a source tree without an install
        mine = "unknown"
    part = path.parent / f".{path.name}.{os.getpid()}.part"
    handler = logging.FileHandler(part, mode="w", encoding="utf-8", delay=False)
    handler.setFormatter(logging.Formatter(_FORMAT, datefmt="%Y-%m-%d %H:%M:%S"))
    handler.setLevel(logging.DEBUG if verbose else logging.INFO)
    log = logging.getLogger("mfdesign")
    old_level = log.level
    log.setLevel(logging.DEBUG if verbose else min(old_level or logging.INFO, logging.INFO))
    log.addHandler(handler)
    settings = {k: _plain(v) for k, v in params.items()}
    header = logging.getLogger("mfdesign.run")
    header.info("mfdesign %s: %s", mine, command)
    header.info("settings: %s", json.dumps(settings, default=str, sort_keys=True))
    header.info(
        "python %s on %s; started %s",
        platform.python_version(),
        platform.platform(),
        datetime.datetime.now().isoformat(timespec="seconds"),
    )
    t0, status = time.perf_counter(), 0
    try:
        yield handler
    except typer.Exit as stop:
        status = stop.exit_code
        raise
    except InputError:  # bad input found by the library: the CLI turns it into exit 2
        status = 2
        raise
    except BaseException:
        status = 1
        raise
    finally:
        header.info("finished: exit status %s after %.1f s", status, time.perf_counter() - t0)
        log.removeHandler(handler)
        log.setLevel(old_level)
        handler.close()
        with contextlib.suppress(OSError):
            if status == 2:  # bad input writes nothing, a log neither
                os.unlink(part)
            else:
                os.replace(part, path)


def console(verbose: bool, quiet: bool) -> None:
    """The console's share of the package's log records (module doc): an stderr handler on
    ``mfdesign`` at DEBUG (``--verbose``), WARNING (``--quiet``) or, by default, none beyond
    the ones the commands install (:func:`mfdesign.cli._app.show_lattice_growth`)."""
    log = logging.getLogger("mfdesign")
    for h in [h for h in log.handlers if getattr(h, "_mfdesign_console", False)]:
        log.removeHandler(h)
    if quiet:
        for name in ("mfdesign.models.exact",):  # the default lines go quiet too
            for h in logging.getLogger(name).handlers:
                h.setLevel(logging.WARNING)
    if verbose:
        exact = logging.getLogger("mfdesign.models.exact")
        for h in [h for h in exact.handlers if isinstance(h, _EchoHandler)]:
            exact.removeHandler(h)  # its lines reach the console through this handler
        handler = _EchoHandler()
        handler.setFormatter(logging.Formatter(_FORMAT, datefmt="%H:%M:%S"))
        handler.setLevel(logging.DEBUG)
        handler._mfdesign_console = True  # type: ignore[attr-defined]
        log.addHandler(handler)
        log.setLevel(logging.DEBUG)


def _one_line_warning(message, category, filename, lineno, line=None) -> str:
    """A Python warning as the user reads it: one line, its words, no source line (the
    default format repeats the code that warned, e.g. ``report = convergence_report(...)``)."""
    return f"warning: {message}\n"


def plain_warnings() -> None:
    """Python warnings (emcee's chain too short, ArviZ's) as one line each on the console."""
    import warnings

    warnings.formatwarning = _one_line_warning  # type: ignore[assignment]
