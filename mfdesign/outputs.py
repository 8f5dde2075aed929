"""Output files: atomic writes, and one run at a time per output folder.

Why atomic: a reader (a browser on ``index.html``, a script polling ``diagnosis.json``)
or a crash half-way through must never see a torn file. Every writer puts its bytes in a
temporary file beside the target (same folder, so same file system) and ``os.replace``s
it into place, which POSIX makes atomic.

Why a lock: two runs writing into one ``--out`` would mix their files. The lock is the
file ``OUT/.mfdesign.lock`` itself, created with ``O_CREAT | O_EXCL`` (atomic on POSIX and
Windows, unlike ``fcntl``, which is Unix-only) and holding the owner's pid and host; the
run removes it when it ends, so no output folder keeps one. A run killed outright leaves
it behind: the next run finds that pid gone (same host) and takes the lock over. Two runs
that take over one stale lock at the very same moment could both win (the check and the
removal are two steps); that needs a killed run and two new ones within microseconds.
"""

from __future__ import annotations

import contextlib
import json
import os
import socket
import stat
import tempfile
from pathlib import Path
from typing import Any, Iterator

from mfdesign.errors import InputError

__all__ = [
    "LOCK_NAME",
    "OutputLock",
    "atomic_path",
    "file_lock",
    "prepare_out_dir",
    "prepare_out_file",
    "refuse_inputs",
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
def _refuse_special(out: Path, option: str) -> None:
    """Refuse a path that exists and is neither a regular file nor a folder.

    Why: a write goes through a temporary file renamed onto the target, and a rename
    replaces whatever the name pointed at: run as root, ``--out /dev/full`` replaced the
    machine's device node with a regular file. A FIFO or a socket is no output either."""
    try:
        mode = os.stat(out).st_mode  # follows links: a link to a device is a device
    except FileNotFoundError:
        return
    except OSError as err:
        raise InputError(
            f"{option} {out}: cannot inspect it ({err.strerror or err}); allowed: a path you can write"
        ) from None
    if not (stat.S_ISREG(mode) or stat.S_ISDIR(mode)):
        kind = next((w for test, w in _SPECIAL if test(mode)), "not a regular file")
        raise InputError(f"{option} {out} is {kind}; allowed: a regular file or a folder")


_SPECIAL = (
    (stat.S_ISCHR, "a character device"),
    (stat.S_ISBLK, "a block device"),
    (stat.S_ISFIFO, "a FIFO (named pipe)"),
    (stat.S_ISSOCK, "a socket"),
)


def _name_max(folder: Path) -> int:
    try:
        return int(os.pathconf(folder if folder.is_dir() else ".", "PC_NAME_MAX"))
    except (OSError, ValueError):
        return 255


def _check_name_length(out: Path, option: str) -> None:
    """The temporary file beside the target (``.<name>.XXXXXXXX<suffix>``, :func:`atomic_path`)
    must fit the file system's name limit too, else the write fails after the computation."""
    longest = len(f".{out.name}.XXXXXXXX{out.suffix}".encode())
    limit = _name_max(out.parent)
    if len(out.name.encode()) > limit or longest > limit:
        raise InputError(
            f"{option}: the name {out.name[:40]!r}... is {len(out.name.encode())} bytes long; allowed: at most "
            f"{limit - len(out.suffix.encode()) - 10} bytes (the file system's limit, less room for a temporary name)"
        )


def refuse_inputs(out: str | os.PathLike, inputs, option: str = "--out") -> None:
    """Refuse an output that resolves to one of ``inputs`` (paths; missing ones ignored).

    Why: ``mfdesign import x.csv --out x.csv`` replaced the input CSV with Parquet bytes."""
    out = Path(out)
    if not out.exists():
        return
    for item in inputs:
        try:
            same = os.path.samefile(out, item)
        except (OSError, TypeError, ValueError):
            continue
        if same:
            raise InputError(f"{option} {out} is the input {item}; allowed: an output that is not one of the inputs")


def prepare_out_dir(out: str | os.PathLike, option: str = "--out") -> Path:
    """Create the output folder (and parents) or say in one line why it cannot be one."""
    out = Path(out)
    _refuse_special(out, option)
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


def prepare_out_file(out: str | os.PathLike, option: str = "--out", suffixes: tuple[str, ...] | None = None) -> Path:
    """Check that a single output file can be written (its folder is created).

    ``suffixes``: the file name endings the written format allows (the first one is what
    the message suggests); why: ``--out name.csv`` holding Parquet bytes misleads every
    later reader of the name."""
    out = Path(out)
    _refuse_special(out, option)
    if out.is_dir():
        raise InputError(f"{option} {out} is a folder; allowed: a file name (e.g. metrics.json)")
    if suffixes and out.suffix.lower() not in suffixes:
        raise InputError(
            f"{option} {out}: the name ends in {out.suffix or 'no suffix'!r} but the file written is "
            f"{suffixes[0].lstrip('.')}; allowed: a name ending in {' or '.join(suffixes)}"
        )
    _check_name_length(out, option)
    prepare_out_dir(out.parent, option=f"{option} folder")
    if out.exists() and not os.access(out, os.W_OK):
        raise InputError(f"{option} {out} is not writable; allowed: a file you can write")
    return out


def file_lock(out: str | os.PathLike, option: str = "--out") -> "OutputLock":
    """The lock of a single output file: ``.<name>.mfdesign.lock`` beside it (the file
    itself cannot carry the lock: the atomic write replaces its inode)."""
    out = Path(out)
    return OutputLock(out.parent, option, lock_name=f".{out.name}{LOCK_NAME}", shown=out)


def _read_owner(path: Path) -> tuple[str, str] | None:
    """``(pid, host)`` written in a lock file, or None when it is unreadable or half written."""
    try:
        parts = path.read_text().split()
    except (OSError, UnicodeDecodeError):
        return None
    return (parts[0], parts[1]) if len(parts) == 2 and parts[0].isdigit() else None


def _stale(owner: tuple[str, str]) -> bool:
    """Whether the run that wrote a lock is gone: same host and its pid no longer runs. A lock
    from another host (a shared folder) is never taken over: its pid means nothing here."""
    pid, host = int(owner[0]), owner[1]
    if host != socket.gethostname():
        return False
    if os.name == "nt":  # pragma: no cover -- os.kill(pid, 0) would terminate it on Windows
        import ctypes

        kernel32 = ctypes.windll.kernel32  # type: ignore[attr-defined]  # Windows only
        handle = kernel32.OpenProcess(0x1000, False, pid)  # PROCESS_QUERY_LIMITED_INFORMATION
        if not handle:
            return True
        code = ctypes.c_ulong()
        kernel32.GetExitCodeProcess(handle, ctypes.byref(code))
        kernel32.CloseHandle(handle)
        return code.value != 259  # STILL_ACTIVE
    try:
        os.kill(pid, 0)
    except ProcessLookupError:
        return True
    except PermissionError:  # alive, another user's
        return False
    return False


_HELD: set[Path] = set()  # lock files this process holds (OutputLock.reentrant)


class OutputLock:
    """Exclusive, non-blocking lock on an output folder, or on one file through
    :func:`file_lock` (see the module doc)."""

    def __init__(
        self,
        out: str | os.PathLike,
        option: str = "--out",
        lock_name: str = LOCK_NAME,
        shown: str | os.PathLike | None = None,
        reentrant: bool = False,
    ):
        self.out, self.option, self.lock_name = Path(out), option, lock_name
        self.reentrant = reentrant  # True: a lock this process holds already is taken as held
        self.shown = Path(shown) if shown is not None else self.out
        self._path: Path | None = None

    def acquire(self) -> "OutputLock":
        path = self.out / self.lock_name
        owner = f"{os.getpid()} {socket.gethostname()}"
        for _ in range(3):  # a stale lock taken over, then created again
            try:
                fd = os.open(path, os.O_WRONLY | os.O_CREAT | os.O_EXCL, 0o644)
            except FileExistsError:
                holder = _read_owner(path)
                if self.reentrant and path.resolve() in _HELD and holder == (str(os.getpid()), socket.gethostname()):
                    # held by this process already (the CLI locks a demo's --out, and the
                    # campaign the demo leaves there locks it again): nested, not a second
                    # run; the outer holder releases it
                    return self
                if holder is not None and not _stale(holder):
                    raise InputError(
                        f"{self.option} {self.shown} is in use by another mfdesign run (pid {holder[0]}); "
                        "allowed: one run per output at a time (wait for it, or choose another "
                        f"{self.option})"
                    ) from None
                with contextlib.suppress(FileNotFoundError):  # a killed run's lock (or one just released)
                    os.unlink(path)
                continue
            except OSError as err:
                raise InputError(
                    f"{self.option} {self.shown}: cannot create the lock file {self.lock_name} "
                    f"({err.strerror or err}); allowed: a folder you can write"
                ) from None
            with os.fdopen(fd, "w") as fh:
                fh.write(owner)
            self._path = path
            _HELD.add(path.resolve())
            return self
        raise InputError(f"{self.option} {self.shown}: could not take the lock {self.lock_name}; try again")

    def release(self) -> None:
        if self._path is not None:
            _HELD.discard(self._path.resolve())
            with contextlib.suppress(FileNotFoundError):
                os.unlink(self._path)  # the folder keeps no lock file once the run ends
            self._path = None

    def __enter__(self) -> "OutputLock":
        return self.acquire()

    def __exit__(self, *exc) -> None:
        self.release()
