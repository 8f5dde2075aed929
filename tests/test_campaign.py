"""mfdesign.Campaign: a lab's loop in one folder (issue 41).

Stand-in physics, virtual-rig data of two membranes at a few heights and tiny chains
(``Settings.quick``): these check the loop's bookkeeping (sources and their hashes,
rounds, proposals, reopening, a killed step), not the fit's quality.
"""

from __future__ import annotations

import json
import os
import signal
import subprocess
import sys
import textwrap
from pathlib import Path

import numpy as np
import pytest
from typer.testing import CliRunner

from mfdesign.campaign import Campaign, Settings, _sha256
from mfdesign.cli import app
from mfdesign.errors import InputError

ROOT = Path(__file__).resolve().parents[1]
runner = CliRunner()

KEYS = ("[2.0, 25.4, nan, nan, nan, nan]", "[2.33, 29.63, 37.63, 5.0, 62.0, 5.0]")
# where the bit-for-bit comparison predicts: a new membrane and a calibrated one
DESIGN = np.array([[1.7, 31.0, np.nan, np.nan, np.nan, np.nan]] * 3 + [[2.0, 25.4, np.nan, np.nan, np.nan, np.nan]])
H_MM = np.array([0.0, 20.0, 40.0, 10.0])
P_PA = np.array([3000.0, 5000.0, 7000.0, 4000.0])


def rig_data(keys=KEYS, seed: int = 1):
    """Force trials of ``keys`` on the virtual rig (stand-in simulator, a hidden 150 Pa
    pressure offset), at 4 heights, 0.2 samples a second: a few hundred rows."""
    from mfdesign.design import Membrane
    from mfdesign.models.standin import standin_plane
    from mfdesign.physics.params import SimParams
    from mfdesign.rig.virtual import Protocol, VirtualRig

    rig = VirtualRig(
        effects=["pressure_sensor"],
        theta={"pressure_sensor.offset_pa": 150.0},
        seed=seed,
        protocol=Protocol(sample_hz=0.2, trials_per_height=1, heights_mm=(0.0, 20.0, 40.0, 60.0)),
        simulator=standin_plane,
        base_params=SimParams(mu_pa=34e3, jm=45.0),
    )
    return rig.run([Membrane.from_key(k) for k in keys], lift=False, progress=False)


@pytest.fixture(scope="module")
def fitted(tmp_path_factory):
    """A campaign with one fitted round (seed 3: the posterior's thinning seed is not 0)."""
    folder = tmp_path_factory.mktemp("campaign") / "c"
    campaign = Campaign.create(folder, data=rig_data(), settings=Settings.quick("standin", seed=3))
    first = campaign.fit()
    return folder, first


def test_create_then_open_keeps_settings_and_hashes_the_source(tmp_path):
    settings = Settings.quick("standin", seed=7, effects=("pressure_sensor",))
    table = rig_data()
    Campaign.create(tmp_path / "c", data=table, settings=settings, call="test")
    opened = Campaign.open(tmp_path / "c")
    assert opened.settings == settings and opened.effects == ("pressure_sensor",)
    status = opened.status()
    (source,) = status.sources
    assert source.rows == len(table) and set(source.membranes) == set(KEYS)
    assert source.sha256 == _sha256(tmp_path / "c" / source.file) and not status.problems
    assert len(opened.data()) == len(table)
    with pytest.raises(InputError, match="already holds a campaign"):
        Campaign.create(tmp_path / "c", data=table)
    # a changed source is named, never read silently
    (tmp_path / "c" / source.file).write_bytes(b"not the told bytes")
    assert "changed" in opened.status().problems[0]
    with pytest.raises(InputError, match="changed"):
        opened.data()


def test_bad_settings_and_a_folder_without_a_campaign_fail_in_one_line(tmp_path):
    with pytest.raises(InputError, match="settings.physics"):
        Settings(physics="fe")
    with pytest.raises(InputError, match="settings.mcmc_steps"):
        Settings(mcmc_steps=0)
    with pytest.raises(InputError, match="unknown setting"):
        Settings.from_json({"mcmc_step": 10})
    r = runner.invoke(app, ["status", str(tmp_path)])
    assert r.exit_code == 2 and "not a campaign" in r.output and len(r.output.strip().splitlines()) == 1


