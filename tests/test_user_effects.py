"""A user's own effect everywhere (issue 41 item 4): ``--effects-module FILE.py`` on
``calibrate`` and ``fit-mf`` (their output folder keeps the file, for every ``--model
OUT``), and a campaign that keeps the file (``Campaign.create``'s ``effects_module``,
``mfdesign create``) and imports it again on every open.

The effect is the docs' example (``docs/examples/lift_height_offset.py``). Before each
test it is taken out of the registry (monkeypatch puts it back), so that it is known only
through the file under test. Stand-in physics and tiny chains: this checks the plumbing,
not the fit's quality.
"""

from __future__ import annotations

import json
import shutil
from pathlib import Path

import pytest
from typer.testing import CliRunner

from mfdesign import campaign as campaign_module
from mfdesign import user_effects
from mfdesign.campaign import Campaign, Settings
from mfdesign.cli import app
from mfdesign.errors import InputError
from mfdesign.physics import effects as fx

ROOT = Path(__file__).resolve().parents[1]
EXAMPLE = ROOT / "docs" / "examples" / "lift_height_offset.py"
NAME, PARAMETER = "lift_height_offset", "lift_height_offset.offset_mm"
runner = CliRunner()


def forget_the_effect(monkeypatch) -> None:
    """As a new process knows it: not at all (the registry and the campaigns' import cache)."""
    monkeypatch.delitem(fx.EFFECTS, NAME, raising=False)
    monkeypatch.setattr(user_effects, "_IMPORTED", {})


@pytest.fixture(scope="module")
def two(tmp_path_factory):
    """Two bundled membranes (as tests/cli/test_mf_model_folder.py)."""
    from mfdesign.data.store import read_parquet, write_parquet
    from mfdesign.workflows.demo import BUNDLED

    meas = read_parquet(BUNDLED)
    path = tmp_path_factory.mktemp("ue") / "two.parquet"
    write_parquet(meas.subset(meas.design_keys[:2]), path)
    return path


SMALL = ["--physics", "standin", "--mcmc-steps", "30", "--walkers", "16", "--max-rows", "60"]


@pytest.mark.parametrize("command", ["calibrate", "fit-mf"])
def test_calibrate_and_fit_mf_take_a_user_effects_module(two, tmp_path, monkeypatch, command):
    forget_the_effect(monkeypatch)
    out = tmp_path / "o"
    args = [command, str(two), "--out", str(out), *SMALL, "--effects", NAME]
    args += ["--members", "2", "--delta-steps", "20"] if command == "fit-mf" else []
    r = runner.invoke(app, args)  # without the file: the effect is unknown, in one line
    assert r.exit_code == 2 and "unknown effect(s) ['lift_height_offset']" in r.output, r.output
    assert "--effects-module FILE.py" in r.output and len(r.output.strip().splitlines()) == 1
    r = runner.invoke(app, [*args, "--effects-module", str(EXAMPLE)])
    assert r.exit_code == 0, r.output
    assert PARAMETER in r.output  # the posterior table
    post = json.loads((out / "posterior.json").read_text())
    assert PARAMETER in post["names"] and post["effects"] == [NAME]
    # the file is an input of the run: its sha256 in the provenance
    assert len(post["provenance"]["inputs_sha256"][str(EXAMPLE)]) == 64
    kept = json.loads((out / "effects" / "modules.json").read_text())["effects_modules"]
    assert [m["effects"] for m in kept] == [[NAME]] and (out / kept[0]["file"]).read_bytes() == EXAMPLE.read_bytes()
    if command == "fit-mf":
        from mfdesign.workflows.models import load_fit

        assert json.loads((out / "mf.json").read_text())["effects"] == [NAME]
        forget_the_effect(monkeypatch)  # a new session: every --model OUT imports the kept copy
        assert PARAMETER in load_fit(out).posterior.names
        (out / kept[0]["file"]).write_text(EXAMPLE.read_text() + "# edited\n")
        forget_the_effect(monkeypatch)
        with pytest.raises(InputError, match="effects module .* is missing or changed since it was kept"):
            load_fit(out)


@pytest.mark.parametrize("command", ["calibrate", "fit-mf"])
@pytest.mark.parametrize(
    "name, text, words",
    [
        ("missing.py", None, "not a Python file (no such file; allowed: an existing .py file"),
        ("effects.txt", "x = 1\n", "not a Python file (allowed: an existing .py file"),
        ("broken.py", "raise RuntimeError('boom')\n", "failed to import: RuntimeError: boom"),
        ("typo.py", "import no_such_module_xyz\n", "failed to import: ModuleNotFoundError"),
    ],
)
def test_a_bad_effects_module_is_one_line_and_exit_2(two, tmp_path, command, name, text, words):
    module = tmp_path / name
    if text is not None:
        module.write_text(text)
    r = runner.invoke(app, [command, str(two), "--out", str(tmp_path / "o"), "--effects-module", str(module)])
    assert r.exit_code == 2, r.output
    assert f"--effects-module {module}: " in r.output or f"--effects-module {module} failed" in r.output
    assert words in r.output and len(r.output.strip().splitlines()) == 1 and "Traceback" not in r.output


