"""experiments/profile_compile.py's log parser on a made-up JAX compile log: XLA seconds,
tracing and lowering per stage and per function. No demo is run."""

from __future__ import annotations

import importlib.util
from pathlib import Path

ROOT = Path(__file__).resolve().parents[1]

LOG = """\
[   0.0 s] load data and force model ...
Finished tracing _plane_kernel for jit in 11.5 sec
Compiling jit(_plane_kernel) with global shapes and types (ShapedArray(float64[8]),).
Finished jaxpr to MLIR module conversion jit(_plane_kernel) in 1.25 sec
Finished XLA compilation of jit(_plane_kernel) in 12.0 sec
[  80.0 s] diagnose: where the model fails, which effect is missing ...
Finished tracing _fit_batch for jit in 2.5 sec
Finished jaxpr to MLIR module conversion jit(_fit_batch) in 0.5 sec
Finished XLA compilation of jit(_fit_batch) in 11.5 sec
Finished tracing _fit_batch for jit in 0.5 sec
Finished XLA compilation of jit(_fit_batch) in 1.0 sec
"""


def test_parse_sums_compile_tracing_and_lowering_per_stage_and_function(monkeypatch):
    monkeypatch.syspath_prepend(str(ROOT / "experiments"))  # its ``from _common import ...``
    spec = importlib.util.spec_from_file_location("profile_compile", ROOT / "experiments" / "profile_compile.py")
    mod = importlib.util.module_from_spec(spec)
    spec.loader.exec_module(mod)
    out = mod.parse(LOG.splitlines())
    load, diag = "load data and force model", "diagnose: where the model fails, which effect is missing"
    assert out["compile_s_total"] == 24.5 and out["compilations"] == 3
    assert out["per_stage_s"] == {load: 12.0, diag: 12.5}
    assert out["trace_s_per_stage"] == {load: 11.5, diag: 3.0}
    assert out["lower_s_per_stage"] == {load: 1.2, diag: 0.5}  # rounded to 0.1 s
    assert out["traced_per_function"][0] == {"function": "_plane_kernel", "seconds": 11.5}
    assert {"function": "_fit_batch", "seconds": 3.0} in out["traced_per_function"]
    assert out["recompiled"] == [{"function": "jit(_fit_batch)", "seconds": 12.5, "compilations": 2}]


def test_profile_callers_names_the_innermost_mfdesign_line_or_its_eager_caller(monkeypatch):
    """experiments/profile_callers.py's attribution: the innermost mfdesign frame, past the
    program store's wrapper; with ``outer``, past the force models and effects a caller ran
    eagerly. A stack without mfdesign is "?"."""
    import traceback

    monkeypatch.syspath_prepend(str(ROOT / "experiments"))
    spec = importlib.util.spec_from_file_location("profile_callers", ROOT / "experiments" / "profile_callers.py")
    mod = importlib.util.module_from_spec(spec)
    spec.loader.exec_module(mod)
    fs = traceback.FrameSummary
    stack = [
        fs("/x/mfdesign/workflows/demo.py", 10, "run_demo", lookup_line=False),
        fs("/x/mfdesign/diagnosis/refit.py", 137, "_bic", lookup_line=False),
        fs("/x/mfdesign/models/exact.py", 103, "_contract", lookup_line=False),
        fs("/x/mfdesign/physics/_traces.py", 50, "call", lookup_line=False),
        fs("/x/site-packages/jax/_src/dispatch.py", 1, "apply_primitive", lookup_line=False),
    ]
    assert mod.site_of(stack) == "models/exact.py:103 _contract"
    assert mod.site_of(stack, outer=True) == "diagnosis/refit.py:137 _bic"
    assert mod.site_of(stack[-1:]) == "?"
