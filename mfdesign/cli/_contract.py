"""The CLI contract, in one place, for every ``mfdesign`` command.

* Bad input (:func:`mfdesign.errors.anticipated`, and click's usage errors: a bad option
  value, an unknown option, a missing argument): one line ``error: ...`` on stderr, exit
  status 2.
* Anything else (a bug): one line naming a log file that holds the traceback, exit
  status 1. The log goes into the command's output folder if it has one, else into
  ``$MFDESIGN_LOG_DIR`` (default: ``<temp dir>/mfdesign-logs``).
* Outputs are checked BEFORE any computation: ``--out`` must be (or become) a writable
  folder (a file for ``cv``), and it is locked (:class:`mfdesign.outputs.OutputLock`) so
  that a second run on the same folder fails at once instead of mixing files.

:class:`ContractGroup` is the ``typer.Typer(cls=...)`` of the app; :func:`apply` makes
every registered command a :class:`ContractCommand`.
"""

from __future__ import annotations

import datetime
import os
import tempfile
import traceback
from pathlib import Path

import typer
from typer.core import TyperCommand, TyperGroup

from mfdesign.errors import anticipated, one_line

__all__ = ["ContractCommand", "ContractGroup", "apply", "item_parser", "effect_name", "log_dir"]

# Commands whose --out is one file, not a folder, and the name endings of what they write.
FILE_OUTPUTS = {"cv": (".json",), "import": (".parquet",)}
_LOG_DIR_KEY = "mfdesign.log_dir"


def log_dir() -> Path:
    return Path(os.environ.get("MFDESIGN_LOG_DIR") or Path(tempfile.gettempdir()) / "mfdesign-logs")


def _write_log(err: BaseException, folder: Path | None, argv: str) -> Path:
    stamp = datetime.datetime.now().strftime("%Y%m%d-%H%M%S")
    text = f"mfdesign {argv}\n\n" + "".join(traceback.format_exception(err))
    for place in ([folder] if folder is not None else []) + [log_dir()]:
        try:
            place.mkdir(parents=True, exist_ok=True)
            fd, name = tempfile.mkstemp(dir=place, prefix=f"mfdesign-error-{stamp}-", suffix=".log")
            with os.fdopen(fd, "w") as fh:
                fh.write(text)
            return Path(name)
        except OSError:
            continue
    return Path("<no writable log folder>")


class ContractCommand(TyperCommand):
    """A command whose ``--out`` is validated and locked before its body runs."""

    def invoke(self, ctx):
        from mfdesign._x64 import enable_x64
        from mfdesign.physics.cluster import use_scheduler

        # The one place the CLI switches JAX to float64: when a command really runs (never
        # for --help), before it creates any array.
        enable_x64()

        flags = {p.name: next((o for o in p.opts if o.startswith("--")), None) for p in self.params}
        check_option_ranges(ctx.params, flags)
        # --scheduler (the commands that solve planes): every plane of the command goes to
        # that Dask scheduler; a missing Dask is refused here, before any computation
        with use_scheduler(ctx.params.get("scheduler")):
            return self._invoke_with_outputs(ctx)

    def _invoke_with_outputs(self, ctx):
        from mfdesign.outputs import OutputLock, file_lock, prepare_out_dir, prepare_out_file, refuse_inputs

        out = ctx.params.get("out")
        if out is None:
            return super().invoke(ctx)
        inputs = _input_paths(ctx.params)
        if self.name in FILE_OUTPUTS:
            prepare_out_file(out, suffixes=FILE_OUTPUTS[self.name])
            refuse_inputs(out, inputs)
            with file_lock(out):  # two runs writing one file: the second is refused, not the last one wins
                ctx.meta[_LOG_DIR_KEY] = Path(out).parent
                with _run_log(ctx, Path(out), is_file=True):
                    return super().invoke(ctx)
        prepare_out_dir(out)
        refuse_inputs(out, inputs)
        with OutputLock(out):
            ctx.meta[_LOG_DIR_KEY] = Path(out)
            with _run_log(ctx, Path(out), is_file=False):
                return super().invoke(ctx)


