"""Headless rendering writes PNGs of the requested size, with either back end."""

from __future__ import annotations

import numpy as np
import pytest

from o3dreg.app.render import render_mesh
from o3dreg.app.synthetic import synthetic_form


def _png_size(path) -> tuple[int, int]:
    with open(path, "rb") as f:
        head = f.read(24)
    assert head[:8] == b"\x89PNG\r\n\x1a\n"
    return int.from_bytes(head[16:20], "big"), int.from_bytes(head[20:24], "big")


@pytest.fixture(scope="module")
def cone():
    return synthetic_form("cone", 300)


def test_matplotlib_backend_writes_png_of_requested_size(tmp_path, cone):
    path = tmp_path / "cone.png"
    scalars = np.asarray(cone.vertices)[:, 2]
    out = render_mesh(
        cone, path, scalars=scalars, size=(320, 240), backend="matplotlib", title="z", label="mm"
    )
    assert out == str(path)
    assert path.stat().st_size > 1000
    assert _png_size(path) == (320, 240)
    assert [p.name for p in tmp_path.iterdir()] == ["cone.png"]  # no temporary left behind


# Filament on Mesa's software Vulkan takes 3-30 s per picture on a loaded 2-core machine.
@pytest.mark.slow
def test_open3d_backend_writes_png_of_requested_size(tmp_path, cone):
    path = tmp_path / "cone.png"
    faces = np.asarray(cone.triangles)
    try:
        render_mesh(cone, path, scalars=np.arange(len(faces)), size=(200, 150), backend="open3d")
    except RuntimeError as error:
        pytest.skip(f"no Open3D offscreen renderer on this machine: {error}")
    assert path.stat().st_size > 1000
    assert _png_size(path) == (200, 150)


def test_render_mesh_rejects_bad_input(tmp_path, cone):
    with pytest.raises(ValueError, match="`scalars` must have one value per vertex"):
        render_mesh(cone, tmp_path / "a.png", scalars=[1.0, 2.0], backend="matplotlib")
    with pytest.raises(ValueError, match="`backend` must be one of"):
        render_mesh(cone, tmp_path / "a.png", backend="vtk")
    with pytest.raises(ValueError, match="`size` must be at least"):
        render_mesh(cone, tmp_path / "a.png", size=(4, 4))
    assert not (tmp_path / "a.png").exists()
