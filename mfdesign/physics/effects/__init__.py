"""Physical effects that the plain membrane model lacks: the candidates for "what is missing".

One effect per module of this package (the template: ``contact_offset.py``). An
effect is a small frozen :class:`equinox.Module` without fields: class-level ``name``, a
one-line physical ``story`` and its ``parameters`` (each with a unit, a prior, the
``neutral`` value at which the effect does nothing and a ``typical`` realistic magnitude),
and two hooks that :class:`Effect` declares abstract; a :class:`MechanicalEffect`
implements the first, a :class:`MeasurementEffect` the second (the other is the identity):

* ``sim_params(base, theta, context) -> SimParams``: effects on the *mechanics* act only
  through the simulator's inputs (:class:`~mfdesign.physics.params.SimParams`);
  ``row_sim_params(base, theta, rows)`` is its row-wise form for a jitted likelihood.
* ``observed_force_fn(theta, force_fn, rows) -> force_fn``: effects of the *measurement
  chain* (sensors, rig, rate-dependence of the rubber), in JAX: the expected recorded
  force at a row's recorded height and pressure. It is the effect's only implementation:
  the likelihood evaluates it at the recorded rows (:func:`apply_expected_force`) and
  the virtual rig records with it (a force trial at its set-points; a mass lift where it
  equals the weight, :func:`recorded_lift_height`).

``theta`` handed to a hook is the effect's own ``{parameter name: value}``; a missing
name means the neutral value. Across several effects, a flat dict with qualified names
``"effect.parameter"`` is used (see :func:`split_theta`).

Writing a new effect (see ``docs/effects.md``)::

    @register_effect
    class LiftHeightOffset(MeasurementEffect):
        name = "lift_height_offset"
        story = "the time-of-flight sensors read the lifted plate a fixed distance high"
        parameters = (Parameter("offset_mm", "mm", Normal(0.0, 2.0), 0.0, 1.5),)

        def observed_force_fn(self, theta, force_fn, rows):
            # a lift row recorded at h had the plate at h - offset
            return lambda h, p: force_fn(jnp.where(rows.is_force, h, h - theta["offset_mm"]), p)

Sign conventions: heights are of the plate above the membrane plane (mm), the membrane
pushes the plate *up* (positive force), the force falls with height at fixed pressure, so
``dF_dh`` (N/mm) is usually negative.
"""

from mfdesign.physics.effects._base import (
    EFFECTS,
    apply_expected_force,
    apply_row_sim_params,
    observed_force_fn,
    Context,
    Effect,
    MeasurementEffect,
    MechanicalEffect,
    Parameter,
    apply_sim_params,
    recorded_lift_height,
    effect,
    neutral_theta,
    register_effect,
    split_theta,
    typical_theta,
)
from mfdesign.physics.effects._priors import Bijection, LogNormal, Normal, Prior, Uniform, bijection
from mfdesign.physics.effects._rows import Rows

# The library: importing a module registers its effect (mechanics first, then the
# measurement chain: the order of EFFECTS is the order of reports).
from mfdesign.physics.effects.thickness_deviation import ThicknessDeviation
from mfdesign.physics.effects.thickness_gradient import ThicknessGradient
from mfdesign.physics.effects.clamp_prestretch import ClampPrestretch
from mfdesign.physics.effects.ring_softening import RingSoftening
from mfdesign.physics.effects.ring_stiffening import RingStiffening
from mfdesign.physics.effects.contact_offset import ContactOffset
from mfdesign.physics.effects.fabric_inset import FabricInset
from mfdesign.physics.effects.rubber_i2 import RubberI2
from mfdesign.physics.effects.stress_softening import StressSoftening
from mfdesign.physics.effects.pressure_sensor import PressureSensor
from mfdesign.physics.effects.load_cell_offset import LoadCellOffset
from mfdesign.physics.effects.rig_compliance import RigCompliance
from mfdesign.physics.effects.hysteresis import Hysteresis
from mfdesign.physics.effects.lift_preload import LiftPreload

__all__ = [
    "EFFECTS",
    "Bijection",
    "Context",
    "Effect",
    "LogNormal",
    "MeasurementEffect",
    "MechanicalEffect",
    "Normal",
    "Parameter",
    "Prior",
    "Rows",
    "Uniform",
    "apply_expected_force",
    "apply_row_sim_params",
    "apply_sim_params",
    "effect",
    "neutral_theta",
    "observed_force_fn",
    "recorded_lift_height",
    "register_effect",
    "bijection",
    "split_theta",
    "typical_theta",
    "ThicknessDeviation",
    "ThicknessGradient",
    "ClampPrestretch",
    "RingSoftening",
    "RingStiffening",
    "ContactOffset",
    "FabricInset",
    "RubberI2",
    "StressSoftening",
    "PressureSensor",
    "LoadCellOffset",
    "RigCompliance",
    "Hysteresis",
    "LiftPreload",
]
