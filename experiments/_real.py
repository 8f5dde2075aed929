"""What the probes of the real lifts share (``real_probes.py``, ``real_plate_contact.py``,
``real_rings_fe.py``): the fits ``real_floor.py`` wrote, and one seeded sample of floating
lift rows per membrane, the same rows in every probe."""

from __future__ import annotations

import dataclasses
import json

import numpy as np
import pandas as pd

from _common import OUT


def real_floor() -> dict:
    """``experiments/out/real_floor.json`` (its ``cases.all7.map`` is the all-seven MAP)."""
    floor = OUT / "real_floor.json"
    if not floor.exists():
        raise SystemExit(f"{floor} is missing: run `python experiments/real_floor.py` first")
    return json.loads(floor.read_text())


@dataclasses.dataclass(frozen=True)
class LiftSample:
    """The real mass lifts and ``per_membrane`` floating lift rows drawn per membrane."""

    df: pd.DataFrame
    lift: np.ndarray  # rows of lift trials
    floating: np.ndarray  # lift rows with the plate floating (mfdesign.data.lifts.floating_rows)
    keys: list[str]  # the membranes, in the file's order
    rows: dict[str, np.ndarray]  # per membrane: positions (df.iloc) of its sampled rows


def lift_sample(per_membrane: int, seed: int) -> LiftSample:
    """One generator drawn membrane after membrane, in the file's order: a seed gives the
    same rows to every probe."""
    from mfdesign.data.lifts import floating_rows
    from mfdesign.data.spa_design import load_mass_lift

    data = load_mass_lift()
    df = data.df
    lift = (df["experiment"] == "lift").to_numpy()
    floating = lift & floating_rows(data)
    keys = list(dict.fromkeys(df["design_key"]))
    rng = np.random.default_rng(seed)
    rows = {
        k: rng.choice(np.nonzero(floating & (df["design_key"] == k).to_numpy())[0], per_membrane, False) for k in keys
    }
    return LiftSample(df=df, lift=lift, floating=floating, keys=keys, rows=rows)
