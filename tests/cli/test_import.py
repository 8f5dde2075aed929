"""`mfdesign import` and the shared DATA loader: SPA_Design pickles, CSV, Parquet, rig job
folders, several sources at once, unknown formats refused in one line (exit 2)."""

from __future__ import annotations

import pickle

import numpy as np
import pandas as pd
import pytest
from typer.testing import CliRunner

from mfdesign.cli import app
from mfdesign.data.measurements import COLUMNS, Measurements
from mfdesign.data.sources import detect_format, load_sources, read_characterisation
from mfdesign.data.spa_design import MASS_LIFT_FILE, load_mass_lift, shared_data_dir
from mfdesign.data.store import read_parquet
from mfdesign.workflows.data import load_data

runner = CliRunner()
RINGLESS = "[2.0, 25.4, nan, nan, nan, nan]"
RINGED = "[2.0, 31.92, 46.0, 5.0, 59.0, 5.0]"


def _shared_mass_lift():
    try:
        path = shared_data_dir() / MASS_LIFT_FILE
    except FileNotFoundError:
        pytest.skip("shared SPA_Design data not available")
    if not path.is_file():
        pytest.skip("shared SPA_Design data not available")
    return path


def _characterisation_dict() -> dict:
    """A tiny characterisation data dictionary: 2 membranes x 2 set heights x 5 pressures."""
    out = {}
    for key, design in (
        (RINGLESS, [2.0, 25.4, np.nan, np.nan, np.nan, np.nan]),
        (RINGED, [2.0, 31.92, 46.0, 5.0, 59.0, 5.0]),
    ):
        rows = [[h] + design for h in (10.0, 30.0) for _ in range(5)]
        us = np.asarray(rows, dtype=np.float32)
        ys = np.tile(np.linspace(0.0, 8000.0, 5), 2)[:, None].astype(np.float32)
        fs = (ys / 200.0 + us[:, :1] / 10.0).astype(np.float32)
        ws = np.full((10, 1), 0.1, dtype=np.float32)
        out[key] = ((us, ys), fs, ws)
    return out


def test_import_round_trips_the_shared_mass_lift_file(tmp_path):
    path = _shared_mass_lift()
    out = tmp_path / "ml.parquet"
    r = runner.invoke(app, ["import", str(path), "--out", str(out)])
    assert r.exit_code == 0, r.output
    assert "42" in r.output and "lift" in r.output
    pd.testing.assert_frame_equal(read_parquet(out).df, load_mass_lift(path).df)


def test_characterisation_dictionary_becomes_force_trials(tmp_path):
    pkl = tmp_path / "char.pkl"
    pkl.write_bytes(pickle.dumps(_characterisation_dict()))
    assert detect_format(pkl) == "characterisation"
    out = tmp_path / "char.parquet"
    r = runner.invoke(app, ["import", str(pkl), "--out", str(out)])
    assert r.exit_code == 0, r.output
    df = read_parquet(out).df
    assert len(df) == 20 and (df["experiment"] == "force").all() and (df["source"] == "file").all()
    np.testing.assert_array_equal(df["height_set_mm"], df["height_mm"])
    trials = df.groupby(["design_key", "trial"])["height_set_mm"].agg(["nunique", "first", "size"])
    assert len(trials) == 4 and (trials["nunique"] == 1).all() and (trials["size"] == 5).all()
    assert sorted(trials.loc[RINGED, "first"]) == [10.0, 30.0]
    np.testing.assert_allclose(df["force_n"], df["pressure_pa"] / 200 + df["height_mm"] / 10, rtol=1e-5)
    # forced format on the same file, and the reader on the loaded dict, agree
    pd.testing.assert_frame_equal(load_sources([pkl], "characterisation").df, df)
    pd.testing.assert_frame_equal(read_characterisation(_characterisation_dict()).df, df)


def test_csv_round_trip_and_missing_columns(tmp_path):
    m = read_characterisation(_characterisation_dict())
    csv = tmp_path / "m.csv"
    m.df.to_csv(csv, index=False)
    out = tmp_path / "m.parquet"
    r = runner.invoke(app, ["import", str(csv), "--out", str(out)])
    assert r.exit_code == 0, r.output
    pd.testing.assert_frame_equal(read_parquet(out).df, m.df)
    # optional columns take their documented defaults (mfdesign.data.columns); required ones are refused
    m.df.drop(columns=["weight", "source"]).to_csv(tmp_path / "opt.csv", index=False)
    r = runner.invoke(app, ["import", str(tmp_path / "opt.csv"), "--out", str(tmp_path / "o.parquet")])
    assert r.exit_code == 0, r.output
    filled = read_parquet(tmp_path / "o.parquet").df
    assert (filled["weight"] == 1.0).all() and (filled["source"] == "file").all()
    m.df.drop(columns=["force_n"]).to_csv(tmp_path / "bad.csv", index=False)
    r = runner.invoke(app, ["import", str(tmp_path / "bad.csv"), "--out", str(tmp_path / "x.parquet")])
    assert r.exit_code == 2 and "missing column(s) ['force_n']" in r.output
    assert len(r.output.strip().splitlines()) == 1


@pytest.mark.parametrize(
    "name, content, words",
    [
        ("notes.txt", b"hello", "unknown format"),
        ("evil.pkl", pickle.dumps({"x": 1}, protocol=2).replace(b"}", b"}"), "not ((us, ys), Fs, ws)"),
        ("set.pkl", pickle.dumps({1, 2}), "builds a set"),
    ],
)
def test_unknown_or_unsafe_input_is_refused_in_one_line(tmp_path, name, content, words):
    (tmp_path / name).write_bytes(content)
    r = runner.invoke(app, ["import", str(tmp_path / name), "--out", str(tmp_path / "x.parquet")])
    assert r.exit_code == 2 and words in r.output, r.output
    assert len(r.output.strip().splitlines()) == 1 and not (tmp_path / "x.parquet").exists()
    r = runner.invoke(app, ["import", str(tmp_path / name), "--format", "xls", "--out", str(tmp_path / "x.parquet")])
    assert r.exit_code == 2 and "--format 'xls' is not known" in r.output


def test_data_takes_several_sources_and_rig_job_folders(tmp_path):
    m = read_characterisation(_characterisation_dict())
    a, job = tmp_path / "a.parquet", tmp_path / "job"
    m.to_parquet(a)
    job.mkdir()
    Measurements(m.df.assign(source="virtual")).to_parquet(job / "measurements.parquet")
    assert detect_format(job) == "rig-job"
    both = load_data([a, job])
    assert len(both) == 2 * len(m)
    per = both.df.groupby("design_key")["trial"].unique()
    assert all(sorted(t) == [0, 1, 2, 3] for t in per)  # ids renumbered per membrane, unique
    assert load_data([a]).df.equals(m.df) and load_data(a).df.equals(m.df)  # one source: as it was
    r = runner.invoke(
        app, ["cv", str(a), str(job), "--model-type", "curve-fit", "--folds", "2", "--out", str(tmp_path / "cv.json")]
    )
    assert r.exit_code == 0, r.output
    r = runner.invoke(app, ["cv", str(a), str(tmp_path), "--model-type", "curve-fit"])
    assert r.exit_code == 2 and "not a rig job" in r.output


def test_measurements_schema_is_documented():
    from pathlib import Path

    doc = (Path(__file__).resolve().parents[2] / "docs" / "data.md").read_text()
    for column in COLUMNS:
        assert f"`{column}`" in doc
