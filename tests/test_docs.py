"""Every command and every Python block in the README and docs/ is real.

Commands are the lines of ```bash blocks that start with ``mfdesign`` or ``python``
(a trailing ``\\`` continues a line; ``#`` starts a comment).

* fast: each ``mfdesign ...`` line parses against the real CLI (command, options and
  their types), without running it; every ```python block compiles;
* slow (``pytest -m slow tests/test_docs.py``): every command runs, in document order,
  from the repository root, and must exit 0; the ```python blocks of each file run in
  order as one script in a fresh folder (``docs/examples`` on the path) and must exit 0.

A Python block that cannot run on its own (a serial port, a fragment of a class, a folder
an earlier command wrote) says why on the line before it, ``<!-- not run: REASON -->``;
it is still compiled.
"""

from __future__ import annotations

import os
import re
import shlex
import subprocess
import sys
import textwrap
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

_PY_BLOCK = re.compile(r"(?:<!-- not run: (.*?) -->\n)?```python\n(.*?)```", re.S)


def doc_python_blocks(path: Path) -> list[tuple[str | None, str]]:
    """``(reason it is not run or None, code)`` of every ```python block, in order."""
    return [(reason or None, textwrap.dedent(code)) for reason, code in _PY_BLOCK.findall(path.read_text())]


PY = {p: doc_python_blocks(p) for p in DOCS if doc_python_blocks(p)}


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
        if "run by tests/" in command:  # its own test runs it (a second terminal, or the real data)
            continue
        t0 = time.perf_counter()
        r = subprocess.run(command, shell=True, cwd=ROOT, env=env, capture_output=True, text=True, timeout=1800)
        # Wall time per command (pytest -s shows it): how long a reader waits for each.
        print(f"[{time.perf_counter() - t0:7.1f} s] {path.name}: {command}", flush=True)
        assert r.returncode == 0, f"{path.name}: {command!r} failed:\n{r.stdout[-2000:]}\n{r.stderr[-2000:]}"


def test_python_blocks_compile():
    assert PY, "no ```python block found in the docs"
    for path, blocks in PY.items():
        for k, (reason, code) in enumerate(blocks):
            assert reason is None or reason.strip(), f"{path.name}: python block {k + 1} is not run without a reason"
            compile(code, f"{path.name}:block{k + 1}", "exec")


@pytest.mark.slow
@pytest.mark.parametrize("path", [p for p, b in PY.items() if any(r is None for r, _ in b)], ids=lambda p: p.name)
def test_python_blocks_run(path, tmp_path):
    code = "\n".join(code for reason, code in PY[path] if reason is None)
    env = dict(os.environ, JAX_PLATFORMS="cpu", MPLBACKEND="Agg")
    # the package of this checkout, and docs/examples (effects.md imports its example effect)
    env["PYTHONPATH"] = os.pathsep.join([str(ROOT), str(ROOT / "docs" / "examples"), env.get("PYTHONPATH", "")])
    t0 = time.perf_counter()
    r = subprocess.run(
        [sys.executable, "-c", code], cwd=tmp_path, env=env, capture_output=True, text=True, timeout=1800
    )
    print(f"[{time.perf_counter() - t0:7.1f} s] {path.name}: python blocks", flush=True)
    assert r.returncode == 0, f"{path.name}: python blocks failed:\n{r.stdout[-2000:]}\n{r.stderr[-3000:]}"


def test_cli_reference_is_in_sync():
    from tools.cli_reference import render

    assert (ROOT / "docs" / "cli.md").read_text() == render(), (
        "docs/cli.md is stale: run `python -m tools.cli_reference > docs/cli.md`"
    )
