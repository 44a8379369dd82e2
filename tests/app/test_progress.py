"""Progress reports: a bar where it can redraw, a line per item elsewhere, nothing when off."""

from __future__ import annotations

import io

from o3dreg.app.progress import Progress, bar_redraws


class Stream(io.StringIO):
    def __init__(self, tty: bool) -> None:
        super().__init__()
        self.tty = tty

    def isatty(self) -> bool:
        return self.tty


def test_a_bar_redraws_on_a_terminal_only(monkeypatch):
    monkeypatch.delitem(__import__("sys").modules, "ipykernel", raising=False)
    assert bar_redraws(Stream(tty=True))
    assert not bar_redraws(Stream(tty=False))
    assert not bar_redraws(object())  # a stream without isatty (a custom writer)


def test_lines_count_from_the_items_done_before(monkeypatch):
    err = Stream(tty=False)
    monkeypatch.setattr("sys.stderr", err)
    monkeypatch.delitem(__import__("sys").modules, "ipykernel", raising=False)
    progress = Progress(3, 1, "patients", "patient", enabled=True)
    progress.current("b")  # on the bar only
    progress.done("b (ok)")
    progress.done("c (suspect)")
    progress.close()
    lines = err.getvalue().splitlines()
    assert [line.split(" (")[0] for line in lines] == ["patients 2/3: b", "patients 3/3: c"]
    assert lines[1].startswith("patients 3/3: c (suspect) (") and lines[1].endswith(" s)")


def test_nothing_is_written_when_disabled(monkeypatch):
    for tty in (True, False):
        err = Stream(tty=tty)
        monkeypatch.setattr("sys.stderr", err)
        progress = Progress(2, 0, "patients", "patient", enabled=False)
        progress.done("a (ok)")
        progress.close()
        assert err.getvalue() == ""
