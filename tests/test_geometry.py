"""Small geometric kernels: the same numbers as the plain NumPy expressions of their formulas."""

import numpy as np
import open3d as o3d
import pytest

from o3dreg import _geometry
from o3dreg._geometry import det3, face_cross, face_doubled_areas, row_norms, vertex_areas
from o3dreg.mesh.distinct import distinct, distinct_ranks, sort_keys


def test_face_cross_and_row_norms_are_numpys_bit_for_bit():
    # Scales far apart (units of metres and of micrometres) and degenerate triangles.
    rng = np.random.default_rng(0)
    for scale in (1e-6, 1.0, 1e6):
        v = rng.normal(size=(500, 3)) * scale
        f = rng.integers(0, 500, size=(2000, 3))
        f[:10, 1] = f[:10, 0]  # repeated corner: zero cross product
        a, b, c = (v[f[:, k]] for k in range(3))
        expected = np.cross(b - a, c - a)
        np.testing.assert_array_equal(face_cross(v, f), expected)
        np.testing.assert_array_equal(row_norms(expected), np.linalg.norm(expected, axis=1))
    assert face_cross(v, f[:0]).shape == (0, 3)


def test_blocks_change_nothing(monkeypatch):
    # Triangles are processed a block at a time; a block size that does not divide the count
    # (and one larger than it) give the same numbers as np.cross and np.linalg.norm.
    rng = np.random.default_rng(1)
    v = rng.normal(size=(300, 3))
    f = rng.integers(0, 300, size=(1001, 3))
    a, b, c = (v[f[:, k]] for k in range(3))
    cross = np.cross(b - a, c - a)
    for block in (7, 1000, 5000):
        monkeypatch.setattr(_geometry, "BLOCK", block)
        np.testing.assert_array_equal(face_cross(v, f), cross)
        np.testing.assert_array_equal(face_doubled_areas(v, f), np.linalg.norm(cross, axis=1))
    assert face_doubled_areas(v, f[:0]).shape == (0,)


def test_det3_is_the_determinant():
    rng = np.random.default_rng(2)
    m = rng.normal(size=(1000, 3, 3))
    m[:5] = np.eye(3)
    m[5, 2] = m[5, 0] + m[5, 1]  # singular
    # Rounding of 9 products of O(1) numbers against LAPACK's factorisation.
    np.testing.assert_allclose(det3(m), np.linalg.det(m), rtol=1e-12, atol=1e-14)
    np.testing.assert_array_equal(det3(m[:5]), 1.0)


@pytest.mark.parametrize("bound", [None, 50, 10**9])
def test_distinct_is_numpys_unique(bound):
    # A bitmap (small bound), a sort (no bound, or one too large for a bitmap): np.unique's
    # values and dtype either way, for int32 and int64, with and without repeats.
    rng = np.random.default_rng(3)
    for dtype in (np.int32, np.int64):
        for size in (0, 1, 7, 5000):
            values = rng.integers(0, 50, size=size).astype(dtype).reshape(-1, 1)
            found = distinct(values, bound)
            np.testing.assert_array_equal(found, np.unique(values))
            assert found.dtype == dtype


def test_distinct_refuses_values_outside_its_bound():
    with pytest.raises(ValueError, match=r"\[0, 10\)"):
        distinct(np.array([3, 10]), 10)
    with pytest.raises(ValueError, match="lie in"):
        distinct(np.array([-1, 3]), 10)


def test_sort_keys_is_numpys_stable_argsort():
    # Keys of 1 to 62 bits (one radix pass to six), with ties: the stable order is unique.
    rng = np.random.default_rng(4)
    for top in (1, 2**11, 2**20, 2**40, 2**62):
        keys = rng.integers(0, top, size=3001, dtype=np.int64)
        keys[::7] = keys[0]  # ties
        order, ordered = sort_keys(keys)
        np.testing.assert_array_equal(order, np.argsort(keys, kind="stable"))
        np.testing.assert_array_equal(ordered, np.sort(keys))
    assert sort_keys(np.zeros(0, dtype=np.int64))[0].shape == (0,)
    with pytest.raises(ValueError, match="non-negative"):
        sort_keys(np.array([3, -1]))


def test_distinct_ranks_are_numpys_unique_inverse():
    rng = np.random.default_rng(5)
    for top in (1, 40, 2**40):
        keys = rng.integers(0, top, size=2000)
        _, inverse = np.unique(keys, return_inverse=True)
        np.testing.assert_array_equal(distinct_ranks(keys), inverse.ravel())
    assert distinct_ranks(np.zeros(0, dtype=np.int64)).shape == (0,)


def test_vertex_areas_share_every_triangle_in_thirds():
    # A unit square in two triangles (area 1/2 each) and a vertex of no triangle: the corners
    # on the diagonal touch both triangles, the others one.
    v = np.array([[0.0, 0, 0], [1, 0, 0], [1, 1, 0], [0, 1, 0], [5, 5, 5]])
    f = np.array([[0, 1, 2], [0, 2, 3]])
    np.testing.assert_allclose(vertex_areas(v, f), [1 / 3, 1 / 6, 1 / 3, 1 / 6, 0.0], rtol=1e-15)
    # On any surface they add up to its area.
    sphere = o3d.geometry.TriangleMesh.create_sphere(2.0, 20)
    sv, sf = np.asarray(sphere.vertices), np.asarray(sphere.triangles)
    np.testing.assert_allclose(vertex_areas(sv, sf).sum(), sphere.get_surface_area(), rtol=1e-12)
