"""Tests of o3dreg.isosurface: analytic shapes, axis order and orientation, real scans."""

from __future__ import annotations

from pathlib import Path

import nibabel as nib
import numpy as np
import pytest
from _helpers import signed_volume
from scipy.special import ellipeinc, ellipkinc

from o3dreg import Volume, connected_components, isosurface, keep_largest_components, read_volume
from o3dreg.app.datasets import headsq_path
from o3dreg.registration.distance import SurfaceDistanceQuery

DATA = Path(__file__).resolve().parents[1] / "data"
HEADSQ = headsq_path().parent  # bundled with the package (o3dreg/data)
LPS_FROM_RAS = np.diag([-1.0, -1.0, 1.0])


def _rotation(degrees_x: float, degrees_z: float) -> np.ndarray:
    cx, sx = np.cos(np.radians(degrees_x)), np.sin(np.radians(degrees_x))
    cz, sz = np.cos(np.radians(degrees_z)), np.sin(np.radians(degrees_z))
    rx = np.array([[1, 0, 0], [0, cx, -sx], [0, sx, cx]])
    rz = np.array([[cz, -sz, 0], [sz, cz, 0], [0, 0, 1]])
    return rz @ rx


def _ellipsoid_volume(
    semi_axes: tuple[float, float, float],
    centre: tuple[float, float, float],
    *,
    shape: tuple[int, int, int],
    spacing: tuple[float, float, float],
    origin: tuple[float, float, float],
    direction: np.ndarray | None = None,
) -> Volume:
    """Sample ``1 - sum(((x - centre) / semi_axes)^2)`` (world coordinates) on a grid, float32."""
    geometry = Volume(np.zeros((1, 1, 1)), spacing, origin, direction)
    index = np.indices(shape, dtype=np.float64).reshape(3, -1).T
    world = geometry.index_to_world(index)
    field = 1.0 - (((world - centre) / semi_axes) ** 2).sum(axis=1)
    return Volume(field.reshape(shape).astype(np.float32), spacing, origin, direction)


def _closed(mesh) -> bool:
    """Closed 2-manifold: every edge shared by exactly two triangles.

    (Open3D's ``is_watertight`` also rejects near-touching triangles, which marching cubes makes.)
    """
    return bool(mesh.is_edge_manifold(allow_boundary_edges=False) and mesh.is_vertex_manifold())


def _ellipsoid_area(a: float, b: float, c: float) -> float:
    """Exact surface area (Legendre's formula with incomplete elliptic integrals), a >= b >= c."""
    a, b, c = sorted((a, b, c), reverse=True)
    phi = np.arccos(c / a)
    m = (a**2 * (b**2 - c**2)) / (b**2 * (a**2 - c**2))
    return float(
        2 * np.pi * c**2
        + 2
        * np.pi
        * a
        * b
        / np.sin(phi)
        * (ellipeinc(phi, m) * np.sin(phi) ** 2 + ellipkinc(phi, m) * np.cos(phi) ** 2)
    )


def test_ellipsoid_area_and_volume():
    semi = (12.0, 9.0, 6.0)
    volume = _ellipsoid_volume(
        semi, (0.0, 0.0, 0.0), shape=(40, 50, 60), spacing=(0.5, 0.5, 0.5), origin=(-15, -12, -10)
    )
    mesh = isosurface(volume, 0.0)
    assert _closed(mesh)
    exact_volume = 4.0 / 3.0 * np.pi * np.prod(semi)
    exact_area = _ellipsoid_area(*semi)
    # Marching cubes on a smooth field interpolates the surface to O(h^2): with h = 0.5 mm and
    # the smallest radius of curvature c^2/a = 3 mm, chords cut inside by ~h^2/(8 r) ~ 0.01 mm,
    # i.e. well below 1 % of volume and area; 1 % leaves room for the quadratic field's
    # interpolation bias.
    assert signed_volume(mesh) == pytest.approx(exact_volume, rel=0.01)
    assert mesh.get_surface_area() == pytest.approx(exact_area, rel=0.01)


