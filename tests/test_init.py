"""The package's public names (``mfdesign/__init__.py``): light to import, documented, and
the functions stay functions when their namesake submodules are imported."""

from __future__ import annotations

import inspect
import subprocess
import sys
from pathlib import Path

import mfdesign

ROOT = Path(__file__).resolve().parents[1]


def test_import_is_light():
    """``import mfdesign`` (and the CLI's ``--help``) must not import JAX."""
    code = "import sys, mfdesign; assert 'jax' not in sys.modules, 'import mfdesign imported jax'"
    r = subprocess.run([sys.executable, "-c", code], cwd=ROOT, capture_output=True, text=True)
    assert r.returncode == 0, r.stderr


def test_every_public_function_has_arguments_and_returns():
    for name in mfdesign.__all__:
        obj = getattr(mfdesign, name)
        if inspect.isclass(obj):
            continue
        doc = obj.__doc__ or ""
        assert "Arguments:" in doc and "Returns:" in doc, f"mfdesign.{name} lacks an Arguments:/Returns: docstring"


def test_submodules_do_not_hide_functions():
    from mfdesign.diagnose import pipeline
    from mfdesign.optimize import TARGET_SETS  # noqa: F401  (imports the submodule mfdesign.optimize)

    assert mfdesign.diagnose is pipeline.diagnose
    assert callable(mfdesign.optimize) and inspect.isfunction(mfdesign.optimize)
    assert sys.modules["mfdesign.optimize"].optimize is mfdesign.optimize


def test_load_bundled():
    meas = mfdesign.load()
    assert isinstance(meas, mfdesign.Measurements)
    assert len(meas.design_keys) == 6 and len(meas) > 100_000
