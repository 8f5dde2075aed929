"""Safe loaders for ../shared/data/spa_design: restricted unpickling and the real files."""

from __future__ import annotations

import os
import pickle

import numpy as np
import pytest

from mfdesign.data import (
    Measurements,
    SharedDataMissing,
    UnsafePickleError,
    load_mass_lift,
    load_sim_planes,
    restricted_load,
    restricted_loads,
    shared_data_dir,
    sim_planes_as_measurements,
)
from mfdesign.data import spa_design


def _shared_dir():
    try:
        return shared_data_dir()
    except SharedDataMissing as err:
        pytest.skip(f"shared SPA_Design data not available: {err}")


@pytest.fixture(scope="module")
def mass_lift():
    _shared_dir()
    return load_mass_lift()


@pytest.fixture(scope="module")
def planes():
    _shared_dir()
    return load_sim_planes()


# -- restricted unpickler (no shared data needed) -----------------------------------------
class _Evil:
    def __init__(self, target):
        self.target = target

    def __reduce__(self):
        return (os.system, (f"touch {self.target}",))


def test_malicious_pickle_is_refused(tmp_path):
    target = tmp_path / "pwned"
    evil = tmp_path / "evil.pkl"
    evil.write_bytes(pickle.dumps({"F": _Evil(target)}))
    with pytest.raises(UnsafePickleError) as err:
        restricted_load(evil)
    assert "system" in str(err.value) and "only NumPy arrays" in str(err.value)
    assert not target.exists()
    assert isinstance(err.value, pickle.UnpicklingError)


@pytest.mark.parametrize(
    "payload",
    [
        pickle.dumps(eval),
        pickle.dumps(getattr),
        pickle.dumps(np.asarray([1, "a"], dtype=object)),
        pickle.dumps(np.load),
    ],
)
def test_other_globals_and_object_arrays_are_refused(payload):
    with pytest.raises(UnsafePickleError):
        restricted_loads(payload)


def test_numpy_arrays_in_containers_load(tmp_path):
    data = {"a": (np.arange(5, dtype=np.float32), [np.eye(2)]), "b": 3}
    out = restricted_loads(pickle.dumps(data))
    assert np.array_equal(out["a"][0], data["a"][0]) and out["a"][0].dtype == np.float32
    assert np.array_equal(out["a"][1][0], np.eye(2)) and out["b"] == 3


def test_jax_array_pickle_loads_as_numpy():
    jnp = pytest.importorskip("jax.numpy")
    arr = jnp.arange(6.0).reshape(2, 3)
    out = restricted_loads(pickle.dumps([arr]))
    assert type(out[0]) is np.ndarray and np.array_equal(out[0], np.arange(6.0).reshape(2, 3))


def test_missing_shared_data_message(tmp_path, monkeypatch):
    monkeypatch.setenv(spa_design.ENV_VAR, str(tmp_path / "nowhere"))
    with pytest.raises(SharedDataMissing) as err:
        shared_data_dir()
    assert "nowhere" in str(err.value) and spa_design.ENV_VAR in str(err.value)
    assert isinstance(err.value, FileNotFoundError)
    with pytest.raises(SharedDataMissing):
        load_mass_lift()
    monkeypatch.setenv(spa_design.ENV_VAR, str(tmp_path))
    assert shared_data_dir() == tmp_path
    with pytest.raises(SharedDataMissing, match="sim_membranes.pkl"):
        load_sim_planes()


def test_default_dir_is_beside_the_repo(monkeypatch):
    monkeypatch.delenv(spa_design.ENV_VAR, raising=False)
    package = os.path.dirname(os.path.dirname(os.path.abspath(spa_design.__file__)))  # mfdesign/
    repo = os.path.dirname(package)
    expected = os.path.join(os.path.dirname(repo), "shared", "data", "spa_design")
    assert str(shared_data_dir(must_exist=False)) == os.path.normpath(expected)


# -- the real files -----------------------------------------------------------------------
def test_mass_lift_counts_and_schema(mass_lift):
    m = mass_lift
    assert isinstance(m, Measurements)
    assert len(m) == 45_924
    assert len(m.design_keys) == 7
    df = m.df
    assert set(df["experiment"]) == {"lift"} and set(df["source"]) == {"file"}
    assert set(df["phase"]) == {"inflate"}
    assert df["time_s"].isna().all() and df["height_set_mm"].isna().all()
    assert np.allclose(sorted(df["force_n"].unique()), [14.715, 24.525, 39.24], atol=1e-4)
    # two runs per (membrane, mass): six trials per membrane, one mass each
    per = df.groupby(["design_key", "trial"])["force_n"].nunique()
    assert (per == 1).all() and len(per) == 42
    assert (df.groupby("design_key")["trial"].nunique() == 6).all()
    assert "[2.0, 31.92, 46.0, 5.0, 59.0, 5.0]" in m.design_keys
    assert df["height_mm"].between(0, 80).all()


def test_sim_planes_label_fix(planes):
    assert len(planes) == 18
    ringless = [(p.design.thickness_mm, p.design.contact_radius_mm) for p in planes[:6]]
    assert ringless == list(spa_design.RINGLESS_ORDER)
    assert all(p.design.n_rings == 0 for p in planes[:6])
    assert planes[0].design.key() == "[1.0, 25.4, nan, nan, nan, nan]"
    assert planes[0].label_in_file == "[1.0, 38.1, nan, nan, nan, nan]"
    assert all(p.design.n_rings == 2 for p in planes[6:])
    assert len({p.design.key() for p in planes}) == 18
    for p in planes:
        assert p.force_n.shape == p.pressure_pa.shape == p.height_mm.shape
        assert 0.9 < p.height_mm.min() and p.height_mm.max() < 150  # converted m -> mm


def test_sim_planes_as_measurements(planes):
    m = sim_planes_as_measurements()
    assert len(m.design_keys) == 18 and len(m) == sum(len(p) for p in planes)
    df = m.df
    assert set(df["experiment"]) == {"force"} and set(df["source"]) == {"simulated"}
    assert df.groupby("design_key")["trial"].nunique().eq(1).all()


def test_label_check_refuses_unexpected_names():
    names = ["[3.0, 25.4, nan, nan, nan, nan]"] * 6
    with pytest.raises(ValueError, match="known upstream shift"):
        spa_design._fixed_designs(names, "test")
