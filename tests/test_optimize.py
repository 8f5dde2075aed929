"""Design optimisation: decoding, smooth minimum, inversions, losses, multi-start, CLI."""

import json

import equinox as eqx
import jax
import jax.numpy as jnp
import numpy as np
import pytest
from typer.testing import CliRunner

from mfdesign.optimization import (
    HeightTargets,
    MASSES_N,
    TARGET_SETS,
    Waypoints,
    _refine,
    first_crossing,
    height_loss,
    lift_heights,
    model_pressures,
    multistart,
    optimize,
    smooth_min,
    trajectory_loss,
)
from mfdesign.design import DesignSpace, Membrane
from mfdesign.models.predictor import AbstractPredictor
from mfdesign.models.trajectory import crossing_or_nan as np_first_crossing

SPACE = DesignSpace()


class Toy(AbstractPredictor):
    """Analytic two-member force model (N): rises with p, falls with h; a thin membrane with a
    large disk lifts highest; rings stiffen it (lower lift)."""

    @property
    def fidelities(self):
        return ("rig",)

    def members(self, fidelity, d, h, p):
        self.check_fidelity(fidelity)
        t, c = d[:, 0], d[:, 1]
        rings = jnp.nan_to_num(d[:, 3]) + jnp.nan_to_num(d[:, 5])
        f = (c / 25.0) * p / 100.0 - (2.0 * t + 0.3 + 0.02 * rings) * h
        return jnp.stack([f, 1.1 * f])


@pytest.mark.parametrize("n_rings", [0, 1, 2])
def test_decoded_designs_are_valid_and_match_numpy(n_rings):
    u = np.random.default_rng(n_rings).uniform(-0.2, 1.2, size=(200, SPACE.dim(n_rings)))
    d = np.asarray(SPACE.decode_unit(jnp.asarray(u), n_rings))
    np.testing.assert_allclose(d, SPACE.decode_array(u, n_rings), equal_nan=True)
    for row in d:
        m = Membrane.from_array(row)  # raises on an invalid design
        assert m.n_rings == n_rings and SPACE.contains(m)


def test_smooth_min_lower_bounds_min_and_converges():
    x = jnp.array([12.0, 30.0, 14.0])
    gaps = []
    for T in (15.0, 5.0, 1.0, 0.1):
        s = float(smooth_min(x, T))
        assert s <= 12.0 + 1e-12
        assert s >= 12.0 - T * np.log(3) - 1e-12
        gaps.append(12.0 - s)
    assert all(a > b for a, b in zip(gaps, gaps[1:])) and gaps[-1] < 1e-6


def test_first_crossing_matches_numpy_twin():
    rng = np.random.default_rng(0)
    x = np.linspace(0, 10, 21)
    y = np.cumsum(rng.uniform(-0.2, 1, size=(50, 21)), 1)
    level = rng.uniform(-1, 15, 50)
    got, reached = first_crossing(x, y, level)
    ref = np_first_crossing(x, y, level)
    np.testing.assert_allclose(np.asarray(got)[np.asarray(reached)], ref[np.asarray(reached)])
    assert np.all(np.isnan(ref[~np.asarray(reached)])) and np.all(np.asarray(got)[~np.asarray(reached)] == 10)


def test_lift_height_reproduces_forward_force():
    toy = Toy()
    d = jnp.asarray(Membrane.from_key("[1.5, 30.0, nan, nan, nan, nan]").to_array())
    F = jnp.array([14.7, 24.5, 39.2])
    p = jnp.array([4000.0, 6000.0, 8000.0])
    h, _ = jax.jit(lift_heights, static_argnums=0)(toy, d, F, p, jnp.linspace(0, 80, 161))
    assert np.all((np.asarray(h) > 0) & (np.asarray(h) < 80))
    back = toy.members("rig", jnp.tile(d, (3, 1)), h, p).mean(0)
    np.testing.assert_allclose(np.asarray(back), np.asarray(F), atol=1e-9)  # linear in h: exact
    pr, _ = jax.jit(model_pressures, static_argnums=0)(toy, d, F, h, jnp.linspace(0, 2e4, 401))
    np.testing.assert_allclose(np.asarray(pr), np.asarray(p), rtol=1e-9)


