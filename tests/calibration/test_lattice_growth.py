"""How calibration grows the exact model's lattice around the MAP (mcmc.fit_force_model):
an axis grows only where the MAP or the posterior's box reaches past it, never as a
default (issue 40). Node arithmetic only: ``_assemble`` is replaced, no plane is solved,
and ``find_map`` returns the MAP given."""

from __future__ import annotations

import jax.numpy as jnp
import numpy as np
import pytest

import mfdesign.calibration.mcmc as mc
import mfdesign.models.exact as ex
from mfdesign.calibration.workflow import model_for
from mfdesign.design import Membrane
from mfdesign.models.hierarchical import CalibrationData
from mfdesign.physics.effects import Rows
from mfdesign.physics import planes as pl
from mfdesign.physics.params import SimParams

# one ringless and one ringed membrane (the ring axis acts on the second only)
KEYS = ("[2.0, 25.4, nan, nan, nan, nan]", "[1.5, 30.0, 45.0, 6.0, nan, nan]")
GRID = pl.PlaneGrid.covering(40.0, 6000.0)


def fake_exact(nodes: dict) -> ex.ExactForceModel:
    """An exact model with lattice ``nodes`` (axis -> (k0, k1)) and zero planes."""
    shape = (len(KEYS), *(k1 - k0 + 3 for k0, k1 in nodes.values()), GRID.h.size + 2, GRID.p.size + 2)
    designs = [Membrane.from_key(k) for k in KEYS]
    return ex.ExactForceModel(
        designs=jnp.asarray(np.stack([d.to_array() for d in designs])),
        ringed=jnp.asarray([d.n_rings > 0 for d in designs]),
        tensor=jnp.zeros(shape),
        additive=(),
        base=SimParams(),
        tensor_axes=tuple(ex.LatticeAxis(k, k0, k1 - k0 + 1) for k, (k0, k1) in nodes.items()),
        additive_axes=(),
        grid=GRID,
        design_keys=KEYS,
        outside="clamp",
    )


@pytest.fixture
def grown(monkeypatch):
    """Every lattice ``covering`` asks for (``_assemble``'s tensor nodes), in order."""
    calls: list[dict] = []

    def assemble(design_keys, base, t_nodes, a_nodes, *rest, **kw):
        calls.append(dict(t_nodes))
        return fake_exact(t_nodes)

    monkeypatch.setattr(ex, "_assemble", assemble)
    return calls


def data() -> CalibrationData:
    """Four force rows a membrane (the growth reads only the constants the rows see)."""
    n = 2 * 4
    design = np.repeat(np.stack([Membrane.from_key(k).to_array() for k in KEYS]), n // 2, axis=0)
    rows = Rows(
        h_mm=jnp.tile(jnp.linspace(5.0, 30.0, n // 2), 2),
        p_pa=jnp.full(n, 3e3),
        is_force=jnp.ones(n, bool),
        is_deflate=jnp.zeros(n, bool),
        is_first_trial=jnp.ones(n, bool),
        membrane=jnp.repeat(jnp.arange(2, dtype=jnp.int32), n // 2),
    )
    return CalibrationData(jnp.asarray(design), rows, jnp.full(n, 10.0), jnp.ones(n), KEYS)


def map_at(model, hess_diag, mu_pa=33_667.0, jm=39.56) -> mc.MapResult:
    """A MAP at the plain demo's constants (mu above the reference: ring coordinate -0.06,
    J_m at its reference node) with a diagonal Hessian ``hess_diag`` (by parameter name)."""
    x0 = dict(zip(model.names, model.initial_physical()))
    x0.update(mu_pa=mu_pa, jm=jm)
    x = np.array([x0[n] for n in model.names])
    u = model.to_unconstrained(x)
    h = np.diag([hess_diag.get(n, 1e6) for n in model.names])
    return mc.MapResult(jnp.asarray(u), jnp.asarray(x), jnp.asarray(0.0), jnp.asarray(h), jnp.asarray(True))


def fit(model, res, monkeypatch):
    monkeypatch.setattr(mc, "find_map", lambda *a, **k: res)  # the MAP stays where it is
    out, _ = mc.fit_force_model(model, data(), res)
    return {a.name: (a.k0, a.k0 + a.n - 1) for a in out.force_model.tensor_axes}


def test_a_narrow_posterior_inside_the_lattice_grows_nothing(grown, monkeypatch):
    model = model_for(fake_exact({"jm": (-1, 1), "ring": (-1, 1)}), KEYS)
    res = map_at(model, {"mu_pa": 1e6, "jm": 1e6})
    assert fit(model, res, monkeypatch) == {"jm": (-1, 1), "ring": (-1, 1)}
    assert grown == []


def test_a_funnel_grows_no_axis(grown, monkeypatch):
    """The hierarchy's flat direction (thickness spread): no curvature, but it moves no
    lattice axis. The old no-Hessian rule grew every axis EDGE_STEP nodes both sides of the
    MAP (jm -3..2, ring -3..2 here: 36 planes of a ringed membrane for 9)."""
    model = model_for(fake_exact({"jm": (-1, 1), "ring": (-1, 1)}), KEYS)
    res = map_at(model, {"mu_pa": 1e6, "jm": 1e6, "thickness_sd": 0.0})
    assert mc._lattice_steps(model, data(), res)[model.names.index("thickness_sd")] == 0.0
    assert fit(model, res, monkeypatch) == {"jm": (-1, 1), "ring": (-1, 1)}
    assert grown == []


def test_an_undetermined_jm_grows_the_jm_axis_only(grown, monkeypatch):
    """J_m without curvature at the MAP: its own axis grows EDGE_STEP nodes each side of the
    MAP; the ring axis, moved by a well-determined mu, stays."""
    model = model_for(fake_exact({"jm": (-1, 1), "ring": (-1, 1)}), KEYS)
    res = map_at(model, {"mu_pa": 1e6, "jm": -1.0})
    nodes = fit(model, res, monkeypatch)
    assert nodes["ring"] == (-1, 1)
    k0, k1 = nodes["jm"]
    assert -3 <= k0 <= -mc.EDGE_STEP and mc.EDGE_STEP <= k1 <= 3, nodes
    assert len(grown) == 1


def test_a_wide_posterior_grows_its_laplace_box(grown, monkeypatch):
    """A determined but wide mu: the ring axis (its coordinate is -log mu / mu0) grows to
    hold MAP +- LATTICE_SD sd, the J_m axis stays."""
    model = model_for(fake_exact({"jm": (-1, 1), "ring": (-1, 1)}), KEYS)
    i = model.names.index("mu_pa")
    res = map_at(model, {"mu_pa": 1e6, "jm": 1e6})
    sd_u = 0.2  # wide in u: the ring coordinate's 5 sd box reaches past -1..1
    h = np.asarray(res.hessian).copy()
    h[i, i] = 1.0 / sd_u**2
    res = mc.MapResult(res.u, res.x, res.log_post, jnp.asarray(h), res.converged)
    steps = mc._lattice_steps(model, data(), res)
    assert steps[i] == pytest.approx(mc.LATTICE_SD * sd_u)
    u = np.asarray(res.u)
    box = mc._params_at(model, data(), np.vstack([u, u + np.diag(steps), u - np.diag(steps)]))
    assert not model.force_model.covers(box)
    nodes = fit(model, res, monkeypatch)
    assert nodes["jm"] == (-1, 1) and nodes["ring"] != (-1, 1), nodes
    assert fake_exact(nodes).covers(box)