def test_reopened_campaign_predicts_bit_for_bit(fitted):
    folder, first = fitted
    again = Campaign.open(folder).model()
    a = np.asarray(first.fit.mf.predict(DESIGN, H_MM, P_PA))
    b = np.asarray(again.mf.predict(DESIGN, H_MM, P_PA))
    assert a.shape[0] > 1 and np.isfinite(a).all()
    assert np.array_equal(a, b)  # bit for bit, every posterior draw in the same order
    assert again.seed == first.fit.seed == 3


def test_status_lists_the_round_and_its_files(fitted):
    folder, first = fitted
    status = Campaign.open(folder).status()
    assert [r["round"] for r in status.rounds] == [0] and status.rounds[0]["heldout"] is None
    assert status.rounds[0]["data"]["membranes"] == 2
    record = json.loads((first.folder / "round.json").read_text())
    assert record["provenance"]["seeds"] == {"seed": 3} and record["provenance"]["machine"]["cores"] >= 1
    assert set(record["data"]["sources"]) == {"s000"}
    for name in ("mf.json", "posterior.json", "posterior.npz", "posterior.nc", "delta/ensemble.json"):
        assert (first.folder / "model" / name).is_file(), name
    # the model's JSON carry the round's provenance (issue 41): version, call, seed, sources
    for name in ("mf.json", "posterior.json"):
        prov = json.loads((first.folder / "model" / name).read_text())["provenance"]
        assert prov["mfdesign_version"] and prov["call"] == "Campaign.fit()" and prov["seeds"] == {"seed": 3}
        assert prov["inputs_sha256"] == record["data"]["sources"] and prov["machine"]["cores"] >= 1
    r = runner.invoke(app, ["status", str(folder)])
    assert r.exit_code == 0 and "\n    0          2 " in r.output, r.output


def test_a_model_folder_written_before_provenance_still_loads(fitted, tmp_path):
    """``mf.json`` and ``posterior.json`` without ``"provenance"`` (older folders) reload
    into the same predictions: readers ignore the record."""
    import shutil

    from mfdesign.calibration.workflow import MFFit

    _, first = fitted
    old = tmp_path / "model"
    shutil.copytree(first.folder / "model", old)
    for name in ("mf.json", "posterior.json"):
        js = json.loads((old / name).read_text())
        del js["provenance"]
        (old / name).write_text(json.dumps(js))
    again = MFFit.load(old)
    np.testing.assert_array_equal(
        np.asarray(again.mf.predict(DESIGN, H_MM, P_PA)), np.asarray(first.fit.mf.predict(DESIGN, H_MM, P_PA))
    )


def test_tell_with_an_unknown_id_fails_in_one_line(fitted, tmp_path):
    folder, _ = fitted
    with pytest.raises(InputError, match="'p99' is not in campaign"):
        Campaign.open(folder).tell("p99", rig_data())
    data = tmp_path / "m.parquet"
    from mfdesign.data.store import write_parquet

    write_parquet(rig_data(), data)
    r = runner.invoke(app, ["tell", str(folder), "p99", str(data)])
    assert r.exit_code == 2, r.output
    assert len(r.output.strip().splitlines()) == 1 and "p99" in r.output
    assert len(Campaign.open(folder).status().sources) == 1  # nothing was added


_KILLED_FIT = """
import os, sys, time
from mfdesign.calibration import workflow
from mfdesign.campaign import Campaign

folder = sys.argv[1]
fit0 = workflow.MFFit.load(os.path.join(folder, "rounds", "round-000", "model"))
# the calibration is not what is tested here: hand back round 0's fit at once
workflow.fit_multi_fidelity = lambda *a, **k: fit0
real_rename = os.rename

def rename(src, dst):
    if os.path.basename(str(src)).startswith(".round-"):
        print("RENAMING", flush=True)  # every file of the round is written: killed now
        time.sleep(600)
    return real_rename(src, dst)

os.rename = rename
Campaign.open(folder).fit()
"""


def test_a_fit_killed_before_its_round_is_renamed_leaves_the_last_round_intact(fitted, tmp_path):
    import shutil

    folder = tmp_path / "c"
    shutil.copytree(fitted[0], folder)
    before = np.asarray(Campaign.open(folder).model().mf.predict(DESIGN, H_MM, P_PA))
    script = tmp_path / "killed.py"
    script.write_text(textwrap.dedent(_KILLED_FIT))
    env = dict(os.environ, JAX_PLATFORMS="cpu", PYTHONPATH=str(ROOT))
    proc = subprocess.Popen([sys.executable, str(script), str(folder)], stdout=subprocess.PIPE, text=True, env=env)
    try:
        line = proc.stdout.readline()  # type: ignore[union-attr]
        assert line.strip() == "RENAMING", line
    finally:
        proc.send_signal(signal.SIGKILL)
        proc.wait()
    assert list((folder / "rounds").glob(".round-001.*.tmp"))  # the half round is there, unread
    opened = Campaign.open(folder)
    assert opened.rounds() == [0] and [r["round"] for r in opened.status().rounds] == [0]
    assert np.array_equal(before, np.asarray(opened.model().mf.predict(DESIGN, H_MM, P_PA)))
    opened.report()  # a write: the killed run's lock is taken over
    assert (folder / "report.json").is_file() and not (folder / ".mfdesign.lock").exists()


