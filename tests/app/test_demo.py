"""`o3dreg demo`: the README's first command."""

import pytest

from o3dreg.cli import main
from o3dreg.cli._demo import MARKER


def test_demo_refuses_a_foreign_folder(tmp_path, capsys):
    (tmp_path / "mine.txt").write_text("precious")
    assert main(["demo", "-o", str(tmp_path)]) == 2
    assert "was not made by `o3dreg demo`" in capsys.readouterr().err
    assert (tmp_path / "mine.txt").read_text() == "precious"


@pytest.mark.slow
def test_demo_runs_end_to_end(tmp_path, capsys):
    out = tmp_path / "demo"
    assert main(["demo", "-o", str(out), "--patients", "4"]) == 0
    printed = capsys.readouterr().out
    assert "Variances %" in printed and "report:" in printed
    report = (out / "report.md").read_text()
    for section in ("Single vs symmetric", "Batch registration", "Table 4", "Landmark prediction"):
        assert section in report
    assert (out / "images" / "variances.png").stat().st_size > 1000
    assert "(explorer.html)" in report and (out / "explorer.html").stat().st_size > 10_000
    assert (out / "model.npz").is_file() and (out / MARKER).is_file()
    # A second run replaces the folder it made.
    assert main(["demo", "-o", str(out), "--patients", "3", "-q"]) == 0
