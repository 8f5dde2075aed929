"""XLA's CPU compiler options for the stored programs of a cold quick demo: compile and run time (issue 40).

Runs ``mfdesign demo --quick`` in this process on an empty ``MFDESIGN_CACHE_DIR`` (a
temporary folder) and records, for every stored program (the solver's kernels and the
``stored_jit`` ones, ``mfdesign.physics._traces``), its kind, the arguments of its first
call and how many times the demo called it. Then, with the persistent compilation cache
off, compiles each program under every option set below and runs it on its recorded
arguments (best of three after a first call): seconds to compile, seconds a call, and
their sum at the demo's call count, and the largest difference of its output from the
default set's (rounding: XLA fuses and orders reductions differently). Prints a table, the totals of each option set, of
this commit's choice (``_traces.OPTIONS`` by kind) and of the best set per program, and
writes ``out/bench_compile_options.json``.

A program's call count and arguments are the quick demo's: a campaign's round calls the
solver's kernels and the ensembles' forward passes far more often, so a set that saves
compile time at a slower call is judged at their counts there too (``_traces.OPTIONS``).

    python experiments/bench_compile_options.py [--repeat 1]
"""

from __future__ import annotations

import collections
import os
import sys
import tempfile
import time
from pathlib import Path

from _common import git_state, machine, parser, write_json

# name -> XLA CPU options (jax.jit's compiler_options)
SETS: dict[str, dict] = {
    "default": {},
    "no emitters": {"xla_cpu_use_fusion_emitters": False},
    "no emitters, O1": {"xla_cpu_use_fusion_emitters": False, "xla_backend_optimization_level": 1},
    "no emitters, O0": {"xla_cpu_use_fusion_emitters": False, "xla_backend_optimization_level": 0},
}


def _record(traces) -> tuple[dict, collections.Counter]:
    """Wrap the store's program makers: each program's first concrete arguments and calls."""
    seen: dict = {}  # name -> (kind, fn, args)
    calls: collections.Counter = collections.Counter()
    compiled_as, lazy_program, read = traces._compiled_as, traces._lazy_program, traces._read
    last = {"name": "?"}  # the stored file read last: the program made next is its

    def _read(path):
        last["name"] = path.name.split(".")[0]
        return read(path)

    def recording(name, kind, fn, program):
        def call(*xs):
            out = program(*xs)
            calls[name] += 1
            seen.setdefault(name, (kind, fn, xs))
            return out

        return call

    def _compiled_as(kind, fn, args):
        program = compiled_as(kind, fn, args)
        if kind != "kernel":  # a plan's kernel compiled ahead into the compilation cache
            return program
        return recording(last["name"], kind, fn, program)

    def _lazy_program(kind, fn):
        return recording(last["name"], kind, fn, lazy_program(kind, fn))

    traces._compiled_as, traces._lazy_program, traces._read = _compiled_as, _lazy_program, _read
    return seen, calls


def _time(fn, args, options: dict, repeat: int) -> tuple[float, float, list]:
    """(seconds to compile, seconds a call: best of ``repeat`` after a first call, the
    call's output leaves as NumPy arrays)."""
    import jax
    import numpy as np

    jax.clear_caches()  # jit's in-memory caches: the demo compiled this program already
    t = time.perf_counter()
    program = jax.jit(fn, compiler_options=options or None).lower(*args).compile()
    compile_s = time.perf_counter() - t
    out = jax.block_until_ready(program(*args))
    best = float("inf")
    for _ in range(repeat):
        t = time.perf_counter()
        jax.block_until_ready(program(*args))
        best = min(best, time.perf_counter() - t)
    return compile_s, best, [np.asarray(x) for x in jax.tree.leaves(out)]


def _max_diff(a: list, b: list) -> float:
    """Largest absolute difference of two outputs' floating leaves (NaNs where both are NaN
    count as equal; a NaN against a number as inf)."""
    import numpy as np

    worst = 0.0
    for x, y in zip(a, b):
        if x.dtype.kind != "f" or x.size == 0:
            worst = max(worst, 0.0 if np.array_equal(x, y) else float("inf"))
            continue
        both = np.isnan(x) & np.isnan(y)
        d = np.where(both, 0.0, np.abs(x - y))
        worst = max(worst, float(np.nanmax(np.where(np.isnan(d), np.inf, d))))
    return worst


def main() -> None:
    ap = parser(__doc__)
    ap.add_argument("--repeat", type=int, default=3, help="timed calls per program and set (best kept)")
    args = ap.parse_args()
    command = " ".join(["python", "experiments/bench_compile_options.py", *sys.argv[1:]])
    commit, dirty = git_state()
    load_before = os.getloadavg()

    import jax

    work = Path(tempfile.mkdtemp(prefix="bench_options_"))
    os.environ["MFDESIGN_CACHE_DIR"] = str(work / "cache")
    from mfdesign.cli import app
    from mfdesign.physics import _traces

    seen, calls = _record(_traces)
    sys.argv = ["mfdesign", "demo", "--out", str(work / "demo"), "--quick"]
    t0 = time.perf_counter()
    try:
        app()
    except SystemExit as stop:
        if stop.code not in (0, None):
            raise
    demo_s = time.perf_counter() - t0
    from jax._src import compilation_cache

    # every compile below is a compile: the persistent cache decides once whether it is on
    # (reset_cache makes it look again), and jit's in-memory caches are cleared at each
    jax.config.update("jax_enable_compilation_cache", False)
    compilation_cache.reset_cache()

    rows = []
    for name, (kind, fn, xs) in seen.items():
        row = {"program": name, "kind": kind, "calls": calls[name], "sets": {}}
        reference = None
        for label, options in SETS.items():
            compile_s, call_s, out = _time(fn, xs, options, args.repeat)
            reference = out if reference is None else reference
            row["sets"][label] = {
                "compile_s": round(compile_s, 3),
                "call_s": round(call_s, 5),
                "total_s": round(compile_s + calls[name] * call_s, 3),
                "max_abs_diff_vs_default": _max_diff(out, reference),
            }
        mine = next(k for k, v in SETS.items() if v == (_traces.OPTIONS[kind] or {}))
        row["this_commit"] = mine
        row["best"] = min(row["sets"], key=lambda k: row["sets"][k]["total_s"])
        rows.append(row)
        cells = "  ".join(f"{v['compile_s']:5.2f}+{row['calls']}x{v['call_s']:.3f}" for v in row["sets"].values())
        print(f"{row['program'][:22]:22s} {kind:8s} {cells}  this: {mine}", flush=True)

    def total(pick) -> dict:
        out = {"compile_s": 0.0, "total_s": 0.0}
        for row in rows:
            cell = row["sets"][pick(row)]
            out["compile_s"] += cell["compile_s"]
            out["total_s"] += cell["total_s"]
        return {k: round(v, 1) for k, v in out.items()}

    totals = {label: total(lambda r, label=label: label) for label in SETS}
    totals["this commit"] = total(lambda r: r["this_commit"])
    totals["best per program"] = total(lambda r: r["best"])
    base = totals["default"]["total_s"]
    for label, t in totals.items():
        print(
            f"{label:18s} compile {t['compile_s']:6.1f} s, with the calls {t['total_s']:6.1f} s (x{t['total_s'] / base:.2f} of default)"
        )
    write_json(
        args.out / "bench_compile_options.json",
        {
            "command": command,
            "commit": commit,
            "dirty": dirty,
            "machine": machine(),
            "load_before": load_before,
            "demo_s": round(demo_s, 1),
            "sets": SETS,
            "programs": rows,
            "totals": totals,
        },
    )


if __name__ == "__main__":
    main()
