"""The whole diagnosis in one call: residuals -> where it fails -> which effect -> add it.

:func:`diagnose` takes measurements and a model (the plain simulator by default, or any
``predict(measurements) -> force [N]``), optionally effects the user adds, and returns a
:class:`Diagnosis`:

* ``before``: residuals of the model as given; ``after``: with the user's effects
  (calibrated) or, when the search claims one, with the claimed effects;
* ``steps``: forward selection (Efroymson 1960), at most ``max_steps`` rounds of: screen
  every candidate on the current residuals (:func:`~mfdesign.diagnosis.screen.screen`) and
  every pair of candidates jointly (:func:`~mfdesign.diagnosis.screen.screen_pairs`), full
  check of the ``check_top`` best single effects and, where none of them reaches the
  noise floor, of the ``check_pairs`` best pairs (:func:`~mfdesign.diagnosis.check.full_check`), verdict
  (:func:`~mfdesign.diagnosis.check.verdict`: a pair is claimed only where it beats the best
  single effect by the claim's margins); claimed effects join the model and the next
  round asks what is still missing. It stops at the first round that claims nothing.

The rule, stated once: refit the top ``check_top`` singles of the linear screen, and where
none explains the residual down to the noise floor also the top ``check_pairs`` pairs of
the joint screen (never only the first candidate: two effects acting together can each
screen as something else); claim the smallest set that clears the margins (a claimed pair is checked against each of its
members refitted alone); name every set the data cannot tell from it.
"""

from __future__ import annotations

from dataclasses import dataclass, field, replace
from types import SimpleNamespace
from typing import TYPE_CHECKING, Any, Callable, Mapping, Sequence

import numpy as np
import pandas as pd

from mfdesign._x64 import enable_x64
from mfdesign.data.lifts import STALL_PA
from mfdesign.data.lifts import stalls as find_stalls
from mfdesign.data.measurements import Measurements
from mfdesign.errors import InputError
from mfdesign.diagnosis.check import calibrate_effects, full_check, verdict
from mfdesign.diagnosis.residuals import (
    Residuals,
    breakdowns,
    compute_residuals,
    residual_shape,
    stall_words,
    trend_words,
    worst_regions,
)
from mfdesign.diagnosis.screen import screen, screen_pairs
from mfdesign.physics import effects as fx

if TYPE_CHECKING:
    from mfdesign.diagnosis.forward import ForwardModel

__all__ = ["Diagnosis", "diagnose"]

PAIRS_REPORTED = 10  # pairs of the joint screen kept in diagnosis.json (of up to n (n - 1) / 2)


@dataclass(frozen=True)
class Diagnosis:
    """What :func:`diagnose` found (residuals [N], effects, parameters, every round's search)."""

    before: Residuals
    after: Residuals | None = None
    effects: list = field(default_factory=list)
    theta: dict = field(default_factory=dict)
    steps: list = field(default_factory=list)
    model: str = "simulator"
    not_screened: dict = field(default_factory=dict)  # candidate -> why the forward model cannot try it
    # where lift plates stall, from the data alone (mfdesign.data.lifts.stalls): a smooth
    # quasi-static model cannot follow a plate that stops while the pressure climbs
    stalls: pd.DataFrame | None = None

    @property
    def found(self) -> list[str]:
        """Effects the search claimed (in order)."""
        return [e for s in self.steps for e in s["verdict"].get("effects", []) if e not in s.get("base_effects", [])]

    def to_json(self) -> dict:
        def part(res: Residuals | None):
            if res is None:
                return None
            return {
                "summary": res.summary(),
                "breakdowns": breakdowns(res),
                "worst_regions": worst_regions(res),
                "trends": trend_words(res),
                "shape": residual_shape(res),
            }

        return {
            "model": self.model,
            "effects_added": self.effects,
            "theta": self.theta,
            "before": part(self.before),
            "after": part(self.after),
            "search": [
                {
                    "base_effects": s["base_effects"],
                    "screen": [r.to_json() for r in s["screen"]],
                    "pair_screen": [r.to_json() for r in s.get("pair_screen", [])[:PAIRS_REPORTED]],
                    "checks": [c.to_json() for c in s["checks"]],
                    "verdict": s["verdict"],
                }
                for s in self.steps
            ],
            "found": self.found,
            "not_screened": self.not_screened,
            "stalls": None
            if self.stalls is None
            else {"min_pa": STALL_PA, "words": stall_words(self.stalls), "rows": self.stalls.to_dict("records")},
        }


