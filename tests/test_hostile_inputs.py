"""Hostile inputs of issue 44, one class at a time: each test names its class.

Every probe is small and built here, as a user or an attacker would build it. A probe that
once hung or crashed the interpreter runs in a child process under a timeout, so that a
regression fails this test instead of taking the test run down with it."""

from __future__ import annotations

import pickle
import subprocess
import sys
import time

import numpy as np
import pytest

from mfdesign.errors import InputError

DESIGN = "[2.0, 25.4, nan, nan, nan, nan]"


# -- class 1: the restricted unpickler --------------------------------------------------
def tuple_dag_key(levels: int) -> bytes:
    """{key: 1} where key is tuple k = (tuple k-1, tuple k-1): a DAG of ``levels`` tuples
    in ~6 bytes a level; hashing it visits 2^levels nodes."""
    out = b"\x80\x02}" + b"K\x01\x85q\x00"  # PROTO 2; EMPTY_DICT; (1,); BINPUT 0
    for i in range(1, levels):
        out += b"h" + bytes([i - 1]) + b"h" + bytes([i - 1]) + b"\x86q" + bytes([i])  # TUPLE2; BINPUT i
    return out + b"K\x01s."  # value 1; SETITEM; STOP


def deep_tuple_key(depth: int) -> bytes:
    """{((((1,),),)...): 1}, ``depth`` levels: hashing it recurses ``depth`` deep in C."""
    return b"\x80\x02}K\x01" + b"\x85" * depth + b"K\x01s."


def _load_in_child(path, timeout: float = 60.0) -> subprocess.CompletedProcess:
    code = (
        "import sys\n"
        "from mfdesign.data.spa_design import restricted_load, UnsafePickleError\n"
        "try:\n    restricted_load(sys.argv[1])\n"
        "except UnsafePickleError as err:\n    print('REFUSED', err); sys.exit(2)\n"
    )
    return subprocess.run([sys.executable, "-c", code, str(path)], capture_output=True, text=True, timeout=timeout)


@pytest.mark.parametrize(
    "name, data, match",
    [
        ("dag", tuple_dag_key(100), "deeper than 32 levels"),
        ("shallow", tuple_dag_key(20), "tuple as a dict key"),
        ("deep", deep_tuple_key(400_000), "deeper than 32 levels|tuple as a dict key"),
    ],
)
def test_class1_tuple_keys_refused_without_hanging_or_crashing(tmp_path, name, data, match):
    path = tmp_path / f"{name}.pkl"
    path.write_bytes(data)
    assert len(data) < 500_000
    t0 = time.perf_counter()
    try:
        run = _load_in_child(path)
    except subprocess.TimeoutExpired:
        pytest.fail(f"{name}: the unpickler hung")
    assert run.returncode == 2, (run.returncode, run.stdout[-300:], run.stderr[-300:])  # not -11 (SIGSEGV)
    assert "REFUSED" in run.stdout and __import__("re").search(match, run.stdout), run.stdout
    assert time.perf_counter() - t0 < 30


def test_class1_memo_reuse_is_bounded():
    from mfdesign.data.spa_design import MAX_MEMO_GETS, UnsafePickleError, restricted_loads

    body = b"\x80\x02K\x01q\x00]q\x01(" + b"h\x00" * (MAX_MEMO_GETS + 1) + b"e."  # [1, 1, 1, ...] by memo
    with pytest.raises(UnsafePickleError, match="re-uses memoised objects"):
        restricted_loads(body)


def _dict_pickle(keys: list[str], rows: int) -> bytes:
    """SPA_Design data dictionary whose entries all share ONE value of ``rows`` rows."""
    us = np.tile(np.r_[0.0, 2.0, 25.4, np.nan, np.nan, np.nan, np.nan], (rows, 1))
    us[:, 0] = np.arange(rows) % 50
    value = ((us, np.full((rows, 1), 5e3)), np.full((rows, 1), 14.715), np.ones((rows, 1)))
    return pickle.dumps({k: value for k in keys}, protocol=4)


