"""Where a calibrated effect's lattice axis goes (``force_model_named(effect_axes=...)``): the
three choices build the lattice they promise, and the middle one ("tensor-jm") stays close to
the simulator where the material and the effect move together."""

from __future__ import annotations

import types

import jax.numpy as jnp
import numpy as np
import pandas as pd
import pytest

from mfdesign.calibration.workflow import EFFECT_AXES, force_model_named
from mfdesign.design import Membrane
from mfdesign.physics.params import SimParams
from mfdesign.physics.solve import force_at

KEY = "[1.5, 30.0, 45.0, 6.0, nan, nan]"  # one ring: the ring ratio acts


@pytest.fixture()
def table(tmp_path, monkeypatch):
    monkeypatch.setenv("MFDESIGN_CACHE_DIR", str(tmp_path))  # planes of this test only
    df = pd.DataFrame(
        {
            "design_key": [KEY] * 2,
            "height_mm": [5.0, 30.0],
            "height_set_mm": [np.nan] * 2,
            "pressure_pa": [800.0, 4000.0],
        }
    )
    return types.SimpleNamespace(df=df)


def _axes(fm):
    return [a.name for a in fm.tensor_axes], [a.name for a in fm.additive_axes]


@pytest.mark.slow  # minutes of plane solves on 2 cores (the default suite stays near 15 minutes)
def test_tensor_jm_crosses_the_effect_with_jm_and_adds_the_ring_ratio(table):
    params = SimParams(mu_pa=28.0e3, jm=33.0, fabric_inset_mm=0.4)  # mu moves the ring ratio too
    fm = force_model_named("exact", table, effect_axes="tensor-jm").covering(params).strict(True)
    assert _axes(fm) == (["jm", "inset"], ["ring"])
    d = Membrane.from_key(KEY)
    h, p = np.array([4.0, 12.0, 25.0]), np.array([1500.0, 3000.0, 4500.0])
    got = np.asarray(fm(jnp.broadcast_to(jnp.asarray(d.to_array()), (3, 6)), jnp.asarray(h), jnp.asarray(p), params))
    ref = np.asarray(force_at(d, h, p, params).force_n)
    assert np.all(np.isfinite(got)) and np.all(np.isfinite(ref))
    # the ring ratio's cross terms only (the rubber moved 12 % from the reference)
    assert np.max(np.abs(got - ref)) <= 0.15, got - ref


def test_the_other_choices_and_a_bad_one(table):
    params = SimParams(jm=36.0, fabric_inset_mm=0.3)
    add = force_model_named("exact", table, effect_axes="additive").covering(params)
    assert _axes(add) == (["jm", "ring"], ["inset"])
    ten = force_model_named("exact", table, effect_axes="tensor").covering(params)
    assert set(_axes(ten)[0]) == {"jm", "inset"} and _axes(ten)[1] == []
    assert set(EFFECT_AXES) == {"tensor", "tensor-jm", "additive"}
    with pytest.raises(ValueError, match="effect_axes must be one of"):
        force_model_named("exact", table, effect_axes="crossed")
