"""Virtual truth: 95 % credible intervals of mu, J_m and the pressure-sensor parameters cover
the drawn truth in >= 85 % of (seed, parameter) cases over 10 seeds (stand-in simulator)."""

from __future__ import annotations

import numpy as np
import pytest

from mfdesign.models.standin import standin_force, standin_plane
from mfdesign.calibration.validation import truth_trial


@pytest.mark.slow  # ~1-6 min on 2 shared cores (10 calibrations)
def test_virtual_truth_coverage_10_seeds():
    trials = [truth_trial(seed, standin_force, standin_plane, n_steps=500, rows=240) for seed in range(10)]
    covered = np.array(
        [
            [t["covered"][k] for k in ("mu_pa", "jm", "pressure_sensor.offset_pa", "pressure_sensor.gain")]
            for t in trials
        ]
    )
    assert covered.mean() >= 0.85, [t["intervals"] for t in trials]
    # informative, not trivially wide: the mu interval is far narrower than its prior
    widths = [t["intervals"]["mu_pa"][1] - t["intervals"]["mu_pa"][0] for t in trials]
    assert np.median(widths) < 0.15 * 34e3


def test_virtual_truth_coverage_fast():
    """The CI version: 3 seeds, shorter chains; 95 % intervals still cover >= 9 of 12 cases."""
    trials = [truth_trial(seed, standin_force, standin_plane, n_steps=600, rows=160) for seed in range(3)]
    covered = np.array(
        [
            [t["covered"][k] for k in ("mu_pa", "jm", "pressure_sensor.offset_pa", "pressure_sensor.gain")]
            for t in trials
        ]
    )
    assert covered.sum() >= 9, [t["intervals"] for t in trials]
