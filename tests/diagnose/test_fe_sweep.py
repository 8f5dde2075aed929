"""The held-out FE-truth sweep, reduced (issue 39): data made by the FE reference, not the
simulator the diagnosis runs on, with a clean control, a pair (thickness -15 % and a
load-cell offset) and a contact offset closing a 3.5 mm rubber gap to 0.5 mm.

Full sweep: ``python experiments/hidden_effects.py --truth fe`` (experiments/out/hidden_effects_fe.json).
Planes (the rig's FE truth and the exact model's) are content-keyed in the default caches.
"""

from __future__ import annotations

import argparse
import importlib.util
from pathlib import Path

import pytest

ROOT = Path(__file__).resolve().parents[2]


@pytest.mark.slow
def test_reduced_fe_truth_sweep(tmp_path, monkeypatch):
    monkeypatch.syspath_prepend(str(ROOT / "experiments"))
    spec = importlib.util.spec_from_file_location("hidden_effects", ROOT / "experiments" / "hidden_effects.py")
    he = importlib.util.module_from_spec(spec)
    spec.loader.exec_module(he)
    args = argparse.Namespace(out=tmp_path, reduced=True, cases=None)
    summary = he.main_fe(args)
    assert (tmp_path / "hidden_effects_fe_reduced.json").is_file()
    assert (tmp_path / "hidden_effects_fe_reduced.png").is_file()
    assert summary["not_evaluated_candidates"] == 0, summary
    assert summary["clean_claims"] == 0, summary
    assert summary["pairs_right"] == 1.0, summary["table"]
    assert summary["right_set"] == 1.0, summary["table"]
    assert summary["right_cases_max_heldout_over_noise"] <= 1.2, summary["table"]
