"""Progress of long runs: a bar where one redraws in place, a line per step elsewhere.

A tqdm bar redraws itself with carriage returns. Piped into a log file or a CI job's output it
shows nothing readable until the run ends, so there each finished item is one line on stderr.
"""

from __future__ import annotations

import sys
import time
from typing import Any

from tqdm.auto import tqdm


def bar_redraws(stream: Any = None) -> bool:
    """Whether a progress bar redraws in place on ``stream`` (default ``sys.stderr``): a
    terminal, or a Jupyter kernel, where ``tqdm.auto`` draws a widget."""
    stream = sys.stderr if stream is None else stream
    isatty = getattr(stream, "isatty", None)
    return bool(isatty is not None and isatty()) or "ipykernel" in sys.modules


def announce(text: str) -> None:
    """Write one line of progress on stderr, above any bar being drawn."""
    if sys.stderr is not None:
        tqdm.write(text, file=sys.stderr)
        sys.stderr.flush()


class Progress:
    """Items done out of a total: a bar, or a line per item where a bar cannot redraw.

    Parameters
    ----------
    total, initial : int
        Items in all, and already done when the run starts.
    desc, unit : str
        What is counted (``"patients"``, ``"patient"``).
    enabled : bool
        Report at all; ``False`` writes nothing.
    """

    def __init__(self, total: int, initial: int, desc: str, unit: str, *, enabled: bool) -> None:
        self.lines = enabled and not bar_redraws()
        self.desc = desc
        self.total = total
        self.count = initial
        self._start = time.perf_counter()
        self._bar = tqdm(
            total=total,
            initial=initial,
            desc=desc,
            unit=unit,
            disable=not enabled or self.lines,
            dynamic_ncols=True,
        )

    def current(self, text: str) -> None:
        """Name the item being worked on (on the bar only: a line per start would double the
        log)."""
        self._bar.set_postfix_str(f"current: {text}")

    def done(self, text: str) -> None:
        """Count one item done, described by ``text``."""
        self.count += 1
        self._bar.set_postfix_str(f"last: {text}")
        self._bar.update(1)
        if self.lines:
            seconds = time.perf_counter() - self._start
            announce(f"{self.desc} {self.count}/{self.total}: {text} ({seconds:.0f} s)")

    def close(self) -> None:
        self._bar.close()
