"""Batch acquisition: decoding, the paper's score, validity, diversity, CLI errors."""

from __future__ import annotations

import json

import jax
import jax.numpy as jnp
import numpy as np
import pytest
from typer.testing import CliRunner

from mfdesign.acquire import (
    EnsemblePredictor,
    FunctionPredictor,
    Grid,
    SplitPredictor,
    evaluate,
    explain,
    propose,
)
from mfdesign.design import DesignSpace, Membrane
from mfdesign.models.ensemble import EnsembleConfig, fit_ensemble
from tiny_models import tiny_ensemble

SPACE = DesignSpace()
GRID = Grid(h_mm=(0.0, 20.0, 40.0), p_pa=(2000.0, 5000.0))
M = 6
W = np.random.default_rng(3).normal(size=(M, 6))


def toy_members(d, h, p):
    """Member m: a linear function of the design (NaN ring slots -> 0), scaled by p, plus h."""
    x = jnp.nan_to_num(d, nan=0.0)
    return (x @ jnp.asarray(W).T).T * (p / 1000.0)[None] + 0.1 * h[None]


def toy_members_np(d, h, p):
    x = np.nan_to_num(d, nan=0.0)
    return (x @ W.T).T * (p / 1000.0)[None] + 0.1 * h[None]


def test_decode_unit_corners_by_hand_and_gradient_under_jit():
    # u = 0: thinnest, smallest disk, minimum widths, all slack after the last ring.
    one = np.asarray(SPACE.decode_unit(jnp.zeros(4), 1))
    np.testing.assert_allclose(one[:4], [1.0, 25.4, 25.4 + 3.0 + 5.0, 5.0], rtol=1e-12)
    assert np.isnan(one[4:]).all()
    # Slack fraction 1 before the ring: the ring sits 3 mm from the clamp.
    u = jnp.array([1.0, 1.0, 0.0, 1.0])
    top = np.asarray(SPACE.decode_unit(u, 1))
    np.testing.assert_allclose(top[:4], [3.0, 38.1, 70.0 - 3.0 - 5.0, 5.0], rtol=1e-12)
    g = jax.jit(jax.grad(lambda v: SPACE.decode_unit(v, 2)[..., 2].sum()))(jnp.full(6, 0.3))
    assert np.all(np.isfinite(np.asarray(g))) and float(g[1]) > 0  # a bigger disk pushes ring 1 out


# One predictor and one set of optimiser settings for every toy proposal: the compiled
# optimiser of each (ring count, fidelity) arm is then shared by the tests.
PRED = FunctionPredictor({"rig": toy_members, "sim": toy_members, "flat": lambda d, h, p: 0.0 * toy_members(d, h, p)})
COSTS = {"rig": 1.0, "sim": 0.01, "flat": 0.01}
SETTINGS = dict(n_restarts=8, grid=GRID, n_steps=4, costs=COSTS)


@pytest.fixture(scope="module")
def rig_proposal():
    return propose(PRED, 2, n_rings=(0, 1, 2), key=1, **SETTINGS)


def test_proposals_are_valid_designs_for_every_ring_count(rig_proposal):
    prop = rig_proposal
    assert len(prop.designs) == 2 and prop.fidelities == ("rig", "rig")
    assert sorted(a["n_rings"] for a in prop.arms) == [0, 1, 2]
    for arm in prop.arms:  # every arm's best batch decodes to valid designs with its ring count
        for u in arm["u"]:
            d = Membrane.from_key(SPACE.decode(u, arm["n_rings"]).key())  # re-validates every rule
            assert d.n_rings == arm["n_rings"] and SPACE.contains(d)
            assert np.all((u >= 0) & (u <= 1))
    for d in prop.designs:
        assert SPACE.contains(Membrane.from_key(d.key()))
    assert all(np.isfinite(prop.scores)) and prop.utility > 0


