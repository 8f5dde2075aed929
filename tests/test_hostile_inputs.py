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


def test_class6_cache_dir_that_is_a_file_and_huge_weights(tmp_path, monkeypatch, small_csv):
    (tmp_path / "cache").write_text("x")
    monkeypatch.setenv("MFDESIGN_CACHE_DIR", str(tmp_path / "cache"))
    _one_line_exit2(_cli("simulate", "--out", tmp_path / "s"), "cannot be used: File exists")
    monkeypatch.delenv("MFDESIGN_CACHE_DIR")
    df = _spoil(_bundled_rows("force", 50), "weight", lambda c: c * 0 + 1e308)
    df.to_csv(tmp_path / "w.csv", index=False)
    _one_line_exit2(
        _cli("import", tmp_path / "w.csv", "--out", tmp_path / "w.parquet"), "column 'weight' reaches 1e+308"
    )


# -- class 3: forces the physical model cannot give --------------------------------------
def test_class3_a_force_above_p_pi_r2_is_never_ok():
    from mfdesign.physics.solve import PointSolution, _classify
    from mfdesign.physics.status import VALID, Status, force_bound_n

    p = np.array([7500.0, 7500.0, 10_000.0])
    bound = force_bound_n(p, 70.0)  # 115.5, 115.5, 153.9 N
    f = np.array([100.0, 122.0, 208.0])  # the 122 N at 7.5 kPa and 208 N at 10 kPa
    n = len(p)
    yes, no = np.ones(n, bool), np.zeros(n, bool)
    sol = PointSolution(yes, no, f, no, np.zeros(n), np.zeros(n), yes, np.zeros((n, 2)))
    res = _classify(np.zeros(n), p, sol)
    assert list(res.status) == [Status.OK, Status.OUTSIDE_MODEL, Status.OUTSIDE_MODEL]
    assert np.isnan(res.force_n[1:]).all() and Status.OUTSIDE_MODEL not in VALID and not res.ok[1:].any()
    assert "p pi R^2" in Status.OUTSIDE_MODEL.reason and bound[0] < 122.0
    signed = _classify(np.zeros(n), p, sol, signed=True)  # planes keep the number, the status says so
    assert list(signed.status) == list(res.status) and np.allclose(signed.force_n, f)


@pytest.mark.slow
def test_class3_simulate_marks_every_point_above_the_bound(tmp_path):
    import pandas as pd

    from mfdesign.physics.status import force_bound_n

    r = _cli("simulate", "--n-heights", "3", "--n-pressures", "5", "--out", tmp_path / "s")
    assert r.exit_code == 0, r.output
    t = pd.read_parquet(tmp_path / "s" / "plane.parquet")
    ok = t["status_name"] == "OK"
    assert (t.loc[ok, "force_n"] <= force_bound_n(t.loc[ok, "pressure_pa"], 70.0)).all()
    assert (t["status_name"] == "OUTSIDE_MODEL").sum() >= 4  # 7.5 and 10 kPa at every height


# -- fuzz over the classes (slow) ---------------------------------------------------------
_FUZZ_CHILD = """
import pickle, sys, time
from mfdesign.errors import InputError
from mfdesign.data.sources import read_source
for path in sys.argv[1:]:
    t0 = time.perf_counter()
    try:
        read_source(path)
        what = "ok"
    except (InputError, pickle.UnpicklingError):
        what = "refused"
    except BaseException as err:
        what = f"BUG {type(err).__name__}: {err}"[:200]
    print(path, round(time.perf_counter() - t0, 3), what, flush=True)
"""


