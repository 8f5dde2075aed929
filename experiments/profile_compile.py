"""Where a cold demo's time goes: XLA compilation per kernel and per stage (issue 40).

Runs ``mfdesign demo --quick`` (or the full demo with ``--full``) in a fresh process with
JAX's compile log on (``JAX_LOG_COMPILES=1``) and an empty compilation cache. With
``--planes DIR`` the new cache folder starts with a copy of DIR's simulator planes, so the
run pays for compilation and computation but not for planes: the difference to a cold
bench_demo run is the planes' cost.

From the log it sums, per jitted function and per demo stage, the seconds XLA reported
("Finished XLA compilation of ... in S sec") and the number of compilations, the seconds
of tracing ("Finished tracing ...") and of lowering to MLIR, and writes
``out/profile_compile.json`` with the commit, the load and the process's wall / user time.

    python experiments/profile_compile.py --planes ~/.cache/mfdesign/planes [--full] [--core 0]

``--log FILE`` reads an existing log of such a run instead of running one (the JSON then
says so, and has no timings of its own); ``--save-log FILE`` keeps the run's log (with
``JAX_LOG_COMPILES`` it names each compiled program's argument shapes: why a kernel
compiled twice). ``recompiled`` in the JSON lists the kernels compiled more than once.
``--keep DIR`` keeps the run's folder there instead of deleting it: the demo's output
(``DIR/demo``: its summary, to check a change left the results as they were) and the cache
(``DIR/cache/planes``: the planes a next run can preload with ``--planes``).
"""

from __future__ import annotations

import collections
import os
import re
import shutil
import subprocess
import sys
import tempfile
import time
from pathlib import Path

from _common import git_state, load, machine, parser, write_json

_COMPILE = re.compile(r"Finished XLA compilation of (\S+).*? in ([\d.e+-]+) sec")
# Python's share: tracing a function to a jaxpr, then lowering it to MLIR. A warm run (the
# persistent cache serves XLA's part) still pays both, every run.
_TRACE = re.compile(r"Finished tracing (?:\+ transforming )?(\S+) for \S+ in ([\d.e+-]+) sec")
_LOWER = re.compile(r"Finished jaxpr to MLIR module conversion (\S+) in ([\d.e+-]+) sec")
_STAGE = re.compile(r"^\[\s*[\d.]+ s\] (.+?) \.\.\.\s*$")


def parse(lines) -> dict:
    """Compile seconds and counts per function and per demo stage, from a compile log."""
    per_fn: dict[str, float] = collections.Counter()
    count: dict[str, int] = collections.Counter()
    per_stage: dict[str, float] = collections.Counter()
    traced: dict[str, float] = collections.Counter()
    trace_stage: dict[str, float] = collections.Counter()
    lower_stage: dict[str, float] = collections.Counter()
    stage = "start"
    for line in lines:
        m = _STAGE.match(line)
        if m:
            stage = m.group(1)
            continue
        m = _TRACE.search(line)
        if m:
            traced[m.group(1)] += float(m.group(2))
            trace_stage[stage] += float(m.group(2))
            continue
        m = _LOWER.search(line)
        if m:
            lower_stage[stage] += float(m.group(2))
            continue
        m = _COMPILE.search(line)
        if m:
            name, secs = m.group(1), float(m.group(2))
            per_fn[name] += secs
            count[name] += 1
            per_stage[stage] += secs
    top = sorted(per_fn, key=per_fn.get, reverse=True)
    row = lambda f: {"function": f, "seconds": round(per_fn[f], 2), "compilations": count[f]}  # noqa: E731
    return {
        "compile_s_total": round(sum(per_fn.values()), 1),
        "compilations": int(sum(count.values())),
        "per_stage_s": {k: round(v, 1) for k, v in per_stage.items()},
        "per_function": [row(f) for f in top[:40]],
        # kernels compiled more than once (new shapes or structures) taking 0.5 s or more:
        # what bucketing shapes can still save
        "recompiled": [row(f) for f in top if count[f] > 1 and per_fn[f] >= 0.5],
        # tracing counts a jit called inside another twice (its own line and its caller's)
        "trace_s_per_stage": {k: round(v, 1) for k, v in trace_stage.items()},
        "lower_s_per_stage": {k: round(v, 1) for k, v in lower_stage.items()},
        "traced_per_function": [
            {"function": f, "seconds": round(v, 2)} for f, v in sorted(traced.items(), key=lambda kv: -kv[1])[:20]
        ],
    }


