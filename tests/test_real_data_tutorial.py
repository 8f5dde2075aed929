"""docs/real_data_log.md is real: its commands run as written, and its tables quote their outputs.

Slow (about 1.5 h on 2 cores) and it needs the authors' measurements
(``../shared/data/spa_design``): skipped without them. It runs every ```bash command of
the page in order from the repository root (they write ``out/real_diagnose`` and
``experiments/out/``), then reads the numbers the page quotes back from the JSON the
commands wrote: the diagnosis's before/after RMSE and the leave-one-membrane-out table.
``MFDESIGN_TUTORIAL_ONLY=REGEX`` runs only the matching commands (the others' outputs on
disk), then every quote check.
"""

from __future__ import annotations

import json
import os
import re
import subprocess
import sys
import time
from pathlib import Path

import pytest

from tests.test_docs import doc_commands

ROOT = Path(__file__).resolve().parents[1]
PAGE = ROOT / "docs" / "real_data_log.md"  # the log of everything tried; docs/real_data.md summarises it
MODELS = ("a_sim_paper", "b_sim_calibrated", "c_ensemble", "d_curve_fit", "e_multi_fidelity")


def _have_real_data() -> bool:
    from mfdesign.data.spa_design import shared_data_dir

    return (shared_data_dir(must_exist=False) / "mass_lift_data_dictionary_N_Pa.pkl").is_file()


def _table_rows(text: str, first_cell: str) -> list[list[str]]:
    return [
        [c.strip() for c in line.strip().strip("|").split("|")]
        for line in text.splitlines()
        if line.startswith("| " + first_cell)
    ]


def _num(cell: str) -> float:
    return float(re.sub(r"[^0-9.+-]", "", cell.split("/")[0]))


def test_the_page_names_its_commands():
    commands = doc_commands(PAGE)
    assert any(c.startswith("mfdesign diagnose mass-lift") for c in commands)
    assert any("experiments/real_mass_lift.py" in c for c in commands)
    assert all("run by tests/test_real_data_tutorial.py" in c for c in commands)


