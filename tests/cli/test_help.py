"""``mfdesign [CMD ...] --help`` stays fast and says what the source says.

Fast: no command's help imports JAX (its import alone takes ~0.6 s; a help page that
imported it, as the group callback once did, took over 1 s) nor Rich (~0.2 s of the 0.3 s
a help page took while typer rendered it with Rich). Each help runs in-process
(``CliRunner``) in one fresh interpreter, and ``sys.modules`` is checked after every page.

Readable: every page shows the design key ``"[t, c, r1, w1, r2, w2]"`` and the units, and
every bracketed part of an option's help (``[mm]``, ``[Pa]``) as written: Rich markup once
ate them (``Design key "" in mm``), and put a ``<bool>`` placeholder on flags.
"""

import json
import re
import subprocess
import sys
import textwrap
from pathlib import Path

ROOT = Path(__file__).resolve().parents[2]

_SCRIPT = textwrap.dedent(
    """
    import json, sys
    import typer.main
    from typer.testing import CliRunner
    from mfdesign.cli import app

    cli = typer.main.get_command(app)

    def walk(cmd, path):
        yield path
        for name, sub in getattr(cmd, "commands", {}).items():
            yield from walk(sub, path + [name])

    def params(cmd, path):
        node = cmd
        for name in path:
            node = node.commands[name]
        return [p.help for p in node.params if getattr(p, "help", None)]

    runner, out = CliRunner(), []
    for path in walk(cli, []):
        res = runner.invoke(app, [*path, "--help"], terminal_width=100)
        out.append({"command": path, "exit": res.exit_code, "usage": "Usage" in res.output,
                    "jax": "jax" in sys.modules, "rich": "rich" in sys.modules,
                    "text": res.output, "helps": params(cli, path)})
    print(json.dumps(out))
    """
)


def test_no_help_page_imports_jax():
    pages = _pages()
    names = {" ".join(p["command"]) for p in pages}
    assert {"", "simulate", "calibrate", "diagnose", "demo", "rig", "rig lift"} <= names
    for p in pages:
        assert p["exit"] == 0 and p["usage"], p
    imported = [" ".join(p["command"]) or "(top)" for p in pages if p["jax"]]
    assert not imported, f"--help imported jax: first at `mfdesign {imported[0]} --help`"


def _pages():
    proc = subprocess.run(
        [sys.executable, "-c", _SCRIPT], cwd=ROOT, capture_output=True, text=True, timeout=300, check=True
    )
    return json.loads(proc.stdout.strip().splitlines()[-1])


def test_every_help_page_shows_the_design_key_and_units():
    pages = _pages()
    assert len(pages) >= 14  # the group, 11 commands, rig and its 3 sub-commands
    for p in pages:
        where = f"`mfdesign {' '.join(p['command'])} --help`"
        text = " ".join(p["text"].split())  # click re-wraps lines: compare on single spaces
        assert '"[t, c, r1, w1, r2, w2]" in mm' in text, where
        assert all(unit in text for unit in ("in mm", "in Pa", "in N")), where
        assert "<bool>" not in text, where
        for helptext in p["helps"]:
            for part in re.findall(r"\[[^\]]*\]", helptext):  # "[mm]", "[t, c, ...]"
                assert part in text, f"{where} lost {part!r} of {helptext!r}"
    rich = [" ".join(p["command"]) or "(top)" for p in pages if p["rich"]]
    assert not rich, f"--help imported rich: first at `mfdesign {rich[0]} --help`"