def _mutants(rng, base: bytes, n: int) -> list[bytes]:
    """Pickles a byte or a few away from ``base``, and opcode soups built to nest and share."""
    out = []
    ops = [b"(", b")", b"\x85", b"\x86", b"\x87", b"t", b"]", b"}", b"e", b"a", b"s", b"u", b"l", b"d", b"0", b"2"]
    for _ in range(n):
        kind = rng.integers(4)
        data = bytearray(base)
        if kind == 0:  # flip bytes
            for i in rng.integers(2, len(data), size=rng.integers(1, 6)):
                data[i] = rng.integers(256)
        elif kind == 1:  # truncate
            data = data[: rng.integers(1, len(data))]
        elif kind == 2:  # splice opcodes after the protocol header
            at = int(rng.integers(2, len(data)))
            data[at:at] = b"".join(ops[i] for i in rng.integers(len(ops), size=rng.integers(1, 40)))
        else:  # a soup that nests, memoises and re-uses: tuples and lists as dict keys and values
            soup = b"\x80\x02}q\x00K\x01q\x01"
            parts = [b"h\x01", b"\x85", b"\x86", b"]", b"(h\x01h\x01t", b"q\x01", b"X\x01\x00\x00\x00a"]
            for _ in range(int(rng.integers(5, 400))):
                soup += parts[int(rng.integers(len(parts)))]
            data = bytearray(soup + b"s.")
        out.append(bytes(data))
    return out


@pytest.mark.slow
def test_fuzz_hostile_inputs(tmp_path):
    """Seeded: mutated and generated pickles (class 1), bad --out targets and corrupt tables
    (2, 5, 6), option values (6), API calls (7), classification of synthetic solver points
    (3), ports (8). Every probe ends in a result or one InputError line: no hang, no crash,
    no exit 1."""
    import os

    rng = np.random.default_rng(44)
    # class 1: in a child process, so that a crash fails the test instead of ending it
    base = _dict_pickle([DESIGN, "[1.5, 30.0, nan, nan, nan, nan]"], 40)
    paths = []
    for i, data in enumerate(_mutants(rng, base, 400) + [tuple_dag_key(int(k)) for k in rng.integers(5, 120, 20)]):
        paths.append(tmp_path / f"m{i}.pkl")
        paths[-1].write_bytes(data)
    run = subprocess.run(
        [sys.executable, "-c", _FUZZ_CHILD, *map(str, paths)], capture_output=True, text=True, timeout=600
    )
    assert run.returncode == 0, (run.returncode, run.stderr[-2000:])
    lines = run.stdout.strip().splitlines()
    assert len(lines) == len(paths)
    bugs = [line for line in lines if " BUG " in line]
    slow = [line for line in lines if float(line.split()[1]) > 5.0]
    assert not bugs and not slow, (bugs[:5], slow[:5])

    # classes 2, 5, 6: import with corrupt tables and bad outputs; exit 0 or one line exit 2
    df = _bundled_rows("force", 120)
    fifo = tmp_path / "fifo"
    os.mkfifo(fifo)
    outs = [tmp_path / "o.parquet", tmp_path / "o.csv", fifo, "/dev/null", tmp_path / ("x" * 300 + ".parquet")]
    spoilers = [
        lambda c: c * 1e-3,
        lambda c: c * 1e3,
        lambda c: -c,
        lambda c: c > c.median(),
        lambda c: c.astype(str).str.replace("0", "_0"),
        lambda c: c * np.nan,
        lambda c: c * np.inf,
        lambda c: c + 4e10,
        lambda c: c.sample(frac=1.0, random_state=1).to_numpy(),
    ]
    for i in range(60):
        column = rng.choice(["time_s", "height_mm", "height_set_mm", "pressure_pa", "force_n", "weight", "trial"])
        bad = _spoil(df, str(column), spoilers[int(rng.integers(len(spoilers)))])
        src = tmp_path / f"in{i}.csv"
        bad.to_csv(src, index=False)
        out = outs[int(rng.integers(len(outs)))] if rng.random() < 0.3 else tmp_path / f"out{i}.parquet"
        r = _cli("import", src, "--out", out)
        assert r.exit_code in (0, 2), r.output
        if r.exit_code == 2:
            assert len(r.output.strip().splitlines()) == 1, r.output

    # class 6: numeric options beyond their ranges are refused before any work
    from mfdesign.cli._contract import OPTION_MAX

    for i in range(40):
        name = str(rng.choice(["members", "batch", "seed"]))
        value = rng.choice([-(10 ** int(rng.integers(1, 12))), OPTION_MAX[name] + int(rng.integers(1, 10**9))])
        flag = {"members": "--members", "batch": "--batch", "seed": "--seed"}[name]
        _one_line_exit2(_cli("fit", small_csv_path(tmp_path, df), "--out", tmp_path / f"f{i}", flag, value), flag)

    # class 7: the API's bad input is an InputError
    import mfdesign

    m = mfdesign.Membrane(2.0, 25.4)
    for junk in (123, 1.5, None, {"a": 1}, b"bytes", object(), [1, 2]):
        with pytest.raises(InputError):
            mfdesign.load(junk)
    for grid in ([], (), np.zeros(0), "abc", [[]]):
        with pytest.raises(InputError):
            mfdesign.force_plane(m, grid, grid)

    # class 3: whatever the solver returns, an OK point never carries more than p pi R^2
    from mfdesign.physics.solve import PointSolution, _classify
    from mfdesign.physics.status import Status, force_bound_n

    n = 5000
    h, p = rng.uniform(-5, 90, n), rng.uniform(-100, 20e3, n)
    sol = PointSolution(
        converged=rng.random(n) < 0.9,
        passed=rng.random(n) < 0.05,
        force_n=rng.uniform(-50, 400, n),
        wrinkled=rng.random(n) < 0.2,
        locking=rng.uniform(0, 1.2, n),
        rise_mm=rng.uniform(0, 5, n),
        profile_ok=rng.random(n) < 0.95,
        state=np.zeros((n, 2)),
    )
    for signed in (False, True):
        res = _classify(h, p, sol, signed=signed)
        ok = np.asarray(res.status) == Status.OK
        assert np.all(np.asarray(res.force_n)[ok] <= force_bound_n(p[ok], 70.0) * (1 + 1e-6))
        outside = np.asarray(res.status) == Status.OUTSIDE_MODEL
        assert outside.any() and (signed or np.all(np.isnan(np.asarray(res.force_n)[outside])))

    # class 8: any --port string is accepted as a device/URL or refused as bad input
    from mfdesign.cli.rig import check_port

    for port in [
        "loop://",
        "LOOP://x",
        "/etc/passwd",
        "/",
        "/dev/null",
        "socket://h:1",
        "x" * 5000,
        "\\x00",
        "://",
        "a://b",
    ]:
        try:
            check_port(port)
        except InputError:
            pass


