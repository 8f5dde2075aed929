"""Which lift rows are equations F(h, p) = W: the plate must float, not rest or be pinned."""

from __future__ import annotations

import numpy as np
import pandas as pd

from mfdesign.data.measurements import Measurements
from mfdesign.diagnosis.expected import usable_rows


def _lift(h, p, trial=0, key="[2.0, 25.4, nan, nan, nan, nan]"):
    n = len(h)
    return pd.DataFrame(
        {
            "design_key": key,
            "trial": np.full(n, trial, np.int64),
            "experiment": "lift",
            "phase": "inflate",
            "time_s": np.arange(n, dtype=float),
            "height_set_mm": np.nan,
            "height_mm": np.asarray(h, float),
            "pressure_pa": np.asarray(p, float),
            "force_n": 14.715,
            "weight": 1.0,
            "source": "file",
        }
    )


def test_a_plate_resting_above_zero_or_pinned_below_the_top_is_not_used():
    p = np.linspace(0.0, 8000.0, 401)
    rest = p < 2000.0
    pinned = p > 6500.0
    # the real rig's resting plate reads 1-4 mm (jitter), then rises 10 mm/kPa, then a
    # tall mass stack pins it at 45 mm while the pressure still rises
    h = np.where(rest, np.tile([1.0, 3.0, 2.0, 4.0], 101)[:401], np.minimum(4.0 + (p - 2000.0) / 100.0, 45.0))
    other = _lift(np.linspace(2.0, 70.0, 50), np.linspace(1500.0, 5000.0, 50), trial=1)  # floats to the rig's top
    meas = Measurements(pd.concat([_lift(h, p), other], ignore_index=True))
    use = usable_rows(meas)[:401]
    assert not use[rest].any()
    assert not use[pinned].any()
    floating = (~rest) & (~pinned) & (h > 6.0) & (h < 44.0)
    assert use[floating].all()
    # a trial that floats all the way keeps its rows (only the global top stop is cut)
    assert usable_rows(meas)[401:].mean() > 0.9


def test_sparse_samples_of_a_steady_rise_are_kept_and_a_snap_is_not():
    """Samples 500 Pa apart (0.2 Hz on the virtual rig) move the plate 6-7 mm each: a
    steady rise, not a jump; a 10 mm move within 20 Pa is a snap-through."""
    p = np.arange(0.0, 10_001.0, 500.0)
    h = np.clip((p - 4000.0) / 75.0, 0.0, 75.0)
    sparse = usable_rows(Measurements(_lift(h, p)))
    assert sparse[h > 2.0].all() and not sparse[h == 0.0].any()
    p = np.linspace(3000.0, 4000.0, 101)
    h = np.where(p < 3500.0, 10.0 + (p - 3000.0) / 100.0, 25.0 + (p - 3500.0) / 100.0)  # jumps 10 mm at 3.5 kPa
    snap = usable_rows(Measurements(_lift(h, p)))
    at = np.argmax(p >= 3500.0)
    assert not snap[at - 1] and not snap[at] and snap[: at - 1].all()
