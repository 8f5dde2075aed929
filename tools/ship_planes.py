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

import os
from pathlib import Path

import numpy as np

from tools import _ship

PACK = _ship.FILES / "planes.npz"


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
    _ship.main(__doc__, pack, PACK, "MFDESIGN_SHIPPED_PLANES", "planes")


if __name__ == "__main__":
    main()
