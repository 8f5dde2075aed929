"""Rubber I2: the rubber's energy depends on its second invariant too (Mooney-Rivlin).

The paper's Gent constants come from uniaxial coupons, and a uniaxial test barely tells
the first strain invariant from the second (Rivlin & Saunders 1951, Phil. Trans. A 243:251:
biaxial tests are needed). An inflated membrane is stretched nearly equibiaxially, where
the second invariant grows as lambda^4: a share of the modulus carried by an ``I2`` term
(Mooney 1940, J. Appl. Phys. 11:582) leaves small strains alone (``mu`` stays the
small-strain shear modulus) and stiffens large biaxial stretch, straightening the lift's
height-pressure curve where plain Gent softens towards an inflation limit point.
Unfilled silicones carry ``C01 / C10`` of about 0.1-0.3, a share of 0.1-0.25.
"""

from __future__ import annotations

from mfdesign.physics.effects._base import MechanicalEffect, Parameter, register_effect, _replace
from mfdesign.physics.effects._priors import Uniform

__all__ = ["RubberI2"]


@register_effect
class RubberI2(MechanicalEffect):
    name = "rubber_i2"
    story = "the rubber's energy has a second-invariant (Mooney-Rivlin) term that uniaxial coupons cannot see: an inflated membrane stiffens at large biaxial stretch"
    direct_check = "an equibiaxial (bulge) test of a rubber coupon beside the uniaxial one"
    parameters = (
        Parameter("share", "1", Uniform(0.0, 0.8), 0.0, 0.2, "share of the small-strain modulus in the I2 term"),
    )

    def sim_params(self, base, theta, context=None):
        return _replace(base, i2_share=base.i2_share + theta["share"])
