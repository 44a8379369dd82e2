"""Headless rendering writes PNGs of the requested size, with either back end."""

from __future__ import annotations

import os
import subprocess
import sys
from pathlib import Path

import numpy as np
import pytest

from o3dreg.app.render import mode_displacements, render_mesh, render_shape_modes, view_rotation
from o3dreg.app.synthetic import synthetic_form

ROOT = Path(__file__).resolve().parents[2]


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


def test_open3d_backend_is_stopped_at_its_time_limit(tmp_path, cone):
    # 0.05 s is less than a fresh interpreter takes to import Open3D, so the child is always
    # stopped: the caller gets an error instead of a hang (Filament on software Vulkan).
    with pytest.raises(RuntimeError, match="time limit of 0.05 s"):
        render_mesh(cone, tmp_path / "a.png", backend="open3d", time_limit=0.05)
    assert not (tmp_path / "a.png").exists()
    with pytest.raises(ValueError, match="`time_limit` must be a positive number"):
        render_mesh(cone, tmp_path / "a.png", backend="open3d", time_limit=0.0)


def test_view_screenshot_is_written_headless_in_bounded_time(tmp_path, cone):
    # The command the docs call headless, as a user runs it: no display, no GPU. It hung in
    # Filament before (killed at 120 s); the matplotlib default takes seconds.
    import open3d as o3d

    mesh_path, png = tmp_path / "cone.ply", tmp_path / "cone.png"
    o3d.io.write_triangle_mesh(str(mesh_path), cone)
    env = {k: v for k, v in os.environ.items() if k not in ("DISPLAY", "WAYLAND_DISPLAY")}
    env["PYTHONPATH"] = os.pathsep.join([str(ROOT), env.get("PYTHONPATH", "")])
    command = [sys.executable, "-m", "o3dreg", "view", str(mesh_path), "--screenshot", str(png)]
    done = subprocess.run(
        [*command, "--distance-to", str(mesh_path), "--size", "640,480"],
        env=env,
        capture_output=True,
        text=True,
        timeout=120,
    )
    assert done.returncode == 0, done.stderr
    assert _png_size(png) == (640, 480)
    assert "mean 0.000" in done.stdout  # a mesh is at distance 0 from itself


def test_view_screenshot_of_several_meshes_is_refused_before_any_work(tmp_path, cone, capsys):
    # It drew the first mesh only, silently.
    import open3d as o3d

    from o3dreg.cli import main

    a, b, png = tmp_path / "a.ply", tmp_path / "b.ply", tmp_path / "ab.png"
    o3d.io.write_triangle_mesh(str(a), cone)
    o3d.io.write_triangle_mesh(str(b), cone)
    assert main(["view", str(a), str(b), "--screenshot", str(png)]) == 2
    assert "--screenshot renders one MESH, got 2" in capsys.readouterr().err
    assert not png.exists()


def _sphere_model(radii):
    import open3d as o3d

    from o3dreg import build_shape_model

    sphere = o3d.geometry.TriangleMesh.create_icosahedron(1.0).subdivide_loop(2)
    unit = np.asarray(sphere.vertices)
    unit = unit / np.linalg.norm(unit, axis=1, keepdims=True)
    faces = np.asarray(sphere.triangles)
    return build_shape_model([r * unit for r in radii], faces), unit


def test_mode_displacements_of_spheres_are_radial():
    # Spheres of radii 8-12 about the origin: the only mode is a change of radius, so the
    # displacement is along the normal at every vertex, the same everywhere, and linear in c.
    radii = [8.0, 9.0, 10.0, 11.0, 12.0]
    model, _ = _sphere_model(radii)
    d = mode_displacements(model, 0, 2.0)
    moved = np.linalg.norm(model.mode_shape(0, 2.0) - model.mean, axis=1)
    # The vertex normals of a subdivided icosahedron deviate from the radial direction by a few
    # degrees at most: cos(5 deg) = 0.996.
    np.testing.assert_allclose(np.abs(d), moved, rtol=4e-3)
    assert np.all(d > 0) or np.all(d < 0)
    # One SD of radius, spread over the vertices in the unit-norm mode: |d| = 2 * std(radii).
    np.testing.assert_allclose(np.abs(d), 2.0 * np.std(radii, ddof=1), rtol=4e-3)
    np.testing.assert_allclose(mode_displacements(model, 0, -2.0), -d, rtol=1e-12)
    np.testing.assert_allclose(mode_displacements(model, 0, 0.0), 0.0, atol=1e-12)


