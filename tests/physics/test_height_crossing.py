"""height_at's vectorised bookkeeping equals the straightforward per-query reading of the rules."""

import numpy as np
import pytest

from mfdesign.physics.solve import _first_crossing
from mfdesign.physics.status import Status


def _reference(F, p, Fh):
    n_q = F.size
    height = np.full(n_q, np.nan)
    status = np.full(n_q, int(Status.NOT_CONVERGED), dtype=np.int8)
    lo = np.zeros(n_q, int)
    refine = np.zeros(n_q, bool)
    above = Fh >= F[:, None]
    for i in range(n_q):
        row_ok = np.isfinite(Fh[i])
        if not (np.isfinite(F[i]) and np.isfinite(p[i]) and p[i] >= 0 and F[i] >= 0):
            status[i] = Status.INVALID_INPUT
            continue
        ok_idx = np.nonzero(row_ok)[0]
        if ok_idx.size == 0:
            continue
        start = ok_idx[0]
        if not above[i, start]:
            if start == 0:
                height[i], status[i] = 0.0, Status.NOT_LIFTED
            continue
        below = np.nonzero(~above[i, start:] & row_ok[start:])[0]
        if below.size == 0 and row_ok[start:].all():
            status[i] = Status.BEYOND_GRID  # above the load up to the top of the grid
            continue
        if below.size == 0 or not row_ok[start : start + below[0] + 1].all():
            continue
        lo[i], refine[i], status[i] = start + below[0] - 1, True, Status.OK
    return height, status, lo, refine


def test_first_crossing_matches_reference_on_random_tables():
    rng = np.random.default_rng(3)
    n_q, n_h = 4000, 12
    # Decreasing force rows with holes (NaN), loads around them, some bad inputs.
    Fh = np.sort(rng.uniform(0, 100, (n_q, n_h)), axis=1)[:, ::-1].copy()
    Fh[rng.random((n_q, n_h)) < 0.15] = np.nan
    F = rng.uniform(-5, 110, n_q)
    F[rng.random(n_q) < 0.02] = np.nan
    p = rng.uniform(-100, 10_000, n_q)
    got = _first_crossing(F, p, Fh)
    want = _reference(F, p, Fh)
    np.testing.assert_array_equal(got[1], want[1])
    np.testing.assert_array_equal(got[3], want[3])
    np.testing.assert_array_equal(got[2][want[3]], want[2][want[3]])
    np.testing.assert_array_equal(np.isnan(got[0]), np.isnan(want[0]))
    # Every outcome occurs, so the comparison covers every branch.
    assert set(np.unique(want[1])) == {
        Status.OK,
        Status.NOT_LIFTED,
        Status.NOT_CONVERGED,
        Status.INVALID_INPUT,
        Status.BEYOND_GRID,
    }


def _interpolate_only(design, params, Fq, pq, Fh, hgrid, lo_idx, refine, height, status, a_grid=None):
    """``_refine_crossings`` without the simulator: the bracket's linear interpolation."""
    idx = np.nonzero(refine)[0]
    j = lo_idx[idx]
    f0, f1 = Fh[idx, j], Fh[idx, j + 1]
    height[idx] = hgrid[j] + (f0 - Fq[idx]) / (f0 - f1) * (hgrid[1] - hgrid[0])


def test_lift_curve_flags_a_jump_over_a_dip(monkeypatch):
    """A synthetic plane whose force dips below the load between two branches: as the
    pressure rises the first crossing jumps past the dip; that pressure is SNAP_THROUGH."""
    from types import SimpleNamespace

    from mfdesign.design import Membrane
    from mfdesign.physics import solve

    hg = np.linspace(0.0, 100.0, 41)
    p = np.linspace(1000.0, 5000.0, 9)
    # F(h, p) = p/100 * (1 - h/100) + a bump centred at 60 mm (the far branch).
    F = p[None, :] / 100.0 * (1.0 - hg[:, None] / 100.0) + 25.0 * np.exp(-(((hg[:, None] - 60.0) / 10.0) ** 2))

    def fake_plane(design, h, pp, params):
        return SimpleNamespace(force_n=F, status=np.zeros(F.shape, np.int8))

    monkeypatch.setattr(solve, "force_plane", fake_plane)
    monkeypatch.setattr(solve, "_refine_crossings", _interpolate_only)
    h, st = solve.lift_curve(Membrane.from_key("[2.0, 25.4, nan, nan, nan, nan]"), 20.0, p)
    jump = np.argmax(np.diff(h)) + 1
    assert np.diff(h)[jump - 1] > 20.0  # the plate leaps onto the far branch
    assert st[jump] == Status.SNAP_THROUGH
    assert np.sum(st == Status.SNAP_THROUGH) == 1
    assert np.all(np.isin(st, [Status.OK, Status.SNAP_THROUGH, Status.NOT_LIFTED]))