@pytest.mark.parametrize("n_rings", [0, 2])
def test_losses_finite_and_differentiable(n_rings):
    toy = Toy()
    u = jnp.asarray(np.random.default_rng(1).uniform(size=(8, SPACE.dim(n_rings))))
    wp = Waypoints([14.7, 24.5], [3000.0, 5000.0], [5.0, 40.0])
    for loss in (
        height_loss(toy, TARGET_SETS["A"], SPACE, n_rings),
        trajectory_loss(toy, wp, SPACE, n_rings),
    ):
        f = jax.jit(lambda x: loss(x)[0])
        val, g = jax.jit(jax.vmap(jax.value_and_grad(f)))(u)
        assert np.all(np.isfinite(val)) and np.all(np.isfinite(g))
        assert np.any(np.abs(np.asarray(g)) > 0)
        # the gradient is the derivative of the loss (central differences, away from kinks)
        e = np.zeros(SPACE.dim(n_rings))
        e[0] = 1e-5
        fd = (f(u[0] + e) - f(u[0] - e)) / 2e-5
        np.testing.assert_allclose(float(g[0, 0]), float(fd), rtol=1e-4, atol=1e-8)


def test_height_grid_inversion_matches_member_path():
    toy = Toy()
    loss = height_loss(toy, TARGET_SETS["B"], SPACE, 1)
    for u in np.random.default_rng(2).uniform(size=(5, 4)):
        d = SPACE.decode_unit(jnp.asarray(u), 1)
        ref, _ = jax.jit(lift_heights, static_argnums=0)(toy, d, loss.force_n, loss.p_pa, loss.h_grid)
        np.testing.assert_allclose(np.asarray(eqx.filter_jit(loss)(jnp.asarray(u))[1]["heights_mm"]), np.asarray(ref))


def test_multistart_improves_every_start_and_finds_optimum():
    class Bowl(eqx.Module):
        def __call__(self, u):
            return jnp.sum((u - jnp.array([0.3, 0.8])) ** 2) + 0.1 * jnp.sin(5 * u[0]) ** 2, {}

    u0 = jax.random.uniform(jax.random.PRNGKey(0), (40, 2), dtype=jnp.float64)
    start = np.asarray(jax.vmap(lambda u: Bowl()(u)[0])(u0))
    u, final = _refine(Bowl(), u0, 150, 0.03, 40)
    assert np.all(np.asarray(final) <= start) and np.all((np.asarray(u) >= 0) & (np.asarray(u) <= 1))
    assert np.mean(np.asarray(final) < start - 1e-3) > 0.9
    res = multistart(Bowl(), 2, n_starts=40, steps=150, n_refine=8)
    g = np.stack(np.meshgrid(np.linspace(0, 1, 401), np.linspace(0, 1, 401), indexing="ij"), -1).reshape(-1, 2)
    vals = np.asarray(jax.vmap(lambda u: Bowl()(u)[0])(jnp.asarray(g)))
    np.testing.assert_allclose(res["u"], g[np.argmin(vals)], atol=0.01)
    assert res["loss"] <= vals.min() + 1e-6


def test_height_loss_multistart_finds_thin_wide_membrane():
    loss = height_loss(Toy(), TARGET_SETS["A"], SPACE, 0)
    res = multistart(loss, 2, n_starts=16, steps=40)  # no screening: one compile
    np.testing.assert_allclose(res["u"], [0.0, 1.0], atol=0.02)  # thinnest, widest disk lifts highest


@pytest.mark.slow
def test_height_maximisation_on_toy_picks_thin_wide_ringless():
    res = optimize(Toy(), TARGET_SETS["A"], rings=(0, 1), n_starts=64, steps=40, n_refine=8, progress=False)
    m = Membrane.from_key(res.design_key)
    assert m.n_rings == 0 and m.thickness_mm < 1.05 and m.contact_radius_mm > 38.0
    assert res.prediction["score_mm"] <= res.prediction["min_h_mm"]
    assert set(res.curves) == {f"{F:.3f}" for F in MASSES_N}