@pytest.mark.parametrize(
    "direction",
    [None, _rotation(25, 40), np.diag([1.0, -1.0, 1.0]) @ _rotation(10, -30)],
    ids=["identity", "rotation", "reflection"],
)
def test_axis_order_spacing_origin_and_orientation(direction):
    # An anisotropic, off-centre ellipsoid defined in world coordinates, on a grid with different
    # spacing along each axis: any swap of axes, spacing or orientation moves the vertices off it.
    semi = np.array([6.0, 10.0, 15.0])
    centre = np.array([30.0, -20.0, 55.0])
    rot = np.eye(3) if direction is None else direction
    spacing = (1.1, 0.7, 0.45)  # (plane, row, column)
    shape = (36, 46, 56)
    # Put the grid centre on the ellipsoid centre: origin = centre - R @ (half extent).
    half = (np.array(shape[::-1]) - 1) / 2 * np.array(spacing[::-1])
    origin = centre - rot @ half
    volume = _ellipsoid_volume(
        tuple(semi), tuple(centre), shape=shape, spacing=spacing, origin=tuple(origin),
        direction=direction,
    )  # fmt: skip
    mesh = isosurface(volume, 0.0)
    vertices = np.asarray(mesh.vertices)
    radius = np.sqrt((((vertices - centre) / semi) ** 2).sum(axis=1))
    # Linear interpolation of a quadratic field: within 2 % of the unit level set.
    assert np.abs(radius - 1.0).max() < 0.02
    assert np.allclose(vertices.min(axis=0), centre - semi, atol=0.5)
    assert np.allclose(vertices.max(axis=0), centre + semi, atol=0.5)
    # Outward orientation whatever the handedness of the index -> world map.
    assert signed_volume(mesh) > 0
    mesh.compute_triangle_normals()
    normals = np.asarray(mesh.triangle_normals)
    centroids = vertices[np.asarray(mesh.triangles)].mean(axis=1)
    assert np.mean(np.einsum("ij,ij->i", normals, centroids - centre) > 0) > 0.99


def test_crop_gives_the_same_surface_and_input_untouched():
    z, y, x = np.mgrid[:30, :32, :34]
    array = (((x - 20) / 6.0) ** 2 + ((y - 12) / 5.0) ** 2 + ((z - 18) / 4.0) ** 2 < 1).astype(
        np.int16
    ) * 1000
    before = array.copy()
    volume = Volume(array, spacing=(2.0, 1.0, 0.5), origin=(5, 6, 7))
    cropped = isosurface(volume, 500)
    full = isosurface(volume, 500, crop=False)
    assert np.allclose(np.asarray(cropped.vertices), np.asarray(full.vertices))
    assert np.array_equal(np.asarray(cropped.triangles), np.asarray(full.triangles))
    assert np.array_equal(array, before)
    coarse = isosurface(volume, 500, step_size=2)
    assert len(coarse.vertices) < len(cropped.vertices)


@pytest.mark.parametrize("step", [2, 3, 4])
@pytest.mark.parametrize("crop", [True, False])
def test_a_coarse_step_gives_a_closed_surface_of_about_the_right_volume(step, crop):
    # With a step, marching cubes samples every step-th voxel: the cropped box ended one voxel
    # past the object, so a step of 3 or 4 left the ball's far side open (half its volume).
    z, y, x = np.mgrid[:40, :40, :40]
    ball = (((x - 20) ** 2 + (y - 20) ** 2 + (z - 20) ** 2) < 81).astype(np.float32)
    box = np.zeros((30, 30, 30), np.float32)
    box[:12, 5:25, 5:25] = 1  # cut by the scan's border
    for array, truth in ((ball, 4 / 3 * np.pi * 9**3), (box, 12 * 20 * 20)):
        mesh = isosurface(Volume(array, spacing=(1, 1, 1)), 0.5, step_size=step, crop=crop)
        assert mesh.is_edge_manifold() and not mesh.get_non_manifold_vertices()
        edges = SurfaceDistanceQuery(np.asarray(mesh.vertices), np.asarray(mesh.triangles))
        assert not edges.has_boundary  # closed
        # A sampling `step` voxels apart misses up to about a step of the shape's detail.
        assert signed_volume(mesh) == pytest.approx(truth, rel=0.12 * step)


def test_object_cut_by_the_border_is_closed():
    array = np.zeros((10, 12, 12), dtype=np.uint8)
    array[:6, 3:9, 3:9] = 1  # touches plane 0
    volume = Volume(array, spacing=(1, 1, 1))
    closed = isosurface(volume, 0.5)
    assert _closed(closed)
    assert signed_volume(closed) > 0
    opened = isosurface(volume, 0.5, close_boundary=False)
    assert not _closed(opened)


def test_bool_mask():
    array = np.zeros((8, 8, 8), dtype=bool)
    array[2:6, 2:6, 2:6] = True
    mesh = isosurface(Volume(array, spacing=(1, 1, 1)), 0.5)
    assert _closed(mesh)


