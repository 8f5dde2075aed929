"""mfdesign: multi-fidelity Bayesian design of axisymmetric soft pneumatic actuators.

The names below are the short public surface; each has an ``Arguments:`` docstring.
They are loaded on first use, so ``import mfdesign`` (and the CLI's ``--help``) does not
import JAX. Public interfaces use the units of the data: millimetres, pascals, newtons.
Physics runs in float64 (JAX's 64-bit mode is on once a JAX-using module is imported).

* designs: :class:`Membrane`, :class:`Ring`, :class:`DesignSpace`;
* physics: :class:`SimParams`, :func:`force_plane`, :func:`force_at`, :func:`height_at`;
* data: :class:`Measurements`;
* effects: :class:`Effect` (and :mod:`mfdesign.physics.effects` for the library);
* the loop: :func:`calibrate`, :func:`diagnose`, :func:`propose`, :func:`optimize`.
"""

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
    "diagnose": "mfdesign.diagnose.pipeline",
    "propose": "mfdesign.acquire",
    "optimize": "mfdesign.optimize",
}
__all__ = list(_WHERE)


def __getattr__(name: str):
    if name in _WHERE:
        import importlib

        return getattr(importlib.import_module(_WHERE[name]), name)
    raise AttributeError(f"module 'mfdesign' has no attribute {name!r}")


def __dir__():
    return sorted(list(globals()) + __all__)
