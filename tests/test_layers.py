"""Imports flow one way: design -> physics / data -> models -> calibration / diagnose ->
acquisition / design optimisation -> report -> workflows -> cli.

Every ``import`` of the package is read from the source (module level and inside
functions alike: a lazy import is still a dependency), and each must point to the same
layer or one upstream; inside the package no two modules may import each other, even
through others (a cycle).
"""

from __future__ import annotations

import ast
from pathlib import Path

PKG = Path(__file__).resolve().parents[1] / "mfdesign"

# Upstream first. A module takes the layer of its longest matching prefix.
LAYERS = (
    (
        "mfdesign._x64",
        "mfdesign._padding",
        "mfdesign._cache",
        "mfdesign._memory",
        "mfdesign.units",
        "mfdesign.errors",
        "mfdesign.outputs",
        "mfdesign.provenance",
    ),
    ("mfdesign.design", "mfdesign.materials"),
    # physics, data, the rig's I/O, and the loader of a user's effects files (beside the registry)
    ("mfdesign.physics", "mfdesign.data", "mfdesign.rig", "mfdesign.user_effects"),
    ("mfdesign.models",),
    ("mfdesign.calibration", "mfdesign.diagnosis"),
    ("mfdesign.acquire", "mfdesign.discriminate", "mfdesign.optimization", "mfdesign.sim_runs"),
    ("mfdesign.campaign",),  # a lab's loop: every step above, kept in one folder
    ("mfdesign.report",),
    ("mfdesign.workflows",),  # each command's workflow (load, fit, write, summarise): the CLI's library
    ("mfdesign.cli",),  # a shell: parses options, calls one workflow, prints its summary
    ("mfdesign",),  # the package's own names: a facade over everything
)


def _modules() -> dict[str, Path]:
    out = {}
    for path in PKG.rglob("*.py"):
        parts = path.relative_to(PKG.parent).with_suffix("").parts
        name = ".".join(parts[:-1] if parts[-1] == "__init__" else parts)
        out[name] = path
    return out


def _layer(name: str) -> int:
    best, rank = -1, None
    for k, prefixes in enumerate(LAYERS):
        for p in prefixes:
            if (name == p or (name.startswith(p + ".") and p != "mfdesign")) and len(p) > best:
                best, rank = len(p), k
    assert rank is not None, f"{name} is in no layer: add it to LAYERS"
    return rank


def _imports(name: str, path: Path, modules: dict[str, Path]) -> set[str]:
    """Package modules that ``name`` imports (``from a import b`` counts ``a.b`` when it is a module)."""
    found = set()
    package = name if path.name == "__init__.py" else name.rpartition(".")[0]
    for node in ast.walk(ast.parse(path.read_text())):
        if isinstance(node, ast.ImportFrom):
            base = node.module or ""
            if node.level:
                base = ".".join(
                    package.split(".")[: len(package.split(".")) - node.level + 1] + ([base] if base else [])
                )
            for alias in node.names:
                full = f"{base}.{alias.name}"
                found.add(full if full in modules else base)
        elif isinstance(node, ast.Import):
            found.update(a.name for a in node.names)
    return {m for m in found if m in modules and m != name}


def _graph():
    modules = _modules()
    return {name: _imports(name, path, modules) for name, path in modules.items()}


def test_every_import_points_upstream_or_sideways():
    bad = [
        f"{a} (layer {_layer(a)}) imports {b} (layer {_layer(b)})"
        for a, targets in _graph().items()
        for b in targets
        if _layer(b) > _layer(a)
    ]
    assert not bad, "imports that run upstream:\n" + "\n".join(sorted(bad))


def test_no_import_cycles():
    graph = _graph()
    # The package __init__ files only re-export their own children: edges from a package to
    # its submodules are not dependencies of the layout.
    graph = {a: {b for b in t if not b.startswith(a + ".")} for a, t in graph.items()}
    state, stack, cycles = {}, [], []

    def visit(node):
        state[node] = 1
        stack.append(node)
        for nxt in sorted(graph[node]):
            if state.get(nxt) == 1:
                cycles.append(" -> ".join(stack[stack.index(nxt) :] + [nxt]))
            elif nxt not in state:
                visit(nxt)
        stack.pop()
        state[node] = 2

    for node in sorted(graph):
        if node not in state:
            visit(node)
    assert not cycles, "import cycles:\n" + "\n".join(cycles)


def test_the_check_sees_a_violation(tmp_path):
    """The parser finds lazy imports (a test that cannot fail proves nothing)."""
    src = "def f():\n    from mfdesign.cli import app\n    return app\n"
    p = tmp_path / "x.py"
    p.write_text(src)
    got = _imports("mfdesign.physics.x", p, {"mfdesign.cli": Path(), "mfdesign.physics.x": p})
    assert got == {"mfdesign.cli"} and _layer("mfdesign.cli") > _layer("mfdesign.physics.x")


def test_no_command_module_imports_another():
    """The CLI is a shell over :mod:`mfdesign.workflows`: a command module imports only the
    shell's private helpers (``mfdesign.cli._app``, ``_contract``, ...), never another
    command's module; what two commands share lives in the library."""
    graph = _graph()
    bad = [
        f"{a} imports {b}"
        for a, targets in graph.items()
        if a.startswith("mfdesign.cli.")
        for b in targets
        if b.startswith("mfdesign.cli.") and not b.rpartition(".")[2].startswith("_") and b != a
    ]
    assert not bad, "command modules importing each other:\n" + "\n".join(sorted(bad))