def main(argv=None) -> dict:
    ap = parser(__doc__)
    ap.add_argument("--planes", type=Path, default=None, help="copy this folder's simulator planes into the new cache")
    ap.add_argument("--full", action="store_true", help="the full demo, not --quick")
    ap.add_argument("--core", type=int, default=None, help="pin the run to this CPU core (taskset)")
    ap.add_argument("--log", type=Path, default=None, help="parse this existing log instead of running")
    ap.add_argument(
        "--save-log", type=Path, default=None, help="also write the run's log here (the compiled shapes, per call)"
    )
    ap.add_argument(
        "--keep", type=Path, default=None, help="keep the run's folder (demo output, cache with planes) here"
    )
    args = ap.parse_args(argv)
    commit, dirty = git_state()
    result: dict = {"commit": commit, "dirty": dirty, "machine": machine(), "load_before": load()}
    if args.log is not None:
        lines = args.log.read_text(errors="replace").splitlines()
        result |= {"source": f"parsed {args.log} (a run made elsewhere; its load is not known here)"}
    else:
        work = Path(tempfile.mkdtemp(prefix="mfdesign-profile-"))
        cache = work / "cache"
        cache.mkdir()
        if args.planes is not None:
            shutil.copytree(args.planes, cache / "planes")
        env = os.environ | {"MFDESIGN_CACHE_DIR": str(cache), "JAX_LOG_COMPILES": "1", "JAX_PLATFORMS": "cpu"}
        cmd = [sys.executable, "-c", "from mfdesign.cli import app; app()", "demo", "--out", str(work / "demo")] + (
            [] if args.full else ["--quick"]
        )
        if args.core is not None:
            cmd = ["taskset", "-c", str(args.core), *cmd]
        t0, r0 = time.perf_counter(), os.times()
        # one stream: the stage lines (stdout) and the compile log (stderr) in their order
        proc = subprocess.run(cmd, env=env, stdout=subprocess.PIPE, stderr=subprocess.STDOUT, text=True)
        r1 = os.times()
        lines = proc.stdout.splitlines()
        if args.save_log is not None:
            args.save_log.parent.mkdir(parents=True, exist_ok=True)
            args.save_log.write_text(proc.stdout)
        result |= {
            "command": " ".join(cmd),
            "planes_preloaded": str(args.planes) if args.planes else None,
            "exit_status": proc.returncode,
            "wall_s": round(time.perf_counter() - t0, 1),
            "user_s": round(r1.children_user - r0.children_user, 1),
            "system_s": round(r1.children_system - r0.children_system, 1),
            "load_after": load(),
        }
        if args.keep is None:
            shutil.rmtree(work, ignore_errors=True)
        else:
            shutil.move(work, args.keep)
            result |= {"kept": str(args.keep)}
    result |= parse(lines)
    path = write_json(args.out / "profile_compile.json", result, indent=1)
    print(
        f"{path}: XLA compile {result['compile_s_total']} s in {result['compilations']} compilations; "
        f"tracing {sum(result['trace_s_per_stage'].values()):.1f} s, lowering {sum(result['lower_s_per_stage'].values()):.1f} s"
    )
    for row in result["per_function"][:8]:
        print(f"  {row['seconds']:7.1f} s  {row['compilations']:4d} x  {row['function']}")
    return result


if __name__ == "__main__":
    main()
