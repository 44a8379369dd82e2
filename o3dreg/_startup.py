"""SIGINT and SIGTERM while the ``o3dreg`` command starts up.

Importing o3dreg's libraries (Open3D, SciPy, libigl) takes one to two seconds, before the command
line is read and the command's own handlers are installed; a signal then would end the process
by the signal (SIGTERM) or with a traceback (SIGINT). When this process is the ``o3dreg``
command, the package's first lines install handlers that end it at once with the documented
status and one line: nothing is written before the command starts. The command hands them back
(:func:`hand_over`) when it installs its own. A program that imports o3dreg keeps its handlers.
"""

from __future__ import annotations

import os
import signal
import sys
import threading
from typing import Any

__all__ = ["guard", "hand_over", "is_the_command"]

#: Exit status and word of each signal, as the command's own handlers end it.
_ENDINGS = {signal.SIGINT: (130, "interrupted"), signal.SIGTERM: (143, "terminated")}

#: The handlers the guard replaced, per signal (empty when no guard is installed).
_replaced: dict[int, Any] = {}


def is_the_command() -> bool:
    """Whether this process runs the ``o3dreg`` command (its script, or ``python -m o3dreg``)."""
    script = os.path.basename(sys.argv[0]) if sys.argv else ""
    if script.removesuffix(".exe") == "o3dreg":
        return True
    original = list(getattr(sys, "orig_argv", ()))
    return "-m" in original and original[original.index("-m") + 1 :][:1] == ["o3dreg"]


def _command_name() -> str:
    words = [a for a in sys.argv[1:] if not a.startswith("-")]
    return f"o3dreg {words[0]}" if words and words[0].isalpha() else "o3dreg"


def _end(signum: int, frame: Any) -> None:
    status, word = _ENDINGS[signal.Signals(signum)]
    try:
        os.write(2, f"{_command_name()}: {word}\n".encode())
    finally:
        os._exit(status)


def guard() -> None:
    """Install the start-up handlers, when this process is the command (see the module)."""
    if _replaced or not is_the_command():
        return
    if threading.current_thread() is not threading.main_thread():
        return
    for sig in _ENDINGS:
        current = signal.getsignal(sig)
        if current is signal.SIG_IGN:
            continue  # a background job ignores SIGINT: it stays ignored
        _replaced[sig] = current
        signal.signal(sig, _end)


def hand_over(sigterm_before: Any) -> Any:
    """Give SIGINT its handler from before the guard back, as the command installs its own
    (call it in the main thread right after installing the SIGTERM one); ``sigterm_before``
    is what that installation replaced: the handler from before the guard is returned in place
    of the guard's own."""
    before = _replaced.pop(signal.SIGTERM, None)
    if sigterm_before is _end and before is not None:
        sigterm_before = before
    interrupt = _replaced.pop(signal.SIGINT, None)
    if interrupt is not None and signal.getsignal(signal.SIGINT) is _end:
        signal.signal(signal.SIGINT, interrupt)
    return sigterm_before
