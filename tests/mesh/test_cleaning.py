"""Tests of o3dreg.cleaning: components, cropping, Taubin smoothing, decimation."""

from __future__ import annotations

import numpy as np
import open3d as o3d
import pytest
from _helpers import assert_untouched, snapshot

from o3dreg import (
    Components,
    connected_components,
    crop_mesh,
    decimate,
    isosurface,
    keep_largest_components,
    read_volume,
    remove_small_components,
    smooth_taubin,
)


def _sphere(radius: float, centre: tuple[float, float, float], resolution: int):
    mesh = o3d.geometry.TriangleMesh.create_sphere(radius, resolution)
    return mesh.translate(centre)


@pytest.fixture
def three_parts() -> o3d.geometry.TriangleMesh:
    """A big sphere, a medium one and a tiny island (a tetrahedron), far apart."""
    big = _sphere(10.0, (0, 0, 0), 30)  # 1742 vertices
    medium = _sphere(5.0, (30, 0, 0), 10)  # 182 vertices
    tiny = o3d.geometry.TriangleMesh.create_tetrahedron(1.0).translate((0, 30, 0))
    return tiny + medium + big  # the largest last: the order must not matter


def test_connected_components_sorted_by_size(three_parts):
    components = connected_components(three_parts)
    assert isinstance(components, Components)
    assert len(components) == 3
    assert components.vertex_counts.tolist() == [1742, 182, 4]
    assert components.triangle_counts.sum() == len(three_parts.triangles)
    assert components.areas[0] == pytest.approx(4 * np.pi * 100, rel=0.02)
    assert repr(components) == "Components(n=3, vertex_counts=[1742, 182, 4])"


def test_components_join_through_edges_not_through_a_lone_vertex():
    # A fan of three triangles on one edge (non-manifold) is one component; a fourth triangle
    # touching it at a single vertex is another; the vertex they share counts in both.
    vertices = np.array(
        [[0, 0, 0], [1, 0, 0], [0, 1, 0], [0, -1, 0], [0, 0, 1], [2, 1, 0], [2, -1, 0]], float
    )
    faces = np.array([[0, 1, 2], [1, 0, 3], [0, 1, 4], [1, 5, 6]])
    components = connected_components((vertices, faces))
    assert components.labels.tolist() == [0, 0, 0, 1]
    assert components.vertex_counts.tolist() == [5, 3]
    assert components.triangle_counts.tolist() == [3, 1]


def test_keep_largest_components(three_parts):
    before = snapshot(three_parts)
    one = keep_largest_components(three_parts)
    assert len(one.vertices) == 1742
    assert np.allclose(np.asarray(one.vertices).mean(axis=0), 0, atol=1e-9)
    two = keep_largest_components(three_parts, 2)
    assert len(connected_components(two)) == 2
    assert len(two.vertices) == 1742 + 182
    everything = keep_largest_components(three_parts, 10)
    assert len(everything.vertices) == len(three_parts.vertices)
    assert_untouched(three_parts, before)
    with pytest.raises(ValueError, match="`n` must be a finite integer > 0, got 0"):
        keep_largest_components(three_parts, 0)


def test_remove_small_components(three_parts):
    before = snapshot(three_parts)
    out = remove_small_components(three_parts, 50)
    assert connected_components(out).vertex_counts.tolist() == [1742, 182]
    assert_untouched(three_parts, before)
    with pytest.raises(ValueError, match=r"must not exceed the largest component \(1742"):
        remove_small_components(three_parts, 2000)
    with pytest.raises(TypeError, match="`min_vertices` must be an integer"):
        remove_small_components(three_parts, 2.5)


def test_crop_mesh_box_and_plane(three_parts):
    before = snapshot(three_parts)
    boxed = crop_mesh(three_parts, box=[[20, -10, -10], [40, 10, 10]])
    assert len(boxed.vertices) == 182  # only the medium sphere
    # Separate along a plane: keep x >= 20 (where the normal points).
    cut = crop_mesh(three_parts, plane=[[20, 0, 0], [1, 0, 0]])
    assert np.asarray(cut.vertices)[:, 0].min() >= 20
    half = crop_mesh(three_parts, plane=[[0, 0, 0], [0, 0, -2]])
    assert np.asarray(half.vertices)[:, 2].max() <= 0
    both = crop_mesh(three_parts, box=[[-50, -50, -50], [50, 50, 50]], plane=[[0, 0, 0], [1, 0, 0]])
    assert np.asarray(both.vertices)[:, 0].min() >= 0
    assert_untouched(three_parts, before)


