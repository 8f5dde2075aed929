"""A user's own effects: Python files whose ``@register_effect`` classes join the library.

One loader for every place that takes such a file: ``mfdesign diagnose``, ``calibrate``
and ``fit-mf`` (``--effects-module FILE.py``, repeatable) and a campaign
(:meth:`mfdesign.campaign.Campaign.create`'s ``effects_module``, imported again by
:meth:`~mfdesign.campaign.Campaign.open`). Importing a file runs its code: treat one from
elsewhere as a script (docs/effects.md).

A folder that needs the effects later keeps copies of the files (:func:`keep`:
``effects/mN_NAME.py``, each with its sha256) and imports them again when it is read
(:func:`import_kept`): a campaign (records in ``campaign.json``) and the output folder of
``calibrate`` / ``fit-mf`` (records in ``effects/modules.json``, :func:`import_folder`,
which every ``--model DIR`` calls), so that neither depends on the user's file staying put.

It sits beside the physics (it imports only :mod:`mfdesign.errors` and the effects'
registry), so that the campaign and the workflows both reach it without importing upward.
"""

from __future__ import annotations

import json
import shutil
import sys
from pathlib import Path
from typing import Iterable, Sequence

from mfdesign.errors import InputError

__all__ = ["import_folder", "import_kept", "keep", "keep_in_output", "load_effects_module", "load_effects_modules"]

KEPT = "effects"  # the folder of the copies, in a campaign's or an output folder
RECORDS = "modules.json"  # an output folder's records, in KEPT (a campaign's are in campaign.json)
# Kept copies imported in this process: (resolved path, sha256) -> the effects each
# registered (every read checks the files; an unchanged one is not run again).
_IMPORTED: dict[tuple[str, str], tuple[str, ...]] = {}


def load_effects_module(path: str | Path, what: str = "--effects-module") -> tuple[str, ...]:
    """Import a user's effects file (its ``@register_effect`` classes join
    :data:`mfdesign.physics.effects.EFFECTS`).

    Arguments:
        path: a Python file (``.py``; its code runs).
        what: how the message names where the file came from (``--effects-module``).

    Returns the names of the effects the file registered (new, or registered again).
    Raises :class:`~mfdesign.errors.InputError` in one line for a missing file, a file
    that is not ``.py`` or one that fails to import (its error's type and message)."""
    import importlib.util

    from mfdesign.physics.effects import EFFECTS

    path = Path(path)
    if not path.is_file() or path.suffix != ".py":
        why = "no such file; " if not path.exists() else ""
        raise InputError(
            f"{what} {path}: not a Python file ({why}allowed: an existing .py file that registers effects)"
        )
    spec = importlib.util.spec_from_file_location(f"mfdesign_user_effects_{path.stem}", path)
    if spec is None or spec.loader is None:
        raise InputError(f"{what} {path}: not a Python file (allowed: an existing .py file that registers effects)")
    module = importlib.util.module_from_spec(spec)
    before = dict(EFFECTS)
    # registered, as importlib's recipe does: its classes are then found by name (pickle, and
    # the kernel store, which keys a kernel by the code of the modules its arguments come from)
    sys.modules[spec.name] = module
    try:
        spec.loader.exec_module(module)
    except Exception as err:  # noqa: BLE001 -- report any failure of the user's file in one line
        sys.modules.pop(spec.name, None)
        raise InputError(f"{what} {path} failed to import: {type(err).__name__}: {err}") from None
    return tuple(name for name, cls in EFFECTS.items() if before.get(name) is not cls)


def load_effects_modules(paths: Iterable[str | Path] | None, what: str = "--effects-module") -> tuple[str, ...]:
    """:func:`load_effects_module` for each of ``paths`` (None: none), in order; the names
    of the effects they registered."""
    names: list[str] = []
    for path in paths or []:
        names += load_effects_module(path, what)
    return tuple(dict.fromkeys(names))