def test_a_campaign_keeps_the_effects_file_across_create_open_fit_ask(tmp_path, monkeypatch):
    """create copies the file (with its sha256); the user's file may go; every open (in a
    new process: here the registry is emptied) imports the copy, so fit (the CLI's),
    diagnose and ask know the effect; a changed copy is refused in one line."""
    from test_campaign import rig_data

    forget_the_effect(monkeypatch)
    mine = tmp_path / "mine" / "my_effects.py"
    mine.parent.mkdir()
    shutil.copy(EXAMPLE, mine)
    folder = tmp_path / "c"
    settings = Settings.quick("standin", seed=3, effects=(NAME,))
    Campaign.create(folder, data=rig_data(), settings=settings, effects_module=[mine])
    shutil.rmtree(mine.parent)  # the campaign does not depend on the user's file staying put
    record = json.loads((folder / "campaign.json").read_text())["effects_modules"]
    assert [m["effects"] for m in record] == [[NAME]] and record[0]["origin"] == str(mine)
    copy = folder / record[0]["file"]
    assert copy.read_bytes() == EXAMPLE.read_bytes() and record[0]["sha256"] == campaign_module._sha256(copy)

    forget_the_effect(monkeypatch)
    r = runner.invoke(app, ["fit", str(folder)])  # Campaign.open: the copy imported again
    assert r.exit_code == 0 and "round 0" in r.output and NAME in r.output, r.output
    assert NAME in fx.EFFECTS
    post = json.loads((folder / "rounds" / "round-000" / "model" / "posterior.json").read_text())
    assert PARAMETER in post["names"]

    forget_the_effect(monkeypatch)
    opened = Campaign.open(folder)
    assert opened.settings.effects == opened.effects == (NAME,)
    assert PARAMETER in opened.model().posterior.names  # a round's model reloads with the effect
    diagnosis = opened.diagnose()  # the effect in force: fitted with the residuals' before / after
    assert NAME in diagnosis.effects and PARAMETER in diagnosis.theta
    (entry,) = opened.ask(q=1)
    assert entry.status == "pending"
    assert f"effects module {record[0]['file']} (from {mine}): {NAME}" in opened.status().summary()

    copy.write_text(copy.read_text() + "\n# edited\n")
    with pytest.raises(InputError, match="effects module .* is missing or changed since it was kept"):
        Campaign.open(folder)
    r = runner.invoke(app, ["status", str(folder)])
    assert r.exit_code == 2 and "sha256 differs" in r.output and len(r.output.strip().splitlines()) == 1
    # a record never points out of the campaign's effects/ folder (campaign.json edited by hand)
    raw = json.loads((folder / "campaign.json").read_text())
    raw["effects_modules"][0]["file"] = "effects/../../elsewhere.py"
    (folder / "campaign.json").write_text(json.dumps(raw))
    with pytest.raises(InputError, match="is not in its effects/ folder"):
        Campaign.open(folder)


def test_a_campaign_refuses_an_effect_it_could_not_know_again(tmp_path, monkeypatch):
    """An effect registered in Python only (no file the campaign keeps), a missing effects
    file, an unknown effect: refused by create, in one line, before anything is written."""
    from test_campaign import rig_data

    forget_the_effect(monkeypatch)
    table = rig_data()
    monkeypatch.setitem(fx.EFFECTS, "only_in_python_test", None)  # taken out again when the test ends

    @fx.register_effect
    class OnlyInPython(fx.MeasurementEffect):
        name = "only_in_python_test"
        story = "registered in this session, by no file"
        parameters = (fx.Parameter("gain", "1", fx.Normal(1.0, 0.05, 0.5, 1.5), 1.0, 1.05),)

        def observed_force_fn(self, theta, force_fn, rows):
            return lambda h, p: theta["gain"] * force_fn(h, p)

    assert fx.EFFECTS["only_in_python_test"] is OnlyInPython
    cases = [
        (dict(settings=Settings.quick(effects=("only_in_python_test",))), "registered in Python, not by a file"),
        (dict(effects_module=[tmp_path / "gone.py"]), "effects module .*gone.py: not a Python file"),
        (dict(settings=Settings.quick(effects=(NAME,))), r"settings.effects \['lift_height_offset'\]: unknown"),
    ]
    for k, (kwargs, words) in enumerate(cases):
        with pytest.raises(InputError, match=words):
            Campaign.create(tmp_path / f"c{k}", data=table, **kwargs)
        assert not (tmp_path / f"c{k}" / "campaign.json").exists()


def test_the_create_command_keeps_the_effects_file(tmp_path, monkeypatch):
    """``mfdesign create D DATA --effects-module FILE.py``: the same record as Python's
    ``Campaign.create``; a bad file or an effect no file registers: one line, exit 2."""
    from test_campaign import rig_data

    from mfdesign.data.store import write_parquet

    forget_the_effect(monkeypatch)
    data = tmp_path / "m.parquet"
    write_parquet(rig_data(), data)
    folder = tmp_path / "c"
    args = ["create", str(folder), str(data), "--physics", "standin", "--quick", "--seed", "3", "--effects", NAME]
    r = runner.invoke(app, [*args, "--effects-module", str(EXAMPLE)])
    assert r.exit_code == 0, r.output
    assert f"effects module effects/m0_lift_height_offset.py (from {EXAMPLE}): {NAME}" in r.output
    assert f"next: mfdesign fit {folder}" in r.output
    forget_the_effect(monkeypatch)
    opened = Campaign.open(folder)
    assert opened.settings == Settings.quick("standin", seed=3, effects=(NAME,)) and NAME in fx.EFFECTS
    for more, words in (
        (["--effects-module", str(tmp_path / "gone.py")], "gone.py: not a Python file (no such file"),
        ([], "settings.effects ['lift_height_offset']: unknown"),
    ):
        forget_the_effect(monkeypatch)
        r = runner.invoke(app, ["create", str(tmp_path / "d"), str(data), "--effects", NAME, *more])
        assert r.exit_code == 2 and words in r.output and len(r.output.strip().splitlines()) == 1, r.output
