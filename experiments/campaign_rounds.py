"""Continue the demo's campaign for more rounds on the virtual rig (issue 41, item 3).

``mfdesign demo --out D`` leaves a campaign in ``D`` (round 0: the corrected fit). Each
further round here is what a lab does:

1. ``ask``: the campaign proposes ``--q`` membranes to build;
2. "build" them: the virtual rig measures each (the bundled dataset's own truth: the
   simulator, or the stand-in for a stand-in campaign, with the hidden effect of the
   dataset's card and its noise), written as a Parquet file;
3. ``tell``: the measurements join the campaign;
4. ``fit``: the next round (its ``round.json`` records the previous round's error on the
   membranes told since: the campaign's own held-out error).

Beside that, every round's model predicts a fixed test set: membranes measured on the
same virtual rig that no round ever sees. Its RMSE [N] and 90 % coverage against the
rig's readings, and its RMSE against the rig's noise-free truth at the same set-points
(the model's own error, which the readings' 0.2 N noise hides), are the held-out error
this experiment follows from round to round.

    python experiments/campaign_rounds.py --campaign out/demo --rounds 2 --q 2

``--world stiff-rings --start`` runs in a world the model does not hold instead: the
stand-in whose rings raise the contact pressure 0.65 each where the model says 0.4
(:class:`mfdesign.models.standin.StandinWorld`), round 0 the stand-in demo on the card's
designs measured there (without thickness latents: the world casts every membrane alike),
and six test membranes over the design space (docs/campaign.md). ``--each-ring-count``
asks for ``--q`` membranes of each ring count a round (``Campaign.ask(each_ring_count=True)``):
there the error fell every round, where free batches did not (docs/campaign.md).

Writes ``experiments/out/campaign_rounds.json`` (one row per round, the commands' times,
the machine) and ``.png`` (test RMSE and coverage against the round).
"""

from __future__ import annotations

import argparse
import json
import os
import sys
import time
from pathlib import Path

HERE = Path(__file__).resolve().parent
OUT = HERE / "out"
# Two membranes no round sees: a thin ringless one and a one-ring one, inside the design
# space and away from the bundled six.
TEST_DESIGNS = ("[1.75, 32.0, nan, nan, nan, nan]", "[2.5, 27.0, 40.0, 5.5, nan, nan]")
# A world with a ring-dependent misfit is judged over the design space: ringless, one- and
# two-ring membranes, thin and thick (the first two are TEST_DESIGNS).
WIDE_TEST_DESIGNS = TEST_DESIGNS + (
    "[1.25, 30.0, 42.0, 6.0, 58.0, 6.0]",
    "[2.75, 34.0, 46.0, 5.5, 60.0, 5.0]",
    "[2.25, 36.0, nan, nan, nan, nan]",
    "[1.5, 26.0, 38.0, 8.0, nan, nan]",
)


WORLDS = ("card", "stiff-rings")


def _world_plane(truth: str, world: str):
    """The truth's plane solver: the bundled card's world (the simulator, or the stand-in for
    a stand-in campaign: the model holds it) or ``stiff-rings`` (the stand-in whose rings
    raise the contact pressure 0.65 each where the model says 0.4: a misfit no effect
    reaches, which only the discrepancy can learn)."""
    if world == "stiff-rings":
        from mfdesign.models.standin import StandinWorld

        return StandinWorld()
    if truth == "standin":
        from mfdesign.models.standin import standin_plane

        return standin_plane
    return None


def _rig(card: dict, truth: str, sample_hz: float, seed: int, noise=None, world: str = "card"):
    """The rig the campaign's data came from (the bundled card's hidden effect and noise, on
    the world's planes), one trial per height at ``sample_hz``, noise seed ``seed`` (new
    draws, not the card's); ``noise=Noise.none()`` records the truth itself."""
    from mfdesign.rig.virtual import VirtualRig

    return VirtualRig.from_card(
        card,
        simulator=_world_plane(truth, world),
        seed=seed,
        noise=noise,
        sample_hz=sample_hz,
        trials_per_height=1,
    )


def start(folder: Path, card: dict, world: str, quick: bool) -> dict:
    """Round 0 in ``world``: the card's six designs measured there with the card's own
    protocol, seed and noise (as the bundled data were), then the stand-in demo on them
    (:func:`mfdesign.workflows.demo.run_demo`), which leaves its campaign in ``folder``."""
    import dataclasses
    import tempfile

    from mfdesign.data.store import write_parquet
    from mfdesign.design import Membrane
    from mfdesign.rig.virtual import VirtualRig
    from mfdesign.workflows.demo import DemoSettings, run_demo

    rig = VirtualRig.from_card(card, simulator=_world_plane("standin", world))
    table = rig.run([Membrane.from_key(k) for k in card["designs"]], progress=False)
    settings = DemoSettings.quick("standin") if quick else DemoSettings(force_model="standin", search_model="standin")
    # the world casts every membrane alike: per-membrane latents would absorb its ring misfit
    # membrane by membrane, leaving the discrepancy nothing to carry to a new one (docs/campaign.md)
    settings = dataclasses.replace(settings, membrane_latents=world == "card")
    with tempfile.TemporaryDirectory() as tmp:
        path = Path(tmp) / f"{world}.parquet"
        write_parquet(table, path)
        return run_demo(folder, settings, data_path=path, progress=False)


