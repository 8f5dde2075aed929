"""64-bit JAX is switched on by mfdesign's entry points, never by importing mfdesign."""

from __future__ import annotations

import subprocess
import sys
import textwrap

_IMPORT_ALL = """
import importlib, pkgutil
import jax
import mfdesign
for m in pkgutil.walk_packages(mfdesign.__path__, "mfdesign."):
    if ".__main__" not in m.name:
        importlib.import_module(m.name)
"""


def _run(code: str) -> str:
    out = subprocess.run([sys.executable, "-c", textwrap.dedent(code)], capture_output=True, text=True, timeout=300)
    assert out.returncode == 0, out.stderr[-2000:]
    return out.stdout.strip()


def test_importing_every_module_leaves_jax_in_32_bit_and_an_entry_point_switches_it_on():
    code = (
        _IMPORT_ALL
        + """
print(jax.config.read("jax_enable_x64"))
from mfdesign.design import Membrane
from mfdesign.models.standin import standin_plane
plane = standin_plane(Membrane(2.0, 25.4), [10.0, 20.0], [2000.0, 4000.0])
print(jax.config.read("jax_enable_x64"), plane.force_n.dtype)
"""
    )
    before, after = _run(code).splitlines()[-2:]
    assert before == "False"  # no import side effect
    assert after == "True float64"  # the entry function switched it on before any array


def test_every_cli_command_runs_in_float64():
    code = """
import jax
from typer.testing import CliRunner
from mfdesign.cli import app
r = CliRunner().invoke(app, ["simulate", "--help"])
print(jax.config.read("jax_enable_x64"))  # --help alone: unchanged
from mfdesign.cli._contract import ContractCommand
cmd = ContractCommand(name="probe", callback=lambda: print(jax.config.read("jax_enable_x64")))
cmd.main([], standalone_mode=False)
"""
    lines = _run(code).splitlines()
    assert lines[-2:] == ["False", "True"]
