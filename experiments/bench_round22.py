"""One round of a 22-membrane campaign, cold, timed per command (issue 40, item 4).

Target: one round (diagnose, calibrate, fit and propose) on the paper's 22 membranes
within 15 minutes on the 2-core CPU, starting from empty caches.

The membranes: the paper's designs as far as the shared SPA_Design files hold them, the
seven mass-lift membranes (``load_mass_lift``) first, then the 18 designs of the authors'
simulator planes (``load_sim_planes``), deduplicated; fewer than ``--membranes`` and the
bundled dataset's designs fill up. The JSON names the source of every key. Their
characterisation is made on the virtual rig (the simulator with the bundled card's hidden
effect and noise, ``Protocol(sample_hz=--sample-hz, trials_per_height=1)``, force
characterisation only) BEFORE the timed round, in its own process, and kept as Parquet
(``--data``: reuse a file made earlier for the same keys).

The timed round, cold: a new temporary ``MFDESIGN_CACHE_DIR`` (empty plane and JAX
compilation caches), each step a fresh process under ``/usr/bin/time -v`` (wall, CPU,
peak RSS):

1. ``create``: ``Campaign.create(D, data, Settings(...))`` (``python -c``: ``mfdesign
   create`` takes a few settings only, and the round runs the demo's);
2. ``diagnose``: ``Campaign.diagnose()`` (``mfdesign fit D`` does not diagnose; what it
   finds joins the effects in force);
3. ``fit``: ``mfdesign fit D`` (calibration with emcee + the discrepancy ensemble);
4. ``ask``: ``mfdesign ask D --q 2`` (propose).

The campaign's settings are the ones ``mfdesign demo`` leaves in its campaign
(``mcmc_steps`` 2000 at most, 1500 rows, 8 x 2000-step members, 2 effects checked in
full; ``restarts`` 64, ``refine`` 4, ``opt_steps`` 10: the campaign defaults 1000 / 32 /
20 held an exact-physics ask at 7.6 GB and over 14 minutes), except the walkers:
automatic (``max(32, 2 dim + 2)``), as the demo's 32 are fewer than emcee needs with 22
thickness latents. ``--quick``: smoke-test sizes (not the benchmark).

``--timeout S`` bounds the whole round: the running command is killed when it is spent,
and the JSON says which one and how long it ran. The JSON is rewritten after every
command, so a killed run keeps the figures of the finished ones.

    python experiments/bench_round22.py                       # the full round
    python experiments/bench_round22.py --membranes 3 --quick --out /tmp/smoke

Writes ``bench_round22.json`` into ``--out``; prints a table and, last,
``bench_round22: cold round of N membranes T s (target 900 s), peak RSS X GB``.
"""

from __future__ import annotations

import datetime
import json
import os
import shutil
import signal
import subprocess
import sys
import tempfile
import time
from pathlib import Path

from _common import PLANE_CACHE, command, git_state, load, parser, write_json
from bench_demo import parse_time_v

NAME = "bench_round22"
TARGET_S = 900.0
TIME_V = Path("/usr/bin/time")

# What `mfdesign demo` leaves in its campaign (mfdesign/workflows/demo.py, _leave_campaign).
FULL = dict(mcmc_steps=2000, walkers=0, max_rows=1500, members=8, delta_steps=2000, check_top=2)
FULL |= dict(restarts=64, refine=4, opt_steps=10)
QUICK = dict(mcmc_steps=60, walkers=0, max_rows=200, members=2, delta_steps=50, check_top=1, check_pairs=0)
QUICK |= dict(diagnose_rounds=1, restarts=8, refine=2, opt_steps=2, sim_heights=4, sim_pressures=4)

CREATE = (
    "import json, sys; from mfdesign._x64 import enable_x64; enable_x64(); "
    "from mfdesign.campaign import Campaign, Settings; "
    "s = Settings.from_json(json.load(open(sys.argv[3]))); "
    "Campaign.create(sys.argv[1], data=sys.argv[2], settings=s, call='bench_round22: Campaign.create'); "
    "print('created', sys.argv[1])"
)
DIAGNOSE = (
    "import sys; from mfdesign._x64 import enable_x64; enable_x64(); "
    "from mfdesign._cache import enable_compilation_cache; enable_compilation_cache(); "
    "from mfdesign.campaign import Campaign; "
    "r = Campaign.open(sys.argv[1]).diagnose(progress=True, call='bench_round22: Campaign.diagnose'); "
    "print('diagnosis found', list(r.found))"
)


