"""Hostile input at every command that reads files: one line + exit 2 (or success), never a
traceback, never a hang, never a silently wrong result, never a lost input.

In-process (typer's CliRunner: JAX compiles once for all cases) with a SIGALRM time limit
per case. The default run throws the issue's categories and a few random mutations (byte
flips, truncations) of each valid file; ``-m slow`` throws many more. The counts are
printed (``pytest -s``) and asserted.
"""

from __future__ import annotations

import hashlib
import json
import math
import pickle
import shutil
import signal
import time
from dataclasses import dataclass, field
from pathlib import Path

import numpy as np
import pytest
from typer.testing import CliRunner

from mfdesign.cli import app
from mfdesign.design import Membrane
from mfdesign.models.standin import standin_plane
from mfdesign.rig.virtual import Protocol, VirtualRig

runner = CliRunner()
KEYS = ("[2.0, 25.4, nan, nan, nan, nan]", "[1.5, 30.0, 45.0, 6.0, nan, nan]")
CASE_LIMIT_S = 60  # a case running longer counts as a hang


class Hang(BaseException):
    """Raised by SIGALRM; a BaseException so that no handler in mfdesign swallows it."""


@dataclass
class Tally:
    tried: int = 0
    ok: int = 0
    clean: int = 0
    tracebacks: list = field(default_factory=list)
    hangs: list = field(default_factory=list)
    silent_wrong: list = field(default_factory=list)
    data_lost: list = field(default_factory=list)
    messages: list = field(default_factory=list)  # the clean errors, shown with -s -v

    def line(self) -> str:
        return (
            f"fuzz: {self.tried} inputs tried, {self.ok} succeeded, {self.clean} clean errors, "
            f"{len(self.tracebacks)} tracebacks/unexpected, {len(self.hangs)} hangs, "
            f"{len(self.silent_wrong)} silent wrong results, {len(self.data_lost)} data lost"
        )


# -- fixtures: one valid file of each kind ----------------------------------------------
@pytest.fixture(scope="module")
def valid(tmp_path_factory):
    d = tmp_path_factory.mktemp("fuzz_valid")
    rig = VirtualRig(effects=[], seed=2, simulator=standin_plane, protocol=Protocol(sample_hz=0.5))
    m = rig.run([Membrane.from_key(k) for k in KEYS], progress=False)
    m.to_parquet(d / "m.parquet")
    for args in (
        [
            "fit",
            d / "m.parquet",
            "--out",
            d / "ens",
            "--members",
            2,
            "--train-steps",
            10,
            "--batch",
            16,
            "--no-monotone",
        ],
        [
            "fit-mf",
            d / "m.parquet",
            "--out",
            d / "mf",
            "--physics",
            "standin",
            "--mcmc-steps",
            12,
            "--members",
            2,
            "--delta-steps",
            5,
            "--max-rows",
            40,
        ],
    ):
        r = runner.invoke(app, [str(a) for a in args])
        assert r.exit_code == 0, r.output
    # a mass-lift pickle like the authors' (one membrane, three masses), in a shared-data folder
    key = KEYS[0]
    n = 60
    h = np.tile(np.linspace(40, 3, 20), 3)
    us = np.column_stack([h, np.tile(Membrane.from_key(key).to_array(), (n, 1))]).astype(np.float32)
    fs = np.repeat([14.715, 24.525, 39.24], 20)[:, None].astype(np.float32)
    ys = (2000 + 100 * fs + 50 * (40 - h[:, None])).astype(np.float32)
    ws = np.full((n, 1), 1000 / n, np.float32)
    (d / "shared").mkdir()
    (d / "shared" / "mass_lift_data_dictionary_N_Pa.pkl").write_bytes(
        pickle.dumps({key: ((us, ys), fs, ws)}, protocol=4)
    )
    return d


