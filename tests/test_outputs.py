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


def test_the_lock_leaves_no_file_and_takes_over_a_killed_runs_lock(tmp_path):
    """The lock is the lock file itself (O_EXCL, portable; fcntl was Unix-only and left
    .mfdesign.lock in every output folder): gone once its run ends; a lock whose pid is dead
    on this host is taken over, a live one refuses, and a lock from another host is left
    alone (its pid means nothing here)."""
    import socket
    import subprocess
    import sys

    from mfdesign.errors import InputError

    lock_file = tmp_path / outputs.LOCK_NAME
    with outputs.OutputLock(tmp_path):
        assert lock_file.read_text().split() == [str(os.getpid()), socket.gethostname()]
        with pytest.raises(InputError, match=f"in use by another mfdesign run \\(pid {os.getpid()}\\)"):
            outputs.OutputLock(tmp_path).acquire()
    assert list(tmp_path.iterdir()) == []
    dead = subprocess.run([sys.executable, "-c", "import os; print(os.getpid())"], capture_output=True, text=True)
    lock_file.write_text(f"{int(dead.stdout)} {socket.gethostname()}")  # a run killed outright
    with outputs.OutputLock(tmp_path):
        assert lock_file.read_text().split()[0] == str(os.getpid())
    assert not lock_file.exists()
    lock_file.write_text(f"{int(dead.stdout)} another-host.example")
    with pytest.raises(InputError, match="in use"):
        outputs.OutputLock(tmp_path).acquire()
