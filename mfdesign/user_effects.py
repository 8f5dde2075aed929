"""A user's own effects: Python files whose ``@register_effect`` classes join the library.

One loader for every place that takes such a file: ``mfdesign diagnose``, ``calibrate``
and ``fit-mf`` (``--effects-module FILE.py``, repeatable) and a campaign
(:meth:`mfdesign.campaign.Campaign.create`'s ``effects_module``, imported again by
:meth:`~mfdesign.campaign.Campaign.open`). Importing a file runs its code: treat one from
elsewhere as a script (docs/effects.md).

It sits beside the physics (it imports only :mod:`mfdesign.errors` and the effects'
registry), so that the campaign and the workflows both reach it without importing upward.
"""

from __future__ import annotations

from pathlib import Path
from typing import Iterable

from mfdesign.errors import InputError

__all__ = ["load_effects_module", "load_effects_modules"]


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
    try:
        spec.loader.exec_module(module)
    except Exception as err:  # noqa: BLE001 -- report any failure of the user's file in one line
        raise InputError(f"{what} {path} failed to import: {type(err).__name__}: {err}") from None
    return tuple(name for name, cls in EFFECTS.items() if before.get(name) is not cls)


def load_effects_modules(paths: Iterable[str | Path] | None, what: str = "--effects-module") -> tuple[str, ...]:
    """:func:`load_effects_module` for each of ``paths`` (None: none), in order; the names
    of the effects they registered."""
    names: list[str] = []
    for path in paths or []:
        names += load_effects_module(path, what)
    return tuple(dict.fromkeys(names))