# -- running one case -------------------------------------------------------------------
def _digest(paths) -> dict:
    out = {}
    for p in paths:
        p = Path(p)
        for f in [p] if p.is_file() else sorted(p.rglob("*")) if p.is_dir() else []:
            if f.is_file() and f.name != ".mfdesign.lock":
                out[str(f)] = hashlib.sha256(f.read_bytes()).hexdigest()
    return out


def _finite(x) -> bool:
    return isinstance(x, (int, float)) and math.isfinite(x)


def _silently_wrong(args: list[str], out: Path | None) -> str | None:
    """What a successful run wrote that cannot be right (NaN where a number is promised)."""
    if out is None or not out.is_dir():
        return None
    if (out / "diagnosis.json").is_file():
        s = json.loads((out / "diagnosis.json").read_text())["before"]["summary"]
        if not (_finite(s.get("rmse_n")) and _finite(s.get("noise_floor_n"))):
            return f"diagnose RMSE {s.get('rmse_n')} noise floor {s.get('noise_floor_n')}"
    if (out / "proposal.json").is_file():
        s = json.loads((out / "proposal.json").read_text())
        if not all(_finite(v) for v in s.get("scores", [])):
            return f"propose scores {s.get('scores')}"
    if (out / "optimize.json").is_file():
        s = json.loads((out / "optimize.json").read_text())["prediction"]
        if not _finite(s.get("score_mm", s.get("traj_rmse"))):
            return f"optimize prediction {s}"
    return None


def run_case(tally: Tally, name: str, args: list, inputs=(), env=None, out: Path | None = None) -> str:
    args = [str(a) for a in args]
    before = _digest(inputs)
    tally.tried += 1

    def alarm(*_):
        raise Hang()

    old = signal.signal(signal.SIGALRM, alarm)
    signal.alarm(CASE_LIMIT_S)
    t0 = time.perf_counter()
    try:
        r = runner.invoke(app, args, env=env)
    except Hang:
        tally.hangs.append(name)
        return "hang"
    finally:
        signal.alarm(0)
        signal.signal(signal.SIGALRM, old)
    text = r.output
    lines = [ln for ln in text.replace("\r", "\n").splitlines() if ln.strip()]
    errors = [ln for ln in lines if ln.startswith("error:")]
    if _digest(inputs) != before:
        tally.data_lost.append(name)
    leftovers = [p.name for p in (out.iterdir() if out is not None and out.is_dir() else []) if p.name.endswith(".tmp")]
    if leftovers:
        tally.data_lost.append(f"{name}: temporary files left {leftovers}")
    if r.exit_code == 0:
        wrong = _silently_wrong(args, out)
        if wrong:
            tally.silent_wrong.append(f"{name}: {wrong}")
            return "wrong"
        tally.ok += 1
        return "ok"
    if r.exit_code == 2 and len(errors) == 1 and lines[-1] == errors[0] and "Traceback" not in text:
        tally.clean += 1
        tally.messages.append(f"{name}: {errors[0][:160]}")
        return "clean"
    tally.tracebacks.append(
        f"{name}: rc {r.exit_code} {lines[-1][:300] if lines else ''} "
        f"{type(r.exception).__name__ if r.exception else ''} ({time.perf_counter() - t0:.1f} s)"
    )
    return "bad"


# -- mutations --------------------------------------------------------------------------
def mutations(data: bytes, rng: np.random.Generator, n: int) -> list[tuple[str, bytes]]:
    out = []
    for k in range(n):
        kind = ("flip", "truncate", "zero-block")[k % 3]
        b = bytearray(data)
        if kind == "flip":
            for i in rng.integers(0, len(b), size=int(rng.integers(1, 9))):
                b[i] ^= 1 << int(rng.integers(0, 8))
        elif kind == "truncate":
            b = b[: int(rng.integers(0, len(b)))]
        else:
            i = int(rng.integers(0, len(b)))
            b[i : i + 64] = bytes(len(b[i : i + 64]))
        out.append((f"{kind}{k}", bytes(b)))
    return out


