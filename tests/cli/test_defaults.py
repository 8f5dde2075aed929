"""One set of calibration defaults: ``calibrate``, ``fit-mf``, the demo and a campaign (issue 41).

They once differed (calibrate 3000 steps / 3000 rows, fit-mf 2000 / 1500, the demo 4000
steps), so the same data gave different fits by the command that ran them.
"""

import typer.main

from mfdesign.campaign import Settings
from mfdesign.cli import app
from mfdesign.workflows.demo import DemoSettings


def _defaults(name: str) -> dict:
    command = typer.main.get_command(app).commands[name]
    return {p.name: p.default for p in command.params}


def test_calibrate_and_fit_mf_take_the_campaign_defaults():
    s = Settings()
    for name in ("calibrate", "fit-mf"):
        d = _defaults(name)
        assert (d["steps"], d["walkers"], d["max_rows"], d["seed"]) == (s.mcmc_steps, s.walkers, s.max_rows, s.seed), (
            name
        )
    fit_mf = _defaults("fit-mf")
    assert (fit_mf["members"], fit_mf["delta_steps"]) == (s.members, s.delta_steps)
    assert "members" not in _defaults("calibrate")  # no ensemble in a plain calibration


def test_demo_chain_ceiling_is_the_campaign_one():
    assert DemoSettings().mcmc_steps == Settings().mcmc_steps
    assert DemoSettings().max_rows == Settings().max_rows
