"""examples/paper_tables.py runs end to end and prints both of the paper's tables."""

from __future__ import annotations

import subprocess
import sys
from pathlib import Path

import pytest

EXAMPLE = Path(__file__).resolve().parents[1] / "examples" / "paper_tables.py"


@pytest.mark.slow
def test_paper_tables_quick():
    out = subprocess.run(
        [sys.executable, str(EXAMPLE), "--quick"],
        capture_output=True,
        text=True,
        check=True,
        timeout=1800,
    ).stdout
    assert "Table 1." in out
    assert "Table 2. Distance gain" in out
    assert "Sphere (low) -> open ring (high)" in out
    # The symmetric method must shrink the sphere->cone (target->source) distances, as in the
    # paper's Table 1.
    single, symmetric = (
        [float(v) for v in line.split()[1:5]]
        for line in out.splitlines()
        if line.startswith(("Single ", "Symmetric "))
    )
    assert symmetric[2] < single[2] and symmetric[3] < single[3]
