"""A large batch of library queries answered in two halves, one on a worker thread.

SciPy's k-d tree releases the GIL while it searches, so the two halves run at once on two cores
(libigl's AABB build holds the GIL, so building a tree ahead on a worker gains nothing). The
worker belongs to a non-daemon pool, which the interpreter joins at exit, so no worker is still
reading arrays while it shuts down (SciPy's own ``workers=`` threads are daemons); a process
forked from this one makes its own worker.
"""

from __future__ import annotations

import os
from collections.abc import Callable
from concurrent.futures import ThreadPoolExecutor
from typing import Any

import numpy as np

__all__ = ["in_halves"]

#: Below this many queries a batch is answered on the calling thread: handing half of it to
#: the worker costs more than that half takes.
MIN_SPLIT = 4096

_pool: ThreadPoolExecutor | None = None


def _forget_pool() -> None:
    global _pool
    _pool = None  # the parent's worker thread does not exist in a forked child


if hasattr(os, "register_at_fork"):
    os.register_at_fork(after_in_child=_forget_pool)


def _usable_cores() -> int:
    if hasattr(os, "sched_getaffinity"):
        return len(os.sched_getaffinity(0))
    return os.cpu_count() or 1


def _worker() -> ThreadPoolExecutor:
    global _pool
    if _pool is None:
        _pool = ThreadPoolExecutor(1, thread_name_prefix="o3dreg-half")
    return _pool


def in_halves(
    query: Callable[[np.ndarray], tuple[Any, ...]], points: np.ndarray
) -> tuple[np.ndarray, ...]:
    """``query(points)``, with the second half of a large batch on a worker thread.

    ``query`` must release the GIL while it works and return arrays whose first axis follows
    the points; the halves' results are concatenated in order, so the answer is the same as
    one call's.
    """
    n = points.shape[0]
    if n < MIN_SPLIT or _usable_cores() < 2:
        return query(points)
    half = n // 2
    second = _worker().submit(query, points[half:])
    try:
        first = query(points[:half])
    finally:
        # The worker reads arrays this call owns: wait for it even when interrupted.
        rest = second.result()
    return tuple(np.concatenate([a, b]) for a, b in zip(first, rest))