def _copy(src: Path, dst: Path) -> Path:
    if dst.exists():
        shutil.rmtree(dst) if dst.is_dir() else dst.unlink()
    (shutil.copytree if src.is_dir() else shutil.copy)(src, dst)
    return dst


# -- the cases --------------------------------------------------------------------------
def _propose_case(label: str, model: Path, out: Path) -> tuple:
    """A cheap ``propose`` on a (possibly corrupted) model folder: name, args, inputs, env, out
    (``--no-simulate``: no simulator check of the membrane, as optimize's ``--no-check``)."""
    args = ["propose", "--model", model, "--q", 1, "--restarts", 2, "--refine", 1, "--opt-steps", 0, "--no-simulate"]
    args += ["--out", out]
    return (label, args, [model], None, out)


def category_cases(v: Path, w: Path):
    """(name, args, inputs, env, out) for each category the issue lists."""
    import pandas as pd

    cases = []
    diag = lambda data, out, *more: ["diagnose", data, "--physics", "standin", "--no-search", "--out", out, *more]  # noqa: E731
    # unsafe / crafted pickles as the shared data
    evil = {
        "malicious": b"\x80\x02cos\nsystem\nX\x04\x00\x00\x00trueq\x85R.",
        "shared-lists": b"\x80\x02]q\x00"
        + b"0"
        + b"".join(
            b"]q" + bytes([i]) + b"(" + (b"h" + bytes([i - 1])) * 4 + b"e" + (b"0" if i < 24 else b"")
            for i in range(1, 25)
        )
        + b".",
        "huge-array": b"\x80\x02cnumpy.core.multiarray\n_reconstruct\ncnumpy\nndarray\nJ\x80\xc3\xc9\x01K\x07\x86U\x01f\x87R.",
        "set": pickle.dumps({"a": {1, 2}}, protocol=4),
        "list-not-dict": pickle.dumps([1, 2], protocol=4),
    }
    for name, payload in evil.items():
        sd = w / f"shared_{name}"
        sd.mkdir()
        (sd / "mass_lift_data_dictionary_N_Pa.pkl").write_bytes(payload)
        cases.append(
            (
                f"pickle {name} -> diagnose",
                diag("mass-lift", w / f"o_{name}"),
                [sd],
                {"MFDESIGN_SHARED_DATA": str(sd)},
                w / f"o_{name}",
            )
        )
    cases.append(
        (
            "missing shared data -> diagnose",
            diag("mass-lift", w / "o_ms"),
            [],
            {"MFDESIGN_SHARED_DATA": str(w / "nowhere")},
            None,
        )
    )
    cases.append(
        (
            "missing shared data -> fit",
            ["fit", "mass-lift", "--out", w / "o_msf"],
            [],
            {"MFDESIGN_SHARED_DATA": str(w / "nowhere")},
            None,
        )
    )
    # bad data tables
    (w / "x.parquet").mkdir()
    cases.append(("folder named x.parquet", diag(w / "x.parquet", w / "o_xp"), [], None, None))
    df = pd.read_parquet(v / "m.parquet")
    from mfdesign.data.measurements import Measurements

    tables = {
        "zero-rows": df.iloc[:0],
        "one-row": df.iloc[:1],
        "duplicated": pd.concat([df, df], ignore_index=True),
        "zero-weights": df.assign(weight=0.0),
    }
    for name, t in tables.items():
        Measurements(t).to_parquet(w / f"{name}.parquet")
        cases.append(
            (
                f"{name} -> diagnose",
                diag(w / f"{name}.parquet", w / f"o_{name}"),
                [w / f"{name}.parquet"],
                None,
                w / f"o_{name}",
            )
        )
        cases.append(
            (
                f"{name} -> calibrate",
                [
                    "calibrate",
                    w / f"{name}.parquet",
                    "--out",
                    w / f"oc_{name}",
                    "--physics",
                    "standin",
                    "--mcmc-steps",
                    3,
                ],
                [w / f"{name}.parquet"],
                None,
                w / f"oc_{name}",
            )
        )
    # outputs that cannot be written: refused before computing
    (w / "afile").write_text("keep me")
    cases.append(("simulate --out <a file>", ["simulate", "--out", w / "afile"], [w / "afile"], None, None))
    cases.append(
        ("diagnose --out <a file>", diag(v / "m.parquet", w / "afile"), [w / "afile", v / "m.parquet"], None, None)
    )
    # designs outside the product's space
    for key in (
        "[100.0, 25.4, nan, nan, nan, nan]",
        "[1e-06, 25.4, nan, nan, nan, nan]",
        "[1e308, 25.4, nan, nan, nan, nan]",
        "[2.0, 1e-06, nan, nan, nan, nan]",
    ):
        cases.append((f"simulate {key}", ["simulate", "--design", key, "--out", w / "o_sim"], [], None, None))
    # model folders: NaN weights, JSON list, missing keys, truncated leaves, empty posterior
    nan_ens = _copy(v / "ens", w / "ens_nan")
    import equinox as eqx
    import jax

    from mfdesign.models.ensemble import Ensemble

    model = Ensemble.load(v / "ens")
    model = jax.tree.map(lambda a: a * np.nan if eqx.is_inexact_array(a) else a, model)
    eqx.tree_serialise_leaves(nan_ens / "ensemble.eqx", model)
    list_ens = _copy(v / "ens", w / "ens_list")
    (list_ens / "ensemble.json").write_text("[1, 2]")
    nokey_ens = _copy(v / "ens", w / "ens_nokey")
    meta = json.loads((nokey_ens / "ensemble.json").read_text())
    del meta["normalisation"]
    (nokey_ens / "ensemble.json").write_text(json.dumps(meta))
    trunc_ens = _copy(v / "ens", w / "ens_trunc")
    (trunc_ens / "ensemble.eqx").write_bytes((v / "ens" / "ensemble.eqx").read_bytes()[:100])
    for ens in (nan_ens, list_ens, nokey_ens, trunc_ens):
        cases.append(
            (
                f"{ens.name} -> diagnose",
                diag(v / "m.parquet", w / f"od_{ens.name}", "--model", ens),
                [ens],
                None,
                w / f"od_{ens.name}",
            )
        )
        cases.append(_propose_case(f"{ens.name} -> propose", ens, w / f"op_{ens.name}"))
        cases.append(
            (
                f"{ens.name} -> optimize",
                [
                    "optimize",
                    "--model",
                    ens,
                    "--target-set",
                    "A",
                    "--starts",
                    2,
                    "--refine",
                    1,
                    "--opt-steps",
                    0,
                    "--no-check",
                    "--rings",
                    "0",
                    "--out",
                    w / f"oo_{ens.name}",
                ],
                [ens],
                None,
                w / f"oo_{ens.name}",
            )
        )
    nan_mf = _copy(v / "mf", w / "mf_nan")
    z = dict(np.load(nan_mf / "posterior.npz"))
    z["samples"] = z["samples"] * np.nan
    np.savez(nan_mf / "posterior.npz", **z)
    list_mf = _copy(v / "mf", w / "mf_list")
    (list_mf / "posterior.json").write_text("[]")
    for mf in (nan_mf, list_mf):
        cases.append(_propose_case(f"{mf.name} -> propose", mf, w / f"op_{mf.name}"))
    bad_chain = _copy(v / "mf", w / "chain_bad")
    (bad_chain / "chain.h5").write_bytes((v / "mf" / "chain.h5").read_bytes()[:2000])
    cases.append(
        (
            "truncated chain.h5 -> calibrate",
            [
                "calibrate",
                v / "m.parquet",
                "--out",
                bad_chain,
                "--physics",
                "standin",
                "--mcmc-steps",
                3,
                "--max-rows",
                40,
            ],
            [v / "m.parquet"],
            None,
            None,
        )
    )
    return cases