def test_rig_only_utility_is_the_papers_formula(rig_proposal):
    prop = rig_proposal
    h, p = GRID.points()
    dev = []
    for d in prop.designs:
        f = toy_members_np(np.repeat(d.to_array()[None], len(h), 0), h, p)  # [M, G]
        dev.append(np.sqrt(((f - f.mean(0)) ** 2).sum(1)))  # L2 over the grid, per member
    paper = np.max(np.stack(dev), axis=0).sum()  # sum over members of the max over the batch
    np.testing.assert_allclose(prop.utility, paper, rtol=1e-9)
    np.testing.assert_allclose(evaluate(PRED, prop.designs, ["rig"] * 2, GRID)["utility"], paper, rtol=1e-9)
    assert prop.cost == 2.0 and np.isclose(prop.score, paper / 2.0)
    # the best arm's best restart is what was returned (nothing better was thrown away)
    assert prop.utility >= max(a["best_utility_n"] for a in prop.arms) - 1e-9


def test_score_is_invariant_to_ring_order():
    pred = EnsemblePredictor(tiny_ensemble())
    row = np.array([2.0, 26.0, 36.0, 6.0, 55.0, 8.0])
    swapped = row[[0, 1, 4, 5, 2, 3]]
    a = evaluate(pred, [row], ["rig"], GRID)
    b = evaluate(pred, [swapped], ["rig"], GRID)
    assert a["utility"] > 0
    np.testing.assert_allclose(a["utility"], b["utility"], rtol=1e-10)


def test_ensemble_grid_members_match_predict():
    ens = tiny_ensemble()
    d = np.array([[2.0, 26.0, 36.0, 6.0, np.nan, np.nan], [1.2, 30.0, np.nan, np.nan, np.nan, np.nan]])
    got = np.asarray(EnsemblePredictor(ens).grid_members("rig", jnp.asarray(d), GRID))  # [M, 2, G]
    h, p = GRID.points()
    for b in range(2):
        want = np.asarray(ens.predict(np.repeat(d[b : b + 1], len(h), 0), h, p))
        np.testing.assert_allclose(got[:, b], want, rtol=1e-6, atol=1e-9)


def test_far_design_scores_higher_than_a_design_on_the_data():
    """A small RPN ensemble fitted on thick small-disk ringless membranes disagrees more on a
    thin, large-disk two-ring membrane than on a training design."""
    rng = np.random.default_rng(0)
    train = [Membrane(t, c) for t, c in [(2.0, 25.4), (2.2, 26.5), (1.8, 27.0), (2.1, 25.9)]]
    rows, hs, ps, fs = [], [], [], []
    for m in train:
        h = rng.uniform(0, 60, 150)
        p = rng.uniform(500, 8000, 150)
        f = np.maximum(0.0, 1e-3 * m.contact_radius_mm**2 * (p - 40 * m.thickness_mm * h) / 100.0)
        rows.append(np.repeat(m.to_array()[None], 150, 0))
        hs.append(h), ps.append(p), fs.append(f)
    cfg = EnsembleConfig(n_members=6, steps=300, chunk=300, latent_width=16, latent_depth=2, monotone=True)
    ens = fit_ensemble(
        cfg, np.concatenate(rows), np.concatenate(hs), np.concatenate(ps), np.concatenate(fs), key=0, progress=False
    )
    pred = EnsemblePredictor(ens)
    grid = Grid(h_mm=(0.0, 20.0, 40.0), p_pa=(2000.0, 5000.0, 8000.0))
    on = evaluate(pred, [train[0]], ["rig"], grid)["utility"]
    far = evaluate(pred, [Membrane(1.0, 38.1, [(48.0, 5.0), (62.0, 5.0)])], ["rig"], grid)["utility"]
    assert far > 1.5 * on


def test_batch_is_diverse_when_diversity_pays():
    """Half the members disagree only at thin membranes, half only at thick ones: the best
    pair covers both, and two copies of one design would score half as much."""
    signs = np.array([1.0, -1.0, 1.0, -1.0, 1.0, -1.0])
    centre = np.array([1.2, 1.2, 1.2, 2.8, 2.8, 2.8])

    def members(d, h, p):
        t = d[:, 0]
        bump = jnp.exp(-(((t[None, :] - jnp.asarray(centre)[:, None]) / 0.25) ** 2))
        return jnp.asarray(signs)[:, None] * bump * (1.0 + 0.0 * h[None] + p[None] / 1e4)

    pred = FunctionPredictor({"rig": members})
    prop = propose(pred, 2, n_restarts=24, n_rings=(0,), grid=GRID, n_steps=15, key=0)
    t = sorted(d.thickness_mm for d in prop.designs)
    assert t[0] < 1.6 and t[1] > 2.4, t
    one = evaluate(pred, [prop.designs[0]] * 2, ["rig", "rig"], GRID)["utility"]
    assert prop.utility > 1.5 * one