@pytest.mark.slow
def test_ask_tell_fit_makes_a_second_round_with_its_heldout_error(fitted, tmp_path):
    """One more round through the CLI (the commands of docs/campaign.md): ask (a rig
    membrane and a simulator run), the membrane "built" on the virtual rig, tell, fit."""
    import shutil

    from mfdesign.data.store import write_parquet

    folder = tmp_path / "c"
    shutil.copytree(fitted[0], folder)
    r = runner.invoke(app, ["ask", str(folder), "--q", "1", "--sim-runs", "1"])
    assert r.exit_code == 0, r.output
    campaign = Campaign.open(folder)
    entries = campaign.status().proposals
    assert all(e.id in r.output for e in entries)
    rig = [e for e in entries if e.fidelity == "rig"]
    sim = [e for e in entries if e.fidelity == "sim"]
    assert len(rig) == 1 and rig[0].status == "pending" and len(sim) == 1 and sim[0].status == "measured"
    again = campaign.ask(q=1)  # the pending membrane counts as measured: not asked twice
    assert again[0].design != rig[0].design
    data = tmp_path / "built.parquet"
    write_parquet(rig_data((rig[0].design,), seed=5), data)
    r = runner.invoke(app, ["tell", str(folder), rig[0].id, str(data)])
    assert r.exit_code == 0 and "measured" in r.output, r.output
    r = runner.invoke(app, ["fit", str(folder)])
    assert r.exit_code == 0 and "round 1" in r.output, r.output
    status = Campaign.open(folder).status()
    held = status.rounds[1]["heldout"]
    assert held["model_round"] == 0 and rig[0].design in held["membranes"] and np.isfinite(held["rmse_n"])
    assert {p.id: p.status for p in status.proposals}[again[0].id] == "pending"


def test_a_fit_made_elsewhere_is_adopted_as_the_next_round_and_continues(fitted, tmp_path):
    """The demo's way in (``mfdesign demo --out D`` leaves a campaign): a fit made outside
    the campaign becomes its round 0, reloadable bit for bit, and ``ask`` continues it."""
    folder = tmp_path / "adopted"
    campaign = Campaign.create(folder, data=rig_data(), settings=Settings.quick("standin", seed=3))
    made_elsewhere = Campaign.open(fitted[0]).model(0)  # an MFFit, as the demo holds one
    written = fitted[0] / "rounds" / "round-000" / "model" / "posterior.nc"
    r0 = campaign.adopt(made_elsewhere, posterior_nc=written)
    assert r0.number == 0 and campaign.rounds() == [0]
    # the posterior.nc the demo already wrote is copied, not computed again
    assert (r0.folder / "model" / "posterior.nc").read_bytes() == written.read_bytes()
    np.testing.assert_array_equal(
        np.asarray(campaign.model(0).mf.predict(DESIGN, H_MM, P_PA)),
        np.asarray(made_elsewhere.mf.predict(DESIGN, H_MM, P_PA)),
    )
    record = json.loads((folder / "rounds" / "round-000" / "round.json").read_text())
    assert record["provenance"]["call"] == "Campaign.adopt()" and record["heldout"] is None
    entries = campaign.ask(q=1)
    assert len(entries) == 1 and entries[0].status == "pending"


def test_the_demo_replaces_only_its_own_untouched_campaign(fitted, tmp_path):
    """A re-run of the demo into its folder replaces the demo's campaign; a campaign a lab
    has continued (more rounds, sources or proposals) is refused in one line."""
    import shutil

    from mfdesign.workflows.demo import check_campaign_folder

    fresh = tmp_path / "fresh"
    Campaign.create(fresh, data=rig_data(), settings=Settings.quick("standin"))
    check_campaign_folder(fresh)  # the demo's own, untouched: no error
    check_campaign_folder(tmp_path / "nothing")  # no campaign: no error
    continued = tmp_path / "continued"
    shutil.copytree(fitted[0], continued)
    Campaign.open(continued).ask(q=1)
    with pytest.raises(InputError, match=r"holds a campaign continued after the demo .*allowed: a new --out folder"):
        check_campaign_folder(continued)