def test_isosurface_rejects_bad_input():
    volume = Volume(np.arange(27, dtype=np.float32).reshape(3, 3, 3), spacing=(1, 1, 1))
    with pytest.raises(
        RuntimeError, match=r"no surface found at level 30: data range is \[0, 26\]"
    ):
        isosurface(volume, 30)
    with pytest.raises(TypeError, match=r"`volume` must be an o3dreg\.Volume"):
        isosurface(np.zeros((3, 3, 3)), 0.5)
    with pytest.raises(ValueError, match="`level` must be finite, got nan"):
        isosurface(volume, float("nan"))
    with pytest.raises(TypeError, match="`level` must be a number"):
        isosurface(volume, "400")
    with pytest.raises(ValueError, match="`step_size` must be a finite integer > 0"):
        isosurface(volume, 5, step_size=0)
    flat = Volume(np.zeros((1, 8, 8)), spacing=(1, 1, 1))
    with pytest.raises(ValueError, match="a 2D image has no surface"):
        isosurface(flat, 0.5)
    bad = np.zeros((4, 4, 4), dtype=np.float32)
    bad[1, 2, 3] = np.nan
    with pytest.raises(ValueError, match=r"must hold finite values, got 1 NaN"):
        isosurface(Volume(bad, spacing=(1, 1, 1)), 0.5)
    # Values beyond float32 (marching cubes' type) and a level at the maximum: said plainly.
    huge = np.zeros((6, 6, 6))
    huge[2:4, 2:4, 2:4] = 1e300
    with pytest.raises(ValueError, match="values must fit in float32"):
        isosurface(Volume(huge, spacing=(1, 1, 1)), 1e299)
    with pytest.raises(RuntimeError, match="strictly between the lowest and the highest"):
        isosurface(Volume((huge > 0).astype(np.uint8), spacing=(1, 1, 1)), 1)
    # A step larger than the object: the message names the step, not the level.
    z, y, x = np.mgrid[:20, :20, :20]
    ball = Volume(
        (((x - 10) ** 2 + (y - 10) ** 2 + (z - 10) ** 2) < 36).astype(np.float32), (1, 1, 1)
    )
    with pytest.raises(
        RuntimeError,
        match=r"no surface found with step_size=30: the object spans \(11, 11, 11\).*smaller step",
    ):
        isosurface(ball, 0.5, step_size=30)


# -- real scans ---------------------------------------------------------------------------------


def test_headsq_skull_at_bone_level():
    volume = read_volume(HEADSQ / "quarter.nhdr")
    mesh = isosurface(volume, 1150)
    components = connected_components(mesh)
    # One skull-sized connected bone surface dominates (a few small islands of noise remain).
    assert components.vertex_counts[0] > 30_000
    assert components.vertex_counts[0] > 0.9 * len(mesh.vertices)
    extent = np.ptp(np.asarray(mesh.vertices), axis=0)
    assert np.all((extent > 120) & (extent < 220)), extent  # millimetres: an adult head
    assert signed_volume(mesh) > 0


def test_dicom_slice_has_no_surface():
    volume = read_volume(DATA / "dicom_slice" / "CT_small.dcm")
    with pytest.raises(ValueError, match="2D image"):
        isosurface(volume, 300)


def test_pitched_ct_extent_matches_the_affine():
    path = DATA / "pitch" / "CT_pitch.nii.gz"
    level = 200
    mesh = isosurface(read_volume(path), level)
    vertices = np.asarray(mesh.vertices)
    # Independent geometry: nibabel's RAS affine applied to the (i, j, k) indices of the bone
    # voxels, converted to LPS.
    image = nib.load(path)
    ijk = np.argwhere(np.asarray(image.dataobj) >= level)
    world = (ijk @ image.affine[:3, :3].T + image.affine[:3, 3]) @ LPS_FROM_RAS
    # Vertices lie within one voxel (at most 2.4 mm along the pitched axis) of the voxel extent.
    assert np.allclose(vertices.min(axis=0), world.min(axis=0), atol=2.5)
    assert np.allclose(vertices.max(axis=0), world.max(axis=0), atol=2.5)
    assert signed_volume(mesh) > 0


# The eight PDDCA mandible masks of the shared (research-only) data; never copied into the repo.
MANDIBLES = ["0001", "0002", "0003", "0009", "0013", "0014", "0017", "0057"]


@pytest.mark.parametrize("case", MANDIBLES)
def test_mandible_mask_gives_one_closed_component(shared_data, case):
    path = shared_data / "mandibles" / "masks" / f"0522c{case}_Mandible.nrrd"
    if not path.exists():
        pytest.skip(f"mandible mask {path} is absent (research-only shared data)")
    mesh = isosurface(read_volume(path), 0.5)
    components = connected_components(mesh)
    dominant = int(components.vertex_counts[0])
    assert 8_000 <= dominant <= 20_000, dominant
    assert dominant >= 0.95 * len(mesh.vertices)
    assert _closed(keep_largest_components(mesh))
    assert signed_volume(mesh) > 0
