"""The new-effect example of docs/effects.md, run as the file it is."""

from __future__ import annotations

import importlib.util
from pathlib import Path

import jax.numpy as jnp
import numpy as np

from mfdesign.physics import effects as fx

ROOT = Path(__file__).resolve().parents[2]
EXAMPLE = ROOT / "docs" / "examples" / "lift_height_offset.py"


def _load():
    if "lift_height_offset" in fx.EFFECTS:
        return fx.EFFECTS["lift_height_offset"]
    spec = importlib.util.spec_from_file_location("lift_height_offset", EXAMPLE)
    mod = importlib.util.module_from_spec(spec)
    spec.loader.exec_module(mod)
    return mod.LiftHeightOffset


def test_the_docs_show_the_file_as_it_is():
    doc = (ROOT / "docs" / "effects.md").read_text()
    assert EXAMPLE.read_text() in doc
    assert len(EXAMPLE.read_text().splitlines()) <= 35  # "about 30 lines"


def test_the_example_registers_and_acts_on_both_sides():
    cls = _load()
    e = fx.effect("lift_height_offset")
    assert isinstance(e, cls) and e.acts_on_measurement and e.has_likelihood and not e.acts_on_mechanics
    h, p, f = np.array([10.0, 20.0]), np.array([3000.0, 4000.0]), np.array([14.715, 14.715])
    sample = fx.Sample(h, p, f)
    lift = fx.Context(experiment="lift", trial_index=0, phase=np.array(["inflate"] * 2))
    force = fx.Context(experiment="force", trial_index=0, phase=np.array(["inflate"] * 2))
    # the virtual rig: lifts read high by the offset, force trials untouched; neutral: identity
    assert np.allclose(e.observe({"offset_mm": 1.5}, sample, lift).height_mm, h + 1.5)
    assert np.array_equal(e.observe({"offset_mm": 1.5}, sample, force).height_mm, h)
    assert np.array_equal(e.observe(e.neutral(), sample, lift).height_mm, h)
    # the likelihood: a lift row recorded at h sees the force of h - offset
    rows = fx.Rows(
        jnp.asarray(h),
        jnp.asarray(p),
        jnp.array([False, True]),
        jnp.zeros(2, bool),
        jnp.zeros(2, bool),
        jnp.zeros(2, jnp.int32),
    )
    expected = e.expected_force({"offset_mm": 1.5}, lambda hh, pp: 100.0 - hh, rows)
    assert np.allclose(expected, [100.0 - 8.5, 100.0 - 20.0])
