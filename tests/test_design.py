"""Membrane designs: validation messages, key round trip, ring order, the design space."""

import math

import jax
import numpy as np
import pytest

from mfdesign.design import DesignError, DesignSpace, Membrane, Ring
from mfdesign.materials import Gent, NeoHookean

REAL_KEYS = [
    "[2.0, 25.4, nan, nan, nan, nan]",
    "[2.0, 25.4, 49.0, 5.0, 62.0, 5.0]",
    "[2.33, 29.63, 37.63, 5.0, 62.0, 5.0]",
    "[2.0, 27.98, 45.58, 5.0, 60.29, 6.71]",
    "[2.0, 38.1, 47.55, 6.45, 62.0, 5.0]",
    "[2.0, 25.4, 33.4, 5.0, 46.4, 5.0]",
    "[2.0, 31.92, 46.0, 5.0, 59.0, 5.0]",
    "[1.0, 25.4, 41.2, 12.8, 62.0, 5.0]",
    "[3.0, 25.4, 34.73, 6.33, 55.53, 11.47]",
]


@pytest.mark.parametrize("key", REAL_KEYS)
def test_key_round_trip_of_real_designs(key):
    assert Membrane.from_key(key).key() == key


def test_swapped_rings_are_equal_and_hash_alike():
    a = Membrane(2.0, 25.4, [(33.4, 5.0), (46.4, 5.0)])
    b = Membrane(2.0, 25.4, [Ring(46.4, 5.0), Ring(33.4, 5.0)])
    assert a == b and hash(a) == hash(b)
    assert Membrane.from_key("[2.0, 25.4, 46.4, 5.0, 33.4, 5.0]") == a


@pytest.mark.parametrize(
    "key, words",
    [
        ("[0, 25.4, nan, nan, nan, nan]", "thickness must be positive"),
        ("[-1, 25.4, nan, nan, nan, nan]", "thickness must be positive"),
        ("[2, inf, nan, nan, nan, nan]", "contact radius must be finite"),
        ("[2, 75, nan, nan, nan, nan]", "smaller than the outer radius"),
        ("[2.0, 25.4, 27, 5.0, nan, nan]", "overlapping the contact disk"),
        ("[2.0, 25.4, 62.5, 5.0, nan, nan]", "overlapping the clamp"),
        ("[2.0, 25.4, 40, 5.0, 50, 5]", "overlapping ring 1"),
        ("[2, 25.4, 40, nan, nan, nan]", "radius (40.0 mm) but no half-width"),
        ("[2, 25.4, nan, 5, nan, nan]", "half-width (5.0 mm) but no radius"),
        ("[2, 25.4, 40, 0, nan, nan]", "ring half-width must be positive"),
        ("[1, 2]", "6 numbers"),
        ("2, 25.4", "looks like"),
        ("[2, 25.4, x, 1, nan, nan]", "not a number"),
    ],
)
def test_invalid_designs_name_the_field_and_rule(key, words):
    with pytest.raises(DesignError, match=None) as err:
        Membrane.from_key(key)
    assert words in str(err.value), str(err.value)


def test_more_than_two_rings_rejected():
    with pytest.raises(DesignError, match="at most 2 rings"):
        Membrane(2.0, 25.4, [(31, 1), (36, 1), (41, 1)])


@pytest.mark.parametrize("n_rings", [0, 1, 2])
def test_unit_cube_decodes_to_valid_designs_inside_the_bounds(n_rings):
    space = DesignSpace()
    rng = np.random.default_rng(0)
    u = rng.uniform(size=(3000, space.dim(n_rings)))
    u[:16] = rng.integers(0, 2, size=(16, space.dim(n_rings)))  # corners
    arr = space.decode_array(u, n_rings)
    for row in arr:
        d = Membrane.from_array(row)  # raises if invalid
        assert d.n_rings == n_rings and space.contains(d)


def test_decoding_is_continuous():
    space = DesignSpace()
    u = np.full(6, 0.37)
    du = np.zeros(6)
    du[3] = 1e-7
    a, b = space.decode_array(u, 2), space.decode_array(u + du, 2)
    assert np.max(np.abs(a - b)) < 1e-5


def test_gent_approaches_neo_hookean_and_locks():
    l1, l2 = 1.3, 1.1
    neo, gent = NeoHookean(mu_pa=30e3), Gent(mu_pa=30e3, jm=1e9)
    assert math.isclose(float(gent.energy(l1, l2)), float(neo.energy(l1, l2)), rel_tol=1e-6)
    w1, w2 = Gent().dW(l1, l2)
    assert float(w1) > 0 and float(w2) > 0
    assert np.isnan(float(Gent(jm=2.0).energy(3.0, 1.0)))  # past the extension limit: NaN, no crash
    # Autodiff derivatives agree with finite differences.
    eps = 1e-6
    fd = (Gent().energy(l1 + eps, l2) - Gent().energy(l1 - eps, l2)) / (2 * eps)
    assert math.isclose(float(w1), float(fd), rel_tol=1e-6)
    assert jax.numpy.isfinite(Gent().d2W(l1, l2)[0])


def test_i2_share_keeps_the_small_strain_modulus_and_stiffens_biaxial_stretch():
    """``Gent(i2_share=b)``: ``mu`` stays the small-strain shear modulus (the energy of a
    small uniaxial strain e is 3/2 mu e^2 for every b), while a large equibiaxial stretch
    costs more energy than plain Gent (the I2 term grows as lambda^4) and a large uniaxial
    one less."""
    e = 1e-3
    uni = lambda m, l: m.energy(l, 1.0 / np.sqrt(l))  # noqa: E731
    for b in (0.0, 0.2, 0.5):
        m = Gent(mu_pa=30e3, jm=40.0, i2_share=b)
        assert math.isclose(float(uni(m, 1 + e)), 1.5 * 30e3 * e**2, rel_tol=3e-3)
    plain, mr = Gent(mu_pa=30e3, jm=40.0), Gent(mu_pa=30e3, jm=40.0, i2_share=0.3)
    assert float(mr.energy(2.5, 2.5)) > 1.2 * float(plain.energy(2.5, 2.5))
    assert float(mr.energy(4.0, 0.5)) < float(plain.energy(4.0, 0.5))


def test_decode_any_reads_the_ring_count_as_data():
    import jax
    import jax.numpy as jnp

    space = DesignSpace()
    u = np.random.default_rng(3).uniform(-0.1, 1.1, size=(30, 6))
    for n in (0, 1, 2):
        np.testing.assert_array_equal(
            np.asarray(space.decode_any(u, n)), np.asarray(space.decode_unit(space.cube_of(u, n), n))
        )
    rows = jax.vmap(space.decode_any, in_axes=(None, 0))(jnp.asarray(u[0]), jnp.arange(3))
    assert [Membrane.from_array(np.asarray(r)).n_rings for r in rows] == [0, 1, 2]


@pytest.mark.parametrize("n_rings", [0, 1, 2])
def test_encode_inverts_decode(n_rings):
    space = DesignSpace()
    for u in np.random.default_rng(n_rings).uniform(size=(30, space.dim(n_rings))):
        np.testing.assert_allclose(space.encode(space.decode(u, n_rings)), u, atol=1e-9)
    fixed = DesignSpace(thickness_mm=(2.0, 2.0))  # a fixed feature has coordinate 0
    assert fixed.encode(Membrane(2.0, 30.0))[0] == 0.0
    assert DesignSpace().encode(Membrane(0.5, 30.0))[0] < 0  # outside the bounds: outside the cube
