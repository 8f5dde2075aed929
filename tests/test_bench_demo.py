"""experiments/bench_demo.py's bookkeeping on a fake summary.json: the record, the JSONL
trajectory, the ratios against the previous run of the same mode and the summary line.
No demo is run (the benchmark itself is ``python experiments/bench_demo.py``)."""

from __future__ import annotations

import importlib.util
import json
import platform
from pathlib import Path

import pytest

ROOT = Path(__file__).resolve().parents[1]


@pytest.fixture
def bench(monkeypatch):
    monkeypatch.syspath_prepend(str(ROOT / "experiments"))  # its ``from _common import ...``
    spec = importlib.util.spec_from_file_location("bench_demo", ROOT / "experiments" / "bench_demo.py")
    mod = importlib.util.module_from_spec(spec)
    spec.loader.exec_module(mod)
    return mod


def fake_summary(scale: float = 1.0, ratio: float = 1.13, converged: bool = True) -> dict:
    names = ["load data and force model", "calibrate mu, J_m (emcee): plain model", "add pressure_sensor: refit"]
    walls = [26.0 * scale, 80.0 * scale, 60.0 * scale]
    return {
        "timings_s": dict(zip(names, walls)),
        "stage_resources": {
            n: {"wall_s": w, "cpu_s": 1.8 * w, "peak_rss_mb": 900.0 + i, "rss_end_mb": 800.0}
            for i, (n, w) in enumerate(zip(names, walls))
        },
        "total_s": sum(walls),
        "diagnosis": {"found": ["pressure_sensor"], "after_over_floor": ratio},
        "convergence": {"plain": {"converged": True}, "with_effects": {"converged": converged}},
        "truth_check": {"mu_pa": {"inside": True}, "jm": {"inside": True}},
    }


TIME_V = """\
\tCommand being timed: "python -m mfdesign.cli demo --out /tmp/x"
\tUser time (seconds): 400.50
\tSystem time (seconds): 20.25
\tElapsed (wall clock) time (h:mm:ss or m:ss): 4:26.30
\tMaximum resident set size (kbytes): 1887436
\tExit status: 0
"""


def test_time_v_report_is_read(bench):
    tv = bench.parse_time_v(TIME_V)
    assert tv == {"user_s": 400.5, "sys_s": 20.25, "max_rss_kb": 1887436, "wall_s": 266.3, "exit_status": 0}
    assert bench.parse_time_v("\tElapsed (wall clock) time (h:mm:ss or m:ss): 1:02:03")["wall_s"] == 3723.0


def test_modes_and_short_stage_names(bench):
    assert [bench.mode_of(q, w) for q, w in ((0, 0), (0, 1), (1, 0), (1, 1))] == ["cold", "warm", "quick", "quick-warm"]
    assert bench.short("add pressure_sensor: refit") == "add"
    assert bench.short("calibrate mu, J_m (emcee): plain model") == "calibrate"


def test_results_checks(bench):
    assert bench.results_of(fake_summary())["ok"]
    assert not bench.results_of(fake_summary(ratio=1.25))["ok"]  # above 1.2 floors
    assert not bench.results_of(fake_summary(converged=False))["ok"]
    s = fake_summary()
    s["truth_check"]["jm"]["inside"] = False
    assert not bench.results_of(s)["ok"]
    assert not bench.results_of({})["ok"]  # a failed demo wrote no summary: not ok


