"""``mfdesign diagnose`` on the analytic stand-in: report files, --effects, config, user effects, bad input."""

from __future__ import annotations

import json
import re

import pytest
from typer.testing import CliRunner

from mfdesign.cli import app
from mfdesign.design import Membrane
from mfdesign.physics import effects as fx
from mfdesign.provenance import sha256 as _sha256
from mfdesign.models.standin import standin_plane
from mfdesign.rig.virtual import Protocol, VirtualRig

runner = CliRunner()
KEYS = ("[2.0, 25.4, nan, nan, nan, nan]", "[1.5, 30.0, 45.0, 6.0, nan, nan]")

USER_EFFECT = """
import jax.numpy as jnp
from mfdesign.physics.effects import MeasurementEffect, Normal, Parameter, register_effect


@register_effect
class ForceGainTest(MeasurementEffect):
    name = "force_gain_test"
    story = "the load cell reads a few per cent high"
    parameters = (Parameter("gain", "1", Normal(1.0, 0.05, 0.5, 1.5), 1.0, 1.05),)

    def observed_force_fn(self, theta, force_fn, rows):
        return lambda h, p: jnp.where(rows.is_force, theta["gain"], 1.0) * force_fn(h, p)
"""
NO_HOOK_EFFECT = (
    USER_EFFECT.split("    def observed_force_fn")[0]
    .replace("force_gain_test", "force_gain_nohook")
    .replace("class ForceGainTest", "class ForceGainNoHook")
)


@pytest.fixture(scope="module")
def data(tmp_path_factory):
    path = tmp_path_factory.mktemp("diag") / "m.parquet"
    rig = VirtualRig(
        effects=["load_cell_offset"],
        theta={"load_cell_offset.offset_n": 0.8},
        seed=2,
        simulator=standin_plane,
        protocol=Protocol(sample_hz=1.0),
    )
    rig.run([Membrane.from_key(k) for k in KEYS], progress=False).to_parquet(path)
    return path


def test_effects_give_a_before_after_report(data, tmp_path):
    out = tmp_path / "rep"
    r = runner.invoke(
        app,
        [
            "diagnose",
            str(data),
            "--physics",
            "standin",
            "--effects",
            "load_cell_offset",
            "--no-search",
            "--out",
            str(out),
        ],
    )
    assert r.exit_code == 0, r.output
    js = json.loads((out / "diagnosis.json").read_text())
    assert js["effects_added"] == ["load_cell_offset"]
    assert js["theta"]["load_cell_offset.offset_n"] == pytest.approx(0.8, abs=0.05)
    assert js["after"]["summary"]["rmse_n"] < 0.5 * js["before"]["summary"]["rmse_n"]
    # provenance (issue 41): version, call (the workflow's name under CliRunner), the data's sha256
    prov = js["provenance"]
    assert prov["mfdesign_version"] and prov["call"] == "mfdesign.workflows.diagnose.diagnose()"
    assert prov["inputs_sha256"] == {str(data): _sha256(data)} and prov["machine"]["cores"] >= 1
    html = (out / "index.html").read_text()
    for png in ("maps_before.png", "maps_after.png", "parity.png", "trial_order.png", "breakdown.png"):
        assert (out / png).is_file() and f'src="{png}"' in html
    # the virtual rig's plates rise smoothly: no stall is claimed (tests/data/test_lift_stalls.py
    # finds them where they are)
    assert js["stalls"] is None and "stall" not in r.output and "stall" not in html


def test_config_file_and_user_effect_module(data, tmp_path):
    mod = tmp_path / "my_effects.py"
    mod.write_text(USER_EFFECT)
    cfg = tmp_path / "diag.toml"
    cfg.write_text(
        f'effects = ["force_gain_test"]\neffects_module = ["{mod}"]\nphysics = "standin"\n'
        '[theta]\n"force_gain_test.gain" = 1.0\n'
    )
    out = tmp_path / "rep"
    r = runner.invoke(app, ["diagnose", str(data), "--config", str(cfg), "--no-search", "--out", str(out)])
    assert r.exit_code == 0, r.output
    js = json.loads((out / "diagnosis.json").read_text())
    assert js["effects_added"] == ["force_gain_test"]
    assert "force_gain_test" in fx.EFFECTS


def test_effect_without_likelihood_hook_is_refused_by_the_exact_backend(data, tmp_path):
    mod = tmp_path / "nohook.py"
    mod.write_text(NO_HOOK_EFFECT)
    r = runner.invoke(
        app,
        [
            "diagnose",
            str(data),
            "--physics",
            "standin",
            "--effects-module",
            str(mod),
            "--effects",
            "force_gain_nohook",
            "--no-search",
            "--out",
            str(tmp_path / "x"),
        ],
    )
    assert r.exit_code == 2
    assert "no likelihood hook" in r.output and len(r.output.strip().splitlines()) == 1


@pytest.mark.parametrize(
    "args, words",
    [
        (["--effects", "no_such_effect"], "unknown effect 'no_such_effect'"),
        (["--theta", "{not json"], "--theta is not valid JSON"),
        (["--physics", "quantum"], "--physics must be one of"),
        (["--effects-module", "nothere.py"], "not a Python file"),
        # click's own usage errors keep the contract too (one line, not a usage block)
        (["--folds", "1"], "Invalid value for '--folds': Input should be greater than or equal to 2"),
        (["--no-such-option"], "No such option: --no-such-option"),
    ],
)
def test_bad_input_is_one_line_exit_2(data, tmp_path, args, words):
    r = runner.invoke(app, ["diagnose", str(data), "--out", str(tmp_path / "x"), *args])
    assert r.exit_code == 2
    assert words in r.output
    assert len(r.output.strip().splitlines()) == 1


@pytest.mark.parametrize(
    "command, option", [("diagnose", "--effects"), ("diagnose", "--candidates"), ("calibrate", "--effects")]
)
def test_a_comma_list_of_effects_is_refused_with_the_repeat_hint(data, tmp_path, command, option):
    """Every list option is written one way, repeated (as --rings): a comma list exits 2 and says so."""
    r = runner.invoke(
        app, [command, str(data), "--out", str(tmp_path / "x"), option, "pressure_sensor,load_cell_offset"]
    )
    assert r.exit_code == 2
    words = " ".join(re.sub("[\u2500-\u257f]", " ", r.output).split())  # click may draw a box around it
    assert "is not an effect name" in words and "repeat the option" in words
    assert not (tmp_path / "x").exists() or not any((tmp_path / "x").iterdir())


def test_missing_data_file(tmp_path):
    r = runner.invoke(app, ["diagnose", str(tmp_path / "none.parquet"), "--out", str(tmp_path / "x")])
    assert r.exit_code == 2 and "does not exist" in r.output
