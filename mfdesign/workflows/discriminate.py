"""``mfdesign discriminate``: which experiment tells the standing hypotheses apart
(:func:`discriminate`; the criterion is :mod:`mfdesign.discriminate`).

Fits each hypothesis (an effect set, ``"fabric_inset+ring_stiffening"``, ``"none"``) to
``DATA`` with small settings (:func:`mfdesign.calibration.workflow.fit_multi_fidelity`),
weighs them by their BIC, ranks the candidate experiments (force sweeps at fixed plate
heights, mass lifts with a given mass, on the measured membranes and on ``new_designs``)
by Box & Hill's (1967) expected log Bayes factor, and writes ``OUT/discriminate.json``
(every candidate ranked, each hypothesis's predictions with 90 % intervals, the off-rig
measurements that would decide) and ``OUT/discriminate.png`` (the top experiment's
predictions per hypothesis). Units: mm, Pa, N.
"""

from __future__ import annotations

import time
from dataclasses import dataclass, field
from pathlib import Path
from typing import Any, Sequence

import numpy as np

from mfdesign.errors import InputError

__all__ = ["DiscriminateResult", "discriminate", "plot_top"]

PHYSICS = ("emulator", "exact", "standin")


@dataclass(frozen=True)
class DiscriminateResult:
    """What :func:`discriminate` found and wrote: ``ranking``
    (:class:`mfdesign.discriminate.Ranking`), per hypothesis its ``bic`` and posterior
    probability ``probability`` on the data, the ``outside`` measurements per pair, the
    files, and the number of ranked lines the summary prints (``top``)."""

    ranking: Any
    bic: dict
    probability: dict
    outside: list
    json_path: Path
    png_path: Path
    top: int = 5
    wall_s: float = 0.0
    warnings: tuple[str, ...] = field(default=())

    def summary(self) -> str:
        r = self.ranking
        lines = ["hypotheses (BIC on the data -> probability):"]
        lines += [f"  {h}: BIC {self.bic[h]:.1f} -> P {self.probability[h]:.3f}" for h in r.hypotheses]
        lines.append(f"experiments ranked by expected log Bayes factor (Box & Hill 1967), {len(r.order)} candidates:")
        lines += ["  " + s for s in r.lines(self.top)]
        if r.unscored:
            lines.append(
                f"not scored ({len(r.unscored)}: no hypothesis has a number at any of their rows, outside the "
                f"physical model or off the planes): " + "; ".join(r.experiments[i].label() for i in r.unscored)
            )
        lines.append("measurements off the rig that would decide:")
        for o in self.outside:
            for name, text in o["measurements"].items():
                lines.append(f"  {' vs '.join(o['pair'])} ({name}): {text}")
        lines.append(f"wrote {self.json_path} and {self.png_path} ({self.wall_s:.0f} s)")
        return "\n".join(lines)


def plot_top(ranking: Any, i: int, path: Path) -> Path:
    """PNG: candidate ``i``'s predicted observable per hypothesis (mean and the central
    interval) against pressure [Pa], one panel per plate height (force sweep) or one panel
    of the plate height [mm] (mass lift)."""
    import matplotlib

    matplotlib.use("Agg")
    import matplotlib.pyplot as plt
    import numpy as np

    from mfdesign import outputs

    e, preds = ranking.experiments[i], ranking.predictions[i]
    rows = preds["rows"]
    heights = list(e.heights_mm) if e.kind == "force" else [None]
    fig, axes = plt.subplots(1, len(heights), figsize=(4.2 * len(heights) + 0.8, 3.8), squeeze=False)
    for ax, h in zip(axes[0], heights):
        idx = [j for j, r in enumerate(rows) if r.get("height_mm") == h]
        p = np.array([rows[j]["pressure_pa"] for j in idx])
        for name, pr in preds["by_hypothesis"].items():
            m, lo, hi = (np.asarray(pr[k])[idx] for k in ("mean", "lo", "hi"))
            (line,) = ax.plot(p, m, marker="o", ms=3, label=name)
            ax.fill_between(p, lo, hi, color=line.get_color(), alpha=0.2)
        ax.set_xlabel("pressure [Pa]")
        ax.set_ylabel("force [N]" if e.kind == "force" else "plate height [mm]")
        ax.set_title(f"h = {h:g} mm" if h is not None else f"lift, load {e.load_n:.1f} N", fontsize=9)
    axes[0][0].legend(fontsize=8)
    import textwrap

    width = max(40, int(13 * (4.2 * len(heights) + 0.8)))  # characters that fit the figure at 9 pt
    title = textwrap.fill(f"top experiment: {e.label()}", width)
    fig.suptitle(f"{title}\nE[ln BF] {ranking.score[i]:.2f}; bands: {ranking.level:.0%} intervals", fontsize=9)
    fig.tight_layout()
    outputs.savefig(fig, path, dpi=110)
    plt.close(fig)
    return Path(path)