def small_csv_path(tmp_path, df):
    path = tmp_path / "fuzz_small.csv"
    if not path.exists():
        df.to_csv(path, index=False)
    return path


# -- class 4/6/7, second pass: diagnose --model and the Python API --------------------------
@pytest.fixture
def small_parquet(tmp_path):
    from mfdesign.data.sources import read_source

    path = tmp_path / "m.parquet"
    read_source("bundled").df.head(200).to_parquet(path)
    return path


@pytest.mark.parametrize("how, words", [("zeros", "predicts NaN or infinite forces"), ("beta", "predicts forces from")])
def test_class4_diagnose_refuses_a_model_predicting_nonsense(tmp_path, small_parquet, how, words):
    """Before: exit 0 and a report of n = 0 rows, RMSE NaN (zeros) or of absurd forces (beta)."""
    model = _spoilt_model(tmp_path / "model", how)
    r = _cli("diagnose", small_parquet, "--model", model, "--no-search", "--out", tmp_path / "d")
    _one_line_exit2(r, f"model {model} {words}")
    assert not (tmp_path / "d" / "diagnosis.json").exists()


def test_class7_diagnose_api_bad_input_is_input_error(small_parquet):
    """Before: AttributeError, KeyError, TypeError, numpy's UFuncTypeError or a broadcast
    ValueError from deep inside, or a silent run (theta naming no parameter, theta NaN)."""
    import mfdesign
    from mfdesign.diagnosis.forward import forward_model

    meas = mfdesign.load(small_parquet)
    sim = forward_model("standin", meas)
    D = mfdesign.diagnose
    for kw, words in [
        (dict(meas="bundled"), "allowed: a Measurements table"),
        (dict(meas=meas.df), "allowed: a Measurements table"),
        (dict(sim="exact"), "allowed: None or a ForwardModel"),
        (dict(effects=["nope"]), "no effect named 'nope'"),
        (dict(effects="pressure_sensor"), "allowed: a list of effect names"),
        (dict(effects=["pressure_sensor"], theta={"x.y": 1.0}), "no parameter 'x.y'"),
        (dict(effects=["pressure_sensor"], theta={"pressure_sensor.offset_pa": float("nan")}), "a finite number"),
        (dict(effects=["pressure_sensor"], theta={"pressure_sensor.offset_pa": "a"}), "a finite number"),
        (dict(theta=[1, 2]), "theta: a list"),
        (dict(model=123), "model: a int"),
        (dict(model=lambda m: np.zeros(3)), "returned 3 forces for 200 rows"),
        (dict(model=lambda m: np.full(len(m), np.nan)), "no finite force"),
        (dict(candidates=["nope"]), "no effect named 'nope'"),
        (dict(n_folds=0), "n_folds must be an integer from 2"),
        (dict(max_steps="a"), "max_steps must be an integer"),
    ]:
        args = {"meas": meas, "sim": sim, "search": False, **kw}
        with pytest.raises(InputError, match=__import__("re").escape(words)):
            D(args.pop("meas"), **args)


