"""mfdesign: multi-fidelity Bayesian design of axisymmetric soft pneumatic actuators.

The names below are the short public surface; each has an ``Arguments:`` docstring.
They are loaded on first use, so ``import mfdesign`` (and the CLI's ``--help``) does not
import JAX. Public interfaces use the units of the data: millimetres, pascals, newtons.
Physics runs in float64 (JAX's 64-bit mode is on once a JAX-using module is imported).

* designs: :class:`Membrane`, :class:`Ring`, :class:`DesignSpace`;
* physics: :class:`SimParams`, :func:`force_plane`, :func:`force_at`, :func:`height_at`;
* data: :class:`Measurements`, :func:`load`;
* effects: :class:`Effect` (and :mod:`mfdesign.physics.effects` for the library);
* the loop, one call a step (``notebooks/tutorial.ipynb``): :func:`load`, :func:`compare`,
  :func:`diagnose`, :func:`fit_multi_fidelity` (calibrate + discrepancy),
  :func:`calibrate` (the posterior alone), :func:`propose`, :func:`optimize`;
* a lab's loop over many rounds, in one folder: :class:`Campaign` (``create``, ``open``,
  ``diagnose``, ``fit``, ``ask``, ``tell``, ``status``; ``docs/campaign.md``).
"""

from __future__ import annotations

import os
from collections.abc import Sequence
from typing import TYPE_CHECKING

if TYPE_CHECKING:  # names for the annotations only: importing them at run time would pull in JAX
    from mfdesign.data.measurements import Measurements
    from mfdesign.diagnosis.residuals import Residuals

__version__ = "0.1.0"

_WHERE = {
    "Membrane": "mfdesign.design",
    "Ring": "mfdesign.design",
    "DesignSpace": "mfdesign.design",
    "SimParams": "mfdesign.physics.params",
    "force_plane": "mfdesign.physics.solve",
    "force_at": "mfdesign.physics.solve",
    "height_at": "mfdesign.physics.solve",
    "Measurements": "mfdesign.data.measurements",
    "Effect": "mfdesign.physics.effects",
    "calibrate": "mfdesign.calibration.mcmc",
    "fit_multi_fidelity": "mfdesign.calibration.workflow",
    "diagnose": "mfdesign.diagnosis.pipeline",
    "propose": "mfdesign.acquire",
    "optimize": "mfdesign.optimization",
    "enable_x64": "mfdesign._x64",
    "Campaign": "mfdesign.campaign",
}
__all__ = [*_WHERE, "load", "compare"]


def load(source: str | os.PathLike | Sequence[str | os.PathLike] = "bundled", fmt: str = "auto") -> Measurements:
    """Read measurements: the bundled dataset, a file, a rig job folder, or several of them.

    The same reader as the command line's ``DATA`` argument
    (:func:`mfdesign.data.sources.load_sources`).

    **Arguments:**

    - `source`: `"bundled"` (six membranes measured on the virtual rig with one hidden
      effect, `mfdesign/data/files/bundled_virtual.parquet`), `"mass-lift"` (the paper's
      real data), a Measurements Parquet or CSV file, an SPA_Design pickle, a rig job
      folder, or a list of these (concatenated; trial ids renumbered per membrane).
    - `fmt`: `"auto"` (detected from the file) or a format name of
      :data:`mfdesign.data.sources.FORMATS`.

    **Returns:**

    A :class:`Measurements` table (heights mm, pressures Pa, forces N; columns in
    ``docs/data.md``). Raises :class:`mfdesign.errors.InputError` (a `ValueError`) naming
    the source when it is missing or malformed.
    """
    from mfdesign.data.sources import load_sources

    return load_sources(source, fmt)


def compare(meas: Measurements, sim=None) -> Residuals:
    """Compare the plain simulator (the authors' constants, no effects) with measurements.

    The residuals that :func:`diagnose` starts from, without its effect search (it is
    ``diagnose(meas, sim, search=False).before``).

    **Arguments:**

    - `meas`: the measurements (:class:`Measurements`, e.g. from :func:`load`).
    - `sim`: the forward model, as in :func:`diagnose`: default the bundled neural emulator
      (fast; about 1 N RMS off the simulator); for simulator accuracy
      ``mfdesign.diagnosis.forward.forward_model("exact", meas)`` (simulator planes of the
      measured membranes, solved once and cached; minutes the first time).

    **Returns:**

    A :class:`~mfdesign.diagnosis.residuals.Residuals`: one row per usable measurement
    (``frame`` with ``height_mm``, ``pressure_pa``, ``observed_n``, ``predicted_n``,
    ``residual_n`` = observed - predicted [N], ...), the noise floor ``noise_floor_n`` [N]
    estimated from the data alone, ``rmse_n`` and ``bias_n`` [N], ``summary()``, and the rows
    left out with their reason (``dropped``: e.g. lift rows with the plate on its stop).
    """
    from mfdesign.diagnosis.pipeline import diagnose

    return diagnose(meas, sim, search=False).before


def __getattr__(name: str):
    if name in _WHERE:
        import importlib

        return getattr(importlib.import_module(_WHERE[name]), name)
    raise AttributeError(f"module 'mfdesign' has no attribute {name!r}")


def __dir__():
    return sorted(list(globals()) + __all__)