def _check_support(hyps, force_model, physics: str) -> None:
    """A hypothesis whose effect moves a simulator constant the force model holds fixed
    (the emulator was not trained on a fabric inset) fails here in one line, not as a NaN
    fit."""
    import dataclasses

    from mfdesign.physics import effects as fx
    from mfdesign.physics.params import SimParams

    support = force_model.support()  # ForceModel declares it (models valid everywhere: {})
    base = SimParams()
    for h in hyps:
        for name in h.effects:
            moved = fx.apply_sim_params([name], fx.typical_theta([name]), base)
            for f in dataclasses.fields(SimParams):
                lo, hi = support.get(f.name, (-np.inf, np.inf))
                if getattr(moved, f.name) != getattr(base, f.name) and lo == hi:
                    raise InputError(
                        f"hypothesis {h.name!r}: effect {name!r} moves {f.name}, which the {physics} physics holds "
                        f"at {lo:g}; allowed: --physics exact or standin for it"
                    )


def discriminate(
    data: Any,
    hypotheses: Sequence[str],
    out: Path,
    *,
    physics: str = "emulator",
    new_designs: Sequence[str] = (),
    heights_mm: Sequence[float] = (0.0, 20.0, 40.0),
    masses_kg: Sequence[float] = (1.5, 2.5, 4.0),
    cost_membrane: float = 3.0,
    mcmc_steps: int = 300,
    max_rows: int = 400,
    members: int = 2,
    delta_steps: int = 200,
    n_draws: int = 32,
    n_pressures: int = 10,
    top: int = 5,
    seed: int = 0,
    progress: bool = False,
    effect_axes: str = "tensor",
) -> DiscriminateResult:
    """Fit each hypothesis to ``data`` and rank the experiments that would tell them apart.

    **Arguments:**

    - `data`: a Measurements table, or ``DATA`` sources
      (:func:`mfdesign.workflows.data.load_data`).
    - `hypotheses`: at least two effect sets, ``"a+b"`` or ``"none"``, optionally
      ``":coupons"`` (the rubber's priors) after one
      (:class:`mfdesign.discriminate.Hypothesis`).
    - `out`: the output folder (``discriminate.json``, ``discriminate.png``).
    - `physics`: ``emulator`` | ``exact`` | ``standin`` (the fits' and the candidates'
      force model; ``exact`` solves the simulator's planes of the measured membranes and of
      ``new_designs``, at the lattice nodes the fits reach).
    - `new_designs`: design keys ``"[t, c, r1, w1, r2, w2]"`` mm of membranes that could be
      made (cost ``cost_membrane`` trials more).
    - `heights_mm`: plate heights [mm]: a force sweep at each alone and at all of them.
    - `masses_kg`: lift masses [kg] (load ``m g`` N), one trial each.
    - `mcmc_steps`, `max_rows`, `members`, `delta_steps`: the fits' settings (small).
    - `n_draws`, `n_pressures`: the criterion's posterior draws and pressures per trial.
    - `top`: ranked experiments the summary prints.
    - `seed`: the fits' and the criterion's seed (same seed, same ranking).
    - `progress`: progress bars (planes, chains).
    - `effect_axes`: the exact model's lattice layout (``tensor`` | ``tensor-jm`` |
      ``additive``, :func:`~mfdesign.calibration.workflow.force_model_named`).

    **Returns:**

    A :class:`DiscriminateResult`. Bad hypotheses, designs or settings raise
    :class:`~mfdesign.errors.InputError` in one line.
    """
    from mfdesign import outputs
    from mfdesign.discriminate import (
        candidate_experiments,
        hypothesis_probabilities,
        outside_rig,
        parse_hypotheses,
        rank_experiments,
    )

    t0 = time.time()
    if physics not in PHYSICS:
        raise InputError(f"physics {physics!r}; allowed {', '.join(PHYSICS)}")
    from mfdesign.calibration.workflow import EFFECT_AXES

    if effect_axes not in EFFECT_AXES:
        raise InputError(f"effect_axes {effect_axes!r}; allowed {', '.join(EFFECT_AXES)}")
    for name, v in (("mcmc_steps", mcmc_steps), ("max_rows", max_rows), ("members", members), ("top", top)):
        if int(v) < 1:
            raise InputError(f"{name} must be >= 1, got {v}")
    if not heights_mm or min(heights_mm) < 0:
        raise InputError(f"heights_mm: plate heights >= 0 mm, got {list(heights_mm)}")
    if any(m <= 0 for m in masses_kg):
        raise InputError(f"masses_kg must be positive, got {list(masses_kg)}")
    hyps = parse_hypotheses(hypotheses)
    if not hasattr(data, "df"):
        from mfdesign.workflows.data import load_data

        data = load_data(data, "fit-mf")
    from mfdesign.calibration.workflow import fit_multi_fidelity, force_model_named, material_priors
    from mfdesign.models.ensemble import EnsembleConfig

    # Exact physics holds planes of the designs it was built for: the measured membranes and
    # the candidates to make, so that every candidate is scored on the simulator itself (the
    # emulator holds some simulator constants fixed: a fabric inset is NaN there).
    from mfdesign.design import Membrane

    try:
        new_designs = [Membrane.from_key(str(k)).key() for k in new_designs]
    except ValueError as err:
        raise InputError(f"--new-design: {err}") from None
    force_model = force_model_named(
        physics, data, progress=progress, effect_axes=effect_axes, extra_designs=tuple(new_designs)
    )
    _check_support(hyps, force_model, physics)
    fits, bic = {}, {}
    for h in hyps:
        fit = fit_multi_fidelity(
            data,
            force_model,
            h.effects,
            n_steps=int(mcmc_steps),
            max_rows=int(max_rows),
            ensemble_config=EnsembleConfig(n_members=int(members), steps=int(delta_steps), monotone=False),
            seed=seed,
            progress=progress,
            membrane_latents=h.latents,
            membrane_effects=h.per_membrane,
            **material_priors(h.material),
        )
        fits[h.name] = fit.mf
        bic[h.name] = float(fit.posterior.bic)  # type: ignore[attr-defined]
    prob = dict(zip(bic, hypothesis_probabilities(list(bic.values())).tolist()))
    existing = list(dict.fromkeys(data.df["design_key"]))
    heights = tuple(float(h) for h in heights_mm)
    sets = [(h,) for h in heights] + ([heights] if len(heights) > 1 else [])
    cands = candidate_experiments(
        existing, new_designs, height_sets_mm=sets, masses_kg=masses_kg, cost_membrane=cost_membrane
    )
    ranking = rank_experiments(fits, cands, n_draws=n_draws, n_pressures=n_pressures, seed=seed)
    outside = outside_rig(hyps)
    out = Path(out)
    out.mkdir(parents=True, exist_ok=True)
    png = plot_top(ranking, ranking.top(1)[0], out / "discriminate.png")
    doc = {
        "method": ranking.method,
        "criterion": "expected log Bayes factor of the true hypothesis against its closest rival, averaged over which is true (equal weights)",
        "physics": physics,
        "hypotheses": [
            {
                "name": h.name,
                "effects": list(h.effects),
                "material": h.material,
                "latents": h.latents,
                "per_membrane": list(h.per_membrane),
                "bic": bic[h.name],
                "probability": prob[h.name],
            }
            for h in hyps
        ],
        "settings": dict(
            mcmc_steps=mcmc_steps,
            max_rows=max_rows,
            members=members,
            delta_steps=delta_steps,
            n_draws=n_draws,
            n_pressures=n_pressures,
            seed=seed,
            effect_axes=effect_axes,
        ),
        "ranked": [ranking.entry(i) | {"rank": k + 1} for k, i in enumerate(ranking.order)],
        "not_scored": [
            {"label": ranking.experiments[i].label(), "why": "no hypothesis has a number at any of its rows"}
            for i in ranking.unscored
        ],
        "outside_rig": outside,
    }
    from mfdesign.provenance import call_line, input_hashes, provenance

    inputs = input_hashes(data if isinstance(data, (list, tuple)) else [data])
    doc["provenance"] = provenance(call_line("mfdesign.workflows.discriminate.discriminate()"), {"seed": seed}, inputs)
    path = outputs.write_json(out / "discriminate.json", doc)
    return DiscriminateResult(ranking, bic, prob, outside, Path(path), png, int(top), time.time() - t0)