def test_batch_never_holds_one_membrane_twice():
    """Every member deviates most at the thickest membrane with c ~ 30-31 mm (peaks 0.2 mm
    apart): far designs add nothing to the paper's score, near-copies add ~1e-5 of it, and
    the old greedy took a copy (0.01 mm away) as the second slot, as in the demo. The second
    slot must be a different membrane."""
    signs = np.array([1.0, -1.0, 1.0, -1.0, 1.0, -1.0])
    c_peak = jnp.asarray([30.0, 30.2, 30.4, 30.6, 30.8, 31.0])

    def members(d, h, p):
        t, c = d[None, :, 0], d[None, :, 1]
        bump = jnp.exp(-(((t - 3.0) / 1.0) ** 2) - (((c - c_peak[:, None]) / 4.0) ** 2))
        return jnp.asarray(signs)[:, None] * bump * (1.0 + 0.0 * h[None] + p[None] / 1e4)

    pred = FunctionPredictor({"rig": members, "sim": members})
    for fids in (("rig",), ("rig", "sim")):
        prop = propose(pred, 2, fidelities=fids, n_restarts=8, n_rings=(0,), grid=GRID, n_steps=10, key=0)
        a, b = prop.designs
        assert max(a.thickness_mm, b.thickness_mm) > 2.9, prop.designs  # the best single design
        # apart by MIN_SEPARATION (0.05 of the unit cube) in thickness (2 mm) or contact radius (12.7 mm)
        apart = abs(a.thickness_mm - b.thickness_mm) >= 0.1 or abs(a.contact_radius_mm - b.contact_radius_mm) >= 0.635
        assert apart, [d.key() for d in prop.designs]


def test_cheap_fidelity_wins_when_it_explains_the_spread():
    """``sim`` members carry the whole spread at 1/100 of the cost: the batch goes to sim;
    ``flat`` (as cheap) carries none of it: the batch goes to the rig."""
    prop = propose(PRED, 2, fidelities=("rig", "sim"), n_rings=(0,), **SETTINGS)
    assert prop.fidelities == ("sim", "sim") and np.isclose(prop.cost, 0.02)
    prop = propose(PRED, 2, fidelities=("rig", "flat"), n_rings=(0,), **SETTINGS)
    assert prop.fidelities == ("rig", "rig")


def test_split_predictor_members_add():
    sim, disc = tiny_ensemble(seed=0), tiny_ensemble(seed=1)
    pred = SplitPredictor(sim, disc)
    d = jnp.asarray([[2.0, 26.0, np.nan, np.nan, np.nan, np.nan]])
    rig = pred.grid_members("rig", d, GRID)
    s = EnsemblePredictor(sim).grid_members("rig", d, GRID)
    q = EnsemblePredictor(disc).grid_members("rig", d, GRID)
    np.testing.assert_allclose(rig, s + q)
    np.testing.assert_allclose(pred.grid_members("sim", d, GRID), s)


def test_bad_arguments_say_what_is_allowed():
    pred = PRED
    with pytest.raises(ValueError, match="q \\(batch size\\) must be an integer >= 1"):
        propose(pred, 0)
    with pytest.raises(ValueError, match="not offered by this model; allowed: \\['rig', 'sim', 'flat'\\]"):
        propose(pred, 1, fidelities=("lab",))
    with pytest.raises(ValueError, match="subset of \\(0, 1, 2\\)"):
        propose(pred, 1, n_rings=(3,))
    with pytest.raises(ValueError, match="positive finite"):
        propose(pred, 1, costs={"rig": -1.0})
    with pytest.raises(ValueError, match="Grid.p_pa must be finite"):
        Grid(p_pa=(1.0, float("nan")))