def unmodelled(names: Sequence[str], sim: ForwardModel) -> dict[str, str]:
    """Candidates whose mechanics the forward model cannot represent: a simulator constant
    its force model pins to one value (the emulator was never trained on a fabric inset).
    Screened, such an effect would read as "explains nothing"; it is named instead."""
    import dataclasses

    from mfdesign.physics.params import SimParams

    pinned = {k: lo for k, (lo, hi) in sim.force_model.support().items() if lo == hi}
    out = {}
    for n in names:
        e = fx.effect(n)
        if e.acts_on_measurement or not pinned:
            continue
        p = fx.apply_sim_params([e], fx.typical_theta([e]), SimParams())
        moved = [
            f.name for f in dataclasses.fields(p) if f.name in pinned and float(getattr(p, f.name)) != pinned[f.name]
        ]
        if moved:
            out[n] = (
                f"the {type(sim.force_model).__name__} force model holds {', '.join(moved)} fixed (use --physics exact)"
            )
    return out


def _refit(picks, *, sim, meas, res, names, theta0, base_pred, n_folds, progress):
    """The full check of the screened sets ``picks`` added to the current model ``names``;
    each set starts from its own screen estimate (a pair from the joint one)."""
    if not picks:
        return []
    return full_check(
        sim,
        meas,
        res,
        [[*names, *r.effects] for r in picks],
        theta0=theta0,
        starts=[r.theta for r in picks],
        base_pred=base_pred,  # the model under diagnosis (``offset`` carries a non-simulator one)
        n_folds=n_folds,
        progress=progress,
        base_effects=names,
    )


def _degeneracies(sim, meas, res, v: dict, checks, names, theta0, base_pred, n_folds: int) -> None:
    """For each set the data cannot tell from the claimed one (``v["alternatives"]``): the
    force trial that would separate them (:func:`~mfdesign.diagnosis.separate.separating_trial`)
    and their joint posterior (the union refitted jointly; Laplace approximation: the
    parameters' correlation). Adds them to ``v`` and to its words."""
    from mfdesign.diagnosis.separate import separating_trial

    floor = v.get("noise_floor_n") or res.noise_floor_n
    words = []
    for alt in v["alternatives"]:
        sep = separating_trial(sim, meas, (v["effects"], v["theta"]), (alt["effects"], alt["theta"]), floor)
        union = list(dict.fromkeys([*v["effects"], *alt["effects"]]))
        joint = next((c for c in checks if set(c.effects) == set(union)), None)
        if joint is None:
            joint = full_check(
                sim,
                meas,
                res,
                [union],
                theta0={**theta0, **v["theta"], **alt["theta"]},
                base_pred=base_pred,
                n_folds=n_folds,
            )[0]
        alt["separated_by"] = sep
        alt["joint"] = {
            "effects": list(joint.effects),
            "theta": joint.theta,
            "stderr": joint.stderr,
            "correlation": joint.correlation,
            "method": "Laplace approximation at the joint refit (exact Jacobian, serial-correlation inflated)",
        }
        words.append(sep["words"])
    v["words"] += "; " + "; ".join(words)


def _count_arg(name: str, v, low: int, high: int) -> None:
    if not isinstance(v, (int, np.integer)) or isinstance(v, bool) or not low <= v <= high:
        raise InputError(f"{name} must be an integer from {low} to {high}, got {v!r}")


def _check_arguments(meas, sim, model, effects, theta, candidates, check_top, check_pairs, max_steps, n_folds):
    """:func:`diagnose`'s arguments, each bad one an ``InputError`` in one line (issue 44, class 6)."""
    from mfdesign.diagnosis.forward import ForwardModel

    if not isinstance(meas, Measurements):
        raise InputError(
            f"meas: a {type(meas).__name__}; allowed: a Measurements table (mfdesign.load(path or 'bundled'))"
        )
    if len(meas) == 0:
        raise InputError("meas holds no rows; allowed: a table with measurements")
    if sim is not None and not isinstance(sim, ForwardModel):
        raise InputError(
            f"sim: a {type(sim).__name__}; allowed: None or a ForwardModel "
            "(mfdesign.diagnosis.forward.forward_model('exact' | 'emulator' | 'standin', meas))"
        )
    if model is not None and not callable(model):
        raise InputError(f"model: a {type(model).__name__}; allowed: None or predict(meas) -> force [N] per row")
    for what, names in (("effects", effects), ("candidates", candidates)):
        if names is None and what == "candidates":
            continue
        if isinstance(names, str) or not isinstance(names, Sequence):
            raise InputError(f"{what}: {names!r}; allowed: a list of effect names from {sorted(fx.EFFECTS)}")
        for e in names:
            if not isinstance(e, fx.Effect) and e not in fx.EFFECTS:
                raise InputError(f"{what}: no effect named {e!r}; allowed: {sorted(fx.EFFECTS)}")
    if theta is not None:
        if not isinstance(theta, Mapping):
            raise InputError(f"theta: a {type(theta).__name__}; allowed: {{'effect.parameter': number}}")
        known = {fx.effect(n).qualified(p.name) for n in fx.EFFECTS for p in fx.effect(n).parameters}
        for k, v in theta.items():
            if k not in known:
                raise InputError(
                    f"theta: no parameter {k!r}; allowed: 'effect.parameter' names, e.g. {sorted(known)[:3]}"
                )
            if not isinstance(v, (int, float, np.integer, np.floating)) or isinstance(v, bool) or not np.isfinite(v):
                raise InputError(f"theta[{k!r}] = {v!r}; allowed: a finite number")
    _count_arg("check_top", check_top, 0, 1000)
    _count_arg("check_pairs", check_pairs, 0, 1000)
    _count_arg("max_steps", max_steps, 0, 100)
    _count_arg("n_folds", n_folds, 2, 1000)


