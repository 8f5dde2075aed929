"""Float64 for JAX. Every mfdesign module that uses JAX imports this first.

The physics runs in float64 (the shooting solver and the Gent energy near its lock need
it). ``import mfdesign`` no longer imports JAX (``mfdesign --help`` stays fast), so the
switch happens where JAX is actually used: importing any JAX-using module of the package
(:mod:`mfdesign.design`, :mod:`mfdesign.materials`, the models, the calibration, ...)
turns 64-bit mode on before that module creates an array.
"""

import jax

jax.config.update("jax_enable_x64", True)