def test_every_model_option_takes_a_campaign_folder(fitted, tmp_path):
    """``--model D`` (propose, optimize, diagnose) reads a campaign's latest round; a
    campaign with no round yet is refused in one line."""
    from mfdesign.workflows.models import load_fit, load_predictor, model_folder

    folder, _ = fitted
    assert model_folder(folder) == folder / "rounds" / "round-000" / "model"
    a = np.asarray(load_fit(folder).mf.predict(DESIGN, H_MM, P_PA))
    b = np.asarray(Campaign.open(folder).model().mf.predict(DESIGN, H_MM, P_PA))
    assert np.array_equal(a, b)
    assert set(load_predictor(folder).fidelities) == {"rig", "sim"}
    empty = tmp_path / "empty"
    Campaign.create(empty, data=rig_data(), settings=Settings.quick("standin"))
    with pytest.raises(InputError, match="has no fitted round yet; allowed: fit it first"):
        load_predictor(empty)


def test_ask_checks_its_membranes_to_build_with_the_simulator(fitted, tmp_path):
    """Issue 43: a membrane the campaign asks for is re-computed by the simulator (in the batch
    of its simulator runs) before it is shown; its entry's note says how far the model is off
    there. A stand-in campaign's own planes check nothing: no note then."""
    import shutil

    from mfdesign.campaign import _standin_planes

    folder = tmp_path / "c"
    shutil.copytree(fitted[0], folder)
    calls = []

    def offset_planes(designs, spec, params):  # a "simulator" 50 N above the stand-in
        calls.append([d.key() for d in designs])
        return [(f + 50.0, s, lock) for f, s, lock in _standin_planes(designs, spec, params)]

    (plain,) = Campaign.open(folder).ask(q=1)
    assert plain.note == ""
    (entry,) = Campaign.open(folder).ask(q=1, simulate=offset_planes)
    assert len(calls) == 1 and calls[0] == [entry.design]  # one batch
    assert entry.status == "pending" and entry.note.startswith("simulator check (converged): model (sim fidelity)")
    assert "well beyond the predicted spread" in entry.note


def test_walkers_are_a_least_number_as_the_membranes_grow(tmp_path):
    """A campaign's model grows a thickness latent per membrane: settings' walkers fixed for
    round 0 (the demo's 32) must not fail a later round with more parameters ("emcee needs
    n_walkers >= 2 * dim"); that round takes 2 dim + 2."""
    campaign = Campaign.create(tmp_path / "c", data=rig_data(), settings=Settings.quick("standin", walkers=4))
    done = campaign.fit()
    dim = done.fit.model.dim
    assert dim >= 3 and done.fit.posterior.convergence["n_walkers"] == 2 * dim + 2


def test_ask_searches_only_the_ring_counts_asked_for(fitted, tmp_path):
    """`ask --rings 0` builds ringless membranes only (a lab without fabric rings in stock);
    `--each-ring-count` asks for q of each kind, one ask per ring count; a ring count
    outside 0-2 fails in one line, exit 2."""
    import shutil

    from mfdesign.design import Membrane

    folder = tmp_path / "c"
    shutil.copytree(fitted[0], folder)
    r = runner.invoke(app, ["ask", str(folder), "--q", "2", "--rings", "0"])
    assert r.exit_code == 0, r.output
    asked = Campaign.open(folder).status().proposals
    assert len(asked) == 2 and all(Membrane.from_key(e.design).n_rings == 0 for e in asked)
    (two,) = Campaign.open(folder).ask(q=1, n_rings=(2,))
    assert Membrane.from_key(two.design).n_rings == 2
    r = runner.invoke(app, ["ask", str(folder), "--q", "1", "--each-ring-count"])
    assert r.exit_code == 0, r.output
    each = Campaign.open(folder).status().proposals[3:]  # after p1, p2 (ringless) and p3 (two rings)
    assert sorted(Membrane.from_key(e.design).n_rings for e in each) == [0, 1, 2], r.output
    assert all(e.id in r.output for e in each) and len({e.design for e in (*asked, two, *each)}) == 6
    r = runner.invoke(app, ["ask", str(folder), "--q", "1", "--rings", "3"])
    assert r.exit_code == 2 and "ring" in r.output and "Traceback" not in r.output, r.output
