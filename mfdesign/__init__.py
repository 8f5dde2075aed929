"""mfdesign: multi-fidelity Bayesian design of axisymmetric soft pneumatic actuators.

Physics runs in float64; importing the package switches JAX to 64-bit mode.
Public interfaces use the units of the data: millimetres, pascals, newtons.
"""

import jax

jax.config.update("jax_enable_x64", True)

from mfdesign.design import DesignSpace, Membrane, Ring  # noqa: E402

__all__ = ["DesignSpace", "Membrane", "Ring"]
__version__ = "0.1.0"
