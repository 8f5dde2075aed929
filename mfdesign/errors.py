"""The one exception type for bad input, and the list of those the CLI treats alike.

The CLI promises: bad input prints ONE line naming what was wrong and what is allowed,
and exits with status 2 (see :mod:`mfdesign.cli._contract`). Library code signals such
input by raising :class:`InputError` (or a subclass: each module's own bad-input type);
anything else escaping a command is a bug and gets a log file.
"""

from __future__ import annotations

__all__ = ["InputError", "anticipated", "one_line"]


class InputError(ValueError):
    """Bad input (file, folder, option, design); the message says what and what is allowed.

    A ``ValueError`` so that callers that already catch ``ValueError`` keep working.
    """


def anticipated() -> tuple[type[BaseException], ...]:
    """Exception types whose message is fit for the terminal as it is (exit status 2).

    Every module's own bad-input type (``DesignError``, ``MeasurementError``, ...) is an
    :class:`InputError`, so this module imports nothing of the package (errors flow up
    from every layer; the import does not flow down). A corrupt pickle from the standard
    library's unpickler counts too.
    """
    import pickle

    return (InputError, pickle.UnpicklingError)


def one_line(text: object, limit: int = 600) -> str:
    """Collapse a message onto one line (tracebacks of nested errors must not leak)."""
    s = " ".join(str(text).split())
    return s if len(s) <= limit else s[: limit - 3] + "..."
