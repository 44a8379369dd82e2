"""o3dreg's compiled kernels (``o3dreg/_kernels.c``), loaded with ctypes and spread over the cores.

The kernels are plain C, built with the package (``setup.py``) and called through ctypes, which
releases the GIL for the length of each call: the rigid step's ICP threads and the registration
keep running beside them, and nothing is paid at start-up beyond loading a small library. Each
kernel answers a range ``[begin, end)`` of independent queries; :func:`split` runs the ranges
of one call on a small pool of Python threads, so every answer is computed by the same code
whatever the number of threads (results are identical run to run).
"""

from __future__ import annotations

import ctypes
import importlib.util
import os
import threading
from collections.abc import Callable
from concurrent.futures import ThreadPoolExecutor
from typing import Any

import numpy as np

__all__ = ["library", "split"]

#: Queries below this many per thread run on the calling thread (a thread's start and join
#: cost more than a few hundred queries).
MIN_PER_THREAD = 512

#: The same for kernels of a few arithmetic operations per item (cross products, the trilinear
#: field, the boundary test): a thread's hand-over costs tens of microseconds, and on a loaded
#: machine milliseconds, more than tens of thousands of such items.
MIN_PER_THREAD_CHEAP = 1 << 15

_int = ctypes.c_int64
_double = ctypes.c_double


def _array(dtype: Any) -> Any:
    return np.ctypeslib.ndpointer(dtype=dtype, flags="C_CONTIGUOUS")


_f8, _i8, _i4, _u1 = (_array(t) for t in (np.float64, np.int64, np.int32, np.uint8))

#: Argument types of each kernel, checked by ctypes at every call (dtype and contiguity).
_SIGNATURES: dict[str, tuple[Any, list[Any]]] = {
    "o3dreg_bvh_build": (
        _int,
        [_f8, _i8, _int, _int, _int, _i8, _f8, _u1, _i8, _i8, _i8, _f8],
    ),
    "o3dreg_bvh_query": (
        None,
        [_f8, _u1, _i8, _i8, _i8, _i8, _i8, _f8, _f8, _i8, _f8, _i8, _f8, _int, _int],
    ),
    "o3dreg_grid_build": (_int, [_f8, _int, _f8, _double, _i8, _i8, _i8]),
    "o3dreg_grid_nearest_two": (
        None,
        [_f8, _i8, _i8, _f8, _double, _i8, _f8, _f8, _i8, _int, _int],
    ),
    "o3dreg_lattice_field": (None, [_f8, _f8, _i8, _f8, _f8, ctypes.c_int, _f8, _int, _int]),
    "o3dreg_damped_cg": (_int, [_int, _i4, _i4, _f8, _f8, _f8, _double, _int, _f8]),
    "o3dreg_face_cross": (None, [_f8, _i8, ctypes.c_int, _f8, _int, _int]),
    "o3dreg_beyond_boundary": (
        None,
        [_f8, _i8, _u1, _u1, _u1, _f8, _i8, _f8, _double, _u1, _int, _int],
    ),
    "o3dreg_pair_sums": (None, [_int, _i8, _i4, _f8, _f8, _int, _int, _i8, _f8, _f8]),
    "o3dreg_ply_walk": (
        _int,
        [_u1, _int, _int, ctypes.c_int, ctypes.c_int, ctypes.c_int, ctypes.c_int],
    ),
    "o3dreg_grid_reassign": (
        None,
        [_f8, _i8, _i8, _f8, _double, _i8, _f8, _f8, _double, ctypes.c_int]
        + [_i8, _f8, _f8, _f8, _f8, _int, _int],
    ),
}


def _load() -> ctypes.CDLL:
    spec = importlib.util.find_spec("o3dreg._kernels")
    if spec is None or spec.origin is None or not os.path.isfile(spec.origin):
        raise ImportError(
            "o3dreg's compiled kernels (o3dreg/_kernels.c) are not built: install the package "
            "with pip (`pip install -e .` in a source checkout; a C compiler is needed)"
        )
    lib = ctypes.CDLL(spec.origin)
    for name, (restype, argtypes) in _SIGNATURES.items():
        function = getattr(lib, name)
        function.restype = restype
        function.argtypes = argtypes
    return lib


#: The loaded library; its functions are declared in ``o3dreg/_kernels.c``.
library = _load()

_pool: ThreadPoolExecutor | None = None
_pool_lock = threading.Lock()


def _forget_pool() -> None:
    """In a forked child: the parent's threads do not exist there; a new pool starts on use."""
    global _pool, _pool_lock
    _pool, _pool_lock = None, threading.Lock()


if hasattr(os, "register_at_fork"):  # POSIX: where fork exists
    os.register_at_fork(after_in_child=_forget_pool)


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


def split(kernel: Callable[..., Any], count: int, *args: Any, cheap: bool = False) -> None:
    """Run ``kernel(*args, begin, end)`` over ``[0, count)``, in one range per core, each of at
    least :data:`MIN_PER_THREAD` items (:data:`MIN_PER_THREAD_CHEAP` for a ``cheap`` kernel)."""
    least = MIN_PER_THREAD_CHEAP if cheap else MIN_PER_THREAD
    parts = min(_threads(), count // max(least, 1))
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
