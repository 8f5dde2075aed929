"""Measurements: schema checks with clear messages, Parquet round trip, membrane k-fold."""

from __future__ import annotations

import copy
import pickle

import numpy as np
import pandas as pd
import pyarrow.parquet as pq
import pytest

from mfdesign.data import COLUMNS, MeasurementError, Measurements, read_parquet, write_parquet
from mfdesign.data import store

KEYS = [
    "[2.0, 25.4, nan, nan, nan, nan]",
    "[1.0, 38.1, nan, nan, nan, nan]",
    "[2.0, 25.4, 33.4, 5.0, 46.4, 5.0]",
    "[2.0, 31.92, 46.0, 5.0, 59.0, 5.0]",
    "[1.5, 25.4, nan, nan, nan, nan]",
    "[3.0, 38.1, 49.0, 5.0, 62.0, 5.0]",
    "[1.0, 25.4, 33.4, 5.0, 57.05, 9.95]",
]


def table(n_membranes: int = 3, rows_per_trial: int = 4, trials: int = 2) -> pd.DataFrame:
    rows = []
    for key in KEYS[:n_membranes]:
        for trial in range(trials):
            for i in range(rows_per_trial):
                rows.append(
                    {
                        "design_key": key,
                        "trial": trial,
                        "experiment": "force",
                        "phase": "inflate",
                        "time_s": 0.1 * i,
                        "height_set_mm": 10.0 * trial,
                        "height_mm": 10.0 * trial + 0.1,
                        "pressure_pa": 500.0 * i,
                        "force_n": 2.0 * i,
                        "weight": 1.0,
                        "source": "virtual",
                    }
                )
    return pd.DataFrame(rows, columns=list(COLUMNS))


def test_valid_table_and_accessors():
    m = Measurements(table())
    assert len(m) == 24
    assert m.design_keys == KEYS[:3]
    assert [d.key() for d in m.designs()] == KEYS[:3]
    assert list(m.df.columns) == list(COLUMNS)
    assert m.df["trial"].dtype == np.int64
    g = m.groups()
    assert g.dtype == np.int64 and list(np.unique(g)) == [0, 1, 2] and g[0] == 0 and g[-1] == 2
    arr = m.arrays()
    assert set(arr) == {"height_mm", "pressure_pa", "force_n", "weight", "design"}
    assert arr["design"].shape == (24, 6) and arr["design"].dtype == np.float64
    assert np.isnan(arr["design"][0, 2:]).all() and arr["design"][-1, 2] == 33.4
    assert all(a.dtype == np.float64 for a in arr.values())


def test_immutable_and_df_is_a_copy():
    m = Measurements(table())
    df = m.df
    df.loc[0, "force_n"] = 999.0
    assert m.df.loc[0, "force_n"] == 0.0
    with pytest.raises(AttributeError):
        m._df = df
    with pytest.raises(AttributeError):
        m.foo = 1
    for clone in (pickle.loads(pickle.dumps(m)), copy.deepcopy(m), copy.copy(m)):
        pd.testing.assert_frame_equal(clone.df, m.df)


def test_keys_are_canonicalised():
    df = table(1)
    df["design_key"] = "[2, 25.40, NaN, nan, nan, nan]"
    m = Measurements(df)
    assert m.design_keys == ["[2.0, 25.4, nan, nan, nan, nan]"]
    # rings given in the other order are the same membrane
    df["design_key"] = "[2.0, 25.4, 46.4, 5.0, 33.4, 5.0]"
    assert Measurements(df).design_keys == ["[2.0, 25.4, 33.4, 5.0, 46.4, 5.0]"]


def _expect(df, *fragments, **kw):
    with pytest.raises(MeasurementError) as err:
        Measurements(df, **kw)
    text = str(err.value)
    for f in fragments:
        assert f in text, f"{f!r} not in {text!r}"
    return text


def test_missing_and_extra_columns():
    df = table().drop(columns=["force_n", "weight"])
    _expect(df, "missing column(s)", "'force_n'", "'weight'")
    df = table().assign(note="x")
    _expect(df, "unexpected column(s)", "'note'", "extra_ok=True")
    m = Measurements(table().assign(note="x"), extra_ok=True)
    assert "note" in m.df.columns
    with pytest.raises(MeasurementError, match="DataFrame"):
        Measurements({"a": 1})


def test_invalid_design_key_names_row_and_reason():
    df = table()
    df.loc[5, "design_key"] = "[2.0, 25.4, 26.0, 5.0, nan, nan]"  # ring overlaps the disk
    _expect(df, "'design_key'", "row 5", "overlapping the contact disk")
    df.loc[5, "design_key"] = "hello"
    _expect(df, "row 5", "hello")
    df.loc[5, "design_key"] = None
    _expect(df, "'design_key'", "row 5", "a string")


@pytest.mark.parametrize(
    "column, value, fragment",
    [
        ("height_mm", np.nan, "finite"),
        ("height_mm", 250.0, "[-5, 200]"),
        ("height_mm", -6.0, "[-5, 200]"),
        ("height_mm", np.inf, "finite"),
        ("height_set_mm", 201.0, "[-5, 200] or NaN"),
        ("pressure_pa", 3e5, "[-20000, 200000]"),
        ("pressure_pa", np.nan, "finite"),
        ("force_n", 1e4, "[-50, 1000]"),
        ("force_n", -51.0, "[-50, 1000]"),
        ("weight", -1.0, "[0, inf]"),
        ("weight", np.nan, "finite"),
        ("time_s", -0.5, "[0, inf] or NaN"),
        ("time_s", "soon", "a number"),
        ("trial", -1, "integer >= 0"),
        ("trial", 1.5, "integer >= 0"),
        ("experiment", "squeeze", "['force', 'lift']"),
        ("phase", "hold", "['inflate', 'deflate']"),
        ("source", "lab", "['rig', 'virtual', 'simulated', 'file']"),
    ],
)
def test_each_rule_names_column_row_value_and_range(column, value, fragment):
    df = table()
    df[column] = df[column].astype(object)
    df.loc[7, column] = value
    text = _expect(df, f"column {column!r}", "row 7", fragment)
    assert repr(value) in text or str(value) in text