def _test_error(campaign, number: int, test, truth) -> dict:
    """Round ``number``'s model on the test membranes, where it meets their data (exact
    physics: their own simulator planes, ``for_table``): RMSE and 90 % coverage against the
    rig's noisy readings, and the RMSE against the noise-free truth at the same set-points
    (the model's own error, which the readings' 0.2 N noise hides). Beside it, the same
    RMSE of the round's saved model, which predicts new membranes on the search physics
    (the emulator for an exact campaign)."""
    from mfdesign.calibration.workflow import for_table
    from mfdesign.models.predictive import coverage

    fit = campaign.model(number)
    mf = for_table(fit, test, campaign.settings.physics)
    cov = coverage(mf, test, level=0.9, key=fit.seed)
    exact = coverage(mf, truth, level=0.9, key=fit.seed)
    saved = coverage(fit.mf, truth, level=0.9, key=fit.seed)
    return {
        "test_rmse_n": cov["rmse_n"],
        "test_coverage90": cov["coverage"],
        "test_truth_rmse_n": exact["rmse_n"],
        "test_truth_rmse_saved_model_n": saved["rmse_n"],
        "test_truth_rmse_per_membrane_n": {k: v["rmse_n"] for k, v in exact["per_membrane"].items()},
    }


def _recorded(record: dict | None) -> dict:
    """What a round's ``round.json`` says of it (for rounds evaluated after the fact)."""
    if not record:
        return {"built": []}
    return {
        "built": [],
        "heldout_told": record.get("heldout"),
        "train_rmse_n": record["fit"]["train_rmse_n"],
        "membranes": record["data"]["membranes"],
    }


