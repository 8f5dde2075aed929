"""Simulator planes on a Dask cluster (issue 40, item 5): a ``LocalCluster`` of two worker
processes (one thread each, started as the docs say: ``--preload mfdesign.physics.cluster``)
solves the same planes as this process, bit for bit, and its workers write them into the
plane cache. Skipped without Dask (``pip install -e ".[dask]"``).

Cost: each worker process compiles the walk kernel once (tens of seconds on a CPU), so
the grid is small (heights 0-10 mm, pressures 0-1 kPa: the low-row descent, the
continuation and the repair of unconverged nodes all run) and the first plane goes alone:
its worker stores the compiled kernels in the shared compilation cache
(``$MFDESIGN_CACHE_DIR``), from which the other worker loads them."""

from __future__ import annotations

import numpy as np
import pytest

from mfdesign.design import Membrane
from mfdesign.errors import InputError
from mfdesign.physics import cluster as cl
from mfdesign.physics import planes as pl
from mfdesign.physics.params import SimParams

distributed = pytest.importorskip("dask.distributed")

KEYS = ("[2.0, 25.4, nan, nan, nan, nan]", "[1.5, 30.0, nan, nan, nan, nan]", "[2.0, 25.4, 40.0, 3.0, nan, nan]")
GRID = pl.PlaneGrid(10.0, 1000.0)


@pytest.fixture(scope="module")
def shared(tmp_path_factory):
    return tmp_path_factory.mktemp("shared")  # the workers' MFDESIGN_CACHE_DIR


@pytest.fixture(scope="module")
def cluster(shared):
    with distributed.LocalCluster(
        n_workers=2,
        threads_per_worker=1,
        processes=True,
        dashboard_address=None,
        preload=["mfdesign.physics.cluster"],
        # no shipped kernels: a worker would pad these small planes onto a shipped kernel's
        # larger shape, equal to the own-shape plane only to ~1e-14 N (CI on 8ea2ce8: 10 of
        # 25 nodes differed by up to 8e-15 N), and this test compares bit for bit
        env={"JAX_PLATFORMS": "cpu", "MFDESIGN_CACHE_DIR": str(shared), "MFDESIGN_SHIPPED_KERNELS": "0"},
    ) as c:
        yield c


def test_planes_on_a_local_cluster_equal_the_local_ones(cluster, shared, tmp_path, monkeypatch, caplog):
    from mfdesign.physics import _traces, solve

    jobs = [(Membrane.from_key(k), SimParams()) for k in KEYS]
    monkeypatch.setattr(pl, "_MEMO", {})
    # Like a fresh worker: no program of an earlier test to pad these planes onto (a padded
    # plane equals its own-shape plane only to ~1e-14 N: XLA vectorises other batch sizes
    # otherwise; CI on d0c2767 saw 2 of 25 nodes differ by 7e-15 N).
    monkeypatch.setattr(solve, "KEPT", solve.KeptPrograms())
    monkeypatch.setattr(_traces, "folder", lambda: None)
    here = pl.solve_planes(jobs, GRID, cache=tmp_path / "here", scheduler=False)

    monkeypatch.setattr(pl, "_MEMO", {})
    monkeypatch.setenv("MFDESIGN_SCHEDULER", cluster.scheduler_address)  # the environment names it
    caplog.set_level("WARNING", logger="mfdesign.physics.planes")
    folder = tmp_path / "cluster"
    first = pl.solve_planes(jobs[:1], GRID, cache=folder)  # one worker compiles, and stores the programs
    assert any(shared.glob("jit__walk_kernel*"))  # in the compilation cache the other worker reads
    there = pl.solve_planes(jobs, GRID, cache=folder, progress=True)  # the bar follows the tasks

    np.testing.assert_array_equal(first[0], here[0])
    for a, b in zip(here, there):
        assert a.shape == (GRID.h.size, GRID.p.size)
        np.testing.assert_array_equal(a, b)
    # every plane was written into the cache by its worker (none was missing afterwards)
    assert "do not see this folder" not in caplog.text
    assert sorted(f.name for f in folder.glob("*.npy")) == sorted(f.name for f in (tmp_path / "here").glob("*.npy"))
    for f in folder.glob("*.npy"):
        np.testing.assert_array_equal(np.load(f), np.load(tmp_path / "here" / f.name))


def test_a_scheduler_that_does_not_answer_is_bad_input(monkeypatch):
    monkeypatch.setattr(cl, "CONNECT_TIMEOUT_S", 1)
    monkeypatch.setattr(pl, "_MEMO", {})
    job = (Membrane.from_key(KEYS[0]), SimParams(jm=41.0))
    with pytest.raises(InputError, match="no scheduler answered"):
        pl.solve_planes([job], GRID, cache=False, scheduler="tcp://127.0.0.1:9")