def test_nan_allowed_where_documented():
    df = table()
    df["time_s"] = np.nan
    df["height_set_mm"] = np.nan
    m = Measurements(df)
    assert m.df["time_s"].isna().all()


def test_trial_id_clash_between_sources():
    a = Measurements(table(1))
    b = Measurements(table(1).assign(source="rig"))
    with pytest.raises(MeasurementError, match="renumber_trials=True"):
        Measurements.concat([a, b])
    c = Measurements.concat([a, b], renumber_trials=True)
    assert sorted(c.df["trial"].unique()) == [0, 1, 2, 3]
    assert len(c) == len(a) + len(b)


def test_subset_and_concat():
    m = Measurements(table(4))
    s = m.subset([KEYS[2], KEYS[0]])
    assert s.design_keys == [KEYS[0], KEYS[2]]
    assert len(s) == 16
    with pytest.raises(MeasurementError, match="not in this table"):
        m.subset([KEYS[5]])
    back = Measurements.concat([m.subset([KEYS[0], KEYS[1]]), m.subset([KEYS[2], KEYS[3]])])
    pd.testing.assert_frame_equal(back.df, m.df)
    with pytest.raises(MeasurementError):
        Measurements.concat([])


# -- Parquet ------------------------------------------------------------------------------
def test_parquet_round_trip(tmp_path):
    df = table(3)
    df.loc[3, "time_s"] = np.nan
    df.loc[4, "height_set_mm"] = np.nan
    m = Measurements(df)
    path = tmp_path / "m.parquet"
    m.to_parquet(path)
    back = Measurements.from_parquet(path)
    pd.testing.assert_frame_equal(back.df, m.df)
    pd.testing.assert_frame_equal(read_parquet(path).df, m.df)
    assert [p.name for p in tmp_path.iterdir()] == ["m.parquet"]


def test_parquet_rejects_unknown_version_and_foreign_files(tmp_path):
    import pyarrow as pa
    import pyarrow.parquet as pq

    m = Measurements(table(2))
    t = pa.Table.from_pandas(m.df, preserve_index=False)
    pq.write_table(t.replace_schema_metadata({store.FORMAT_KEY: b"99"}), tmp_path / "v99.parquet")
    with pytest.raises(MeasurementError, match="version '99'"):
        read_parquet(tmp_path / "v99.parquet")
    pq.write_table(t.replace_schema_metadata({}), tmp_path / "plain.parquet")
    with pytest.raises(MeasurementError, match="not written by"):
        read_parquet(tmp_path / "plain.parquet")
    (tmp_path / "junk.parquet").write_bytes(b"not parquet")
    with pytest.raises(MeasurementError, match="not a readable Parquet"):
        read_parquet(tmp_path / "junk.parquet")


def test_atomic_write_leaves_no_partial_file(tmp_path, monkeypatch):
    m = Measurements(table(2))
    path = tmp_path / "m.parquet"

    def broken(table, where, **kw):
        where.write(b"PAR1 half a file")
        raise OSError("disk full")

    monkeypatch.setattr(pq, "write_table", broken)
    with pytest.raises(OSError, match="disk full"):
        write_parquet(m, path)
    assert list(tmp_path.iterdir()) == []  # neither target nor temporary file
    monkeypatch.undo()

    write_parquet(m, path)
    before = path.read_bytes()
    monkeypatch.setattr(pq, "write_table", broken)
    with pytest.raises(OSError):
        write_parquet(Measurements(table(3)), path)
    assert path.read_bytes() == before  # the old good file survives
    assert [p.name for p in tmp_path.iterdir()] == ["m.parquet"]


# -- k-fold -------------------------------------------------------------------------------
def test_kfold_properties():
    m = Measurements(table(7))
    folds = m.kfold(3, seed=0)
    assert len(folds) == 3
    tests = [set(te.design_keys) for _, te in folds]
    assert sorted(len(t) for t in tests) == [2, 2, 3]  # as even as possible
    assert set().union(*tests) == set(KEYS)  # cover all
    assert sum(len(t) for t in tests) == 7  # each membrane in exactly one test fold
    for (train, test), keys in zip(folds, tests):
        assert set(train.design_keys).isdisjoint(test.design_keys)
        assert set(train.design_keys) | keys == set(KEYS)
        assert len(train) + len(test) == len(m)
    again = [set(te.design_keys) for _, te in m.kfold(3, seed=0)]
    assert again == tests  # reproducible
    other = {tuple(sorted(te.design_keys)) for seed in range(1, 6) for _, te in m.kfold(3, seed=seed)}
    assert other != {tuple(sorted(t)) for t in tests}  # different seeds differ


def test_kfold_bad_k_and_leave_one_out():
    m = Measurements(table(3))
    with pytest.raises(MeasurementError, match="k = 4 folds but 3 membrane"):
        m.kfold(4, seed=0)
    with pytest.raises(MeasurementError, match="2 <= k"):
        m.kfold(1, seed=0)
    loo = m.leave_one_out()
    assert [te.design_keys for _, te in loo] == [[k] for k in KEYS[:3]]
    assert all(len(tr.design_keys) == 2 for tr, _ in loo)
    with pytest.raises(MeasurementError, match="at least 2 membranes"):
        Measurements(table(1)).leave_one_out()
