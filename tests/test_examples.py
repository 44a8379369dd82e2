"""Every example script runs headless (slow: they do real registrations)."""

import subprocess
import sys
from pathlib import Path

import pytest

# paper_tables.py and mandible_model.py have slow tests of their own (test_examples_paper.py,
# test_cli_model.py::test_mandible_example) with the options that keep them short.
OWN_TESTS = {"paper_tables.py", "mandible_model.py"}
EXAMPLES = sorted(
    p
    for p in (Path(__file__).resolve().parents[1] / "examples").glob("*.py")
    if p.name not in OWN_TESTS
)


@pytest.mark.slow
@pytest.mark.parametrize("script", EXAMPLES, ids=lambda p: p.name)
def test_example_runs(script, tmp_path):
    args = [sys.executable, str(script)]
    if script.name == "ct_to_model.py":
        args.append(str(tmp_path / "out"))
    proc = subprocess.run(args, capture_output=True, text=True, timeout=600, cwd=tmp_path)
    assert proc.returncode == 0, proc.stderr[-2000:]
    assert proc.stdout.strip()
