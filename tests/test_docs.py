"""Every command in the README and docs/ is real.

Commands are the lines of ```bash blocks that start with ``mfdesign`` or ``python``
(a trailing ``\\`` continues a line; ``#`` starts a comment).

* fast: each ``mfdesign ...`` line parses against the real CLI (command, options and
  their types), without running it;
* slow (``pytest -m slow tests/test_docs.py``): every command runs, in document order,
  from the repository root, and must exit 0.
"""

from __future__ import annotations

import os
import re
import shlex
import subprocess
import sys
import time
from pathlib import Path

import pytest
import typer

ROOT = Path(__file__).resolve().parents[1]
DOCS = [ROOT / "README.md", *sorted((ROOT / "docs").glob("*.md"))]
_BLOCK = re.compile(r"```(?:bash|sh|console)\n(.*?)```", re.S)


def doc_commands(path: Path) -> list[str]:
    out = []
    for block in _BLOCK.findall(path.read_text()):
        lines, cur = [], ""
        for raw in block.splitlines():
            line = raw.strip()
            if line.startswith("$ "):
                line = line[2:]
            if cur:
                line = cur + " " + line
                cur = ""
            if line.endswith("\\"):
                cur = line[:-1].strip()
                continue
            lines.append(line)
        out += [ln for ln in lines if re.match(r"^(mfdesign|python)\b", ln)]
    return out


def _rest(ctx) -> list[str]:
    """Arguments a group left for its sub-command (click renamed ``protected_args``)."""
    protected = getattr(ctx, "_protected_args", None)
    if protected is None:
        protected = getattr(ctx, "protected_args", [])
    return list(protected) + list(ctx.args)


ALL = [(p, c) for p in DOCS for c in doc_commands(p)]


def test_docs_have_commands():
    assert any(c.startswith("mfdesign demo") for _, c in ALL), "the README's main job is missing"
    assert any(c.startswith("pytest") or "pytest" in c for p in DOCS for c in _BLOCK.findall(p.read_text()))


@pytest.mark.parametrize(
    "path,command",
    [a for a in ALL if a[1].startswith("mfdesign")],
    ids=[f"{a[0].name}:{a[1][:60]}" for a in ALL if a[1].startswith("mfdesign")],
)
def test_cli_lines_parse(path, command):
    from mfdesign.cli import app

    cli = typer.main.get_command(app)
    args = shlex.split(command.split(" #")[0])[1:]
    args = [a for a in args if not re.match(r"^[|>&]", a)]
    ctx = cli.make_context("mfdesign", list(args), resilient_parsing=False)
    # Walk down the groups to the leaf command and let click parse its options.
    with ctx:
        cmd, sub_args = cli, _rest(ctx)
        while hasattr(cmd, "resolve_command") and sub_args:
            name, cmd, sub_args = cmd.resolve_command(ctx, sub_args)
            sub = cmd.make_context(name, list(sub_args), parent=ctx)
            ctx, sub_args = sub, _rest(sub) if hasattr(cmd, "resolve_command") else []
        assert not hasattr(cmd, "resolve_command"), f"{path.name}: {command!r} names no command"


@pytest.mark.slow
def test_every_doc_command_runs(tmp_path):
    env = dict(os.environ, JAX_PLATFORMS="cpu", MPLBACKEND="Agg")
    bindir = str(Path(sys.executable).parent)
    env["PATH"] = bindir + os.pathsep + env.get("PATH", "")
    for path, command in ALL:
        if "run by tests/" in command:  # needs a second terminal (rig + emulator): its own test runs it
            continue
        t0 = time.perf_counter()
        r = subprocess.run(command, shell=True, cwd=ROOT, env=env, capture_output=True, text=True, timeout=1800)
        # Wall time per command (pytest -s shows it): how long a reader waits for each.
        print(f"[{time.perf_counter() - t0:7.1f} s] {path.name}: {command}", flush=True)
        assert r.returncode == 0, f"{path.name}: {command!r} failed:\n{r.stdout[-2000:]}\n{r.stderr[-2000:]}"


def test_cli_reference_is_in_sync():
    from tools.cli_reference import render

    assert (ROOT / "docs" / "cli.md").read_text() == render(), (
        "docs/cli.md is stale: run `python -m tools.cli_reference > docs/cli.md`"
    )