# Upper bounds of the numeric options, by parameter name (every command alike); why: a
# value the machine cannot hold (``--q 1000000``, ``--batch 1e9``, ``--walkers 100000``)
# ended in an out-of-memory kill or a traceback hours later, not a message. Each bound is
# far above any useful value (the docs' largest in brackets) and far below exhaustion.
OPTION_MAX: dict[str, float] = {
    "seed": 2**32 - 1,
    "members": 1024,  # ensemble members [32]
    "steps": 1_000_000,  # training / emcee / optimiser steps [10,000]
    "delta_steps": 1_000_000,  # [3,000]
    "batch": 100_000,  # minibatch rows [100]
    "walkers": 1024,  # emcee walkers [28]
    "max_rows": 2_000_000,  # rows a calibration keeps [3,000]; mfdesign.data.plausible.MAX_ROWS
    "folds": 1000,  # [7]
    "check_top": 100,  # [3]
    "check_pairs": 1000,  # [3]
    "max_steps": 100,  # [2]
    "q": 256,  # batch of proposals [2]
    "membranes": 256,  # [2]
    "sim_runs": 10_000,  # [4]
    "restarts": 1_000_000,  # [1,000]
    "refine": 100_000,  # [64]
    "starts": 10_000_000,  # [2,500]
    "sim_heights": 400,  # as simulate --n-heights
    "sim_pressures": 2000,  # as simulate --n-pressures
    "cost_rig": 1e12,
    "cost_sim": 1e12,
    "tie_tol": 1.0,
    "h_max_mm": 200.0,  # the Measurements range of heights
    "p_max_pa": 200e3,  # the Measurements range of pressures
    "mu_pa": 1e9,
    "jm": 1e6,
}
# ... and the least value of those that had none (a negative seed or count is no value).
OPTION_MIN: dict[str, float] = {
    "seed": 0,
    "restarts": 1,
    "refine": 0,
    "steps": 0,
    "q": 1,
    "membranes": 0,
    "sim_runs": 0,
    "sim_heights": 2,
    "sim_pressures": 2,
    "cost_rig": 0.0,
    "cost_sim": 0.0,
    "tie_tol": 0.0,
}


def check_option_ranges(params: dict, flags: dict[str, str] | None = None) -> None:
    """Refuse a numeric option outside :data:`OPTION_MIN` / :data:`OPTION_MAX`, or a float
    option that is not finite, in one line naming the option."""
    import math

    from mfdesign.errors import InputError

    for name, value in params.items():
        if isinstance(value, bool) or not isinstance(value, (int, float)):
            continue
        flag = (flags or {}).get(name) or "--" + name.replace("_", "-")
        if isinstance(value, float) and not math.isfinite(value):
            raise InputError(f"{flag} {value}: allowed: a finite number")
        low, high = OPTION_MIN.get(name, -math.inf), OPTION_MAX.get(name, math.inf)
        if not low <= value <= high:
            shown = [f"{v:,}" if float(v).is_integer() else f"{v:g}" for v in (value, low, high)]
            rule = f"at most {shown[2]}" if low == -math.inf else f"{shown[1]} to {shown[2]}"
            raise InputError(f"{flag} {shown[0]}: allowed: {rule}")


def _run_log(ctx, out: Path, is_file: bool):
    """The command's ``run.log`` (:mod:`mfdesign.cli._runlog`), at the verbosity the group
    callback left in ``ctx.meta``."""
    import sys

    from mfdesign.cli._runlog import VERBOSITY_KEY, log_path, run_log

    # the command line as typed when run as `mfdesign ...` / `python -m mfdesign.cli ...`;
    # under a test runner sys.argv is the runner's, and the settings line says it all
    typed = Path(sys.argv[0]).name in ("mfdesign", "__main__.py")
    command = " ".join(["mfdesign", *sys.argv[1:]]) if typed else ctx.command_path
    return run_log(log_path(out, is_file), command, ctx.params, verbose=ctx.meta.get(VERBOSITY_KEY) == "verbose")