def test_jsonl_trajectory_and_ratios(bench, tmp_path):
    path = tmp_path / "bench_demo.jsonl"

    def rec(summary, mode="cold", wall=170.0, commit="aaaa"):
        return bench.make_record(
            summary, mode=mode, wall_s=wall, cpu_s=300.0, peak_rss_kb=2 * 2**20, rss_source="x", commit=commit
        )

    first = rec(fake_summary())
    assert first["peak_rss_gb"] == 2.0 and first["results"]["ok"]
    assert first["stages"]["calibrate"] == {"wall_s": 80.0, "cpu_s": 144.0, "peak_rss_mb": 901.0, "rss_end_mb": 800.0}
    assert bench.previous(bench.read_jsonl(path), "cold") is None
    bench.append_jsonl(path, first)
    bench.append_jsonl(path, rec(fake_summary(), mode="quick", wall=50.0, commit="qqqq"))
    with open(path, "a") as f:
        f.write('{"mode": "cold", "torn')  # a killed writer's last line is skipped
    records = bench.read_jsonl(path)
    assert [r["mode"] for r in records] == ["cold", "quick"]
    prev = bench.previous(records, "cold")
    assert prev["commit"] == "aaaa"  # the previous run of the same mode, not the latest line

    now = rec(fake_summary(scale=0.5), wall=85.0, commit="bbbb")
    line = bench.ratio_line(now, prev)
    assert line.startswith("stages vs aaaa (cold, now/then):")
    assert "calibrate 40.0 s (x0.50)" in line and "total 85.0 s (x0.50)" in line and "(x1.00)" in line
    table = bench.stage_table(now, prev)
    assert len(table) == 1 + 3 and table[2].split()[0] == "calibrate" and table[2].endswith("x0.50")
    assert bench.ratio_line(now, None).startswith("stages (cold, no earlier cold run")
    assert bench.summary_line(now) == (
        "bench_demo: cold wall 85.0 s (target 300 s), peak RSS 2.00 GB (target 2 GB), results ok"
    )
    bad = rec(fake_summary(ratio=2.0), mode="quick")
    assert bench.summary_line(bad).endswith("(target 120 s), peak RSS 2.00 GB (target 2 GB), results NOT ok")
    # the file stays one JSON object a line
    bench.append_jsonl(path, now)
    assert json.loads(path.read_text().splitlines()[-1])["commit"] == "bbbb"


def test_summary_without_stage_resources(bench):
    """A demo before stage_resources: wall times only."""
    s = fake_summary()
    del s["stage_resources"]
    assert bench.stages_of(s)["load"] == {"wall_s": 26.0}
    r = bench.make_record(s, mode="warm", wall_s=1.0, cpu_s=None, peak_rss_kb=None, rss_source="none")
    assert "peak RSS unknown" in bench.summary_line(r) and "(target 120 s)" in bench.summary_line(r)
    assert bench.stage_table(r, None)[1].split()[2] == "-"


def test_machine_probe_is_recorded_and_compared(bench):
    """The fixed workload runs in a fresh process and gives positive seconds; the line
    compares it with the previous run's probe, and says so where there was none."""
    probe = bench.speed_probe()
    assert probe is not None and set(probe) == {"python_s", "xla_compile_s", "xla_run_s", "total_s"}
    assert all(v > 0 for v in probe.values())
    assert abs(probe["total_s"] - sum(v for k, v in probe.items() if k != "total_s")) < 0.01
    now = {"speed_probe": {"python_s": 0.6, "xla_compile_s": 0.8, "xla_run_s": 0.6, "total_s": 2.0}}
    line = bench.probe_line(now, {"speed_probe": {"total_s": 1.0}})
    assert line.startswith("machine probe: 2.00 s") and "x2.00" in line
    assert "no earlier probe" in bench.probe_line(now, {"mode": "cold"})
    assert bench.probe_line({"speed_probe": None}, None) == "machine probe: failed"


def test_the_cpu_is_named_with_its_widest_vector_unit(bench):
    # float32 sums differ between hosts by their vector unit: a line names both, so two lines
    # whose stored programs were traced anew can be told apart by host (session 46)
    import _common  # on the path through the ``bench`` fixture

    info = _common.cpu_info()
    assert set(info) == {"model", "vector"}
    assert isinstance(info["model"], str)
    assert info["vector"] in {"avx512f", "avx2", "avx", "sse4_2", ""}
    if platform.machine() == "x86_64" and Path("/proc/cpuinfo").is_file():  # read, not guessed
        assert info["model"] and info["vector"]
