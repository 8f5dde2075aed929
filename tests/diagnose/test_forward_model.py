"""The diagnosis forward model's interface: an abstract module, two immutable back ends, growth in an explicit cache."""

from __future__ import annotations

import dataclasses

import equinox as eqx
import numpy as np
import pytest

from mfdesign.design import Membrane
from mfdesign.diagnosis.forward import (
    EmulatorForwardModel,
    ExactForwardModel,
    ForwardModel,
    GrowingLattice,
    forward_model,
)
from mfdesign.models.force import ForceModel
from mfdesign.models.standin import StandinForceModel, standin_force, standin_plane
from mfdesign.physics.params import SimParams
from mfdesign.rig.virtual import Protocol, VirtualRig

KEYS = ("[2.0, 25.4, nan, nan, nan, nan]", "[1.5, 30.0, 45.0, 6.0, nan, nan]")
THETA = {"contact_offset.offset_mm": 0.5}


@pytest.fixture(scope="module")
def meas():
    rig = VirtualRig(simulator=standin_plane, seed=1, protocol=Protocol(sample_hz=0.5, pressure_step_pa=500.0))
    return rig.run([Membrane.from_key(k) for k in KEYS], progress=False)


class _Growing(ForceModel):
    """The stand-in, 'holding' contact offsets up to ``reach`` mm: ``covering`` returns a wider
    copy when asked for more (as the exact model's lattice does), itself otherwise."""

    reach: float = eqx.field(static=True, default=0.0)
    name = "growing"

    def __call__(self, design, h_mm, p_pa, params: SimParams = SimParams()):
        return standin_force(design, h_mm, p_pa, params)

    def covering(
        self, params: SimParams, progress: bool = False, margin: int = 0, edge: float | None = None
    ) -> "_Growing":
        need = float(np.max(np.abs(np.asarray(params.contact_offset_mm))))
        return self if need <= self.reach else _Growing(need)


def test_the_interface_is_abstract_and_the_back_ends_immutable():
    with pytest.raises(TypeError):
        ForwardModel()  # type: ignore[abstract]
    for sim in (EmulatorForwardModel(StandinForceModel()), ExactForwardModel(StandinForceModel())):
        assert isinstance(sim, ForwardModel) and isinstance(sim, eqx.Module)
        with pytest.raises(dataclasses.FrozenInstanceError):
            sim.base_params = SimParams()  # type: ignore[misc]


def test_forward_model_by_name():
    assert type(forward_model("standin", None)) is EmulatorForwardModel  # type: ignore[arg-type]
    with pytest.raises(ValueError, match="--physics must be one of"):
        forward_model("nope", None)  # type: ignore[arg-type]


def test_back_ends_agree_where_nothing_grows(meas):
    """The two back ends share every evaluation: on a force model that holds every constant
    they give the same forces and derivatives, bit for bit."""
    emu, exact = EmulatorForwardModel(StandinForceModel()), ExactForwardModel(StandinForceModel())
    rows = np.arange(0, len(meas), 3)
    for kw in ({}, {"effects": ["contact_offset", "pressure_sensor"], "theta": THETA}):
        np.testing.assert_array_equal(emu.expected_force(meas, **kw), exact.expected_force(meas, **kw))
        np.testing.assert_array_equal(
            emu.jacobian(meas, ["contact_offset.offset_mm"], rows=rows, **kw),
            exact.jacobian(meas, ["contact_offset.offset_mm"], rows=rows, **kw),
        )


def test_the_exact_back_end_grows_its_lattice_in_the_cache(meas):
    """Growth happens in the GrowingLattice (an explicit cache), never in the model; the
    emulator back end never grows its force model."""
    exact = ExactForwardModel(_Growing())
    assert isinstance(exact.lattice, GrowingLattice)
    plain = exact.expected_force(meas)
    assert exact.force_model.reach == 0.0
    shifted = exact.expected_force(meas, ["contact_offset"], THETA)
    grown = exact.force_model
    assert grown.reach == pytest.approx(0.5)
    exact.expected_force(meas, ["contact_offset"], THETA)
    assert exact.force_model is grown  # covered: no new model
    np.testing.assert_array_equal(
        shifted, EmulatorForwardModel(StandinForceModel()).expected_force(meas, ["contact_offset"], THETA)
    )
    assert not np.array_equal(plain, shifted)

    emu = EmulatorForwardModel(_Growing())
    start = emu.force_model
    emu.expected_force(meas, ["contact_offset"], THETA)
    assert emu.force_model is start


