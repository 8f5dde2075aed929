"""The package's public names (``mfdesign/__init__.py``): light to import, documented, and
the functions stay functions when their namesake submodules are imported."""

from __future__ import annotations

import importlib
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
        where = mfdesign._WHERE.get(name)
        obj = getattr(importlib.import_module(where), name) if where else getattr(mfdesign, name)
        if inspect.isclass(obj):
            continue
        doc = obj.__doc__ or ""
        assert "Arguments:" in doc and "Returns:" in doc, f"mfdesign.{name} lacks an Arguments:/Returns: docstring"


def test_diagnose_and_optimize_are_the_functions_and_no_module_shares_their_names():
    """The public functions ``diagnose`` / ``optimize`` live in modules of other names
    (``mfdesign.diagnosis``, ``mfdesign.optimization``): importing those never rebinds the
    package's attributes (a subpackage named ``diagnose`` did, and needed a module-type swap)."""
    import mfdesign.diagnosis.residuals  # noqa: F401  (sets the package attribute, were it not kept)
    import mfdesign.optimization  # noqa: F401
    from mfdesign.diagnosis import pipeline
    from mfdesign.optimization import optimize

    assert mfdesign.diagnose is pipeline.diagnose
    assert mfdesign.optimize is optimize
    assert callable(sys.modules["mfdesign.optimization"].multistart)
    assert not hasattr(mfdesign, "_Facade") and type(sys.modules["mfdesign"]) is type(sys)


def test_load_bundled():
    meas = mfdesign.load()
    assert isinstance(meas, mfdesign.Measurements)
    assert len(meas.design_keys) == 6 and len(meas) > 100_000