def main(argv=None) -> dict:
    ap = argparse.ArgumentParser(description=__doc__.split("\n\n")[0])
    ap.add_argument("--campaign", required=True, help="a folder `mfdesign demo --out` left (it is modified)")
    ap.add_argument(
        "--world",
        choices=WORLDS,
        default="card",
        help="the truth: the bundled card's (the model holds it) or stiff-rings (a stand-in world it does not)",
    )
    ap.add_argument(
        "--start", action="store_true", help="first run the stand-in demo into --campaign on the world's data"
    )
    ap.add_argument("--quick", action="store_true", help="with --start: the quick demo")
    ap.add_argument("--rounds", type=int, default=2)
    ap.add_argument(
        "--q", type=int, default=2, help="membranes built per round (with --each-ring-count: per ring count)"
    )
    ap.add_argument(
        "--each-ring-count",
        action="store_true",
        help="ask once per ring count (0, 1, 2) each round, --q membranes each: every kind of membrane is built",
    )
    ap.add_argument("--sample-hz", type=float, default=2.0, help="the virtual rig's sampling rate [Hz]")
    ap.add_argument("--seed", type=int, default=7)
    ap.add_argument("--out", default=str(OUT / "campaign_rounds.json"))
    ap.add_argument("--no-figure", action="store_true")
    ap.add_argument(
        "--evaluate", action="store_true", help="no new rounds: evaluate every round the campaign holds on the test set"
    )
    args = ap.parse_args(argv)

    import numpy as np

    from mfdesign._cache import enable_compilation_cache
    from mfdesign.campaign import Campaign, provenance
    from mfdesign.data.shipped import bundled_card_path
    from mfdesign.data.store import write_parquet
    from mfdesign.design import Membrane
    from mfdesign.rig.virtual import Noise

    enable_compilation_cache()
    folder = Path(args.campaign)
    card = json.loads(bundled_card_path().read_text())
    if args.start:
        t = time.perf_counter()
        demo = start(folder, card, args.world, args.quick)
        print(
            f"round 0 (the demo in the {args.world} world): found {demo['diagnosis']['found']}, "
            f"{time.perf_counter() - t:.0f} s"
        )
    campaign = Campaign.open(folder)
    truth = "standin" if campaign.settings.physics == "standin" else "simulator"
    if args.world != "card" and truth != "standin":
        ap.error(f"--world {args.world} is a stand-in world: the campaign's physics must be standin")
    rig = _rig(card, truth, args.sample_hz, args.seed, world=args.world)
    built = folder / "built"
    built.mkdir(exist_ok=True)
    t0 = time.perf_counter()
    test_keys = TEST_DESIGNS if args.world == "card" else WIDE_TEST_DESIGNS
    test_designs = [Membrane.from_key(k) for k in test_keys]
    test = rig.run(test_designs, lift=False, progress=False)
    truth_rig = _rig(card, truth, args.sample_hz, args.seed, noise=Noise.none(), world=args.world)
    test_truth = truth_rig.run(test_designs, lift=False, progress=False)
    first = campaign.rounds() if args.evaluate else campaign.rounds()[-1:]
    records = {r["round"]: r for r in campaign.status().rounds}
    rows = [{"round": n, **_test_error(campaign, n, test, test_truth), **_recorded(records.get(n))} for n in first]
    times = {"test_set_s": round(time.perf_counter() - t0, 1)}
    print(
        f"round {rows[0]['round']}: test RMSE {rows[0]['test_rmse_n']:.3f} N (against the truth "
        f"{rows[0]['test_truth_rmse_n']:.3f} N), cov90 {rows[0]['test_coverage90']:.2f}"
    )
    for r in range(0 if args.evaluate else args.rounds):
        t = time.perf_counter()
        asked = [
            e for e in campaign.ask(args.q, each_ring_count=args.each_ring_count, progress=True) if e.fidelity == "rig"
        ]
        t_ask = time.perf_counter() - t
        for e in asked:
            table = rig.run([Membrane.from_key(e.design)], lift=False, progress=False)
            path = built / f"{e.id}.parquet"
            write_parquet(table, path)
            campaign.tell(e.id, str(path))
        t_build = time.perf_counter() - t - t_ask
        done = campaign.fit(progress=True)
        t_fit = time.perf_counter() - t - t_ask - t_build
        rows.append(
            {
                "round": done.number,
                **_test_error(campaign, done.number, test, test_truth),
                "built": [e.design for e in asked],
                "heldout_told": done.record["heldout"],
                "train_rmse_n": done.record["fit"]["train_rmse_n"],
                "membranes": done.record["data"]["membranes"],
                "seconds": {"ask": round(t_ask, 1), "build": round(t_build, 1), "fit": round(t_fit, 1)},
            }
        )
        last = rows[-1]
        print(
            f"round {last['round']}: {last['membranes']} membranes; test RMSE {last['test_rmse_n']:.3f} N "
            f"(against the truth {last['test_truth_rmse_n']:.3f} N), "
            f"cov90 {last['test_coverage90']:.2f}; ask {t_ask:.0f} s, build {t_build:.0f} s, fit {t_fit:.0f} s"
        )
    rmse = [r["test_rmse_n"] for r in rows]
    result = {
        "campaign": str(folder),
        "physics": campaign.settings.physics,
        "truth": f"virtual rig on the {truth if args.world == 'card' else 'stand-in with stiff rings (0.65, model 0.4)'}"
        f" with {card['hidden_effect']['name']} {card['hidden_effect']['theta']}",
        "world": args.world,
        "test_designs": list(test_keys),
        "q": args.q,
        "each_ring_count": args.each_ring_count,
        "sample_hz": args.sample_hz,
        "rounds": rows,
        "test_rmse_falls_every_round": bool(np.all(np.diff(rmse) < 0)),
        "test_truth_rmse_falls_every_round": bool(np.all(np.diff([r["test_truth_rmse_n"] for r in rows]) < 0)),
        "times_s": times | {"total": round(time.perf_counter() - t0, 1)},
        "load_avg": os.getloadavg(),
        "provenance": provenance(" ".join(["python", *sys.argv])),
        "status": campaign.status().summary(),
    }
    out = Path(args.out)
    out.parent.mkdir(parents=True, exist_ok=True)
    out.write_text(json.dumps(result, indent=1, default=float))
    if not args.no_figure:
        _figure(rows, out.with_suffix(".png"), result["truth"])
    print(campaign.status().summary())
    return result


def _figure(rows: list[dict], path: Path, truth: str) -> None:
    import matplotlib

    matplotlib.use("Agg")
    import matplotlib.pyplot as plt

    x = [r["round"] for r in rows]
    fig, (a, b) = plt.subplots(1, 2, figsize=(8, 3.2))
    a.plot(x, [r["test_rmse_n"] for r in rows], "o-", label="readings")
    a.plot(x, [r["test_truth_rmse_n"] for r in rows], "s-", label="noise-free truth")
    saved = [r.get("test_truth_rmse_saved_model_n") for r in rows]
    if all(v is not None for v in saved):
        a.plot(x, saved, "^--", label="noise-free truth, saved model (search physics)")
    per = [r.get("test_truth_rmse_per_membrane_n") for r in rows]
    if all(per):  # each test membrane against the truth: which of them the mean hides
        for key in per[0]:
            a.plot(x, [p[key] for p in per], color="0.7", lw=0.8)
            a.annotate(key.replace(", nan", "").replace("nan", ""), (x[-1], per[-1][key]), fontsize=5, color="0.4")
    a.set(xlabel="round", ylabel="test RMSE [N]", title="membranes no round saw", ylim=(0, None))
    a.legend(fontsize=7)
    b.plot(x, [r["test_coverage90"] for r in rows], "o-")
    b.axhline(0.9, color="0.6", ls="--", lw=0.8)
    b.set(xlabel="round", ylabel="90 % interval coverage [-]", ylim=(0, 1.02), title="coverage")
    for ax in (a, b):
        ax.set_xticks(x)
    fig.suptitle(truth, fontsize=8)
    fig.tight_layout()
    fig.savefig(path, dpi=120)
    plt.close(fig)


if __name__ == "__main__":
    main()
