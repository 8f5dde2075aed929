"""mfdesign.provenance: what made an output (issue 41 item 6)."""

from __future__ import annotations

import hashlib

from mfdesign.provenance import input_hashes, provenance


def test_inputs_are_hashed_whatever_form_they_take(tmp_path):
    f = tmp_path / "m.csv"
    f.write_bytes(b"a,b\n1,2\n")
    job = tmp_path / "job"
    job.mkdir()
    (job / "samples.csv").write_bytes(b"x\n")
    got = input_hashes([f, str(job), "bundled", object()])
    assert got[str(f)] == hashlib.sha256(b"a,b\n1,2\n").hexdigest()
    assert got[str(job / "samples.csv")] == hashlib.sha256(b"x\n").hexdigest()
    assert got["bundled"] == "(named source)" and got["<object>"] == "(in memory)"
    rec = provenance("mfdesign test", {"seed": 3}, got)
    assert rec["seeds"] == {"seed": 3} and rec["inputs_sha256"] == got and rec["machine"]["cores"] >= 1


def test_the_call_is_the_command_line_only_under_mfdesign(monkeypatch):
    """``mfdesign ...`` and ``python -m mfdesign.cli ...`` give the command line; any other
    program (``python -m pytest``: its ``__main__.py`` too) the Python call's description."""
    from mfdesign.provenance import call_line

    monkeypatch.setattr("sys.argv", ["/venv/bin/mfdesign", "fit-mf", "a b.csv"])
    assert call_line("f()") == "mfdesign fit-mf 'a b.csv'"
    monkeypatch.setattr("sys.argv", ["/src/mfdesign/cli/__main__.py", "status", "D"])
    assert call_line("f()") == "mfdesign status D"
    monkeypatch.setattr("sys.argv", ["/venv/lib/python3.12/site-packages/pytest/__main__.py", "-q"])
    assert call_line("f()") == "f()"
    monkeypatch.setattr("sys.argv", [""])
    assert call_line("f()") == "f()"
