"""Which lines of mfdesign make a cold demo compile: every XLA compilation and every trace
attributed to the mfdesign line that asked for it (issue 40).

``profile_compile.py`` says which jitted functions compile and for how long; a program
named ``jit(multiply)`` or ``jit(_where)`` there is a JAX operation run outside any jit,
and its name does not say whose. This runs ``run_demo`` in this process with JAX's
compile log on and a logging handler that, at each "Finished XLA compilation" (and
"Finished tracing") record, walks the Python stack to the innermost frame in mfdesign
(``--outer``: the innermost one outside the force models, effects and design helpers,
i.e. the caller that ran them eagerly). Sums seconds and counts per line; writes
``out/profile_callers.json``.

    python experiments/profile_callers.py --planes ~/.cache/mfdesign/planes [--full] [--outer]

``--planes DIR``: the new cache folder starts with DIR's simulator planes (the run then
pays for compilation and computation, not for planes). Session 36 found this way that
the exact force model's eager calls were 642 of a quick demo's 1,228 compilations.
"""

from __future__ import annotations

import collections
import logging
import os
import re
import shutil
import sys
import tempfile
import time
import traceback
from pathlib import Path

from _common import git_state, load, machine, parser, write_json

_COMPILE = re.compile(r"Finished XLA compilation of (\S+).*? in ([\d.e+-]+) sec")
_TRACE = re.compile(r"Finished tracing (?:\+ transforming )?(\S+) for \S+ in ([\d.e+-]+) sec")
# modules a caller runs eagerly through (with --outer the line is the caller's, not theirs)
INNER = (
    "mfdesign/models/exact.py",
    "mfdesign/models/force.py",
    "mfdesign/models/hierarchical.py",
    "mfdesign/physics/effects/",
    "mfdesign/design.py",
    "mfdesign/_padding.py",
    "mfdesign/physics/params.py",
)


def site_of(frames, outer: bool = False) -> str:
    """``file:line function`` of the innermost mfdesign frame of ``frames`` (oldest first,
    as ``traceback.extract_stack`` gives them), skipping the program store's wrapper
    (``physics/_traces.py``) and, with ``outer``, the :data:`INNER` modules; ``"?"`` if none."""
    for fr in reversed(frames):
        name = fr.filename.replace(os.sep, "/")
        if "/mfdesign/" not in name or "/physics/_traces.py" in name:
            continue
        if outer and any(x in name for x in INNER):
            continue
        return f"{name.split('/mfdesign/')[-1]}:{fr.lineno} {fr.name}"
    return "?"


class _Sites(logging.Handler):
    def __init__(self, outer: bool) -> None:
        super().__init__(logging.DEBUG)
        self.outer = outer
        self.compiled: dict = collections.defaultdict(lambda: [0, 0.0, collections.Counter()])
        self.traced: dict = collections.defaultdict(lambda: [0, 0.0])

    def emit(self, record) -> None:
        msg = record.getMessage()
        c, t = _COMPILE.search(msg), _TRACE.search(msg)
        if not (c or t):
            return
        site = site_of(traceback.extract_stack(), self.outer)
        if c:
            e = self.compiled[site]
            e[0], e[1] = e[0] + 1, e[1] + float(c.group(2))
            e[2][c.group(1)] += 1
        else:
            e = self.traced[site]
            e[0], e[1] = e[0] + 1, e[1] + float(t.group(2))


def main(argv=None) -> dict:
    ap = parser(__doc__)
    ap.add_argument("--planes", type=Path, default=None, help="copy this folder's simulator planes into the new cache")
    ap.add_argument("--full", action="store_true", help="the full demo, not --quick")
    ap.add_argument("--outer", action="store_true", help="attribute to the caller of the force models and effects")
    args = ap.parse_args(argv)
    commit, dirty = git_state()
    work = Path(tempfile.mkdtemp(prefix="mfdesign-callers-"))
    cache = work / "cache"
    cache.mkdir()
    if args.planes is not None:
        shutil.copytree(args.planes, cache / "planes")
    # before JAX is imported: an empty cache of its own, CPU
    os.environ |= {"MFDESIGN_CACHE_DIR": str(cache), "JAX_PLATFORMS": "cpu"}
    from mfdesign._cache import enable_compilation_cache

    enable_compilation_cache()  # as the CLI: the persistent cache and the program store on
    import jax

    jax.config.update("jax_log_compiles", True)
    sites = _Sites(args.outer)
    for name in ("jax._src.dispatch", "jax._src.interpreters.pxla", "jax._src.compiler"):
        lg = logging.getLogger(name)
        lg.addHandler(sites)
        lg.setLevel(logging.DEBUG)
        lg.propagate = False  # the handler counts them; nothing printed
    from mfdesign.workflows.demo import DemoSettings, run_demo

    before = load()
    t0 = time.perf_counter()
    run_demo(work / "demo", DemoSettings() if args.full else DemoSettings.quick(), progress=False)
    wall = time.perf_counter() - t0
    rows = sorted(sites.compiled.items(), key=lambda kv: -kv[1][1])
    result = {
        "commit": commit,
        "dirty": dirty,
        "machine": machine(),
        "command": " ".join([Path(sys.argv[0]).name, *(argv if argv is not None else sys.argv[1:])]),
        "demo": "full" if args.full else "quick",
        "planes_preloaded": str(args.planes) if args.planes else None,
        "outer": args.outer,
        "load_before": before,
        "load_after": load(),
        "wall_s": round(wall, 1),
        "compile_s_total": round(sum(v[1] for v in sites.compiled.values()), 1),
        "compilations": int(sum(v[0] for v in sites.compiled.values())),
        "trace_s_total": round(sum(v[1] for v in sites.traced.values()), 1),
        "sites": [
            {"site": k, "compilations": v[0], "seconds": round(v[1], 2), "programs": dict(v[2].most_common(5))}
            for k, v in rows[:60]
        ],
        "traced": [
            {"site": k, "traces": v[0], "seconds": round(v[1], 2)}
            for k, v in sorted(sites.traced.items(), key=lambda kv: -kv[1][1])[:30]
        ],
    }
    write_json(args.out / "profile_callers.json", result)
    print(
        f"profile_callers: {result['compilations']} compilations, {result['compile_s_total']} s of XLA, "
        f"{result['trace_s_total']} s of tracing, demo {result['wall_s']} s"
    )
    for r in result["sites"][:15]:
        print(f"  {r['seconds']:7.2f} s {r['compilations']:5d} x  {r['site']}")
    shutil.rmtree(work, ignore_errors=True)
    return result


if __name__ == "__main__":
    main()