@pytest.mark.slow
def test_trajectory_targeting_recovers_the_generating_design():
    toy = Toy()
    truth = Membrane.from_key("[1.8, 31.0, nan, nan, nan, nan]")
    F = np.repeat(MASSES_N, 3)
    h = np.tile([5.0, 40.0, 50.0], 3)
    p, _ = model_pressures(
        toy, jnp.asarray(truth.to_array()), jnp.asarray(F), jnp.asarray(h), jnp.linspace(0, 2e4, 801)
    )
    res = optimize(toy, Waypoints(F, np.asarray(p), h), rings=(0,), n_starts=64, steps=80, n_refine=16, progress=False)
    assert res.prediction["traj_rmse"] < 0.01
    m = Membrane.from_key(res.design_key)
    # the toy's force depends on t and c only through c / 25 and 2 t: both identifiable
    assert abs(m.thickness_mm - 1.8) < 0.1 and abs(m.contact_radius_mm - 31.0) < 1.0


def test_problem_validation_messages():
    with pytest.raises(ValueError, match="p_pa needs 3"):
        HeightTargets([1.0, 2.0, 3.0], [1.0])
    with pytest.raises(ValueError, match="force_n must be finite and > 0"):
        Waypoints([-1.0], [1.0], [1.0])
    with pytest.raises(ValueError, match="n_refine"):
        multistart(lambda u: (u.sum(), {}), 2, n_starts=4, n_refine=9)


def test_cli_bad_input_fails_with_one_line(tmp_path):
    from mfdesign.cli import app

    runner = CliRunner()
    bad = tmp_path / "t.csv"
    bad.write_text("force,pressure\n1,2\n")
    out = tmp_path / "out"  # not the model folder: an output that is an input is refused first
    cases = [
        (["optimize", "--model", str(tmp_path), "--out", str(out)], "exactly one of"),
        (
            ["optimize", "--model", str(tmp_path), "--out", str(out), "--target-set", "C"],
            "--target-set must be one of",
        ),
        (
            ["optimize", "--model", str(tmp_path), "--out", str(out), "--target-set", "A", "--rings", "3"],
            "--rings",
        ),
        (["optimize", "--model", str(tmp_path), "--out", str(out), "--targets", str(bad)], "need columns force_n"),
        (
            ["optimize", "--model", str(tmp_path / "none"), "--out", str(out), "--target-set", "A"],
            "does not exist",
        ),
    ]
    for args, msg in cases:
        r = runner.invoke(app, args)
        assert r.exit_code == 2, r.output
        lines = [ln for ln in r.output.strip().splitlines() if ln.strip()]
        assert len(lines) == 1 and msg in lines[0], r.output


def test_cli_reads_targets_files(tmp_path):
    from mfdesign.workflows.optimize import read_targets

    (tmp_path / "h.json").write_text(json.dumps({"targets": [{"force_n": 14.7, "pressure_pa": 6895}]}))
    assert isinstance(read_targets(tmp_path / "h.json"), HeightTargets)
    (tmp_path / "w.csv").write_text("force_n,pressure_pa,height_mm\n14.7,3000,5\n14.7,4000,40\n")
    wp = read_targets(tmp_path / "w.csv")
    assert isinstance(wp, Waypoints) and wp.h_mm == (5.0, 40.0)