def membranes(n: int) -> tuple[list[str], dict]:
    """``n`` design keys: mass-lift, then the authors' simulator planes, then bundled."""
    from mfdesign.data.shipped import bundled_path
    from mfdesign.data.spa_design import load_mass_lift, load_sim_planes
    from mfdesign.data.store import read_parquet
    from mfdesign.design import Membrane

    lists = {
        "mass_lift": [Membrane.from_key(k).key() for k in load_mass_lift().design_keys],
        "sim_planes": [p.design.key() for p in load_sim_planes()],
        "bundled": [Membrane.from_key(k).key() for k in read_parquet(bundled_path()).design_keys],
    }
    keys: list[str] = []
    origin: dict[str, list[str]] = {name: [] for name in lists}
    for name, found in lists.items():
        for k in found:
            if len(keys) < n and k not in keys:
                keys.append(k)
                origin[name].append(k)
    paper = list(dict.fromkeys(lists["mass_lift"] + lists["sim_planes"]))
    return keys, {
        "paper_designs_available": len(paper),
        "from": {name: {"count": len(v), "keys": v} for name, v in origin.items()},
        "paper_designs_left_out": [k for k in paper if k not in keys],
    }


def make_data(path: Path, keys: list[str], sample_hz: float, seed: int) -> None:
    """The virtual rig's force characterisation of ``keys`` into ``path`` (Parquet)."""
    from mfdesign.data.shipped import bundled_card_path
    from mfdesign.data.store import write_parquet
    from mfdesign.design import Membrane
    from mfdesign.physics.params import SimParams
    from mfdesign.rig.virtual import Protocol, VirtualRig

    hidden = json.loads(bundled_card_path().read_text())["hidden_effect"]
    rig = VirtualRig(
        effects=[hidden["name"]],
        theta=hidden["theta"],
        seed=seed,
        protocol=Protocol(sample_hz=sample_hz, trials_per_height=1),
        base_params=SimParams(),
        cache_dir=PLANE_CACHE,
    )
    table = rig.run([Membrane.from_key(k) for k in keys], lift=False, progress=True)
    path.parent.mkdir(parents=True, exist_ok=True)
    write_parquet(table, path)
    print(f"{NAME}: made {len(table)} rows of {len(table.design_keys)} membranes into {path}", flush=True)


def run_step(name: str, argv: list[str], env: dict, tmp: Path, timeout_s: float) -> dict:
    """One command under ``/usr/bin/time -v`` in its own process group; killed (the whole
    group) when ``timeout_s`` runs out."""
    time_file = tmp / f"time_{name}.txt"
    log_path = tmp / f"{name}.log"
    cmd = ([str(TIME_V), "-v", "-o", str(time_file)] if TIME_V.is_file() else []) + argv
    row: dict = {"command": " ".join(argv[1:] if argv[0] == sys.executable else argv), "log": str(log_path)}
    row["load_average_before"] = load()
    t0 = time.perf_counter()
    print(f"{NAME}: {name} ... (log {log_path})", flush=True)
    with open(log_path, "w") as log_file:
        proc = subprocess.Popen(cmd, env=env, stdout=log_file, stderr=subprocess.STDOUT, start_new_session=True)
        try:
            rc = proc.wait(timeout=max(timeout_s, 1.0))
            row["timed_out"] = False
        except subprocess.TimeoutExpired:
            os.killpg(proc.pid, signal.SIGKILL)
            rc = proc.wait()
            row["timed_out"] = True
    row["wall_s"] = round(time.perf_counter() - t0, 2)
    row["returncode"] = rc
    row["load_average_after"] = load()
    tv = parse_time_v(time_file.read_text()) if time_file.is_file() else {}
    if "user_s" in tv:
        row["cpu_s"] = round(tv["user_s"] + tv.get("sys_s", 0.0), 2)
    if "max_rss_kb" in tv:
        row["peak_rss_gb"] = round(tv["max_rss_kb"] / 2**20, 3)
    tail = log_path.read_text(errors="replace").splitlines()
    row["last_lines"] = [line[-300:] for line in tail[-4:]]
    return row


