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


def _rows(h, p, is_force):
    n = len(h)
    return fx.Rows(
        jnp.asarray(h, float),
        jnp.asarray(p, float),
        jnp.asarray(is_force),
        jnp.zeros(n, bool),
        jnp.zeros(n, bool),
        jnp.zeros(n, jnp.int32),
    )


def test_the_docs_show_the_file_as_it_is():
    doc = (ROOT / "docs" / "effects.md").read_text()
    assert EXAMPLE.read_text() in doc
    assert len(EXAMPLE.read_text().splitlines()) <= 35  # "about 30 lines"


def test_the_example_registers_and_acts_on_both_sides():
    cls = _load()
    e = fx.effect("lift_height_offset")
    assert isinstance(e, cls) and e.acts_on_measurement and not e.acts_on_mechanics
    h, p = np.array([10.0, 20.0]), np.array([3000.0, 4000.0])
    # the virtual rig: a plate in equilibrium at a true 30 mm (F = 100 - h N under W = 70 N)
    # is recorded 1.5 mm high in a lift; neutral: where it is
    law = lambda hh, pp: 100.0 - hh  # noqa: E731
    lift = _rows(h, p, [False, False])
    recorded = fx.recorded_lift_height([e], {"lift_height_offset.offset_mm": 1.5}, law, lift, 70.0, 20.0)
    assert np.allclose(recorded, 31.5)
    assert np.allclose(fx.recorded_lift_height([e], fx.neutral_theta([e]), law, lift, 70.0, 20.0), 30.0)
    # the likelihood: a lift row recorded at h sees the force of h - offset; force rows untouched
    expected = e.expected_force({"offset_mm": 1.5}, law, _rows(h, p, [False, True]))
    assert np.allclose(expected, [100.0 - 8.5, 100.0 - 20.0])
    np.testing.assert_array_equal(e.expected_force(e.neutral(), law, lift), law(h, p))