def test_class7_campaign_open_bad_input_is_input_error(tmp_path):
    import mfdesign

    for bad in (None, 123, 1.5):  # before: TypeError from pathlib
        with pytest.raises(InputError, match="allowed: a path"):
            mfdesign.Campaign.open(bad)
    (tmp_path / "c").mkdir()
    (tmp_path / "c" / "campaign.json").write_bytes(b"\xff\xfe\x00")
    with pytest.raises(InputError, match="not a readable campaign file"):
        mfdesign.Campaign.open(tmp_path / "c")


def test_class7_propose_api_bad_input_is_input_error():
    """Before: AttributeError (no predictor), ValueError, a JAX out-of-memory error (q = 1e9),
    TypeError from JAX's PRNG (key "a") or from Membrane (pending [123])."""
    import sys
    from pathlib import Path

    import mfdesign

    sys.path.insert(0, str(Path(__file__).parent))
    from tiny_models import tiny_ensemble

    from mfdesign.models.predictor import EnsemblePredictor

    pred = EnsemblePredictor(tiny_ensemble())
    for args, kw, words in [
        ((None,), dict(q=1), "predictor: a NoneType"),
        (("model",), dict(q=1), "predictor: a str"),
        ((tiny_ensemble(),), dict(q=1), "predictor: a Ensemble"),
        ((pred,), dict(q=0), "q (batch size) must be an integer >= 1"),
        ((pred,), dict(q=10**9), "q (batch size) must be an integer from 1 to 256"),
        ((pred,), dict(budget="rig"), "budget: 'rig'"),
        ((pred,), dict(q=1, fidelities="rig"), "fidelities: 'rig'"),
        ((pred,), dict(q=1, fidelities=("sim",)), "fidelity 'sim' not offered"),
        ((pred,), dict(q=1, costs={"rig": -1}), "must be a positive finite number"),
        ((pred,), dict(q=1, n_restarts=0), "n_restarts must be an integer from 1"),
        ((pred,), dict(q=1, n_rings=(5,)), "n_rings must be a non-empty subset"),
        ((pred,), dict(q=1, key="a"), "key: 'a'"),
        ((pred,), dict(q=1, pending=[123]), "pending:"),
        ((pred,), dict(q=1, grid="x"), "grid: a str"),
        ((pred,), dict(q=1, space="x"), "space: a str"),
    ]:
        with pytest.raises(InputError, match=__import__("re").escape(words)):
            mfdesign.propose(*args, n_restarts=kw.pop("n_restarts", 2), **kw)
