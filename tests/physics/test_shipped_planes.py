"""The planes shipped with the package (``mfdesign/data/files/planes.npz``, written by
``python -m tools.ship_planes``): the demo's force model of the bundled membranes is built
from them without solving a plane, they are what the simulator solves today, and they are
read only where a disk cache is (issue 40: 72 planes, ~190 s of a lab's first demo)."""

from __future__ import annotations

import numpy as np
import pytest

from mfdesign.calibration.workflow import force_model_named
from mfdesign.data.shipped import bundled_path
from mfdesign.data.store import read_parquet
from mfdesign.design import Membrane
from mfdesign.physics import planes as pl
from mfdesign.physics import solve
from mfdesign.physics.params import SimParams


def _no_solving(*args, **kwargs):
    raise AssertionError(
        "a plane was solved: the shipped planes lack one the demo asks for (python -m tools.ship_planes)"
    )


@pytest.fixture
def empty_cache(tmp_path, monkeypatch):
    monkeypatch.setenv("MFDESIGN_CACHE_DIR", str(tmp_path))
    monkeypatch.delenv(pl.SHIPPED_ENV, raising=False)
    monkeypatch.setattr(pl, "_MEMO", {})  # nothing from planes other tests solved
    return tmp_path


def test_the_demo_force_model_of_the_bundled_membranes_solves_no_plane(empty_cache, monkeypatch):
    monkeypatch.setattr(solve, "force_planes", _no_solving)
    meas = read_parquet(bundled_path())
    fm = force_model_named("exact", meas)
    assert len(fm.design_keys) == len(meas.design_keys) == 6
    assert np.isfinite(np.asarray(fm.tensor)).any()
    assert not (empty_cache / "planes").exists() or not any((empty_cache / "planes").iterdir())  # none solved


def _base_job(meas):
    """The bundled dataset's first ringless membrane at the authors' constants, on the
    demo's grid (as force_model_named builds it), and its key."""
    fm = force_model_named("exact", meas)
    design = next(Membrane.from_key(k) for k in fm.design_keys if Membrane.from_key(k).n_rings == 0)
    return design, fm.grid, pl._job_key(design, SimParams(), fm.grid)


def test_switched_off_or_without_a_disk_cache_the_planes_are_solved(empty_cache, monkeypatch):
    meas = read_parquet(bundled_path())
    design, grid, key = _base_job(meas)
    assert pl.shipped_plane(key) is not None
    monkeypatch.setattr(pl, "_MEMO", {})
    monkeypatch.setattr(solve, "force_planes", _no_solving)
    with pytest.raises(AssertionError, match="a plane was solved"):
        pl.solve_planes([(design, SimParams())], grid, cache=False)  # no disk cache: no shipped planes
    monkeypatch.setenv(pl.SHIPPED_ENV, "0")
    assert pl.shipped_plane(key) is None
    with pytest.raises(AssertionError, match="a plane was solved"):
        pl.solve_planes([(design, SimParams())], grid)


@pytest.mark.slow
def test_a_shipped_plane_is_what_the_simulator_solves_today(empty_cache, monkeypatch):
    """Fails where the solver changed a plane and ``planes.SCHEMA`` was not bumped (then
    the pack, and every lab's cache, hold stale planes)."""
    meas = read_parquet(bundled_path())
    design, grid, key = _base_job(meas)
    shipped = pl.shipped_plane(key)
    monkeypatch.setattr(pl, "_MEMO", {})  # _base_job read it from the pack
    (fresh,) = pl.solve_planes([(design, SimParams())], grid, cache=False)
    assert shipped is not None and shipped.shape == fresh.shape
    np.testing.assert_array_equal(np.isfinite(shipped), np.isfinite(fresh))
    np.testing.assert_allclose(shipped, fresh, rtol=1e-6, atol=1e-6, equal_nan=True)


def test_ship_planes_packs_a_cache_folder_as_the_solver_reads_it(tmp_path):
    from tools.ship_planes import pack

    planes = tmp_path / "cache" / "planes"
    planes.mkdir(parents=True)
    want = {"a" * 24: np.arange(6.0).reshape(2, 3), "b" * 24: np.full((2, 3), np.nan)}
    for k, v in want.items():
        np.save(planes / f"{k}.npy", v)
    np.save(planes / ".torn.123.npy", np.zeros(1))  # a plane being written: left out
    assert pack([tmp_path / "cache"], dest=tmp_path / "planes.npz") == 2
    with np.load(tmp_path / "planes.npz", allow_pickle=False) as got:
        assert sorted(got.files) == sorted(want)
        for k, v in want.items():
            np.testing.assert_array_equal(got[k], v)
