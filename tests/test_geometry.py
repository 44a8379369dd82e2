"""Small geometric kernels: the same numbers as the NumPy expressions they replace."""

import numpy as np

from o3dreg._geometry import face_cross, row_norms


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
