"""Pack the simulator planes the demo asks of the bundled membranes into the package.

    python -m tools.ship_planes                      # solve them: demo and demo --quick, empty cache
    python -m tools.ship_planes --from DIR [DIR ...] # pack the planes/ of cache folders such runs filled

Writes ``mfdesign/data/files/planes.npz`` (cache key -> signed plane [N], the layout of
``$MFDESIGN_CACHE_DIR/planes/KEY.npy``), which :func:`mfdesign.physics.planes.solve_planes`
reads where the user's cache has no such plane (issue 40: a lab's first demo solved 72
planes, ~190 s of its ~560 s on 2 cores). Rerun it when a change alters the planes the demo
asks for (``tests/physics/test_shipped_planes.py`` fails then: the demo's load stage would
solve planes again) or their content (bump ``planes.SCHEMA``: every old key is orphaned).

The solving runs set ``MFDESIGN_SHIPPED_PLANES=0`` (nothing read from an older pack) and a
fresh ``MFDESIGN_CACHE_DIR``; each takes ~10 minutes on 2 cores.
"""

from __future__ import annotations

import argparse
import os
import subprocess
import sys
import tempfile
from pathlib import Path

import numpy as np

PACK = Path(__file__).resolve().parents[1] / "mfdesign" / "data" / "files" / "planes.npz"


def _solve(cache: Path) -> None:
    env = dict(os.environ, MFDESIGN_CACHE_DIR=str(cache), MFDESIGN_SHIPPED_PLANES="0", JAX_PLATFORMS="cpu")
    for extra in ([], ["--quick"]):
        with tempfile.TemporaryDirectory() as out:
            cmd = [sys.executable, "-m", "mfdesign.cli", "demo", "--out", out, *extra]
            print("running:", " ".join(cmd), flush=True)
            subprocess.run(cmd, env=env, check=True)


def pack(folders: list[Path], dest: Path = PACK) -> int:
    """Every ``KEY.npy`` under ``folder/planes`` (or ``folder`` itself) into ``dest``; returns the count."""
    planes: dict[str, np.ndarray] = {}
    for folder in folders:
        root = folder / "planes" if (folder / "planes").is_dir() else folder
        for path in sorted(root.glob("*.npy")):
            if path.name.startswith("."):  # a plane being written (planes._write_plane)
                continue
            planes.setdefault(path.stem, np.load(path, allow_pickle=False))
    if not planes:
        raise SystemExit(f"no planes found in {', '.join(map(str, folders))}")
    tmp = dest.with_suffix(".tmp.npz")
    np.savez_compressed(tmp, **planes)
    os.replace(tmp, dest)
    return len(planes)


def main() -> None:
    ap = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    ap.add_argument("--from", dest="folders", nargs="+", type=Path, help="cache folders to pack (no solving)")
    args = ap.parse_args()
    if args.folders:
        n = pack(args.folders)
    else:
        with tempfile.TemporaryDirectory() as cache:
            _solve(Path(cache))
            n = pack([Path(cache)])
    print(f"{n} planes -> {PACK} ({PACK.stat().st_size / 1e6:.2f} MB)")


if __name__ == "__main__":
    main()
