"""JAX's persistent compilation cache: how much a second ``mfdesign simulate`` saves.

Runs ``mfdesign simulate`` on a small plane (``--n-heights`` x ``--n-pressures``) three
times, each in a fresh Python process:

1. **cold**: an empty cache folder (``MFDESIGN_CACHE_DIR``, see ``mfdesign.cli._app``);
2. **warm**: the same folder again, now holding what run 1 compiled;
3. **control**: another empty folder (a cold run after the warm one, so that a difference
   between runs 1 and 2 is not the machine warming up: OS file cache, load).

Prints wall and CPU seconds (the child's user + system) of each run and the ratios
cold / warm; writes ``bench_cache.json``. The machine's load goes into the JSON with every
run: on a shared CPU the wall times are upper bounds, the CPU times the steadier figure.
"""

from __future__ import annotations

import os
import resource
import subprocess
import sys
import tempfile
import time
from pathlib import Path

from _common import command, load, machine, parser, timed, write_json


def _run(cache: Path, out: Path, args) -> dict:
    """One ``mfdesign simulate`` in a fresh process with ``cache`` as its compilation cache."""
    env = dict(os.environ, MFDESIGN_CACHE_DIR=str(cache))
    cmd = [
        sys.executable,
        "-m",
        "mfdesign.cli",
        "simulate",
        "--n-heights",
        str(args.n_heights),
        "--n-pressures",
        str(args.n_pressures),
        "--out",
        str(out),
    ]
    before = resource.getrusage(resource.RUSAGE_CHILDREN)
    with timed() as t:
        subprocess.run(cmd, env=env, check=True, capture_output=True, text=True)
    after = resource.getrusage(resource.RUSAGE_CHILDREN)
    entries = sorted(p.name for p in cache.iterdir() if p.is_file())
    return {
        "wall_s": round(t["wall_s"], 2),
        "cpu_s": round((after.ru_utime - before.ru_utime) + (after.ru_stime - before.ru_stime), 2),
        "load_average_before": t["load_average_before"],
        "load_average_after": t["load_average_after"],
        "cache_entries": len(entries),
        "cache_bytes": sum((cache / p).stat().st_size for p in entries),
    }


def main() -> None:
    ap = parser(__doc__)
    ap.add_argument("--n-heights", type=int, default=4, help="plate heights of the simulated plane")
    ap.add_argument("--n-pressures", type=int, default=4, help="pressures of the simulated plane")
    args = ap.parse_args()
    t0 = time.perf_counter()
    with tempfile.TemporaryDirectory(prefix="mfdesign_bench_cache_") as tmp:
        tmp = Path(tmp)
        cache, control = tmp / "cache", tmp / "cache_control"
        cache.mkdir()
        control.mkdir()
        runs = {}
        for name, folder in (("cold", cache), ("warm", cache), ("control", control)):
            runs[name] = _run(folder, tmp / f"sim_{name}", args)
            r = runs[name]
            print(f"{name:8s} wall {r['wall_s']:6.1f} s  cpu {r['cpu_s']:6.1f} s  cache entries {r['cache_entries']}")
    cold_wall = (runs["cold"]["wall_s"] + runs["control"]["wall_s"]) / 2
    cold_cpu = (runs["cold"]["cpu_s"] + runs["control"]["cpu_s"]) / 2
    ratios = {
        "cold_over_warm_wall": round(cold_wall / runs["warm"]["wall_s"], 2),
        "cold_over_warm_cpu": round(cold_cpu / runs["warm"]["cpu_s"], 2),
    }
    print(
        f"cold (mean of runs 1 and 3) / warm: wall {ratios['cold_over_warm_wall']:.2f}x, "
        f"cpu {ratios['cold_over_warm_cpu']:.2f}x"
    )
    path = write_json(
        args.out / "bench_cache.json",
        {
            "command": command(__file__, args),
            "machine": machine(),
            "plane": [args.n_heights, args.n_pressures],
            "runs": runs,
            "ratios": ratios,
            "total_s": round(time.perf_counter() - t0, 1),
            "load_average_end": load(),
        },
    )
    print(f"wrote {path}")


if __name__ == "__main__":
    main()