def test_losses_take_the_padded_cube_and_share_one_structure_across_ring_counts():
    """optimize() searches the 6-d padded cube with the ring count as data: a padded point
    scores as its cube coordinates do, and losses of different ring counts are one pytree
    structure (so the compiled screen and refinement are shared)."""
    toy = Toy()
    wp = Waypoints([14.7, 24.5], [3000.0, 5000.0], [5.0, 40.0])
    u6 = np.random.default_rng(4).uniform(size=6)
    for make, problem in ((height_loss, TARGET_SETS["A"]), (trajectory_loss, wp)):
        losses = {n: make(toy, problem, SPACE, n) for n in (0, 1, 2)}
        for n, loss in losses.items():
            padded = float(eqx.filter_jit(loss)(jnp.asarray(u6))[0])
            cube = float(eqx.filter_jit(loss)(jnp.asarray(SPACE.cube_of(u6, n)))[0])
            assert padded == pytest.approx(cube, rel=1e-12, abs=1e-12)
        structures = {jax.tree_util.tree_structure(eqx.filter(l, eqx.is_array)) for l in losses.values()}
        statics = {jax.tree_util.tree_structure(eqx.partition(l, eqx.is_array)[1]) for l in losses.values()}
        assert len(structures) == 1 and len(statics) == 1
    with pytest.raises(ValueError, match="2, 4 or 6"):
        height_loss(toy, TARGET_SETS["A"], SPACE, 1)(jnp.zeros(3))
    with pytest.raises(Exception, match="another ring count"):  # 2 coordinates: 0 rings, not 1
        jax.block_until_ready(eqx.filter_jit(height_loss(toy, TARGET_SETS["A"], SPACE, 1))(jnp.zeros(2)))


# --------------------------------------------------------------------------- limits, ties, check
def test_limit_flags_name_grid_rig_and_design_space_limits():
    from mfdesign.optimization import limit_flags

    design = Membrane.from_key("[1.0, 30.0, 40.0, 6.0, nan, nan]")  # ring 1 starts 1 mm past the gap
    targets = HeightTargets([10.0, 20.0, 30.0, 40.0], [5000.0, 5000.0, 13000.0, 5000.0])
    pred = {"force_n": list(targets.force_n), "p_pa": list(targets.p_pa), "h_mean_force_mm": [80.0, 77.0, 30.0, 0.0]}
    flags = limit_flags(targets, pred, design, SPACE)
    text = "\n".join(flags)
    assert "10 N at 5 kPa is at the 80 mm top of the height grid" in text
    assert "higher), and above the rig's 75 mm travel" in text  # the grid top (80 mm) is past the travel
    assert "20 N at 5 kPa is 77 mm, above the rig's 75 mm travel" in text
    assert "40 N at 5 kPa is 0 mm: the load is not lifted" in text
    assert "target pressure 13 kPa is above the rig's 12 kPa limit" in text
    assert "thickness 1 mm is at the design space's lower bound 1 mm" in text
    assert not any("30 N" in f for f in flags) and not any("contact radius" in f for f in flags)
    wp = Waypoints([10.0, 20.0], [5000.0, 5000.0], [10.0, 78.0])
    pred = {"force_n": [10.0, 20.0], "p_pa": [5000.0, 5000.0], "p_model_pa": [20000.0, 12500.0]}
    gap = Membrane.from_key("[2.0, 30.0, 39.0, 6.0, nan, nan]")  # inner edge 33 mm = disk + 3 mm
    text = "\n".join(limit_flags(wp, pred, gap, SPACE))
    assert "never reached below 20 kPa" in text and "needs 12.5 kPa, above the rig's 12 kPa" in text
    assert "78 mm (target 5 kPa) is above the rig's 75 mm travel" in text
    assert "ring 1 sits at the 3 mm minimum gap from the contact disk" in text
    fixed = DesignSpace(thickness_mm=(1.0, 1.0))  # a fixed feature is the caller's choice, not a limit
    assert not any("thickness" in f for f in limit_flags(wp, pred, design, fixed))


def test_optimum_at_design_space_bounds_is_flagged():
    res = optimize(Toy(), TARGET_SETS["A"], rings=(0,), n_starts=16, steps=20, n_refine=8, progress=False)
    assert res.design_key == "[1.0, 38.1, nan, nan, nan, nan]"
    assert res.limits == [
        "thickness 1 mm is at the design space's lower bound 1 mm",
        "contact radius 38.1 mm is at the design space's upper bound 38.1 mm",
    ]
    assert res.to_json()["limits"] == res.limits and res.alternatives == []


