"""A non-editable install works from another folder: the package data (the demo's dataset,
its planes, the emulator, the reports' HTML templates) travel inside the wheel and are found with importlib.resources."""

from __future__ import annotations

import os
import subprocess
import sys
from pathlib import Path

import pytest

ROOT = Path(__file__).resolve().parents[1]


@pytest.mark.slow
def test_wheel_install_finds_its_data_from_another_folder(tmp_path):
    site = tmp_path / "site"
    r = subprocess.run(
        [sys.executable, "-m", "pip", "install", "--quiet", "--no-deps", "--target", str(site), str(ROOT)],
        capture_output=True,
        text=True,
    )
    assert r.returncode == 0, r.stderr[-3000:]
    elsewhere = tmp_path / "elsewhere"
    elsewhere.mkdir()
    check = (
        "import mfdesign.cli, mfdesign.data.shipped as s\n"
        "from mfdesign.data.sources import load_sources\n"
        "from mfdesign.models.emulator import load_default\n"
        f"assert mfdesign.cli.__file__.startswith({str(site)!r}), mfdesign.cli.__file__\n"
        "assert s.bundled_path().is_file() and s.bundled_card_path().is_file()\n"
        "from mfdesign.physics.planes import _shipped_pack\n"
        "assert _shipped_pack(), 'no shipped planes'\n"  # the demo's planes travel too
        "from mfdesign.physics._traces import _shipped_pack as kernels\n"
        "assert kernels(), 'no shipped kernels'\n"  # and its traced kernels
        "from mfdesign.report.render import environment\n"
        "assert 'base.html.j2' in environment().list_templates()\n"  # the reports' templates travel too
        "print(len(load_sources('bundled')), type(load_default()).__name__)\n"
    )
    env = dict(os.environ, PYTHONPATH=str(site), JAX_PLATFORMS="cpu")
    r = subprocess.run([sys.executable, "-c", check], cwd=elsewhere, env=env, capture_output=True, text=True)
    assert r.returncode == 0, r.stderr[-3000:]
    rows, kind = r.stdout.split()
    assert int(rows) > 100_000 and kind == "Emulator"
    r = subprocess.run(
        [sys.executable, "-m", "mfdesign.cli", "--version"], cwd=elsewhere, env=env, capture_output=True, text=True
    )
    assert r.returncode == 0 and r.stdout.startswith("mfdesign "), r.stderr
