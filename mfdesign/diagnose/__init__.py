"""Diagnosis: compare a model with measurements, see where it fails, find the missing effect.

* :mod:`~mfdesign.diagnose.emulated`: the default forward model: a JAX force model (the
  simulator's emulator) + the effects' likelihood hooks, exact autodiff (:class:`EmulatorModel`);
* :mod:`~mfdesign.diagnose.expected`: the same from simulator planes and the effects library
  (:class:`PlaneSimulator`, for ``--simulator full``);
* :mod:`~mfdesign.diagnose.refit`: the full check's nonlinear refit (optimistix) on the exact back end;
* :mod:`~mfdesign.diagnose.residuals`: residuals, breakdowns, noise floor, worst regions in words;
* :mod:`~mfdesign.diagnose.screen`: the fast effect screen (sensitivities + least squares);
* :mod:`~mfdesign.diagnose.check`: the full check (calibration, held-out error, BIC) and the verdict;
* :mod:`~mfdesign.diagnose.pipeline`: the whole story in one call (:func:`diagnose`);
* :mod:`~mfdesign.diagnose.report`: pictures, HTML and JSON.

See ``docs/diagnose.md``.
"""

from mfdesign.diagnose.check import CheckResult, calibrate_effects, full_check, verdict
from mfdesign.diagnose.emulated import EmulatorModel, analytic_force, emulator_plane
from mfdesign.diagnose.expected import PlaneSimulator, query_heights, trial_order, usable_rows
from mfdesign.diagnose.residuals import Residuals, breakdowns, compute_residuals, noise_floor, worst_regions
from mfdesign.diagnose.screen import ScreenResult, effect_jacobian, screen

__all__ = [
    "CheckResult", "EmulatorModel", "PlaneSimulator", "analytic_force", "emulator_plane", "Residuals", "ScreenResult", "breakdowns", "calibrate_effects",
    "compute_residuals", "effect_jacobian", "full_check", "noise_floor", "query_heights", "screen",
    "trial_order", "usable_rows", "verdict", "worst_regions",
]
