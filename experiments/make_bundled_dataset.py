"""Regenerate the bundled virtual dataset (``mfdesign/data/files/bundled_virtual.parquet``) bit for bit.

Six membranes spanning the design space (ringless, one ring, two rings; four of them the
real mass-lift designs), run through the virtual rig with the paper's protocol (force
characterisation 0-70 mm, 3 trials per height; ringed to 4.3 then 6.1 kPa; ringless to
contact with the rig; mass lifts at 1.5, 2.5, 4.0 kg, 2 trials each), the authors'
simulator constants, sensor noise, and ONE hidden effect: a pressure-sensor zero offset
(``pressure_sensor.offset_pa = 150 Pa``, gain 1). The card ``bundled_card.json``
records seed, effect, protocol, noise, designs, row count, SHA-256 of the Parquet file and
the simulator fingerprint. Same seed, same simulator source and same library versions ->
the same bytes (``tests/rig/test_virtual_rig.py``).

    python experiments/make_bundled_dataset.py [--out mfdesign/data/files] [--cache-dir DIR | --no-cache]
"""

from __future__ import annotations

import dataclasses
import hashlib
import sys
from pathlib import Path

from _common import PLANE_CACHE, Timing, parser, write_json  # experiments/ is on a script's path

ROOT = Path(__file__).resolve().parents[1]
SEED = 20250401  # the paper's arXiv month; any fixed integer would do
HIDDEN_EFFECT = "pressure_sensor"
HIDDEN_THETA = {"pressure_sensor.offset_pa": 150.0, "pressure_sensor.gain": 1.0}
PARQUET = "bundled_virtual.parquet"
CARD = "bundled_card.json"
DESIGN_KEYS = (
    "[2.0, 25.4, nan, nan, nan, nan]",  # real (mass-lift file), ringless
    "[1.0, 38.1, nan, nan, nan, nan]",  # thin, large disk, ringless
    "[1.5, 30.0, 45.0, 6.0, nan, nan]",  # one ring
    "[2.0, 25.4, 33.4, 5.0, 46.4, 5.0]",  # real, two rings (optimised design A)
    "[2.33, 29.63, 37.63, 5.0, 62.0, 5.0]",  # real, two rings
    "[2.0, 38.1, 47.55, 6.45, 62.0, 5.0]",  # real, two rings, large disk
)


def default_protocol():
    from mfdesign.rig.virtual import Protocol

    return Protocol()  # 10 Hz at 100 Pa/s: one sample per 10 Pa


def build(
    out_dir,
    designs=None,
    simulator=None,
    protocol=None,
    seed: int = SEED,
    cache_dir=PLANE_CACHE,
    progress: bool = True,
) -> dict:
    """Run the virtual rig and write the Parquet file and its card into ``out_dir``."""
    import jax
    import numpy as np
    import pandas as pd
    import pyarrow

    from mfdesign.design import Membrane
    from mfdesign.physics.effects import effect
    from mfdesign.rig.virtual import VirtualRig, simulator_fingerprint

    out_dir = Path(out_dir)
    out_dir.mkdir(parents=True, exist_ok=True)
    designs = [Membrane.from_key(k) for k in DESIGN_KEYS] if designs is None else list(designs)
    protocol = default_protocol() if protocol is None else protocol
    rig = VirtualRig(
        effects=[HIDDEN_EFFECT],
        theta=HIDDEN_THETA,
        seed=seed,
        protocol=protocol,
        simulator=simulator,
        cache_dir=cache_dir,
    )
    clock = Timing()
    m = rig.run(designs, progress=progress)
    parquet = out_dir / PARQUET
    m.to_parquet(parquet)
    sha = hashlib.sha256(parquet.read_bytes()).hexdigest()
    df = m.df
    e = effect(HIDDEN_EFFECT)
    card = {
        "file": PARQUET,
        "what": "virtual measurements of soft pneumatic actuator membranes (Measurements table, source 'virtual')",
        "seed": seed,
        "hidden_effect": {
            "name": HIDDEN_EFFECT,
            "story": e.story,
            "theta": HIDDEN_THETA,
            "units": {p.name: p.unit for p in e.parameters},
            "note": "observed pressure = gain * true pressure + offset (before sensor noise); "
            "the simulator constants are the authors' (SimParams() defaults)",
        },
        "simulator": "mfdesign.physics.solve.force_plane" if simulator is None else repr(simulator),
        "simulator_fingerprint": simulator_fingerprint(),
        "protocol": dataclasses.asdict(protocol),
        "noise": dataclasses.asdict(rig.noise),
        "designs": [d.key() for d in designs],
        "n_rows": int(len(df)),
        "rows_per_membrane": {k: int(v) for k, v in df.groupby("design_key", sort=False).size().items()},
        "trials_per_membrane": {k: int(v) for k, v in df.groupby("design_key", sort=False)["trial"].nunique().items()},
        "bursts": [ev for ev in rig.events if ev["status"] == "burst"],
        "omitted_samples": int(sum(ev.get("n_omitted", 0) for ev in rig.events)),
        "sha256": sha,
        "bytes": parquet.stat().st_size,
        "versions": {
            "python": sys.version.split()[0],
            "numpy": np.__version__,
            "pandas": pd.__version__,
            "pyarrow": pyarrow.__version__,
            "jax": jax.__version__,
        },
        "regenerate": "python experiments/make_bundled_dataset.py",
    }
    card_path = write_json(out_dir / CARD, card, indent=1, default=float)
    return {"parquet": parquet, "card": card_path, "card_data": card, "seconds": round(clock.elapsed(), 1)}


def main(argv=None) -> None:
    ap = parser(__doc__, out=ROOT / "mfdesign" / "data" / "files", plane_cache=True)
    args = ap.parse_args(argv)
    from mfdesign._cache import enable_compilation_cache

    enable_compilation_cache()
    res = build(args.out, cache_dir=args.cache_dir)
    c = res["card_data"]
    print(
        f"{res['parquet']}: {c['n_rows']} rows, {c['bytes'] / 1e6:.2f} MB, sha256 {c['sha256'][:16]}..., "
        f"{len(c['bursts'])} burst(s), {res['seconds']} s"
    )


if __name__ == "__main__":
    main()
