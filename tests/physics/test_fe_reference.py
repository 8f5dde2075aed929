"""Independent references for the simulator (issue 2, items 5a and 5c).

* Hencky's classical solution of the clamped circular membrane (``tests/hencky.py``),
  checked against the textbook constants and against a second, independent formulation;
* the finite-element energy minimisation (``mfdesign.physics.fe``) against Hencky in the
  small-strain limit (free inflation, no plate);
* the finite-element plate force: mesh convergence and the two force formulas
  (envelope theorem vs vertical balance of the disk);
* the plate as a contact beyond the disk (``plate_contact_k``): a converged penalty, the
  vertical balance at the line where the membrane leaves the plate, and no change where
  the membrane stays below the plate.

The shooting solver is compared with ``fe_force`` elsewhere; nothing here imports it.
"""

from __future__ import annotations

import numpy as np
import pytest
from scipy.integrate import solve_bvp

from hencky import hencky
from mfdesign.design import Membrane
from mfdesign.physics.fe import fe_force, fe_forces, fe_free_inflation, fe_rows
from mfdesign.physics.params import SimParams

RINGLESS = "[2.0, 25.4, nan, nan, nan, nan]"
TWO_RINGS = "[2.0, 25.4, 33.4, 5.0, 46.4, 5.0]"
POINTS = ([20.0, 40.0], [5000.0, 8000.0])  # (h mm, p Pa) pairs


# ------------------------------------------------------------------------------ Hencky
def test_hencky_against_timoshenko_constants():
    """Timoshenko & Woinowsky-Krieger (1959), § 98: for nu = 0.3,
    w0 = 0.662 a (q a / E h)^(1/3) and sigma_0 = 0.423 (E q^2 a^2 / h^2)^(1/3).

    Our solution of the same equations gives K = 0.6534 and S = 0.4311: 1.3 % and 1.9 %
    from the book. We did not tune anything to close that gap, because:
    (i) a second formulation of the same equations (displacements u, w with
    ``solve_bvp``, :func:`test_hencky_two_formulations_agree`) gives the same K to 1e-4;
    (ii) the nonlinear finite-element membrane, which shares no code or equations with
    either, reproduces our nu = 0.5 constant to 0.15 % in the small-strain limit
    (:func:`test_fe_free_inflation_matches_hencky`);
    (iii) the book's constants are Hencky's 1915 power-series values, whose computation
    contained an error later corrected by Chien (1948) and Alekseev (1953) (see e.g.
    Sun et al., Mathematics 8 (2020) 653, introduction).
    So the classical anchor is reproduced to 2 %, and the residual is the historical
    error in the published constants, not ours.
    """
    sol = hencky(0.3)
    assert sol.deflection_coefficient == pytest.approx(0.662, rel=0.02)
    assert sol.stress_coefficient == pytest.approx(0.423, rel=0.02)
    # Pin our own numbers so that a regression in hencky.py shows up.
    assert sol.deflection_coefficient == pytest.approx(0.65344, abs=2e-5)
    assert sol.stress_coefficient == pytest.approx(0.43110, abs=2e-5)


def _foppl_displacement_form(nu: float) -> float:
    """Föppl's equations in (u, N_r, w) with solve_bvp (a = E = h = 1): returns K(nu)."""
    Q = 1e-3

    def rhs(r, y):
        u, nr, w = y
        wp = -Q * r / (2.0 * nr)  # vertical equilibrium N_r w' = -q r / 2
        et = u / r
        er = (1.0 - nu**2) * nr - nu * et  # Hooke's law solved for e_r
        nt = (et + nu * er) / (1.0 - nu**2)
        return np.vstack([er - wp**2 / 2.0, (nt - nr) / r, wp])  # u', N_r' (radial eq.), w'

    def bc(ya, yb):
        return np.array([ya[0], yb[0], yb[2]])  # u(0) = 0, u(a) = 0, w(a) = 0

    r = np.linspace(1e-3, 1.0, 400)
    y0 = np.vstack([0 * r, 0.4 * Q ** (2 / 3) * np.ones_like(r), 0.6 * Q ** (1 / 3) * (1 - r**2)])
    sol = solve_bvp(rhs, bc, r, y0, tol=1e-8, max_nodes=200000)
    assert sol.status == 0, sol.message
    return float(sol.sol(1e-3)[2] / Q ** (1 / 3))


@pytest.mark.parametrize("nu", [0.3, 0.5])
def test_hencky_two_formulations_agree(nu):
    assert _foppl_displacement_form(nu) == pytest.approx(hencky(nu).deflection_coefficient, rel=1e-4)


