"""What tools.ship_planes and tools.ship_kernels share: the demo runs that fill a cache, and the command line."""

from __future__ import annotations

import argparse
import os
import subprocess
import sys
import tempfile
from pathlib import Path
from typing import Callable

FILES = Path(__file__).resolve().parents[1] / "mfdesign" / "data" / "files"


def run_demos(cache: Path, off: str) -> None:
    """``mfdesign demo`` and ``demo --quick`` on the cache folder ``cache``, with the shipped
    pack named by the environment variable ``off`` turned off (nothing read from an older pack)."""
    env = dict(os.environ, MFDESIGN_CACHE_DIR=str(cache), JAX_PLATFORMS="cpu", **{off: "0"})
    for extra in ([], ["--quick"]):
        with tempfile.TemporaryDirectory() as out:
            cmd = [sys.executable, "-m", "mfdesign.cli", "demo", "--out", out, *extra]
            print("running:", " ".join(cmd), flush=True)
            subprocess.run(cmd, env=env, check=True)


def main(doc: str, pack: Callable[[list[Path]], int], dest: Path, off: str, noun: str) -> None:
    """``--from DIR ...``: pack those cache folders; else run the demos on an empty cache and pack it."""
    ap = argparse.ArgumentParser(description=doc.splitlines()[0])
    ap.add_argument("--from", dest="folders", nargs="+", type=Path, help="cache folders to pack (no runs)")
    args = ap.parse_args()
    if args.folders:
        n = pack(args.folders)
    else:
        with tempfile.TemporaryDirectory() as cache:
            run_demos(Path(cache), off)
            n = pack([Path(cache)])
    print(f"{n} {noun} -> {dest} ({dest.stat().st_size / 1e6:.2f} MB)")
