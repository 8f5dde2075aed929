"""A plane's unconverged nodes repaired by the FE reference (planes._repair): a height whose
nodes failed in a run walks its inflation once (fe_rows), a stray node is solved alone
(fe_forces), and both give the FE reference's own numbers (issue 40)."""

from __future__ import annotations

import numpy as np

from mfdesign.design import Membrane
from mfdesign.physics import fe
from mfdesign.physics import planes as pl
from mfdesign.physics.params import SimParams
from mfdesign.physics.status import Status


def test_a_failed_row_walks_its_inflation_once_and_a_stray_node_goes_alone(monkeypatch):
    design, params = Membrane.from_key("[2.0, 25.4, nan, nan, nan, nan]"), SimParams()
    grid = pl.PlaneGrid.covering(15.0, 1000.0)  # h 0 .. 17.5 mm, p 250 .. 2000 Pa
    H, P = np.meshgrid(grid.h, grid.p[1:], indexing="ij")
    f = np.full(H.shape, 1.0)
    status = np.full(H.shape, int(Status.OK))
    row = int(np.flatnonzero(grid.h == 10.0)[0])
    f[row], status[row] = np.nan, int(Status.ODE_FAILURE)  # a whole row the shooting lost
    f[2, 3], status[2, 3] = np.nan, int(Status.ODE_FAILURE)  # and one stray node
    calls = []
    for name in ("fe_rows", "fe_forces"):
        real = getattr(fe, name)
        monkeypatch.setattr(fe, name, lambda *a, _real=real, _name=name, **k: calls.append(_name) or _real(*a, **k))

    pl._repair(design, params, grid, f, status)

    assert calls == ["fe_rows", "fe_forces"]  # the row walked, the stray node alone
    assert np.isfinite(f).all()
    want = fe.fe_forces(
        [(design, params)], [np.append(H[row], H[2, 3])], [np.append(P[row], P[2, 3])], n_elements=pl.FE_ELEMENTS
    )[0]
    np.testing.assert_allclose(np.append(f[row], f[2, 3]), want.force_n, rtol=1e-8, atol=1e-8)
    assert (f[np.arange(f.shape[0]) != row] == 1.0).sum() == f.size - f.shape[1] - 1  # nothing else touched
