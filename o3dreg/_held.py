"""A process-wide setting held at one value while any caller needs it.

Some libraries keep a setting for the whole process (NumPy's huge-page advice, Open3D's thread
count). A call that needs it changed must restore the caller's value afterwards, and two such
calls that overlap (nested, or in two threads) must not restore it while the other still runs:
the first to enter saves the caller's value and the last to leave puts it back.
"""

from __future__ import annotations

import threading
from collections.abc import Callable, Iterator
from contextlib import contextmanager
from typing import Any

__all__ = ["HeldSetting"]


class HeldSetting:
    """``enter()`` sets the value and returns the one it replaced; ``leave(saved)`` restores it.

    :meth:`held` is re-entrant and thread-safe, and usable as a decorator.
    """

    def __init__(self, enter: Callable[[], Any], leave: Callable[[Any], Any]) -> None:
        self._enter, self._leave = enter, leave
        self._lock = threading.Lock()
        self._depth = 0
        self._saved: Any = None

    @contextmanager
    def held(self) -> Iterator[None]:
        with self._lock:
            if self._depth == 0:
                self._saved = self._enter()
            self._depth += 1
        try:
            yield
        finally:
            with self._lock:
                self._depth -= 1
                if self._depth == 0:
                    self._leave(self._saved)
