"""Result files are written atomically and get the mode of any other new file."""

from __future__ import annotations

import os
import stat

import pytest

from mfdesign import outputs


def test_atomic_write_replaces_whole_and_respects_umask(tmp_path):
    old = os.umask(0o022)
    try:
        path = outputs.write_text(tmp_path / "a.txt", "one")
        outputs.write_text(path, "two")
    finally:
        os.umask(old)
    assert path.read_text() == "two"
    assert stat.S_IMODE(path.stat().st_mode) == 0o644  # mkstemp alone would leave 0600
    assert [p.name for p in tmp_path.iterdir()] == ["a.txt"]  # no temporary left behind


def test_failed_write_leaves_the_old_file(tmp_path):
    path = outputs.write_text(tmp_path / "a.txt", "old")
    with pytest.raises(RuntimeError):
        with outputs.atomic_path(path) as tmp:
            tmp.write_text("half")
            raise RuntimeError("crash mid-write")
    assert path.read_text() == "old"
    assert [p.name for p in tmp_path.iterdir()] == ["a.txt"]
