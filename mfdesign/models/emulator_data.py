"""Training data for the simulator emulator: simulator planes over designs and priors.

Each *sample* is one ``(design, SimParams)`` pair drawn from the design space (0, 1, 2
rings in turn) and the ranges in :data:`PARAM_RANGES` (they cover the calibration priors
and the effects library's priors, :mod:`mfdesign.physics.effects`), solved by
:func:`mfdesign.physics.solve.force_plane` on a randomly placed ``N_H x N_P`` grid of
heights (0-80 mm) and pressures (0-10 kPa). The grid *shape* is fixed, so JAX compiles
once (every ring count has the same array shapes); the *values* vary, so the data cover the plane densely. Points with
status OK or NO_CONTACT (force 0) are kept, failures dropped.

Samples are written in parts (Parquet) of ``chunk`` samples: a killed run loses at most
one part and resumes from the next sample id (sample ``i`` is drawn from a generator
seeded by ``(seed, i)``, so a resumed run produces the same data).

    python -m mfdesign.models.emulator_data --n 2000 --out data/emulator/parts
"""

from __future__ import annotations

import argparse
import math
from pathlib import Path

import jax
import jax.numpy as jnp
import numpy as np
import pandas as pd

from mfdesign._x64 import enable_x64
from mfdesign.design import DesignSpace
from mfdesign.physics.params import SimParams
from mfdesign.physics.status import Status

N_H, N_P = 8, 8
H_RANGE_MM = (0.0, 80.0)
P_RANGE_PA = (0.0, 10_000.0)
# (low, high, "lin" | "log"): uniform or log-uniform.
PARAM_RANGES: dict[str, tuple[float, float, str]] = {
    "mu_pa": (15.0e3, 50.0e3, "lin"),
    "jm": (10.0, 100.0, "log"),
    "ring_mu_pa": (0.03e6, 1.5e6, "log"),
    "thickness_factor": (0.7, 1.3, "lin"),
    "thickness_gradient": (-0.45, 0.45, "lin"),
    "clamp_prestretch": (1.0, 1.08, "lin"),
    "contact_offset_mm": (0.0, 6.0, "lin"),
}
RING_JM = 25.0  # fixed (the authors' fabric)
OFFSET_GAP_MM = 1.0  # rubber kept between the effective disk edge and the first ring
PARAM_FIELDS = (
    "mu_pa",
    "jm",
    "ring_mu_pa",
    "ring_jm",
    "thickness_factor",
    "thickness_gradient",
    "clamp_prestretch",
    "contact_offset_mm",
)
DESIGN_COLS = ("t_mm", "c_mm", "r1_mm", "w1_mm", "r2_mm", "w2_mm")


def _draw(rng: np.random.Generator, lo: float, hi: float, kind: str) -> float:
    if kind == "log":
        return float(math.exp(rng.uniform(math.log(lo), math.log(hi))))
    return float(rng.uniform(lo, hi))


def draw_sample(seed: int, i: int, space: DesignSpace = DesignSpace()):
    """Sample ``i``: design array [6] (mm), params dict, heights [N_H] mm, pressures [N_P] Pa."""
    rng = np.random.default_rng([seed, i])
    n_rings = i % 3
    design = space.decode_array(rng.uniform(size=space.dim(n_rings)), n_rings)
    params = {k: _draw(rng, *v) for k, v in PARAM_RANGES.items()}
    params["ring_jm"] = RING_JM
    if n_rings:  # the effective disk must stay clear of the first ring
        room = design[2] - design[3] - design[1] - OFFSET_GAP_MM
        params["contact_offset_mm"] = min(params["contact_offset_mm"], max(room, 0.0))
    h = np.sort(rng.uniform(*H_RANGE_MM, size=N_H))
    if rng.uniform() < 0.3:
        h[0] = 0.0
    p = np.sort(rng.uniform(*P_RANGE_PA, size=N_P))
    p = np.maximum(p, 50.0) + 1e-3 * np.arange(N_P)  # strictly increasing, > 0
    return design, params, h, p


