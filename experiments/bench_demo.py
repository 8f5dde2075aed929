"""The README's main job, timed and weighed: ``mfdesign demo`` per stage (issue 40).

Runs ``mfdesign demo --out DIR`` in a fresh process, wrapped in ``/usr/bin/time -v``:

* **cold** (default): ``MFDESIGN_CACHE_DIR`` a new temporary folder, so the plane cache
  and JAX's compilation cache are empty (what a lab's first run meets);
* ``--warm DIR``: that cache folder as it is (run cold with ``--keep-cache DIR`` first,
  or point it at a folder a cold run filled), for the warm figure;
* ``--quick``: ``mfdesign demo --quick`` (the install test's and browser test's smoke run);
* ``--solve-planes``: ``MFDESIGN_SHIPPED_PLANES=0``, so the demo solves the bundled
  membranes' planes instead of reading those shipped in the package (what every cold run
  did before session 38; ``shipped_planes`` in the record says which);
* ``--trace-kernels``: ``MFDESIGN_SHIPPED_KERNELS=0``, so the demo traces every kernel
  instead of reading those shipped in the package (what every cold run did before session
  40; ``shipped_kernels`` says which, and ``kernels`` how many the run read from the pack,
  from the user's store, or traced: in a cold run with the pack on, "traced" counts what a
  stale pack no longer holds, ``python -m tools.ship_kernels``).

Records, one JSON line per run appended to ``experiments/out/bench_demo.jsonl`` (the
trajectory over commits): the commit, the machine (CPUs, ``nproc``, load average before
and after), total wall and CPU seconds, peak RSS (``/usr/bin/time -v``'s "Maximum
resident set size"; ``getrusage(RUSAGE_CHILDREN)`` where that program is missing), each
stage's wall / CPU seconds and peak RSS so far (the demo's ``summary.json``
``stage_resources``; ``timings_s`` alone for a demo that predates it) and the demo's
result checks (``summary.json``): after / floor <= 1.2, both chains converged, the truth
inside every 90 % interval. And ``speed_probe``: a fixed workload (Python, an XLA
compilation and its run; none of mfdesign's code) timed just before the demo, so that runs
on machines of different speed can be told apart (:data:`_PROBE`).

Prints the stage table, the probe against the previous run's, then as its last two lines the stages against the previous line
of the JSONL run in the same mode (ratios now / then) and one summary line::

    bench_demo: cold wall 266.3 s (target 300 s), peak RSS 1.80 GB (target 2 GB), results ok

Figures on a shared CPU are upper bounds: read them beside the load average recorded.
Debian's ``time`` package provides ``/usr/bin/time`` (``apt-get install time``).
"""

from __future__ import annotations

import datetime
import json
import os
import re
import resource
import shutil
import subprocess
import sys
import tempfile
import time
from pathlib import Path

from _common import accelerators, command, cpu_info, git_state, load, parser

JSONL = "bench_demo.jsonl"
# Issue 40's targets on the 2-core CPU [s]; the warm quick run has none of its own.
TARGET_WALL_S = {"cold": 300.0, "warm": 120.0, "quick": 120.0}
TARGET_RSS_GB = 2.0
AFTER_OVER_FLOOR_MAX = 1.2  # the demo's diagnosis must leave at most this many noise floors
TIME_V = Path("/usr/bin/time")

# A fixed workload, none of mfdesign's code, timed in a fresh process just before the demo:
# the demo's time is Python (tracing), XLA compilation and XLA execution on the CPU, and
# the same commit ran 2.0x slower on one day's machine than on another's (sessions 30 and
# 32: the quick demo of unchanged code, 349.1 vs 707.4 s). A run's wall is read beside its
# probe: two runs whose probes differ measured two machines. Best of three, each part.
_PROBE = r"""
import json, os, time
os.environ["JAX_PLATFORMS"] = "cpu"
import jax, jax.numpy as jnp
jax.config.update("jax_enable_x64", True)
jax.config.update("jax_enable_compilation_cache", False)
py, comp, run = [], [], []
for k in range(3):
    t = time.perf_counter(); s = 0
    for i in range(2_000_000):
        s += i * i
    py.append(time.perf_counter() - t)
    def f(x, k=k):  # a new function each time: compiled anew
        def body(i, y):
            return jnp.tanh(y @ y.T / y.shape[0]) + jnp.sin(y + k) * jnp.exp(-y * y)
        return jax.lax.fori_loop(0, 400, body, x).sum()
    x = jnp.full((96, 96), 0.01)
    t = time.perf_counter(); c = jax.jit(jax.grad(f)).lower(x).compile(); comp.append(time.perf_counter() - t)
    t = time.perf_counter(); c(x).block_until_ready(); run.append(time.perf_counter() - t)
print(json.dumps({"python_s": min(py), "xla_compile_s": min(comp), "xla_run_s": min(run)}))
"""