def test_class1_spellings_of_one_design_are_one_key(tmp_path):
    from mfdesign.data.sources import read_source

    spellings = [DESIGN, "[2, 25.4, nan, nan, nan, nan]", "[+2.0, 25.4, NaN, nan, nan, nan]"]
    path = tmp_path / "dupes.pkl"
    path.write_bytes(_dict_pickle(spellings, 60))
    for fmt in ("auto", "mass-lift", "characterisation"):
        with pytest.raises(InputError, match=r"are one design \[2.0, 25.4"):
            read_source(path, fmt)


def test_class1_rows_bounded_before_frames_are_built(tmp_path):
    from mfdesign.data import plausible
    from mfdesign.data.sources import read_source

    # 2,000 spellings of one design sharing one 10k-row value: 470 kB, 2e7 rows once expanded
    spellings = [f"[2.0,{' ' * k}25.4, nan, nan, nan, nan]" for k in range(2000)]
    path = tmp_path / "spellings.pkl"
    path.write_bytes(_dict_pickle(spellings, 10_000))
    t0 = time.perf_counter()
    with pytest.raises(InputError, match="one design"):
        read_source(path, "mass-lift")
    # distinct designs over one shared value: refused by the row bound, before any frame
    keys = [f"[{1.0 + k * 0.008:.3f}, 25.4, nan, nan, nan, nan]" for k in range(250)]
    path.write_bytes(_dict_pickle(keys, 10_000))
    assert 250 * 10_000 > plausible.MAX_ROWS
    for fmt in ("auto", "mass-lift", "characterisation"):
        with pytest.raises(InputError, match=f"allowed: at most {plausible.MAX_ROWS:,} rows"):
            read_source(path, fmt)
    assert time.perf_counter() - t0 < 20


# -- class 2: outputs that replace what they should not --------------------------------
def _cli(*args: str):
    from typer.testing import CliRunner

    from mfdesign.cli import app

    return CliRunner().invoke(app, [str(a) for a in args])


def _one_line_exit2(r, words: str) -> None:
    assert r.exit_code == 2, r.output
    assert len(r.output.strip().splitlines()) == 1, r.output
    assert words in r.output, r.output


@pytest.fixture
def small_csv(tmp_path):
    from mfdesign.data.sources import read_source

    path = tmp_path / "in.csv"
    read_source("bundled").df.head(200).to_csv(path, index=False)
    return path


def test_class2_out_that_is_no_regular_file_or_folder_is_refused(tmp_path, small_csv):
    import os

    fifo = tmp_path / "fifo"
    os.mkfifo(fifo)
    _one_line_exit2(_cli("import", small_csv, "--out", fifo), "is a FIFO (named pipe); allowed: a regular file")
    _one_line_exit2(_cli("import", small_csv, "--out", "/dev/null"), "is a character device")
    link = tmp_path / "link.json"
    link.symlink_to("/dev/null")
    _one_line_exit2(_cli("cv", small_csv, "--model-type", "curve-fit", "--out", link), "is a character device")
    _one_line_exit2(_cli("fit", small_csv, "--out", fifo), "is a FIFO")
    assert fifo.exists() and not fifo.is_file() and os.path.realpath(link) == "/dev/null"


def test_class2_out_that_is_an_input_or_the_wrong_suffix_is_refused(tmp_path, small_csv):
    parquet = tmp_path / "in.parquet"
    assert _cli("import", small_csv, "--out", parquet).exit_code == 0
    before = parquet.read_bytes()
    _one_line_exit2(_cli("import", parquet, "--out", parquet), "is the input")
    alias = tmp_path / "alias.parquet"
    alias.symlink_to(parquet)
    _one_line_exit2(_cli("import", alias, "--out", parquet), "is the input")
    assert parquet.read_bytes() == before
    before = small_csv.read_bytes()
    _one_line_exit2(_cli("import", small_csv, "--out", small_csv), "allowed: a name ending in .parquet")
    _one_line_exit2(_cli("import", small_csv, "--out", tmp_path / "x.csv"), "the file written is parquet")
    _one_line_exit2(_cli("cv", small_csv, "--out", tmp_path / "cv.parquet"), "allowed: a name ending in .json")
    assert small_csv.read_bytes() == before and not (tmp_path / "x.csv").exists()


