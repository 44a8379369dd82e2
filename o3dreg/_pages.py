"""NumPy's transparent-huge-page advice, off while o3dreg works on large meshes.

NumPy advises the kernel to back arrays of 4 MB and more with transparent huge pages
(``madvise``). Where the kernel then compacts memory to find them on the first touch of each
fresh array (``/sys/kernel/mm/transparent_hugepage/defrag`` set to ``madvise``, the common
default), a registration onto a million-vertex target, which allocates and frees hundreds of
such temporaries, spent a third of its time there: measured 8.8 s against 5.8 s with the advice
off, same code, on the 2-core VM of docs/benchmarks.md. The environment variable
``NUMPY_MADVISE_HUGEPAGE=0`` does the same for a whole process; :func:`small_pages` does it for
the duration of one call and restores the caller's setting afterwards (re-entrant and
thread-safe: nested or concurrent calls restore it once, when the last one leaves).
"""

from __future__ import annotations

import importlib
from collections.abc import Callable, Iterator
from contextlib import contextmanager

from ._held import HeldSetting


def _switch() -> Callable[[bool], bool] | None:
    """NumPy's ``_set_madvise_hugepage`` (sets the advice, returns the previous setting), or
    ``None`` where this NumPy has none."""
    for module in ("numpy._core.multiarray", "numpy.core.multiarray"):  # NumPy 2, then 1
        try:
            return getattr(importlib.import_module(module), "_set_madvise_hugepage", None)
        except ImportError:  # pragma: no cover
            continue
    return None  # pragma: no cover


_set_madvise_hugepage = _switch()

__all__ = ["small_pages"]


def _held_advice() -> HeldSetting | None:
    switch = _set_madvise_hugepage
    return None if switch is None else HeldSetting(lambda: switch(False), switch)


_advice = _held_advice()


@contextmanager
def small_pages() -> Iterator[None]:
    """Switch NumPy's huge-page advice off inside the block (a no-op where NumPy has no switch);
    usable as a decorator."""
    if _advice is None:  # pragma: no cover
        yield
        return
    with _advice.held():
        yield