class FlatInThickness(AbstractPredictor):
    """Toy without a thickness effect: every thickness ties with the best."""

    @property
    def fidelities(self):
        return ("rig",)

    def members(self, fidelity, d, h, p):
        f = (d[:, 1] / 25.0) * p / 100.0 - 2.3 * h + 0.0 * d[:, 0]
        return jnp.stack([f, 1.1 * f])


def test_near_ties_are_reported_as_alternatives():
    res = optimize(FlatInThickness(), TARGET_SETS["A"], rings=(0,), n_starts=16, steps=20, n_refine=8, progress=False)
    assert res.alternatives, "thickness does not matter: other starts tie"
    t_best = Membrane.from_key(res.design_key).thickness_mm
    seen = [t_best]
    for alt in res.alternatives:
        assert 0.0 <= alt["gap_pct"] <= 2.0 and alt["loss"] >= res.loss
        t = Membrane.from_key(alt["design_key"]).thickness_mm
        assert min(abs(t - s) for s in seen) >= 0.05 * 2.0 - 1e-9  # a different membrane each
        seen.append(t)
    assert len(res.alternatives) <= 5 and res.settings["tie_tol"] == 0.02
    strict = optimize(
        FlatInThickness(), TARGET_SETS["A"], rings=(0,), n_starts=16, steps=20, n_refine=8, progress=False, tie_tol=0.0
    )
    assert all(a["gap_pct"] == 0.0 for a in strict.alternatives)
    with pytest.raises(ValueError, match="tie_tol"):
        optimize(FlatInThickness(), TARGET_SETS["A"], rings=(0,), tie_tol=-1.0)


def test_cli_checks_by_default_only_when_the_simulator_serves_the_model(tmp_path):
    from mfdesign.workflows.models import simulator_for_check

    assert simulator_for_check(tmp_path) == (True, "")
    (tmp_path / "mf.json").write_text(json.dumps({"physics": "standin", "search_physics": "standin"}))
    ok, why = simulator_for_check(tmp_path)
    assert not ok and "standin" in why


def test_cli_prints_limits_and_writes_them(tmp_path):
    import mfdesign
    from mfdesign.cli import app
    from tiny_models import tiny_ensemble

    mfdesign.enable_x64()
    tiny_ensemble().save(tmp_path / "m")
    args = ["optimize", "--model", str(tmp_path / "m"), "--target-set", "A", "--rings", "0", "--starts", "4"]
    args += ["--refine", "2", "--opt-steps", "2", "--no-check", "--thickness-mm", "1.5", "2", "--out", str(tmp_path)]
    r = CliRunner().invoke(app, args)
    assert r.exit_code == 0, r.output
    out = json.loads((tmp_path / "optimize.json").read_text())
    assert isinstance(out["limits"], list) and isinstance(out["alternatives"], list) and out["simulator"] is None
    assert 1.5 <= Membrane.from_key(out["design_key"]).thickness_mm <= 2.0
    assert all(f"limit: {f}" in r.output for f in out["limits"])
    assert "simulator check: not run (asked with --no-check)" in r.output
    bad = CliRunner().invoke(app, [*args[:-2], "--thickness-mm", "0.5", "2", "--out", str(tmp_path)])
    assert bad.exit_code == 2 and "--thickness-mm 0.5 2 is outside the allowed 1-3 mm" in bad.output


def test_starts_are_a_sobol_sequence_that_covers_the_cube_better_than_uniform_draws():
    """Multistarts from scipy.stats.qmc (scrambled Sobol): seeded, in the unit cube, and of
    lower centred discrepancy than uniform random starts of the same count (what made the
    uniform starts leave parts of the design cube unexplored)."""
    from scipy.stats import qmc

    from mfdesign.optimization import sobol_starts

    u = sobol_starts(300, 6, seed=0)
    assert u.shape == (300, 6) and 0.0 <= u.min() and u.max() < 1.0
    np.testing.assert_array_equal(u, sobol_starts(300, 6, seed=0))
    assert not np.array_equal(u, sobol_starts(300, 6, seed=1))
    uniform = [qmc.discrepancy(np.random.default_rng(k).uniform(size=(300, 6))) for k in range(5)]
    assert qmc.discrepancy(u) < min(uniform)
