"""Which measurement would tell two explanations apart, when the data cannot.

Two candidate sets that fit the data equally well (:func:`~mfdesign.diagnosis.check.ties`)
may still predict different forces elsewhere. Each fitted set is evaluated on the force
trials the rig can run on the measured membranes (plate heights 0-70 mm every 10 mm, the
pressure ramp to each membrane's limit; :class:`~mfdesign.rig.virtual.Protocol`), and the
trial (membrane, height) where their predictions differ most is named, with the pressure
and the difference over the noise floor. Where they differ by less than
``SEPARABLE`` noise floors everywhere, no force trial on these membranes separates them:
an exact degeneracy (a global thickness change and the rubber's modulus on ringless
membranes: ``F = s G(h, p / s)`` for both) or nearly one. Then only a direct measurement of
the quantity helps, and the verdict says which (each effect's ``direct_check``).
"""

from __future__ import annotations

from typing import TYPE_CHECKING, Mapping, Sequence

import numpy as np
import pandas as pd

from mfdesign.data.measurements import Measurements
from mfdesign.design import Membrane
from mfdesign.physics import effects as fx

if TYPE_CHECKING:
    from mfdesign.diagnosis.forward import ForwardModel

__all__ = ["SEPARABLE", "separating_trial"]

SEPARABLE = 3.0  # noise floors: a difference a single force trial shows plainly
HEIGHTS_MM = (0.0, 10.0, 20.0, 30.0, 40.0, 50.0, 60.0, 70.0)
P_STEP_PA = 250.0


def _trials(keys: Sequence[str]) -> Measurements:
    """Force trials (inflation ramps) on ``keys`` at :data:`HEIGHTS_MM`, to each membrane's limit."""
    from mfdesign.rig.virtual import Protocol

    pr = Protocol()
    rows = []
    for key in keys:
        top = max(pr.force_limits(Membrane.from_key(key)))
        for i, h in enumerate(HEIGHTS_MM):
            for p in np.arange(P_STEP_PA, top + 1e-9, P_STEP_PA):
                rows.append((key, i, h, p))
    df = pd.DataFrame(rows, columns=["design_key", "trial", "height_set_mm", "pressure_pa"])
    df = df.assign(
        experiment="force",
        phase="inflate",
        time_s=np.nan,
        height_mm=df["height_set_mm"],
        force_n=0.0,
        weight=1.0,
        source="simulated",
    )
    return Measurements(df)


def separating_trial(
    sim: ForwardModel,
    meas: Measurements,
    a: tuple[Sequence[str], Mapping[str, float]],
    b: tuple[Sequence[str], Mapping[str, float]],
    floor_n: float,
) -> dict:
    """The force trial on the measured membranes where the fitted sets ``a`` and ``b``
    (``(effects, theta)``) differ most, and a sentence saying what to measure.

    Arguments:
        sim: the diagnosis' forward model (its planes grow to the trials' pressures).
        meas: the measurements (their membranes are the ones a trial can use).
        a, b: two fitted candidate sets, ``(effect names, {"effect.param": value})``.
        floor_n: the noise floor [N].

    Returns ``{"design_key", "height_mm", "pressure_pa", "difference_n", "over_noise",
    "separable", "words"}``.
    """
    keys = list(dict.fromkeys(meas.df["design_key"].astype(str)))
    trials = _trials(keys)
    fa = sim.expected_force(trials, list(a[0]), dict(a[1]))
    fb = sim.expected_force(trials, list(b[0]), dict(b[1]))
    d = np.abs(fa - fb)
    name = lambda s: "+".join(s)  # noqa: E731
    if not np.any(np.isfinite(d)):
        return {
            "separable": False,
            "words": f"no trial on these membranes has a value for both {name(a[0])} and {name(b[0])}",
        }
    i = int(np.nanargmax(d))
    row = trials.df.iloc[i]
    over = float(d[i] / floor_n) if floor_n > 0 else float("inf")
    out: dict = {
        "design_key": str(row["design_key"]),
        "height_mm": float(row["height_set_mm"]),
        "pressure_pa": float(row["pressure_pa"]),
        "difference_n": float(d[i]),
        "over_noise": over,
        "separable": over >= SEPARABLE,
    }
    if out["separable"]:
        out["words"] = (
            f"a force trial of {out['design_key']} at h = {out['height_mm']:.0f} mm up to "
            f"{out['pressure_pa'] / 1000:.1f} kPa separates {name(a[0])} from {name(b[0])}: they predict "
            f"{d[i]:.2f} N apart there ({over:.1f} x the noise floor)"
        )
    else:
        direct = [fx.effect(e).direct_check for e in [*a[0], *b[0]] if fx.effect(e).direct_check]
        out["words"] = (
            f"no force trial on these membranes separates {name(a[0])} from {name(b[0])} (at most {d[i]:.2f} N "
            f"apart, {over:.1f} x the noise floor)"
            + ("; measure directly: " + "; ".join(dict.fromkeys(direct)) if direct else "")
        )
    return out
