"""Rows padded to a few sizes, so that a few compiled shapes serve every call (issue 40).

A jitted function compiles once per input shape; callers with varying row counts pad them
to the next power of two by repeating the last row, then slice the result back. A repeated
row changes no number of the real rows (every use here is row-wise, or per membrane).
"""

from __future__ import annotations

import numpy as np

__all__ = ["bucketed_size", "padded_size", "pad_last"]


def padded_size(n: int, minimum: int = 1) -> int:
    """The smallest power of two >= ``n``, at least ``minimum``."""
    return max(minimum, 1 << (max(n, 1) - 1).bit_length())


def bucketed_size(n: int, minimum: int = 1) -> int:
    """``n`` rounded up to one of eight sizes per power of two (at most 1/8 more rows), at
    least ``minimum``: for large tables, where the next power of two nearly doubles the
    memory (the bundled data's 150,503 rows became 262,144 and a demo's peak RSS rose by
    ~200 MB, issue 40)."""
    step = max(minimum, padded_size(n, minimum) // 8)
    return -(-max(n, 1) // step) * step


def pad_last(a, size: int) -> np.ndarray:
    """``a`` (leading axis of length n <= size) with its last row repeated up to ``size`` rows."""
    a = np.asarray(a)
    return np.concatenate([a, np.repeat(a[-1:], size - len(a), axis=0)])
