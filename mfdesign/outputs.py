"""Output files: atomic writes, and one run at a time per output folder.

Why atomic: a reader (a browser on ``report.html``, a script polling ``diagnosis.json``)
or a crash half-way through must never see a torn file. Every writer puts its bytes in a
temporary file beside the target (same folder, so same file system) and ``os.replace``s
it into place, which POSIX makes atomic.

Why a lock: two runs writing into one ``--out`` would mix their files. The lock is a
``fcntl.flock`` on ``OUT/.mfdesign.lock``: the OS drops it when the holding process dies,
so a killed run never leaves a stale lock behind. The file itself stays (deleting it
would let a third run lock a fresh inode while a second still holds the old one).
"""

from __future__ import annotations

import contextlib
import fcntl
import json
import os
import tempfile
from pathlib import Path
from typing import Any, Iterator

from mfdesign.errors import InputError

__all__ = [
    "LOCK_NAME",
    "OutputLock",
    "atomic_path",
    "prepare_out_dir",
    "prepare_out_file",
    "savefig",
    "write_bytes",
    "write_json",
    "write_text",
]

LOCK_NAME = ".mfdesign.lock"


def _umask() -> int:
    mask = os.umask(0)  # the only portable way to read it
    os.umask(mask)
    return mask


@contextlib.contextmanager
def atomic_path(path: str | os.PathLike, suffix: str | None = None) -> Iterator[Path]:
    """Yield a temporary path beside ``path``; on success it is renamed onto ``path``.

    ``suffix`` (default: ``path``'s own) keeps the extension, for writers that choose the
    format by it (matplotlib's ``savefig``, pandas). On an exception the temporary file is
    removed and ``path`` is untouched.
    """
    path = Path(path)
    fd, tmp = tempfile.mkstemp(
        dir=path.parent, prefix=f".{path.name}.", suffix=path.suffix if suffix is None else suffix
    )
    os.close(fd)
    try:
        yield Path(tmp)
        # mkstemp creates 0600; a result file gets the mode any other new file would (umask)
        with contextlib.suppress(FileNotFoundError):
            os.chmod(tmp, 0o666 & ~_umask())
        os.replace(tmp, path)
    except BaseException:
        with contextlib.suppress(FileNotFoundError):
            os.unlink(tmp)
        raise


def write_bytes(path: str | os.PathLike, data: bytes) -> Path:
    with atomic_path(path) as tmp:
        with open(tmp, "wb") as fh:
            fh.write(data)
            fh.flush()
            os.fsync(fh.fileno())
    return Path(path)


def write_text(path: str | os.PathLike, text: str) -> Path:
    return write_bytes(path, text.encode("utf-8"))


def write_json(path: str | os.PathLike, data: Any, **kwargs) -> Path:
    kwargs.setdefault("indent", 2)
    return write_text(path, json.dumps(data, **kwargs))


def savefig(fig, path: str | os.PathLike, **kwargs) -> Path:
    """``fig.savefig`` through a temporary file (the format follows ``path``'s suffix)."""
    path = Path(path)
    kwargs.setdefault("format", path.suffix.lstrip(".") or None)
    with atomic_path(path) as tmp:
        fig.savefig(tmp, **kwargs)
    return path


# -- checking outputs before any computation ----------------------------------------------
def prepare_out_dir(out: str | os.PathLike, option: str = "--out") -> Path:
    """Create the output folder (and parents) or say in one line why it cannot be one."""
    out = Path(out)
    if out.exists() and not out.is_dir():
        raise InputError(f"{option} {out} is an existing file, not a folder; allowed: a new or existing folder")
    try:
        out.mkdir(parents=True, exist_ok=True)
    except OSError as err:
        raise InputError(
            f"{option} {out}: cannot create the folder ({err.strerror or err}); allowed: a folder you can write"
        ) from None
    if not os.access(out, os.W_OK | os.X_OK):
        raise InputError(f"{option} {out} is not writable; allowed: a folder you can write")
    return out


def prepare_out_file(out: str | os.PathLike, option: str = "--out") -> Path:
    """Check that a single output file can be written (its folder is created)."""
    out = Path(out)
    if out.is_dir():
        raise InputError(f"{option} {out} is a folder; allowed: a file name (e.g. metrics.json)")
    prepare_out_dir(out.parent, option=f"{option} folder")
    if out.exists() and not os.access(out, os.W_OK):
        raise InputError(f"{option} {out} is not writable; allowed: a file you can write")
    return out


class OutputLock:
    """Exclusive, non-blocking lock on an output folder (see the module doc)."""

    def __init__(self, out: str | os.PathLike, option: str = "--out"):
        self.out, self.option = Path(out), option
        self._fd: int | None = None

    def acquire(self) -> "OutputLock":
        path = self.out / LOCK_NAME
        try:
            fd = os.open(path, os.O_RDWR | os.O_CREAT, 0o644)
        except OSError as err:
            raise InputError(
                f"{self.option} {self.out}: cannot create the lock file {LOCK_NAME} "
                f"({err.strerror or err}); allowed: a folder you can write"
            ) from None
        try:
            fcntl.flock(fd, fcntl.LOCK_EX | fcntl.LOCK_NB)
        except BlockingIOError:
            holder = os.read(fd, 64).decode(errors="replace").strip() or "?"
            os.close(fd)
            raise InputError(
                f"{self.option} {self.out} is in use by another mfdesign run (pid {holder}); "
                "allowed: one run per output folder at a time (wait for it, or choose another "
                f"{self.option})"
            ) from None
        os.ftruncate(fd, 0)
        os.write(fd, str(os.getpid()).encode())
        self._fd = fd
        return self

    def release(self) -> None:
        if self._fd is not None:
            os.close(self._fd)  # closing the descriptor drops the flock
            self._fd = None

    def __enter__(self) -> "OutputLock":
        return self.acquire()

    def __exit__(self, *exc) -> None:
        self.release()