def _input_paths(params: dict) -> list[Path]:
    """Every path a command was given other than ``--out`` (its inputs)."""
    found: list[Path] = []
    for name, value in params.items():
        if name == "out":
            continue
        for item in value if isinstance(value, (list, tuple)) else [value]:
            if isinstance(item, Path):
                found.append(item)
    return found


def _click_exception():
    try:  # typer >= 0.2x vendors click as typer._click; older typer uses click itself
        from typer._click.exceptions import ClickException
    except ImportError:
        from click.exceptions import ClickException
    return ClickException


def _usage_line(err) -> typer.Exit:
    """A usage error (a bad option value, an unknown option, a missing argument) as the
    contract's one line, instead of click's usage block and boxed message; exit status 2."""
    ctx = getattr(err, "ctx", None)
    where = f" (see '{ctx.command_path} --help')" if ctx is not None else ""
    typer.echo(f"error: {one_line(err.format_message())}{where}", err=True)
    return typer.Exit(code=err.exit_code)


def _is_help(err) -> bool:
    # ``mfdesign`` alone prints the help (no_args_is_help): click raises it as a usage error
    return type(err).__name__ == "NoArgsIsHelpError"


class ContractGroup(TyperGroup):
    """The top-level group: maps what escapes a command onto the contract (module doc)."""

    def make_context(self, info_name, args, parent=None, **extra):
        try:
            return super().make_context(info_name, args, parent=parent, **extra)
        except _click_exception() as err:  # the group's own options (``mfdesign --bogus``)
            if _is_help(err):
                raise
            raise _usage_line(err) from None

    def invoke(self, ctx):
        try:
            return super().invoke(ctx)
        except (typer.Exit, typer.Abort, KeyboardInterrupt):
            raise
        except BrokenPipeError:
            # the reader went away (`mfdesign ... | head`): stop quietly, as a Unix filter does
            # (the Python docs' recipe: stdout onto devnull, so the interpreter's last flush is silent)
            import os
            import sys

            os.dup2(os.open(os.devnull, os.O_WRONLY), sys.stdout.fileno())
            raise typer.Exit(code=141) from None
        except Exception as err:  # noqa: BLE001 -- the contract: no traceback ever reaches the user
            if isinstance(err, _click_exception()):  # a command's usage error (or an unknown command)
                if _is_help(err):
                    raise
                raise _usage_line(err) from None
            if isinstance(err, anticipated()):
                typer.echo(f"error: {one_line(err)}", err=True)
                raise typer.Exit(code=2) from None
            folder = ctx.meta.get(_LOG_DIR_KEY)
            log = _write_log(err, folder, ctx.invoked_subcommand or ctx.info_name)
            typer.echo(
                f"error: unexpected {type(err).__name__} (a bug, not your input): "
                f"{one_line(err, 200)}; traceback in {log}",
                err=True,
            )
            raise typer.Exit(code=1) from None


def item_parser(convert, what: str):
    """``typer.Option(parser=...)`` for ONE item of a list option. Every list option of the
    CLI is a repeated option (``--rings 0 --rings 2``); a comma list (the old form of some
    options) is refused with a message that says so, exit status 2."""

    def parse(text: str):
        try:
            return convert(text)
        except (TypeError, ValueError):
            hint = (
                " (a comma-separated list is not accepted: repeat the option, one value each)"
                if "," in str(text)
                else ""
            )
            raise typer.BadParameter(f"{text!r} is not {what}{hint}") from None

    parse.__name__ = what.replace(" ", "_")
    return parse


def effect_name(text: str) -> str:
    """An item that is a name (an effect): a comma in it can only be an old-style list, so
    :func:`item_parser` refuses it with its repeat-the-option hint."""
    if "," in text:
        raise ValueError(text)
    return text


def apply(app: typer.Typer) -> None:
    """Make every command registered on ``app`` so far a :class:`ContractCommand`."""
    for info in app.registered_commands:
        if info.cls in (None, TyperCommand):  # typer's default; keep a command's own class
            info.cls = ContractCommand