# ------------------------------------------------------------ FE free inflation vs Hencky
def test_fe_free_inflation_matches_hencky():
    """Free inflation (no plate) of a neo-Hookean membrane vs Hencky's nu = 0.5 constant.

    Small strain: an incompressible neo-Hookean sheet in plane stress has E = 3 mu,
    nu = 0.5. The pressure is chosen for w0 = 4 % of the radius. Expected differences:
    the Föppl theory drops terms of relative order (slope)^2 ~ (2 w0 / a)^2 ~ 0.6 %
    (measured: 0.02 % at w0/a = 2 %, 0.15 % at 4 %, 0.65 % at 8 %), and the membrane
    needs a rigid disk (contact radius 0.5 mm, 0.7 % of the radius) where Hencky has a
    point: its effect on w0 is of order the slope there times 0.5 mm, far below 0.1 %.
    Tolerance 1 % (the brief asked for ~2 %).
    """
    mu, t, a = 31.7e3, 2.0, 70.0
    E = 3.0 * mu
    K = hencky(0.5).deflection_coefficient
    w_rel = 0.04
    Q = (w_rel / K) ** 3
    q = Q * E * t / a  # ~0.83 Pa
    params = SimParams(mu_pa=mu, jm=1e12)  # Gent with J_m -> infinity = neo-Hookean
    res = fe_free_inflation(Membrane(t, 0.5), q, params, n_elements=400)
    assert bool(res.converged)
    w0 = float(res.h_mm)
    assert w0 == pytest.approx(K * a * Q ** (1.0 / 3.0), rel=0.01)
    # No plate: the disk is in equilibrium by itself, F = -dPi/dh = 0.
    assert abs(float(res.force_n)) < 1e-9


# ------------------------------------------------------------------ FE plate force checks
@pytest.mark.parametrize("key", [RINGLESS, TWO_RINGS])
def test_fe_force_formulas_agree(key):
    """Envelope theorem F = -dPi*/dh vs the disk balance on the first element.

    They differ by O(first element / r0) (graded mesh: 0.02 mm against r0 = 25.4 mm);
    measured <= 0.05 % at 400 elements.
    """
    res = fe_force(Membrane.from_key(key), *POINTS, n_elements=400)
    assert np.all(np.asarray(res.converged))
    np.testing.assert_allclose(res.force_disk_n, res.force_n, rtol=1e-3)
    assert np.all(np.asarray(res.force_n) > 10.0)  # order of magnitude: tens of newtons


@pytest.mark.parametrize("key", [RINGLESS, TWO_RINGS])
def test_fe_plate_contact(key):
    """The plate as a frictionless penalty contact beyond the disk.

    At these points the contact-free membrane rises 10-37 mm above the plate beside the
    disk. With the contact: (1) the penalty is converged (k 10 vs 100 N/mm^3: measured
    <= 0.01 N, penetration < 1e-3 mm at 100); (2) everything inside the line where the
    membrane leaves the plate (horizontal there) balances, F = p pi R(a)^2 (the first
    integral of the ODEs with beta = 0; measured within 0.5 %, a node spacing); (3) the
    plate pushed by the membrane carries more than the disk alone (measured 53 -> 57 N,
    164 -> 225 N ringless; 30 -> 43, 50 -> 68 N ringed).
    """
    design = Membrane.from_key(key)
    h, p = np.asarray(POINTS[0]), np.asarray(POINTS[1])
    free = fe_force(design, h, p, n_elements=400)
    assert np.all(np.asarray(free.Z_mm).max(1) - h > 10.0)  # the case contact is about
    soft = fe_force(design, h, p, n_elements=400, plate_contact_k=10.0)
    stiff = fe_force(design, h, p, n_elements=400, plate_contact_k=100.0)
    assert np.all(np.asarray(soft.converged)) and np.all(np.asarray(stiff.converged))
    np.testing.assert_allclose(soft.force_n, stiff.force_n, rtol=1e-3)
    above = np.asarray(stiff.Z_mm) - h[:, None]
    assert above.max() < 1e-3
    last = np.array([np.nonzero(row > 0.0)[0].max() for row in above])  # where it leaves the plate
    R_a = np.asarray(stiff.R_mm)[np.arange(h.size), last]
    np.testing.assert_allclose(stiff.force_n, p * 1e-6 * np.pi * R_a**2, rtol=0.01)
    assert np.all(np.asarray(stiff.force_n) > np.asarray(free.force_n) + 3.0)


def test_fe_plate_contact_inactive_below_the_plate():
    """Where the contact-free membrane stays below the plate, the contact changes nothing."""
    design = Membrane.from_key(TWO_RINGS)
    h, p = np.array([60.0, 70.0]), np.array([2000.0, 3000.0])
    free = fe_force(design, h, p, n_elements=400)
    assert np.all(np.asarray(free.Z_mm).max(1) <= h)
    touch = fe_force(design, h, p, n_elements=400, plate_contact_k=10.0)
    np.testing.assert_allclose(touch.force_n, free.force_n, rtol=0, atol=1e-9)