def test_render_shape_modes_writes_one_grid(tmp_path):
    from o3dreg import build_shape_model

    sphere, unit = _sphere_model([1.0, 2.0])
    # Ellipsoids whose x and y semi-axes vary independently: two modes.
    axes = [(8.0, 9.0, 10.0), (12.0, 9.5, 10.0), (9.0, 12.0, 10.0), (11.0, 8.0, 10.0)]
    model = build_shape_model([unit * a for a in axes], sphere.faces)
    path = render_shape_modes(model, tmp_path / "modes.png", modes=(0, 1, 5), panel=(200, 180))
    # One row per mode the model has (mode 6 it lacks), three columns and a colour bar.
    assert _png_size(path) == (3 * 200 + 130, 2 * (180 + 30))
    with pytest.raises(ValueError, match="`modes` must name at least one"):
        render_shape_modes(model, tmp_path / "x.png", modes=(7,))
    assert not (tmp_path / "x.png").exists()


def _left_right_squares():
    # Two squares facing -x, side by side along y: value 0 at y > 0, value 1 at y < 0.
    square = np.array([[0.0, 0.2, -0.5], [0.0, 1.2, -0.5], [0.0, 1.2, 0.5], [0.0, 0.2, 0.5]])
    other = square * [1.0, -1.0, 1.0]
    vertices = np.vstack([square, other])
    faces = np.array([[0, 1, 2], [0, 2, 3], [4, 6, 5], [4, 7, 6]])
    return (vertices, faces), np.array([0.0, 0.0, 1.0, 1.0])


def test_pictures_are_not_mirrored(tmp_path):
    # Up z, azimuth 0, elevation 0: the camera sits on -x looking towards +x (render's
    # convention, as Open3D's back end and the explorer place it), so +y is on the left.
    import matplotlib.image

    mesh, values = _left_right_squares()
    path = render_mesh(
        mesh, tmp_path / "lr.png", scalars=values, view=(0, 0), size=(300, 200), cmap="viridis"
    )
    image = matplotlib.image.imread(path)[..., :3]
    purple, yellow = np.array([0.27, 0.0, 0.33]), np.array([0.99, 0.91, 0.14])
    columns = np.arange(image.shape[1])

    def mean_column(colour):
        near = np.linalg.norm(image - colour, axis=2) < 0.25
        return columns[near.any(axis=0)].mean()

    assert mean_column(purple) < mean_column(yellow)  # y > 0 (value 0) drawn on the left
    # The explorer's camera agrees: its right-hand direction is -y.
    rotation = np.reshape(view_rotation((0, 0), (0, 0, 1)), (3, 3))
    np.testing.assert_allclose(rotation[0], [0.0, -1.0, 0.0], atol=1e-12)


@pytest.mark.parametrize("scale", [0.0031, 0.052, 37.0])
def test_the_colour_bar_label_stays_inside_the_picture(tmp_path, scale):
    # Long tick labels ("-0.75") can push the label's second line past the right edge (the
    # last column of the picture holding ink): a margin of white must stay, whatever the scale.
    import matplotlib.image
    from _helpers import population

    from o3dreg import build_shape_model

    (_, tf), _, truths, _, _ = population(6, seed=1)
    model = build_shape_model([t * scale for t in truths], tf)
    image = matplotlib.image.imread(render_shape_modes(model, tmp_path / "m.png"))[..., :3]
    ink = np.flatnonzero((image.min(axis=2) < 0.9).any(axis=0))
    assert ink.max() < image.shape[1] - 2


def test_a_colour_bar_says_when_values_pass_its_ends():
    # The demo's distance pictures end their scale at 3 mm while distances reach 6.85 mm:
    # the bar's pointed end says that some values are beyond it.
    from o3dreg.app.render import colorbar_extend

    values = np.array([0.0, 1.0, 6.85, np.nan])
    assert colorbar_extend(values, 0.0, 3.0) == "max"
    assert colorbar_extend(values, 0.5, 3.0) == "both"
    assert colorbar_extend(values, 0.5, 7.0) == "min"
    assert colorbar_extend(values, 0.0, 7.0) == "neither"
