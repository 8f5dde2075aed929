"""What made an output: one record for every JSON file a command or a campaign writes.

``provenance(call, seeds, inputs)``: the mfdesign version, the command line or Python call,
the seeds, the sha256 of every input file, the machine (cores, JAX devices, Python,
platform) and the time (UTC). Never imports JAX for it (``--help`` and ``status`` stay fast).
"""

from __future__ import annotations

import datetime
import hashlib
import os
import shlex
import sys
from pathlib import Path
from typing import Iterable

__all__ = ["call_line", "input_hashes", "now", "provenance", "sha256"]


def now() -> str:
    """The time, UTC, to the second (ISO 8601)."""
    return datetime.datetime.now(datetime.timezone.utc).isoformat(timespec="seconds")


def sha256(path: str | os.PathLike) -> str:
    """The sha256 of a file's bytes (read in 1 MiB blocks)."""
    h = hashlib.sha256()
    with open(path, "rb") as fh:
        for block in iter(lambda: fh.read(1 << 20), b""):
            h.update(block)
    return h.hexdigest()


def input_hashes(paths: Iterable[str | os.PathLike]) -> dict[str, str]:
    """``{path: sha256}`` of the input files among ``paths``; a folder (a rig job) gives its
    files' hashes, a name that is no file (``bundled``, ``mass-lift``) is kept as itself."""
    out: dict[str, str] = {}
    for item in paths:
        if not isinstance(item, (str, os.PathLike)):  # a table handed over in Python: no file to hash
            out[f"<{type(item).__name__}>"] = "(in memory)"
            continue
        p = Path(item)
        if p.is_file():
            out[str(p)] = sha256(p)
        elif p.is_dir():
            for f in sorted(q for q in p.rglob("*") if q.is_file() and not q.name.startswith("."))[:64]:
                out[str(f)] = sha256(f)
        else:
            out[str(item)] = "(named source)"
    return out


def call_line(default: str) -> str:
    """The command line when run as ``mfdesign ...`` / ``python -m mfdesign.cli``, else ``default``
    (a Python call's description; also under ``python -m pytest``, whose ``__main__.py`` is
    not ours)."""
    script = Path(sys.argv[0]) if sys.argv and sys.argv[0] else Path()
    if script.name == "mfdesign" or script.parts[-3:] == ("mfdesign", "cli", "__main__.py"):
        return shlex.join(["mfdesign", *sys.argv[1:]])
    return default


def provenance(call: str, seeds: dict | None = None, inputs: dict | None = None) -> dict:
    """What made an output: the mfdesign version, ``call`` (a command line or a Python
    call), ``seeds``, ``inputs`` (name -> sha256 of its bytes) and the machine (cores,
    JAX's devices, Python, platform)."""
    import platform
    from importlib.metadata import PackageNotFoundError, version

    try:
        mine = version("mfdesign")
    except PackageNotFoundError:  # a source tree on the path, not installed
        mine = "unknown"
    devices: list[str] = []
    if "jax" in sys.modules:  # never import JAX for this alone (status must stay fast)
        devices = [str(d) for d in sys.modules["jax"].devices()]
    return {
        "mfdesign_version": mine,
        "call": call,
        "seeds": dict(seeds or {}),
        "inputs_sha256": dict(inputs or {}),
        "machine": {
            "cores": os.cpu_count(),
            "jax_devices": devices,
            "python": platform.python_version(),
            "platform": platform.platform(),
        },
        "time": now(),
    }
