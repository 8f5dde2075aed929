"""Which line of mfdesign each XLA compilation of a cold demo comes from, and on which thread (issue 40).

Runs ``mfdesign demo --quick`` (``--full``: the full demo) in this process, on an empty
``MFDESIGN_CACHE_DIR`` (a temporary folder), with JAX's compile log on, and records every
"Finished tracing / jaxpr to MLIR / XLA compilation" message with the innermost mfdesign
frame of the thread that logged it (``?``: none, the thread that compiles a plan's kernels
ahead, ``physics._traces.compile_ahead``) and the time. Prints the seconds and compilations
per call site and per thread, the ahead thread's kernels with the time each was ready,
and writes ``out/profile_compile_sites.json``.

Why beside ``profile_compile.py`` (which sums the compile log per stage in a separate
process): a program's seconds here are those its caller waited, so a small program that
waited behind a large one compiling ahead shows where it was called (session 43: in a cold
quick demo the main thread's 514 compilations took 74 s, its ``sigmoid`` programs 1.2 s
each, and the diagnosis' BIC likelihood 11.0 s, against 1.9 s alone).

    python experiments/profile_compile_sites.py [--full] [--top 40]
"""

from __future__ import annotations

import collections
import logging
import re
import sys
import tempfile
import threading
import time
import traceback
from pathlib import Path

from _common import git_state, machine, parser, write_json

_MESSAGES = (
    ("compile", re.compile(r"Finished XLA compilation of (\S+) in ([\d.e+-]+) sec")),
    ("lower", re.compile(r"Finished jaxpr to MLIR module conversion (\S+) in ([\d.e+-]+) sec")),
    ("trace", re.compile(r"Finished tracing (\S+) for jit in ([\d.e+-]+) sec")),
)


def _site() -> str:
    """The innermost mfdesign frame of this thread (the kernel store's own frames aside)."""
    own = [
        f
        for f in traceback.extract_stack()[:-2]
        if "/mfdesign/" in f.filename and not f.filename.endswith("physics/_traces.py")
    ]
    return f"{own[-1].filename.split('/mfdesign/')[-1]}:{own[-1].lineno} {own[-1].name}" if own else "?"


class _Recorder(logging.Handler):
    def __init__(self) -> None:
        super().__init__(logging.DEBUG)
        self.records: list[tuple[int, str, str, float, str, float]] = []

    def emit(self, record: logging.LogRecord) -> None:
        message = record.getMessage()
        for kind, pattern in _MESSAGES:
            m = pattern.search(message)
            if m:
                self.records.append((threading.get_ident(), kind, m.group(1), float(m.group(2)), _site(), time.time()))


def main() -> None:
    ap = parser(__doc__)
    ap.add_argument("--full", action="store_true", help="the full demo (default: --quick)")
    ap.add_argument("--top", type=int, default=40, help="call sites printed")
    args = ap.parse_args()
    command = " ".join(["python", "experiments/profile_compile_sites.py", *sys.argv[1:]])
    commit, dirty = git_state()  # before the run: it takes minutes

    import os

    import jax

    work = Path(tempfile.mkdtemp(prefix="profile_sites_"))
    os.environ["MFDESIGN_CACHE_DIR"] = str(work / "cache")
    jax.config.update("jax_log_compiles", True)
    recorder = _Recorder()
    logging.getLogger("jax").addHandler(recorder)
    from mfdesign.cli import app

    argv = ["mfdesign", "demo", "--out", str(work / "demo")] + ([] if args.full else ["--quick"])
    sys.argv, t0, c0 = argv, time.perf_counter(), time.process_time()
    try:
        app()
    except SystemExit as stop:
        if stop.code not in (0, None):
            raise
    wall, cpu = time.perf_counter() - t0, time.process_time() - c0

    records = recorder.records
    counts = collections.Counter(r[0] for r in records if r[1] == "compile")
    main_thread = threading.main_thread().ident
    threads: dict = collections.defaultdict(lambda: collections.defaultdict(float))
    sites: dict = collections.defaultdict(lambda: {"compilations": 0, "s": 0.0})
    for tid, kind, name, secs, site, _ in records:
        who = "main" if tid == main_thread else "ahead" if site == "?" else f"thread {tid}"
        threads[who][kind] += secs
        entry = sites[f"{who} | {name} | {site}"]
        entry["compilations"] += kind == "compile"
        entry["s"] += secs
    start = min((r[5] for r in records), default=t0)
    ahead = [
        {"ready_s": round(r[5] - start, 1), "compile_s": round(r[3], 2), "program": r[2]}
        for r in records
        if r[0] != main_thread and r[1] == "compile" and r[4] == "?" and r[3] > 0.3
    ]
    ranked = sorted(sites.items(), key=lambda kv: -kv[1]["s"])
    print(
        f"demo {'full' if args.full else '--quick'}: {wall:.1f} s wall, {cpu:.1f} CPU-s; {sum(counts.values())} compilations"
    )
    for who, kinds in threads.items():
        print(f"  {who}: " + ", ".join(f"{k} {v:.1f} s" for k, v in kinds.items()))
    for key, entry in ranked[: args.top]:
        print(f"{entry['s']:7.2f} s {entry['compilations']:4d} x  {key}")
    write_json(
        args.out / "profile_compile_sites.json",
        {
            "command": command,
            "demo": " ".join(argv[1:]),
            "commit": commit,
            "dirty": dirty,
            "machine": machine(),
            "wall_s": wall,
            "cpu_s": cpu,
            "compilations": sum(counts.values()),
            "threads": {who: dict(kinds) for who, kinds in threads.items()},
            "ahead": ahead,
            "sites": [{"site": key, **entry} for key, entry in ranked],
        },
    )


if __name__ == "__main__":
    main()