def test_many_designs_in_one_call_match_one_at_a_time():
    """``fe_forces`` stacks the meshes of unlike jobs (a ringless and a ringed membrane,
    other rubbers, a plate contact) and solves every point in one kernel; each job's
    result must be that job's own solve, in its own shape (a scalar, a vector, a 2 x 1
    grid broadcast against a row), never a neighbour's mesh or points."""
    ring, plain = Membrane.from_key(TWO_RINGS), Membrane.from_key(RINGLESS)
    soft = SimParams(mu_pa=25e3, jm=30.0)
    jobs = [(ring, SimParams()), (plain, soft), (ring, soft)]
    hs = [40.0, np.array([20.0, 40.0, 30.0]), np.array([[30.0], [50.0]])]
    ps = [8000.0, np.array([5000.0, 8000.0, 6000.0]), np.array([4000.0, 7000.0])]
    ks = [0.0, 10.0, 0.0]
    many = fe_forces(jobs, hs, ps, n_elements=100, plate_contact_k=ks)
    assert [np.shape(r.force_n) for r in many] == [(), (3,), (2, 2)]
    assert many[2].R_mm.shape == (2, 2, 101)
    for (d, prm), h, p, k, got in zip(jobs, hs, ps, ks, many):
        one = fe_force(d, h, p, prm, n_elements=100, plate_contact_k=k)
        assert np.all(np.asarray(one.converged))
        np.testing.assert_allclose(got.force_n, one.force_n, rtol=1e-10)
        np.testing.assert_allclose(got.Z_mm, one.Z_mm, rtol=1e-10, atol=1e-10)
    # the jobs differ, so a mix-up of meshes could not pass unseen
    assert abs(float(many[0].force_n) - float(many[2].force_n[1, 0])) > 1.0
    with pytest.raises(ValueError, match="2 jobs but 1 height"):
        fe_forces(jobs[:2], hs[:1], ps[:2], n_elements=100)


def test_rows_walk_the_inflation_once_and_equal_the_points():
    """``fe_rows`` (each height inflated through its pressures, one increment a node after
    the first) reaches the equilibria ``fe_forces`` reaches from ``p = 0`` at each point:
    the same quasi-static path, walked once; a bad pressure list is refused."""
    ring = Membrane.from_key(TWO_RINGS)
    hs, ps = np.array([20.0, 35.0, 50.0]), np.array([2000.0, 3000.0, 4500.0, 6000.0, 8000.0])
    rows = fe_rows(ring, SimParams(), hs, ps, n_elements=100)
    assert np.shape(rows.force_n) == (3, 5) and np.asarray(rows.converged).all()
    H, P = np.meshgrid(hs, ps, indexing="ij")
    points = fe_forces([(ring, SimParams())], [H], [P], n_elements=100)[0]
    assert np.asarray(points.converged).all()
    np.testing.assert_allclose(rows.force_n, points.force_n, rtol=1e-8, atol=1e-8)
    np.testing.assert_allclose(rows.Z_mm, points.Z_mm, rtol=1e-8, atol=1e-8)
    assert float(np.ptp(np.asarray(rows.force_n))) > 10.0  # the grid's forces differ: no node copies another
    with pytest.raises(ValueError, match="increasing pressures"):
        fe_rows(ring, SimParams(), hs, ps[::-1], n_elements=100)


@pytest.mark.slow
@pytest.mark.parametrize("key", [RINGLESS, TWO_RINGS])
def test_fe_force_mesh_convergence(key):
    """400 vs 800 elements differ by < 0.1 % in force (measured: <= 0.001 %)."""
    design = Membrane.from_key(key)
    coarse = fe_force(design, *POINTS, n_elements=400)
    fine = fe_force(design, *POINTS, n_elements=800)
    assert np.all(np.asarray(coarse.converged)) and np.all(np.asarray(fine.converged))
    np.testing.assert_allclose(coarse.force_n, fine.force_n, rtol=1e-3)
    np.testing.assert_allclose(fine.force_disk_n, fine.force_n, rtol=1e-3)


@pytest.mark.slow
def test_fe_unconverged_is_nan():
    """A minimisation that runs out of steps reports converged=False and NaN, not a number."""
    res = fe_force(Membrane.from_key(RINGLESS), 40.0, 8000.0, n_elements=100, n_steps=1, max_steps=3)
    assert not bool(res.converged)
    assert np.isnan(float(res.force_n)) and np.isnan(float(res.force_disk_n))