def chain_of(camp: Path) -> dict | None:
    """The round's emcee chain as its posterior records it (the last round's
    ``model/posterior.json``): a round within the time target with a chain that has not
    converged is not the round a lab needs, so the JSON and the last line say which."""
    rounds = sorted((camp / "rounds").glob("round-*"))
    post = rounds[-1] / "model" / "posterior.json" if rounds else None
    if post is None or not post.is_file():
        return None
    conv = json.loads(post.read_text()).get("convergence") or {}
    keep = ("converged", "steps_over_tau", "tau_max", "acceptance", "problems")
    return {k: conv[k] for k in keep if k in conv}


def table(steps: dict) -> list[str]:
    lines = [f"{'step':<10} {'wall s':>8} {'cpu s':>8} {'peak GB':>8}  status"]
    for name, r in steps.items():
        cpu, rss = r.get("cpu_s"), r.get("peak_rss_gb")
        status = "timed out" if r.get("timed_out") else "ok" if r.get("returncode") == 0 else f"exit {r['returncode']}"
        lines.append(
            f"{name:<10} {r['wall_s']:>8.1f} {'-' if cpu is None else f'{cpu:.1f}':>8} "
            f"{'-' if rss is None else f'{rss:.2f}':>8}  {status}"
        )
    return lines


