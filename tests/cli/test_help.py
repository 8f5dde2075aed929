"""``mfdesign [CMD ...] --help`` stays fast: no command's help imports JAX.

JAX's import alone takes ~0.6 s; a help page that imports it (the group callback once did,
to set the compilation cache) takes over 1 s. Each help runs in-process (``CliRunner``) in
one fresh interpreter, and ``sys.modules`` is checked after every page.
"""

import json
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

    runner, out = CliRunner(), []
    for path in walk(cli, []):
        res = runner.invoke(app, [*path, "--help"])
        out.append({"command": path, "exit": res.exit_code, "usage": "Usage" in res.output,
                    "jax": "jax" in sys.modules})
    print(json.dumps(out))
    """
)


def test_no_help_page_imports_jax():
    proc = subprocess.run(
        [sys.executable, "-c", _SCRIPT], cwd=ROOT, capture_output=True, text=True, timeout=300, check=True
    )
    pages = json.loads(proc.stdout.strip().splitlines()[-1])
    names = {" ".join(p["command"]) for p in pages}
    assert {"", "simulate", "calibrate", "diagnose", "demo", "rig", "rig lift"} <= names
    for p in pages:
        assert p["exit"] == 0 and p["usage"], p
    imported = [" ".join(p["command"]) or "(top)" for p in pages if p["jax"]]
    assert not imported, f"--help imported jax: first at `mfdesign {imported[0]} --help`"