def mutation_cases(v: Path, w: Path, n: int, seed: int = 0):
    """Random mutations of each valid file, thrown at the commands that read it."""
    rng = np.random.default_rng(seed)
    cases = []
    diag = lambda data, out, *more: ["diagnose", data, "--physics", "standin", "--no-search", "--out", out, *more]  # noqa: E731
    for name, b in mutations((v / "m.parquet").read_bytes(), rng, n):
        p = w / f"m_{name}.parquet"
        p.write_bytes(b)
        cmd = (
            diag(p, w / f"om_{name}")
            if rng.uniform() < 0.7
            else ["cv", p, "--model-type", "curve-fit", "--out", w / f"cv_{name}.json"]
        )
        cases.append((f"parquet {name} -> {cmd[0]}", cmd, [p], None, w / f"om_{name}"))
    for fname in ("ensemble.eqx", "ensemble.json"):
        for name, b in mutations((v / "ens" / fname).read_bytes(), rng, n):
            ens = _copy(v / "ens", w / f"ens_{fname}_{name}")
            (ens / fname).write_bytes(b)
            cases.append(
                (
                    f"{fname} {name} -> diagnose --model",
                    diag(v / "m.parquet", w / f"oe_{fname}_{name}", "--model", ens),
                    [ens],
                    None,
                    w / f"oe_{fname}_{name}",
                )
            )
    for fname in ("posterior.npz", "posterior.json", "mf.json"):
        for name, b in mutations((v / "mf" / fname).read_bytes(), rng, max(1, n // 2)):
            mf = _copy(v / "mf", w / f"mf_{fname}_{name}")
            (mf / fname).write_bytes(b)
            cases.append(_propose_case(f"{fname} {name} -> propose", mf, w / f"opm_{fname}_{name}"))
    for name, b in mutations((v / "mf" / "chain.h5").read_bytes(), rng, n):
        out = _copy(v / "mf", w / f"ch_{name}")
        (out / "chain.h5").write_bytes(b)
        cases.append(
            (
                f"chain.h5 {name} -> fit-mf",
                [
                    "fit-mf",
                    v / "m.parquet",
                    "--out",
                    out,
                    "--physics",
                    "standin",
                    "--mcmc-steps",
                    12,
                    "--members",
                    2,
                    "--delta-steps",
                    5,
                    "--max-rows",
                    40,
                ],
                [v / "m.parquet"],
                None,
                None,
            )
        )
    pkl = (v / "shared" / "mass_lift_data_dictionary_N_Pa.pkl").read_bytes()
    for name, b in mutations(pkl, rng, n):
        sd = w / f"sh_{name}"
        sd.mkdir()
        (sd / "mass_lift_data_dictionary_N_Pa.pkl").write_bytes(b)
        cases.append(
            (
                f"pickle {name} -> diagnose",
                diag("mass-lift", w / f"osh_{name}"),
                [sd],
                {"MFDESIGN_SHARED_DATA": str(sd)},
                w / f"osh_{name}",
            )
        )
    return cases


def _run_all(valid, tmp_path, n_mutations):
    tally = Tally()
    t0 = time.perf_counter()
    for name, args, inputs, env, out in category_cases(valid, tmp_path) + mutation_cases(valid, tmp_path, n_mutations):
        run_case(tally, name, args, inputs, env, out)
    print(f"\n{tally.line()} in {time.perf_counter() - t0:.0f} s")
    for kind in ("messages", "tracebacks", "hangs", "silent_wrong", "data_lost"):
        for item in getattr(tally, kind):
            print(f"  {kind}: {item}")
    assert not (tally.tracebacks or tally.hangs or tally.silent_wrong or tally.data_lost), tally.line()
    return tally


def test_fuzz_every_reading_command(valid, tmp_path):
    tally = _run_all(valid, tmp_path, n_mutations=3)
    assert tally.clean >= 40


@pytest.mark.slow
def test_fuzz_every_reading_command_long(valid, tmp_path):
    _run_all(valid, tmp_path, n_mutations=30)
