"""The lattice box of a set of constants (exact._box_of): one jitted program per padded
size (issue 40: the axes' jnp ops ran eagerly, ~30 small compilations a demo)."""

import math

import numpy as np
import pytest

from mfdesign.models.exact import _box_of
from mfdesign.physics.params import SimParams


def test_box_of_mixed_shapes_is_each_axis_coordinate_range():
    rng = np.random.default_rng(0)
    base = SimParams()
    jm = base.jm * np.exp(rng.normal(0, 0.1, 7))  # per draw [K]
    ring = base.ring_mu_pa * np.exp(rng.normal(0, 0.3, (7, 5)))  # per draw and row [K, N]
    offset = np.array([np.nan, 1.0, 2.0, 3.0, 4.0, 5.0, 6.0])  # NaN: not a coordinate
    params = SimParams(jm=jm, ring_mu_pa=ring, contact_offset_mm=offset)
    box = _box_of(params, base, True, {"jm"})
    assert set(box) == {"jm", "ring", "offset"}
    assert box["jm"] == pytest.approx((math.log(jm.min() / base.jm), math.log(jm.max() / base.jm)), rel=1e-12)
    assert box["ring"] == pytest.approx((np.log(ring / base.ring_mu_pa).min(), np.log(ring / base.ring_mu_pa).max()))
    assert box["offset"] == (1.0, 6.0)
    assert "ring" not in _box_of(params, base, False)  # no ringed design: no ring axis
    assert _box_of(base, base, False, {"jm"}) == {"jm": (0.0, 0.0)}  # scalars; a zero axis only when named
    assert _box_of(SimParams(jm=np.zeros(0)), base, True) == {}