def test_crop_mesh_rejects_bad_input(three_parts):
    with pytest.raises(ValueError, match="needs `box` or `plane`"):
        crop_mesh(three_parts)
    with pytest.raises(ValueError, match=r"`box` must have min <= max"):
        crop_mesh(three_parts, box=[[1, 1, 1], [0, 0, 0]])
    with pytest.raises(ValueError, match="normal must be non-zero"):
        crop_mesh(three_parts, plane=[[0, 0, 0], [0, 0, 0]])
    with pytest.raises(ValueError, match="removed every triangle"):
        crop_mesh(three_parts, box=[[100, 100, 100], [200, 200, 200]])


def test_smooth_taubin_removes_noise_and_keeps_size():
    sphere = _sphere(10.0, (1, 2, 3), 40)
    rng = np.random.default_rng(1)
    vertices = np.asarray(sphere.vertices) + rng.normal(0, 0.2, (len(sphere.vertices), 3))
    noisy = o3d.geometry.TriangleMesh(
        o3d.utility.Vector3dVector(vertices), o3d.geometry.TriangleMesh(sphere).triangles
    )
    before = snapshot(noisy)
    smooth = smooth_taubin(noisy, 20)
    radius_noisy = np.linalg.norm(np.asarray(noisy.vertices) - (1, 2, 3), axis=1)
    radius_smooth = np.linalg.norm(np.asarray(smooth.vertices) - (1, 2, 3), axis=1)
    assert radius_smooth.std() < 0.5 * radius_noisy.std()
    # Taubin's lambda/mu pair barely shrinks: the mean radius stays within 2 %.
    assert radius_smooth.mean() == pytest.approx(10.0, rel=0.02)
    assert np.array_equal(np.asarray(smooth.triangles), before[1])
    assert_untouched(noisy, before)
    again = smooth_taubin(noisy, 20)
    assert np.array_equal(np.asarray(again.vertices), np.asarray(smooth.vertices))


def test_smooth_taubin_rejects_bad_input():
    sphere = _sphere(1.0, (0, 0, 0), 5)
    with pytest.raises(ValueError, match=r"`mu` must be negative with lambda_filter < -mu < 1"):
        smooth_taubin(sphere, 5, mu=0.3)
    with pytest.raises(ValueError, match=r"`lambda_filter` must be in \(0, 1\)"):
        smooth_taubin(sphere, 5, lambda_filter=1.5)
    with pytest.raises(ValueError, match="`number_of_iterations` must be a finite integer >= 0"):
        smooth_taubin(sphere, -1)


def test_decimate_to_vertex_count_deterministic():
    sphere = _sphere(10.0, (0, 0, 0), 60)  # 3482 vertices
    before = snapshot(sphere)
    out = decimate(sphere, 1000)
    assert 980 <= len(out.vertices) <= 1000
    assert out.is_edge_manifold(allow_boundary_edges=False)
    again = decimate(sphere, 1000)
    assert np.array_equal(np.asarray(out.vertices), np.asarray(again.vertices))
    assert np.array_equal(np.asarray(out.triangles), np.asarray(again.triangles))
    assert_untouched(sphere, before)
    small = decimate(sphere, 10_000)  # already below the target: a copy
    assert len(small.vertices) == len(sphere.vertices)


def test_decimate_rejects_bad_input():
    sphere = _sphere(1.0, (0, 0, 0), 5)
    with pytest.raises(ValueError, match="`number_of_vertices` must be >= 4, got 3"):
        decimate(sphere, 3)
    with pytest.raises(TypeError, match=r"`mesh` must be an open3d\.geometry\.TriangleMesh"):
        decimate("mesh.ply", 100)


def test_connected_components_rejects_bad_input():
    with pytest.raises(ValueError, match=r"`mesh.faces` must index vertices in \[0, 2\]"):
        connected_components((np.eye(3), [[0, 1, 5]]))


def test_mandible_template_pipeline(shared_data):
    path = shared_data / "mandibles" / "masks" / "0522c0001_Mandible.nrrd"
    if not path.exists():
        pytest.skip(f"mandible mask {path} is absent (research-only shared data)")
    mesh = keep_largest_components(isosurface(read_volume(path), 0.5))
    template = decimate(smooth_taubin(mesh, 10), 2000)
    assert 1960 <= len(template.vertices) <= 2000
    assert template.is_edge_manifold(allow_boundary_edges=False)
    # Smoothing and decimation keep the bone's size: volume within 3 % of the raw surface.
    assert template.get_volume() == pytest.approx(mesh.get_volume(), rel=0.03)
