"""A lab's own CSV layout: a column map with a unit per column, documented defaults for the
optional columns, and implausible units refused in one line (exit 2)."""

from __future__ import annotations

import numpy as np
import pandas as pd
import pytest
from typer.testing import CliRunner

from mfdesign.cli import app
from mfdesign.data.columns import ColumnMap
from mfdesign.data.sources import load_sources, read_csv
from mfdesign.data.store import read_parquet
from mfdesign.errors import InputError

runner = CliRunner()
KEYS = ("[2.0, 30.0, 45.0, 5.0, nan, nan]", "[1.5, 25.0, nan, nan, nan, nan]")
MAP = "design_key=design,pressure_pa=pressure_kpa:kPa"


def _lab_csv(path, force_scale=1.0, header=("design", "height_mm", "pressure_kpa", "force_n"), h_scale=1.0):
    """A rig log in a lab's own layout: pressure in kPa, force in N (times ``force_scale``),
    height in mm (times ``h_scale``)."""
    rows = []
    for key in KEYS:
        for h in (10.0, 20.0, 30.0):
            for p_kpa in np.linspace(0.5, 5.0, 12):
                f = p_kpa * 1e3 * np.pi * 0.05**2 * (1 - h / 60)  # below p pi R^2: plausible newtons
                rows.append((key, h * h_scale, round(p_kpa, 4), round(f * force_scale, 4)))
    pd.DataFrame(rows, columns=list(header)).to_csv(path, index=False)
    return path


def test_the_issue_csv_imports_with_a_map_and_fails_without_one_saying_what_to_add(tmp_path):
    src = _lab_csv(tmp_path / "lab.csv")
    out = tmp_path / "lab.parquet"
    bare = runner.invoke(app, ["import", str(src), "--out", str(out)])
    assert bare.exit_code == 2 and not out.exists()
    line = bare.output.strip()
    assert "\n" not in line and "Traceback" not in line
    assert "missing column(s) ['design_key', 'pressure_pa']" in line
    assert f"--columns {MAP}" in line  # the map to add, guessed from the column names

    res = runner.invoke(app, ["import", str(src), "--out", str(out), "--columns", MAP])
    assert res.exit_code == 0, res.output
    m = read_parquet(out)
    df = m.df
    assert len(m) == 72 and sorted(m.design_keys) == sorted(KEYS)
    raw = pd.read_csv(src)
    np.testing.assert_allclose(df["pressure_pa"], raw["pressure_kpa"] * 1e3)  # kPa -> Pa
    np.testing.assert_allclose(df["force_n"], raw["force_n"])
    # the documented defaults of the optional columns
    assert (df["experiment"] == "force").all() and (df["phase"] == "inflate").all()
    assert (df["source"] == "file").all() and (df["weight"] == 1.0).all() and df["time_s"].isna().all()
    np.testing.assert_array_equal(df["height_set_mm"], df["height_mm"])
    # one trial per membrane and set height, numbered per membrane in order of appearance
    trials = df.groupby(["design_key", "height_set_mm"])["trial"].unique()
    assert all(len(t) == 1 for t in trials)
    assert all(sorted(t.unique()) == [0, 1, 2] for _, t in df.groupby("design_key")["trial"])


def test_units_convert_and_a_mistaken_unit_is_still_refused(tmp_path):
    # force logged in grams: mapped with its unit it imports; mapped as newtons it is refused
    src = _lab_csv(tmp_path / "grams.csv", force_scale=1 / 9.80665e-3)
    ok = read_csv(src, MAP + ",force_n=force_n:g")
    np.testing.assert_allclose(ok.df["force_n"], read_csv(_lab_csv(tmp_path / "n.csv"), MAP).df["force_n"], atol=1e-3)
    with pytest.raises(InputError, match=r"'force_n' .* not newtons .*force_n=COLUMN:g"):
        read_csv(src, MAP)
    # pressure mapped without its unit reads as Pa and looks like kPa
    with pytest.raises(InputError, match=r"'pressure_pa' never exceeds 5 .* looks like kPa"):
        read_csv(_lab_csv(tmp_path / "p.csv"), "design_key=design,pressure_pa=pressure_kpa")
    # psi and cm are converted to Pa and mm
    psi = _lab_csv(tmp_path / "psi.csv", header=("design", "height_cm", "pressure_psi", "force_n"), h_scale=0.1)
    raw = pd.read_csv(psi)
    m = load_sources([psi], columns="design_key=design,height_mm=height_cm:cm,pressure_pa=pressure_psi:psi")
    np.testing.assert_allclose(m.df["pressure_pa"], raw["pressure_psi"] * 6894.757293168)
    np.testing.assert_allclose(m.df["height_mm"], raw["height_cm"] * 10)


@pytest.mark.parametrize(
    "spec, message",
    [
        ("pressure_pa", "allowed: TARGET=SOURCE or TARGET=SOURCE:UNIT"),
        ("pressure=pressure_kpa", "not a Measurements column; allowed: ['design_key'"),
        ("pressure_pa=pressure_kpa:atm", "unit 'atm' for 'pressure_pa' is not known; allowed: Pa, kPa"),
        ("design_key=design:mm", "takes no unit"),
        ("force_n=a,force_n=b", "names 'force_n' twice"),
    ],
)
def test_a_bad_map_fails_in_one_line(tmp_path, spec, message):
    with pytest.raises(InputError, match=message.replace("[", r"\[").replace("(", r"\(")):
        ColumnMap.parse(spec)
    res = runner.invoke(
        app, ["import", str(_lab_csv(tmp_path / "lab.csv")), "--out", str(tmp_path / "o.parquet"), "--columns", spec]
    )
    assert res.exit_code == 2 and len(res.output.strip().splitlines()) == 1 and message.split(";")[0] in res.output


def test_a_map_naming_an_absent_column_or_a_pickle_is_refused(tmp_path):
    src = _lab_csv(tmp_path / "lab.csv")
    with pytest.raises(InputError, match=r"no column 'press'; allowed: one of \['design'"):
        read_csv(src, "design_key=design,pressure_pa=press:kPa")
    with pytest.raises(InputError, match="a column map .* reads a CSV or Parquet table"):
        load_sources(["mass-lift"], columns=MAP)
