"""Tests of ``o3dreg reconstruct``."""

from __future__ import annotations

import json
from pathlib import Path

import numpy as np
import open3d as o3d
import pytest
import SimpleITK as sitk

from o3dreg.app.datasets import headsq_path
from o3dreg.cli import main

DATA = Path(__file__).resolve().parents[1] / "data"
HEADSQ = headsq_path().parent  # bundled with the package (o3dreg/data)


@pytest.fixture
def scan(tmp_path) -> Path:
    """A MetaImage 'CT': a ball of bone (1000 HU) and a small bone island, in air (-1000)."""
    z, y, x = np.mgrid[:24, :30, :36]
    array = np.full((24, 30, 36), -1000, dtype=np.int16)
    array[((x - 14) ** 2 + (y - 15) ** 2 + (z - 12) ** 2) < 64] = 1000
    array[2:4, 2:4, 30:32] = 1000
    image = sitk.GetImageFromArray(array)
    image.SetSpacing((0.5, 0.75, 1.5))
    image.SetOrigin((-10.0, 20.0, 5.0))
    path = tmp_path / "scan.mha"
    sitk.WriteImage(image, str(path))
    return path


def _run(capsys, *argv: str, quiet: bool = True) -> tuple[int, str, str]:
    code = main([*(["-q"] if quiet else []), "reconstruct", *argv])
    out, err = capsys.readouterr()
    return code, out, err


def test_reconstruct_json_summary(tmp_path, scan, capsys):
    output = tmp_path / "bone.ply"
    code, out, err = _run(capsys, str(scan), "-o", str(output), "--threshold", "400", "--json")
    assert code == 0, err
    summary = json.loads(out)
    assert summary["components_found"] == 2
    assert summary["vertices"] == len(o3d.io.read_triangle_mesh(str(output)).vertices)
    assert summary["triangles"] > 0
    # The ball's outermost voxels are 7 voxels from its centre along each axis; level 400 lies
    # 0.3 of the way from 1000 to -1000, so the surface spans 2 * 7.3 voxels: x, y, z spacings
    # 0.5, 0.75, 1.5 mm pin the axis order.
    code, out, _ = _run(
        capsys, str(scan), "-o", str(tmp_path / "ball.ply"), "--threshold", "400", "--largest",
        "1", "--json",
    )  # fmt: skip
    ball = json.loads(out)
    assert ball["components_kept"] == 1
    # A ball inside the scan: closed and edge-manifold (checked from its edges; Open3D's
    # is_watertight() said False for such marching-cubes surfaces, touching triangles).
    assert ball["closed"] is True and ball["edge_manifold"] is True
    assert np.allclose(ball["extent_mm"], np.array([0.5, 0.75, 1.5]) * 14.6, atol=1e-4)
    centre = np.mean(ball["bounds_mm"], axis=0)
    assert np.allclose(centre, [-10 + 14 * 0.5, 20 + 15 * 0.75, 5 + 12 * 1.5], atol=0.5)


def test_reconstruct_cleaning_options(tmp_path, scan, capsys):
    output = tmp_path / "clean.ply"
    code, out, err = _run(
        capsys, str(scan), "-o", str(output), "--threshold", "400",
        "--min-component-vertices", "30", "--smooth", "5", "--decimate", "200",
        "--crop-box", "-20", "0", "0", "20", "50", "50",
        "--crop-plane", "0", "0", "10", "0", "0", "1", quiet=False,
    )  # fmt: skip
    assert code == 0, err
    assert "wrote" in out and "component(s) found" in out
    mesh = o3d.io.read_triangle_mesh(str(output))
    assert len(mesh.vertices) <= 200
    assert np.asarray(mesh.vertices)[:, 2].min() >= 10 - 1e-9


def test_reconstruct_refuses_to_overwrite(tmp_path, scan, capsys):
    output = tmp_path / "bone.ply"
    output.write_text("keep me")
    code, _, err = _run(capsys, str(scan), "-o", str(output), "--threshold", "400")
    assert code == 2
    assert "exists; pass --overwrite" in err
    assert output.read_text() == "keep me"
    code, _, err = _run(capsys, str(scan), "-o", str(output), "--threshold", "400", "--overwrite")
    assert code == 0, err
    assert len(o3d.io.read_triangle_mesh(str(output)).vertices) > 0


def test_reconstruct_bad_input_leaves_no_file(tmp_path, scan, capsys):
    output = tmp_path / "bone.ply"
    code, _, err = _run(capsys, str(scan), "-o", str(output), "--threshold", "5000")
    assert code == 2
    assert "--threshold must lie strictly between" in err
    assert "[-1000, 1000] (the file's own units), got 5000" in err
    code, _, err = _run(
        capsys, str(scan), "-o", str(output), "--threshold", "400", "--largest", "0"
    )
    assert code == 2
    assert "`--largest` must be a finite integer > 0" in err
    # An error from the library names the flag too (it named only `step_size`).
    code, _, err = _run(
        capsys, str(scan), "-o", str(output), "--threshold", "400", "--step-size", "0"
    )
    assert code == 2
    assert "`step_size` (--step-size) must be a finite integer > 0" in err
    code, _, err = _run(
        capsys, str(tmp_path / "missing.nii"), "-o", str(output), "--threshold", "1"
    )
    assert code == 2
    assert "no such file" in err
    code, _, err = _run(capsys, str(scan), "-o", str(tmp_path / "bone.txt"), "--threshold", "1")
    assert code == 2
    assert "must end with one of" in err
    assert list(tmp_path.iterdir()) == [scan]  # nothing written, no temporary left behind


def test_reconstruct_headsq(tmp_path, capsys):
    output = tmp_path / "skull.ply"
    code, out, err = _run(
        capsys, str(HEADSQ / "quarter.nhdr"), "-o", str(output),
        "--threshold", "1150", "--largest", "1", "--smooth", "10", "--decimate", "3000", "--json",
    )  # fmt: skip
    assert code == 0, err
    summary = json.loads(out)
    assert summary["components_found"] > 1
    assert summary["components_kept"] == 1
    assert 2900 <= summary["vertices"] <= 3000
    assert all(120 < e < 220 for e in summary["extent_mm"])


def test_reconstruct_quiet_prints_nothing(tmp_path, scan, capsys):
    code, out, err = _run(capsys, str(scan), "-o", str(tmp_path / "q.ply"), "--threshold", "400")
    assert code == 0 and out == "" and err == ""
    assert (
        main(["reconstruct", str(scan), "-o", str(tmp_path / "v.ply"), "--threshold", "400"]) == 0
    )
    assert capsys.readouterr().out.startswith("wrote ")
