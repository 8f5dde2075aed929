"""What the experiments share: the command line's common flags, the output folder, the
machine's description, wall / CPU timing with the load around it, and atomic JSON (a
killed run never leaves a torn file).

Scripts import it as ``from _common import ...``: Python puts a script's own folder first
on its path (``python experiments/x.py``), so no script touches ``sys.path``.
"""

from __future__ import annotations

import argparse
import contextlib
import json
import os
import platform
import subprocess
import time
from pathlib import Path
from typing import Any, Callable, Iterator

from mfdesign import outputs
from mfdesign._x64 import enable_x64

# Every experiment measures float64 physics: switch JAX to 64-bit here, explicitly, before
# a script creates its first array (importing mfdesign never does).
enable_x64()

OUT = Path(__file__).resolve().parent / "out"
PLANE_CACHE = OUT / "plane_cache"  # simulator planes of the virtual rig (git-ignored)
# The RPN ensemble paper_design.py fits once on the real mass lifts; bench_optimize.py reuses it.
PAPER_DESIGN_MODEL = OUT / "paper_design_model"


class _HelpFormatter(argparse.RawDescriptionHelpFormatter, argparse.ArgumentDefaultsHelpFormatter):
    """The docstring as written (its usage block stays a block) and every default shown."""


def _cache_dir(text: str) -> Path | None:
    return Path(text) if text else None


def parser(
    doc: str | None, *, out: Path = OUT, seed: bool = False, plane_cache: bool = False
) -> argparse.ArgumentParser:
    """The script's argument parser: ``--help`` prints its docstring ``doc``, and the flags
    every experiment spells the same way are already there.

    * ``--out DIR`` (default ``out``): the folder the JSON (and PNG) files go to; their names
      are the script's own;
    * ``--seed N`` (default 0) when ``seed``: the seed of the script's random draws;
    * ``--cache-dir DIR`` / ``--no-cache`` when ``plane_cache``: the virtual rig's simulator
      plane cache (``args.cache_dir``: a folder, or None for no cache; '' also means none).
    """
    ap = argparse.ArgumentParser(description=doc, formatter_class=_HelpFormatter)
    ap.add_argument("--out", type=Path, default=out, metavar="DIR", help="folder the results are written to")
    if seed:
        ap.add_argument("--seed", type=int, default=0, metavar="N", help="seed of the random draws")
    if plane_cache:
        ap.add_argument(
            "--cache-dir", type=_cache_dir, default=PLANE_CACHE, metavar="DIR", help="simulator plane cache ('' = none)"
        )
        ap.add_argument(  # SUPPRESS: --cache-dir's default stands; --help shows no "(default: None)"
            "--no-cache",
            dest="cache_dir",
            action="store_const",
            const=None,
            default=argparse.SUPPRESS,
            help="recompute every simulator plane",
        )
    return ap


def command(script: str, args: argparse.Namespace, skip: tuple[str, ...] = ("out",)) -> str:
    """The command line that repeats a run with every option spelled out (JSON records it).

    Lists are space-separated; a ``store_true`` flag appears when set; None, False and the
    names in ``skip`` (by default the output folder: where a run wrote is not what it did) are
    left out.
    """
    parts = [f"python experiments/{Path(script).name}"]
    for k, v in vars(args).items():
        if k in skip or v is None or v is False:
            continue
        flag = "--" + k.replace("_", "-")
        if v is True:
            parts.append(flag)
        elif isinstance(v, (list, tuple)):
            parts.append(" ".join([flag, *map(str, v)]))
        else:
            parts.append(f"{flag} {v}")
    return " ".join(parts)


def load() -> list[float]:
    """The 1, 5 and 15 minute load averages (figures are reported with the machine's load)."""
    return list(os.getloadavg())


def cpu_info() -> dict:
    """The CPU's model and its widest vector unit: float32 sums of the ensembles may differ in
    their last bits between hosts (AVX2 against AVX-512), and a run that follows a host change
    can then retrace a stored program keyed by a fitted constant (session 46)."""
    model, flags = platform.processor(), set()
    try:
        for line in Path("/proc/cpuinfo").read_text().splitlines():
            name, _, value = line.partition(":")
            if name.strip() == "model name":
                model = value.strip()
            elif name.strip() == "flags":
                flags = set(value.split())
                break
    except OSError:
        pass
    vector = next((v for v in ("avx512f", "avx2", "avx", "sse4_2") if v in flags), "")
    return {"model": model, "vector": vector}


def accelerators() -> list[str]:
    """The GPUs ``nvidia-smi -L`` lists ([] where there is none): a run's line says whether
    the machine had one, whichever backend JAX was told to use (``JAX_PLATFORMS``)."""
    try:
        out = subprocess.run(["nvidia-smi", "-L"], capture_output=True, text=True, timeout=30).stdout
    except (OSError, subprocess.SubprocessError):
        return []
    return [line.strip() for line in out.splitlines() if line.strip()]


def machine() -> dict:
    import jax

    return {
        "cpus": os.cpu_count(),
        "platform": platform.platform(),
        "jax": jax.__version__,
        "backend": jax.default_backend(),
        "devices": [str(d) for d in jax.devices()],
        "accelerators": accelerators(),
        "cpu": cpu_info(),
        "load_average": load(),
    }


def git_state() -> tuple[str, bool]:
    """The repository's commit and whether tracked files differ from it: what a benchmark
    line records, taken before a run that takes minutes. Outside a git checkout (a copy of
    the tree sent to a GPU machine) the commit named by ``MFDESIGN_COMMIT``, else "", and
    False."""

    def git(*args: str) -> str:
        root = Path(__file__).resolve().parents[1]
        try:
            return subprocess.run(["git", *args], cwd=root, capture_output=True, text=True, check=True).stdout.strip()
        except (OSError, subprocess.CalledProcessError):
            return ""

    commit = git("rev-parse", "HEAD")
    if not commit:
        return os.environ.get("MFDESIGN_COMMIT", ""), False
    return commit, bool(git("status", "--porcelain", "--untracked-files=no"))


class Timing(dict):
    """What :func:`timed` yields: after the block ``wall_s``, ``cpu_s`` (this process) and
    the load average before / after; a plain dict, so it goes into JSON as it is."""

    def __init__(self) -> None:
        super().__init__(load_average_before=load())
        self._wall0, self._cpu0 = time.perf_counter(), time.process_time()

    def elapsed(self) -> float:
        """Wall seconds since the block began (progress lines, a JSON written inside the block)."""
        return time.perf_counter() - self._wall0

    def stop(self) -> None:
        self.update(wall_s=self.elapsed(), cpu_s=time.process_time() - self._cpu0, load_average_after=load())


@contextlib.contextmanager
def timed() -> Iterator[Timing]:
    """``with timed() as t: ...``; afterwards ``t`` holds wall_s, cpu_s and the load before / after."""
    t = Timing()
    try:
        yield t
    finally:
        t.stop()


def write_json(path: str | os.PathLike, data: Any, indent: int = 2, default: Callable[[Any], Any] = str) -> Path:
    """Write ``data`` as JSON atomically (``mfdesign.outputs``), newline-terminated; the folder
    is created. ``default`` converts what JSON cannot hold (NumPy scalars, paths)."""
    path = Path(path)
    path.parent.mkdir(parents=True, exist_ok=True)
    return outputs.write_text(path, json.dumps(data, indent=indent, default=default) + "\n")