def test_class2_a_file_output_is_locked_like_a_folder(tmp_path, small_csv):
    from mfdesign.outputs import file_lock

    out = tmp_path / "m.parquet"
    with file_lock(out):  # another run holds it
        _one_line_exit2(_cli("import", small_csv, "--out", out), "is in use by another mfdesign run")
    assert not out.exists()
    assert _cli("import", small_csv, "--out", out).exit_code == 0 and out.is_file()


# -- class 7: the Python API -------------------------------------------------------------
def test_class7_python_api_bad_input_is_input_error(tmp_path):
    import mfdesign
    from mfdesign.data.sources import read_source

    with pytest.raises(InputError, match="allowed"):
        mfdesign.load(123)
    m = mfdesign.Membrane(2.0, 25.4)
    with pytest.raises(InputError, match="allowed"):
        mfdesign.force_plane(m, [], [])
    with pytest.raises(InputError, match="does not exist"):
        read_source("bundled").to_parquet(tmp_path / "missing" / "m.parquet")
    with pytest.raises(FileNotFoundError):  # still one, for callers that catch it
        read_source("bundled").to_parquet(tmp_path / "missing" / "m.parquet")


# -- class 8: the rig's port --------------------------------------------------------------
@pytest.mark.parametrize(
    "port, words",
    [
        ("/etc/passwd", "is a regular file, not a serial device"),
        ("loop://", "pyserial's loopback"),
        ("/", "is a folder, not a serial device"),
    ],
)
def test_class8_a_port_that_is_no_rig_is_a_bad_argument(tmp_path, port, words):
    for command in (["characterize", "--heights", "0"], ["lift", "--mass-kg", "1"]):
        r = _cli("rig", *command, "--port", port, "--design", DESIGN, "--out", tmp_path / "job", "--no-progress")
        _one_line_exit2(r, words)
    assert not (tmp_path / "job").exists()


def test_class6_rig_out_that_cannot_be_a_job_folder(tmp_path):
    import os

    (tmp_path / "file").write_text("x")
    r = _cli("rig", "characterize", "--port", "/dev/null", "--design", DESIGN, "--out", tmp_path / "file")
    _one_line_exit2(r, "is an existing file, not a folder")
    if os.geteuid() != 0:  # root writes anywhere
        ro = tmp_path / "ro"
        ro.mkdir(mode=0o500)
        r = _cli("rig", "characterize", "--port", "/dev/null", "--design", DESIGN, "--out", ro / "job")
        _one_line_exit2(r, "cannot create the folder")


# -- class 5: silent wrong imports -------------------------------------------------------
def _bundled_rows(experiment: str, n: int = 300):
    from mfdesign.data.sources import read_source

    df = read_source("bundled").df
    df = df[df["experiment"] == experiment]
    first = df[["design_key", "trial"]].iloc[0]
    one = df[(df["design_key"] == first["design_key"]) & (df["trial"] == first["trial"])]
    return one.head(n).reset_index(drop=True)


def _spoil(df, column: str, how):
    df = df.copy()
    df[column] = how(df[column])
    return df


@pytest.mark.parametrize(
    "experiment, column, how, words",
    [
        ("force", "time_s", lambda c: c + 3.99e10, "looks like a clock time stamp"),
        ("force", "pressure_pa", lambda c: c > 3000, "holds True/False values"),
        ("force", "height_mm", lambda c: c / 1000, "looks like metres"),
        ("force", "pressure_pa", lambda c: c / 1000, "looks like kPa"),
        ("force", "pressure_pa", lambda c: -c - 9e3, "with a force of"),
        ("force", "force_n", lambda c: c * 0 + 999.0, "stays at one value through force trial"),
        ("lift", "force_n", lambda c: c + np.arange(len(c)) * 0.01, "changes within lift trial"),
    ],
)
def test_class5_implausible_columns_are_refused_naming_the_column(tmp_path, experiment, column, how, words):
    df = _spoil(_bundled_rows(experiment), column, how)
    path = tmp_path / "in.csv"
    df.to_csv(path, index=False)
    r = _cli("import", path, "--out", tmp_path / "m.parquet")
    _one_line_exit2(r, words)
    assert f"column {column!r}" in r.output
    df.to_parquet(tmp_path / "in.parquet")  # a plain Parquet table: the same checks
    _one_line_exit2(_cli("import", tmp_path / "in.parquet", "--out", tmp_path / "m.parquet"), words)