runner = CliRunner()


def _text(r):
    return (r.stdout or "") + (getattr(r, "stderr", "") or "")


def test_cli_bad_input_fails_with_one_line(tmp_path):
    from mfdesign.cli import app

    tiny_ensemble().save(tmp_path / "m")
    cases = [
        (["--model", str(tmp_path / "nope")], "is not a folder"),
        (["--model", str(tmp_path)], "holds no ensemble.json"),
        (["--model", str(tmp_path / "m"), "--q", "0"], "--q 0: allowed: 1 to 256"),
        (["--model", str(tmp_path / "m"), "--fidelity", "lab"], "--fidelity must be rig or sim"),
        (["--model", str(tmp_path / "m"), "--rings", "3"], "--rings must be 0, 1 or 2"),
        (["--model", str(tmp_path / "m"), "--cost-sim", "-1", "--fidelity", "sim"], "--cost-sim -1.0: allowed: 0.0 to"),
        (["--model", str(tmp_path / "m"), "--fidelity", "sim"], "offers fidelities ['rig'], not 'sim'"),
    ]
    for args, msg in cases:
        r = runner.invoke(app, ["propose", *args, "--out", str(tmp_path / "o")])
        text = _text(r).strip()
        assert r.exit_code == 2, (args, text)
        assert msg in text and len(text.splitlines()) == 1, (args, text)


def test_cli_writes_json_and_png(tmp_path):
    from mfdesign.cli import app

    tiny_ensemble().save(tmp_path / "m")
    r = runner.invoke(
        app,
        [
            "propose",
            "--model",
            str(tmp_path / "m"),
            "--q",
            "2",
            "--rings",
            "1",
            "--restarts",
            "4",
            "--opt-steps",
            "2",
            "--no-simulate",  # the simulator check of the membranes: tests/test_sim_runs.py
            "--out",
            str(tmp_path / "o"),
        ],
    )
    assert r.exit_code == 0, _text(r)
    out = json.loads((tmp_path / "o" / "proposal.json").read_text())
    assert len(out["designs"]) == 2 and out["fidelities"] == ["rig", "rig"]
    assert all(Membrane.from_key(k).n_rings == 1 for k in out["designs"])
    assert (tmp_path / "o" / "proposal.png").stat().st_size > 1000


def test_screening_scores_random_batches_exactly_and_refines_the_best():
    """With ``n_refine < n_restarts`` the random batches are scored by a forward pass (the
    same deviations ``evaluate`` gives) and only the best are refined: with 0 L-BFGS steps
    the proposal is the best screened batch, and with steps it is at least as good."""
    from mfdesign.acquire import BatchUncertainty, _screen

    u0 = jax.random.uniform(jax.random.PRNGKey(5), (2, 40, 2, 6))
    n_arr = jnp.asarray([0, 2])
    dev = np.asarray(_screen(BatchUncertainty(PRED, jnp.zeros(1), "rig", GRID), u0, n_arr, SPACE))  # [A, R, q, M]
    assert dev.shape == (2, 40, 2, M)
    for a, n in enumerate((0, 2)):
        for r in (0, 17, 39):
            rows = np.asarray(SPACE.decode_any(u0[a, r], n))
            np.testing.assert_allclose(dev[a, r], evaluate(PRED, rows, ["rig", "rig"], GRID)["deviation"], rtol=1e-10)
    kw = dict(n_rings=(2,), grid=GRID, costs=COSTS, key=3, n_restarts=200)
    util = [propose(PRED, 2, n_refine=r, n_steps=0, **kw).arms[0]["best_utility_n"] for r in (200, 4, 1)]
    assert util[0] == pytest.approx(util[1]) == pytest.approx(util[2])  # the screen keeps the best start
    refined = propose(PRED, 2, n_refine=4, n_steps=10, **kw)
    assert refined.arms[0]["refined"] == 4 and refined.arms[0]["screened"] == 200
    assert refined.arms[0]["best_utility_n"] >= util[0] - 1e-9
    with pytest.raises(ValueError, match="n_refine"):
        propose(PRED, 2, n_refine=0, **kw)