def main() -> None:
    ap = parser(__doc__)
    ap.add_argument("--membranes", type=int, default=22, metavar="N", help="membranes in the campaign")
    ap.add_argument("--mcmc-steps", type=int, default=None, metavar="N", help="most emcee steps (default: demo's)")
    ap.add_argument("--quick", action="store_true", help="smoke-test settings (not the benchmark)")
    ap.add_argument("--q", type=int, default=2, help="membranes the ask proposes")
    ap.add_argument("--sample-hz", type=float, default=1.0, help="the virtual rig's sampling rate [Hz]")
    ap.add_argument("--seed", type=int, default=7, help="the virtual rig's seed")
    ap.add_argument("--timeout", type=float, default=1800.0, metavar="S", help="kill the round after S seconds")
    ap.add_argument("--data", type=Path, default=None, metavar="FILE", help="the made data (reused if present)")
    ap.add_argument("--make-data", type=Path, default=None, help=__import__("argparse").SUPPRESS)
    args = ap.parse_args()

    from mfdesign.data.spa_design import SharedDataMissing

    try:
        keys, origin = membranes(args.membranes)
    except SharedDataMissing as err:
        print(f"{NAME}: the shared SPA_Design data are missing ({err})", file=sys.stderr)
        sys.exit(2)
    if args.make_data is not None:  # the data-making child process
        make_data(args.make_data, keys, args.sample_hz, args.seed)
        return

    commit, dirty = git_state()
    tmp = Path(tempfile.mkdtemp(prefix=f"{NAME}_"))
    out_json = Path(args.out) / f"{NAME}.json"
    record: dict = {
        "commit": commit,
        "dirty": dirty,
        "when": datetime.datetime.now(datetime.timezone.utc).isoformat(timespec="seconds"),
        "command": command(__file__, args),
        "machine": {"cpus": os.cpu_count(), "nproc": len(os.sched_getaffinity(0)), "platform": sys.platform},
        "target_s": TARGET_S,
        "membranes": len(keys),
        "design_keys": keys,
        "design_sources": origin,
        "tmp": str(tmp),
    }

    # -- the data, outside the timed round
    data = args.data or tmp / "rig_data.parquet"
    t0 = time.perf_counter()
    if data.is_file():
        from mfdesign.data.store import read_parquet

        made = read_parquet(data)
        if sorted(made.design_keys) != sorted(keys):
            sys.exit(f"{NAME}: --data {data} holds other membranes than {keys}")
        record["data"] = {"file": str(data), "made_s": None, "reused": True}
    else:
        argv = [sys.executable, __file__, "--membranes", str(args.membranes), "--sample-hz", str(args.sample_hz)]
        argv += ["--seed", str(args.seed), "--make-data", str(data)]
        proc = subprocess.run(argv)
        if proc.returncode != 0:
            sys.exit(f"{NAME}: making the rig data failed ({proc.returncode})")
        record["data"] = {"file": str(data), "made_s": round(time.perf_counter() - t0, 1), "reused": False}
        from mfdesign.data.store import read_parquet

        made = read_parquet(data)
    record["data"] |= {
        "rows": len(made),
        "sample_hz": args.sample_hz,
        "truth": "virtual rig, the simulator with the bundled card's hidden effect, 1 trial a height, no lifts",
    }
    del made

    # -- the timed round, cold
    sizes = dict(QUICK if args.quick else FULL)
    if args.mcmc_steps is not None:
        sizes["mcmc_steps"] = args.mcmc_steps
    from mfdesign.campaign import Settings

    settings = Settings(physics="exact", **sizes).to_json()
    (tmp / "settings.json").write_text(json.dumps(settings))
    cache = tmp / "cache"
    cache.mkdir()
    camp = tmp / "campaign"
    env = dict(os.environ, MFDESIGN_CACHE_DIR=str(cache))
    py = sys.executable
    steps_argv = {
        "create": [py, "-c", CREATE, str(camp), str(data), str(tmp / "settings.json")],
        "diagnose": [py, "-c", DIAGNOSE, str(camp)],
        "fit": [py, "-m", "mfdesign.cli", "fit", str(camp)],
        "ask": [py, "-m", "mfdesign.cli", "ask", str(camp), "--q", str(args.q)],
    }
    record |= {
        "settings": settings,
        "quick": args.quick,
        "cache_dir": str(cache),
        "campaign": str(camp),
        "peak_rss_source": "/usr/bin/time -v" if TIME_V.is_file() else "none (/usr/bin/time missing)",
        "load_average_before": load(),
        "steps": {},
        "timeout_s": args.timeout,
    }
    start = time.perf_counter()
    for name, argv in steps_argv.items():
        left = args.timeout - (time.perf_counter() - start)
        row = run_step(name, argv, env, tmp, left)
        record["steps"][name] = row
        record["total_s"] = round(time.perf_counter() - start, 2)
        write_json(out_json, record)
        if row["timed_out"] or row["returncode"] != 0:
            print("\n".join(Path(row["log"]).read_text(errors="replace").splitlines()[-30:]), flush=True)
            break
    total = time.perf_counter() - start
    steps = record["steps"]
    complete = len(steps) == len(steps_argv) and all(r["returncode"] == 0 for r in steps.values())
    peaks = [r["peak_rss_gb"] for r in steps.values() if "peak_rss_gb" in r]
    record |= {
        "total_s": round(total, 2),
        "cpu_s": round(sum(r.get("cpu_s", 0.0) for r in steps.values()), 2),
        "peak_rss_gb": max(peaks) if peaks else None,
        "complete": complete,
        "met": bool(complete and total <= TARGET_S),
        "load_average_after": load(),
    }
    bad = [n for n, r in steps.items() if r["timed_out"] or r["returncode"] != 0]
    if bad:
        r = steps[bad[0]]
        record["stopped_at"] = {"step": bad[0], "ran_s": r["wall_s"], "timed_out": r["timed_out"]}
    if complete:
        st = subprocess.run([py, "-m", "mfdesign.cli", "status", str(camp)], env=env, capture_output=True, text=True)
        record["status"] = st.stdout.strip().splitlines()
        diag = camp / "diagnosis.json"
        if diag.is_file():
            d = json.loads(diag.read_text())
            record["diagnosis_found"] = d.get("effects_after")
        record["chain"] = chain_of(camp)
    write_json(out_json, record)

    print("\n".join(table(steps)))
    print(
        f"total {total:.1f} s, CPU {record['cpu_s']:.1f} s; load before {record['load_average_before']}, after "
        f"{record['load_average_after']}; nproc {record['machine']['nproc']}; written {out_json}"
    )
    for line in record.get("status", []):
        print(line)
    rss = record["peak_rss_gb"]
    state = "" if complete else f" (NOT complete: stopped at {bad[0] if bad else '?'})"
    chain, chain_state = record.get("chain") or {}, ""
    if chain.get("converged"):
        chain_state = "; chain converged"
    elif chain:
        tau, acc = chain.get("steps_over_tau", float("nan")), chain.get("acceptance", float("nan"))
        chain_state = f"; chain NOT converged ({tau:.1f} tau, acceptance {acc:.2f})"
    print(
        f"{NAME}: cold round of {len(keys)} membranes {total:.1f} s (target {TARGET_S:.0f} s){state}, "
        f"peak RSS {'unknown' if rss is None else f'{rss:.2f}'} GB{chain_state}"
    )
    shutil.rmtree(cache, ignore_errors=True)
    if not complete:
        sys.exit(1)


if __name__ == "__main__":
    main()