def speed_probe() -> dict | None:
    """The machine's speed on :data:`_PROBE` (seconds of each part and their sum; None
    where the probe fails: the benchmark runs without it)."""
    env = dict(os.environ, JAX_PLATFORMS="cpu")
    try:
        out = subprocess.run([sys.executable, "-c", _PROBE], env=env, capture_output=True, text=True, timeout=300)
        probe = {k: round(float(v), 3) for k, v in json.loads(out.stdout.strip().splitlines()[-1]).items()}
    except (subprocess.SubprocessError, OSError, ValueError, IndexError):
        return None
    probe["total_s"] = round(sum(probe.values()), 3)
    return probe


def probe_line(record: dict, prev: dict | None) -> str:
    """The machine's probe now against the previous run's (the ratio > 1: a slower machine)."""
    now, then = record.get("speed_probe"), (prev or {}).get("speed_probe")
    if not now:
        return "machine probe: failed"
    parts = ", ".join(f"{k[:-2]} {v:.2f}" for k, v in now.items() if k != "total_s")
    ratio = _ratio(now["total_s"], (then or {}).get("total_s")) if then else "no earlier probe"
    return f"machine probe: {now['total_s']:.2f} s ({parts}) vs previous run: {ratio}"


# ``/usr/bin/time -v`` lines this script reads (GNU time 1.7-1.9 spell them so).
_TIME_FIELDS = {
    "user_s": r"User time \(seconds\): ([\d.]+)",
    "sys_s": r"System time \(seconds\): ([\d.]+)",
    "max_rss_kb": r"Maximum resident set size \(kbytes\): (\d+)",
    "wall": r"Elapsed \(wall clock\) time \(h:mm:ss or m:ss\): ([\d:.]+)",
    "exit_status": r"Exit status: (\d+)",
}


def parse_time_v(text: str) -> dict:
    """The figures of ``/usr/bin/time -v``'s report: user / system seconds, peak RSS [kB],
    wall seconds, exit status (a field it did not print is absent)."""
    out: dict = {}
    for key, pattern in _TIME_FIELDS.items():
        m = re.search(pattern, text)
        if not m:
            continue
        v = m.group(1)
        if key == "wall":  # h:mm:ss or m:ss(.ss)
            secs = 0.0
            for part in v.split(":"):
                secs = 60.0 * secs + float(part)
            out["wall_s"] = round(secs, 2)
        elif key in ("max_rss_kb", "exit_status"):
            out[key] = int(v)
        else:
            out[key] = float(v)
    return out


def mode_of(quick: bool, warm: bool) -> str:
    return ("quick" if quick else "") + ("-warm" if quick and warm else "warm" if warm else "" if quick else "cold")


def short(stage: str) -> str:
    """A stage's name for the one-line table: its first word (the demo's stage names carry
    the effect found, ``add pressure_sensor: ...``, which differs between runs)."""
    return stage.split()[0].rstrip(":,") if stage.split() else stage


def stages_of(summary: dict) -> dict[str, dict]:
    """Per stage (short name) wall and, where the demo recorded them, CPU seconds and peak
    RSS [MB] from ``summary.json``."""
    res = summary.get("stage_resources") or {}
    out = {}
    for name, wall in (summary.get("timings_s") or {}).items():
        row = {"wall_s": wall}
        row.update({k: v for k, v in (res.get(name) or {}).items() if k != "wall_s"})
        out[short(name)] = row
    return out