@pytest.mark.slow
def test_the_tutorial_runs_and_quotes_its_outputs():
    if not _have_real_data():
        pytest.skip("needs the authors' measurements in ../shared/data/spa_design")
    env = dict(os.environ, JAX_PLATFORMS="cpu", MPLBACKEND="Agg")
    env["PATH"] = str(Path(sys.executable).parent) + os.pathsep + env.get("PATH", "")
    commands = doc_commands(PAGE)
    # MFDESIGN_TUTORIAL_ONLY=REGEX runs only the commands it matches (a page that gained
    # one command need not rerun 1.5 h of the others; their outputs must be on disk). The
    # quote checks below always run in full. A run that skips commands says so.
    only = os.environ.get("MFDESIGN_TUTORIAL_ONLY")
    if only:
        commands = [c for c in commands if re.search(only, c)]
        print(f"MFDESIGN_TUTORIAL_ONLY={only!r}: {len(commands)} of {len(doc_commands(PAGE))} commands run", flush=True)
        assert commands, f"MFDESIGN_TUTORIAL_ONLY={only!r} matches none of the page's commands"
    for command in commands:
        t0 = time.perf_counter()
        r = subprocess.run(command, shell=True, cwd=ROOT, env=env, capture_output=True, text=True, timeout=3 * 3600)
        print(f"[{time.perf_counter() - t0:7.1f} s] {command}", flush=True)
        assert r.returncode == 0, f"{command!r} failed:\n{r.stdout[-2000:]}\n{r.stderr[-2000:]}"
    text = PAGE.read_text()
    diag = json.loads((ROOT / "out" / "real_diagnose" / "diagnosis.json").read_text())
    before = re.search(r"before: RMSE ([0-9.]+) N", text)
    assert before and float(before.group(1)) == pytest.approx(diag["before"]["summary"]["rmse_n"], abs=0.01)
    # the diagnosis with one membrane a fold (section 3): the rings' round-2 check, not claimed
    lomo_diag = json.loads((ROOT / "out" / "real_diagnose_lomo" / "diagnosis.json").read_text())
    quoted = re.search(r"one membrane a fold: held-out ([0-9.]+) -> ([0-9.]+) N", text)
    assert quoted, "the page's one-membrane-a-fold diagnosis is missing"
    best = min(lomo_diag["search"][1]["checks"], key=lambda c: c["heldout_rmse_n"])
    assert best["effects"] == ["fabric_inset", "ring_stiffening"] and lomo_diag["found"] == ["fabric_inset"]
    assert [float(quoted.group(1)), float(quoted.group(2))] == pytest.approx(
        [best["heldout_rmse_base_n"], best["heldout_rmse_n"]], abs=0.001
    )
    # the lattice and the simulator against the data at the ring MAPs (section 8)
    scored = re.findall(
        r"the\s+lattice\s+scores\s+([0-9.]+) N\s+and\s+the\s+simulator\s+([0-9.]+) N\s+\(`(bench_effect_axes[^`]+)`",
        text,
    )
    assert len(scored) == 2, scored
    for lattice, simulator, name in scored:
        vs = json.loads((ROOT / "experiments" / "out" / name).read_text())["pooled_rmse_vs_data"]
        assert [float(lattice), float(simulator)] == pytest.approx([vs["lattice_n"], vs["simulator_n"]], abs=0.01), name
    tables = _held_out_tables(text)
    assert [t[0] for t in tables] == list(HELD_OUT_TABLES), "the page's held-out tables and their outputs differ"
    for title, header, pooled in tables:
        lomo = json.loads((ROOT / "experiments" / "out" / HELD_OUT_TABLES[title] / "real_mass_lift.json").read_text())
        for head, cell in zip(header[1:], pooled[1:]):
            name = {m[0]: m for m in MODELS}.get(head[:1])
            if name is not None and cell:
                assert _num(cell) == pytest.approx(lomo["metrics_held_out"][name]["rmse_n"], abs=0.02), (title, name)
    # the in-sample floor (experiments/real_floor.py): its last two columns, fitted on all
    # seven and each membrane on itself
    ((_, _, pooled),) = _held_out_tables(text, "in sample")
    floor = json.loads((ROOT / "experiments" / "out" / "real_floor.json").read_text())["cases"]
    traj = _row_of_table(text, "in sample", "trajectory mean / median")
    for cell, tcell, case in zip(pooled[-2:], traj[-2:], ("all7", "each")):
        assert _num(cell) == pytest.approx(floor[case]["summary"]["pooled_rmse_n"], abs=0.02), case
        mean, median = (float(v) for v in tcell.split("/"))
        assert mean == pytest.approx(floor[case]["summary"]["traj_mean"], abs=0.001), case
        assert median == pytest.approx(floor[case]["summary"]["traj_median"], abs=0.001), case
    # section 8: the in-sample fit with the rings calibrated too (real_floor.py --effects ...)
    rings = json.loads((ROOT / "experiments" / "out" / "real_floor_rings" / "real_floor.json").read_text())
    quoted = re.search(r"pooled force falls from 2.96 to \*\*([0-9.]+) N", text)
    assert quoted and float(quoted.group(1)) == pytest.approx(
        rings["cases"]["all7"]["summary"]["pooled_rmse_n"], abs=0.01
    )
    # section 8: rubber (free / coupons') x rings (model's / calibrated), in sample
    quoted = {
        row[0].split(" (")[0]: row[1:3]
        for row in _table_rows(text, "rubber free (") + _table_rows(text, "coupons' rubber (")
    }
    for rubber, folders in (
        ("rubber free", ("", "real_floor_rings")),
        ("coupons' rubber", ("real_floor_coupons", "real_floor_rings_coupons")),
    ):
        for cell, folder in zip(quoted[rubber], folders):
            fit = json.loads((ROOT / "experiments" / "out" / folder / "real_floor.json").read_text())["cases"]["all7"]
            force, mean, median = (float(v) for v in re.findall(r"[0-9.]+", cell.split(" (")[0].replace("*", "")))
            assert [force, mean, median] == pytest.approx(
                [fit["summary"]["pooled_rmse_n"], fit["summary"]["traj_mean"], fit["summary"]["traj_median"]], abs=0.006
            ), (rubber, folder)
    # section 8's probes (experiments/real_probes.py): the rings x J_m table
    grid = json.loads((ROOT / "experiments" / "out" / "real_probes.json").read_text())["cases"]["rings"]["jm_grid"]
    quoted = {row[0]: row[1:4] for row in _table_rows(text, "") if re.fullmatch(r"[0-9.]+x", row[0])}
    assert quoted, "the page's rings x J_m table is missing"
    for g in grid:
        cell = quoted[f"{g['factor']:g}x"][[21.0, 30.0, 39.6].index(g["jm"])]  # "**3.34** (7)": 3.34
        assert float(re.search(r"[0-9.]+", cell).group()) == pytest.approx(g["rmse_n"], abs=0.01), g
    # section 8: the plate as a contact beyond the disk (experiments/real_plate_contact.py)
    contact = json.loads((ROOT / "experiments" / "out" / "real_plate_contact.json").read_text())
    (row,) = _table_rows(text, "pooled |")  # its table's last row: "| pooled | 6.40 | 11.03 | ..."
    quoted = [_num(c) for c in row[1:5]]
    measured = [contact["pooled"][n][c] for n in ("paper", "map") for c in ("no_contact_n", "contact_n")]
    assert quoted == pytest.approx(measured, abs=0.01)
    assert contact["best_contact_rubber"]["rmse_n"] > 2 * contact["pooled"]["map"]["no_contact_n"]
    # section 8: rings up to 100x stiffer with the FE reference (experiments/real_rings_fe.py)
    rings_fe = json.loads((ROOT / "experiments" / "out" / "real_rings_fe.json").read_text())["pooled_rmse_n"]
    for row in _table_rows(text, "pooled RMSE [N],"):
        name = "map" if "MAP" in row[0] else "coupons"
        assert [_num(c) for c in row[1:]] == pytest.approx(list(rings_fe[name].values()), abs=0.01), name


