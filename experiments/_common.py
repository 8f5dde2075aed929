"""What the experiments share: the output folder, the machine's description, wall / CPU
timing with the load around it, and atomic JSON (a killed run never leaves a torn file).

Scripts import it as ``from _common import ...``: a script's own folder is on its path.
"""

from __future__ import annotations

import contextlib
import os
import platform
import time
from pathlib import Path
from typing import Any, Iterator

from mfdesign import outputs

OUT = Path(__file__).resolve().parent / "out"


def load() -> list[float]:
    """The 1, 5 and 15 minute load averages (figures are reported with the machine's load)."""
    return list(os.getloadavg())


def machine() -> dict:
    import jax

    return {
        "cpus": os.cpu_count(),
        "platform": platform.platform(),
        "jax": jax.__version__,
        "devices": [str(d) for d in jax.devices()],
        "load_average": load(),
    }


@contextlib.contextmanager
def timed() -> Iterator[dict]:
    """``with timed() as t: ...``; afterwards ``t`` holds wall_s, cpu_s and the load before / after."""
    t: dict[str, Any] = {"load_average_before": load()}
    w0, c0 = time.perf_counter(), time.process_time()
    try:
        yield t
    finally:
        t.update(wall_s=time.perf_counter() - w0, cpu_s=time.process_time() - c0, load_average_after=load())


def write_json(path: str | os.PathLike, data: Any, indent: int = 2) -> Path:
    """Write ``data`` as JSON atomically (``mfdesign.outputs``); the folder is created."""
    path = Path(path)
    path.parent.mkdir(parents=True, exist_ok=True)
    return outputs.write_json(path, data, indent=indent, default=str)
