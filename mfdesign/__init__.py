"""mfdesign: multi-fidelity Bayesian design of axisymmetric soft pneumatic actuators.

Physics runs in float64: importing any JAX-using module of the package (``mfdesign.design``
and everything that builds on it) switches JAX to 64-bit mode (:mod:`mfdesign._x64`).
``import mfdesign`` itself does not import JAX (the CLI's ``--help`` stays fast); the
names below are loaded on first use.
Public interfaces use the units of the data: millimetres, pascals, newtons.
"""

__all__ = ["DesignSpace", "Membrane", "Ring"]
__version__ = "0.1.0"


def __getattr__(name: str):
    if name in __all__:
        from mfdesign import design

        return getattr(design, name)
    raise AttributeError(f"module 'mfdesign' has no attribute {name!r}")