# --------------------------------------------------------------------------- pending, budget, reasons
SIGNS = np.array([1.0, -1.0, 1.0, -1.0, 1.0, -1.0])
CENTRE = np.array([1.2, 1.2, 1.2, 2.8, 2.8, 2.8])


def two_camps(d, h, p):
    """Half the members disagree only at thin membranes (t ~ 1.2 mm), half at thick ones (2.8 mm)."""
    t = d[:, 0]
    bump = jnp.exp(-(((t[None, :] - jnp.asarray(CENTRE)[:, None]) / 0.25) ** 2))
    return jnp.asarray(SIGNS)[:, None] * bump * (1.0 + 0.0 * h[None] + p[None] / 1e4)


CAMPS = FunctionPredictor({"rig": two_camps, "sim": two_camps})


def test_pending_membranes_count_as_measured():
    """A thin membrane being built already tells the thin camp from the consensus: one more
    membrane goes to the thick camp, and the batch utility is ``U(B + P) - U(P)``."""
    thin = Membrane(1.2, 30.0)
    prop = propose(CAMPS, 1, n_restarts=24, n_rings=(0,), grid=GRID, n_steps=15, key=0, pending=[thin])
    assert prop.designs[0].thickness_mm > 2.4, prop.designs
    assert prop.pending == (thin,) and prop.to_json()["pending"] == [thin.key()]
    both = evaluate(CAMPS, [thin, prop.designs[0]], ["rig", "rig"], GRID)["utility"]
    alone = evaluate(CAMPS, [thin], ["rig"], GRID)["utility"]
    np.testing.assert_allclose(prop.utility, both - alone, rtol=1e-9)
    np.testing.assert_allclose(evaluate(CAMPS, prop.designs, ["rig"], GRID, pending=[thin])["utility"], prop.utility)
    assert evaluate(CAMPS, [thin], ["rig"], GRID, pending=[thin])["utility"] == pytest.approx(0.0, abs=1e-12)
    # with both camps pending, nothing is left to gain and no slot repeats a pending membrane
    thick = Membrane(2.8, 30.0)
    prop = propose(CAMPS, 1, n_restarts=24, n_rings=(0,), grid=GRID, n_steps=15, key=0, pending=[thin, thick])
    d = prop.designs[0]
    assert min(abs(d.thickness_mm - 1.2), abs(d.thickness_mm - 2.8)) >= 0.1 or abs(d.contact_radius_mm - 30) >= 0.635
    assert prop.utility == pytest.approx(0.0, abs=1e-6 * alone)


def test_budget_gives_each_fidelity_its_runs_ranked_with_reasons():
    prop = propose(PRED, budget={"rig": 1, "sim": 2}, n_rings=(0,), **SETTINGS)
    assert sorted(prop.fidelities) == ["rig", "sim", "sim"] and prop.budget == {"rig": 1, "sim": 2}
    assert prop.cost == pytest.approx(1.02)
    assert len(prop.fabricate) == 1 and len(prop.simulate) == 2
    assert [r.rank for r in prop.runs] == [1, 2, 3]
    assert sum(r.reduction_n for r in prop.runs) == pytest.approx(prop.utility, rel=1e-9)
    reductions = [r.reduction_n for r in prop.runs]
    assert reductions[0] == max(r.alone_n for r in prop.runs)  # rank 1: the largest reduction alone
    for r in prop.runs:
        assert r.cost == COSTS[r.fidelity] and r.alone_n >= r.reduction_n - 1e-12
        assert "mm" in r.reason and "kPa" in r.reason and " N" in r.reason
        assert r.reduction_rms_n == pytest.approx(r.reduction_n / (M * np.sqrt(6)))  # GRID: 3 x 2 points
    out = prop.to_json()
    assert [r["fidelity"] for r in out["fabricate"]] == ["rig"]
    assert all(r["made_by"].startswith("the tool") for r in out["simulate"])
    with pytest.raises(ValueError, match="not both"):
        propose(PRED, 2, budget={"rig": 1})
    with pytest.raises(ValueError, match="no run"):
        propose(PRED, budget={"rig": 0})
    with pytest.raises(ValueError, match=r"budget\['sim'\]"):
        propose(PRED, budget={"rig": 1, "sim": -1})
    with pytest.raises(ValueError, match="not offered"):
        propose(PRED, budget={"lab": 1})