def results_of(summary: dict) -> dict:
    """The demo's result checks (issue 40, item 3): after / floor, both chains converged, the
    truth inside every 90 % interval; ``ok`` when all three hold."""
    diag = summary.get("diagnosis") or {}
    ratio = diag.get("after_over_floor")
    conv = {tag: bool(c.get("converged")) for tag, c in (summary.get("convergence") or {}).items()}
    truth = {name: bool(c.get("inside")) for name, c in (summary.get("truth_check") or {}).items()}
    ok = (
        ratio is not None
        and ratio <= AFTER_OVER_FLOOR_MAX
        and bool(conv)
        and all(conv.values())
        and all(truth.values())
    )
    return {
        "found": diag.get("found"),
        "after_over_floor": ratio,
        "converged": conv,
        "truth_inside": truth,
        "ok": bool(ok and bool(truth)),
    }


def read_jsonl(path: Path) -> list[dict]:
    """Every record of the JSONL file (a torn last line, from a killed writer, is skipped)."""
    if not path.is_file():
        return []
    out = []
    for line in path.read_text().splitlines():
        try:
            out.append(json.loads(line))
        except json.JSONDecodeError:
            continue
    return out


def previous(records: list[dict], mode: str) -> dict | None:
    """The last record of the same mode (a cold run compared with a warm one says nothing)."""
    same = [r for r in records if r.get("mode") == mode]
    return same[-1] if same else None


def append_jsonl(path: Path, record: dict) -> None:
    """One line appended (the file is a log: earlier lines are never rewritten)."""
    path.parent.mkdir(parents=True, exist_ok=True)
    # a killed writer's torn last line has no newline: start a fresh line, or this record
    # would be glued to it and lost with it
    torn = path.is_file() and path.stat().st_size > 0 and not path.read_bytes().endswith(b"\n")
    with open(path, "a") as f:
        f.write(("\n" if torn else "") + json.dumps(record, default=str) + "\n")


def _ratio(now, then) -> str:
    return f"x{now / then:.2f}" if isinstance(now, (int, float)) and then else "new"


def stage_table(record: dict, prev: dict | None) -> list[str]:
    """The stage table: wall, CPU, peak RSS so far, and the wall ratio against ``prev``."""
    then = (prev or {}).get("stages") or {}
    lines = [f"{'stage':<12} {'wall s':>8} {'cpu s':>8} {'peak MB':>9} {'vs prev':>8}"]
    for name, row in record["stages"].items():
        cpu, peak = row.get("cpu_s"), row.get("peak_rss_mb")
        lines.append(
            f"{name:<12} {row['wall_s']:>8.1f} {'-' if cpu is None else f'{cpu:.1f}':>8} "
            f"{'-' if peak is None else f'{peak:.0f}':>9} {_ratio(row['wall_s'], (then.get(name) or {}).get('wall_s')):>8}"
        )
    return lines


def ratio_line(record: dict, prev: dict | None) -> str:
    """One line: every stage's wall now, with the ratio now / then against ``prev``."""
    if prev is None:
        head = f"stages ({record['mode']}, no earlier {record['mode']} run to compare):"
    else:
        head = f"stages vs {str(prev.get('commit', '?'))[:9]} ({record['mode']}, now/then):"
    then = (prev or {}).get("stages") or {}
    parts = [
        f"{name} {row['wall_s']:.1f} s ({_ratio(row['wall_s'], (then.get(name) or {}).get('wall_s'))})"
        for name, row in record["stages"].items()
    ]
    total = f"total {record['wall_s']:.1f} s ({_ratio(record['wall_s'], (prev or {}).get('wall_s'))})"
    rss = record.get("peak_rss_gb")
    rss_then = (prev or {}).get("peak_rss_gb")
    peak = f"peak RSS {rss:.2f} GB ({_ratio(rss, rss_then)})" if rss is not None else "peak RSS unknown"
    return " ".join([head, ", ".join(parts + [total, peak])])


def summary_line(record: dict) -> str:
    target = TARGET_WALL_S.get(record["mode"])
    rss = record.get("peak_rss_gb")
    return (
        f"bench_demo: {record['mode']} wall {record['wall_s']:.1f} s"
        + (f" (target {target:.0f} s)" if target else " (no target)")
        + (f", peak RSS {rss:.2f} GB" if rss is not None else ", peak RSS unknown")
        + f" (target {TARGET_RSS_GB:g} GB), results {'ok' if record['results']['ok'] else 'NOT ok'}"
    )


