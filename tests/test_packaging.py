"""o3dreg is pure Python on its dependencies: no compiled code of its own, a wheel for every
platform."""

from __future__ import annotations

import ast
import subprocess
import sys
import zipfile
from pathlib import Path

import pytest

ROOT = Path(__file__).resolve().parents[1]
PACKAGE = ROOT / "o3dreg"


def test_the_package_holds_no_native_source_and_loads_no_native_library():
    native = [p.name for p in PACKAGE.rglob("*") if p.suffix in {".c", ".cc", ".cpp", ".pyx"}]
    assert native == []
    assert not (ROOT / "setup.py").exists()
    for path in PACKAGE.rglob("*.py"):
        for node in ast.walk(ast.parse(path.read_text(encoding="utf-8"))):
            if isinstance(node, ast.Import | ast.ImportFrom):
                names = [a.name for a in node.names] + [getattr(node, "module", None) or ""]
                assert "ctypes" not in names, path


@pytest.mark.slow
def test_the_wheel_is_pure_python(tmp_path):
    # Built as a user's pip would (an isolated build environment); no compiler is asked for.
    env = {"PATH": "/usr/bin:/bin", "CC": "/bin/false", "CXX": "/bin/false"}
    done = subprocess.run(
        [sys.executable, "-m", "pip", "wheel", "--no-deps", "-q", "-w", str(tmp_path), str(ROOT)],
        capture_output=True, text=True, env=env,
    )  # fmt: skip
    assert done.returncode == 0, done.stderr[-2000:]
    (wheel,) = tmp_path.glob("*.whl")
    assert wheel.name.endswith("-py3-none-any.whl")
    with zipfile.ZipFile(wheel) as archive:
        assert not [n for n in archive.namelist() if n.endswith((".so", ".pyd", ".dll"))]