def test_reason_names_where_the_members_disagree():
    """Members that disagree only at 40 mm and 5 kPa: the reason names that point."""

    def members(d, h, p):
        spot = (jnp.abs(h - 40.0) < 1e-9) & (jnp.abs(p - 5000.0) < 1e-9)
        return jnp.asarray(SIGNS)[:, None] * (1.0 + 2.0 * spot[None]) * (d[None, :, 0] + 0.0 * h[None])

    phrase, where = explain(FunctionPredictor({"rig": members}), Membrane(2.0, 30.0), "rig", GRID)
    assert where["h_mm"] == [40.0] and where["p_pa"] == [5000.0]
    assert where["std_n"] == pytest.approx(6.0)  # members +-(1 + 2) * 2 mm
    assert phrase.startswith("at 40 mm, 5 kPa where the members disagree most (member std up to 6 N)")


def test_reduction_is_reported_as_a_spread_in_newtons():
    """The paper's score sums L2 grid norms over members ("reduces the spread by 16.9 N" read
    as a spread was ~M sqrt(G) times too large): members that sit +-1.5 N off their mean at
    every grid point give a reduction of 1.5 N per member and grid point, whatever M and G."""
    from mfdesign.acquire import _reason, batch_utility, per_point

    signs = np.array([1.0, -1.0, 1.0, -1.0])
    members = 1.5 * signs[:, None] * np.ones((4, len(GRID.h_mm) * len(GRID.p_pa)))  # [M, G]
    dev = np.linalg.norm(members - members.mean(0), axis=1)[:, None]  # [M, q=1]
    score = float(batch_utility(jnp.asarray(dev)))
    assert score == pytest.approx(4 * 1.5 * np.sqrt(6))  # the paper's sum, not a spread
    assert per_point(score, 4, 6) == pytest.approx(1.5)
    words = _reason("at 40 mm, 5 kPa", score, score, 1, 4, 6)
    assert words.startswith("reduces the spread by 1.5 N RMS per member and grid point")
    assert f"the paper's score {score:.3g} N is that summed over 4 members' L2 norms on the 6-point grid" in words


def _split_folder(path):
    import mfdesign

    mfdesign.enable_x64()
    tiny_ensemble(seed=0).save(path / "sim")
    tiny_ensemble(seed=1).save(path / "discrepancy")
    return path


def test_cli_budget_and_pending(tmp_path):
    from mfdesign.cli import app

    model = _split_folder(tmp_path / "split")
    pending = "[2.0, 30.0, nan, nan, nan, nan]"
    args = ["propose", "--model", str(model), "--membranes", "1", "--sim-runs", "1", "--pending", pending]
    args += ["--no-simulate"]  # making the run: tests/test_sim_runs.py
    args += ["--rings", "0", "--thickness-mm", "2", "2", "--restarts", "4", "--refine", "2", "--opt-steps", "2"]
    r = runner.invoke(app, [*args, "--out", str(tmp_path / "o")])
    assert r.exit_code == 0, _text(r)
    out = json.loads((tmp_path / "o" / "proposal.json").read_text())
    assert out["budget"] == {"rig": 1, "sim": 1} and out["pending"] == [pending]
    assert len(out["fabricate"]) == 1 and len(out["simulate"]) == 1
    assert all(Membrane.from_key(k).thickness_mm == 2.0 for k in out["designs"])  # the fixed feature
    text = _text(r)
    assert "membranes to fabricate:" in text and "simulator runs (listed, not made: --no-simulate):" in text
    assert "expected reduction" in text


