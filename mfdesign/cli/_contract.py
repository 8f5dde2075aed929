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
        from mfdesign.outputs import OutputLock, file_lock, prepare_out_dir, prepare_out_file, refuse_inputs

        # The one place the CLI switches JAX to float64: when a command really runs (never
        # for --help), before it creates any array.
        enable_x64()

        out = ctx.params.get("out")
        if out is None:
            return super().invoke(ctx)
        inputs = _input_paths(ctx.params)
        if self.name in FILE_OUTPUTS:
            prepare_out_file(out, suffixes=FILE_OUTPUTS[self.name])
            refuse_inputs(out, inputs)
            with file_lock(out):  # two runs writing one file: the second is refused, not the last one wins
                ctx.meta[_LOG_DIR_KEY] = Path(out).parent
                return super().invoke(ctx)
        prepare_out_dir(out)
        refuse_inputs(out, inputs)
        with OutputLock(out):
            ctx.meta[_LOG_DIR_KEY] = Path(out)
            return super().invoke(ctx)


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
