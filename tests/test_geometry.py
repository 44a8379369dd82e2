"""Small geometric kernels: the same numbers as the NumPy expressions they replace."""

import numpy as np

from o3dreg import _geometry
from o3dreg._geometry import face_cross, face_doubled_areas, row_norms


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
        # The caller's own contiguous columns (a caller going through blocks of triangles).
        columns = [np.ascontiguousarray(v[:, i]) for i in range(3)]
        np.testing.assert_array_equal(
            face_doubled_areas(v, f, columns=columns), np.linalg.norm(cross, axis=1)
        )
    assert face_doubled_areas(v, f[:0]).shape == (0,)