def test_cli_budget_and_bounds_errors_are_one_line(tmp_path):
    from mfdesign.cli import app

    tiny_ensemble().save(tmp_path / "m")
    m = ["--model", str(tmp_path / "m")]
    cases = [
        ([*m, "--membranes", "1", "--q", "2"], "not both"),
        ([*m, "--membranes", "0"], "the budget holds no run"),
        ([*m, "--membranes", "-1"], "--membranes -1: allowed: 0 to 256"),
        ([*m, "--sim-runs", "1"], "offers fidelities ['rig'], not --sim-runs"),
        ([*m, "--pending", "[2.0, 80.0, nan, nan, nan, nan]"], "--pending"),
        ([*m, "--thickness-mm", "3", "1"], "--thickness-mm takes LO HI with LO <= HI"),
        ([*m, "--contact-radius-mm", "20", "30"], "outside the allowed 25.4-38.1 mm"),
        ([*m, "--contact-radius-mm", "50", "50", "--allow-outside-design-space"], "bounds do not fit"),
    ]
    for args, msg in cases:
        r = runner.invoke(app, ["propose", *args, "--out", str(tmp_path / "o")])
        text = _text(r).strip()
        assert r.exit_code == 2, (args, text)
        assert msg in text and len(text.splitlines()) == 1, (args, text)


class _DataFidelity(FunctionPredictor):
    """PRED's rig and flat members, the fidelity taken as data (an index, traced or not):
    what MultiFidelityPredictor offers acquisition."""

    fidelity_as_data = True

    def members(self, fidelity, design, h_mm, p_pa):
        if isinstance(fidelity, str):
            return super().members(fidelity, design, h_mm, p_pa)
        f = toy_members(design, h_mm, p_pa)
        return jnp.where(jnp.asarray(fidelity) == 0, f, 0.5 * f)


def test_a_fidelity_as_data_shares_one_program_and_pads_the_smaller_count():
    """A budget of 2 rig + 1 sim with the fidelity as data: the sim batch is padded to 2
    (a masked slot) and one compiled L-BFGS serves both fidelities; the proposal is that
    of the same members given by name, one program per fidelity, unpadded."""
    from mfdesign.acquire import _optimise

    twin = FunctionPredictor({"rig": toy_members, "sim": lambda d, h, p: 0.5 * toy_members(d, h, p)})
    data = _DataFidelity({"rig": toy_members, "sim": lambda d, h, p: 0.5 * toy_members(d, h, p)})
    kw = dict(budget={"rig": 2, "sim": 1}, n_rings=(0, 1), n_restarts=6, n_refine=3, grid=GRID, n_steps=4, key=2)
    before = _optimise.jitted._cached._cache_size()
    got = propose(data, **kw)
    assert _optimise.jitted._cached._cache_size() == before + 1  # one program for rig and sim
    ref = propose(twin, **kw)
    assert got.fidelities == ref.fidelities
    for a, b in zip(got.designs, ref.designs):
        np.testing.assert_allclose(a.to_array(), b.to_array(), rtol=1e-9, equal_nan=True)
    assert got.utility == pytest.approx(ref.utility, rel=1e-9)
    for a, b in zip(got.arms, ref.arms):
        np.testing.assert_allclose(a["restart_utility"], b["restart_utility"], rtol=1e-9)
        assert a["u"].shape == b["u"].shape and a["dev"].shape == b["dev"].shape
    assert [r.reason for r in got.runs] == [r.reason for r in ref.runs]


def test_fidelities_share_a_program_only_while_the_padding_is_cheap():
    """The demo's budget (2 rig + 1 sim, 2 restarts x 5 steps) pads one slot for a few
    L-BFGS steps: shared. The campaign's defaults (1,000 screened, 32 refined x 20 steps)
    would pad thousands of slot-steps (the sim arm took twice as long): one program each."""
    from mfdesign.acquire import SHARED_MAX_PADDING, _padding_work

    assert _padding_work([2, 1], 2, 3, 2, 2, 5) == 30 <= SHARED_MAX_PADDING
    assert _padding_work([2, 2], 2, 3, 1000, 32, 20) == 0  # equal counts: nothing to pad
    assert _padding_work([2, 1], 2, 3, 1000, 32, 20) > SHARED_MAX_PADDING