def _model_forces(model, meas: Measurements) -> np.ndarray:
    """``model(meas)`` as one finite-or-NaN force per row; a wrong answer is an ``InputError``."""
    try:
        f = np.asarray(model(meas), float).ravel()
    except (TypeError, ValueError) as err:
        raise InputError(
            f"model(meas) did not return forces ({type(err).__name__}: {err}); allowed: [N] per row"
        ) from None
    if f.shape != (len(meas),):
        raise InputError(f"model(meas) returned {f.size} forces for {len(meas)} rows; allowed: one per row")
    if not np.isfinite(f).any():
        raise InputError("model(meas) predicts no finite force on any row; allowed: a model with a value on the data")
    return f


def diagnose(
    meas: Measurements,
    sim: ForwardModel | None = None,
    model: Callable[[Measurements], np.ndarray] | None = None,
    model_name: str = "simulator",
    effects: Sequence[str | fx.Effect] = (),
    theta: Mapping[str, Any] | None = None,
    candidates: Sequence[str] | None = None,
    search: bool = True,
    check_top: int = 3,
    check_pairs: int = 3,
    max_steps: int = 2,
    n_folds: int = 3,
    progress: bool = False,
) -> Diagnosis:
    """Where the model fails on ``meas``, and which physical effect is missing.

    Residuals by height, pressure, design, trial and phase with a noise floor; then forward
    selection (Efroymson 1960) of effects: an autodiff screen of every candidate, a
    nonlinear refit of the best with held-out membranes and delta BIC, and a verdict that
    claims nothing at the noise floor or when no candidate explains the residual (module
    doc).

    **Arguments:**

    - `meas`: the measurements (:class:`~mfdesign.data.measurements.Measurements`).
    - `sim`: the forward model, a :class:`~mfdesign.diagnosis.forward.ForwardModel` (build
      one with :func:`~mfdesign.diagnosis.forward.forward_model`: `"exact"` simulator planes
      of the measured designs, `"emulator"` or `"standin"`); default the bundled emulator.
    - `model`: the model under diagnosis, `predict(meas) -> force [N] per row` (default: the
      plain simulator of `sim`).
    - `model_name`: its name in the report.
    - `effects`: effects the user adds; their parameters are calibrated unless every one is
      given in `theta`.
    - `theta`: effect parameters, `{"effect.parameter": value}`.
    - `candidates`: effects the search may try (default: every registered one).
    - `search`: `False` skips the effect search (residuals and the user's effects only).
    - `check_top`: screened candidates refitted in each round.
    - `check_pairs`: pairs of the joint screen refitted in each round (0: singles only).
    - `max_steps`: rounds of forward selection.
    - `n_folds`: folds of held-out membranes in the refit.
    - `progress`: progress output.

    **Returns:**

    A :class:`Diagnosis`: residuals before and after, every round's screen, checks and
    verdict, the effects found with their parameters; `to_json()` for files and
    :func:`~mfdesign.report.diagnosis.write_report` for HTML.
    """
    enable_x64()  # float64 physics: mfdesign._x64
    _check_arguments(meas, sim, model, effects, theta, candidates, check_top, check_pairs, max_steps, n_folds)
    if sim is None:
        from mfdesign.diagnosis.forward import forward_model

        sim = forward_model("emulator", meas, progress=progress)
    effects = [fx.effect(e) for e in effects]
    e0 = sim.expected_force(meas)
    base_pred = e0 if model is None else _model_forces(model, meas)
    offset = None if model is None else base_pred - e0
    # rows outside the physical model (force above p pi R^2) are dropped and counted
    before = compute_residuals(meas, base_pred, outside=sim.outside_model(meas))
    found = find_stalls(meas)
    out = Diagnosis(before=before, model=model_name, stalls=found if len(found) else None)
    cur_res, cur_effects, cur_theta = before, [], {}
    if effects:
        given = dict(theta or {})
        needed = [e.qualified(p.name) for e in effects for p in e.parameters]
        if all(k in given for k in needed):
            th = {k: float(given[k]) for k in needed}
            pred = sim.expected_force(meas, effects, th) + (0.0 if offset is None else offset)
        else:
            th, pred = calibrate_effects(sim, meas, before, effects, given, offset)
        cur_res, cur_effects, cur_theta = (
            compute_residuals(meas, pred, sim.outside_model(meas, effects, th)),
            effects,
            th,
        )
        out = replace(out, after=cur_res, effects=[e.name for e in effects], theta=th)
    if not search:
        return out
    if candidates is not None:
        pool = list(candidates)
    else:  # every effect with a likelihood hook
        from mfdesign.diagnosis.forward import likelihood_effects

        pool = likelihood_effects()
    skipped = unmodelled(pool, sim)
    if skipped:
        pool = [c for c in pool if c not in skipped]
        out = replace(out, not_screened=skipped)
    for _ in range(max_steps):
        names = [e.name for e in cur_effects]
        cands = [c for c in pool if c not in names]
        if not cands:
            break
        ranked = screen(cur_res, meas, sim, cands, cur_effects, cur_theta, progress=progress)
        if verdict(cur_res, [])["status"] == "at_noise_floor":  # nothing to explain: no full check
            out.steps.append({"base_effects": names, "screen": ranked, "checks": [], "verdict": verdict(cur_res, [])})
            break
        base_pred = None if offset is None else e0 + offset

        kw = dict(sim=sim, meas=meas, res=cur_res, names=names, theta0=cur_theta, base_pred=base_pred, n_folds=n_folds)
        checks = _refit(ranked[:check_top], progress=progress, **kw)
        pairs: list = []
        # Pairs only where no single effect reaches the floor: a pair must beat the best
        # single by the claim's margins, which a single at the floor leaves no room for
        # (and the refits of pairs cost as much again).
        if check_pairs > 0 and verdict(cur_res, checks)["status"] != "explained":
            pairs = screen_pairs(cur_res, meas, sim, cands, cur_effects, cur_theta)
            checks = sorted(
                checks + _refit(pairs[:check_pairs], progress=progress, **kw), key=lambda c: c.heldout_rmse_n
            )
        v = verdict(cur_res, checks)
        # Backward step (stepwise selection): a claimed pair must beat each of its own
        # members alone, not only the singles the screen ranked. A member the linear screen
        # ranked low (a 5x ring, far from the neutral point it is linearised at) is
        # otherwise only ever refitted beside a partner it does not need.
        added = [e for e in v.get("effects", []) if e not in names]
        have = {tuple(c.effects) for c in checks}
        alone = [
            SimpleNamespace(effects=(e,), theta={k: x for k, x in v["theta"].items() if k.split(".")[0] == e})
            for e in added
            if len(added) == 2 and (*names, e) not in have
        ]
        if alone:
            checks = sorted(checks + _refit(alone, progress=progress, **kw), key=lambda c: c.heldout_rmse_n)
            v = verdict(cur_res, checks)
        if v.get("alternatives"):
            _degeneracies(sim, meas, cur_res, v, checks, names, cur_theta, base_pred, n_folds)
        out.steps.append(
            {"base_effects": names, "screen": ranked, "pair_screen": pairs, "checks": checks, "verdict": v}
        )
        if v["status"] not in ("explained", "partly_explained"):
            break
        best = next(c for c in checks if list(c.effects) == v["effects"])
        cur_effects = [fx.effect(n) for n in best.effects]
        cur_theta = dict(best.theta)
        pred = sim.expected_force(meas, cur_effects, cur_theta) + (0.0 if offset is None else offset)
        cur_res = compute_residuals(meas, pred, sim.outside_model(meas, cur_effects, cur_theta))
        if not effects:  # no user effects: "after" is the model with what the search found
            out = replace(out, after=cur_res, effects=[e.name for e in cur_effects], theta=cur_theta)
        if v["status"] == "explained":
            break
    return out
