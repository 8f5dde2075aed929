"""Pack the traced kernels a cold demo stores into the package.

    python -m tools.ship_kernels                       # run demo and demo --quick on an empty cache, then pack
    python -m tools.ship_kernels --from DIR [DIR ...]  # pack the kernels/ of cache folders such runs filled

Writes ``mfdesign/data/files/kernels.npz`` (file name -> bytes of
``$MFDESIGN_CACHE_DIR/kernels/NAME``: each kernel's ``jax.export`` module and each family's
``.shapes.json``), which :mod:`mfdesign.physics._traces` reads where the user's kernel store
lacks a file: a lab's first demo then traces none of these kernels (issue 40: their tracing was
~38 s of a cold demo on 2 cores, profile_callers.py on 6b24fdf). A kernel's file name is its key (library versions, the
sources its module and arguments import, its arguments' structure and shapes), so a kernel
whose code changed is traced as before and the pack's copy is never read: rerun this after
a change to the physics, the models, the acquisition or the optimiser, or the cold demo
slows by what it traces again (``bench_demo.py`` records ``shipped_kernels``, the pack's
files the run read).

The runs set ``MFDESIGN_SHIPPED_KERNELS=0`` (nothing read from an older pack) and a fresh
``MFDESIGN_CACHE_DIR``; together ~10 minutes on 2 cores.
"""

from __future__ import annotations

import json
import os
from pathlib import Path

import numpy as np

from mfdesign.physics._traces import environment
from tools import _ship

PACK = _ship.FILES / "kernels.npz"
# The environment the pack was made in (library versions, Python): every kernel's key holds
# it, so in another the pack is never read, and its kernels cannot be checked there.
VERSIONS = "versions.json"


def pack(folders: list[Path], dest: Path = PACK) -> int:
    """Every kernel and shapes list under ``folder/kernels`` (or ``folder`` itself) into
    ``dest`` (a family's shapes lists merged); returns the number of kernels."""
    blobs: dict[str, bytes] = {}
    shapes: dict[str, list] = {}
    for folder in folders:
        root = folder / "kernels" if (folder / "kernels").is_dir() else folder
        for path in sorted(root.glob("*.jaxexport")):
            if not path.name.startswith("."):  # "." marks a file being written (mfdesign.outputs)
                blobs.setdefault(path.name, path.read_bytes())
        for path in sorted(root.glob("*.plan.json")):  # the order a default demo calls them in
            if not path.name.startswith("."):
                blobs.setdefault(path.name, path.read_bytes())
        for path in sorted(root.glob("*.roots.json")):  # each kernel's sources and their hash
            if not path.name.startswith("."):
                blobs.setdefault(path.name, path.read_bytes())
        for path in sorted(root.glob("*.shapes.json")):
            if not path.name.startswith("."):
                listed = shapes.setdefault(path.name, [])
                listed += [s for s in json.loads(path.read_text()) if s not in listed]
    if not blobs:
        raise SystemExit(f"no kernels found in {', '.join(map(str, folders))}")
    arrays = {name: np.frombuffer(blob, np.uint8) for name, blob in blobs.items()}
    arrays |= {name: np.frombuffer(json.dumps(listed).encode(), np.uint8) for name, listed in shapes.items()}
    arrays[VERSIONS] = np.frombuffer(json.dumps(environment()).encode(), np.uint8)
    tmp = dest.with_suffix(".tmp.npz")
    np.savez_compressed(tmp, **arrays)
    os.replace(tmp, dest)
    return sum(name.endswith(".jaxexport") for name in blobs)


def main() -> None:
    _ship.main(__doc__, pack, PACK, "MFDESIGN_SHIPPED_KERNELS", "kernels")


if __name__ == "__main__":
    main()