def test_class5_the_untouched_tables_still_import(tmp_path):
    for experiment in ("force", "lift"):
        _bundled_rows(experiment).to_csv(tmp_path / f"{experiment}.csv", index=False)
        r = _cli("import", tmp_path / f"{experiment}.csv", "--out", tmp_path / f"{experiment}.parquet")
        assert r.exit_code == 0, r.output


def _lift_pickle() -> bytes:
    """A mass-lift data dictionary: two masses, the height falling through 0..49 mm at each."""
    rows = 100
    us = np.tile(np.r_[0.0, 2.0, 25.4, np.nan, np.nan, np.nan, np.nan], (rows, 1))
    us[:, 0] = np.r_[np.arange(49, -1, -1), np.arange(49, -1, -1)]
    fs = np.r_[np.full(50, 14.715), np.full(50, 24.525)][:, None]
    ys = (3000.0 + 40.0 * us[:, 0])[:, None]
    return pickle.dumps({DESIGN: ((us, ys), fs, np.ones((rows, 1)))}, protocol=4)


def test_class5_format_cannot_turn_lifts_into_force_trials(tmp_path):
    path = tmp_path / "lift.pkl"
    path.write_bytes(_lift_pickle())
    assert _cli("import", path, "--out", tmp_path / "ok.parquet").exit_code == 0
    r = _cli("import", path, "--format", "characterisation", "--out", tmp_path / "m.parquet")
    _one_line_exit2(r, "--format characterisation, but the file holds mass-lift trials")
    assert not (tmp_path / "m.parquet").exists()


@pytest.mark.parametrize("text", ["1_000", "１２３"])
def test_class6_csv_numbers_pandas_cannot_read_are_bad_input(tmp_path, text):
    df = _bundled_rows("force", 20).astype({"pressure_pa": object})
    df.loc[3, "pressure_pa"] = text
    df.to_csv(tmp_path / "in.csv", index=False)
    _one_line_exit2(_cli("import", tmp_path / "in.csv", "--out", tmp_path / "m.parquet"), "column 'pressure_pa': row 3")


@pytest.mark.parametrize(
    "theta, words",
    [
        ('{"pressure_sensor.offset_pa": NaN}', "allowed: a finite number"),
        ('{"pressure_sensor.offset_pa": Infinity}', "allowed: a finite number"),
        ('{"pressure_sensor.offset_pa": "150"}', "allowed: a finite number"),
    ],
)
def test_class5_diagnose_theta_must_be_finite(tmp_path, theta, words):
    r = _cli("diagnose", "bundled", "--effects", "pressure_sensor", "--theta", theta, "--out", tmp_path / "d")
    _one_line_exit2(r, words)


@pytest.mark.parametrize(
    "toml, words",
    [
        ("effects = 3\n", "effects is 3; allowed: a string or a list of strings"),
        ("model = 5\n", "model is 5; allowed: a string"),
        ('[theta]\n"pressure_sensor.offset_pa" = "x"\n', "allowed: a finite number"),
        ("effects_module = [1]\n", "allowed: a string or a list of strings"),
    ],
)
def test_class6_config_of_wrong_types_is_bad_input(tmp_path, toml, words):
    (tmp_path / "c.toml").write_text(toml)
    r = _cli("diagnose", "bundled", "--config", tmp_path / "c.toml", "--out", tmp_path / "d")
    _one_line_exit2(r, words)


