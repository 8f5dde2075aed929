"""Unit conversions and the one value of g, each defined once for the whole package.

Public interfaces use millimetres, pascals and newtons; the solver works in MPa and mm
(so stresses times lengths are N/mm); the rig's firmware reports lbf and psi.

g is 9.81 m/s^2, not the standard 9.80665: the real mass-lift file (the only
measurements we have) records its 1.5, 2.5 and 4.0 kg lifts as 14.715, 24.525 and
39.24 N, and the paper's design targets are those newtons. A lab comparing new lifts with
that file needs the same conversion; the 0.03 % between the two values is far below the
load cell's resolution, and a second value would make the rig driver, the virtual rig
and the design study disagree in the fourth digit.
"""

from __future__ import annotations

__all__ = ["G_M_S2", "LBF_TO_N", "PA_TO_MPA", "PSI_TO_PA"]

G_M_S2 = 9.81  # m/s^2: the authors' value (see the module doc)
LBF_TO_N = 4.4482216152605  # N per pound-force (exact by definition)
PSI_TO_PA = 6894.757293168  # Pa per pound-force per square inch (exact by definition)
PA_TO_MPA = 1e-6