def solve_sample(seed: int, i: int) -> pd.DataFrame:
    """Run the simulator on sample ``i``; rows of the usable points (OK, NO_CONTACT)."""
    enable_x64()  # float64 physics: mfdesign._x64
    from mfdesign.design import Membrane
    from mfdesign.physics.solve import force_plane

    design, params, h, p = draw_sample(seed, i)
    # Array leaves: SimParams values are traced, so new values do not recompile.
    sp = SimParams(**{k: jnp.asarray(v, float) for k, v in params.items()})
    res = force_plane(Membrane.from_array(design), h, p, sp)
    H, P = np.meshgrid(h, p, indexing="ij")
    keep = np.isin(res.status, [Status.OK, Status.NO_CONTACT])
    n = int(keep.sum())
    df = pd.DataFrame({"sample": np.full(n, i, np.int32), "n_rings": np.full(n, i % 3, np.int8)})
    for k, col in enumerate(DESIGN_COLS):
        df[col] = np.full(n, design[k])
    for k in PARAM_FIELDS:
        df[k] = np.full(n, params[k])
    df["height_mm"] = H[keep]
    df["pressure_pa"] = P[keep]
    df["force_n"] = res.force_n[keep]
    df["status"] = res.status[keep].astype(np.int8)
    df["n_grid"] = np.full(n, H.size, np.int16)
    return df


def done_samples(out: Path) -> set[int]:
    ids: set[int] = set()
    for f in sorted(out.glob("part_*.parquet")):
        ids |= set(pd.read_parquet(f, columns=["sample"])["sample"].unique().tolist())
    for f in sorted(out.glob("empty_*.txt")):  # samples where nothing converged
        ids |= {int(x) for x in f.read_text().split()}
    return ids


def generate(out: Path, n: int, seed: int = 0, chunk: int = 12, start: int = 0) -> None:
    """Solve samples ``start .. start + n - 1`` not yet in ``out`` (resumable)."""
    from tqdm.auto import tqdm

    out.mkdir(parents=True, exist_ok=True)
    todo = [i for i in range(start, start + n) if i not in done_samples(out)]
    frames, empty = [], []
    for i in tqdm(todo, desc="simulator samples", mininterval=10):
        df = solve_sample(seed, i)
        (frames if len(df) else empty).append(df if len(df) else i)
        if len(frames) + len(empty) >= chunk or i == todo[-1]:
            tag = f"{seed}_{i:06d}"
            if frames:
                tmp = out / f"part_{tag}.parquet.tmp"
                pd.concat(frames, ignore_index=True).to_parquet(tmp)
                tmp.rename(out / f"part_{tag}.parquet")
            if empty:
                (out / f"empty_{tag}.txt").write_text(" ".join(map(str, empty)))
            frames, empty = [], []


def load_training(out: Path) -> pd.DataFrame:
    """All parts in ``out`` as one table (a ``training.parquet`` file is read as is)."""
    out = Path(out)
    if out.is_file():
        return pd.read_parquet(out)
    parts = sorted(out.glob("part_*.parquet"))
    if not parts:
        raise FileNotFoundError(f"no simulator parts (part_*.parquet) in {out}")
    return pd.concat([pd.read_parquet(f) for f in parts], ignore_index=True)


def main(argv=None) -> None:
    ap = argparse.ArgumentParser(description=__doc__.split("\n")[0])
    ap.add_argument("--n", type=int, default=2000)
    ap.add_argument("--seed", type=int, default=0)
    ap.add_argument("--start", type=int, default=0)
    ap.add_argument("--chunk", type=int, default=12)
    ap.add_argument("--out", type=Path, default=Path("data/emulator/parts"))
    ap.add_argument("--cache", type=str, default="/tmp/mfdesign_jax_cache")
    a = ap.parse_args(argv)
    if a.cache:
        jax.config.update("jax_compilation_cache_dir", a.cache)
        jax.config.update("jax_persistent_cache_min_compile_time_secs", 1.0)
    generate(a.out, a.n, a.seed, a.chunk, a.start)


if __name__ == "__main__":
    main()