def make_record(
    summary: dict, *, mode: str, wall_s: float, cpu_s: float | None, peak_rss_kb: int | None, rss_source: str, **extra
) -> dict:
    """The JSONL record of one run (``extra``: commit, machine, load, command, ...)."""
    return {
        "mode": mode,
        "wall_s": round(wall_s, 2),
        "cpu_s": None if cpu_s is None else round(cpu_s, 2),
        "peak_rss_gb": None if peak_rss_kb is None else round(peak_rss_kb / 2**20, 3),
        "peak_rss_source": rss_source,
        "demo_total_s": summary.get("total_s"),
        "stages": stages_of(summary),
        "results": results_of(summary),
        **extra,
    }


def _nproc() -> int | None:
    """CPUs this process may run on (``nproc``: the affinity mask, not the box's count)."""
    try:
        return len(os.sched_getaffinity(0))
    except AttributeError:  # not Linux
        return os.cpu_count()


def _time_v() -> Path | None:
    """``/usr/bin/time`` (GNU time), installed from Debian's ``time`` package when missing
    and apt-get is at hand (root); None where neither works (peak RSS then from rusage)."""
    if TIME_V.is_file():
        return TIME_V
    if shutil.which("apt-get") and hasattr(os, "geteuid") and os.geteuid() == 0:
        print("bench_demo: /usr/bin/time missing; apt-get install time", flush=True)
        subprocess.run(["apt-get", "install", "-y", "-qq", "time"], check=False, capture_output=True)
    return TIME_V if TIME_V.is_file() else None


