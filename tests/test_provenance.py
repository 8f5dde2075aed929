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
