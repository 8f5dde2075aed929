"""Calibration checked against known truth: virtual-rig data with drawn constants.

One trial (:func:`truth_trial`): draw the truth (mu [Pa] ~ U(26, 42) kPa, J_m ~ U(28, 60),
the active effects' parameters from their priors), run the virtual rig on three membranes
with that truth (``plane``: the simulator it uses), calibrate with the same force model
(``force_model``), and record whether each central ``level`` credible interval holds
the truth. Over many seeds the fraction covered should be about ``level`` (the
frequentist check of a Bayesian procedure, Cook, Gelman & Rubin 2006).
"""

from __future__ import annotations

import warnings

import numpy as np

__all__ = ["DESIGN_KEYS", "truth_trial"]

DESIGN_KEYS = (
    "[2.0, 25.4, nan, nan, nan, nan]",
    "[2.0, 31.92, 46.0, 5.0, 59.0, 5.0]",
    "[2.33, 29.63, 37.63, 5.0, 62.0, 5.0]",
)


def truth_trial(
    seed: int,
    force_model,
    plane,
    effects=("pressure_sensor",),
    *,
    rows: int = 240,
    n_steps: int = 600,
    n_walkers: int | None = None,
    level: float = 0.95,
    protocol=None,
    designs=DESIGN_KEYS,
    model_kwargs=None,
) -> dict:
    """One virtual-truth calibration; returns truth, intervals and ``covered`` per parameter."""
    from mfdesign.calibration.mcmc import ConvergenceWarning, build_model, calibrate
    from mfdesign.design import Membrane
    from mfdesign.models.hierarchical import CalibrationData
    from mfdesign.physics import effects as fx
    from mfdesign.physics.params import SimParams
    from mfdesign.rig.virtual import Protocol, VirtualRig

    rng = np.random.default_rng(seed)
    truth = {"mu_pa": float(rng.uniform(26e3, 42e3)), "jm": float(rng.uniform(28.0, 60.0))}
    for name in effects:
        e = fx.effect(name)
        truth.update({e.qualified(k): v for k, v in e.sample_prior(rng).items()})
    theta = {k: v for k, v in truth.items() if "." in k}
    protocol = protocol or Protocol(sample_hz=0.2, trials_per_height=1, heights_mm=(0.0, 20.0, 40.0, 60.0))
    rig = VirtualRig(
        effects=list(effects),
        theta=theta,
        seed=seed,
        protocol=protocol,
        simulator=plane,
        base_params=SimParams(mu_pa=truth["mu_pa"], jm=truth["jm"]),
    )
    table = rig.run([Membrane.from_key(k) for k in designs], progress=False)
    data = CalibrationData.from_measurements(table, max_rows=rows - 20, seed=seed).padded(rows)
    model = build_model(force_model, data, list(effects), **(model_kwargs or {}))
    with warnings.catch_warnings():
        warnings.simplefilter("ignore", ConvergenceWarning)
        post = calibrate(data, model, n_steps=n_steps, n_walkers=n_walkers, seed=seed, progress=False)
    out = {
        "seed": seed,
        "truth": truth,
        "intervals": {},
        "covered": {},
        "steps_over_tau": post.convergence["steps_over_tau"],
        "acceptance": post.convergence["acceptance"],
    }
    for name, value in truth.items():
        lo, hi = post.interval(name, level)
        out["intervals"][name] = [lo, hi]
        out["covered"][name] = bool(lo <= value <= hi)
    return out