# The page's leave-one-membrane-out tables (the header's first cell) and the --out folder
# (under experiments/out) whose real_mass_lift.json each quotes, in the page's order.
HELD_OUT_TABLES = {
    "held out": "real_mass_lift_free_latents",
    "held out (J_m held at 39.6)": "real_mass_lift_jm_coupons",
    "held out (mu, J_m held)": "real_mass_lift_material_coupons",
    "held out (mu, J_m held, no latents)": "real_mass_lift_material_nolatents",
    "held out (rubber free, no latents)": "real_mass_lift_nolatents",
    "held out (rubber free, no latents, stiff rings)": "real_mass_lift_rings",
    "held out (coupons' rubber, no latents, stiff rings)": "real_mass_lift_rings_coupons",
    "held out (coupons' rubber, no latents, stiff rings, tensor lattice)": "real_mass_lift_rings_coupons_tensor",
}


def _rows_of_tables(text: str, prefix: str, first_cell: str) -> list[tuple[list[str], list[str]]]:
    """(header cells, row cells) of the row ``first_cell`` of every table whose header starts
    with ``prefix``, in the page's order."""
    out, header = [], None
    for line in text.splitlines():
        cells = [c.strip() for c in line.strip().strip("|").split("|")] if line.startswith("|") else None
        if cells is None:
            header = None
        elif header is None:
            header = cells
        elif cells[0] == first_cell and header[0].startswith(prefix):
            out.append((header, cells))
    return out


def _row_of_table(text: str, prefix: str, first_cell: str) -> list[str]:
    """The row ``first_cell`` of the one table whose header starts with ``prefix``."""
    ((_, row),) = _rows_of_tables(text, prefix, first_cell)
    return row


def _held_out_tables(text: str, prefix: str = "held out") -> list[tuple[str, list[str], list[str]]]:
    """(first header cell, header cells, pooled-force-RMSE row cells) of every table whose
    header starts with ``prefix``."""
    return [(header[0], header, row) for header, row in _rows_of_tables(text, prefix, "pooled force RMSE")]