# -- class 6: options and files beyond what the machine can hold -------------------------
@pytest.mark.parametrize(
    "args, words",
    [
        (["propose", "--model", "m", "--q", "1000000"], "--q 1,000,000: allowed: 1 to 256"),
        (["fit", "bundled", "--out", "{tmp}/f", "--batch", "1000000000"], "--batch 1,000,000,000: allowed: at most"),
        (["calibrate", "bundled", "--out", "{tmp}/c", "--walkers", "100000"], "--walkers 100,000: allowed"),
        (["calibrate", "bundled", "--out", "{tmp}/c", "--mcmc-steps", "100000000"], "--mcmc-steps 100,000,000"),
        (["propose", "--model", "m", "--cost-sim", "nan"], "--cost-sim nan: allowed: a finite number"),
        (["fit", "bundled", "--out", "{tmp}/f", "--seed", "-1"], "--seed -1: allowed: 0 to"),
        (["simulate", "--out", "{tmp}/s", "--p-max-pa", "1e12"], "--p-max-pa"),
    ],
)
def test_class6_every_option_has_an_upper_bound(tmp_path, args, words):
    _one_line_exit2(_cli(*[a.format(tmp=tmp_path) for a in args]), words)


def test_class6_files_of_too_many_rows_are_refused_before_reading(tmp_path, monkeypatch, small_csv):
    from mfdesign.data import plausible, sources

    monkeypatch.setattr(plausible, "MAX_ROWS", 150)
    monkeypatch.setattr(sources, "MAX_ROWS", 150)
    _one_line_exit2(_cli("import", small_csv, "--out", tmp_path / "m.parquet"), "more than 150 rows")
    import pandas as pd

    pd.read_csv(small_csv).to_parquet(tmp_path / "big.parquet")
    _one_line_exit2(_cli("import", tmp_path / "big.parquet", "--out", tmp_path / "m.parquet"), "200 rows; allowed")


# -- class 4: models that load but predict nonsense --------------------------------------
def _spoilt_model(folder, how: str):
    import json
    import sys
    from pathlib import Path

    sys.path.insert(0, str(Path(__file__).parent))
    from tiny_models import tiny_ensemble

    import equinox as eqx
    import jax

    ens = tiny_ensemble()
    if how == "zeros":  # all-zero weights: NaN everywhere (the first probe)
        ens = jax.tree.map(lambda a: a * 0 if eqx.is_inexact_array(a) else a, ens)
    ens.save(folder)
    meta = json.loads((folder / "ensemble.json").read_text())
    if how == "beta":
        meta["beta"] = -1e9
    (folder / "ensemble.json").write_text(json.dumps(meta))
    return folder


@pytest.mark.parametrize("how, words", [("zeros", "NaN or infinite forces"), ("beta", "predicts forces from")])
def test_class4_a_model_predicting_nonsense_is_refused_naming_the_folder(tmp_path, how, words):
    model = _spoilt_model(tmp_path / "model", how)
    r = _cli(
        "optimize", "--model", model, "--target-set", "A", "--starts", "8", "--refine", "2", "--out", tmp_path / "o"
    )
    _one_line_exit2(r, f"model {model} {'predicts ' if 'NaN' in words else ''}{words}")
    r = _cli("propose", "--model", model, "--q", "1", "--restarts", "2", "--out", tmp_path / "p")
    _one_line_exit2(r, f"model {model}")
    assert "thickness must be finite" not in r.output


def test_class4_a_sound_model_passes_the_check(tmp_path):
    from mfdesign.models.ensemble import Ensemble
    from mfdesign.models.predictor import EnsemblePredictor
    from mfdesign.models.sanity import check_predictor

    model = _spoilt_model(tmp_path / "model", "none")
    predictor = EnsemblePredictor(Ensemble.load(model))
    assert check_predictor(predictor, str(model)) is predictor


# -- class 9: a config file runs code, and says so where --config is documented -----------
def test_class9_config_effects_module_is_documented_as_code():
    from pathlib import Path

    root = Path(__file__).resolve().parents[1]
    cli_md = root / "docs" / "cli.md"
    config_row = next(
        line for line in cli_md.read_text().splitlines() if line.startswith("| `--config` | option | TOML")
    )
    assert "runs the Python files" in config_row
    assert "A config file can run code" in (root / "docs" / "diagnose.md").read_text()
    r = _cli("diagnose", "--help")
    assert r.exit_code == 0 and "runs the Python files it names" in " ".join(r.output.replace("│", " ").split())