@pytest.mark.slow
def test_lift_curve_agrees_with_height_at_on_the_simulator(monkeypatch):
    """lift_curve starts each fixed-force solve from a path solved at the guessed height;
    height_at from the states its plane solved (no path again, no program of its own)."""
    from mfdesign.design import Membrane
    from mfdesign.physics import solve
    from mfdesign.physics.solve import force_at, height_at, lift_curve

    # A ringed paper membrane: it lifts 25 N from ~3 to ~67 mm over 3.7-7 kPa. (The ringless
    # 2 mm one pushes more than 25 N at every height of the 0-100 mm grid above 4 kPa: no
    # crossing to compare, both functions say BEYOND_GRID there.)
    d = Membrane.from_key("[2.0, 25.4, 49.0, 5.0, 62.0, 5.0]")
    p = np.linspace(3000.0, 7000.0, 7)
    h, st = lift_curve(d, 25.0, p)
    paths, path_guess = [], solve._a_guess
    monkeypatch.setattr(solve, "_a_guess", lambda *a: paths.append(a) or path_guess(*a))
    h2, st2 = height_at(d, np.full(p.size, 25.0), p)
    assert not paths  # every bracket had its two states
    ok = (st == Status.OK) & (st2 == Status.OK)
    assert ok.sum() >= 4
    np.testing.assert_allclose(h[ok], h2[ok], atol=1e-3)
    # And the force there is the load.
    f = force_at(d, h[ok], p[ok]).force_n
    np.testing.assert_allclose(f, 25.0, rtol=1e-3)


def test_height_at_reads_outside_model_nodes_as_above_the_load(monkeypatch):
    """A thin membrane with a large disk balloons past the clamp at low plate heights
    (OUTSIDE_MODEL: F > p pi R^2, force NaN) and lifts its loads past 100 mm: those nodes
    push harder than any load below p pi R^2, so the crossing above them is found (it was
    NOT_CONVERGED: a gap below the crossing). A NaN node of any other status still is a gap."""
    from types import SimpleNamespace

    from mfdesign.design import Membrane
    from mfdesign.physics import solve

    hg = np.linspace(0.0, 120.0, 25)
    row = np.where(hg >= 70.0, 100.0 - 0.9 * np.clip(hg - 70.0, 0.0, None) ** 1.2, np.nan)
    row[0] = 99.0

    def fake_plane(status_between):
        """The plane's nodes: ``row`` at every pressure, NaN nodes of ``status_between``;
        a node solved again point by point stays unsolved."""

        def classify(H, P, sol, signed=False, outer_radius_mm=70.0):
            F = np.broadcast_to(row[:, None], H.shape).copy()
            st = np.where(np.isnan(F), status_between, Status.OK).astype(np.int8)
            return SimpleNamespace(force_n=F, status=st)

        def points(design, H, P, params):
            return SimpleNamespace(force_n=np.full(H.shape, np.nan), status=np.full(H.shape, status_between)), H * 0

        monkeypatch.setattr(
            solve,
            "_solve_plane",
            lambda d, hg, path, rep, prm, parts: SimpleNamespace(state=np.zeros((hg.size, len(rep), 2))),
        )
        monkeypatch.setattr(solve, "_classify", classify)
        monkeypatch.setattr(solve, "_force_and_state", points)

    monkeypatch.setattr(solve, "_refine_crossings", _interpolate_only)
    design = Membrane.from_key("[1.2, 37.5, nan, nan, nan, nan]")
    loads = np.array([14.7, 39.2])
    fake_plane(Status.OUTSIDE_MODEL)
    h, st = solve.height_at(design, loads, 6895.0, h_max_mm=120.0, n_heights=25)
    assert list(st) == [Status.OK, Status.OK]
    want = [np.interp(-f, -row[14:], hg[14:]) for f in loads]  # the row falls from 70 mm on
    np.testing.assert_allclose(h, want, atol=1e-9)
    assert h[0] > 100.0
    fake_plane(Status.NOT_CONVERGED)
    h, st = solve.height_at(design, loads, 6895.0, h_max_mm=120.0, n_heights=25)
    assert list(st) == [Status.NOT_CONVERGED, Status.NOT_CONVERGED] and np.isnan(h).all()
