"""How o3dreg's compiled kernels are compiled and spread over the cores.

The kernels (:mod:`o3dreg._bvh`, :mod:`o3dreg._nearest`) are Numba functions compiled once per
installation (``cache=True``: the machine code is kept beside the sources, or in Numba's user
cache where those are read-only) and run without the GIL. Each answers a range ``[begin, end)``
of independent queries; :func:`split` runs the ranges of one call on a small pool of Python
threads, so every answer is computed by the same code whatever the number of threads (results
are identical run to run), and calls from several threads at once (the rigid step's candidate
search) are safe without a thread-safe Numba threading layer.
"""

from __future__ import annotations

import os
import threading
from collections.abc import Callable
from concurrent.futures import ThreadPoolExecutor
from typing import Any

__all__ = ["JIT", "split"]

#: Options of every kernel: compiled to a file once, run without the GIL, NumPy's float
#: semantics (a division by zero gives inf or NaN, not an exception).
JIT: dict[str, Any] = {"nogil": True, "cache": True, "error_model": "numpy"}

#: Queries below this many per thread run on the calling thread (a thread's start and join
#: cost more than a few hundred queries).
MIN_PER_THREAD = 512

_pool: ThreadPoolExecutor | None = None
_pool_lock = threading.Lock()


def _threads() -> int:
    try:
        return max(1, len(os.sched_getaffinity(0)))
    except AttributeError:  # not on Linux
        return max(1, os.cpu_count() or 1)


def _executor() -> ThreadPoolExecutor:
    global _pool
    with _pool_lock:
        if _pool is None:
            _pool = ThreadPoolExecutor(_threads(), thread_name_prefix="o3dreg-kernel")
        return _pool


def split(kernel: Callable[..., None], count: int, *args: Any) -> None:
    """Run ``kernel(*args, begin, end)`` over ``[0, count)``, in one range per core."""
    parts = min(_threads(), count // MIN_PER_THREAD)
    if parts <= 1:
        kernel(*args, 0, count)
        return
    bounds = [count * k // parts for k in range(parts + 1)]
    pool = _executor()
    futures = [pool.submit(kernel, *args, bounds[k], bounds[k + 1]) for k in range(1, parts)]
    # The calling thread answers the first range itself.
    kernel(*args, bounds[0], bounds[1])
    for future in futures:
        future.result()