def test_padded_shapes_give_the_unpadded_numbers(meas):
    """Columns padded to one per parameter and fits run in chunks of FIT_CHUNK problems (one
    compiled program for every count, issue 40) give what the unpadded calls give: each
    Jacobian column as when asked alone, each fit as the whole batch in one call."""
    import jax.numpy as jnp

    from mfdesign.diagnosis import forward as fw

    sim = EmulatorForwardModel(StandinForceModel())
    rows = np.arange(0, len(meas), 5)
    effects = ["contact_offset", "pressure_sensor"]
    free = ["contact_offset.offset_mm", "pressure_sensor.gain", "pressure_sensor.offset_pa"]
    J = sim.jacobian(meas, free, effects, THETA, rows=rows)  # 3 columns of one per parameter
    assert J.shape == (len(rows), 3)
    for j, f in enumerate(free):
        np.testing.assert_allclose(J[:, j], sim.jacobian(meas, [f], effects, THETA, rows=rows)[:, 0], rtol=1e-12)

    order = fw.effect_order(["contact_offset"])
    names = fw.parameter_names(order)
    t0 = fw.theta_vector(order, None)
    target = sim.expected_force(meas, ["contact_offset"], THETA, rows=rows)
    b = fw.FIT_CHUNK + 1  # a full chunk and one problem in a padded one
    P = np.zeros((b, len(names), 1))
    P[:, names.index("contact_offset.offset_mm"), 0] = 1.0
    rng = np.random.default_rng(0)
    w = (rng.random((b, len(rows))) < 0.7).astype(float)
    tau = np.full((b, 1), 2.0)
    x0 = np.linspace(0.0, 0.4, b)[:, None]
    t0s = np.broadcast_to(t0, (b, len(t0)))
    x, ok = sim.fit(meas, rows, target, order, t0s, P, w, tau, x0, 0.1)
    assert x.shape == (b, 1) and ok.shape == (b,) and ok.all()
    design, rws = sim.table(meas, rows)
    x_all, ok_all = fw._fit_batch(  # the whole batch in one call, as before the chunks
        sim.clipped,
        order,
        names,
        sim.base_params,
        design,
        rws,
        jnp.asarray(target),
        0.1,
        *(jnp.asarray(a, float) for a in (t0s, P, w, tau, x0)),
        60,
    )
    np.testing.assert_allclose(x, np.asarray(x_all), rtol=1e-10, atol=1e-12)
    np.testing.assert_array_equal(ok, np.asarray(ok_all))
    assert np.allclose(x, 0.5, atol=0.05)


def test_row_subsets_of_any_size_share_one_gather_and_give_the_rows_values(meas):
    """The forward model gathers each chunk of a row subset from the whole table: subsets of
    three sizes compile one gather (a subset taken first compiled one a size, ~30 small
    programs a cold diagnosis, issue 40), and each subset's forces and derivatives are those
    of its rows in the whole table's."""
    from mfdesign.diagnosis import forward as fw

    sim = EmulatorForwardModel(StandinForceModel())
    whole = sim.expected_force(meas, ["contact_offset"], THETA)
    J_whole = sim.jacobian(meas, ["contact_offset.offset_mm"], ["contact_offset"], THETA)
    before = fw._take._cached._cache_size()
    for n in (5, 7, 301):
        rows = np.linspace(0, len(meas) - 1, n).astype(int)[::-1]  # any order
        np.testing.assert_array_equal(sim.expected_force(meas, ["contact_offset"], THETA, rows=rows), whole[rows])
        np.testing.assert_array_equal(
            sim.jacobian(meas, ["contact_offset.offset_mm"], ["contact_offset"], THETA, rows=rows), J_whole[rows]
        )
    assert fw._take._cached._cache_size() - before <= 1
