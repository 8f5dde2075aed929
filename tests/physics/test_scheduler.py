"""Where plane jobs go (:mod:`mfdesign.physics.cluster`), without Dask: which scheduler is
named (argument, ``--scheduler``, ``MFDESIGN_SCHEDULER``), and a named one without Dask
installed is one line of bad input, before anything is solved. Dask itself is blocked here
(``sys.modules``), so these run whether or not it is installed; the cluster run is
tests/physics/test_planes_dask.py."""

from __future__ import annotations

import sys

import pytest
from typer.testing import CliRunner

from mfdesign.design import Membrane
from mfdesign.errors import InputError
from mfdesign.physics import cluster
from mfdesign.physics.params import SimParams


@pytest.fixture
def no_dask(monkeypatch):
    for name in ("distributed", "dask.distributed"):
        monkeypatch.setitem(sys.modules, name, None)  # import raises ImportError


def test_which_scheduler_is_named(monkeypatch):
    monkeypatch.delenv(cluster.SCHEDULER_ENV, raising=False)
    assert cluster.scheduler_from() is None  # nothing named: this machine
    monkeypatch.setenv(cluster.SCHEDULER_ENV, " ")
    assert cluster.scheduler_from() is None  # empty: this machine
    monkeypatch.setenv(cluster.SCHEDULER_ENV, "tcp://env:8786")
    assert cluster.scheduler_from() == "tcp://env:8786"
    assert cluster.scheduler_from("tcp://arg:1") == "tcp://arg:1"
    assert cluster.scheduler_from(False) is None  # here, whatever the environment says
    monkeypatch.setattr(cluster, "_distributed", lambda address: None)  # as if Dask were installed
    with cluster.use_scheduler("tcp://cli:2"):
        assert cluster.scheduler_from() == "tcp://cli:2"  # --scheduler wins over the environment
        assert cluster.scheduler_from(False) is None
    with cluster.use_scheduler(None):
        assert cluster.scheduler_from() == "tcp://env:8786"  # no --scheduler: the environment's


def test_a_scheduler_without_dask_is_one_line_before_any_solve(no_dask, monkeypatch):
    from mfdesign.physics import solve as sv

    with pytest.raises(InputError, match=r'Dask distributed is not installed; allowed: pip install "mfdesign\[dask\]"'):
        with cluster.use_scheduler("tcp://host:8786"):
            pass
    monkeypatch.setattr(sv, "force_plane", lambda *a, **k: pytest.fail("solved a plane"))
    monkeypatch.setenv(cluster.SCHEDULER_ENV, "tcp://host:8786")
    with pytest.raises(InputError, match="MFDESIGN_SCHEDULER"):
        sv.force_planes([(Membrane.from_key("[2.0, 25.4, nan, nan, nan, nan]"), SimParams())], [10.0], [1000.0])


def test_cli_scheduler_without_dask_exits_2_with_one_line(no_dask, tmp_path, monkeypatch):
    from mfdesign.cli import app

    monkeypatch.delenv(cluster.SCHEDULER_ENV, raising=False)
    res = CliRunner().invoke(
        app,
        ["calibrate", "mass-lift", "--physics", "standin", "--scheduler", "tcp://host:8786", "--out", str(tmp_path)],
    )
    assert res.exit_code == 2, res.output
    lines = res.output.strip().splitlines()
    assert len(lines) == 1 and lines[0].startswith("error: ") and "Dask distributed is not installed" in lines[0]


def test_prepare_worker_honours_the_workers_jax_platforms():
    """A worker spawned by a script that imports JAX at its top has imported JAX before Dask
    sets the worker's environment; prepare_worker (the preload) applies JAX_PLATFORMS then."""
    import subprocess

    code = (
        "import os; os.environ.pop('JAX_PLATFORMS', None); import jax; "
        "os.environ['JAX_PLATFORMS'] = 'cpu'; "  # what Dask's env= does, after the import
        "from mfdesign.physics.cluster import prepare_worker; prepare_worker(); "
        "print(jax.config.jax_platforms, jax.default_backend())"
    )
    out = subprocess.run([sys.executable, "-c", code], capture_output=True, text=True, check=True, timeout=120)
    assert out.stdout.split() == ["cpu", "cpu"]