def _sha256(path: Path) -> str:
    from mfdesign.provenance import sha256

    return sha256(path)


def keep(folder: Path, paths: Sequence[Path], registered: Sequence[Sequence[str]]) -> list[dict]:
    """Copy the effects files ``paths`` (already imported: ``registered`` are the names each
    registered) into ``folder/effects/`` as ``m0_NAME.py``, ``m1_NAME.py``, ...

    Returns their records: ``file`` (relative to ``folder``), ``sha256`` (of the copy),
    ``origin`` (the path given), ``effects`` (the names)."""
    records = []
    for i, (path, names) in enumerate(zip(paths, registered)):
        copy = Path(folder) / KEPT / f"m{i}_{Path(path).name}"
        copy.parent.mkdir(parents=True, exist_ok=True)
        shutil.copyfile(path, copy)
        digest = _sha256(copy)
        _IMPORTED[(str(copy.resolve()), digest)] = tuple(names)  # the bytes just imported
        file = str(copy.relative_to(folder))
        records.append({"file": file, "sha256": digest, "origin": str(path), "effects": list(names)})
    return records


def import_kept(folder: Path, records: Sequence[dict], what: str) -> None:
    """Import the kept copies of ``records`` (:func:`keep`) in ``folder``; an unchanged copy
    already imported in this process is not run again.

    Arguments:
        folder: the folder holding the copies.
        records: their records (``file``, ``sha256``, ``origin``, ``effects``).
        what: how the message names the folder (``campaign D``).

    Raises ``InputError`` in one line for a copy outside ``folder/effects/``, missing or
    changed (its sha256 differs), or that no longer registers its effects."""
    from mfdesign.physics.effects import EFFECTS

    for r in records:
        path = Path(folder) / r["file"]
        if path.resolve().parent != (Path(folder) / KEPT).resolve():  # a record never points elsewhere
            raise InputError(
                f"{what}: effects module {r['file']!r} is not in its {KEPT}/ folder; allowed: {KEPT}/NAME.py"
            )
        if not path.is_file() or _sha256(path) != r["sha256"]:
            raise InputError(
                f"{path}: {what}'s copy of the effects module {r['origin']} is missing or changed since it was "
                "kept (sha256 differs); allowed: the file as it was copied"
            )
        key = (str(path.resolve()), r["sha256"])
        if key not in _IMPORTED or any(e not in EFFECTS for e in r["effects"]):
            _IMPORTED[key] = load_effects_module(path, f"{what}: effects module")
        missing = [e for e in r["effects"] if e not in EFFECTS]
        if missing:
            raise InputError(f"{path} no longer registers {missing}; allowed: the file as it was copied")


def keep_in_output(folder: Path, paths: Sequence[Path], registered: Sequence[Sequence[str]]) -> None:
    """An output folder's copies (:func:`keep`) and their records, ``effects/modules.json``
    (no files: nothing written, and an earlier run's records are removed)."""
    record = Path(folder) / KEPT / RECORDS
    if not paths:
        record.unlink(missing_ok=True)
        return
    from mfdesign.outputs import write_json

    write_json(record, {"effects_modules": keep(folder, paths, registered)})


def import_folder(folder: Path) -> None:
    """Import the effects files an output folder keeps (``effects/modules.json``, written by
    ``calibrate`` / ``fit-mf``); nothing when it keeps none. ``InputError`` in one line for
    an unreadable record or a missing or changed copy."""
    record = Path(folder) / KEPT / RECORDS
    if not record.is_file():
        return
    try:
        records = json.loads(record.read_text())["effects_modules"]
        ok = isinstance(records, list) and all(
            isinstance(r, dict) and {"file", "sha256", "origin", "effects"} <= set(r) for r in records
        )
    except (ValueError, KeyError, TypeError, UnicodeDecodeError):
        ok = False
    if not ok:
        raise InputError(f"{record} is not a readable record of effects modules; allowed: the file fit-mf wrote")
    import_kept(folder, records, f"model folder {folder}")
