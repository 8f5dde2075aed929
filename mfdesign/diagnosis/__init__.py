"""Diagnosis: compare a model with measurements, see where it fails, find the missing effect.

* :mod:`~mfdesign.diagnosis.forward`: the forward model, one interface
  (:class:`ForwardModel`, the diagnosis' :class:`~mfdesign.models.force.RecordedForceModel`)
  on two back ends (:class:`ExactForwardModel`: exact simulator planes;
  :class:`EmulatorForwardModel`: the emulator or the stand-in; :func:`forward_model` by name):
  a JAX force model + the effects' likelihood hooks (:func:`~mfdesign.models.force.recorded_force`),
  exact autodiff;
* :mod:`~mfdesign.diagnosis.expected`: query heights, usable rows, trial order;
* :mod:`~mfdesign.diagnosis.refit`: the full check's nonlinear refit (optimistix);
* :mod:`~mfdesign.diagnosis.residuals`: residuals, breakdowns, noise floor, worst regions in words;
* :mod:`~mfdesign.diagnosis.screen`: the fast effect screen (sensitivities + least squares);
* :mod:`~mfdesign.diagnosis.check`: the full check (calibration, held-out error, BIC) and the verdict;
* :mod:`~mfdesign.diagnosis.pipeline`: the whole story in one call (:func:`diagnose`).

Pictures, HTML and JSON of a diagnosis: :mod:`mfdesign.report.diagnosis` (downstream).

See ``docs/diagnose.md``.
"""

from mfdesign.diagnosis.check import CheckResult, calibrate_effects, full_check, verdict
from mfdesign.diagnosis.forward import (
    EmulatorForwardModel,
    ExactForwardModel,
    ForwardModel,
    emulator_plane,
    forward_model,
)
from mfdesign.diagnosis.expected import query_heights, trial_order, usable_rows
from mfdesign.diagnosis.residuals import Residuals, breakdowns, compute_residuals, noise_floor, worst_regions
from mfdesign.diagnosis.screen import ScreenResult, screen

__all__ = [
    "CheckResult",
    "EmulatorForwardModel",
    "ExactForwardModel",
    "ForwardModel",
    "emulator_plane",
    "forward_model",
    "Residuals",
    "ScreenResult",
    "breakdowns",
    "calibrate_effects",
    "compute_residuals",
    "full_check",
    "noise_floor",
    "query_heights",
    "screen",
    "trial_order",
    "usable_rows",
    "verdict",
    "worst_regions",
]