def main() -> None:
    ap = parser(__doc__)
    ap.add_argument("--quick", action="store_true", help="run `mfdesign demo --quick`")
    ap.add_argument("--warm", type=Path, default=None, metavar="DIR", help="reuse this MFDESIGN_CACHE_DIR (a warm run)")
    ap.add_argument(
        "--keep-cache",
        type=Path,
        default=None,
        metavar="DIR",
        help="cold run: use this new (empty or missing) folder as the cache and keep it for a --warm run",
    )
    ap.add_argument(
        "--demo-out", type=Path, default=None, metavar="DIR", help="the demo's output (default: a temp folder)"
    )
    ap.add_argument("--nice", type=int, default=0, metavar="N", help="run the demo under `nice -n N` (0: not)")
    ap.add_argument(
        "--solve-planes",
        action="store_true",
        help="solve the bundled membranes' planes too (MFDESIGN_SHIPPED_PLANES=0): the cold demo before they shipped",
    )
    ap.add_argument(
        "--trace-kernels",
        action="store_true",
        help="trace every kernel (MFDESIGN_SHIPPED_KERNELS=0): the cold demo before the kernels shipped",
    )
    args = ap.parse_args()
    if args.warm is not None and not args.warm.is_dir():
        ap.error(f"--warm {args.warm}: no such cache folder")
    if args.keep_cache is not None and args.keep_cache.exists() and any(args.keep_cache.iterdir()):
        ap.error(f"--keep-cache {args.keep_cache} is not empty: a cold run needs an empty cache")
    mode = mode_of(args.quick, args.warm is not None)

    tmp = Path(tempfile.mkdtemp(prefix="bench_demo_"))
    cache = args.warm or args.keep_cache or tmp / "cache"
    cache.mkdir(parents=True, exist_ok=True)
    demo_out = args.demo_out or tmp / "demo"
    time_file = tmp / "time_v.txt"
    env = dict(os.environ, MFDESIGN_CACHE_DIR=str(cache))
    if args.solve_planes:
        env["MFDESIGN_SHIPPED_PLANES"] = "0"
    shipped = env.get("MFDESIGN_SHIPPED_PLANES", "1").strip() != "0"
    if args.trace_kernels:
        env["MFDESIGN_SHIPPED_KERNELS"] = "0"
    kernels_shipped = env.get("MFDESIGN_SHIPPED_KERNELS", "1").strip() != "0"
    demo = [sys.executable, "-m", "mfdesign.cli", "demo", "--out", str(demo_out)] + (["--quick"] if args.quick else [])
    time_v = _time_v()
    cmd = ([str(time_v), "-v", "-o", str(time_file)] if time_v else []) + demo
    if args.nice:
        cmd = ["nice", "-n", str(args.nice)] + cmd

    # the commit the demo runs: taken before it starts (the tree may move on meanwhile)
    commit, dirty = git_state()
    probe = speed_probe()  # before the demo, on the machine it meets
    load_before = load()
    before = resource.getrusage(resource.RUSAGE_CHILDREN)
    t0 = time.perf_counter()
    log_path = tmp / "demo.log"
    planes = "shipped planes read" if shipped else "shipped planes off: every plane solved"
    planes += ", shipped kernels read" if kernels_shipped else ", shipped kernels off: every kernel traced"
    print(f"bench_demo: {mode} run ({planes}), cache {cache}, log {log_path}", flush=True)
    with open(log_path, "w") as log_file:
        proc = subprocess.run(cmd, env=env, stdout=log_file, stderr=subprocess.STDOUT)
    wall = time.perf_counter() - t0
    after = resource.getrusage(resource.RUSAGE_CHILDREN)
    load_after = load()

    tv = parse_time_v(time_file.read_text()) if time_v and time_file.is_file() else {}
    if "max_rss_kb" in tv:
        peak_kb, source = tv["max_rss_kb"], "/usr/bin/time -v"
        cpu = tv.get("user_s", 0.0) + tv.get("sys_s", 0.0)
    else:  # ru_maxrss of the largest child waited for: the demo (kB on Linux)
        peak_kb, source = int(after.ru_maxrss), "getrusage(RUSAGE_CHILDREN)"
        cpu = (after.ru_utime - before.ru_utime) + (after.ru_stime - before.ru_stime)
    summary_path = demo_out / "summary.json"
    summary = json.loads(summary_path.read_text()) if proc.returncode == 0 and summary_path.is_file() else {}
    if proc.returncode != 0:
        print("".join(log_path.read_text().splitlines(keepends=True)[-40:]), flush=True)
        print(f"bench_demo: the demo exited with {proc.returncode} (log {log_path})", flush=True)

    record = make_record(
        summary,
        mode=mode,
        wall_s=wall,
        cpu_s=cpu,
        peak_rss_kb=peak_kb,
        rss_source=source,
        returncode=proc.returncode,
        time_v=tv or None,
        commit=commit,
        dirty=dirty,
        when=datetime.datetime.now(datetime.timezone.utc).isoformat(timespec="seconds"),
        command=command(__file__, args),
        demo_command=" ".join(demo[2:]),
        nice=args.nice,
        # the bundled membranes' planes read from the package (mfdesign/data/files/planes.npz,
        # since session 38) rather than solved; records before it solved them (absent: False)
        shipped_planes=shipped,
        # the kernels' traces read from the package (mfdesign/data/files/kernels.npz, since
        # session 40); "kernels": the demo's count of kernels by origin
        shipped_kernels=kernels_shipped,
        kernels=summary.get("kernels"),
        machine={
            "cpus": os.cpu_count(),
            "nproc": _nproc(),
            "platform": sys.platform,
            "accelerators": accelerators(),
            "cpu": cpu_info(),
            "jax_platforms": os.environ.get("JAX_PLATFORMS", ""),
            "xla_flags": os.environ.get("XLA_FLAGS", ""),  # they change what XLA compiles, and how fast
        },
        load_average_before=load_before,
        load_average_after=load_after,
        speed_probe=probe,
        cache_dir=str(cache),
        demo_out=str(demo_out),
    )
    path = Path(args.out) / JSONL
    prev = previous(read_jsonl(path), mode)
    append_jsonl(path, record)
    print("\n".join(stage_table(record, prev)))
    print(f"load average before {load_before}, after {load_after}; nproc {_nproc()}; written {path}")
    if record.get("kernels"):
        print("kernels: " + ", ".join(f"{n} {origin}" for origin, n in record["kernels"].items()))
    print(probe_line(record, prev))
    print(ratio_line(record, prev))
    print(summary_line(record))
    if proc.returncode != 0:
        sys.exit(proc.returncode)


if __name__ == "__main__":
    main()
