"""Sorted distinct values of integer arrays: ``np.unique(values)``, at a fraction of its cost.

NumPy 2's ``np.unique`` without ``return_*`` collects the values in a hash table and sorts them
afterwards; on the integer arrays o3dreg meets (node numbers, node-pair keys, vertex keys) it was
measured 10 to 45 times slower than one sort (80k int64: 16 ms against 1.4 ms; 1M: 860 ms against
19 ms). Values known to lie in a small range are marked on a bitmap instead (no sort at all).
"""

from __future__ import annotations

import numpy as np

__all__ = ["distinct"]

#: A bitmap of up to this many entries per value (or this floor) beats a sort.
_BITMAP_PER_VALUE = 16
_BITMAP_FLOOR = 1 << 16


def distinct(values: np.ndarray, bound: int | None = None) -> np.ndarray:
    """The sorted distinct values of ``values`` (flattened), as ``np.unique(values)`` gives them.

    ``bound``: all values lie in ``[0, bound)``, where the caller knows it (a bitmap then
    replaces the sort when the range is small).
    """
    v = np.asarray(values).ravel()
    if v.size == 0:
        return v.copy()
    if bound is not None and bound <= max(_BITMAP_PER_VALUE * v.size, _BITMAP_FLOOR):
        if v.min() < 0 or v.max() >= bound:
            raise ValueError(f"values must lie in [0, {bound}), got {v.min()}..{v.max()}")
        seen = np.zeros(int(bound), dtype=bool)
        seen[v] = True
        return np.flatnonzero(seen).astype(v.dtype, copy=False)
    s = np.sort(v)
    first = np.empty(s.size, dtype=bool)
    first[0] = True
    np.not_equal(s[1:], s[:-1], out=first[1:])
    return s[first]
